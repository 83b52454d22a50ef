#!/usr/bin/env bash
# A lent GPU machine without network (the workplace's `device` machines): carry what the package needs, in three calls.
#
# Here, with PyPI and apt (once):
#   bash benchmarks/platforms/gpu_offline.sh prepare [FRAMES]
# writes three folders that git ignores (.git/info/exclude), each under the 64 MiB a call may carry with the tree:
#   .gpu_a/  the first 58 MiB of the open3d-cpu wheel
#   .gpu_b/  the rest of it; gsplat, plyfile, pytorch-msssim, tbb and small-gicp wheels; Debian's libEGL, libGL, libusb & co
#   .gpu_c/  the 7-Scenes kitchen's first FRAMES frames (default 200) as a TUM-style folder: .gpu_c/kitchen
# Wheels are for CPython $PYVER (default 3.12, the device image's python3).
#
# There, three calls in a row (a machine goes back after 30 s idle; a folder carried by one call is removed by the
# next call that does not carry it, and so is anything written inside the checkout: what must last goes to /tmp):
#   1. carry [".gpu_a"]:  bash benchmarks/platforms/gpu_offline.sh stash
#   2. carry [".gpu_b"]:  bash benchmarks/platforms/gpu_offline.sh setup
#        installs the wheels into /tmp/gpu_site (a .pth in python3's site-packages puts it on every interpreter's
#        path, subprocesses too), takes the carried libraries where `import open3d` needs them (the H200 image has
#        no libEGL.so.1), stands in for plotly and dash where they are missing (open3d imports both for its Plotly
#        viewer; nothing here draws with it), warms numba's kernels and compiles gsplat's CUDA extension (stop 50,
#        an H200: 4 s install, 34 s numba, 84 s gsplat)
#   3. carry [".gpu_c"]:  source benchmarks/platforms/gpu_offline.sh env; then e.g.
#        python3 -m pytest -q -m cuda tests/
#        python3 benchmarks/speed/cuda_syncs.py --data "$DATA" --renderer gsplat
#        python3 -m eligsir_o3d.cli map "$DATA" --device cuda:0 --renderer gsplat --out /tmp/k -q
#        DATA="$DATA" PY=python3 SKIP_REPEAT=1 bash benchmarks/platforms/gpu_check.sh
# Later calls need only `source ... env` (and carry [".gpu_c"] if they read the frames).
#
# The update's GPU check (one call after 'setup', under 10 minutes; figures in /tmp/gpu_out and $OUT when set):
#   carry [".gpu_c"]:  bash benchmarks/platforms/gpu_offline.sh check
#     1. benchmarks/speed/update_profile.py on the kitchen: launches, syncs and copies per update from
#        torch.profiler, GPU-busy and host ms per update, ms per admitted frame, and ms per update at 160x120 with
#        20k and 200k Gaussians in view;
#     2. the carried frames mapped on cuda:0 in calibrated real time, and the TSDF peer's covered pixels;
#     3. the CPU update's thread scaling on this machine's cores (benchmarks/speed/update_time.py, 1..16 threads).
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
[ "${BASH_SOURCE[0]}" = "$0" ] && set -uo pipefail && cd "$ROOT"  # run, not sourced: leave a caller's shell as it is
PY=${PY:-python3}
PYVER=${PYVER:-3.12}
SITE=/tmp/gpu_site
STASH=/tmp/gpu_stash
KITCHEN=${KITCHEN:-../shared/data/7scenes_redkitchen_jpg1000}
O3D=open3d-cpu==0.20.0
PART_MIB=58

prepare() {
  local frames=${1:-200} tmp
  tmp=$(mktemp -d)
  for d in .gpu_a .gpu_b .gpu_c; do
    grep -qx "/$d/" .git/info/exclude 2>/dev/null || echo "/$d/" >> .git/info/exclude
    rm -rf "$d"; mkdir -p "$d"
  done
  "$PY" -m pip download -q --no-deps --only-binary=:all: --python-version "$PYVER" --implementation cp \
    --platform manylinux_2_35_x86_64 --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
    --platform manylinux2014_x86_64 --platform any -d "$tmp" \
    "$O3D" gsplat==1.5.3 plyfile==1.1.5 pytorch-msssim==1.0.0 tbb==2023.2.0 small-gicp==1.0.1 || return 1
  local whl
  whl=$(ls "$tmp"/open3d_cpu-*.whl) || return 1
  head -c $((PART_MIB * 1024 * 1024)) "$whl" > .gpu_a/open3d.part0
  tail -c +$((PART_MIB * 1024 * 1024 + 1)) "$whl" > .gpu_b/open3d.part1
  basename "$whl" > .gpu_b/open3d.name
  mv "$tmp"/*.whl .gpu_b/ && rm .gpu_b/open3d_cpu-*.whl
  mkdir -p .gpu_b/debs
  (cd "$tmp" && apt-get download libegl1 libgl1 libglx0 libglvnd0 libopengl0 libusb-1.0-0 libx11-6 libx11-data \
     libxcb1 libxau6 libxdmcp6 libbsd0 libmd0 libudev1 libidn2-0 libunistring2 libgomp1 >/dev/null) || return 1
  for f in "$tmp"/*.deb; do cp "$f" ".gpu_b/debs/$(basename "$f" | sed 's/%3a/_/g')"; done
  "$PY" - "$KITCHEN" .gpu_c/kitchen "$frames" <<'EOF' || return 1
import os, shutil, sys
src, dst, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
os.makedirs(dst + "/rgb"); os.makedirs(dst + "/depth")
for f in ("intrinsics.json", "camera-intrinsics.txt", "README.txt"):
    if os.path.exists(f"{src}/{f}"):
        shutil.copy(f"{src}/{f}", f"{dst}/{f}")
for f in ("rgb.txt", "depth.txt", "groundtruth.txt"):
    lines = open(f"{src}/{f}").readlines()
    body = [l for l in lines if l.strip() and not l.startswith("#")][:n]
    open(f"{dst}/{f}", "w").writelines([l for l in lines if l.startswith("#")] + body)
    if f != "groundtruth.txt":
        for l in body:
            shutil.copy(f"{src}/{l.split()[1]}", f"{dst}/{l.split()[1]}")
EOF
  rm -rf "$tmp"
  du -sh .gpu_a .gpu_b .gpu_c
  echo "then three device calls in a row: carry .gpu_a 'stash', carry .gpu_b 'setup', carry .gpu_c 'source ... env; ...'"
}

stash() {
  mkdir -p "$STASH" && cp .gpu_a/open3d.part0 "$STASH"/ && ls -la "$STASH"
}

setup() {
  local t0=$SECONDS whl
  [ -f .gpu_b/open3d.name ] || { echo "setup: no .gpu_b/open3d.name here: carry .gpu_b (made by 'prepare')"; return 1; }
  whl=/tmp/$(cat .gpu_b/open3d.name)
  cat "$STASH/open3d.part0" .gpu_b/open3d.part1 > "$whl" || { echo "no $STASH/open3d.part0: run 'stash' first"; return 1; }
  "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" "$whl" \
    .gpu_b/*.whl || return 1
  echo "$SITE" > "$("$PY" -c 'import site; print(site.getsitepackages()[0])')/gpu_site.pth"
  # pip --target leaves out the tbb wheel's data files (its libtbb.so.12): put them where eligsir_o3d.runtime.tbb looks for them,
  # the interpreter's lib/, so that numba runs on TBB as it does on users' machines
  "$PY" - .gpu_b/tbb-*.whl <<'EOF'
import sys, zipfile
from pathlib import Path
lib = Path(sys.prefix) / "lib"
with zipfile.ZipFile(sys.argv[1]) as z:
    for name in z.namelist():
        if "/data/lib/libtbb" in name:
            (lib / Path(name).name).write_bytes(z.read(name))
EOF
  # open3d imports plotly and dash for its Plotly viewer: stand-ins where they are missing (the viewer is not used)
  mkdir -p "$SITE-stubs"
  if ! "$PY" -c "import plotly.graph_objects" 2>/dev/null; then
    mkdir -p "$SITE-stubs/plotly" && : > "$SITE-stubs/plotly/__init__.py" && : > "$SITE-stubs/plotly/graph_objects.py"
  fi
  if ! "$PY" -c "import dash" 2>/dev/null; then
    mkdir -p "$SITE-stubs/dash"
    printf 'html = dcc = None\n\n\nclass Dash:\n    def __init__(self, *a, **k):\n        raise ImportError("dash is a stand-in here")\n' \
      > "$SITE-stubs/dash/__init__.py"
  fi
  echo "$SITE-stubs" > "$("$PY" -c 'import site; print(site.getsitepackages()[0])')/gpu_stubs.pth"
  : > "$SITE/ldpath"
  if ! "$PY" -c "import open3d" 2>/dev/null; then
    mkdir -p /tmp/gpu_sys && for f in .gpu_b/debs/*.deb; do dpkg -x "$f" /tmp/gpu_sys; done
    echo "/tmp/gpu_sys/usr/lib/x86_64-linux-gnu:/tmp/gpu_sys/lib/x86_64-linux-gnu" > "$SITE/ldpath"
    echo "open3d needs the carried system libraries: $(cat "$SITE/ldpath")"
  fi
  env
  echo "installed in $((SECONDS - t0)) s"
  "$PY" -c "import open3d, numba, torch, eligsir_o3d
print('open3d', open3d.__version__, '| numba', numba.__version__, '| torch', torch.__version__,
      '| CUDA', torch.cuda.is_available())" || return 1
  "$PY" -c "import time; t = time.time()
from eligsir_o3d.render.cpu_backend import warmup; warmup()
import numba; print(f'numba kernels warm in {time.time() - t:.0f} s, threading layer {numba.threading_layer()}')"
  if "$PY" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)"; then
    "$PY" -c "import logging; logging.basicConfig(level=logging.INFO, format='%(message)s')
from eligsir_o3d.render.availability import load_gsplat_extension
print(f'gsplat extension ready; compile seconds: {load_gsplat_extension():.1f}')"
  else
    echo "no CUDA device: gsplat's extension not compiled"
  fi
  echo "setup done in $((SECONDS - t0)) s"
}

env() {
  export PYTHONPATH=$ROOT PYTHONUNBUFFERED=1 NUMBA_CACHE_DIR=/tmp/numba_cache TORCH_EXTENSIONS_DIR=/tmp/gpu_ext
  export MAX_JOBS=${MAX_JOBS:-$(nproc)} DATA=$ROOT/.gpu_c/kitchen
  local ld
  ld=$(cat "$SITE/ldpath" 2>/dev/null)
  [ -n "$ld" ] && export LD_LIBRARY_PATH=$ld${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
  return 0
}

check() {
  env
  local out=${OUT:-/tmp/gpu_out} t0=$SECONDS
  mkdir -p "$out"
  timeout 120 "$PY" benchmarks/speed/update_profile.py --data "$DATA" --device cuda:0 --in-view 20000 200000 \
    --json "$out/profile.json" 2>&1 | tail -60
  echo "== profile done at $((SECONDS - t0)) s"
  timeout 300 "$PY" -m eligsir_o3d.cli map "$DATA" --device cuda:0 --realtime --no-pictures -q --out /tmp/k_cuda \
    && timeout 120 "$PY" benchmarks/quality/tsdf_baseline.py /tmp/k_cuda --json > "$out/tsdf_cuda.json" \
    && "$PY" -c "import json; m = json.load(open('/tmp/k_cuda/metrics.json')); t = json.load(open('$out/tsdf_cuda.json'))
print('cuda map: updates', m.get('updates'), '| heldout', m.get('heldout', {}).get('psnr'), '| tsdf-covered', t)"
  cp /tmp/k_cuda/metrics.json "$out/metrics_cuda.json" 2>/dev/null
  echo "== map done at $((SECONDS - t0)) s"
  timeout 150 "$PY" benchmarks/speed/update_time.py --data "$DATA" --gaussians 20000 --threads 1 2 4 8 16 \
    --rounds 2 --updates 5 --json "$out/threads.json" 2>&1 | tail -15
  echo "== check done in $((SECONDS - t0)) s"
}

case "${1:-}" in
  prepare) shift; prepare "$@" ;;
  check) check ;;
  stash) stash ;;
  setup) setup ;;
  env) env ;;
  *) echo "usage: $0 prepare [FRAMES] | stash | setup | env | check   (see the header)"; return 2 2>/dev/null || exit 2 ;;
esac
