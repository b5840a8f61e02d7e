"""Headless Chromium driven through chromedriver's W3C WebDriver HTTP API (plain urllib, no
Selenium), loopback only: for tests that must see what a browser renders (the Rerun web viewer).

Debian's `chromium` + `chromium-driver` (deploy/install.sh installs them with the test extra).
Every host name except 127.0.0.1 resolves to nothing, so a page cannot reach the network.
"""
from __future__ import annotations

import base64
import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from contextlib import contextmanager
from typing import Any, Iterator

from aerotest import free_port

CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--enable-unsafe-swiftshader",                    # WebGL on the CPU (no GPU on these machines)
    "--host-resolver-rules=MAP * ~NOTFOUND , EXCLUDE 127.0.0.1",
    "--window-size=1600,1000",
]


def missing_tools() -> list[str]:
    return [t for t in ("chromium", "chromedriver") if shutil.which(t) is None]


class Browser:
    def __init__(self, port: int, session_id: str):
        self.port, self.session_id = port, session_id

    def _call(self, method: str, path: str, body: Any = None, timeout_s: float = 60.0) -> Any:
        req = urllib.request.Request(f"http://127.0.0.1:{self.port}/session/{self.session_id}{path}", method=method,
                                     data=None if body is None else json.dumps(body).encode(),
                                     headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(req, timeout=timeout_s) as r:
            return json.loads(r.read())["value"]

    def get(self, url: str) -> None:
        self._call("POST", "/url", {"url": url})

    def screenshot_png(self) -> bytes:
        return base64.b64decode(self._call("GET", "/screenshot"))

    def console(self) -> list[dict]:
        """Browser console lines since the last call (chromedriver's goog:loggingPrefs)."""
        try:
            return self._call("POST", "/se/log", {"type": "browser"})
        except OSError:
            return []


def _post(port: int, path: str, body: Any, timeout_s: float) -> Any:
    req = urllib.request.Request(f"http://127.0.0.1:{port}{path}", method="POST", data=json.dumps(body).encode(),
                                 headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=timeout_s) as r:
        return json.loads(r.read())["value"]


@contextmanager
def headless_chromium(start_timeout_s: float = 30.0) -> Iterator[Browser]:
    """A fresh headless Chromium (own --user-data-dir) behind its own chromedriver on a free port;
    both stopped by handle at exit."""
    port = free_port()
    profile = tempfile.mkdtemp(prefix="aero-chromium-")
    driver = subprocess.Popen(["chromedriver", f"--port={port}", "--allowed-ips=127.0.0.1"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL)
    session_id = None
    try:
        caps = {"capabilities": {"alwaysMatch": {
            "browserName": "chrome",
            "goog:loggingPrefs": {"browser": "ALL"},
            "goog:chromeOptions": {"binary": shutil.which("chromium"),
                                   "args": [*CHROMIUM_FLAGS, f"--user-data-dir={profile}"]}}}}
        deadline = time.monotonic() + start_timeout_s
        while True:
            try:
                session_id = _post(port, "/session", caps, timeout_s=start_timeout_s)["sessionId"]
                break
            except OSError:
                if time.monotonic() > deadline or driver.poll() is not None:
                    raise
                time.sleep(0.2)
        yield Browser(port, session_id)
    finally:
        if session_id is not None:
            try:
                req = urllib.request.Request(f"http://127.0.0.1:{port}/session/{session_id}", method="DELETE")
                urllib.request.urlopen(req, timeout=10).close()
            except OSError:
                pass
        driver.terminate()
        try:
            driver.wait(5)
        except subprocess.TimeoutExpired:
            driver.kill()
            driver.wait(5)
        shutil.rmtree(profile, ignore_errors=True)
