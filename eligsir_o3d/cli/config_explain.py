"""What each config key means: its type, default and attribute docstring, for ``eligsir config --explain KEY``
and the docs' config reference.

Python keeps no attribute docstrings at run time (the string literal under a dataclass field is evaluated and
dropped), so they are read from the source of the class that declares the field, with :mod:`ast`.
"""

from __future__ import annotations

import ast
import dataclasses
import difflib
import inspect
from dataclasses import dataclass
from functools import lru_cache


@dataclass(frozen=True)
class KeyDoc:
    """One config key: its dotted path, annotated type, default (``None`` for a section) and docstring."""

    key: str
    type: str
    default: object
    doc: str
    section: bool


@lru_cache(maxsize=None)
def _class_docs(cls: type) -> dict[str, tuple[str, str]]:
    """``{field: (annotation, docstring)}`` of dataclass ``cls``, read from its source ("" where there is none)."""
    tree = ast.parse(inspect.getsource(inspect.getmodule(cls)))
    node = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == cls.__name__)
    docs: dict[str, tuple[str, str]] = {}
    body = node.body
    for i, stmt in enumerate(body):
        if isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name):
            after = body[i + 1] if i + 1 < len(body) else None
            doc = ""
            if (isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
                    and isinstance(after.value.value, str)):
                doc = inspect.cleandoc(after.value.value)
            docs[stmt.target.id] = (ast.unparse(stmt.annotation), doc)
    return docs


def _default(f: dataclasses.Field):
    return f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default


def key_docs(cls: type | None = None, prefix: str = "") -> list[KeyDoc]:
    """Every key of the config tree below ``cls`` (default: :class:`~eligsir_o3d.config.Config`), sections and
    values, in declaration order, each with its type, default and docstring."""
    if cls is None:
        from ..config import Config

        cls = Config
    docs = _class_docs(cls)
    out: list[KeyDoc] = []
    for f in dataclasses.fields(cls):
        annotation, doc = docs.get(f.name, (str(f.type), ""))
        default = _default(f)
        if dataclasses.is_dataclass(default):
            out.append(KeyDoc(prefix + f.name, annotation, None, doc, True))
            out.extend(key_docs(type(default), f"{prefix}{f.name}."))
        else:
            out.append(KeyDoc(prefix + f.name, annotation, default, doc, False))
    return out


def explain(key: str) -> str:
    """The text ``eligsir config --explain KEY`` prints: the key's type, default and docstring (a section lists
    its keys). An unknown key is a ValueError naming the closest keys."""
    docs = {d.key: d for d in key_docs()}
    d = docs.get(key.strip())
    if d is None:
        close = difflib.get_close_matches(key, list(docs), n=5, cutoff=0.5)
        close += [k for k in docs if k.endswith("." + key) and k not in close][:5]
        hint = f"; close matches: {', '.join(close)}" if close else "; `eligsir config` prints every key"
        raise ValueError(f"--explain {key!r}: no such config key{hint}")
    if d.section:
        keys = [k for k in docs if k.startswith(d.key + ".")]
        return f"{d.key} (section {d.type})\n  {d.doc or '(undocumented)'}\n  keys: {', '.join(keys)}"
    return f"{d.key}\n  type:    {d.type}\n  default: {d.default!r}\n  {d.doc or '(undocumented)'}"


def markdown() -> str:
    """The docs' config reference page: one table row per key."""
    lines = ["# Config reference", "",
             "Every key that `--set KEY=VALUE`, `--config FILE` and `config.json` take, with its type, default and",
             "rule. Generated from the attribute docstrings in the source (`python -m eligsir_o3d.cli.reference docs`);",
             "`eligsir config --explain KEY` prints one entry.", ""]
    docs = key_docs()
    sections = {"": "Values at the top level of the config."} | {d.key: d.doc for d in docs if d.section}
    for section, about in sections.items():
        rows = [d for d in docs if not d.section and d.key.rpartition(".")[0] == section]
        if not rows:
            continue
        lines += [f"## `{section}`" if section else "## Top level", "", about, "",
                  "| key | type | default | rule |", "|---|---|---|---|"]
        for d in rows:
            cell = d.doc.replace("``", "`").replace("|", "\\|").replace("\n", " ") or "(undocumented)"
            lines.append(f"| `{d.key}` | `{d.type}` | `{d.default!r}` | {cell} |")
        lines.append("")
    return "\n".join(lines)
