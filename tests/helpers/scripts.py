"""A repository script (a benchmark or a tool, run by path rather than imported from a package) loaded as a module,
so that tests can call its functions."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def load_script(relpath: str, name: str | None = None):
    """The module of ``ROOT / relpath`` (named ``name``, default the file's stem), freshly executed."""
    path = ROOT / relpath
    spec = importlib.util.spec_from_file_location(name or path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
