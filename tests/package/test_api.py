"""The public surface: names in __all__ exist, and the package imports with numpy, torch and open3d alone."""

import subprocess
import sys

import eligsir_o3d


def test_public_names():
    for name in eligsir_o3d.__all__:
        assert hasattr(eligsir_o3d, name), name
    assert {"Reconstructor", "Config", "Frame", "get_renderer"} <= set(eligsir_o3d.__all__)


def test_import_does_not_pull_optional_dependencies():
    code = ("import sys, eligsir_o3d; bad = [m for m in ('gsplat', 'kiss_icp', 'pycolmap', 'matplotlib', 'lpips') "
            "if m in sys.modules]; print(','.join(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"import eligsir_o3d imported optional modules: {out}"
