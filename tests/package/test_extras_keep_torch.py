"""Every optional extra installs beside the pinned torch without moving it (issue 29).

Dry runs (``pip install --dry-run --report -``, nothing is installed), made with this venv's pip:

* ``--ignore-installed`` with the pin as a requirement (``torch==2.13.0`` plus the package's dependencies and the
  ``all`` extra's, which holds every other extra): every extra is resolvable against the pin, and the report's torch
  is the pinned release;
* per extra, what a user does after tools/setup.sh (pinned torch installed first, then ``pip install ".[extra]"``, no pin on the
  command line), against a scratch environment that holds only the pinned torch's metadata (its dist-info copied from
  this venv, so nothing else this venv holds changes the answer): torch must not be in the report's install list.
  The first check alone misses the failure this guards against: with the pin named, pip backtracks torchvision to
  the release that fits, while the user's command upgrades torch to fit the newest torchvision (lpips -> torchvision).

The registry is reached over the network: the module skips, saying why, where it cannot be reached. Slow (the
resolves take minutes on the 2-core CI machine), so marked ``slow``: deselected by default, run by .ci/run.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import venv
from concurrent.futures import ThreadPoolExecutor
from importlib import metadata
from pathlib import Path
from urllib.parse import urlparse

import pytest

tomllib = pytest.importorskip("tomllib", reason="tomllib needs Python >= 3.11")

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
EXTRAS = sorted(PROJECT["optional-dependencies"])
NETWORK_ERRORS = re.compile(r"NewConnectionError|Max retries exceeded|Temporary failure in name resolution|"
                            r"Network is unreachable|Could not fetch URL|ConnectTimeout|ProxyError")


def _pinned_torch() -> str:
    """The torch release tools/setup.sh installs (its TORCH_VERSION default), e.g. '2.13.0'."""
    m = re.search(r"torch==\$\{TORCH_VERSION:-([0-9.]+)\}", (ROOT / "tools" / "setup.sh").read_text())
    assert m, "tools/setup.sh no longer names its default torch pin as ${TORCH_VERSION:-X}"
    return m.group(1)


def _requirements(extra: str) -> list[str]:
    """The package's dependencies plus the extra's, self-references (``eligsir-o3d[a,b]``) expanded."""
    out, todo, seen = list(PROJECT["dependencies"]), [extra], set()
    while todo:
        e = todo.pop()
        if e in seen:
            continue
        seen.add(e)
        for req in PROJECT["optional-dependencies"][e]:
            m = re.fullmatch(r"eligsir-o3d\[([^\]]+)\]", req.replace(" ", ""))
            if m:
                todo.extend(m.group(1).split(","))
            else:
                out.append(req)
    return out


def _registry_reachable() -> str | None:
    """None if the index pip uses answers a TCP connection, else why not."""
    url = os.environ.get("PIP_INDEX_URL") or "https://pypi.org/simple"
    cfg = subprocess.run([sys.executable, "-m", "pip", "config", "get", "global.index-url"],
                         capture_output=True, text=True)
    if cfg.returncode == 0 and cfg.stdout.strip() and "PIP_INDEX_URL" not in os.environ:
        url = cfg.stdout.strip()
    u = urlparse(url)
    if u.scheme == "file":
        return None
    try:
        socket.create_connection((u.hostname, u.port or (443 if u.scheme == "https" else 80)), timeout=10).close()
    except OSError as err:
        return f"package index {u.hostname} unreachable ({err})"
    return None


def _dry_run(args: list[str], target: tuple[str, ...] = ()) -> dict:
    """pip's --report of ``pip [TARGET] install --dry-run ARGS``; skips on a network failure, fails on any other."""
    cmd = [sys.executable, "-m", "pip", *target, "install", "--dry-run", "--quiet", "--report", "-", "--timeout",
           "60", "--retries", "2", *args]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    if p.returncode != 0:
        if NETWORK_ERRORS.search(p.stderr):
            pytest.skip(f"package index unreachable: {NETWORK_ERRORS.search(p.stderr).group(0)}")
        raise AssertionError(f"pip could not resolve {' '.join(args)}:\n{p.stderr[-3000:]}")
    return json.loads(p.stdout)


def _to_install(report: dict) -> dict[str, str]:
    return {i["metadata"]["name"].lower(): i["metadata"]["version"] for i in report["install"]}


def _scratch_env_with_torch(folder: Path) -> Path:
    """A venv without pip whose site-packages holds only this venv's torch metadata; returns its python."""
    venv.create(folder, with_pip=False)
    py = folder / "bin" / "python"
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    dist = metadata.distribution("torch")
    src = Path(dist.locate_file(f"torch-{dist.version}.dist-info"))
    shutil.copytree(src, Path(site) / src.name, ignore=shutil.ignore_patterns("RECORD"))
    return py


@pytest.fixture(scope="module")
def reports(tmp_path_factory) -> dict[str, dict]:
    """Per extra, and for 'all' with the pin: pip's dry-run report (see the module docstring)."""
    why = _registry_reachable()
    if why:
        pytest.skip(why)
    if not metadata.version("torch").startswith(_pinned_torch()):
        pytest.skip(f"this venv's torch is {metadata.version('torch')}, not the pinned {_pinned_torch()}")
    py = _scratch_env_with_torch(tmp_path_factory.mktemp("scratch_env"))
    jobs = {extra: (_requirements(extra), ("--python", str(py))) for extra in EXTRAS}
    # 'all' holds every extra: one solution with the pin is a solution for each extra's subset of it
    jobs["pinned"] = (["--ignore-installed", f"torch=={_pinned_torch()}", *_requirements("all")], ())
    with ThreadPoolExecutor(max_workers=4) as pool:
        futures = {k: pool.submit(_dry_run, args, target) for k, (args, target) in jobs.items()}
        return {k: f.result() for k, f in futures.items()}


def test_every_extra_resolves_against_the_pinned_torch(reports):
    got = _to_install(reports["pinned"]).get("torch")
    assert got is not None and got.split("+")[0] == _pinned_torch(), (
        f"[all] with torch=={_pinned_torch()} pinned (--ignore-installed) resolves torch {got}")


@pytest.mark.parametrize("extra", EXTRAS)
def test_installing_the_extra_after_the_pinned_torch_keeps_it(reports, extra):
    moved = _to_install(reports[extra]).get("torch")
    assert moved is None, (f'pip install ".[{extra}]" after torch {_pinned_torch()} would install torch {moved}; '
                           "constrain the package that pulls it (see the eval extra's torchvision)")
