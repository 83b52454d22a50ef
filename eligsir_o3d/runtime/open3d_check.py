"""Open3D's import, with the first error a new user meets turned into one actionable line.

Open3D's Linux wheels link against system libraries that minimal images (containers, CI runners, WSL) lack; the
import then fails with ``libusb-1.0.so.0: cannot open shared object file``, which names the library but not the
package that provides it. ``import_open3d`` names the Debian/Ubuntu and the Fedora package instead.
"""

from __future__ import annotations

import os
import re
import sys

# soname -> (Debian/Ubuntu package, Fedora package). Debian's names are those tools/setup.sh installs.
SYSTEM_PACKAGES = {
    "libusb-1.0.so.0": ("libusb-1.0-0", "libusb1"),
    "libGL.so.1": ("libgl1", "mesa-libGL"),
    "libEGL.so.1": ("libegl1", "mesa-libEGL"),
    "libOpenGL.so.0": ("libopengl0", "libglvnd-opengl"),
    "libGLX.so.0": ("libglx0", "libglvnd-glx"),
    "libX11.so.6": ("libx11-6", "libX11"),
    "libxcb.so.1": ("libxcb1", "libxcb"),
    "libudev.so.1": ("libudev1", "systemd-libs"),
    "libgomp.so.1": ("libgomp1", "libgomp"),
    "libidn2.so.0": ("libidn2-0", "libidn2"),
}
_MISSING_LIB = re.compile(r"([\w.+-]+\.so(?:\.[\w.]+)?): cannot open shared object file")


class MissingSystemLibrary(ImportError):
    """Open3D is installed but a system library it links against is not (the message says which package)."""


def hint(err: BaseException) -> str | None:
    """The one-line install hint for an Open3D import error, or None if it is not a missing shared library."""
    m = _MISSING_LIB.search(str(err))
    if not m:
        return None
    lib = m.group(1)
    if lib in SYSTEM_PACKAGES:
        deb, fedora = SYSTEM_PACKAGES[lib]
        return (f"Open3D cannot load {lib}: install it with `sudo apt-get install {deb}` (Debian/Ubuntu) or "
                f"`sudo dnf install {fedora}` (Fedora), or run tools/setup.sh, which installs all of them")
    return (f"Open3D cannot load {lib}: install the system package that provides it (Debian/Ubuntu: "
            f"`apt-file search {lib}`; Fedora: `dnf provides '*/{lib}'`)")


def _running_the_cli() -> bool:
    """True when this process is the ``eligsir`` console script (pyproject's [project.scripts])."""
    return bool(sys.argv) and os.path.basename(sys.argv[0]) in ("eligsir", "eligsir.exe", "eligsir-script.py")


def import_open3d():
    """``import open3d``; a missing system library becomes ``MissingSystemLibrary`` with one line naming the
    package to install (the ``eligsir`` command prints just that line and exits with status 1)."""
    try:
        import open3d
    except (ImportError, OSError) as err:  # a missing .so: ImportError from the extension, OSError from ctypes
        line = hint(err)
        if line is None:
            raise
        if _running_the_cli():
            print(f"eligsir: {line}", file=sys.stderr)
            raise SystemExit(1) from None
        raise MissingSystemLibrary(line) from None
    return open3d
