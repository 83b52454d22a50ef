#!/usr/bin/env bash
# Linux aarch64, checked under emulation (issue 29): an arm64 Debian root (debootstrap + qemu-user-static through
# binfmt_misc), PyPI's aarch64 wheels of our dependencies, then on the emulated CPU
#   1. the ISA the cpu renderer's kernels are compiled for (benchmarks/speed/render.py's `numba_target` line),
#   2. the renderer agreement tests (cpu backend vs the torch reference, images and gradients),
#   3. a 12-frame map of the synthetic room (`eligsir demo --frames 12`), whose held-out PSNR is compared with the
#      same command run natively on this x86-64 machine.
# No speed is measured or claimed: qemu translates every instruction. Needs root (debootstrap, chroot, mounts), the
# Debian archive and PyPI. Slow: the first run builds the root (~10 min on 2 busy cores), numba's compile and the
# tests run 10-50x slower than natively.
#   bash benchmarks/platforms/aarch64_check.sh [WORKDIR]     (default /tmp/eligsir_arm64; the root is kept and reused)
# Env: X86_PYTHON (the native interpreter for the x86-64 run; default .venv/bin/python), TORCH_ARM (default 2.9.1:
# PyPI's aarch64 torch 2.9.1 is a CPU build), FRAMES (12).
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/../.." && pwd)"
WORK="${1:-/tmp/eligsir_arm64}"; mkdir -p "$WORK"; WORK="$(cd "$WORK" && pwd)"
FS="$WORK/rootfs"; FRAMES=${FRAMES:-12}; TORCH_ARM=${TORCH_ARM:-2.9.1}
X86_PYTHON=${X86_PYTHON:-$ROOT/.venv/bin/python}
say() { echo "aarch64_check: $*"; }
t0=$(date +%s)

# -- the emulator, registered with binfmt_misc so that the chroot's arm64 binaries run directly
for p in qemu-user-static debootstrap binfmt-support; do
  dpkg -s "$p" >/dev/null 2>&1 || { apt-get update -q && apt-get install -y -q "$p"; }
done
[ -e /proc/sys/fs/binfmt_misc/register ] || mount -t binfmt_misc binfmt_misc /proc/sys/fs/binfmt_misc
[ -e /proc/sys/fs/binfmt_misc/qemu-aarch64 ] || update-binfmts --enable qemu-aarch64
grep -q enabled /proc/sys/fs/binfmt_misc/qemu-aarch64 || { say "binfmt_misc: qemu-aarch64 not enabled"; exit 1; }

# -- the arm64 Debian root (bookworm: Python 3.11, glibc 2.36 >= open3d's manylinux_2_35)
if [ ! -e "$FS/.eligsir_root_ready" ]; then
  rm -rf "$FS"
  debootstrap --arch=arm64 --foreign --variant=minbase \
    --include=python3,python3-venv,python3-pip,libgomp1,libusb-1.0-0,libegl1,libgl1,libx11-6,ca-certificates \
    bookworm "$FS" http://deb.debian.org/debian
  # debootstrap's --second-stage runs every maintainer script under emulation (it had not finished after 45 min on
  # 2 busy cores); the check needs only the packages' files, so unpack the downloaded packages natively instead.
  for d in "$FS"/var/cache/apt/archives/*.deb; do dpkg-deb -x "$d" "$FS"; done
  touch "$FS/.eligsir_root_ready"
fi
cleanup() { for m in dev/shm dev proc; do mountpoint -q "$FS/$m" && umount -l "$FS/$m"; done; return 0; }
trap cleanup EXIT
for m in proc dev dev/shm; do mkdir -p "$FS/$m"; mountpoint -q "$FS/$m" || mount --bind "/$m" "$FS/$m"; done
cp /etc/resolv.conf "$FS/etc/resolv.conf"
say "emulated: $(chroot "$FS" uname -m), $(chroot "$FS" python3 --version)"

# -- aarch64 wheels, resolved and downloaded natively (fast), installed in the emulated venv from that folder.
# open3d, not open3d-cpu (pyproject's marker: open3d-cpu is published for Linux x86-64 only).
reqs=$(python3 - "$ROOT/pyproject.toml" "$TORCH_ARM" <<'EOF'
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
say "requirements: $reqs"
plat=""; for t in manylinux2014_aarch64 manylinux_2_17_aarch64 manylinux_2_27_aarch64 manylinux_2_28_aarch64 \
  manylinux_2_31_aarch64 manylinux_2_34_aarch64 manylinux_2_35_aarch64 manylinux_2_36_aarch64; do plat="$plat --platform $t"; done
mkdir -p "$FS/wheels"
# shellcheck disable=SC2086
# pip evaluates dependency markers for the host, not for --platform: with platform.machine() answering aarch64, torch's
# `platform_machine == "x86_64"` CUDA dependencies (3 GB) are left out, as they are on a real aarch64 machine.
python3 -c 'import platform, runpy, sys; platform.machine = lambda: "aarch64"; sys.argv[0] = "pip"
runpy.run_module("pip", run_name="__main__")' download -q -d "$FS/wheels" $plat --python-version 3.11 \
  --implementation cp --only-binary=:all: $reqs
if [ ! -x "$FS/opt/venv/bin/python" ]; then chroot "$FS" python3 -m venv /opt/venv; fi
# shellcheck disable=SC2086
chroot "$FS" /opt/venv/bin/python -m pip install -q --no-index --find-links /wheels $reqs
chroot "$FS" /opt/venv/bin/python -m pip list 2>/dev/null | grep -i -E "^(torch|numba|llvmlite|open3d|numpy) "
rm -rf "$FS/src" && mkdir -p "$FS/src" && (cd "$ROOT" && git ls-files -co --exclude-standard -z | grep -z -v '^docs/images' |
  xargs -0 cp --parents -t "$FS/src")
t1=$(date +%s); say "set-up took $((t1 - t0)) s"

arm() { chroot "$FS" /usr/bin/env -i PATH=/opt/venv/bin:/usr/bin:/bin HOME=/root PYTHONPATH=/src \
  NUMBA_CACHE_DIR=/tmp/numba_cache OMP_NUM_THREADS=2 bash -c "cd /src && $*"; }

# 1. the ISA report
arm "python -c 'import platform, torch, numba, open3d
from eligsir_o3d.render._cpu_kernels import target_summary
print(\"aarch64_check: machine\", platform.machine(), \"| torch\", torch.__version__, \"| numba\", numba.__version__,
      \"| open3d\", open3d.__version__, \"| numba_target\", target_summary())'"

# 2. the renderer agreement tests
arm "python -m pytest -q -p no:cacheprovider tests/render/test_render_agreement.py" 2>&1 | tail -15 | tee "$WORK/agreement.log"
grep -q -E "^[0-9]+ passed" "$WORK/agreement.log" && ! grep -q -E "[0-9]+ failed|error" "$WORK/agreement.log" ||
  { say "agreement tests did not pass"; exit 1; }
t2=$(date +%s); say "agreement tests took $((t2 - t1)) s (emulated)"

# 3. the 12-frame map, emulated and native
arm "rm -rf /tmp/demo && python -m eligsir_o3d.cli demo --frames $FRAMES --out /tmp/demo" 2>&1 | tail -5
rm -rf "$WORK/x86_demo"
(cd "$WORK" && PYTHONPATH="$ROOT" "$X86_PYTHON" -m eligsir_o3d.cli demo --frames "$FRAMES" --out "$WORK/x86_demo" 2>&1 | tail -3)
python3 - "$FS/tmp/demo" "$WORK/x86_demo" <<'EOF'
import hashlib, json, pathlib, sys
arm, x86 = (pathlib.Path(p) for p in sys.argv[1:])
ma, mx = (json.loads((p / "metrics.json").read_text()) for p in (arm, x86))
ha, hx = ma["heldout"], mx["heldout"]
for k in ("psnr", "ssim", "depth_rmse_m"):
    a, x = ha.get(k), hx.get(k)
    d = f"{a - x:+.2e}" if isinstance(a, float) and isinstance(x, float) else "n/a"
    print(f"aarch64_check: held-out {k}: aarch64 {a}  x86-64 {x}  difference {d}")
same = [n for n in ("map.ply",) if (arm / n).is_file() and (x86 / n).is_file()
        and hashlib.sha256((arm / n).read_bytes()).digest() == hashlib.sha256((x86 / n).read_bytes()).digest()]
print("aarch64_check: map.ply", "bit-identical" if same else "differs", "between aarch64 and x86-64")
EOF
t3=$(date +%s); say "done in $((t3 - t0)) s (no speed claimed: emulated)"
