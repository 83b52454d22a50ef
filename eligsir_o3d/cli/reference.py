"""The docs' generated reference pages: every ``eligsir`` command with its options (from the typer app), and
every config key with its type, default and rule (:mod:`.config_explain`).

``python -m eligsir_o3d.cli.reference docs`` rewrites ``docs/reference/cli.md`` and ``docs/reference/config.md``;
a test fails while the committed pages differ from what this prints.
"""

from __future__ import annotations

import sys
from pathlib import Path

PAGES = ("reference/cli.md", "reference/config.md")


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def cli_markdown() -> str:
    """One section per command: its help, usage, and a table of its arguments and options by help panel."""
    import typer

    from .app import app

    group = typer.main.get_command(app)
    lines = ["# CLI reference", "",
             "Every `eligsir` command and option, generated from the command line itself",
             "(`python -m eligsir_o3d.cli.reference docs`); `eligsir COMMAND --help` prints the same.", ""]
    for name in sorted(group.commands):
        cmd = group.commands[name]
        ctx = typer.Context(cmd, info_name=f"eligsir {name}")
        lines += [f"## eligsir {name}", "", _cell(cmd.help or ""), "", "```text",
                  " ".join(cmd.collect_usage_pieces(ctx)).join([f"eligsir {name} ", ""]), "```", "",
                  "| argument or option | panel | help |", "|---|---|---|"]
        for param in cmd.params:
            option = param.param_type_name == "option"
            record = param.get_help_record(ctx) if option else None
            if option and record is None:
                continue  # hidden
            spelled = record[0] if record else (param.metavar or param.name.upper())
            panel = getattr(param, "rich_help_panel", None) or ""
            text = record[1] if record else getattr(param, "help", "") or ""
            lines.append(f"| `{_cell(spelled)}` | {_cell(panel)} | {_cell(text)} |")
        lines.append("")
    return "\n".join(lines)


def pages() -> dict[str, str]:
    """``{path under docs/: text}`` of the generated pages."""
    from .config_explain import markdown

    return {PAGES[0]: cli_markdown(), PAGES[1]: markdown()}


def main(argv: list[str] | None = None) -> None:
    docs = Path((argv if argv is not None else sys.argv[1:] or ["docs"])[0])
    for rel, text in pages().items():
        (docs / rel).parent.mkdir(parents=True, exist_ok=True)
        (docs / rel).write_text(text)
        print(docs / rel)


if __name__ == "__main__":
    main()
