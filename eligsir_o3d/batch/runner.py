"""The driver of a batch: expands the inputs, skips finished sequences, runs one Ray task per remaining sequence
(local Ray by default, a cluster with ``address``), shows progress and writes the summary."""

from __future__ import annotations

import json
import logging
import os
import sys
from pathlib import Path
from typing import Callable, Iterable

from ..io.inputs import printable
from ..io.outputs import check_output_folder
from ..run.option_table import check_option, default
from .limits import check_resources, task_timeout as timeout_for
from .report import Progress, SequenceResult, comparison, write_summary
from .specs import BatchError, Defaults, build_request, expand_inputs, folder_status, read_state
from .task import map_sequence, one_line

INSTALL_HINT = "eligsir batch needs Ray: pip install 'eligsir-o3d[batch]' (or: pip install ray)"
OBJECT_STORE_BYTES = 128 * 2**20  # tasks pass only small dicts; Ray's default would reserve 30% of the RAM


def import_ray():
    try:
        import ray
    except ImportError:
        raise BatchError(INSTALL_HINT) from None
    return ray


def map_many(inputs: Iterable, out: str | Path = "runs/batch", *, address: str | None = None,
             cpus_per_task: float = default("cpus_per_task"), gpus_per_task: float | None = None,
             max_retries: int = default("max_retries"), checkpoint_every: int = default("checkpoint_every"),
             max_frames: int | None = None, pose: str = "gt", speed: float | None = None,
             config: str | None = None, updates_per_frame: int | None = None, eval_every: int = default("eval_every"),
             holdout_every: int = default("holdout_every"), seed: int | None = None, cost_model: str | None = None,
             device: str | None = None, plots: bool = True, task_timeout: float = default("task_timeout"),
             run_options: dict | None = None, echo: Callable[[str], None] | None = print,
             live: bool | None = None) -> list[SequenceResult]:
    """Map many sequences, one Ray task each, into ``out/<name>/`` (the results folder of ``eligsir map``).

    Finished sequences (``out/<name>/batch.json`` says done for the same request) are not mapped again;
    unfinished ones resume from their last checkpoint.

    Args:
        inputs: sequence paths, manifest files (see :mod:`eligsir_o3d.batch.specs`) or SequenceSpec objects.
        out: the batch folder: one results folder per sequence and ``summary.csv``.
        address: None starts Ray in this process with this machine's CPUs and GPUs (or joins the cluster of
            ``ray job submit``); ``"auto"`` or ``"ray://host:port"`` joins one.
        cpus_per_task: CPUs per sequence (also its torch and numba thread count).
        gpus_per_task: GPUs per sequence; None: 1 when the cluster has GPUs, else 0 (the CPU renderer).
        max_retries: retries of a sequence whose worker died, each resuming from its last checkpoint.
        checkpoint_every: source frames between checkpoints.
        run_options: any other RunOptions field, for every sequence.
        echo: where progress lines go (None: nowhere).
        max_frames: the batch's default for ``eligsir map``'s option of that name, as are ``pose``, ``speed``,
            ``config``, ``updates_per_frame``, ``eval_every``, ``holdout_every``, ``seed``, ``cost_model``,
            ``device`` and ``plots``; a manifest line's own options win. ``cost_model`` None uses the config's
            (``eligsir_o3d.run.options.COST_MODEL_RULE``). Numeric options are checked against the run-options
            table (:mod:`eligsir_o3d.run.option_table`), the CPUs and GPUs per task against the cluster's
            machines, before anything is mapped.
        task_timeout: seconds a task may run before it is stopped and reported failed (0: from its recording's
            length and speed, :mod:`.limits`).

    Returns:
        One :class:`~eligsir_o3d.batch.report.SequenceResult` per sequence, in input order (``status`` done,
        done-earlier or failed; ``metrics``); ``out/summary.csv`` holds the same.

    Example:
        ```python
        from eligsir_o3d.batch import map_many

        results = map_many(["synthetic"], "runs/api-batch", max_frames=4, eval_every=0, plots=False,
                           run_options={"sequence_options": {"n_frames": 4, "width": 160, "height": 120}},
                           echo=None)
        print([r.status for r in results])  # ['done']
        ```
    """
    echo = echo or (lambda line: None)
    cpus_per_task = check_option("cpus_per_task", cpus_per_task)
    gpus_per_task = check_option("gpus_per_task", gpus_per_task)
    max_retries = check_option("max_retries", max_retries)
    task_timeout = check_option("task_timeout", task_timeout)
    check_output_folder(out, "--out")  # a file there: one line, exit 3
    specs = expand_inputs(inputs)
    d = Defaults(max_frames=max_frames, pose=pose, speed=speed, config=config, updates_per_frame=updates_per_frame,
                 eval_every=eval_every, holdout_every=holdout_every, seed=seed, cost_model=cost_model, device=device,
                 checkpoint_every=checkpoint_every, plots=plots, extra_options=dict(run_options or {}))
    requests = [build_request(s, d) for s in specs]
    out = Path(out).resolve()
    out.mkdir(parents=True, exist_ok=True)

    results, todo = _earlier_results(requests, out, echo)
    if todo:
        limits = {r["name"]: timeout_for(r, task_timeout) for r in todo}
        _run_tasks(todo, out, results, address, cpus_per_task, gpus_per_task, max_retries, device, echo, live,
                   limits)
    ordered = [results[r["name"]] for r in requests]
    write_summary(ordered, out)
    return ordered


def _earlier_results(requests: list[dict], out: Path, echo) -> tuple[dict[str, SequenceResult], list[dict]]:
    """Each request's result as its folder stands (finished earlier, or a folder not of a batch: failed) and the
    requests still to map."""
    results: dict[str, SequenceResult] = {}
    todo = []
    for req in requests:
        folder = out / req["name"]
        status = folder_status(folder, req)
        res = SequenceResult(req["name"], req["path"], str(folder), status="failed")
        if status == "done":
            st = read_state(folder) or {}
            res.status, res.attempts, res.resumed_from = "done-earlier", st.get("attempts", 1), st.get("resumed_from")
            res.metrics = json.loads((folder / "metrics.json").read_text())
            echo(f"{req['name']}: finished earlier, not mapped again")
        elif status == "foreign":
            res.error = f"{folder}: exists and was not written by eligsir batch; choose another --out or remove it"
            echo(f"{req['name']}: FAILED: {res.error}")
        else:
            if status == "changed":
                echo(f"{req['name']}: its options changed since it was mapped; mapping it again from frame 0")
            todo.append(req)
        results[req["name"]] = res
    return results, todo


def _run_tasks(todo: list[dict], out: Path, results: dict, address, cpus_per_task, gpus_per_task, max_retries,
               device, echo, live, limits: dict) -> None:
    import time

    ray = import_ray()
    started = _connect(ray, address)
    try:
        gpus = gpus_per_task
        if gpus is None:
            gpus = 1 if ray.cluster_resources().get("GPU", 0) > 0 else 0
        check_resources(ray, cpus_per_task, gpus)  # a request no machine can meet would wait for ever
        if device is None and gpus > 0:
            device = "cuda:0"  # Ray hands each task its own GPUs as CUDA_VISIBLE_DEVICES
        cpus = ray.cluster_resources().get("CPU", 0)
        echo(f"batch: {len(todo)} sequence(s) to map on Ray ({cpus:g} CPUs, "
             f"{ray.cluster_resources().get('GPU', 0):g} GPUs; {cpus_per_task:g} CPU and {gpus:g} GPU per task, "
             f"up to {max_retries} retries) into {out}")
        # progress messages travel through Ray's own queue actor: a worker that imports only Ray (~85 MB), where
        # an actor class of this package would import torch and Open3D (~430 MB)
        from ray.util.queue import Queue

        board = Queue(actor_options={"num_cpus": 0})
        # max_calls=1: a fresh worker process per sequence, so memory (and a GPU context) is returned between
        # sequences and metrics.json's peak RSS is this sequence's, not the worker's peak over earlier tasks
        task = ray.remote(max_calls=1)(_ray_task).options(num_cpus=cpus_per_task, num_gpus=gpus,
                                                          max_retries=max_retries, retry_exceptions=False)
        refs = {task.remote(req, str(out), cpus_per_task, device, board): req["name"] for req in todo}
        progress = Progress([r["name"] for r in todo], echo=echo,
                            live=sys.stdout.isatty() if live is None else live)
        pending = list(refs)
        deadline = {ref: time.monotonic() + limits[name] for ref, name in refs.items()}
        while pending:
            ready, pending = ray.wait(pending, num_returns=len(pending), timeout=0.5)
            for ref in [r for r in pending if time.monotonic() > deadline[r]]:
                pending.remove(ref)
                _stop(ray, ref, refs[ref], limits[refs[ref]], out, results, progress)
            for name, info in _drain(board):
                progress.handle(name, info)
            for ref in ready:
                name = refs[ref]
                try:
                    r = ray.get(ref)
                except ray.exceptions.RayError as e:  # the worker died more than max_retries times
                    msg = f"the task failed after {max_retries} retries: {one_line(e)}"
                    progress.handle(name, {"event": "failed", "error": msg})
                    st = read_state(out / name) or {}
                    results[name] = SequenceResult(name, results[name].path, str(out / name), "failed", msg,
                                                   attempts=st.get("attempts", 0))
                    continue
                results[name] = SequenceResult(name, r["path"], r["folder"], r["status"], r["error"], r["metrics"],
                                               r["attempts"], r["resumed_from"])
        for name, info in _drain(board):
            progress.handle(name, info)
    finally:
        if started:
            ray.shutdown()


def _stop(ray, ref, name: str, limit: float, out: Path, results: dict, progress) -> None:
    """Cancel the task ``ref`` of sequence ``name`` that ran past ``limit`` seconds; report it failed."""
    ray.cancel(ref, force=True)
    msg = f"stopped after {limit:.0f} s (--task-timeout; 0 derives it from the recording's length and speed)"
    progress.handle(name, {"event": "failed", "error": msg})
    st = read_state(out / name) or {}
    results[name] = SequenceResult(name, results[name].path, str(out / name), "failed", msg,
                                   attempts=st.get("attempts", 0))


def _ray_task(request: dict, out_root: str, cpus: float, device: str | None, board) -> dict:
    """The Ray task: map_sequence with its progress messages put on the driver's queue."""
    import time

    return map_sequence(request, out_root, cpus, device,
                        report=lambda name, info: board.put_nowait((name, dict(info, t=time.time()))))


def _drain(board) -> list:
    n = board.qsize()
    return board.get_nowait_batch(n) if n else []


def _connect(ray, address: str | None) -> bool:
    """Start or join Ray unless this process already did; True when this call started the connection."""
    if ray.is_initialized():
        return False
    quiet = dict(log_to_driver=False, logging_level=logging.WARNING)
    if address is None and not os.environ.get("RAY_ADDRESS"):
        # a private Ray in this process: this machine's cores (and GPUs, detected by Ray), no dashboard, a small
        # object store
        ray.init(num_cpus=os.cpu_count(), include_dashboard=False, object_store_memory=OBJECT_STORE_BYTES, **quiet)
    elif address is not None and address.startswith("ray://"):
        ray.init(address=address)  # Ray Client (needs ray[client] here and on the head node)
    else:
        ray.init(address=address, **quiet)  # "auto", host:port, or RAY_ADDRESS set by `ray job submit`
    return True


def format_report(results: list[SequenceResult], out: Path) -> list[str]:
    """The closing lines: counts, the eval table of finished sequences, failures with their reasons."""
    lines = []
    done = [r for r in results if r.status != "failed"]
    failed = [r for r in results if r.status == "failed"]
    earlier = sum(r.status == "done-earlier" for r in results)
    table = comparison(results)
    if table:
        lines += ["", table, ""]
    for r in failed:
        lines.append(printable(f"FAILED {r.name}: {r.error}"))
    lines.append(f"{len(done)} of {len(results)} sequences finished ({earlier} earlier), {len(failed)} failed; "
                 f"summary in {Path(out) / 'summary.csv'}")
    return lines
