"""Helpers shared by the tests (imported as ``helpers.<module>``; tests/ is on sys.path through its conftest):
the repository's paths and the real recordings (:data:`DATA`, :data:`SEVEN`), a pure-torch gsplat stand-in, a
headless browser for the viewer, and the visual fixtures."""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]  # the repository
DATA = ROOT.parent / "shared" / "data"  # the real RGB-D recordings (tests that need them skip without them)
SEVEN = DATA / "7scenes_redkitchen_jpg1000"
