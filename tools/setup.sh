#!/usr/bin/env bash
# Set up eligsir_o3d on a fresh Debian/Ubuntu machine with Python >= 3.10:
#   system libraries Open3D needs, a virtual environment in .venv, the CPU build of torch, the package.
#   --test  also installs the test extras (and Debian's chromium, which the viewer's browser test drives, if absent);
#   --all  also installs the optional pose sources (kiss-icp, pycolmap).
set -euo pipefail
cd "$(dirname "$0")/.."
SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
pkgs="libusb-1.0-0 libegl1 libgl1 libx11-6 libudev1 libidn2-0 libgomp1 python3-venv"
missing=""
for p in $pkgs; do dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"; done
if [ -n "$missing" ]; then
  $SUDO apt-get update -q && $SUDO apt-get install -y -q --no-install-recommends $missing
fi
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
# torch first, pinned. Set TORCH_INDEX=https://download.pytorch.org/whl/cpu to take PyTorch's small CPU build
# where PyPI would serve the multi-GB CUDA one (machines with a local torch wheel pick that up via pip's find-links).
if [ -n "${TORCH_INDEX:-}" ]; then
  .venv/bin/python -m pip install -q "torch==${TORCH_VERSION:-2.13.0}" --index-url "$TORCH_INDEX" --extra-index-url https://pypi.org/simple
else
  .venv/bin/python -m pip install -q "torch==${TORCH_VERSION:-2.13.0}"
fi
extras=""
for a in "$@"; do
  case "$a" in
    --test) extras="${extras:+$extras,}test,pose" ;;
    --all) extras="${extras:+$extras,}test,pose,eval" ;;
  esac
done
case " $* " in
  *" --test "*|*" --all "*)
    if ! command -v chromium >/dev/null 2>&1; then  # tests/visual/test_viewer_browser.py skips, saying so, without it
      { $SUDO apt-get update -q && $SUDO apt-get install -y -q chromium; } ||
        echo "chromium could not be installed: the viewer's browser test will be skipped"
    fi
    # the SPZ test reads map.spz back with PlayCanvas' splat-transform (an independent reader); skipped without it
    if command -v npm >/dev/null 2>&1 && [ ! -x .npm/node_modules/.bin/splat-transform ]; then
      npm install -q --prefix .npm @playcanvas/splat-transform@3.7.0 >/dev/null 2>&1 ||
        echo "splat-transform could not be installed: the SPZ read-back test will be skipped"
    fi ;;
esac
if [ -n "$extras" ]; then .venv/bin/python -m pip install -q -e ".[$extras]"; else .venv/bin/python -m pip install -q -e .; fi
echo "eligsir_o3d installed in $(pwd)/.venv"
