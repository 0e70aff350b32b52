"""Load a local HTML page in headless Chromium and report what happened (for report tests).

Talks to the browser over the Chrome DevTools Protocol on one websocket (the ``websocket-client``
package, the ``dev`` extra) rather than through a browser-automation framework: Debian's
``chromium`` package is all it needs, and nothing is downloaded at test time.

    >>> page = load_page(Path("report.html"), screenshot=Path("shot.png"), wait_for=JS)
    >>> assert not page.errors, page.errors
"""

from __future__ import annotations

import base64
import itertools
import json
import os
import re
import shutil
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["PageResult", "browser_part_missing", "chromium_path", "load_page"]

_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
          "--disable-background-networking", "--disable-component-update", "--disable-sync",
          # WebGL on the CPU (SwiftShader): headless with --disable-gpu has no other GL
          "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
          "--remote-debugging-port=0", "--window-size=1280,900"]


def browser_part_missing(msg: str) -> None:
    """Skip the calling test for a missing browser part (Chromium, websocket-client), or fail
    it when ``SVOLSDF_REQUIRE_BROWSER`` is set (CI, where the browser test must run)."""
    import pytest

    if os.environ.get("SVOLSDF_REQUIRE_BROWSER"):
        pytest.fail(msg)
    pytest.skip(msg)


def chromium_path() -> str | None:
    """The Chromium / Chrome executable: $CHROMIUM, else the first on PATH, else None."""
    env = os.environ.get("CHROMIUM")
    if env:
        return env
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        p = shutil.which(name)
        if p:
            return p
    return None


@dataclass
class PageResult:
    """What loading a page produced.

    Attributes:
        errors: uncaught exceptions, console.error messages and error-level log entries
            (e.g. a failed request), as text.
        console: every console message, as "type: text".
        value: the last value of the ``wait_for`` expression.
        screenshot: the PNG written, or None.
    """

    errors: list[str] = field(default_factory=list)
    console: list[str] = field(default_factory=list)
    value: object = None
    screenshot: Path | None = None


class _CDP:
    def __init__(self, url: str) -> None:
        import websocket

        self.ws = websocket.create_connection(url, timeout=30, suppress_origin=True)
        self.ids = itertools.count(1)
        self.events: list[dict] = []

    def send(self, method: str, params: dict | None = None, session: str | None = None,
             timeout: float = 30.0) -> dict:
        i = next(self.ids)
        msg = {"id": i, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        self.ws.send(json.dumps(msg))
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            m = json.loads(self.ws.recv())
            if m.get("id") == i:
                if "error" in m:
                    raise RuntimeError(f"{method}: {m['error']}")
                return m.get("result", {})
            self.events.append(m)
        raise TimeoutError(f"{method}: no answer in {timeout} s")

    def wait_event(self, method: str, timeout: float) -> dict | None:
        for m in self.events:
            if m.get("method") == method:
                return m
        self.ws.settimeout(timeout)
        end = time.monotonic() + timeout
        try:
            while time.monotonic() < end:
                m = json.loads(self.ws.recv())
                self.events.append(m)
                if m.get("method") == method:
                    return m
        except Exception:  # the socket's timeout
            return None
        finally:
            self.ws.settimeout(30)
        return None


def _describe(ev: dict) -> tuple[str | None, str | None]:
    """(error text or None, console line or None) of one CDP event."""
    method, p = ev.get("method"), ev.get("params", {})
    if method == "Runtime.exceptionThrown":
        d = p.get("exceptionDetails", {})
        text = d.get("exception", {}).get("description") or d.get("text", "exception")
        return f"uncaught: {text}", None
    if method == "Runtime.consoleAPICalled":
        text = " ".join(str(a.get("value", a.get("description", ""))) for a in p.get("args", []))
        line = f"{p.get('type')}: {text}"
        return (f"console.{p.get('type')}: {text}" if p.get("type") in ("error", "assert")
                else None), line
    if method == "Log.entryAdded":
        e = p.get("entry", {})
        if e.get("level") == "error":
            return f"log ({e.get('source')}): {e.get('text')} {e.get('url', '')}".strip(), None
    return None, None


def load_page(path: Path, wait_for: str = "true", timeout: float = 30.0,
              screenshot: Path | None = None, settle: float = 0.5) -> PageResult:
    """Open ``path`` (a local file) in headless Chromium with networking off.

    Args:
        path: the HTML file.
        wait_for: a JavaScript expression polled after the load event until it is truthy (e.g.
            a canvas exists) or ``timeout`` passes.
        timeout: seconds for the whole page load and ``wait_for``.
        screenshot: write a PNG of the whole page (up to 8000 px tall) here, for debugging.
        settle: seconds to keep listening for late errors once ``wait_for`` holds.

    Returns:
        `PageResult`.

    Raises:
        RuntimeError: no Chromium, or it did not start.
    """
    exe = chromium_path()
    if exe is None:
        raise RuntimeError("no chromium on PATH (apt-get install chromium)")
    profile = tempfile.mkdtemp(prefix="report_browser_")
    proc = subprocess.Popen([exe, *_FLAGS, f"--user-data-dir={profile}", "about:blank"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    result = PageResult()
    try:
        url = None
        end = time.monotonic() + 30
        while url is None and time.monotonic() < end:
            line = proc.stderr.readline()
            if not line and proc.poll() is not None:
                break
            m = re.search(r"DevTools listening on (ws://\S+)", line)
            url = m.group(1) if m else None
        if url is None:
            raise RuntimeError(f"{exe} did not start (exit code {proc.poll()})")
        # keep draining its log: a full pipe would block the browser
        threading.Thread(target=lambda: [None for _ in proc.stderr], daemon=True).start()
        cdp = _CDP(url)
        target = cdp.send("Target.createTarget", {"url": "about:blank"})["targetId"]
        sid = cdp.send("Target.attachToTarget", {"targetId": target, "flatten": True})[
            "sessionId"]
        for dom in ("Page", "Runtime", "Log"):
            cdp.send(f"{dom}.enable", session=sid)
        # the page must not reach the network: every http(s) request fails and is logged
        cdp.send("Network.enable", session=sid)
        cdp.send("Network.emulateNetworkConditions", {"offline": True, "latency": 0,
                                                      "downloadThroughput": -1,
                                                      "uploadThroughput": -1}, session=sid)
        t0 = time.monotonic()
        cdp.send("Page.navigate", {"url": Path(path).resolve().as_uri()}, session=sid)
        cdp.wait_event("Page.loadEventFired", timeout)
        while time.monotonic() - t0 < timeout:
            r = cdp.send("Runtime.evaluate", {"expression": wait_for, "returnByValue": True},
                         session=sid)
            result.value = r.get("result", {}).get("value")
            if result.value:
                break
            time.sleep(0.2)
        cdp.wait_event("__never__", settle)
        if screenshot is not None:
            size = cdp.send("Page.getLayoutMetrics", session=sid)["cssContentSize"]
            clip = {"x": 0, "y": 0, "width": size["width"], "scale": 1,
                    "height": min(size["height"], 8000)}
            png = cdp.send("Page.captureScreenshot", {"format": "png", "clip": clip,
                                                      "captureBeyondViewport": True},
                           session=sid)["data"]
            Path(screenshot).write_bytes(base64.b64decode(png))
            result.screenshot = Path(screenshot)
        for ev in cdp.events:
            err, line = _describe(ev)
            if err:
                result.errors.append(err)
            if line:
                result.console.append(line)
        try:
            cdp.send("Browser.close", timeout=5)
        except Exception:
            pass
    finally:
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        shutil.rmtree(profile, ignore_errors=True)
    return result
