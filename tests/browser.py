"""A page rendered by headless Chromium with software WebGL (SwiftShader), captured over the DevTools protocol.

A one-shot ``--screenshot`` fires when Chromium's virtual time runs out, which on a loaded machine can be before a
WebGL page has drawn; driving the browser over its DevTools websocket instead lets a test poll screenshots until
the page shows what it should or a deadline passes.
"""

from __future__ import annotations

import base64
import itertools
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

BROWSERS = ("chromium", "chromium-browser", "google-chrome")


def chromium() -> str | None:
    """The first Chromium-like browser on PATH, or None."""
    return next((p for p in map(shutil.which, BROWSERS) if p), None)


def capture_until(
    url: str, done: Callable[[np.ndarray], bool], timeout: float = 60.0, size: tuple[int, int] = (800, 600)
) -> np.ndarray:
    """Screenshots (BGR (H, W, 3)) of ``url`` every half second until ``done(image)`` or ``timeout`` seconds; the
    last one is returned either way."""
    from websockets.sync.client import connect

    # Chromium's helper processes can still write to the profile after the main one exits: the whole process group
    # is ended, and a file written at the last moment does not fail the test.
    with tempfile.TemporaryDirectory(prefix="chromium-", ignore_cleanup_errors=True) as profile:
        cmd = [
            chromium(),
            "--headless=new",
            "--no-sandbox",
            "--disable-gpu",
            "--use-gl=angle",
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--no-first-run",
            "--remote-debugging-port=0",
            f"--user-data-dir={profile}",
            f"--window-size={size[0]},{size[1]}",
            url,
        ]
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            port = _debugging_port(Path(profile), proc, time.monotonic() + 30)
            pages = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10).read())
            ws_url = next(p["webSocketDebuggerUrl"] for p in pages if p.get("type") == "page")
            ids = itertools.count(1)
            with connect(ws_url, max_size=None, open_timeout=10) as ws:

                def call(method: str, **params) -> dict:
                    i = next(ids)
                    ws.send(json.dumps({"id": i, "method": method, "params": params}))
                    while True:
                        msg = json.loads(ws.recv(timeout=30))
                        if msg.get("id") == i:
                            if "error" in msg:
                                raise RuntimeError(f"{method}: {msg['error']}")
                            return msg["result"]

                deadline = time.monotonic() + timeout
                call(
                    "Emulation.setDeviceMetricsOverride",
                    width=size[0],
                    height=size[1],
                    deviceScaleFactor=1,
                    mobile=False,
                )
                im = None
                while True:
                    try:
                        png = base64.b64decode(call("Page.captureScreenshot", format="png")["data"])
                        im = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
                    except RuntimeError:  # still loading: the page is not attached yet
                        pass
                    if (im is not None and done(im)) or time.monotonic() > deadline:
                        if im is None:
                            raise RuntimeError(f"chromium gave no screenshot of {url} within {timeout} s")
                        return im
                    time.sleep(0.5)
        finally:
            _end_group(proc)


def _end_group(proc: subprocess.Popen) -> None:
    """Terminate the browser and every process it started (its session), killing what outlives 10 s."""
    for sig, wait in ((signal.SIGTERM, 10.0), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=wait)
        except subprocess.TimeoutExpired:
            continue
        deadline = time.monotonic() + wait  # the main process is gone: give its helpers the same time
        while time.monotonic() < deadline:
            try:
                os.killpg(proc.pid, 0)
            except ProcessLookupError:
                return
            time.sleep(0.05)


def _debugging_port(profile: Path, proc: subprocess.Popen, deadline: float) -> int:
    """The DevTools port Chromium chose (it writes it to DevToolsActivePort in its profile)."""
    f = profile / "DevToolsActivePort"
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"chromium exited with {proc.returncode} before opening its DevTools port")
        if f.is_file() and f.read_text().strip():
            return int(f.read_text().split()[0])
        time.sleep(0.1)
    raise RuntimeError("chromium opened no DevTools port within 30 s")
