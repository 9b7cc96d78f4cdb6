"""A screenshot of a web page with headless Chromium, over the DevTools protocol.

    python -m soma_ros.viewer.screenshot URL OUT.png [--wait 20] [--size 960x720]

Starts ``chromium`` (Debian's package; or ``--browser``) headless with a new empty
profile, no network beyond the page's own address, and WebGL on the CPU (SwiftShader),
loads URL, waits until the page is loaded and has a canvas, then ``--wait`` seconds more for
it to draw (a viser page streams its scene over a websocket after the load event, so the
load event alone is too early), and saves ``Page.captureScreenshot``. Used by the viewer's browser test and to make pictures of
`soma view` for documentation.
"""

from __future__ import annotations

import argparse
import base64
import json
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Optional

from ..core.processes import stop_process_group

__all__ = ["screenshot", "CHROMIUM_FLAGS"]

#: Flags for a headless, offline, throw-away Chromium (plus --user-data-dir=<new empty dir>).
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--enable-unsafe-swiftshader", "--hide-scrollbars", "--mute-audio")


def find_browser(name: Optional[str] = None) -> str:
    for cand in ([name] if name else ["chromium", "chromium-browser", "google-chrome"]):
        path = shutil.which(cand)
        if path:
            return path
    raise FileNotFoundError(f"no browser found ({name or 'chromium'}); on Debian: apt-get install -y chromium")


def _devtools_port(profile: Path, proc: subprocess.Popen, timeout: float) -> int:
    f = profile / "DevToolsActivePort"
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the browser exited with {proc.returncode} before it opened DevTools")
        if f.is_file():
            lines = f.read_text().splitlines()
            if lines and lines[0].strip().isdigit():
                return int(lines[0])
        time.sleep(0.1)
    raise RuntimeError(f"the browser opened no DevTools port within {timeout:.0f} s")


def _until_stable(capture, png: bytes, region: tuple[int, int, int, int], deadline: float,
                  interval_s: float = 3.0, tolerance: int = 8) -> bytes:
    """Screenshots (PNG bytes from `capture()`) until `region` matches in two in a row."""
    import cv2
    import numpy as np

    x, y, w, h = region

    def part(b: bytes):
        img = cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_COLOR)
        return img[y:y + h, x:x + w].astype(np.int16)

    last = part(png)
    while time.monotonic() < deadline:
        time.sleep(interval_s)
        png = capture()
        now = part(png)
        if now.shape == last.shape and int(np.abs(now - last).max(initial=0)) <= tolerance:
            return png
        last = now
    raise RuntimeError("the page did not stop changing")


def screenshot(url: str, out: Path, wait_s: float = 20.0, size: tuple[int, int] = (960, 720),
               browser: Optional[str] = None, timeout_s: float = 120.0,
               ready_js: str = "document.readyState === 'complete' && !!document.querySelector('canvas')",
               stable_region: Optional[tuple[int, int, int, int]] = None) -> Path:
    """Save a PNG of `url` as headless Chromium draws it `wait_s` seconds after the JavaScript
    expression `ready_js` first holds (default: the page is loaded and has a canvas); returns `out`.

    ``stable_region`` (x, y, width, height in pixels): then keep taking screenshots until this part
    of the page is the same in two in a row (a page still drawing, fading in or loading its
    scene changes between them); RuntimeError when it does not settle within ``timeout_s``."""
    from websockets.sync.client import connect

    exe = find_browser(browser)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    # the browser's helper processes may still be writing its profile as it goes away:
    # removing that scratch folder must not fail the screenshot
    with tempfile.TemporaryDirectory(prefix="soma_chromium_", ignore_cleanup_errors=True) as profile:
        cmd = [exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "--remote-debugging-port=0",
               f"--window-size={size[0]},{size[1]}", "about:blank"]
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, process_group=0)
        try:
            port = _devtools_port(Path(profile), proc, timeout=min(60.0, timeout_s))
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
                pages = [p for p in json.load(r) if p.get("type") == "page"]
            if not pages:
                raise RuntimeError("the browser has no page open")
            ids = iter(range(1, 1_000_000))
            with connect(pages[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=10) as ws:

                def call(method: str, **params) -> dict:
                    i = next(ids)
                    ws.send(json.dumps({"id": i, "method": method, "params": params}))
                    deadline = time.monotonic() + timeout_s
                    while time.monotonic() < deadline:
                        msg = json.loads(ws.recv(timeout=timeout_s))
                        if msg.get("id") == i:
                            if "error" in msg:
                                raise RuntimeError(f"{method}: {msg['error'].get('message')}")
                            return msg.get("result", {})
                    raise RuntimeError(f"{method}: no answer within {timeout_s:.0f} s")

                call("Page.enable")
                call("Emulation.setDeviceMetricsOverride", width=size[0], height=size[1], deviceScaleFactor=1,
                     mobile=False)
                call("Page.navigate", url=url)
                # the page's canvas first (a loaded page can still be assembling), then the drawing time
                deadline = time.monotonic() + timeout_s
                while time.monotonic() < deadline:
                    r = call("Runtime.evaluate", expression=ready_js, returnByValue=True)
                    if r.get("result", {}).get("value") is True:
                        break
                    time.sleep(0.5)
                else:
                    raise RuntimeError(f"{url}: the page did not become ready within {timeout_s:.0f} s")
                time.sleep(wait_s)
                png = base64.b64decode(call("Page.captureScreenshot", format="png")["data"])
                if stable_region is not None:
                    png = _until_stable(lambda: base64.b64decode(call("Page.captureScreenshot", format="png")["data"]),
                                        png, stable_region, deadline)
            out.write_bytes(png)
        finally:
            stop_process_group(proc)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("url")
    ap.add_argument("out", type=Path)
    ap.add_argument("--wait", type=float, default=20.0, help="seconds to let the page draw")
    ap.add_argument("--size", default="960x720", help="WIDTHxHEIGHT")
    ap.add_argument("--browser", help="browser executable (default: chromium)")
    args = ap.parse_args(argv)
    try:
        w, h = (int(v) for v in args.size.lower().split("x"))
        print(screenshot(args.url, args.out, args.wait, (w, h), args.browser))
    except (FileNotFoundError, RuntimeError, ValueError, OSError) as exc:
        print(f"screenshot: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
