"""Headless Chromium driven over the DevTools protocol, enough to screenshot a page after a wait.

`chromium-headless-shell --screenshot` fires at page load, before a WebAssembly app (the Rerun web viewer)
has started, so the test opens the page with --remote-debugging-port and asks for Page.captureScreenshot
itself, when it wants. The DevTools socket is a WebSocket; this is a minimal client for it (text frames, no
extensions), so the tests need no WebSocket package.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import socket
import struct
import subprocess
import time
import urllib.request

from procs import wait_for

BROWSERS = ("chromium-headless-shell", "chromium", "chromium-browser")
# software rendering (no GPU on a head or in CI): SwiftShader through ANGLE gives the viewer its WebGL
FLAGS = ("--headless", "--no-sandbox", "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
         "--disable-dev-shm-usage", "--no-first-run", "--no-default-browser-check", "--hide-scrollbars",
         "--mute-audio", "--disable-renderer-backgrounding", "--disable-background-timer-throttling",
         "--disable-backgrounding-occluded-windows")


def find_browser() -> str | None:
    for name in BROWSERS:
        path = shutil.which(name) or (f"/usr/lib/chromium/{name}" if os.path.exists(f"/usr/lib/chromium/{name}")
                                      else None)
        if path:
            return path
    return None


class WebSocket:
    def __init__(self, url: str, timeout: float = 180.0):
        assert url.startswith("ws://")
        hostport, _, path = url[5:].partition("/")
        host, _, port = hostport.partition(":")
        self.sock = socket.create_connection((host, int(port)), timeout=timeout)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET /{path} HTTP/1.1\r\nHost: {hostport}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n")
                          .encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise ConnectionError("DevTools closed the socket during the handshake")
            head += chunk
        if b" 101 " not in head.split(b"\r\n", 1)[0]:
            raise ConnectionError(f"no WebSocket upgrade: {head[:200]!r}")
        self.buf = head.split(b"\r\n\r\n", 1)[1]

    def _fill(self, n: int) -> None:
        """At least n bytes in the buffer (a timeout leaves what was read in it, so a later call goes on)."""
        while len(self.buf) < n:
            chunk = self.sock.recv(1 << 20)
            if not chunk:
                raise ConnectionError("DevTools closed the socket")
            self.buf += chunk

    def send(self, text: str) -> None:
        data = text.encode()
        n = len(data)
        head = bytes([0x81])
        if n < 126:
            head += bytes([0x80 | n])
        elif n < 1 << 16:
            head += bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            head += bytes([0x80 | 127]) + struct.pack(">Q", n)
        mask = os.urandom(4)
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def recv(self) -> str:
        message = b""
        while True:
            self._fill(2)
            b0, b1 = self.buf[0], self.buf[1]
            n, head = b1 & 0x7F, 2
            if n == 126:
                self._fill(4)
                n, head = struct.unpack(">H", self.buf[2:4])[0], 4
            elif n == 127:
                self._fill(10)
                n, head = struct.unpack(">Q", self.buf[2:10])[0], 10
            self._fill(head + n)  # the whole frame before any of it is taken
            message += self.buf[head:head + n]
            self.buf = self.buf[head + n:]
            if b0 & 0x80:  # FIN
                return message.decode()

    def close(self) -> None:
        self.sock.close()


class Browser:
    """A headless Chromium showing `url` in a width x height window; screenshot() over DevTools."""

    def __init__(self, exe: str, url: str, port: int, profile: str, log, width: int = 1280, height: int = 800):
        self.p = subprocess.Popen([exe, *FLAGS, f"--remote-debugging-port={port}", f"--user-data-dir={profile}",
                                   f"--window-size={width},{height}", url],
                                  stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                  start_new_session=True)
        self.port, self.ws, self.n = port, None, 0
        self.requests: dict[str, str] = {}  # request id -> URL the page asked for (after Network.enable)
        self.blocked: dict[str, str] = {}  # request id -> why the browser did not send it (csp, ...)

    def connect(self, timeout: float = 30.0) -> None:
        def page():
            if self.p.poll() is not None:
                raise TimeoutError(f"no DevTools page on port {self.port} (browser rc {self.p.poll()})")
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{self.port}/json/list", timeout=2) as r:
                    pages = [t for t in json.load(r) if t.get("type") == "page"]
            except OSError:
                return None
            return pages[0] if pages else None

        first = wait_for(page, timeout, f"a DevTools page on port {self.port}", interval=0.3)
        self.ws = WebSocket(first["webSocketDebuggerUrl"])

    def call(self, method: str, timeout: float = 180.0, **params) -> dict:
        """The result of a DevTools command; TimeoutError after `timeout` s (events keep the socket busy, so
        the deadline is checked between messages too; a late answer is skipped by its id)."""
        self.n += 1
        self.ws.send(json.dumps({"id": self.n, "method": method, "params": params}))
        end = time.monotonic() + timeout
        while True:
            left = end - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"{method}: no answer within {timeout} s")
            self.ws.sock.settimeout(left)
            msg = json.loads(self.ws.recv())
            if msg.get("method") == "Network.requestWillBeSent":
                self.requests[msg["params"]["requestId"]] = msg["params"]["request"]["url"]
            elif msg.get("method") == "Network.loadingFailed" and msg["params"].get("blockedReason"):
                self.blocked[msg["params"]["requestId"]] = msg["params"]["blockedReason"]
            if msg.get("id") == self.n:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def evaluate(self, expression: str):
        return self.call("Runtime.evaluate", expression=expression, returnByValue=True).get("result", {}).get("value")

    def screenshot(self, timeout: float = 60.0) -> bytes | None:
        """A PNG of the page, or None when the browser did not give one within `timeout` s (a busy renderer:
        ask again later; the late answer is skipped by id), or while a reload detaches the page for a moment."""
        try:
            return base64.b64decode(self.call("Page.captureScreenshot", timeout=timeout, format="png")["data"])
        except TimeoutError:
            return None
        except RuntimeError as e:
            if "Not attached to an active page" in str(e):
                return None
            raise

    def close(self) -> None:
        if self.ws:
            self.ws.close()
        if self.p.poll() is None:
            os.killpg(self.p.pid, 15)
            try:
                self.p.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(self.p.pid, 9)
                self.p.wait(5)
