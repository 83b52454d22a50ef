"""Renderer benchmark: forward and forward+backward time of every available backend on a real scene.

Gaussians are seeded from the first frames of ``../shared/data/7scenes_redkitchen_jpg1000`` (depth back-projected
to coloured points, isotropic scales from nearest-neighbour spacing, opacity 0.5) and rendered from frame 0's pose
at 1/8, 1/4, 1/2 and 1x of 640x480. Times are the best of ``--repeats`` runs after one untimed warm-up run (the
best, not the median: on a machine shared with other jobs, interference only ever adds time; a row whose warm-up
took over 5 s is timed once). The cpu backend's first-call kernel compile (or cache load) is reported separately, and the header names the CPU
target numba compiles the kernels for (``NUMBA_CPU_NAME``: ``NUMBA_CPU_NAME=haswell`` measures AVX2 code on any
x86-64 machine, ``generic`` baseline SSE2; the script then compiles for that CPU's own features, where numba alone
would add the host's). The loss of the backward pass is an L1 colour + depth loss against the frame, so every output
carries gradient.

    python benchmarks/speed/render.py                       # table
    python benchmarks/speed/render.py --json                # one JSON object per line
    python benchmarks/speed/render.py --gaussians 20000 --scales 0.25 --backends torch cpu

Peak memory: on the CPU, the rise of the process's peak RSS (``/proc/self/status`` VmHWM, reset through
``/proc/self/clear_refs`` before each configuration) over its RSS before; on CUDA, ``torch.cuda.max_memory_allocated``.
The torch reference is skipped where its forward+backward is predicted (from the same scene at the next lower
resolution, scaled by pixel count) to exceed ``--max-ref-seconds``; such rows say ``"skipped"`` and have no speedup.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

if "--omp-passive" in sys.argv:  # must reach libgomp before torch loads it
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
if os.environ.get("NUMBA_CPU_NAME") and "NUMBA_CPU_FEATURES" not in os.environ:
    # numba would add the *host's* features to the named CPU (haswell + AVX-512 on an AVX-512 host): compile for
    # the named CPU's own features instead, so that NUMBA_CPU_NAME=haswell measures AVX2 code
    os.environ["NUMBA_CPU_FEATURES"] = ""

import numpy as np  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]

from eligsir_o3d.core.camera import Camera, pose_from_tum  # noqa: E402
from eligsir_o3d.render import available_backends, get_renderer  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "7scenes_redkitchen_jpg1000"
BASE = Camera(640, 480, 585.0, 585.0, 320.0, 240.0)


def _read_frame(i: int):
    import open3d as o3d
    color = np.asarray(o3d.t.io.read_image(str(DATA / "rgb" / f"{i:06d}.jpg")).as_tensor().numpy(), np.float32) / 255.0
    depth = np.asarray(o3d.t.io.read_image(str(DATA / "depth" / f"{i:06d}.png")).as_tensor().numpy())[..., 0]
    return color, depth.astype(np.float32) / 1000.0


def _poses() -> list[np.ndarray]:
    rows = [ln.split() for ln in (DATA / "groundtruth.txt").read_text().splitlines() if ln and not ln.startswith("#")]
    return [pose_from_tum(np.array(r[1:4], float), np.array(r[4:8], float)) for r in rows]


def load_scene(n: int, frames=(0, 15, 30), seed: int = 0):
    """(params dict, frame-0 colour [480, 640, 3], depth [480, 640], frame-0 T_world_cam) with ``n`` Gaussians."""
    import open3d as o3d
    poses = _poses()
    pts, cols = [], []
    for i in frames:
        color, depth = _read_frame(i)
        p, idx = BASE.backproject(torch.from_numpy(depth))
        T = torch.from_numpy(poses[i]).float()
        pts.append(p @ T[:3, :3].T + T[:3, 3])
        cols.append(torch.from_numpy(color.reshape(-1, 3))[idx])
    pts, cols = torch.cat(pts), torch.cat(cols)
    g = torch.Generator().manual_seed(seed)
    sel = torch.randperm(pts.shape[0], generator=g)[:n]
    pts, cols = pts[sel].contiguous(), cols[sel].contiguous()
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.double().numpy()))
    nn = torch.from_numpy(np.asarray(pcd.compute_nearest_neighbor_distance())).float()
    scale = nn.clamp(1e-3, 0.05)
    params = {
        "means": pts,
        "quats": torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1),
        "scales": scale[:, None].expand(n, 3).contiguous(),
        "opacities": torch.full((n,), 0.5),
        "colors": cols,
    }
    color0, depth0 = _read_frame(frames[0])
    return params, color0, depth0, poses[frames[0]]


def resize(img: np.ndarray, w: int, h: int) -> torch.Tensor:
    import cv2
    interp = cv2.INTER_AREA if img.ndim == 3 else cv2.INTER_NEAREST
    return torch.from_numpy(cv2.resize(img, (w, h), interpolation=interp))


def _peak_rss_reset() -> int:
    """Hand freed heap back to the OS, reset the kernel's peak-RSS counter; return the RSS in kB (0 without /proc)."""
    import ctypes
    import gc
    gc.collect()
    try:  # glibc keeps freed memory resident; without the trim a later run reuses it and its peak reads as ~0
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass
    return _status_kb("VmRSS")


def _status_kb(key: str) -> int:
    try:
        for ln in Path("/proc/self/status").read_text().splitlines():
            if ln.startswith(key + ":"):
                return int(ln.split()[1])
    except OSError:
        pass
    return 0


def render_steps(renderer, ps: dict, camera: Camera, T_world_cam, bg, target_rgb, target_depth):
    """(fwd, fwdbwd): a forward render of the parameters ``ps``, and a forward + backward of the L1 colour + 0.1 x
    L1 depth loss (depth where the target [H, W] has some) against ``target_rgb`` [H, W, 3], gradients cleared."""
    def fwd():
        return renderer.render(ps["means"], ps["quats"], ps["scales"], ps["opacities"], ps["colors"], camera,
                               T_world_cam, background=bg)

    def fwdbwd():
        out = fwd()
        valid = target_depth > 0
        loss = (out.color - target_rgb).abs().mean() + 0.1 * (out.depth - target_depth)[valid].abs().mean()
        loss.backward()
        for p in ps.values():
            p.grad = None

    return fwd, fwdbwd


def time_backend(name: str, params, camera: Camera, T_world_cam, target_rgb, target_depth, device, repeats: int,
                 clock=time.perf_counter):
    renderer = get_renderer(name, device)
    ps = {k: v.to(device).clone().requires_grad_(True) for k, v in params.items()}
    tgt_rgb, tgt_d = target_rgb.to(device), target_depth.to(device)
    bg = torch.zeros(3, device=device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)

    fwd, fwdbwd = render_steps(renderer, ps, camera, T_world_cam, bg, tgt_rgb, tgt_d)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
        mem0 = torch.cuda.memory_allocated(device)
    rss0 = _peak_rss_reset()
    t0 = clock()
    fwdbwd()  # warm-up (allocator, caches)
    if clock() - t0 > 5.0:
        repeats = 1  # slow rows (the reference at high resolution): one timed run is enough
    fwd_t, fb_t = [], []
    for _ in range(repeats):
        sync()
        t0 = clock()
        fwd()
        sync()
        fwd_t.append(clock() - t0)
        t0 = clock()
        fwdbwd()
        sync()
        fb_t.append(clock() - t0)
    if device.type == "cuda":
        peak = (torch.cuda.max_memory_allocated(device) - mem0) / 2**20
    else:
        peak = max(0, _status_kb("VmHWM") - rss0) / 1024
    return min(fwd_t), min(fb_t), peak


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--gaussians", type=int, nargs="+", default=[5000, 20000, 100000])
    ap.add_argument("--scales", type=float, nargs="+", default=[0.125, 0.25, 0.5, 1.0])
    ap.add_argument("--backends", nargs="+", default=None, help="default: every available backend")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--max-ref-seconds", type=float, default=30.0,
                    help="skip a torch-reference row predicted to take longer than this per forward+backward")
    ap.add_argument("--json", action="store_true", help="one JSON object per line instead of a table")
    ap.add_argument("--omp-passive", action="store_true",
                    help="OMP_WAIT_POLICY=PASSIVE for torch and numba (one shared libgomp): idle OpenMP threads sleep "
                         "instead of spinning, which keeps timings sane on a machine shared with other jobs")
    ap.add_argument("--single-thread-cpu-time", action="store_true",
                    help="run torch and numba on one thread and time the main thread's CPU time instead of the wall "
                         "clock: a measure of work that holds up on a machine shared with other jobs (CPU only)")
    args = ap.parse_args(argv)

    device = torch.device(args.device)
    clock = time.perf_counter
    if args.single_thread_cpu_time:
        if device.type != "cpu":
            ap.error("--single-thread-cpu-time is for --device cpu")
        import numba
        torch.set_num_threads(1)
        numba.set_num_threads(1)
        clock = time.thread_time
    backends = args.backends or available_backends(device)
    if "torch" in backends:  # the reference first: speedups need its time
        backends = ["torch"] + [b for b in backends if b != "torch"]
    info = {"device": str(device), "torch_threads": torch.get_num_threads(), "cpu_count": os.cpu_count(),
            "clock": "main-thread CPU time, 1 thread" if args.single_thread_cpu_time else "wall",
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "default"),
            "loadavg_1min": round(os.getloadavg()[0], 2)}
    if "cpu" in backends:
        from eligsir_o3d.render._cpu_kernels import target_summary
        from eligsir_o3d.render.cpu_backend import warmup
        info["numba_target"] = target_summary()
        info["cpu_kernel_first_call_s"] = round(warmup(), 3)
    if not args.json:
        print("# " + ", ".join(f"{k}={v}" for k, v in info.items()))
        print(f"{'backend':>8} {'WxH':>9} {'gaussians':>9} {'fwd_ms':>9} {'fwdbwd_ms':>10} {'speedup':>8} {'peak_MB':>8}")
    for n in args.gaussians:
        params, color0, depth0, T0 = load_scene(n)
        ref_prev = None  # (pixels, seconds) of the reference at the previous resolution
        for s in sorted(args.scales):
            cam = BASE.scaled(s)
            rgb, dep = resize(color0, cam.width, cam.height), resize(depth0, cam.width, cam.height)
            ref_fb = None
            for b in backends:
                row = {"backend": b, "width": cam.width, "height": cam.height, "gaussians": n}
                if b == "torch" and ref_prev is not None and \
                        ref_prev[1] * cam.pixels / ref_prev[0] > args.max_ref_seconds:
                    row.update(fwd_s=None, fwdbwd_s=None, speedup_fwdbwd=None, peak_mem_mb=None,
                               skipped=f"predicted {ref_prev[1] * cam.pixels / ref_prev[0]:.0f} s > "
                                       f"--max-ref-seconds {args.max_ref_seconds:g}")
                    ref_prev = (cam.pixels, ref_prev[1] * cam.pixels / ref_prev[0])
                else:
                    f, fb, peak = time_backend(b, params, cam, T0, rgb, dep, device, args.repeats, clock)
                    if b == "torch":
                        ref_fb, ref_prev = fb, (cam.pixels, fb)
                    row.update(fwd_s=round(f, 5), fwdbwd_s=round(fb, 5),
                               speedup_fwdbwd=round(ref_fb / fb, 2) if ref_fb else None,
                               peak_mem_mb=round(peak, 1))
                if args.json:
                    print(json.dumps(row), flush=True)
                else:
                    def ms(x):
                        return f"{1e3 * x:9.1f}" if x is not None else f"{'skipped':>9}"
                    sp = f"{row['speedup_fwdbwd']:7.1f}x" if row["speedup_fwdbwd"] else f"{'-':>8}"
                    pk = f"{row['peak_mem_mb']:8.0f}" if row["peak_mem_mb"] is not None else f"{'-':>8}"
                    print(f"{b:>8} {cam.width:>4}x{cam.height:<4} {n:>9} {ms(row['fwd_s'])} {ms(row['fwdbwd_s']):>10} "
                          f"{sp} {pk}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
