"""Where the cockpit goes: rr.init and the sinks (a file, the web viewer, the native viewer), and the watch on a
--save file that can no longer be written."""

from __future__ import annotations

import os
import socket
import sys
import time

from services.observe.rerun_sdk import blueprint
from services.observe.web import serve_offline, viewer_assets


SERVER_MEMORY = "256MiB"  # --web: the backlog kept for viewers that connect later


def host_address() -> str:
    """An address other machines can reach this one on (the hostname's, else 127.0.0.1)."""
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.connect(("10.255.255.255", 1))  # no packet is sent: only picks the outgoing interface
            return s.getsockname()[0]
    except OSError:
        return "127.0.0.1"


class SaveWatch:
    """Whether the --save file can still be written (issue #29): Rerun writes it from a thread of its own and
    says nothing when a write fails, so every CHECK_S the file must still be the one opened (not removed or
    replaced) and its filesystem must have MIN_FREE bytes left. fault(): why not (kept once found), or ""."""

    CHECK_S = 1.0
    MIN_FREE = 256 * 1024  # less than this left: Rerun's next chunks do not fit

    def __init__(self, path: str | None):
        self.path, self.why, self._ident, self._next = path, "", None, 0.0

    def fault(self) -> str:
        now = time.monotonic()
        if self.path is None or self.why or now < self._next:
            return self.why
        self._next = now + self.CHECK_S
        try:
            st = os.stat(self.path)
            fs = os.statvfs(self.path)
        except OSError:
            if self._ident is not None:
                self.why = f"cannot write {self.path!r}: it was removed"
            return self.why  # not created yet (Rerun opens it with its first data): next time
        if self._ident is None:
            self._ident = (st.st_dev, st.st_ino)
        elif (st.st_dev, st.st_ino) != self._ident:
            self.why = f"cannot write {self.path!r}: it was replaced by another file"
        if fs.f_bavail * fs.f_frsize < self.MIN_FREE:
            self.why = (f"cannot write {self.path!r}: No space left on device (its filesystem has "
                        f"{fs.f_bavail * fs.f_frsize // 1024} KiB free)")
        return self.why


def start(rr, app: str, *, save: str | None = None, web: bool = False, port: int = 9090, grpc_port: int = 9876,
          spawn: bool = False, bind: str = "0.0.0.0") -> str | None:
    """rr.init and the sinks asked for; returns the web viewer's URL when serving it."""
    rr.init(app, spawn=False)
    sinks, url = [], None
    if save:
        sinks.append(rr.FileSink(save))
    if web:
        # a viewer that connects late gets the newest data first (its first picture is now, not the backlog's
        # start), and the backlog kept for it is bounded (rerun's default, 1 GiB, takes minutes to send)
        server = rr.GrpcServerSink(bind_ip=bind, port=grpc_port, server_memory_limit=SERVER_MEMORY,
                                   newest_first=True)
        sinks.append(server)
    if spawn and sys.platform.startswith("linux") and not (os.environ.get("DISPLAY")
                                                         or os.environ.get("WAYLAND_DISPLAY")):
        raise RuntimeError("--spawn needs a display (DISPLAY or WAYLAND_DISPLAY is not set): give --web to watch "
                           "from a browser, or --save FILE.rrd")
    if spawn:
        rr.spawn(connect=False, port=grpc_port + 1 if web else 9876)
        sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{grpc_port + 1 if web else 9876}/proxy"))
    rr.set_sinks(*sinks, default_blueprint=blueprint(rr))
    if web:
        host = "127.0.0.1" if bind.startswith("127.") else host_address()
        data = server.uri.replace("0.0.0.0", host)
        serve_offline(bind, port, viewer_assets(), grpc_port)
        from urllib.parse import quote

        url = f"http://{host}:{port}/?url={quote(data, safe='')}"
    return url
