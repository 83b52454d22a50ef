"""The package's comments and docstrings state rules and units; the measurements behind them live in the lab
notebook (docs/lab/). None names a work session (``stop 41``), an issue (``issue 32``), a date, a commit hash or a
figure in dB, except the metric definitions, which define the dB scale itself."""

import ast
import io
import re
import tokenize
from pathlib import Path

PKG = Path(__file__).resolve().parents[2] / "eligsir_o3d"

# modules that define the metrics in dB (PSNR's cap, the regional deltas' thresholds, the paper's Table III
# criteria): dB figures are their rule
METRIC_DEFINITIONS = {"eval/metrics.py", "eval/spatial.py", "eval/ablation.py"}

PATTERNS = {
    "a work session": re.compile(r"\bstops? \d+", re.I),
    "an issue number": re.compile(r"\bissues? #?\d+", re.I),
    "a date": re.compile(r"\b20\d{2}-\d{2}-\d{2}\b"),
    "a commit hash": re.compile(r"(?<![\w./-])(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,40}(?![\w/-]|\.\w)"),
    "a dB figure": re.compile(r"\d\s?dB\b"),
}


def prose(source: str) -> list[tuple[int, str]]:
    """``(line, text)`` of every comment block (consecutive comment lines joined) and every docstring, module,
    class, function or attribute (a string literal standing as a statement)."""
    found, block, start, last = [], [], 0, -2
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type == tokenize.COMMENT:
            line = tok.start[0]
            if line != last + 1 and block:
                found.append((start, " ".join(block)))
                block = []
            if not block:
                start = line
            block.append(tok.string.lstrip("#").strip())
            last = line
    if block:
        found.append((start, " ".join(block)))
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            found.append((node.lineno, " ".join(node.value.value.split())))
    return found


def offences(source: str, metric_definitions: bool = False) -> list[str]:
    hits = []
    for line, text in prose(source):
        for what, pattern in PATTERNS.items():
            if what == "a dB figure" and metric_definitions:
                continue
            for m in pattern.finditer(text):
                hits.append(f"{line}: {what} ({m.group(0)!r})")
    return hits


def test_no_lab_notes_in_the_package():
    found = {}
    for path in sorted(PKG.rglob("*.py")):
        rel = str(path.relative_to(PKG))
        hits = offences(path.read_text(), rel in METRIC_DEFINITIONS)
        if hits:
            found[rel] = hits
    assert not found, ("state the rule and unit; move figures to docs/lab/ (cite them as 'lab: ID'): "
                       + "; ".join(f"{k} {v}" for k, v in found.items()))


def test_the_check_finds_each_kind_and_spares_code_and_metric_definitions():
    bad = '''"""Refitted 2026-12-04 (issue 32, stop 47) against db912e2."""
# 22.41 vs 21.51 dB on the kitchen,
# at Stop 43
x = 1
"""+0.4 dB."""
'''
    kinds = {h.split(" (")[0].split(": ", 1)[1] for h in offences(bad)}
    assert kinds == set(PATTERNS), kinds
    assert sorted(h.split(":")[0] for h in offences(bad) if "work session" in h) == ["1", "2"]  # a block's first line
    code = 'PSNR_CAP = 120  # the cap: PSNR of a perfect render, in dB\nname = "alexnet-owt-7be5be79.pth"\nn = 1000000\n'
    assert offences(code) == []
    assert offences('"""PSNR is capped at 120 dB."""', metric_definitions=True) == []
