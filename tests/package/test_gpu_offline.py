"""benchmarks/platforms/gpu_offline.sh: what a later device call sources leaves the caller's shell as it was and
points at the checkout's carried frames; the script names its modes when given none; 'setup' says what is missing
rather than installing half a package."""

import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "benchmarks" / "platforms" / "gpu_offline.sh"


def _bash(cmd: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", "-c", cmd], cwd=cwd, capture_output=True, text=True, timeout=60)


def test_sourced_env_keeps_the_callers_shell(tmp_path):
    r = _bash(f'source "{SCRIPT}" env; echo "$-"; echo "$DATA"; echo "$PYTHONPATH"; pwd', tmp_path)
    assert r.returncode == 0, r.stderr
    flags, data, pythonpath, cwd = r.stdout.split("\n")[:4]
    assert "u" not in flags and "e" not in flags  # no set -u / -e left behind
    assert data == str(ROOT / ".gpu_c" / "kitchen") and pythonpath == str(ROOT)
    assert cwd == str(tmp_path)


def test_modes(tmp_path):
    copy = tmp_path / "benchmarks" / "platforms" / SCRIPT.name  # a checkout with nothing carried
    copy.parent.mkdir(parents=True)
    copy.write_text(SCRIPT.read_text())
    r = _bash(f'bash "{copy}"', tmp_path)
    assert r.returncode == 2 and "prepare" in r.stdout and "setup" in r.stdout
    r = _bash(f'bash "{copy}" setup', tmp_path)
    assert r.returncode == 1 and "carry .gpu_b" in r.stdout
