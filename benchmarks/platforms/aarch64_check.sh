#!/usr/bin/env bash
# Linux aarch64, checked under emulation (issue 29): an arm64 Debian root (debootstrap's packages unpacked natively;
# qemu-user-static through binfmt_misc runs its binaries), PyPI's aarch64 wheels of our dependencies unpacked
# natively into it, then on the emulated CPU
#   1. the ISA the cpu renderer's kernels are compiled for (benchmarks/speed/render.py's `numba_target` line),
#   2. the renderer agreement tests (cpu backend vs the torch reference, images and gradients),
#   3. a 12-frame map of the synthetic room (`eligsir demo --frames 12`), whose held-out PSNR is compared with the
#      same command run natively on this x86-64 machine,
#   4. benchmarks/platforms/bits_fingerprint.py on both: which stage (numpy, torch, the cpu kernels) first gives other bits.
# Only Python *running* is emulated: the root's files and the wheels are unpacked by native tools (installing under
# qemu took over 50 min on 2 busy cores and checks nothing of ours). No speed is measured or claimed: qemu translates
# every instruction. Needs root (chroot, mounts), the Debian archive and PyPI on the first run.
#   bash benchmarks/platforms/aarch64_check.sh [WORKDIR]     (default /tmp/eligsir_arm64)
# Resumable: every finished step leaves a stamp in WORKDIR (or the root) and is skipped on the next run; FORCE=1
# redoes the emulated steps 2-3. Env: ROOTFS (the arm64 root; default WORKDIR/rootfs), X86_PYTHON (the native
# interpreter for the x86-64 run; default .venv/bin/python), HOST_PYTHON (the native pip; default python3),
# TORCH_ARM (default 2.9.1: PyPI's aarch64 torch 2.9.1 is a CPU build), FRAMES (12).
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/../.." && pwd)"
WORK="${1:-/tmp/eligsir_arm64}"; mkdir -p "$WORK"; WORK="$(cd "$WORK" && pwd)"
FS="${ROOTFS:-$WORK/rootfs}"; FRAMES=${FRAMES:-12}; TORCH_ARM=${TORCH_ARM:-2.9.1}; FORCE=${FORCE:-0}
X86_PYTHON=${X86_PYTHON:-$ROOT/.venv/bin/python}; HOST_PYTHON=${HOST_PYTHON:-python3}
SITE=/opt/site  # the aarch64 site-packages inside the root
say() { echo "aarch64_check: $(date -u +%H:%M:%S) $*"; }
t0=$(date +%s)

# -- the emulator, registered with binfmt_misc so that the chroot's arm64 binaries run directly
for p in qemu-user-static debootstrap binfmt-support; do
  dpkg -s "$p" >/dev/null 2>&1 || { apt-get update -q && apt-get install -y -q "$p"; }
done
[ -e /proc/sys/fs/binfmt_misc/register ] || mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc
[ -e /proc/sys/fs/binfmt_misc/qemu-aarch64 ] || update-binfmts --enable qemu-aarch64
grep -q enabled /proc/sys/fs/binfmt_misc/qemu-aarch64 || { say "binfmt_misc: qemu-aarch64 not enabled"; exit 1; }
say "emulator: $(qemu-aarch64-static --version | head -1)"

# -- the arm64 Debian root (bookworm: Python 3.11, glibc 2.36 >= open3d's manylinux_2_35)
if [ ! -e "$FS/.eligsir_root_ready" ]; then
  rm -rf "$FS"
  debootstrap --arch=arm64 --foreign --variant=minbase \
    --include=python3,libgomp1,libusb-1.0-0,libegl1,libgl1,libx11-6,ca-certificates \
    bookworm "$FS" http://deb.debian.org/debian
  # debootstrap's --second-stage runs every maintainer script under emulation (it had not finished after 45 min on
  # 2 busy cores); the check needs only the packages' files, so unpack the downloaded packages natively instead.
  for d in "$FS"/var/cache/apt/archives/*.deb; do dpkg-deb -x "$d" "$FS"; done
  touch "$FS/.eligsir_root_ready"
else
  say "arm64 root: reusing $FS"
fi
# -- Debian packages a wheel needs beyond the root's (libgfortran5: open3d's pybind module links it), unpacked natively
# from bookworm's arm64 archive (their dependencies, gcc-12-base and libgcc-s1, are in the root already)
for p in ${EXTRA_DEBS:-libgfortran5}; do
  [ -e "$FS/.eligsir_deb_$p" ] && continue
  "$HOST_PYTHON" - "$p" "$WORK/$p.deb" <<'EOF'
import lzma, sys, urllib.request
mirror = "http://deb.debian.org/debian"
index = urllib.request.urlopen(f"{mirror}/dists/bookworm/main/binary-arm64/Packages.xz", timeout=120).read()
for stanza in lzma.decompress(index).decode().split("\n\n"):
    f = dict(line.split(": ", 1) for line in stanza.splitlines() if ": " in line and not line[0].isspace())
    if f.get("Package") == sys.argv[1]:
        urllib.request.urlretrieve(f"{mirror}/{f['Filename']}", sys.argv[2])
        print(f"aarch64_check: {sys.argv[1]} {f['Version']} from {mirror}/{f['Filename']}")
        break
else:
    sys.exit(f"aarch64_check: {sys.argv[1]} is not in bookworm's arm64 index")
EOF
  dpkg-deb -x "$WORK/$p.deb" "$FS" && rm "$WORK/$p.deb" && touch "$FS/.eligsir_deb_$p"
done
cleanup() { for m in dev/shm dev proc; do mountpoint -q "$FS/$m" && umount -l "$FS/$m"; done; return 0; }
trap cleanup EXIT
for m in proc dev dev/shm; do mkdir -p "$FS/$m"; mountpoint -q "$FS/$m" || mount --bind "/$m" "$FS/$m"; done
say "emulated: $(chroot "$FS" uname -m), $(chroot "$FS" python3 --version)"

# -- aarch64 wheels, resolved and downloaded natively (open3d, not open3d-cpu: pyproject's marker; open3d-cpu is
# published for Linux x86-64 only)
reqs=$("$HOST_PYTHON" - "$ROOT/pyproject.toml" "$TORCH_ARM" <<'EOF'
import sys, tomllib
deps = tomllib.load(open(sys.argv[1], "rb"))["project"]["dependencies"]
out = []
for d in deps:
    name, _, marker = d.partition(";")
    if marker and "!= 'x86_64'" not in marker:
        continue  # the Linux x86-64 branch of a platform marker
    out.append(f"torch=={sys.argv[2]}" if name.strip().startswith("torch") else name.strip())
print(" ".join(out + ["pytest>=8", "scipy>=1.10"]))
EOF
)
plat=""; for t in manylinux2014_aarch64 manylinux_2_17_aarch64 manylinux_2_27_aarch64 manylinux_2_28_aarch64 \
  manylinux_2_31_aarch64 manylinux_2_34_aarch64 manylinux_2_35_aarch64 manylinux_2_36_aarch64; do plat="$plat --platform $t"; done
tags="$plat --python-version 3.11 --implementation cp --abi cp311 --only-binary=:all:"
# pip evaluates dependency markers for the host, not for --platform: with platform.machine() answering aarch64, torch's
# `platform_machine == "x86_64"` CUDA dependencies (3 GB) are left out, as they are on a real aarch64 machine.
pip_aarch64() { "$HOST_PYTHON" -c 'import platform, runpy, sys; platform.machine = lambda: "aarch64"; sys.argv[0] = "pip"
runpy.run_module("pip", run_name="__main__")' "$@"; }
mkdir -p "$FS/wheels"
if [ ! -e "$FS/wheels/.eligsir_reqs" ] || [ "$(cat "$FS/wheels/.eligsir_reqs")" != "$reqs" ]; then
  say "requirements: $reqs"
  # shellcheck disable=SC2086
  pip_aarch64 download -q -d "$FS/wheels" $tags $reqs
  echo "$reqs" > "$FS/wheels/.eligsir_reqs"
else
  say "wheels: reusing $FS/wheels ($(ls "$FS/wheels" | grep -c '\.whl$') wheels)"
fi
# -- unpacked natively into $SITE: the newest wheel of each name in the folder the resolver filled (--no-deps: that
# resolution already happened, with aarch64 markers)
if [ ! -e "$FS$SITE/.eligsir_site_ready" ] || [ "$(cat "$FS$SITE/.eligsir_site_ready")" != "$reqs" ]; then
  wheels=$("$HOST_PYTHON" - "$FS/wheels" <<'EOF'
import pathlib, sys
from pip._vendor.packaging.utils import parse_wheel_filename
best = {}
for w in pathlib.Path(sys.argv[1]).glob("*.whl"):
    name, version, _, _ = parse_wheel_filename(w.name)
    if name not in best or version > best[name][0]:
        best[name] = (version, w)
print(" ".join(str(w) for _, w in sorted(best.values(), key=lambda vw: vw[1].name)))
EOF
)
  rm -rf "$FS$SITE"
  # shellcheck disable=SC2086
  "$HOST_PYTHON" -m pip install -q --no-deps --no-index $tags --target "$FS$SITE" $wheels
  echo "$reqs" > "$FS$SITE/.eligsir_site_ready"
else
  say "site-packages: reusing $FS$SITE"
fi
# our source, timestamps kept (numba's cache keys on them, so a rerun reuses the emulated compiles)
rm -rf "$FS/src" && mkdir -p "$FS/src" && (cd "$ROOT" && git ls-files -co --exclude-standard -z | grep -z -v '^docs/images' |
  xargs -0 cp -p --parents -t "$FS/src")
t1=$(date +%s); say "set-up took $((t1 - t0)) s"

arm() { chroot "$FS" /usr/bin/env -i PATH=/usr/bin:/bin HOME=/root PYTHONPATH=/src:$SITE \
  NUMBA_CACHE_DIR=/var/cache/numba OMP_NUM_THREADS=2 bash -c "cd /src && $*"; }
arm "python3 -c 'import numpy, numba, torch, open3d' 2>&1" | tail -3
arm "python3 - <<'EOF'
import importlib.metadata as md
print('aarch64_check: wheels', ', '.join(f'{n} {md.version(n)}' for n in ('torch', 'numba', 'llvmlite', 'open3d', 'numpy')))
EOF"

# 1. the ISA report (what LLVM reports for the emulated host, and our summary of it)
arm "python3 -c 'import platform, llvmlite.binding as ll
from numba.core.codegen import get_host_cpu_features
from eligsir_o3d.render._cpu_kernels import target_summary
print(\"aarch64_check: machine\", platform.machine(), \"| llvm host cpu\", ll.get_host_cpu_name(),
      \"| llvm host features\", repr(get_host_cpu_features()), \"| numba_target\", target_summary())'"

# 2. the renderer agreement tests
if [ "$FORCE" = 1 ] || ! grep -q -E "^=* *[0-9]+ passed" "$WORK/agreement.log" 2>/dev/null; then
  say "agreement tests: running (emulated)"
  arm "python3 -m pytest -q -p no:cacheprovider tests/render/test_render_agreement.py" 2>&1 | tail -15 > "$WORK/agreement.run" || true
  mv "$WORK/agreement.run" "$WORK/agreement.log"
fi
cat "$WORK/agreement.log"
grep -q -E "[0-9]+ passed" "$WORK/agreement.log" && ! grep -q -E "[0-9]+ (failed|error)" "$WORK/agreement.log" ||
  { say "agreement tests did not pass"; exit 1; }
t2=$(date +%s); say "agreement tests: passed ($((t2 - t1)) s this run, emulated)"

# 3. the 12-frame map, emulated and native
if [ "$FORCE" = 1 ] || [ ! -e "$FS/out/demo/metrics.json" ]; then
  say "12-frame map: running (emulated)"
  arm "rm -rf /out/demo && mkdir -p /out && python3 -m eligsir_o3d.cli demo --frames $FRAMES --out /out/demo" 2>&1 | tail -6
fi
if [ ! -e "$WORK/x86_demo/metrics.json" ]; then
  rm -rf "$WORK/x86_demo"
  (cd "$WORK" && PYTHONPATH="$ROOT" "$X86_PYTHON" -m eligsir_o3d.cli demo --frames "$FRAMES" --out "$WORK/x86_demo" 2>&1 | tail -3)
fi
"$HOST_PYTHON" - "$FS/out/demo" "$WORK/x86_demo" <<'EOF'
import hashlib, json, pathlib, sys
arm, x86 = (pathlib.Path(p) for p in sys.argv[1:])
ma, mx = (json.loads((p / "metrics.json").read_text()) for p in (arm, x86))
ha, hx = ma["heldout"], mx["heldout"]
for k in ("psnr", "ssim", "depth_rmse_m"):
    a, x = ha.get(k), hx.get(k)
    d = f"{a - x:+.3e}" if isinstance(a, float) and isinstance(x, float) else "n/a"
    print(f"aarch64_check: held-out {k}: aarch64 {a!r}  x86-64 {x!r}  difference {d}")
for k in ("gaussians", "updates", "supervised_mpix"):
    if k in ma or k in mx:
        print(f"aarch64_check: {k}: aarch64 {ma.get(k)!r}  x86-64 {mx.get(k)!r}")
digest = lambda p: hashlib.sha256(p.read_bytes()).hexdigest()[:16] if p.is_file() else None
da, dx = digest(arm / "map.ply"), digest(x86 / "map.ply")
print(f"aarch64_check: map.ply sha256 aarch64 {da}  x86-64 {dx}:", "bit-identical" if da == dx else "differs")
EOF
# 4. where the bits part, if they do: a digest of each stage an update goes through, on fixed inputs, both machines
if [ "$FORCE" = 1 ] || [ ! -s "$WORK/fingerprint_aarch64.json" ]; then
  arm "python3 benchmarks/platforms/bits_fingerprint.py" > "$WORK/fingerprint_aarch64.json"
fi
(cd "$ROOT" && PYTHONPATH="$ROOT" "$X86_PYTHON" benchmarks/platforms/bits_fingerprint.py > "$WORK/fingerprint_x86_64.json")
"$HOST_PYTHON" "$ROOT/benchmarks/platforms/bits_fingerprint.py" --compare "$WORK/fingerprint_aarch64.json" \
  "$WORK/fingerprint_x86_64.json" | sed 's/^/aarch64_check: /'
t3=$(date +%s); say "done in $((t3 - t0)) s this run (no speed claimed: emulated)"
