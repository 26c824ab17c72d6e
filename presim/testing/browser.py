"""Headless Chromium for checks of served pages (the rerun web viewer, the teleop page).

Drives Debian's ``chromedriver`` over its W3C WebDriver HTTP API with the standard library (no
selenium needed). WebGL runs on SwiftShader (``--use-gl=swiftshader --enable-unsafe-swiftshader``);
``chromium --screenshot`` alone is not enough because its virtual time does not wait for the wasm
viewer to compile, so we poll real time instead.
"""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

import cv2
import numpy as np

from presim.outputs.viewer import free_port, wait_for_port

__all__ = ["CHROMIUM_ARGS", "Browser", "find_browser", "screenshot", "saturated_fraction", "save_png"]

CHROMIUM_ARGS = ("--headless", "--no-sandbox", "--disable-gpu", "--use-gl=swiftshader",
                 "--enable-unsafe-swiftshader", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run",
                 "--disable-dev-shm-usage")


def find_browser() -> tuple[str, str]:
    """(chromium, chromedriver) paths; FileNotFoundError naming what is missing."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if not chromium or not driver:
        raise FileNotFoundError("headless browser check needs Debian's chromium and chromium-driver "
                                f"(found chromium={chromium}, chromedriver={driver})")
    return chromium, driver


def _req(base: str, method: str, path: str, body: dict | None = None, timeout_s: float = 120.0) -> dict:
    data = json.dumps(body).encode() if body is not None else None
    r = urllib.request.Request(base + path, data=data, method=method,
                               headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(r, timeout=timeout_s) as f:
        return json.loads(f.read())


class Browser:
    """A headless Chromium driven over chromedriver's W3C WebDriver API: ``open``, ``screenshot``,
    ``execute`` (JavaScript), ``keys`` (held key presses). Use as a context manager."""

    def __init__(self, width: int = 1280, height: int = 800):
        self.width, self.height = width, height
        self.proc: subprocess.Popen | None = None
        self.sid: str | None = None
        self._profile: tempfile.TemporaryDirectory | None = None

    def __enter__(self) -> "Browser":
        chromium, driver = find_browser()
        port = free_port()
        self._profile = tempfile.TemporaryDirectory(prefix="presim-chromium-")
        self.proc = subprocess.Popen([driver, f"--port={port}", "--allowed-ips=127.0.0.1"],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.base = f"http://127.0.0.1:{port}"
        try:
            wait_for_port("127.0.0.1", port, 20)
            args = list(CHROMIUM_ARGS) + [f"--window-size={self.width},{self.height}",
                                          f"--user-data-dir={self._profile.name}"]
            caps = {"capabilities": {"alwaysMatch": {
                "browserName": "chrome", "goog:chromeOptions": {"binary": chromium, "args": args}}}}
            self.sid = _req(self.base, "POST", "/session", caps)["value"]["sessionId"]
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def _s(self, method: str, path: str, body: dict | None = None) -> dict:
        return _req(self.base, method, f"/session/{self.sid}{path}", body)

    def open(self, url: str) -> None:
        self._s("POST", "/url", {"url": url})

    def screenshot(self) -> np.ndarray:
        """RGB uint8 (H, W, 3) of the viewport."""
        png = base64.b64decode(self._s("GET", "/screenshot")["value"])
        return cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)

    def execute(self, script: str, *args):
        """Run ``script`` (a function body; ``return`` gives the value) in the page."""
        return self._s("POST", "/execute/sync", {"script": script, "args": list(args)})["value"]

    def keys(self, key: str, hold_s: float) -> None:
        """Press ``key`` (a character, or a WebDriver key code such as ``\ue013`` for arrow up) and
        hold it ``hold_s`` seconds."""
        self._s("POST", "/actions", {"actions": [{"type": "key", "id": "keyboard", "actions": [
            {"type": "keyDown", "value": key}, {"type": "pause", "duration": int(hold_s * 1000)},
            {"type": "keyUp", "value": key}]}]})

    def new_tab(self) -> str:
        """Open a new tab, switch to it, return its handle."""
        handle = self._s("POST", "/window/new", {"type": "tab"})["value"]["handle"]
        self.switch_to(handle)
        return handle

    def switch_to(self, handle: str) -> None:
        self._s("POST", "/window", {"handle": handle})

    def close_tab(self) -> None:
        self._s("DELETE", "/window")

    def handles(self) -> list[str]:
        return self._s("GET", "/window/handles")["value"]

    def __exit__(self, *exc) -> None:
        if self.sid is not None:
            try:
                _req(self.base, "DELETE", f"/session/{self.sid}", timeout_s=20)
            except OSError:
                pass
            self.sid = None
        if self.proc is not None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
            self.proc = None
        if self._profile is not None:
            self._profile.cleanup()
            self._profile = None


def screenshot(url: str, ready, width: int = 1280, height: int = 800, timeout_s: float = 90.0,
               poll_s: float = 2.0) -> np.ndarray:
    """Load ``url`` and return the first screenshot (RGB uint8 (H, W, 3)) for which ``ready(img)``
    is true, or the last one after ``timeout_s``."""
    with Browser(width, height) as b:
        b.open(url)
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                img = b.screenshot()
            except urllib.error.HTTPError as e:
                # chromedriver answers 500 "timed out receiving message from renderer" while the page's
                # renderer is busy (the wasm viewer compiling on a loaded machine): try again.
                if time.monotonic() > deadline:
                    raise TimeoutError(f"no screenshot of {url} within {timeout_s:.0f} s ({e})") from e
                time.sleep(poll_s)
                continue
            if ready(img) or time.monotonic() > deadline:
                return img
            time.sleep(poll_s)


def saturated_fraction(img: np.ndarray, min_saturation: int = 120, min_value: int = 60) -> float:
    """Fraction of pixels that are clearly colored (HSV S and V above thresholds). The rerun UI is
    grey; a colored scene cloud is what makes this large."""
    hsv = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2HSV)
    return float(np.mean((hsv[..., 1] >= min_saturation) & (hsv[..., 2] >= min_value)))


def save_png(path: str | Path, img: np.ndarray) -> None:
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
