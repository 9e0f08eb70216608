"""Load a page from disk in a real headless Chromium and report what happened, through the
DevTools protocol: every request the page made, how many of its images loaded, and a
screenshot of the whole page.

Also a command: ``python tests/browser.py PAGE.html SHOT.png`` (how docs/report.png is made).
"""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

import websocket

# The flags Chromium needs on a machine with no network and no display (root, no sandbox).
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--hide-scrollbars", "--remote-debugging-port=0")


def chromium_binary() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


class _DevTools:
    def __init__(self, url: str) -> None:
        # No Origin header: Chromium 111 and later refuse a DevTools WebSocket whose origin is
        # not listed in --remote-allow-origins (150 answered 403), and a client without one is
        # not a web page.
        self.socket = websocket.create_connection(url, timeout=60, suppress_origin=True)
        self.next_id = 0
        self.events: list[dict] = []

    def call(self, method: str, **params) -> dict:
        self.next_id += 1
        self.socket.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            message = json.loads(self.socket.recv())
            if message.get("id") == self.next_id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message.get("result", {})
            self.events.append(message)

    def wait_for(self, event: str, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while not any(e.get("method") == event for e in self.events):
            if time.monotonic() > deadline:
                raise TimeoutError(f"Chromium sent no {event} within {timeout} s")
            self.events.append(json.loads(self.socket.recv()))


def load_page(page: Path, screenshot: Path, width: int = 1280) -> dict:
    """Open ``page`` (a file) in headless Chromium; returns the URLs requested and the
    page's count of loaded and broken images, and writes a full-page PNG screenshot."""
    binary = chromium_binary()
    if binary is None:
        raise FileNotFoundError("no Chromium binary (install Debian's chromium)")
    profile = tempfile.mkdtemp(prefix="chromium-profile-")
    try:
        process = subprocess.Popen([binary, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--window-size={width},900",
                                    "about:blank"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            port_file = Path(profile) / "DevToolsActivePort"
            deadline = time.monotonic() + 60
            while not port_file.is_file() or not port_file.read_text().strip():
                if time.monotonic() > deadline or process.poll() is not None:
                    raise RuntimeError("Chromium did not start its DevTools endpoint")
                time.sleep(0.1)
            port = port_file.read_text().split()[0]
            targets = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=30).read())
            tab = next(t for t in targets if t["type"] == "page")
            devtools = _DevTools(tab["webSocketDebuggerUrl"])
            devtools.call("Network.enable")
            devtools.call("Page.enable")
            devtools.call("Page.navigate", url=page.resolve().as_uri())
            devtools.wait_for("Page.loadEventFired")
            state = json.loads(devtools.call("Runtime.evaluate", returnByValue=True, expression="""JSON.stringify({
                total: document.images.length,
                loaded: document.body.dataset.imagesLoaded,
                broken: Array.prototype.filter.call(document.images, i => !i.complete || i.naturalWidth === 0).map(i => i.src),
                height: document.documentElement.scrollHeight})""")["result"]["value"])
            # Videos do not hold up the load event: wait (10 s at most) until each has its metadata.
            state["videos"] = json.loads(devtools.call("Runtime.evaluate", returnByValue=True, awaitPromise=True,
                                                       expression="""new Promise(done => {
                const videos = Array.from(document.querySelectorAll('video'));
                const report = () => done(JSON.stringify(videos.map(v => ({src: v.src, ready: v.readyState,
                    duration: v.duration, width: v.videoWidth, error: v.error ? v.error.code : null,
                    playable: v.canPlayType('video/mp4; codecs="avc1.640028"')}))));
                const start = Date.now();
                (function wait() {
                    if (videos.every(v => v.readyState >= 1 || v.error) || Date.now() - start > 10000) report();
                    else setTimeout(wait, 100);
                })();
            })""")["result"]["value"])
            height = min(int(state["height"]), 16000)
            devtools.call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1, mobile=False)
            shot = devtools.call("Page.captureScreenshot", format="png")
            screenshot.write_bytes(base64.b64decode(shot["data"]))
            requests = [e["params"]["request"]["url"] for e in devtools.events if e.get("method") == "Network.requestWillBeSent"]
            devtools.socket.close()
        finally:
            process.terminate()
            process.wait(timeout=30)
    finally:
        _remove_profile(Path(profile))
    return {"requests": requests, **state}


def _remove_profile(profile: Path, patience: float = 10.0) -> None:
    """Remove Chromium's profile folder. Its helper processes can still write there for a
    moment after the browser has exited (a test once failed on "Directory not empty"), so
    removal is tried again for up to ``patience`` seconds."""
    deadline = time.monotonic() + patience
    while True:
        try:
            shutil.rmtree(profile)
            return
        except FileNotFoundError:
            return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


if __name__ == "__main__":
    result = load_page(Path(sys.argv[1]), Path(sys.argv[2]))
    print(json.dumps({k: v for k, v in result.items() if k != "requests"}, indent=1), f"{len(result['requests'])} requests")
