"""Issue 31 item 5: eligsir view cannot hang on an address it cannot listen on: a port out of range, a host that
does not resolve, an address this machine does not have are one line and exit 2; --host 0.0.0.0 prints this
machine's URLs and warns that the map is served to the network."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from eligsir_o3d.visual.bind_check import NETWORK_WARNING, check_bind, served_urls

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("host, port, said", [("127.0.0.1", 70000, "--port 70000: not a port number"),
                                              ("127.0.0.1", -1, "--port -1"),
                                              ("999.1.1.1", 8080, "--host 999.1.1.1: not an address or a name"),
                                              ("10.1.2.3", 8080, "--host 10.1.2.3: not an address of this machine")])
def test_check_bind_refuses(host, port, said):
    with pytest.raises(ValueError, match=said.replace(".", r"\.")):
        check_bind(host, port)


def test_check_bind_accepts_loopback_and_a_taken_port():
    import socket

    check_bind("127.0.0.1", 0)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        check_bind("127.0.0.1", s.getsockname()[1])  # taken: the viewer takes the next free one


def test_wildcard_urls_and_warning():
    urls = served_urls("0.0.0.0", 8123)
    assert urls[0] == "http://127.0.0.1:8123" and all(u.endswith(":8123") for u in urls)
    assert "every network" in NETWORK_WARNING


@pytest.mark.parametrize("args, said", [(["--port", "70000"], "not a port number"),
                                        (["--host", "10.1.2.3"], "not an address of this machine")])
def test_eligsir_view_exits_2_at_once(tmp_path, args, said):
    from tests.cli.test_one_line_errors import map_ply  # noqa: F401  (fixture body reused below)
    import torch

    from eligsir_o3d.core.gaussians import GaussianMap
    from eligsir_o3d.io.ply import save_ply

    g = GaussianMap(0)
    g.add(torch.rand(20, 3), torch.rand(20, 3), torch.rand(20, 3) * 0.1 + 0.01, torch.rand(20) * 0.5 + 0.4,
          torch.randn(20, 4))
    save_ply(g, tmp_path / "map.ply")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-m", "eligsir_o3d.cli", "view", str(tmp_path / "map.ply"), *args],
                       capture_output=True, text=True, env=env, timeout=240)
    assert r.returncode == 2 and said in r.stderr and "Traceback" not in r.stderr + r.stdout, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
