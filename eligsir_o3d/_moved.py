"""Old import paths of modules that moved in the layout by concern, kept for one release.

``import eligsir_o3d.pipeline`` (or ``from eligsir_o3d.checkpoint import ...``) still works: a finder at the head of
``sys.meta_path`` (ahead of an editable install's finder and of stale files of an older install) answers the old
name with the module at its new home, the very same module object, after a :class:`DeprecationWarning` that names
the new path. Pickles and ``monkeypatch`` strings that hold an old path
resolve the same way. Remove this module (and its line in ``__init__``) in the release after next."""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

MOVED = {  # old module -> new module, both under eligsir_o3d
    "camera": "core.camera", "frame": "core.frame", "gaussians": "core.gaussians", "voxels": "core.voxels",
    "atomic_io": "io.atomic", "ply": "io.ply", "checkpoint": "io.checkpoint",
    "pipeline": "run.pipeline", "results": "run.results", "resume_check": "run.resume", "runlock": "run.lock",
    "safe_outputs": "run.outputs", "live": "run.live_run", "frame_faults": "run.frame_faults",
    "row_adam": "optim.row_adam", "_update_kernels": "optim.update_kernels", "_dssim_kernels": "optim.dssim_kernels",
    "pose_refine": "pose.refine", "cli_commands": "cli.commands", "memory": "budget.memory",
    "color_calibration": "datasets.color_calibration", "clock": "budget",
    "budget.config": "budget.clock", "scheduling.load": "scheduling.fixed_work",
    "visual.results": "visual.run_pictures",
}


class _Alias(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds ``eligsir_o3d.<old>`` and loads it as the already-imported ``eligsir_o3d.<new>``."""

    def find_spec(self, fullname, path=None, target=None):
        root, _, old = fullname.partition(".")
        if root != __package__ or old not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        new = f"{__package__}.{MOVED[spec.name.partition('.')[2]]}"
        warnings.warn(f"{spec.name} moved to {new}; the old path works until the next release", DeprecationWarning,
                      stacklevel=2)
        return importlib.import_module(new)

    def exec_module(self, module) -> None:
        """Nothing to run: ``create_module`` returned the imported module."""


def install() -> None:
    if not any(isinstance(f, _Alias) for f in sys.meta_path):
        sys.meta_path.insert(0, _Alias())
