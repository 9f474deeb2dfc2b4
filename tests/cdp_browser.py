"""A headless Chromium driven over the DevTools protocol (websocket-client), for the viewer's browser tests.

Debian's `chromium` with software WebGL (SwiftShader through ANGLE); as root it needs --no-sandbox. No browser is
downloaded: a test that needs one skips when `chromium` is absent, unless CI is "true" (then it fails).
"""
from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome")


def find_chromium() -> str | None:
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


class Browser:
    """One headless Chromium with one page; `screenshot()` returns an (h, w, 3) uint8 array."""

    def __init__(self, width: int = 1280, height: int = 800):
        import websocket  # websocket-client

        exe = find_chromium()
        if exe is None:
            raise RuntimeError("chromium not found")
        self.profile = tempfile.mkdtemp(prefix="ot-chromium-")
        args = [exe, "--headless=new", "--no-sandbox", "--disable-gpu-sandbox", "--use-gl=angle",
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
                "--no-first-run", "--no-default-browser-check", "--disable-extensions", "--mute-audio",
                f"--window-size={width},{height}", "--remote-debugging-port=0", "--remote-allow-origins=*",
                f"--user-data-dir={self.profile}", "about:blank"]
        self.proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        port_file = Path(self.profile) / "DevToolsActivePort"
        deadline = time.monotonic() + 60
        while not (port_file.is_file() and port_file.read_text().strip()):
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.close()
                raise RuntimeError("chromium did not open its DevTools port")
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        page = None
        while page is None:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as resp:
                page = next((t for t in json.load(resp) if t.get("type") == "page"), None)
            if page is None:
                if time.monotonic() > deadline:
                    self.close()
                    raise RuntimeError("chromium opened no page")
                time.sleep(0.1)
        self.ws = websocket.create_connection(page["webSocketDebuggerUrl"], timeout=60, suppress_origin=True)
        self._id = 0
        self.events: list[str] = []
        self.send("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1,
                  mobile=False)

    def send(self, method: str, **params):
        self._id += 1
        self.ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        while True:
            reply = json.loads(self.ws.recv())
            if "method" in reply:
                self.events.append(reply["method"])
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})

    def navigate(self, url: str, timeout: float = 60.0) -> None:
        """Open url and wait for its load event (a screenshot during the switch of documents fails)."""
        self.send("Page.enable")
        self.events = []
        self.send("Page.navigate", url=url)
        deadline = time.monotonic() + timeout
        self.ws.settimeout(1.0)
        try:
            while "Page.loadEventFired" not in self.events and time.monotonic() < deadline:
                try:
                    reply = json.loads(self.ws.recv())
                except Exception:  # websocket timeout: poll again
                    continue
                if "method" in reply:
                    self.events.append(reply["method"])
        finally:
            self.ws.settimeout(60)
        if "Page.loadEventFired" not in self.events:
            raise RuntimeError(f"{url} did not load in {timeout:.0f} s")

    def evaluate(self, expression: str):
        return self.send("Runtime.evaluate", expression=expression, returnByValue=True).get("result", {}).get("value")

    def screenshot(self, path: Path | None = None) -> np.ndarray:
        from PIL import Image
        import io

        data = base64.b64decode(self.send("Page.captureScreenshot", format="png")["data"])
        if path is not None:
            Path(path).write_bytes(data)
        return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))

    def close(self) -> None:
        try:
            if getattr(self, "ws", None) is not None:
                self.ws.close()
        except Exception:
            pass
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def chromium_or_skip():
    """The pytest skip (or, on CI, failure) for a missing chromium."""
    import pytest

    if find_chromium() is not None:
        return
    if os.environ.get("CI") == "true":
        pytest.fail("chromium is required on CI (apt-get install -y chromium)")
    pytest.skip("chromium not installed (apt-get install -y chromium); the browser tests need it")
