"""`eligsir view` as a person uses it: start the command, open its page in headless Chromium, wait for the splats,
take a screenshot and check that the map is drawn. Needs Debian's `chromium` (tools/setup.sh --test installs it)
and viser (the `view` extra); skipped with the reason where either is missing."""

import os
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from helpers.headless_browser import HeadlessChromium, find_chromium
from helpers.visual_fixtures import wall_colors, write_wall_map

ROOT = Path(__file__).resolve().parents[2]

pytestmark = [
    pytest.mark.skipif(find_chromium() is None, reason="chromium is not installed (Debian: apt-get install chromium; "
                                                       "tools/setup.sh --test installs it)"),
]


def _start_view(map_ply: Path) -> tuple[subprocess.Popen, str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.Popen([sys.executable, "-c", "from eligsir_o3d.cli.app import main; main()", "view", str(map_ply),
                             "--port", "0"], cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(ln) for ln in proc.stdout], daemon=True).start()
    seen = []
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        try:
            line = lines.get(timeout=1.0)
        except queue.Empty:
            if proc.poll() is not None:
                break
            continue
        seen.append(line)
        m = re.search(r"viewer at (http://\S+)", line)
        if m:
            return proc, m.group(1)
    proc.kill()
    raise AssertionError("eligsir view printed no URL:\n" + "".join(seen))


def _stop(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGINT)  # Ctrl-C, as a person stops it
    try:
        proc.wait(20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _settled(browser: HeadlessChromium, until=None, timeout_s: float = 120.0) -> np.ndarray:
    """Screenshots every second until two in a row are equal (and ``until(img)`` holds, if given)."""
    prev = None
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        time.sleep(1.0)
        img = browser.screenshot()
        if prev is not None and np.array_equal(img, prev) and (until is None or until(img)):
            return img
        prev = img
    return prev


def _changed(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(a.astype(int) - b.astype(int)).max(-1) > 40  # [H, W]


def test_eligsir_view_draws_a_third_party_sh3_map_in_chromium(tmp_path):
    pytest.importorskip("viser", reason="viser is not installed (pip install 'eligsir-o3d[view]')")
    from eligsir_o3d.visual.splats import read_splats
    from eligsir_o3d.visual.viewer import MapViewer

    map_ply, traj = write_wall_map(tmp_path / "run")  # SH degree 3 in the original 3DGS layout
    splats = read_splats(map_ply)
    from eligsir_o3d.pose.trajectory import read_tum_trajectory

    first = read_tum_trajectory(traj)[1][0]
    from eligsir_o3d.export.views import DEFAULT_CAMERA

    empty = MapViewer(port=0)  # the same page and start view with nothing in the scene
    empty.set_start_view(splats, first, DEFAULT_CAMERA)
    proc, url = _start_view(map_ply)
    try:
        with HeadlessChromium(800, 600) as browser:
            browser.open(empty.url)
            blank = _settled(browser)
            browser.open(url)
            shot = _settled(browser, until=lambda img: _changed(img, blank).mean() > 0.3)
            browser.screenshot(tmp_path / "viewer.png")
    finally:
        _stop(proc)
        empty.close()
    print(f"screenshot: {tmp_path / 'viewer.png'}")
    changed = _changed(shot, blank)
    assert changed.mean() > 0.3, f"only {changed.mean():.1%} of the page differs from an empty scene"
    # the drawn pixels have the wall's colours: near some splat colour of the map (blended splats lie between
    # neighbouring colours of the smooth gradient), and on average the map's average colour
    u, v = np.meshgrid(np.linspace(0, 1, 64), np.linspace(0, 1, 48))
    palette = wall_colors(u.ravel(), v.ravel()) * 255.0  # [P, 3]
    pixels = shot[changed].astype(float)[:: max(1, int(changed.sum()) // 5000)]  # [M, 3]
    nearest = np.sqrt(((pixels[:, None, :] - palette[None]) ** 2).sum(-1)).min(1)
    assert np.median(nearest) < 25, f"median distance to the map's colours {np.median(nearest):.1f}"
    assert np.abs(pixels.mean(0) - splats.rgbs.mean(0) * 255).max() < 40, (pixels.mean(0), splats.rgbs.mean(0))
