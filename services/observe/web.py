"""The offline web viewer: the viewer's files of the rerun-sdk wheel, served with a policy that keeps the browser
from calling out (csp), on an HTTP server of our own."""

from __future__ import annotations

import socket
import subprocess
import sys
import threading


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def csp(grpc_port: int) -> str:
    """The Content-Security-Policy the cockpit's page is served with: the page may load only from where it
    came and fetch only from the cockpit's data port. The bundled viewer otherwise calls out from the
    browser: its usage analytics (tel.rerun.io, no opt-out in the web build), a check for a newer release
    (api.github.com) and Google's fonts; a head's network has no business calling out."""
    data = f"http://*:{grpc_port} ws://*:{grpc_port}"
    return ("default-src 'self'; script-src 'self' 'unsafe-inline' 'wasm-unsafe-eval'; "
            "style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; font-src 'self' data:; "
            f"worker-src 'self' blob:; connect-src 'self' {data}; form-action 'none'; base-uri 'self'")


ASSETS = ("/", "/re_viewer.js", "/re_viewer_bg.wasm", "/favicon.ico", "/apple-touch-icon.png")


def viewer_assets(timeout: float = 120.0) -> dict[str, tuple[str, bytes]]:
    """The web viewer's files (path -> (content type, bytes)), read once from rerun's own web server, run in a
    helper process that stops once they are read: that server listens on every interface (it cannot be told
    otherwise) and serves the page without the policy of csp()."""
    import time
    import urllib.request

    inner = _free_port()
    code = ("import sys, time, rerun as rr\n"
            "rr.serve_web_viewer(web_port=int(sys.argv[1]), open_browser=False)\n"
            "time.sleep(3600)\n")
    helper = subprocess.Popen([sys.executable, "-c", code, str(inner)], stdin=subprocess.DEVNULL,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    out: dict[str, tuple[str, bytes]] = {}
    try:
        end = time.monotonic() + timeout
        for path in ASSETS:
            while True:
                try:
                    with urllib.request.urlopen(f"http://127.0.0.1:{inner}{path}", timeout=30) as r:
                        out[path] = (r.headers.get("Content-Type", "application/octet-stream"), r.read())
                    break
                except OSError as e:
                    if helper.poll() is not None or time.monotonic() > end:
                        raise RuntimeError(f"the web viewer's files: {e}") from None
                    time.sleep(0.2)
    finally:
        helper.terminate()
        try:
            helper.wait(10)
        except subprocess.TimeoutExpired:
            helper.kill()
            helper.wait(5)
    return out


def serve_offline(bind: str, port: int, assets: dict[str, tuple[str, bytes]], grpc_port: int):
    """Serve the viewer's files on bind:port with csp(grpc_port), from a daemon thread."""
    import http.server

    policy = csp(grpc_port)

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 (the http.server API)
            path = self.path.split("?", 1)[0]
            hit = assets.get("/" if path == "/index.html" else path)
            if hit is None:
                self.send_error(404)
                return
            ctype, body = hit
            self.send_response(200)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Content-Security-Policy", policy)
            self.send_header("Cache-Control", "no-cache")
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):  # quiet
            pass

    httpd = http.server.ThreadingHTTPServer((bind, port), Handler)
    httpd.daemon_threads = True
    threading.Thread(target=httpd.serve_forever, name="viewer-http", daemon=True).start()
    return httpd
