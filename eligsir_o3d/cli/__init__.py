"""The ``eligsir`` command line: one typer app (:mod:`.app`) whose commands import heavy modules inside them; the
longer command bodies live in :mod:`.commands`. The command owns its process, so the process-level set-up
(:func:`eligsir_o3d.runtime.prepare`) runs before anything else is imported."""

from ..runtime import prepare

prepare()

from .app import app, main  # noqa: E402

__all__ = ["app", "main"]
