"""The README is a short front door and the docs site builds: ``mkdocs build --strict`` (a broken link or API
reference fails), and every fenced block marked ``<!-- runnable -->`` in README.md and docs/*.md runs as written
(``eligsir`` as ``python -m eligsir_o3d.cli``), in a scratch folder, on the small data it names."""

import importlib.util
import os
import re
import subprocess
import sys

import pytest

from helpers import ROOT

MARKED = re.compile(r"<!-- runnable -->\s*\n```(bash|python)[^\n]*\n(.*?)\n```", re.S)
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def runnable_blocks() -> list[tuple[str, str, str]]:
    """(page, language, code) of every block marked runnable."""
    return [(p.name, lang, code) for p in PAGES for lang, code in MARKED.findall(p.read_text())]


def test_readme_is_a_short_front_door():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 110
    results = text.split("## Results\n", 1)[1].split("\n## ", 1)[0].strip().splitlines()
    assert len(results) <= 8 and "docs/results.md" in "\n".join(results), results
    assert "bash tools/setup.sh && .venv/bin/eligsir demo" in text
    assert "bash tools/setup.sh --test && .venv/bin/python -m pytest -q" in text
    assert "../shared" not in text  # no path a user does not have
    links = re.findall(r"\]\(([^)#]+)\)", text)
    missing = [link for link in links if not link.startswith("http") and not (ROOT / link).exists()]
    assert not missing, missing


def test_the_runnable_markers_find_the_readme_examples():
    found = {(page, lang) for page, lang, _ in runnable_blocks()}
    assert {("README.md", "python"), ("README.md", "bash")} <= found


@pytest.mark.parametrize("page,lang,code", runnable_blocks(), ids=lambda v: v if isinstance(v, str) and len(v) < 20 else "")
def test_runnable_block_runs_as_written(page, lang, code, tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    if lang == "python":
        cmd = [sys.executable, "-c", code]
    else:
        eligsir = f"{sys.executable} -m eligsir_o3d.cli"
        script = "set -euo pipefail\n" + re.sub(r"^eligsir\b", eligsir, code, flags=re.M)
        cmd = ["bash", "-c", script]
    done = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=1200)
    assert done.returncode == 0, f"{page} {lang} block failed:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}"


@pytest.mark.skipif(importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("mkdocstrings") is None,
                    reason="the docs extra is not installed (pip install -e .[docs])")
def test_docs_site_builds_strict(tmp_path):
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-q", "-d", str(tmp_path / "site")],
                          cwd=ROOT, capture_output=True, text=True, timeout=900,
                          env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert (tmp_path / "site" / "api" / "index.html").is_file()
