"""The package's shape: no import circle between its modules (counting imports inside functions too, which
only hide a circle), no module over 350 lines, no function over 80 lines outside the compiled kernels, and no
``_private`` name imported from another package. The scripts beside it (tools/*.py, benchmarks/**/*.py) keep the
same line limits, edit no ``sys.path``, and every benchmark is a module named in benchmarks/README.md."""

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[2] / "eligsir_o3d"
MAX_LINES = 350  # "no module over 350 lines"
KNOWN_LONG: set[str] = set()  # modules allowed over the limit (none today)
MAX_FUNCTION_LINES = 80
# numba kernels (and the factories that close over them) are long straight-line loops, kept whole on purpose
KERNEL_MODULES = {"render/_cpu_forward.py", "render/_cpu_backward.py", "render/_cpu_projection.py",
                  "render/_cpu_kernels.py", "render/_cpu_binning.py", "optim/update_kernels.py",
                  "optim/dssim_kernels.py", "kernels/cpu_kernels.py"}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path, modules: set[str]) -> set[str]:
    """The package modules that ``path`` imports explicitly (anywhere in the file)."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            # "from .x import y": y is a submodule of x (x's __init__ adds nothing) or a name defined in x
            subs = [f"{mod}.{a.name}" for a in node.names]
            targets = subs + ([mod] if any(t not in modules for t in subs) else [])
        else:
            continue
        found.update(t for t in targets if t in modules and t != name)
    return found


def _graph():
    files = {_module_name(p): p for p in PKG.rglob("*.py")}
    return {m: _imports(p, set(files)) for m, p in files.items()}


def _cycle(graph):
    state, stack = {}, []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                return stack[stack.index(n):] + [n]
            if n not in state:
                found = visit(n)
                if found:
                    return found
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state:
            found = visit(m)
            if found:
                return found
    return None


def test_no_import_circle():
    cycle = _cycle(_graph())
    assert cycle is None, "import circle: " + " -> ".join(cycle)


def test_the_cycle_finder_finds_a_circle():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


def test_no_module_is_over_350_lines():
    long = {str(p.relative_to(PKG)): n for p in PKG.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > MAX_LINES and str(p.relative_to(PKG)) not in KNOWN_LONG}
    assert not long, long


def _long_functions(tree: ast.AST, limit: int) -> list[tuple[str, int]]:
    return [(n.name, n.end_lineno - n.lineno + 1) for n in ast.walk(tree)
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.end_lineno - n.lineno + 1 > limit]


def test_no_function_is_over_80_lines_outside_the_kernels():
    long = {f"{p.relative_to(PKG)}:{name}": n for p in PKG.rglob("*.py") if str(p.relative_to(PKG)) not in KERNEL_MODULES
            for name, n in _long_functions(ast.parse(p.read_text()), MAX_FUNCTION_LINES)}
    assert not long, long


def _private_imports(path: Path) -> list[str]:
    """``_name``s (modules or attributes) that ``path`` imports from a package it is not part of."""
    name = _module_name(path)
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.ImportFrom):
            continue
        if node.level:
            base = package.split(".")
            mod = ".".join(base[: len(base) - (node.level - 1)] + ([node.module] if node.module else []))
        else:
            mod = node.module or ""
        if mod.split(".")[0] != PKG.name:
            continue
        for alias in node.names:
            parts = f"{mod}.{alias.name}".split(".")
            private = [i for i, s in enumerate(parts) if s.startswith("_") and not s.startswith("__")
                       and s != "_version"]  # the version module: a packaging convention, read by the CLI
            if not private:
                continue
            owner = parts[: private[0]]  # the package (or module) that holds the private name
            if not (PKG.parent.joinpath(*owner)).is_dir():
                owner = owner[:-1]
            if package != ".".join(owner):  # a subpackage is another package too
                found.append(f"{path.relative_to(PKG)}:{node.lineno} imports {'.'.join(parts)}")
    return found


def test_no_private_name_is_imported_across_packages():
    found = [hit for p in sorted(PKG.rglob("*.py")) for hit in _private_imports(p)]
    assert not found, found


def test_the_private_import_check_fails_on_a_cross_package_import(tmp_path, monkeypatch):
    """The check itself: a module of one package importing another package's _name is caught; its own isn't."""
    bad = PKG / "visual" / "video.py"
    text = "from ..render._cpu_kernels import TILE\nfrom ..export import _private_helper\nfrom .pictures import _u8\n"
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: text if self == bad else Path.read_bytes(self).decode())
    hits = _private_imports(bad)
    assert len(hits) == 2 and "render._cpu_kernels" in hits[0] and "export._private_helper" in hits[1], hits


# ---- the scripts beside the package: tools/*.py and benchmarks/**/*.py -------------------------------------------
REPO = PKG.parent
SCRIPTS = sorted([*(REPO / "tools").glob("*.py"), *(REPO / "benchmarks").rglob("*.py")])
# functions over the limit, by "path:name" (none: every script function fits)
KNOWN_LONG_SCRIPT_FUNCTIONS: set = set()


def test_the_script_checks_see_the_scripts():
    names = {str(p.relative_to(REPO)) for p in SCRIPTS}
    assert {"benchmarks/budget/soak.py", "benchmarks/speed/render.py"} <= names, names


def test_no_script_is_over_350_lines():
    long = {str(p.relative_to(REPO)): n for p in SCRIPTS if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, long


def test_no_script_function_is_over_80_lines():
    long = {key: n for p in SCRIPTS for name, n in _long_functions(ast.parse(p.read_text()), MAX_FUNCTION_LINES)
            if (key := f"{p.relative_to(REPO)}:{name}") not in KNOWN_LONG_SCRIPT_FUNCTIONS}
    assert not long, long


def _sys_path_edits(tree: ast.AST) -> list[int]:
    """Lines that change ``sys.path`` (a call on it, or an assignment to it or to an item of it)."""
    def is_sys_path(node) -> bool:
        return (isinstance(node, ast.Attribute) and node.attr == "path" and isinstance(node.value, ast.Name)
                and node.value.id == "sys")

    hits = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and is_sys_path(node.func.value):
            hits.append(node.lineno)
        elif isinstance(node, (ast.Assign, ast.AugAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(is_sys_path(t) or (isinstance(t, ast.Subscript) and is_sys_path(t.value)) for t in targets):
                hits.append(node.lineno)
    return hits


def test_no_script_edits_sys_path():
    """Benchmarks run as ``python -m benchmarks.<group>.<name>`` or by path, and tools by path, on the installed
    package: none puts a folder on ``sys.path``."""
    found = {str(p.relative_to(REPO)): lines for p in SCRIPTS if (lines := _sys_path_edits(ast.parse(p.read_text())))}
    assert not found, found
    bad = "import sys\nsys.path.insert(0, 'x')\nsys.path[0:0] = ['y']\nsys.path += ['z']\nprint(sys.path[0])\n"
    assert sorted(_sys_path_edits(ast.parse(bad))) == [2, 3, 4]


def test_every_benchmark_is_a_module_named_in_the_index():
    """Each folder under benchmarks/ is a package (``python -m`` finds it), and benchmarks/README.md names every
    script by its path there."""
    bench = REPO / "benchmarks"
    index = (bench / "README.md").read_text()
    folders = {p.parent for p in bench.rglob("*.py")}
    assert all((d / "__init__.py").is_file() for d in folders), sorted(map(str, folders))
    scripts = [p for p in [*bench.rglob("*.py"), *bench.rglob("*.sh")] if p.name != "__init__.py"]
    missing = [str(p.relative_to(bench)) for p in scripts if f"`{p.relative_to(bench)}`" not in index]
    assert scripts and not missing, missing


def test_the_package_top_level_is_its_face_and_its_subpackages():
    """``eligsir_o3d/`` holds ``__init__``, ``_version`` and the subpackages only: every concept, the Reconstructor
    and the config included, lives in a package of its own."""
    modules = sorted(p.name for p in PKG.glob("*.py"))
    assert modules == ["__init__.py", "_version.py"], modules
    folders = [p for p in PKG.iterdir() if p.is_dir() and p.name != "__pycache__"]
    assert {"config", "mapper"} <= {p.name for p in folders}
    assert all((p / "__init__.py").is_file() for p in folders), [p.name for p in folders]
