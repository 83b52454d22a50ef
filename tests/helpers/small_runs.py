"""Small inputs several test modules share: a saved 200-Gaussian map with its trajectory, a quick run's config and
options, a local Ray."""

import pytest
import torch

from eligsir_o3d import Config
from eligsir_o3d.core.gaussians import GaussianMap
from eligsir_o3d.io.ply import save_ply
from eligsir_o3d.run.pipeline import RunOptions


def write_small_map(folder):
    """``folder/map.ply`` (200 random Gaussians in a 5 x 5 x 3 m box) and a two-pose ``trajectory.txt``."""
    g = GaussianMap(0)
    torch.manual_seed(0)
    g.add(torch.rand(200, 3) * torch.tensor([5.0, 5.0, 3.0]), torch.rand(200, 3), torch.rand(200, 3) * 0.1 + 0.01,
          torch.rand(200) * 0.5 + 0.4, torch.randn(200, 4))
    folder.mkdir(parents=True, exist_ok=True)
    p = folder / "map.ply"
    save_ply(g, p)
    (folder / "trajectory.txt").write_text("0 2.5 2.5 1.5 0 0 0 1\n1 2.6 2.5 1.5 0 0 0 1\n")
    return p


def quick_config() -> Config:
    """The torch renderer, two updates a frame, four in the drain."""
    cfg = Config(renderer="torch")
    cfg.clock.mode, cfg.clock.updates_per_frame, cfg.clock.drain_updates = "updates", 2, 4
    return cfg


def quick_options(**kw) -> RunOptions:
    """Ten frames, every fifth held out, no evaluation during the run, nothing drawn."""
    return RunOptions(**{**dict(max_frames=10, holdout_every=5, eval_every=0, progress=False, plots=False,
                                pictures=False), **kw})


def start_local_ray():
    """A two-CPU Ray in this process (skips without ray); the caller shuts it down."""
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, object_store_memory=100 * 2**20, log_to_driver=False,
             logging_level="WARNING")
    return ray
