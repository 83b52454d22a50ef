"""Can gsplat run here? Decided without triggering gsplat's JIT compile (which can take minutes).

gsplat 1.5.3 from PyPI ships CUDA sources, not a compiled extension. ``gsplat.cuda._backend`` resolves it at import:
a prebuilt module (``gsplat.csrc``, from a wheel built for this torch/CUDA), else a JIT build cached under
torch's extensions directory, else - when a CUDA toolkit (``nvcc``) is found - a fresh JIT compile, else
``_C = None``, after which every render fails deep inside gsplat with an AttributeError. :func:`gsplat_status`
reads those cases in the same order, importing ``gsplat.cuda._backend`` only when that import is quick (a prebuilt
or cached extension: then ``_C is not None`` is checked for real). :func:`load_gsplat_extension` is the one place
that may compile; it is called by the gsplat renderer on first use and by ``auto`` before it settles on gsplat.
"""

from __future__ import annotations

import importlib
import importlib.util
import logging
import os
import shutil
import sys
import time
from dataclasses import dataclass

import torch

log = logging.getLogger("eligsir_o3d")

INSTALL_HINT = (
    "gsplat 1.5.3 needs its compiled CUDA extension: install a CUDA toolkit whose nvcc matches torch's CUDA "
    f"({torch.version.cuda or 'none in this torch build'}) so that gsplat compiles it once on first use (minutes, "
    "cached under ~/.cache/torch_extensions), or build it at install time with `pip install --no-build-isolation "
    "gsplat==1.5.3 --no-binary gsplat` on such a machine, or take a prebuilt wheel from "
    "https://docs.gsplat.studio/whl (torch 2.0-2.4 only); meanwhile use --renderer torch (CUDA) or cpu")


DEVICE_HINT = "Use --device cuda:0 on a machine with a CUDA GPU, or --renderer cpu or torch"


class GsplatUnavailable(RuntimeError):
    """gsplat cannot render here; ``reason`` is the one-line cause, the message adds what to do about it."""

    def __init__(self, reason: str, hint: str = INSTALL_HINT):
        super().__init__(f"the 'gsplat' renderer cannot run: {reason}. {hint}")
        self.reason, self.hint = reason, hint


@dataclass(frozen=True)
class GsplatStatus:
    """usable: gsplat can render on the device; compile_pending: only after a JIT compile (minutes, once);
    reason: one line saying why not, or how the extension loads; hint: what to do when it is not usable."""

    usable: bool
    reason: str
    compile_pending: bool = False
    hint: str = INSTALL_HINT

    def error(self) -> GsplatUnavailable:
        return GsplatUnavailable(self.reason, self.hint)


def _backend_module():
    return sys.modules.get("gsplat.cuda._backend")


def _prebuilt_loads() -> bool:
    """A compiled ``gsplat.csrc`` that imports (a wheel built for this torch/CUDA); never compiles."""
    if importlib.util.find_spec("gsplat.csrc") is None:
        return False
    try:
        importlib.import_module("gsplat.csrc")
    except ImportError:  # built for another torch or CUDA: gsplat would fall back to a JIT compile
        return False
    return True


def _jit_build_dir() -> str:
    from torch.utils.cpp_extension import _get_build_directory  # private but stable since torch 1.x

    return _get_build_directory("gsplat_cuda", verbose=False)


def _cached_jit_build() -> bool:
    try:
        d = _jit_build_dir()
    except Exception:  # noqa: BLE001 - a torch without the helper: treat as no cache
        return False
    return os.path.exists(os.path.join(d, "gsplat_cuda.so"))


def _toolkit_found() -> bool:
    """gsplat's own test for a CUDA toolkit (CUDA_HOME or nvcc on PATH), without importing its backend."""
    from torch.utils.cpp_extension import _find_cuda_home

    home = _find_cuda_home()
    if home and os.path.isfile(os.path.join(home, "bin", "nvcc")):
        return True
    return shutil.which("nvcc") is not None


def gsplat_status(device: str | torch.device) -> GsplatStatus:
    """Whether the gsplat renderer can run on ``device``; never starts a JIT compile."""
    device = torch.device(device)
    if device.type != "cuda":
        reason = f"gsplat renders on CUDA only and the device is {device}"
        if torch.cuda.is_available():  # say whether the GPU that is there would do
            on_cuda = gsplat_status("cuda")
            reason += (" (--device cuda:0 would use it)" if on_cuda.usable else
                       f"; on this machine's CUDA device it could not run either: {on_cuda.reason}")
        return GsplatStatus(False, reason, hint=DEVICE_HINT)
    if not torch.cuda.is_available():
        return GsplatStatus(False, "torch sees no CUDA device (torch.cuda.is_available() is False)",
                            hint=DEVICE_HINT)
    if importlib.util.find_spec("gsplat") is None:
        return GsplatStatus(False, "gsplat is not installed",
                            hint="Install it: pip install 'eligsir-o3d[cuda]' (gsplat 1.5.3)")
    backend = _backend_module()
    if backend is None and (_prebuilt_loads() or _cached_jit_build()):
        try:
            backend = _import_backend()  # quick: a prebuilt or cached extension only loads
        except GsplatUnavailable as err:
            return GsplatStatus(False, err.reason)
    if backend is not None:
        if getattr(backend, "_C", None) is None:
            return GsplatStatus(False, "gsplat's CUDA extension did not load (gsplat.cuda._backend._C is None)")
        return GsplatStatus(True, "gsplat's CUDA extension is loaded")
    if _toolkit_found():
        return GsplatStatus(True, "gsplat's CUDA extension is not built yet: the first use JIT-compiles it "
                                  "(a few minutes, once per machine)", compile_pending=True)
    return GsplatStatus(False, "gsplat has no compiled CUDA extension here and there is no CUDA toolkit (nvcc) "
                               "to build one")


def _import_backend():
    try:
        return importlib.import_module("gsplat.cuda._backend")
    except Exception as err:  # noqa: BLE001 - a failed JIT build raises anything from OSError to RuntimeError
        first = (str(err).strip().splitlines() or [""])[0][:200]
        raise GsplatUnavailable(f"its CUDA extension failed to build or load ({type(err).__name__}: {first})") \
            from err


def load_gsplat_extension() -> float:
    """Import gsplat's CUDA extension, JIT-compiling it when nothing is built yet (logged before and after).

    Returns the seconds spent compiling (0.0 when it only loaded). Raises :class:`GsplatUnavailable` (a
    RuntimeError with install hints) when the extension cannot be had.
    """
    if _backend_module() is None and not (_prebuilt_loads() or _cached_jit_build()):
        log.info("gsplat: compiling its CUDA extension now (first use on this machine; a few minutes, cached "
                 "afterwards)")
        t0 = time.perf_counter()
        backend = _import_backend()
        compile_s = time.perf_counter() - t0
        if getattr(backend, "_C", None) is not None:
            log.info("gsplat: CUDA extension compiled in %.0f s", compile_s)
    else:
        backend, compile_s = _import_backend(), 0.0
    if getattr(backend, "_C", None) is None:
        raise GsplatUnavailable("gsplat's CUDA extension did not load (gsplat.cuda._backend._C is None)")
    return compile_s
