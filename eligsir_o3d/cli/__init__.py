"""The ``eligsir`` command line: one typer app (:mod:`.app`) whose commands import heavy modules inside them; the
longer command bodies live in :mod:`.commands`."""

from .app import app, main

__all__ = ["app", "main"]
