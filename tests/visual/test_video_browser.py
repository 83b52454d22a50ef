"""flythrough.mp4 plays in a browser: headless Chromium loads it in a <video> element and reads its duration."""

from __future__ import annotations

import functools
import http.server
import threading

import numpy as np
import pytest

from eligsir_o3d.visual.video import VideoWriter
from helpers.headless_browser import HeadlessChromium, find_chromium

pytestmark = pytest.mark.skipif(find_chromium() is None, reason="chromium is not installed (tools/setup.sh --test)")

PROBE = """new Promise(resolve => {
  const v = document.createElement('video');
  v.muted = true;
  v.onloadedmetadata = () => resolve(JSON.stringify({duration: v.duration, width: v.videoWidth}));
  v.onerror = () => resolve(JSON.stringify({error: v.error ? v.error.code : -1}));
  v.src = '%s';
  setTimeout(() => resolve(JSON.stringify({error: 'timeout'})), 15000);
})"""


def _video(path, codec, frames=48, fps=24.0):
    w = VideoWriter(path, fps, codec=codec)
    for k in range(frames):
        img = np.full((240, 320, 3), 40, np.uint8)
        img[100:140, 5 * k:5 * k + 30] = (255, 200, 0)
        w.write(img)
    w.close()
    return w


def _probe(folder, names):
    import json

    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(folder))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with HeadlessChromium() as browser:
            browser.open(f"http://127.0.0.1:{server.server_port}/")
            out = {}
            for name in names:
                r = browser.call("Runtime.evaluate", expression=PROBE % name, awaitPromise=True, returnByValue=True)
                assert "exceptionDetails" not in r and isinstance(r["result"].get("value"), str), r
                out[name] = json.loads(r["result"]["value"])
            return out
    finally:
        server.shutdown()


def test_flythrough_h264_plays_in_chromium(tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    assert _video(tmp_path / "fly.mp4", "auto").codec == "h264"
    _video(tmp_path / "old.mp4", "mp4v")
    (tmp_path / "index.html").write_text("<html><body></body></html>")
    res = _probe(tmp_path, ["fly.mp4", "old.mp4"])
    assert res["fly.mp4"].get("duration") == pytest.approx(2.0, abs=0.1), res
    assert res["fly.mp4"]["width"] == 320
    assert "error" in res["old.mp4"], res  # MPEG-4 Part 2, what OpenCV writes: browsers refuse it
