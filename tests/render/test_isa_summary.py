"""The ISA summary of the cpu kernels' target (``benchmarks/speed/render.py``'s ``numba_target``) from LLVM feature strings.

The strings are those LLVM's ``getHostCPUFeatures`` gives (numba's ``get_host_cpu_features``): on aarch64 Linux it maps
/proc/cpuinfo's ``Features`` line (``asimd`` -> ``+neon``, ``sve`` -> ``+sve``, ...); under qemu-user 7.2, whose
/proc/cpuinfo is the x86 host's, it finds none and reports only the few it sets either way. QEMU_USER_AARCH64 was
captured under emulation; the Neoverse/x86 strings are written in LLVM's format from the CPUs' published feature sets,
not captured on those machines.
"""

from __future__ import annotations

import pytest

from eligsir_o3d.render._cpu_kernels import isa_of

QEMU_USER_AARCH64 = "-aes,-rand,-sha2,-sve"  # llvmlite 0.50 under qemu-aarch64 7.2 (benchmarks/aarch64_check.sh)
NEOVERSE_N1 = "+neon,+fp-armv8,+crc,+lse,+rdm,+rcpc,+dotprod,+fullfp16,+aes,+sha2,-sve,-sve2"  # Graviton2
NEOVERSE_V1 = "+neon,+fp-armv8,+crc,+lse,+rdm,+rcpc,+dotprod,+fullfp16,+bf16,+i8mm,+sve,-sve2,+aes,+sha2"  # Graviton3
NEOVERSE_V2 = "+neon,+fp-armv8,+crc,+lse,+dotprod,+bf16,+i8mm,+sve,+sve2,+sve2-bitperm"  # Graviton4, Grace
ZEN4 = "+sse2,+sse4.2,+avx,+avx2,+fma,+avx512f,+avx512bw,-amx-tile"
HASWELL = "+sse2,+sse4.2,+avx,+avx2,+fma,-avx512f"


@pytest.mark.parametrize("feats, machine, isa", [
    (QEMU_USER_AARCH64, "aarch64", "neon"),  # generic ARMv8-A: NEON is in the baseline, SVE explicitly off
    (NEOVERSE_N1, "aarch64", "neon"),
    (NEOVERSE_V1, "aarch64", "neon+sve"),
    (NEOVERSE_V2, "aarch64", "neon+sve+sve2"),
    ("", "arm64", "neon, its own features"),  # macOS: a named CPU (apple-m1), its features not listed
    ("-neon,-fp-armv8", "aarch64", "baseline"),
    (ZEN4, "x86_64", "avx512f"),
    (HASWELL, "x86_64", "avx2"),
    ("+sse2,-avx", "x86_64", "baseline"),
    ("", "x86_64", "its own features"),
])
def test_isa_of_feature_strings(feats, machine, isa):
    assert isa_of(feats, machine) == isa


def test_aarch64_names_never_read_as_x86_and_back():
    """``+sve2-bitperm`` is not SVE2's name, and x86's ``avx512f`` means nothing on aarch64."""
    assert isa_of("+neon,+sve2-bitperm", "aarch64") == "neon"
    assert isa_of("+avx512f", "aarch64") == "neon"
    assert isa_of("+neon,+sve", "x86_64") == "baseline"
