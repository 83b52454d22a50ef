"""Kernel sets: the device work of one mapping update (select, backward, step) behind one object chosen per map.

- ``numba`` (:mod:`.cpu`): float32 maps on the CPU, compiled passes over rows and pixels;
- ``torch`` (:mod:`.reference`): composed torch operators on any device, the reference the others are tested
  against;
- ``fused`` (:mod:`.device`): the device path: a bucketed row capacity, no host synchronisation of its own, each
  stage one or a few fused kernels (Triton where it runs: CUDA, or its interpreter on the CPU; the same stages in
  torch operators elsewhere).

``config.optim.kernels`` names one; ``auto`` takes ``numba`` for a float32 map on the CPU and ``fused`` on CUDA.
Any set runs on any device its operators support, so the CUDA path's code runs on a CPU by choice (tests,
benchmarks/speed/update_launches.py), not by patching.
"""

from __future__ import annotations

import torch

from .base import KernelSet, RowView, StepTerms

KERNEL_SETS = ("auto", "numba", "torch", "fused")

__all__ = ["KERNEL_SETS", "KernelSet", "RowView", "StepTerms", "get_kernels"]


def get_kernels(name: str = "auto", device: str | torch.device = "cpu",
                dtype: torch.dtype = torch.float32) -> KernelSet:
    """The kernel set ``name`` (see the module docstring) for a map on ``device`` with parameters of ``dtype``."""
    device = torch.device(device)
    if name not in KERNEL_SETS:
        raise ValueError(f"unknown kernel set {name!r}: choose from {', '.join(KERNEL_SETS)}")
    if name == "auto":
        name = "fused" if device.type == "cuda" else "numba" if device.type == "cpu" and dtype == torch.float32 \
            else "torch"
    if name == "numba":
        if device.type != "cpu" or dtype != torch.float32:
            raise ValueError(f"the numba kernel set takes float32 maps on the CPU, not {dtype} on {device}")
        from .cpu import NumbaKernels

        return NumbaKernels()
    if name == "fused":
        from .device import FusedKernels

        return FusedKernels(device)
    from .reference import TorchKernels

    return TorchKernels()
