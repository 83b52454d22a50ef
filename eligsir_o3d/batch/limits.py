"""What a batch checks before its first task, and how long each task may run.

- :func:`check_resources`: a task asking for more CPUs or GPUs than any one machine of the cluster has would wait
  for ever; it is refused before anything is submitted, naming the option and the largest machine.
- :func:`task_timeout`: the seconds a sequence may take (``--task-timeout``; 0: :func:`default_timeout`). A task
  past it is stopped and reported failed; the other sequences go on.
- :data:`RESERVED_NAMES`: the batch folder's own files; no sequence folder takes one of these names.
"""

from __future__ import annotations

import logging

log = logging.getLogger("eligsir_o3d")

RESERVED_NAMES = ("summary.csv", "batch.json", "batch.log")  # compared case-insensitively
BASE_S = 600.0  # seconds every task is allowed: start-up, calibration, evaluation, pictures
MAPPING_FACTOR = 10.0  # times the mapping time a recording asks for (its length / the replay speed)
PER_FRAME_S = 5.0  # seconds per frame at 8 updates a frame (the updates clock: no modelled time)


def check_resources(ray, cpus_per_task: float, gpus_per_task: float) -> None:
    """Raise ValueError when no alive machine of the cluster offers ``cpus_per_task`` CPUs and ``gpus_per_task``
    GPUs (a Ray task asking for more would never be scheduled)."""
    nodes = [n.get("Resources", {}) for n in ray.nodes() if n.get("Alive", n.get("alive", True))]
    if not nodes:
        return
    most_cpus = max(float(r.get("CPU", 0)) for r in nodes)
    most_gpus = max(float(r.get("GPU", 0)) for r in nodes)
    if cpus_per_task > most_cpus:
        raise ValueError(f"--cpus-per-task {cpus_per_task:g}: no machine of the cluster has that many CPUs (the "
                         f"largest has {most_cpus:g}); use --cpus-per-task {most_cpus:g} or fewer")
    if gpus_per_task > most_gpus:
        raise ValueError(f"--gpus-per-task {gpus_per_task:g}: no machine of the cluster has that many GPUs (the "
                         f"largest has {most_gpus:g}); use --gpus-per-task {most_gpus:g} or fewer")
    if not any(float(r.get("CPU", 0)) >= cpus_per_task and float(r.get("GPU", 0)) >= gpus_per_task for r in nodes):
        raise ValueError(f"--cpus-per-task {cpus_per_task:g} --gpus-per-task {gpus_per_task:g}: no single machine "
                         f"of the cluster has both; ask for fewer")


def default_timeout(request: dict) -> float:
    """Seconds a task of ``request`` may take: :data:`BASE_S` + :data:`MAPPING_FACTOR` x (the recording's length
    / the replay speed) for the cost and real-time clocks, + :data:`PER_FRAME_S` per frame (scaled by the updates
    per frame) for every clock. A recording that cannot be opened here gets :data:`BASE_S` (its task fails fast)."""
    from ..datasets import open_sequence

    clock = request["config"].get("clock", {})
    try:
        seq = open_sequence(request["path"], **(request["options"].get("sequence_options") or {}))
    except Exception as e:  # noqa: BLE001 - the task reports the error; the timeout only needs a bound
        log.debug("%s: not opened for its timeout (%s)", request["path"], e)
        return BASE_S
    n = len(seq) if request["options"].get("max_frames") is None else min(len(seq), request["options"]["max_frames"])
    span = float(seq.timestamps[max(n - 1, 0)] - seq.timestamps[0]) + seq.frame_period_s
    seconds = BASE_S + PER_FRAME_S * n * max(1.0, float(clock.get("updates_per_frame", 8)) / 8.0)
    if clock.get("mode", "cost") in ("cost", "realtime"):
        seconds += MAPPING_FACTOR * span / float(clock.get("speed", 1.0))
    return seconds


def task_timeout(request: dict, given: float) -> float:
    """``given`` seconds (``--task-timeout``), or :func:`default_timeout` when 0."""
    return float(given) if given else default_timeout(request)
