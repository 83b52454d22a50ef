"""CVQ-AUC integrates over the *stream's* progress (issue 18): two variants whose maps are identical at every moment
of the stream but that make very different numbers of updates (one keeps up, one falls behind and drops most frames
of a burst) must get the same CVQ-AUC, up to the error of where their checkpoints fall."""

import copy

import numpy as np
import pytest

from eligsir_o3d import Config
from eligsir_o3d.budget import CostModel
from eligsir_o3d.run.pipeline import MappingPipeline, RunOptions, run_mapping

N_FRAMES, W, H = 48, 64, 48


@pytest.fixture(scope="module")
def maps():
    """Two map states: of the first 8 frames of the synthetic loop (poor), and of all of them (good)."""
    from eligsir_o3d.datasets import open_sequence
    from eligsir_o3d.mapper import Reconstructor

    seq = open_sequence("synthetic", n_frames=N_FRAMES, width=W, height=H)
    rec = Reconstructor(seq.camera, "cpu", Config(renderer="cpu"))
    states = []
    for i in range(N_FRAMES):
        rec.integrate(seq.frame(i), updates=6)
        if i in (7, N_FRAMES - 1):
            states.append(copy.deepcopy(rec.gmap.state_dict()))
    return states


def _scripted_run(tmp_path, monkeypatch, maps, update_s: float) -> dict:
    """The pipeline with a mapper whose map is a function of the stream alone: the poor map until the stream has
    released half of its source frames, the good one after; its updates only count and cost time. The stream has a
    burst: the first half of the frames at 30 Hz, the second half 1 s apart."""
    import eligsir_o3d.datasets as datasets

    real_open = datasets.open_sequence

    def open_with_burst(path, **kw):
        seq = real_open(path, **kw)
        ts = np.asarray(seq.timestamps, dtype=np.float64).copy()
        half = len(ts) // 2
        ts[half:] = ts[half - 1] + 1.0 + np.arange(len(ts) - half)
        seq.timestamps = ts
        return seq

    real_build = MappingPipeline.build

    def frozen_build(self):
        real_build(self)
        rec = self.rec
        rec.gmap.load_state_dict(copy.deepcopy(maps[0]))
        released = self._on_release

        def on_release(frame):
            released(frame)
            if self.released == len(self.source) // 2:
                rec.gmap.load_state_dict(copy.deepcopy(maps[1]))

        self._on_release = on_release
        rec.growth.on_frame = lambda frame, admitted, ctx: 0

        def step(scale=None):  # an update that leaves the map as it is: only counters, time and callbacks
            rec.stats.updates += 1
            rec.stats.supervised_pixels += rec.camera.pixels
            for cb in rec.callbacks:
                cb(rec)

        rec._step = step

    monkeypatch.setattr(datasets, "open_sequence", open_with_burst)
    monkeypatch.setattr(MappingPipeline, "build", frozen_build)
    cfg = Config(renderer="cpu")
    cfg.clock.cost = CostModel(update_s=update_s, gaussian_s=0.0, pixel_s=0.0, pixel_gaussian_s=0.0, frame_s=0.0)
    cfg.clock.drain_updates = 0
    opts = RunOptions(max_frames=N_FRAMES, holdout_every=8, eval_every=1000, progress=False, plots=False,
                      pictures=False, eval_ssim_at_checkpoints=False, eval_sample_stride=1,
                      sequence_options={"n_frames": N_FRAMES, "width": W, "height": H})
    return run_mapping("synthetic", tmp_path, cfg, opts)


def test_identical_maps_with_different_update_counts_get_the_same_cvq_auc(tmp_path, monkeypatch, maps):
    keeps_up = _scripted_run(tmp_path / "a", monkeypatch, maps, update_s=0.004)  # ~8 updates per frame period
    behind = _scripted_run(tmp_path / "b", monkeypatch, maps, update_s=0.3)  # drops most of the 30 Hz burst
    assert keeps_up["dropped_frames"] == 0 and behind["dropped_frames"] >= 12
    assert keeps_up["updates"] > 5 * behind["updates"]
    assert keeps_up["gaussians"] == behind["gaussians"]  # the maps are the same
    for m in (keeps_up, behind):
        ps = [c["progress"] for c in m["curve"]]
        assert ps[-1] == 1.0 and ps == sorted(ps)
    # the curve has a shape: a step up at half the stream
    cvqs = [c["cvq"] for c in keeps_up["curve"] if c["cvq"] is not None]
    spread = max(cvqs) - min(cvqs)
    assert spread > 1.0
    # checkpoint-spacing error: progress checkpoints every 10 % of the stream bound the trapezoid rule's
    # misplacement to a small share of the curve's spread (counting progress by integrated frames or by updates
    # instead squeezes the behind variant's burst into a sliver and moves its AUC by about half the spread)
    assert behind["cvq_auc"] == pytest.approx(keeps_up["cvq_auc"], abs=0.15 * spread)
