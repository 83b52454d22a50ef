"""Where two machines' bits part: a digest of each stage a mapping update goes through, on fixed inputs.

    python benchmarks/platforms/bits_fingerprint.py > a.json      # on each machine / environment, then
    python benchmarks/platforms/bits_fingerprint.py --compare a.json b.json

Stages (inputs from numpy's PCG64, whose streams are the same on every platform): numpy float32/float64 elementwise
maths and a reduction; torch elementwise maths, a float32 matrix product and a sum; the cpu renderer's forward
(colour, depth, alpha) and backward (gradients of all five parameters) on 300 random Gaussians at 64x48; the DSSIM
loss's value and gradient (numba on the CPU). Used by ``benchmarks/platforms/aarch64_check.sh`` to explain a difference between
the emulated aarch64 map and the x86-64 one. No timing.
"""

from __future__ import annotations

import hashlib
import json
import platform
import sys

import numpy as np


def digest(*arrays) -> str:
    """First 16 hex digits of the SHA-256 of the arrays' bytes (torch tensors are detached to numpy)."""
    h = hashlib.sha256()
    for a in arrays:
        a = a.detach().cpu().numpy() if hasattr(a, "detach") else np.asarray(a)
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def stages() -> dict:
    """{stage: digest} for this interpreter's numpy, torch and cpu kernels."""
    import torch
    from eligsir_o3d.core.camera import Camera
    from eligsir_o3d.optim.losses import dssim
    from eligsir_o3d.render import get_renderer
    rng = np.random.default_rng(0)
    x64 = rng.uniform(-4.0, 4.0, 100_000)
    x32 = x64.astype(np.float32)
    out = {"numpy f64 exp/log/sin": digest(np.exp(x64), np.log1p(np.abs(x64)), np.sin(x64)),
           "numpy f32 exp/log/sin": digest(np.exp(x32), np.log1p(np.abs(x32)), np.sin(x32)),
           "numpy f32 sum/dot": digest(np.float32(x32.sum()), np.float32(x32 @ x32))}
    t = torch.from_numpy(x32)
    a = torch.from_numpy(rng.standard_normal((128, 96)).astype(np.float32))
    b = torch.from_numpy(rng.standard_normal((96, 80)).astype(np.float32))
    out["torch f32 exp/log/sigmoid"] = digest(torch.exp(t), torch.log1p(t.abs()), torch.sigmoid(t))
    out["torch f32 matmul"] = digest(a @ b)
    out["torch f32 sum"] = digest(t.sum(), (t * t).mean())
    n = 300
    params = dict(means=rng.standard_normal((n, 3)) * [0.8, 0.6, 0.6], quats=rng.standard_normal((n, 4)),
                  scales=np.exp(rng.uniform(-4.0, -1.5, (n, 3))), opacities=rng.uniform(0.05, 0.99, n),
                  colors=rng.uniform(0.0, 1.0, (n, 3)))
    ps = {k: torch.tensor(v, dtype=torch.float32, requires_grad=True) for k, v in params.items()}
    T = np.eye(4)
    T[2, 3] = -3.0  # camera at z = -3 looking along +z at the origin
    cam = Camera(64, 48, 60.0, 60.0, 31.5, 23.5)
    r = get_renderer("cpu")
    o = r.render(ps["means"], ps["quats"], ps["scales"], ps["opacities"], ps["colors"], cam, T)
    w = {k: torch.from_numpy(rng.uniform(0.0, 1.0, tuple(v.shape)).astype(np.float32))
         for k, v in (("color", o.color), ("depth", o.depth), ("alpha", o.alpha))}
    ((o.color * w["color"]).sum() + (o.depth * w["depth"]).sum() + (o.alpha * w["alpha"]).sum()).backward()
    out["cpu renderer forward"] = digest(o.color, o.depth, o.alpha)
    out["cpu renderer backward"] = digest(*(ps[k].grad for k in params))
    pred = o.color.detach().clone().requires_grad_(True)
    ref = torch.from_numpy(rng.uniform(0.0, 1.0, tuple(pred.shape)).astype(np.float32))
    loss = dssim(pred, ref)
    loss.backward()
    out["dssim value+grad (numba)"] = digest(loss, pred.grad)
    return out


def main() -> None:
    if len(sys.argv) == 4 and sys.argv[1] == "--compare":
        a, b = (json.load(open(p)) for p in sys.argv[2:])
        print(f"{'stage':<28} {a['machine']:>18} {b['machine']:>18}")
        for k in a["stages"]:
            va, vb = a["stages"][k], b["stages"].get(k)
            print(f"{k:<28} {va:>18} {str(vb):>18}  {'same' if va == vb else 'DIFFERS'}")
        return
    import torch
    print(json.dumps({"machine": platform.machine(), "torch": torch.__version__, "numpy": np.__version__,
                      "stages": stages()}, indent=1))


if __name__ == "__main__":
    main()
