#!/usr/bin/env bash
# Build the sdist and the wheel as a package index would serve them, install the wheel into a fresh venv (the pinned
# torch first, as tools/setup.sh does), and run a short `eligsir demo` from it, outside the repository.
#   tools/check_wheel.sh [WORKDIR]     (default: a new temporary folder; kept, its path printed)
# Fails if the build prints a deprecation warning, if the sdist or the wheel lacks what the package needs, if the
# installed package resolves to anything but the venv's copy, or if the demo writes no held-out score.
# Env: PYTHON (default python3), TORCH_VERSION (default 2.13.0), TORCH_INDEX (as in tools/setup.sh), FRAMES (12).
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
if [ -n "${1:-}" ]; then mkdir -p "$1"; WORK="$(cd "$1" && pwd)"; else WORK="$(mktemp -d /tmp/eligsir_wheel.XXXXXX)"; fi
PY=${PYTHON:-python3}
FRAMES=${FRAMES:-12}
echo "check_wheel: working in $WORK"
rm -rf "$WORK/dist" "$WORK/buildenv" "$WORK/venv" "$WORK/run"
t0=$(date +%s)

# 1. sdist, then the wheel built from the sdist (python -m build's default), in pip's isolated build env.
"$PY" -m venv "$WORK/buildenv"
"$WORK/buildenv/bin/python" -m pip install -q --upgrade pip build
"$WORK/buildenv/bin/python" -m build --outdir "$WORK/dist" "$ROOT" >"$WORK/build.log" 2>&1 ||
  { tail -40 "$WORK/build.log"; echo "check_wheel: python -m build failed"; exit 1; }
if grep -n -i -E "deprecat|SetuptoolsWarning|SetuptoolsDeprecationWarning" "$WORK/build.log"; then
  echo "check_wheel: the build printed the warnings above"; exit 1
fi
sdist=$(ls "$WORK"/dist/eligsir_o3d-*.tar.gz); wheel=$(ls "$WORK"/dist/eligsir_o3d-*-py3-none-any.whl)
echo "check_wheel: built $(basename "$sdist") ($(du -k "$sdist" | cut -f1) KiB), $(basename "$wheel") ($(du -k "$wheel" | cut -f1) KiB)"
"$WORK/buildenv/bin/python" - "$ROOT" "$sdist" "$wheel" <<'EOF'
"""Every module of the package is in both archives; the wheel's metadata carries the SPDX licence."""
import pathlib, sys, tarfile, zipfile
root, sdist, wheel = pathlib.Path(sys.argv[1]), sys.argv[2], sys.argv[3]
want = {p.relative_to(root).as_posix() for p in (root / "eligsir_o3d").rglob("*")
        if p.is_file() and "__pycache__" not in p.parts and p.suffix not in (".pyc", ".so")}
in_wheel = set(zipfile.ZipFile(wheel).namelist())
with tarfile.open(sdist) as t:
    in_sdist = {n.split("/", 1)[1] for n in t.getnames() if "/" in n}
for name, have in (("wheel", in_wheel), ("sdist", in_sdist)):
    missing = sorted(want - have)
    assert not missing, f"{name} lacks {missing[:10]}"
assert "LICENSE" in in_sdist, "sdist lacks LICENSE"
meta = next(n for n in in_wheel if n.endswith(".dist-info/METADATA"))
text = zipfile.ZipFile(wheel).read(meta).decode()
assert "License-Expression: Apache-2.0" in text, "wheel METADATA has no License-Expression: Apache-2.0"
print(f"check_wheel: {len(want)} package files in the wheel and the sdist; License-Expression: Apache-2.0")
EOF
t1=$(date +%s)

# 2. A fresh venv: the pinned torch first, then the wheel (its dependencies from the index, as a user gets them).
"$PY" -m venv "$WORK/venv"
"$WORK/venv/bin/python" -m pip install -q --upgrade pip
if [ -n "${TORCH_INDEX:-}" ]; then
  "$WORK/venv/bin/python" -m pip install -q "torch==${TORCH_VERSION:-2.13.0}" --index-url "$TORCH_INDEX" \
    --extra-index-url https://pypi.org/simple
else
  "$WORK/venv/bin/python" -m pip install -q "torch==${TORCH_VERSION:-2.13.0}"
fi
torch_before=$("$WORK/venv/bin/python" -c "import importlib.metadata as m; print(m.version('torch'))")
"$WORK/venv/bin/python" -m pip install -q "$wheel"
torch_after=$("$WORK/venv/bin/python" -c "import importlib.metadata as m; print(m.version('torch'))")
[ "$torch_before" = "$torch_after" ] || { echo "check_wheel: the wheel moved torch $torch_before -> $torch_after"; exit 1; }
t2=$(date +%s)

# 3. The demo, from elsewhere, with nothing of the repository on the path.
mkdir -p "$WORK/run" && cd "$WORK/run"
unset PYTHONPATH
"$WORK/venv/bin/python" -c "
import eligsir_o3d, sys
assert eligsir_o3d.__file__.startswith('$WORK/venv/'), eligsir_o3d.__file__
assert not any(p.startswith('$ROOT') for p in sys.path if p), sys.path
print('check_wheel: eligsir_o3d', eligsir_o3d.__version__, 'from', eligsir_o3d.__file__, '| torch', '$torch_after')"
"$WORK/venv/bin/eligsir" demo --frames "$FRAMES" --out "$WORK/run/demo" 2>&1 | tail -12
ls "$WORK/run/demo"
"$WORK/venv/bin/python" - "$WORK/run/demo" <<'EOF'
import json, pathlib, sys
out = pathlib.Path(sys.argv[1])
files = sorted(out.glob("*.json"))
assert files, f"the demo wrote no JSON under {out}"
found = [(f.name, json.loads(f.read_text()).get("heldout", {}).get("psnr")) for f in files]
scored = [(n, p) for n, p in found if isinstance(p, (int, float))]
assert scored, f"no held-out PSNR in {found}"
print(f"check_wheel: demo from the wheel: held-out PSNR {scored[0][1]:.2f} dB ({scored[0][0]})")
EOF
t3=$(date +%s)
echo "check_wheel: passed in $((t3 - t0)) s (build $((t1 - t0)) s, install $((t2 - t1)) s, demo $((t3 - t2)) s)"
