"""Held-out views are held compactly (issue 31, item 12): about 1 MiB per 640x480 view with its regional samples,
decoded to the very float32 images they were read as, and scored to the same figures as float32 Frames.

Before, a held-out view was a float32 Frame (4.9 MiB at 640x480) and its regional samples copied pixel indices,
reference colour and depth (2.4 MiB more at the pipeline's sample stride 2): ~7 MiB per view.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from eligsir_o3d.core.camera import Camera
from eligsir_o3d.core.frame import Frame
from eligsir_o3d.datasets import open_sequence
from eligsir_o3d.eval import HeldoutEvaluator
from eligsir_o3d.eval.heldout_view import HeldoutView
from eligsir_o3d.run.frame_faults import read_heldout

SEVEN = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "7scenes_redkitchen_jpg1000"
MIB = 2 ** 20
HELD = [4, 12, 20, 28]  # held out with --holdout-every 8


def _kitchen():
    if not SEVEN.is_dir():
        pytest.skip("../shared/data is not available")
    return open_sequence(SEVEN)


def _render(views):
    """A deterministic stand-in render of each view: its colour darkened with fixed noise, depth 2 % farther."""
    def render(f):
        color, depth = f.color, f.depth
        g = torch.Generator().manual_seed(int(f.index))
        noise = 0.05 * torch.rand(color.shape, generator=g)
        return SimpleNamespace(color=(0.9 * color + noise).clamp(0, 1), depth=depth * 1.02)
    return render


def test_a_640x480_heldout_view_holds_about_one_mib_with_its_regional_samples():
    seq = _kitchen()
    views, skipped = read_heldout(seq, HELD, depth_max=8.0)
    assert not skipped and all(isinstance(v, HeldoutView) for v in views)
    ev = HeldoutEvaluator(views, sample_stride=2)  # the pipeline's default regional stride
    for k, v in enumerate(views):
        assert v.shape == (480, 640)
        total = v.nbytes + ev.regional.samples_nbytes(k)
        assert total <= 1.2 * MIB, f"view {v.index}: {total / MIB:.2f} MiB"
        # a float32 Frame alone was 4.9 MiB
        assert v.nbytes < 0.25 * (v.color.nbytes + v.depth.nbytes)


def test_decoded_views_are_bit_identical_to_the_frames_read():
    seq = _kitchen()
    views, _ = read_heldout(seq, HELD, depth_max=8.0)
    for v in views:
        f = seq.frame(v.index, depth_max=8.0)
        assert v._color.dtype == torch.uint8 and v._depth_dtype == np.uint16  # 8-bit colour, 16-bit depth files
        assert torch.equal(v.color, f.color) and torch.equal(v.depth, f.depth)
        assert v.color.dtype == torch.float32 and v.depth.dtype == torch.float32
        assert np.array_equal(v.T_world_cam, f.T_world_cam) and v.timestamp == f.timestamp


def test_views_score_exactly_as_float32_frames():
    seq = _kitchen()
    views, _ = read_heldout(seq, HELD, depth_max=8.0)
    frames = [seq.frame(i, depth_max=8.0) for i in HELD]
    a = HeldoutEvaluator(frames, sample_stride=2, min_samples=50)
    b = HeldoutEvaluator(views, sample_stride=2, min_samples=50)
    for ev in (a, b):
        for i in range(0, 40, 3):
            if i not in HELD:
                ev.observe_source(seq.frame(i, depth_max=8.0))
    kw = dict(t_s=1.0, progress=0.5, updates=10, supervised_mpix=1.0, gaussians=5)
    ra, rb = a.checkpoint(_render(frames), **kw), b.checkpoint(_render(views), **kw)
    drop = ("eval_s",)
    assert {k: v for k, v in ra.items() if k not in drop} == {k: v for k, v in rb.items() if k not in drop}
    assert ra["cvq"] is not None  # the regional figure is compared, not two Nones
    fa, fb = a.final(_render(frames)), b.final(_render(views))
    drop = ("eval_seconds",)
    assert {k: v for k, v in fa.items() if k not in drop} == {k: v for k, v in fb.items() if k not in drop}
    assert [s["cell"].tolist() for s in a.regional.samples] == [s["cell"].tolist() for s in b.regional.samples]


def test_colour_and_depth_that_are_not_8_or_16_bit_codes_are_kept_exactly():
    cam = Camera(fx=20.0, fy=20.0, cx=8.0, cy=6.0, width=16, height=12)
    rng = np.random.default_rng(0)
    color = rng.random((12, 16, 3), dtype=np.float32)  # not k / 255
    depth = (0.5 + rng.random((12, 16), dtype=np.float32)).astype(np.float32)  # not k / 1000
    f = Frame.from_arrays(color, depth, cam, np.eye(4), index=3)
    v = HeldoutView(f, depth_scale=1000.0)
    assert v._color.dtype == torch.float32 and v._depth_dtype == np.float32
    assert torch.equal(v.color, f.color) and torch.equal(v.depth, f.depth)
    assert v.to_frame().index == 3 and torch.equal(v.to_frame().color, f.color)
    assert HeldoutView.from_frame(v) is v  # a view is not copied again
