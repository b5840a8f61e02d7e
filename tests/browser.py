"""Headless Chromium driven through chromedriver's W3C WebDriver HTTP API (plain urllib, no
Selenium), loopback only: for tests that must see what a browser renders (the Rerun web viewer).

Debian's `chromium` + `chromium-driver` (deploy/install.sh installs them with the test extra).
Every host name except 127.0.0.1 resolves to nothing, so a page cannot reach the network.

On a loaded machine a software-rendered (SwiftShader) page makes every WebDriver call slow: each
call has its own bound, a screenshot that times out is asked for again (chromedriver finishes the
first one meanwhile) within an overall bound, and the window is as small as the check allows.
"""
from __future__ import annotations

import base64
import functools
import http.server
import json
import socket
import shutil
import subprocess
import tempfile
import threading
import time
import urllib.request
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

from aerotest import free_port

CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--enable-unsafe-swiftshader",                    # WebGL on the CPU (no GPU on these machines)
    "--host-resolver-rules=MAP * ~NOTFOUND , EXCLUDE 127.0.0.1",
]
WINDOW = (1600, 1000)
CALL_TIMEOUT_S = 60.0


class BrowserTimeout(AssertionError):
    """A WebDriver call did not answer within its bounds (the message says which and how long)."""


def _timed_out(e: OSError) -> bool:
    return isinstance(e, (TimeoutError, socket.timeout)) or isinstance(getattr(e, "reason", None), TimeoutError)


def missing_tools() -> list[str]:
    return [t for t in ("chromium", "chromedriver") if shutil.which(t) is None]


class Browser:
    def __init__(self, port: int, session_id: str):
        self.port, self.session_id = port, session_id

    def _call(self, method: str, path: str, body: Any = None, timeout_s: float = CALL_TIMEOUT_S) -> Any:
        req = urllib.request.Request(f"http://127.0.0.1:{self.port}/session/{self.session_id}{path}", method=method,
                                     data=None if body is None else json.dumps(body).encode(),
                                     headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(req, timeout=timeout_s) as r:
            return json.loads(r.read())["value"]

    def get(self, url: str, timeout_s: float = CALL_TIMEOUT_S) -> None:
        """Navigate; chromedriver gives up on the page load after `timeout_s` too."""
        self._call("POST", "/timeouts", {"pageLoad": int(timeout_s * 1000)})
        self._call("POST", "/url", {"url": url}, timeout_s=timeout_s + 5.0)

    def screenshot_png(self, timeout_s: float = 30.0, total_s: float = 120.0) -> bytes:
        """A PNG of the viewport; a call that takes longer than `timeout_s` is made again (the
        renderer was busy), for at most `total_s`; then BrowserTimeout."""
        start = time.monotonic()
        attempts = 0
        while True:
            attempts += 1
            try:
                return base64.b64decode(self._call("GET", "/screenshot", timeout_s=timeout_s))
            except OSError as e:
                if not _timed_out(e):
                    raise
                if time.monotonic() - start + timeout_s > total_s:
                    raise BrowserTimeout(f"no screenshot within {time.monotonic() - start:.0f} s "
                                         f"({attempts} calls of <= {timeout_s:.0f} s)") from None

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
def serve_files(directory: Path) -> Iterator[int]:
    """`directory` over HTTP on 127.0.0.1 (the port is yielded), readable from any origin (CORS):
    files a page fetches from another port, e.g. a Rerun blueprint for the web viewer's `url=`."""
    class Handler(http.server.SimpleHTTPRequestHandler):
        def end_headers(self) -> None:
            self.send_header("Access-Control-Allow-Origin", "*")
            super().end_headers()

        def log_message(self, *args) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Handler, directory=str(directory)))
    thread = threading.Thread(target=server.serve_forever, name="serve-files", daemon=True)
    thread.start()
    try:
        yield server.server_address[1]
    finally:
        server.shutdown()
        server.server_close()
        thread.join(5)


@contextmanager
def headless_chromium(start_timeout_s: float = 30.0, window: tuple[int, int] = WINDOW) -> Iterator[Browser]:
    """A fresh headless Chromium (own --user-data-dir) behind its own chromedriver on a free port;
    both stopped by handle at exit. `window`: width, height in pixels (fewer: less to render)."""
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
                                   "args": [*CHROMIUM_FLAGS, f"--window-size={window[0]},{window[1]}",
                                            f"--user-data-dir={profile}"]}}}}
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
