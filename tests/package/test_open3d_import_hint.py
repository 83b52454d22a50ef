"""A missing system library under Open3D gives one line naming the package, not a traceback (issue 29)."""

import ctypes
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from eligsir_o3d.runtime import open3d_check as _open3d_check
from eligsir_o3d.runtime.open3d_check import MissingSystemLibrary, hint, import_open3d

ROOT = Path(__file__).resolve().parents[2]
# The loader's own words, as `import open3d` prints them on a machine without libusb (Open3D 0.19/0.20 wheels).
LIBUSB_ERROR = "libusb-1.0.so.0: cannot open shared object file: No such file or directory"


class _FailingFinder:
    """A meta-path finder that makes ``import open3d`` raise ``error`` as the dynamic loader would."""

    def __init__(self, error):
        self.error = error

    def find_spec(self, name, path=None, target=None):
        if name == "open3d" or name.startswith("open3d."):
            raise self.error
        return None


@pytest.fixture
def broken_open3d(monkeypatch):
    def install(error):
        for mod in [m for m in sys.modules if m == "open3d" or m.startswith("open3d.")]:
            monkeypatch.delitem(sys.modules, mod)
        monkeypatch.setattr(sys, "meta_path", [_FailingFinder(error), *sys.meta_path])
    return install


@pytest.mark.parametrize("error", [ImportError(LIBUSB_ERROR),
                                   OSError("libGL.so.1: cannot open shared object file: No such file or directory"),
                                   ImportError("libEGL.so.1: cannot open shared object file: No such file or directory")])
def test_missing_library_names_the_debian_and_fedora_package(broken_open3d, monkeypatch, error):
    broken_open3d(error)
    monkeypatch.setattr(sys, "argv", ["python"])
    with pytest.raises(MissingSystemLibrary) as info:
        import_open3d()
    msg = str(info.value)
    lib = str(error).split(":")[0]
    deb, fedora = _open3d_check.SYSTEM_PACKAGES[lib]
    assert "\n" not in msg and lib in msg
    assert f"apt-get install {deb}" in msg and f"dnf install {fedora}" in msg
    assert info.value.__cause__ is None and info.value.__suppress_context__  # no chained loader traceback


def test_unknown_library_gets_a_lookup_hint_from_the_real_loader_message():
    with pytest.raises(OSError) as info:  # the real dynamic loader's message, for a library that does not exist
        ctypes.CDLL("libeligsir-absent.so.7")
    line = hint(info.value)
    assert line is not None and "libeligsir-absent.so.7" in line
    assert "apt-file search libeligsir-absent.so.7" in line and "dnf provides" in line


def test_other_import_errors_pass_through(broken_open3d, monkeypatch):
    broken_open3d(ModuleNotFoundError("No module named 'open3d'", name="open3d"))
    monkeypatch.setattr(sys, "argv", ["python"])
    with pytest.raises(ModuleNotFoundError):
        import_open3d()
    assert hint(ImportError("undefined symbol: _ZN6open3d4core6Tensor")) is None


def test_the_cli_prints_one_line_and_exits_1(tmp_path):
    """The console script, with open3d's import failing as without libusb: stderr is the one line, no traceback."""
    script = tmp_path / "eligsir"  # the name pip gives the console script, which is what the check keys on
    script.write_text(textwrap.dedent(f"""\
        import sys
        class Finder:
            def find_spec(self, name, path=None, target=None):
                if name == "open3d" or name.startswith("open3d."):
                    raise ImportError({LIBUSB_ERROR!r})
        sys.meta_path.insert(0, Finder())
        sys.path.insert(0, {str(ROOT)!r})
        from eligsir_o3d.cli import main
        sys.exit(main())
        """))
    p = subprocess.run([sys.executable, str(script), "demo", "--frames", "2"], capture_output=True, text=True,
                       timeout=300, cwd=tmp_path)
    assert p.returncode == 1, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1, p.stderr
    assert lines[0].startswith("eligsir: Open3D cannot load libusb-1.0.so.0")
    assert "apt-get install libusb-1.0-0" in lines[0] and "dnf install libusb1" in lines[0]
