"""No dangling reference: a module path (``eligsir_o3d.x.y``, ``eligsir_o3d/x/y.py``), a repository file
(``tests/...``, ``benchmarks/...``, ``tools/...``, ``docs/...``), a markdown link or its anchor, or a ``lab: ID``
measurement id, named in a docstring, a comment, a docs page or the README, must exist."""

import re
from pathlib import Path

from helpers import ROOT

PKG = ROOT / "eligsir_o3d"
MODULE = re.compile(r"\beligsir_o3d(?:\.[A-Za-z_]\w*)+")
FILE = re.compile(r"(?<![\w./-])((?:eligsir_o3d|tests|benchmarks|tools|docs|examples)/[\w/.-]*\w\.(?:py|md|sh|json|yml))")
LINK = re.compile(r"\]\(([^)\s]+)\)")
LAB_ID = re.compile(r"\blab: ([a-z0-9-]+)")
HEADING = re.compile(r"^#{1,6}\s+(.*)$", re.M)


def slug(title: str) -> str:
    """The anchor mkdocs' toc (and GitHub) gives a heading."""
    text = re.sub(r"[`*_]", "", title.strip().lower())
    text = re.sub(r"[^\w\s-]", "", text)
    return re.sub(r"\s+", "-", text).strip("-")


def anchors(page: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    return {slug(t) for t in HEADING.findall(text)}


def _aliases() -> set[str]:
    """Old module paths that still import through ``eligsir_o3d/_moved.py`` while it exists."""
    moved = PKG / "_moved.py"
    return set(re.findall(r'"([\w.]+)":\s*"', moved.read_text())) if moved.is_file() else set()


def module_exists(dotted: str) -> bool:
    """``eligsir_o3d.a.b[.name...]``: the longest prefix is a module or package, and a name after it is defined
    (or imported) there."""
    parts = dotted.split(".")
    if ".".join(parts[1:]) in _aliases():
        return True
    for n in range(len(parts), 0, -1):
        base = ROOT.joinpath(*parts[:n])
        path = base.with_suffix(".py") if base.with_suffix(".py").is_file() else base / "__init__.py"
        if path.is_file():
            if n == len(parts):
                return True
            name = parts[n]
            defined = (rf"\b(def|class)\s+{name}\b|^\s*{name}\s*[:=]|[\"']{name}[\"']\s*:"  # a lazy export's key too
                       rf"|\bimport\b.*\b{name}\b|\b{name}\b.*\bimport\b")
            return re.search(defined, path.read_text(), re.M) is not None
    return False


def _texts():
    for path in sorted(PKG.rglob("*.py")):
        yield path, path.read_text()
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        yield path, path.read_text()


def dangling_names(text: str) -> list[str]:
    bad = [m for m in MODULE.findall(text) if not module_exists(m.rstrip("."))]
    bad += [f for f in FILE.findall(text) if not (ROOT / f).exists()]
    return bad


def test_module_and_file_references_exist():
    """The lab notebook (docs/lab/) is history: it may name code that has since been removed."""
    found = {str(p.relative_to(ROOT)): hits for p, text in _texts()
             if "lab" not in p.relative_to(ROOT).parts[:2] and (hits := dangling_names(text))}
    assert not found, found


def test_markdown_links_and_anchors_exist():
    found = {}
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
        for target in LINK.findall(text):
            if target.startswith(("http:", "https:", "mailto:")):
                continue
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            if not dest.exists():
                found.setdefault(str(page.relative_to(ROOT)), []).append(target)
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                found.setdefault(str(page.relative_to(ROOT)), []).append(target)
    assert not found, found


def test_lab_ids_resolve_in_the_lab_notebook():
    ids = anchors(ROOT / "docs" / "lab" / "code-notes.md")
    found = {str(p.relative_to(ROOT)): missing for p, text in _texts()
             if (missing := [i for i in LAB_ID.findall(text) if i not in ids])}
    assert not found, found


def test_the_checks_catch_what_they_are_for(tmp_path):
    assert dangling_names("see eligsir_o3d.scheduling.nowhere and eligsir_o3d/culling.py") == [
        "eligsir_o3d.scheduling.nowhere", "eligsir_o3d/culling.py"]
    assert dangling_names("eligsir_o3d.scheduling.views.ViewConfig, eligsir_o3d/config/checks.py, tests/helpers") == []
    assert dangling_names("eligsir_o3d.config.NoSuchThing") == ["eligsir_o3d.config.NoSuchThing"]
    assert slug("The `cpu` renderer: on CUDA (gsplat)") == "the-cpu-renderer-on-cuda-gsplat"


LAB_NOTE = re.compile(r"\bstops? \d+|\bissues? #?\d+|\b20\d{2}-\d{2}-\d{2}\b|\d\s?dB\b", re.I)


def test_user_pages_state_rules_and_leave_figures_to_results_and_the_lab():
    """The user pages (everything outside docs/lab/ but the Results page) carry no dated entry, issue or session
    number and no dB figure."""
    pages = [p for p in (ROOT / "docs").rglob("*.md") if "lab" not in p.relative_to(ROOT / "docs").parts
             and p.name != "results.md"]
    found = {str(p.relative_to(ROOT)): LAB_NOTE.findall(p.read_text()) for p in pages}
    assert not {k: v for k, v in found.items() if v}
