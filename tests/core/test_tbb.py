"""numba's threading layer (eligsir_o3d/runtime/tbb.py): TBB when the ``tbb`` wheel is installed and eligsir_o3d's
kernels or public names are used before Open3D is imported, OpenMP otherwise (silently), the user's
NUMBA_THREADING_LAYER first; and the same map bit for bit on either layer. Each case runs in a fresh interpreter: a
process picks its layer once."""

import hashlib
import importlib.metadata
import json
import os
import platform
import subprocess
import sys

import pytest

from eligsir_o3d.runtime import tbb as tbb_runtime


def _has_tbb_wheel() -> bool:
    try:
        importlib.metadata.version("tbb")
    except importlib.metadata.PackageNotFoundError:
        return False
    return sys.platform.startswith("linux") and platform.machine() == "x86_64"


needs_tbb = pytest.mark.skipif(not _has_tbb_wheel(), reason="the tbb wheel is Linux x86_64 only")

LAYER = """
import {first}
import numba, numpy as np
import eligsir_o3d.runtime.jit
@numba.njit(parallel=True)
def f(x):
    for i in numba.prange(x.shape[0]):
        x[i] += 1
f(np.zeros(8))
print(numba.threading_layer())
"""

# a few updates of the rendered room on 2 numba threads (small kernels pinned to one thread are made parallel too,
# so the TBB and OpenMP schedules both run): a digest of every parameter
MAP = """
import hashlib, numba, torch
import eligsir_o3d.runtime.jit as jit
jit.ROWS_LIMIT = jit.PARALLEL_MIN_PIXELS = 1
from eligsir_o3d import Config, Reconstructor
from eligsir_o3d.datasets.synthetic import SyntheticRoom
numba.set_num_threads(2)
seq = SyntheticRoom(n_frames=3, width=160, height=120)
rec = Reconstructor(seq.camera, "cpu", Config(renderer="cpu"), depth_scale=seq.depth_scale)
for item in seq:
    rec.integrate(item.rgbd, item.T_world_cam, updates=4)
h = hashlib.sha256()
for t in rec.gmap.params.values():
    h.update(t.detach().contiguous().numpy().tobytes())
print(numba.threading_layer(), len(rec.gmap), h.hexdigest())
"""


def _run(code: str, **env) -> subprocess.CompletedProcess:
    e = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_THREADING_LAYER")}
    e.update(env)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=e, timeout=600)


@needs_tbb
def test_tbb_serves_numba_when_eligsir_o3d_comes_first():
    r = _run(LAYER.format(first="eligsir_o3d"))
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[-1] == "tbb"
    assert "NumbaWarning" not in r.stderr


def test_open3d_first_falls_back_to_openmp_without_a_warning():
    r = _run(LAYER.format(first="open3d"))
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[-1] == "omp"  # Open3D's bundled TBB (interface 12050) is older than numba accepts
    assert "NumbaWarning" not in r.stderr and "TBB" not in r.stderr


def test_the_users_threading_layer_wins():
    r = _run(LAYER.format(first="eligsir_o3d"), NUMBA_THREADING_LAYER="workqueue")
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[-1] == "workqueue"


@needs_tbb
def test_the_same_map_bit_for_bit_on_tbb_and_openmp():
    got = {}
    for layer in ("tbb", "omp"):
        r = _run(MAP, NUMBA_THREADING_LAYER=layer)
        assert r.returncode == 0, r.stderr
        name, n, digest = r.stdout.split()[-3:]
        assert name == layer
        got[layer] = (int(n), digest)
    assert got["tbb"] == got["omp"] and got["tbb"][0] > 0


def test_the_interface_version_is_read_from_the_library_that_loaded_first():
    code = ("import {first}\nfrom eligsir_o3d import runtime\nfrom eligsir_o3d.runtime import tbb\n"
            "runtime.prepare()\nprint(tbb.interface_version(), tbb.usable())")
    got = {}
    for first in ("eligsir_o3d", "open3d"):
        r = _run(code.format(first=first))
        assert r.returncode == 0, r.stderr
        version, usable = r.stdout.split()[-2:]
        got[first] = (None if version == "None" else int(version), usable == "True")
    if _has_tbb_wheel():
        assert got["eligsir_o3d"][0] >= tbb_runtime.MIN_INTERFACE and got["eligsir_o3d"][1]
    if got["open3d"][0] is not None:  # Open3D's own TBB, where its wheel bundles one
        assert got["open3d"][1] == (got["open3d"][0] >= tbb_runtime.MIN_INTERFACE)


@needs_tbb
def test_the_public_names_prepare_the_process_before_open3d_loads():
    """``eligsir_o3d.Reconstructor`` (the first use) loads the tbb wheel's library before Open3D: the kernels then
    run on TBB, as in a mapping run."""
    code = "import eligsir_o3d\neligsir_o3d.Reconstructor\nimport open3d\n" + LAYER.format(first="numba")
    r = _run(code)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split()[-1] == "tbb"


IMPORT_ONLY = """
import os, sys
env, hooks, modules = dict(os.environ), list(sys.meta_path), set(sys.modules)
import eligsir_o3d
maps = open("/proc/self/maps").read() if os.path.exists("/proc/self/maps") else ""
print(dict(os.environ) == env, sys.meta_path == hooks, "libtbb" in maps,
      sorted(m for m in set(sys.modules) - modules if m.split(".")[0] in ("eligsir_o3d", "open3d", "torch", "numba")))
"""


def test_import_eligsir_o3d_has_no_side_effects_beyond_imports():
    """No environment variable set, no import hook installed, no shared library loaded, nothing heavy imported."""
    r = _run(IMPORT_ONLY)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "True True False ['eligsir_o3d', 'eligsir_o3d._version']"
