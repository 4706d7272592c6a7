"""The offline web viewer: the viewer's files of the rerun-sdk wheel, served with a policy that keeps the browser
from calling out (csp), on an HTTP server of our own.

The files are read once per rerun-sdk version and kept in the user's cache (<XDG_CACHE_HOME or ~/.cache>/vergence/
web-viewer-<version>/), with the 43 MB wasm also gzip-compressed (14 MB): later starts of `vergence view --web`
serve them without the helper process, browsers that accept gzip get the small one, and a browser that saw them
once revalidates them (ETag: 304), so it keeps its compiled wasm."""

from __future__ import annotations

import gzip
import hashlib
import json
import logging
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

log = logging.getLogger("vergence.view")
GZIP_OVER = 64 * 1024  # files larger than this are kept gzip-compressed too

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


def cache_dir() -> Path | None:
    """Where the viewer's files of this rerun-sdk version are kept (None: no rerun-sdk metadata)."""
    import importlib.metadata

    try:
        version = importlib.metadata.version("rerun-sdk")
    except importlib.metadata.PackageNotFoundError:
        return None
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "vergence" / f"web-viewer-{version}"


def _read_cache(d: Path) -> dict[str, tuple[str, bytes, bytes | None]] | None:
    try:
        index = json.loads((d / "index.json").read_text())
        return {path: (ctype, (d / name).read_bytes(), (d / gz).read_bytes() if gz else None)
                for path, (ctype, name, gz) in index.items()}
    except (OSError, ValueError, TypeError):
        return None


def _write_cache(d: Path, assets: dict[str, tuple[str, bytes, bytes | None]]) -> None:
    """Each file, then the index last (a cache without its index is not one), each written whole (rename)."""
    def put(name: str, data: bytes) -> None:
        tmp = d / f".{name}.{os.getpid()}"
        tmp.write_bytes(data)
        tmp.replace(d / name)

    try:
        d.mkdir(parents=True, exist_ok=True)
        index = {}
        for i, (path, (ctype, body, gz)) in enumerate(assets.items()):
            put(f"{i}.bin", body)
            if gz is not None:
                put(f"{i}.gz", gz)
            index[path] = [ctype, f"{i}.bin", f"{i}.gz" if gz is not None else None]
        put("index.json", json.dumps(index).encode())
    except OSError as e:  # a read-only home: read them again next time
        log.warning("the web viewer's files not cached in %s: %s", d, e)


def viewer_assets(timeout: float = 120.0, cache: bool = True) -> dict[str, tuple[str, bytes, bytes | None]]:
    """The web viewer's files (path -> (content type, bytes, gzip of them or None)): from the cache (cache_dir)
    when it has them, else read once from rerun's own web server (_read_assets) and cached."""
    d = cache_dir() if cache else None
    got = _read_cache(d) if d else None
    if got and all(a in got for a in ASSETS):
        return got
    out = {path: (ctype, body, gzip.compress(body, 6) if len(body) > GZIP_OVER else None)
           for path, (ctype, body) in _read_assets(timeout).items()}
    if d:
        _write_cache(d, out)
    return out


def _read_assets(timeout: float) -> dict[str, tuple[str, bytes]]:
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


def serve_offline(bind: str, port: int, assets: dict[str, tuple], grpc_port: int):
    """Serve the viewer's files (viewer_assets) on bind:port with csp(grpc_port), from a daemon thread: gzip to
    the browsers that accept it, 304 to those that have them (ETag)."""
    import http.server

    policy = csp(grpc_port)
    tags = {path: '"%s"' % hashlib.sha1(a[1]).hexdigest()[:16] for path, a in assets.items()}

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 (the http.server API)
            path = self.path.split("?", 1)[0]
            hit = assets.get("/" if path == "/index.html" else path)
            if hit is None:
                self.send_error(404)
                return
            ctype, body = hit[0], hit[1]
            gz = hit[2] if len(hit) > 2 else None
            tag = tags["/" if path == "/index.html" else path]
            if self.headers.get("If-None-Match") == tag:  # the browser has it (and its compiled wasm)
                self.send_response(304)
                self.send_header("ETag", tag)
                self.send_header("Content-Security-Policy", policy)
                self.end_headers()
                return
            zipped = gz is not None and "gzip" in self.headers.get("Accept-Encoding", "")
            self.send_response(200)
            self.send_header("Content-Type", ctype)
            if zipped:
                self.send_header("Content-Encoding", "gzip")
                body = gz
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Content-Security-Policy", policy)
            self.send_header("Cache-Control", "no-cache")  # always asked again: ETag, 304 when unchanged
            self.send_header("ETag", tag)
            self.send_header("Vary", "Accept-Encoding")
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):  # quiet
            pass

    httpd = http.server.ThreadingHTTPServer((bind, port), Handler)
    httpd.daemon_threads = True
    threading.Thread(target=httpd.serve_forever, name="viewer-http", daemon=True).start()
    return httpd
