"""Many recordings at once: ``eligsir batch`` / :func:`map_many` run one Ray task per sequence.

    from eligsir_o3d.batch import map_many
    results = map_many(["runs/in/kitchen", "runs/in/office", "list.txt"], "runs/batch", max_frames=500)
    {r.name: r.metrics["heldout"]["psnr"] for r in results if r.metrics}

Each task calls the mapping entry point of ``eligsir map`` (``pipeline.run_mapping``) with periodic checkpoints;
a task whose worker dies is retried by Ray and resumes from the last checkpoint; a second call over the same
``out`` skips finished sequences. Ray is imported only when there is mapping to do (the ``batch`` extra).
"""

from .report import SequenceResult
from .runner import INSTALL_HINT, format_report, import_ray, map_many
from .specs import BatchError, SequenceSpec, expand_inputs, read_manifest

__all__ = ["BatchError", "INSTALL_HINT", "SequenceResult", "SequenceSpec", "expand_inputs", "format_report",
           "import_ray", "map_many", "read_manifest"]
