"""The pose benchmark (benchmarks/quality/poses.py) tracks the frames a mapping run tracks, where asked."""

from __future__ import annotations

import pytest

poses_bench = pytest.importorskip("benchmarks.quality.poses")

from eligsir_o3d.run.pipeline import heldout_indices  # noqa: E402


def test_tracked_frames_are_the_mapping_runs_source_frames():
    held = set(heldout_indices(1000, 8))
    frames = poses_bench.tracked_frames(1000, 8)
    assert frames == [i for i in range(1000) if i not in held]
    assert len(frames) == 875 and 4 not in frames and 12 not in frames and 0 in frames
    assert poses_bench.tracked_frames(30, 0) == list(range(30))
    assert poses_bench.tracked_frames(30, 7) == [i for i in range(30) if i % 7 != 3]
