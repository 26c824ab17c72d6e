"""Screenshot a page in headless Chromium (used to check the served web viewer renders).

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
import urllib.request
from pathlib import Path

import cv2
import numpy as np

from presim.outputs.viewer import free_port, wait_for_port

__all__ = ["CHROMIUM_ARGS", "find_browser", "screenshot", "saturated_fraction"]

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


def screenshot(url: str, ready, width: int = 1280, height: int = 800, timeout_s: float = 90.0,
               poll_s: float = 2.0) -> np.ndarray:
    """Load ``url`` and return the first screenshot (RGB uint8 (H, W, 3)) for which ``ready(img)``
    is true, or the last one after ``timeout_s``."""
    chromium, driver = find_browser()
    port = free_port()
    with tempfile.TemporaryDirectory(prefix="presim-chromium-") as profile:
        proc = subprocess.Popen([driver, f"--port={port}", "--allowed-ips=127.0.0.1"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        base = f"http://127.0.0.1:{port}"
        sid = None
        try:
            wait_for_port("127.0.0.1", port, 20)
            args = list(CHROMIUM_ARGS) + [f"--window-size={width},{height}", f"--user-data-dir={profile}"]
            caps = {"capabilities": {"alwaysMatch": {
                "browserName": "chrome", "goog:chromeOptions": {"binary": chromium, "args": args}}}}
            sid = _req(base, "POST", "/session", caps)["value"]["sessionId"]
            _req(base, "POST", f"/session/{sid}/url", {"url": url})
            deadline = time.monotonic() + timeout_s
            while True:
                png = base64.b64decode(_req(base, "GET", f"/session/{sid}/screenshot")["value"])
                img = cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR),
                                   cv2.COLOR_BGR2RGB)
                if ready(img) or time.monotonic() > deadline:
                    return img
                time.sleep(poll_s)
        finally:
            if sid is not None:
                try:
                    _req(base, "DELETE", f"/session/{sid}", timeout_s=20)
                except OSError:
                    pass
            proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def saturated_fraction(img: np.ndarray, min_saturation: int = 120, min_value: int = 60) -> float:
    """Fraction of pixels that are clearly colored (HSV S and V above thresholds). The rerun UI is
    grey; a colored scene cloud is what makes this large."""
    hsv = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2HSV)
    return float(np.mean((hsv[..., 1] >= min_saturation) & (hsv[..., 2] >= min_value)))


def save_png(path: str | Path, img: np.ndarray) -> None:
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
