"""Choosing gsplat only when it can run: the availability probe, ``auto``'s fallback and its log line, the error of an
explicit ``gsplat``, and the JIT compile that is announced and never started where it cannot succeed.

A CUDA machine is faked (``torch.cuda.is_available`` patched) and so is gsplat's extension module
(``gsplat.cuda._backend`` in ``sys.modules``), so every case runs on a CPU-only machine without compiling anything.
"""

from __future__ import annotations

import logging
import sys
import types

import pytest
import torch

from eligsir_o3d.render import availability, available_backends, get_renderer, resolve_backend
from eligsir_o3d.render.availability import GsplatUnavailable, gsplat_status

pytest.importorskip("gsplat")


def _fake_backend(monkeypatch, compiled: bool):
    mod = types.ModuleType("gsplat.cuda._backend")
    mod._C = object() if compiled else None
    monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", mod)
    return mod


@pytest.fixture
def fake_gpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(availability, "_prebuilt_loads", lambda: False)
    monkeypatch.setattr(availability, "_cached_jit_build", lambda: False)
    monkeypatch.delitem(sys.modules, "gsplat.cuda._backend", raising=False)


def test_auto_falls_back_when_the_extension_did_not_load(fake_gpu, monkeypatch, caplog):
    _fake_backend(monkeypatch, compiled=False)  # what gsplat leaves behind without a toolkit: _C = None
    status = gsplat_status("cuda")
    assert not status.usable and "_C is None" in status.reason
    with caplog.at_level(logging.INFO, logger="eligsir_o3d"):
        assert resolve_backend("auto", "cuda") == "torch"
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "renderer auto -> torch, not gsplat" in lines[0] and "_C is None" in lines[0]
    assert "gsplat" not in available_backends("cuda")
    with pytest.raises(GsplatUnavailable) as err:
        get_renderer("gsplat", "cuda")
    msg = str(err.value)
    assert "_C is None" in msg and "nvcc" in msg and "--renderer torch" in msg  # why, and what to do


def test_auto_takes_gsplat_when_the_extension_loads(fake_gpu, monkeypatch, caplog):
    _fake_backend(monkeypatch, compiled=True)
    with caplog.at_level(logging.INFO, logger="eligsir_o3d"):
        assert resolve_backend("auto", "cuda") == "gsplat"
    assert not caplog.records and "gsplat" in available_backends("cuda")
    assert get_renderer("gsplat", "cuda").name == "gsplat"


def test_no_toolkit_means_no_compile_attempt(fake_gpu, monkeypatch):
    """Without a compiled extension and without nvcc, gsplat is refused before its backend is ever imported."""
    monkeypatch.setattr(availability, "_toolkit_found", lambda: False)
    imported = []
    monkeypatch.setattr(availability, "_import_backend", lambda: imported.append(1))
    status = gsplat_status("cuda")
    assert not status.usable and "no CUDA toolkit" in status.reason
    assert resolve_backend("auto", "cuda") == "torch" and not imported
    assert "gsplat.cuda._backend" not in sys.modules


def test_a_pending_compile_is_announced_and_a_failed_one_falls_back(fake_gpu, monkeypatch, caplog):
    monkeypatch.setattr(availability, "_toolkit_found", lambda: True)
    status = gsplat_status("cuda")
    assert status.usable and status.compile_pending and "JIT-compiles" in status.reason

    def failing_build():
        raise GsplatUnavailable("its CUDA extension failed to build or load (OSError: nvcc fatal: unsupported gpu)")

    monkeypatch.setattr(availability, "_import_backend", failing_build)
    with caplog.at_level(logging.INFO, logger="eligsir_o3d"):
        assert resolve_backend("auto", "cuda") == "torch"
    lines = [r.getMessage() for r in caplog.records]
    assert "compiling its CUDA extension now" in lines[0] and "failed to build" in lines[-1]

    # an explicit gsplat renderer is built without compiling; its first render (warmup) compiles, and says so
    monkeypatch.setattr(availability, "_import_backend", lambda: _fake_backend(monkeypatch, compiled=True))
    renderer = get_renderer("gsplat", "cuda")
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="eligsir_o3d"):
        rasterization = renderer._load()
    import gsplat

    assert rasterization is gsplat.rasterization and renderer.compile_s >= 0.0
    lines = [r.getMessage() for r in caplog.records]
    assert "compiling its CUDA extension now" in lines[0] and "compiled in" in lines[1]


def test_cpu_device_says_why_and_mentions_the_gpu(fake_gpu, monkeypatch, caplog, tmp_path):
    """The default device is the CPU: ``auto`` maps with the cpu renderer and its log line says why, including what
    a GPU that is present could do - here: nothing, its gsplat extension is missing."""
    from eligsir_o3d import Config
    from eligsir_o3d.run.pipeline import RunOptions, run_mapping

    _fake_backend(monkeypatch, compiled=False)
    cfg = Config(renderer="auto")
    cfg.clock.mode, cfg.clock.updates_per_frame, cfg.clock.drain_updates = "updates", 2, 2
    with caplog.at_level(logging.INFO, logger="eligsir_o3d"):
        m = run_mapping("synthetic", tmp_path, cfg, RunOptions(max_frames=6, holdout_every=3, eval_every=0,
                                                               progress=False, plots=False))
    assert m["renderer"] == "cpu"
    why = [r.getMessage() for r in caplog.records if "renderer auto" in r.getMessage()]
    assert why and "renderer auto -> cpu, not gsplat: gsplat renders on CUDA only and the device is cpu" in why[0]
    assert "could not run either" in why[0] and "_C is None" in why[0]


def test_explicit_gsplat_on_the_cpu_is_a_one_line_cli_error(tmp_path):
    from typer.testing import CliRunner

    from eligsir_o3d.cli.app import app

    r = CliRunner().invoke(app, ["map", "synthetic", "--max-frames", "6", "--renderer", "gsplat", "-q",
                                 "--out", str(tmp_path)])
    assert r.exit_code != 0 and "Traceback" not in r.output
    assert "the 'gsplat' renderer cannot run" in r.output and "--renderer cpu" in r.output
