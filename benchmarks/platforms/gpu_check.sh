#!/usr/bin/env bash
# GPU check: on a machine with a CUDA GPU, get the gsplat path running and measure it, in one go.
#
#   bash benchmarks/platforms/gpu_check.sh [OUT_DIR]            # default OUT_DIR: $OUT, else runs/gpu_check
#
# Steps (each bounded by a timeout, each logged to OUT_DIR; a failing step is reported and the next one runs):
#   1. an interpreter with torch + CUDA and this package's dependencies (see "What it needs" below);
#   2. the environment: GPU, torch/CUDA versions, nvcc, gsplat and whether its extension can be had;
#   3. gsplat's CUDA extension: loaded, or JIT-compiled once (minutes; cached under ~/.cache/torch_extensions);
#   4. the CUDA tests (pytest -m cuda: gsplat against the torch reference on the stand-in's scenes, SH degrees 1-3,
#      empty map, no_grad, a Reconstructor end to end, the MCMC step without host round trips);
#   5. the renderer benchmark's GPU rows (torch reference and gsplat on CUDA, 7-Scenes Gaussians);
#   6. host round trips per mapping update (benchmarks/speed/cuda_syncs.py);
#   7. a MAP_FRAMES-frame map of the 7-Scenes kitchen with --renderer gsplat (the deterministic budget clock);
#   8. repeatability: the same frames mapped twice and once resumed (benchmarks/reliability/repeatability.py).
#
# What it needs: a Python whose torch sees the GPU (PY=..., else .venv/bin/python, else python3). Missing Python
# packages are installed with pip when PyPI is reachable (tools/setup.sh --test builds a .venv when no usable
# interpreter exists); a machine without network needs them installed beforehand. gsplat 1.5.3 from PyPI has no
# compiled extension: step 3 compiles it with nvcc (a CUDA toolkit matching torch.version.cuda, CUDA_HOME or nvcc on
# PATH, plus ninja); without one the gsplat steps report why and the torch-on-CUDA rows still run.
# Data: DATA=path to 7scenes_redkitchen_jpg1000 (default ../shared/data/..., then shared/data/...); without it the
# map and repeatability steps use the embedded synthetic room.
# Knobs: MAP_FRAMES (200), REPEAT_FRAMES (40), SKIP_REPEAT=1, MAP_TORCH=1 (also map with the torch renderer),
# MAX_JOBS (nvcc jobs, default: all cores), STEP_TIMEOUT (seconds per step, 900).
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT=${1:-${OUT:-runs/gpu_check}}
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
export MAX_JOBS=${MAX_JOBS:-$(nproc)}
MAP_FRAMES=${MAP_FRAMES:-200}
REPEAT_FRAMES=${REPEAT_FRAMES:-40}
STEP_TIMEOUT=${STEP_TIMEOUT:-900}
FAILED=()
log() { echo; echo "== $(date -u +%H:%M:%S) $*"; }
step() {  # step NAME CMD... : run with a timeout, tee to OUT/NAME.log, remember failures
  local name=$1; shift
  local t0=$SECONDS
  timeout "$STEP_TIMEOUT" "$@" 2>&1 | tee "$OUT/$name.log"
  local rc=${PIPESTATUS[0]}
  echo "-- $name: exit $rc after $((SECONDS - t0)) s"
  [ "$rc" -eq 0 ] || FAILED+=("$name (exit $rc)")
  return 0
}

# ---- 1. interpreter ------------------------------------------------------------------------------------------------
log "1. interpreter"
usable() { "$1" -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)" >/dev/null 2>&1; }
if [ -z "${PY:-}" ]; then
  for c in .venv/bin/python python3 python; do
    if command -v "$c" >/dev/null 2>&1 && usable "$c"; then PY=$c; break; fi
  done
fi
online() {
  timeout 10 "${PY:-python3}" -c "import urllib.request as r; r.urlopen('https://pypi.org/simple/pip/', timeout=8)" \
    >/dev/null 2>&1
}
if [ -z "${PY:-}" ]; then
  if online; then
    echo "no interpreter with torch + CUDA: building .venv with tools/setup.sh --test (torch from PyPI carries CUDA)"
    bash tools/setup.sh --test && PY=.venv/bin/python
  fi
fi
if [ -z "${PY:-}" ] || ! usable "$PY"; then
  echo "FATAL: no Python whose torch sees a CUDA device (set PY=...; offline machines need torch with CUDA installed)"
  exit 2
fi
need="open3d numba plyfile typer pytest scipy cv2 pytorch_msssim matplotlib tqdm gsplat ninja"
missing=$("$PY" -c "
import importlib.util as u
print(' '.join(m for m in '$need'.split() if u.find_spec(m) is None))")
if [ -n "$missing" ]; then
  echo "missing Python packages: $missing"
  if online; then "$PY" -m pip install -q -e ".[test]" ninja || FAILED+=("pip install")
  else echo "offline: install them beforehand (pip install -e '.[test]' ninja)"; FAILED+=("missing: $missing"); fi
fi
echo "using $PY"

# ---- 2. environment ------------------------------------------------------------------------------------------------
log "2. environment"
nvidia-smi -L 2>/dev/null || echo "nvidia-smi: not found"
command -v nvcc >/dev/null 2>&1 && nvcc --version | tail -1 || echo "nvcc: not on PATH (CUDA_HOME=${CUDA_HOME:-unset})"
"$PY" - <<'EOF' | tee "$OUT/environment.log"
import importlib.metadata as md, platform, torch
from eligsir_o3d.render.availability import gsplat_status
print(f"python {platform.python_version()}  torch {torch.__version__}  torch CUDA {torch.version.cuda}  "
      f"device {torch.cuda.get_device_name(0)}")
try:
    print(f"gsplat {md.version('gsplat')}")
except md.PackageNotFoundError:
    print("gsplat not installed")
s = gsplat_status("cuda")
print(f"gsplat usable={s.usable} compile_pending={s.compile_pending}: {s.reason}")
EOF

# ---- 3. gsplat extension -------------------------------------------------------------------------------------------
log "3. gsplat CUDA extension (MAX_JOBS=$MAX_JOBS)"
step gsplat_extension "$PY" -c "
import logging; logging.basicConfig(level=logging.INFO, format='%(message)s')
from eligsir_o3d.render.availability import load_gsplat_extension
print(f'gsplat extension ready; compile seconds: {load_gsplat_extension():.1f}')"
GSPLAT=0
"$PY" -c "
import sys
from eligsir_o3d.render.availability import gsplat_status
s = gsplat_status('cuda')
sys.exit(0 if s.usable and not s.compile_pending else 1)" && GSPLAT=1
echo "gsplat ready: $GSPLAT"

# ---- 4. CUDA tests -------------------------------------------------------------------------------------------------
log "4. CUDA tests"
step cuda_tests "$PY" -m pytest -q -m cuda -rs tests/

# ---- 5. renderer benchmark, GPU rows -------------------------------------------------------------------------------
DATA=${DATA:-}
for d in ../shared/data/7scenes_redkitchen_jpg1000 shared/data/7scenes_redkitchen_jpg1000; do
  [ -z "$DATA" ] && [ -d "$d" ] && DATA=$d
done
log "5. renderer benchmark on CUDA"
if [ -d ../shared/data/7scenes_redkitchen_jpg1000 ]; then
  step render_bench "$PY" benchmarks/speed/render.py --device cuda --json --gaussians 20000 100000 300000 \
    --scales 0.25 0.5 1.0 --max-ref-seconds 2
else
  echo "skipped: benchmarks/speed/render.py reads ../shared/data/7scenes_redkitchen_jpg1000, not found"
fi

# ---- 6. host round trips per update --------------------------------------------------------------------------------
log "6. host round trips per mapping update"
RENDERER=torch; [ "$GSPLAT" = 1 ] && RENDERER=gsplat
step cuda_syncs "$PY" benchmarks/speed/cuda_syncs.py --data "${DATA:-synthetic}" --renderer $RENDERER

# ---- 7. a map on CUDA ----------------------------------------------------------------------------------------------
log "7. $MAP_FRAMES-frame map, --renderer $RENDERER (data: ${DATA:-synthetic})"
run_map() {  # run_map RENDERER
  step "map_$1" "$PY" -c "from eligsir_o3d.cli import main; main()" map "${DATA:-synthetic}" \
    --max-frames "$MAP_FRAMES" --device cuda:0 --renderer "$1" --out "$OUT/map_$1" -q
  [ -f "$OUT/map_$1/metrics.json" ] && "$PY" - "$OUT/map_$1/metrics.json" <<'EOF'
import json, sys
m = json.load(open(sys.argv[1]))
h = m["heldout"]
print(json.dumps({k: m.get(k) for k in ("renderer", "device", "frames_total", "updates", "gaussians", "mapping_time_s",
                                        "rtf", "cvq_auc", "peak_rss_mb")} | {"heldout_psnr": h["psnr"],
                                        "heldout_ssim": h["ssim"], "depth_rmse_m": h["depth_rmse_m"]}))
EOF
}
run_map $RENDERER
[ "${MAP_TORCH:-0}" = 1 ] && [ "$RENDERER" != torch ] && run_map torch

# ---- 8. repeatability ----------------------------------------------------------------------------------------------
if [ "${SKIP_REPEAT:-0}" != 1 ]; then
  log "8. repeatability: two runs and a resumed one, $REPEAT_FRAMES frames"
  step repeatability "$PY" benchmarks/reliability/repeatability.py --device cuda:0 --renderer $RENDERER \
    --frames "$REPEAT_FRAMES" --data "${DATA:-synthetic}"
fi

log "done: logs in $OUT"
if [ ${#FAILED[@]} -gt 0 ]; then printf 'FAILED: %s\n' "${FAILED[@]}"; exit 1; fi
echo "all steps passed"
