"""Checkpoints: a round trip renders identically and continues identically under a seed, views are stored
compactly or as sequence references, a crash mid-write leaves the previous checkpoint loadable, and a mapping
process killed with SIGKILL resumes from its last checkpoint and finishes like an uninterrupted run."""

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest
import torch

import eligsir_o3d as eo3d
from eligsir_o3d.io import checkpoint as ckpt
from eligsir_o3d.io.checkpoint import CheckpointError, read_checkpoint, save_checkpoint

load_checkpoint = eo3d.Reconstructor.load
from eligsir_o3d.datasets import open_sequence

W, H, N = 40, 30, 10
PLAIN = ("views", "fidelity", "growth")


@pytest.fixture(scope="module")
def seq():
    return open_sequence("synthetic", n_frames=N, width=W, height=H, depth_dtype="uint16")


@pytest.fixture(scope="module")
def frames(seq):
    return [seq.frame(i) for i in range(N)]


def _deterministic(rec):
    """What a budget clock does: a modelled update cost instead of measured seconds, so fidelity is reproducible."""
    attach = getattr(rec.fidelity, "attach", None)
    if attach is not None:
        attach(None, lambda pixels: 2e-3 + 1e-6 * pixels)
    return rec


def _rec(seq, ablate=(), seed=0):
    cfg = eo3d.Config(ablate=ablate, seed=seed)
    cfg.depth_scale = seq.depth_scale
    cfg.keyframes.every = 2
    return _deterministic(eo3d.Reconstructor(seq.intrinsic, "cpu", cfg))


def _assert_same_state(a, b):
    for name in a.gmap.params:
        torch.testing.assert_close(a.gmap.params[name], b.gmap.params[name], rtol=0, atol=0)
        for key in ("exp_avg", "exp_avg_sq"):
            torch.testing.assert_close(getattr(a.gmap.adam, key)[name], getattr(b.gmap.adam, key)[name], rtol=0, atol=0)
    assert a.gmap.adam.steps == b.gmap.adam.steps and a.gmap.adam.lr == b.gmap.adam.lr
    counters = lambda r: {k: v for k, v in vars(r.stats).items() if not k.endswith("_s")}  # noqa: E731
    assert counters(a) == counters(b)  # wall-clock seconds differ after a continuation, counters must not
    va, vb = a.views.views, b.views.views
    assert [(f.index, f.timestamp) for f in va] == [(f.index, f.timestamp) for f in vb]
    for fa, fb in zip(va, vb):
        assert torch.equal(fa.color, fb.color) and torch.equal(fa.depth, fb.depth) and fa.camera == fb.camera
        np.testing.assert_array_equal(fa.T_world_cam, fb.T_world_cam)


@pytest.mark.parametrize("ablate", [
    (),
    ("fidelity",),
    PLAIN,
], ids=["eligsir", "no-fidelity", "plain"])
def test_round_trip_renders_and_continues_identically(tmp_path, seq, frames, ablate):
    a = _rec(seq, ablate, seed=3)
    for f in frames[:5]:
        a.integrate(f, updates=3)
    path = save_checkpoint(a, tmp_path / "ck.pt", extra={"next": 5, "trajectory": {"3": [0.1, 0.2]}})
    b = _deterministic(load_checkpoint(path))
    assert read_checkpoint(path)["extra"] == {"next": 5, "trajectory": {"3": [0.1, 0.2]}}
    assert b.config.to_dict() == a.config.to_dict() and b.camera == a.camera
    assert [type(p) for p in (b.views, b.fidelity, b.growth)] == [type(p) for p in (a.views, a.fidelity, a.growth)]
    _assert_same_state(a, b)
    for T in (seq.poses[1], seq.poses[7]):
        ra, rb = a.render(T), b.render(T)
        assert torch.equal(ra.color, rb.color) and torch.equal(ra.depth, rb.depth)
    for f in frames[5:]:
        a.integrate(f, updates=3)
        b.integrate(f, updates=3)
    _assert_same_state(a, b)


def test_drain_after_resume_continues_identically(tmp_path, seq, frames):
    """Updates without new frames (finalize's drain, idle time) replay views chosen from the active set and
    priorities of the last refresh: a resumed run must hold the same ones (7-Scenes diverged 2 frames after)."""
    a = _rec(seq, seed=3)
    a.config.views.active_size = 2  # fewer active than retained views, so the active set matters
    for f in frames[:7]:
        a.integrate(f, updates=3)
    b = _deterministic(load_checkpoint(save_checkpoint(a, tmp_path / "ck.pt")))
    a.optimize(12)
    b.optimize(12)
    _assert_same_state(a, b)


def test_views_are_stored_compactly_or_as_sequence_references(tmp_path, seq, frames):
    rec = _rec(seq, ("fidelity",))
    for f in frames[:6]:
        rec.integrate(f, updates=1)
    n_views = len(rec.views.views)
    assert n_views >= 2
    p1 = save_checkpoint(rec, tmp_path / "images.pt")
    raw = torch.load(p1, weights_only=True)
    assert len(raw["frames"]) == n_views  # each view once, though the policy state also refers to it
    for e in raw["frames"]:
        assert e["color"]["q"].dtype == torch.uint8 and e["depth"]["q"].dtype == torch.uint16  # lossless here
    p2 = save_checkpoint(rec, tmp_path / "refs.pt", sequence=seq)
    assert all(e.get("ref") == "sequence" for e in torch.load(p2, weights_only=True)["frames"])
    assert os.path.getsize(p2) < os.path.getsize(p1) - n_views * W * H * 4
    with pytest.raises(CheckpointError, match="pass sequence="):
        load_checkpoint(p2)
    other = open_sequence("synthetic", n_frames=N, width=W, height=H, depth_dtype="uint16", seed=1)
    with pytest.raises(CheckpointError, match="differs from the retained view"):
        load_checkpoint(p2, sequence=other)
    for p in (p1, p2):
        _assert_same_state(rec, load_checkpoint(p, sequence=seq))

    # float depth (metres) cannot be stored as uint16 exactly, so it is kept as float32: still bit-exact
    fseq = open_sequence("synthetic", n_frames=3, width=W, height=H)
    frec = _rec(fseq, ("fidelity",))
    frec.integrate(fseq.frame(0), updates=0)
    p3 = save_checkpoint(frec, tmp_path / "float.pt")
    assert torch.load(p3, weights_only=True)["frames"][0]["depth"]["raw"].dtype == torch.float32
    _assert_same_state(frec, load_checkpoint(p3))


def test_crash_mid_write_leaves_the_previous_checkpoint(tmp_path, seq, frames, monkeypatch):
    rec = _rec(seq, ("fidelity",))
    for f in frames[:3]:
        rec.integrate(f, updates=1)
    path = save_checkpoint(rec, tmp_path / "ck.pt")
    before = path.read_bytes()
    for f in frames[3:5]:
        rec.integrate(f, updates=1)

    def dies_halfway(payload, fh):
        fh.write(before[: len(before) // 2])  # a partial archive on disk, then the "crash"
        raise OSError("No space left on device")

    monkeypatch.setattr(ckpt, "_serialize", dies_halfway)
    with pytest.raises(OSError, match="No space left"):
        save_checkpoint(rec, path)
    monkeypatch.undo()
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["ck.pt"]
    assert load_checkpoint(path).stats.frames_released == 3

    # a SIGKILLed writer leaves its temporary file: loading ignores it, the next save removes it
    stale = tmp_path / ".ck.pt.99999.tmp"
    stale.write_bytes(before[:100])
    assert load_checkpoint(path).stats.frames_released == 3
    save_checkpoint(rec, path)
    assert not stale.exists() and load_checkpoint(path).stats.frames_released == 5


def test_unreadable_checkpoints_raise_clear_errors(tmp_path, seq, frames):
    with pytest.raises(CheckpointError, match="missing.pt: no such checkpoint"):
        load_checkpoint(tmp_path / "missing.pt")
    rec = _rec(seq, ("fidelity",))
    rec.integrate(frames[0], updates=0)
    good = save_checkpoint(rec, tmp_path / "good.pt").read_bytes()
    (tmp_path / "cut.pt").write_bytes(good[: len(good) // 3])
    with pytest.raises(CheckpointError, match="cut.pt: not a readable checkpoint"):
        load_checkpoint(tmp_path / "cut.pt")
    torch.save({"weights": torch.zeros(3)}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="other.pt: not an eligsir_o3d checkpoint"):
        read_checkpoint(tmp_path / "other.pt")
    raw = torch.load(tmp_path / "good.pt", weights_only=True)
    raw["version"] = ckpt.VERSION + 1
    torch.save(raw, tmp_path / "future.pt")
    with pytest.raises(CheckpointError, match="newer than this eligsir_o3d reads"):
        load_checkpoint(tmp_path / "future.pt")


def test_state_that_cannot_be_checkpointed_is_named(tmp_path, seq, frames, monkeypatch):
    rec = _rec(seq, ("fidelity",))
    monkeypatch.setattr(rec.fidelity, "state_dict", lambda: {"clock": object()})
    with pytest.raises(CheckpointError, match=r"policies\.fidelity\.state\.clock: a builtins\.object"):
        save_checkpoint(rec, tmp_path / "ck.pt")
    assert not list(tmp_path.iterdir())


MAPPER = textwrap.dedent("""
    import json, sys, time
    import torch
    import eligsir_o3d as eo3d
    from eligsir_o3d.io.checkpoint import save_checkpoint
    load_checkpoint = eo3d.Reconstructor.load
    from eligsir_o3d.datasets import open_sequence

    def run(ck, n, every, stall_after=-1, resume=False):
        seq = open_sequence("synthetic", n_frames=n, width=%(w)d, height=%(h)d, depth_dtype="uint16")
        if resume:
            rec = load_checkpoint(ck, sequence=seq)
        else:
            cfg = eo3d.Config(ablate=("fidelity",), seed=7)
            cfg.depth_scale = seq.depth_scale
            rec = eo3d.Reconstructor(seq.intrinsic, "cpu", cfg)
        start = rec.stats.frames_released
        print("start", start, flush=True)
        for i in range(start, n):
            rec.integrate(seq.frame(i), updates=2)
            if (i + 1) %% every == 0:
                save_checkpoint(rec, ck, sequence=seq, extra={"frames": i + 1})
                print("checkpoint", i + 1, flush=True)
            if i + 1 == stall_after:
                print("stalled", flush=True)
                time.sleep(600)
        return rec

    if __name__ == "__main__":
        ck, n, every, stall, resume, out = sys.argv[1:7]
        rec = run(ck, int(n), int(every), int(stall), resume == "1")
        torch.save({k: v.detach() for k, v in rec.gmap.params.items()}, out)
        print(json.dumps({"frames": rec.stats.frames_released, "updates": rec.stats.updates}), flush=True)
""") % {"w": 32, "h": 24}


def test_resume_after_sigkill(tmp_path):
    script = tmp_path / "mapper.py"
    script.write_text(MAPPER)
    ck, n, every, stall = tmp_path / "ck.pt", 8, 3, 5
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, str(script), str(ck), str(n), str(every), str(stall), "0",
                             str(tmp_path / "killed.pt")], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=env)
    lines = []
    deadline = time.time() + 90
    for line in proc.stdout:
        lines.append(line.strip())
        if line.startswith("stalled") or time.time() > deadline:
            break
    proc.send_signal(signal.SIGKILL)  # mid-sequence: frames 4 and 5 are done but not checkpointed
    proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL and "checkpoint 3" in lines and "stalled" in lines, lines
    assert not (tmp_path / "killed.pt").exists()
    assert read_checkpoint(ck)["stats"]["frames_released"] == 3

    done = subprocess.run([sys.executable, str(script), str(ck), str(n), str(every), "-1", "1",
                           str(tmp_path / "resumed.pt")], capture_output=True, text=True, env=env, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.splitlines()[0] == "start 3"
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["frames"] == n

    # the uninterrupted run, in this process with the same code, finishes with the same map
    sys.path.insert(0, str(tmp_path))
    try:
        import mapper
        ref = mapper.run(str(tmp_path / "ref.pt"), n, every)
    finally:
        sys.path.remove(str(tmp_path))
        sys.modules.pop("mapper", None)
    assert ref.stats.frames_released == n and ref.stats.updates == result["updates"]
    resumed = torch.load(tmp_path / "resumed.pt", weights_only=True)
    for name, p in ref.gmap.params.items():
        torch.testing.assert_close(resumed[name], p.detach(), rtol=0, atol=0)


def test_policies_replaced_after_construction_must_be_replaced_again(tmp_path, seq, frames):
    from eligsir_o3d.scheduling.plain import FixedFidelity

    rec = _rec(seq)
    rec.fidelity = FixedFidelity(0.5)  # as a driver's special mode might
    rec.integrate(frames[0], updates=1)
    path = save_checkpoint(rec, tmp_path / "ck.pt")
    with pytest.raises(CheckpointError, match="fidelity policy was FixedFidelity when saved.*setup="):
        load_checkpoint(path)
    back = load_checkpoint(path, setup=lambda r: setattr(r, "fidelity", FixedFidelity(0.5)))
    assert back.fidelity.scale() == 0.5
    _assert_same_state(rec, back)


def test_a_state_dict_is_a_copy_that_mapping_on_does_not_change(seq, frames):
    rec = _rec(seq, ("fidelity",))
    for f in frames[:3]:
        rec.integrate(f, updates=1)
    state = rec.gmap.state_dict()
    params = {n: p.clone() for n, p in state["params"].items()}
    moments = {k: {n: t.clone() for n, t in state["adam"][k].items()} for k in ("exp_avg", "exp_avg_sq")}
    steps = dict(state["adam"]["steps"])
    rec.integrate(frames[3], updates=3)  # updates the live parameters and Adam moments in place
    assert rec.gmap.adam.steps != steps and state["adam"]["steps"] == steps
    for n, p in state["params"].items():
        assert torch.equal(p, params[n]), n
    for k, held in moments.items():
        for n, t in held.items():
            assert torch.equal(state["adam"][k][n], t), (k, n)
