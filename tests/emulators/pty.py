"""A device model served on a pseudo-terminal, reachable through a stable path (a symlink) that can be
unplugged and plugged again: the way a USB serial adapter disappears and comes back.

A model is any object with feed(data: bytes) -> bytes (the bytes it answers). One thread owns the pty: it
reads what the driver wrote, feeds the model and writes its answer; unplug/replug requests are carried out
by that thread between reads, so no file descriptor is closed under a select() in another thread.
"""

from __future__ import annotations

import os
import queue
import select
import threading
import tty


class PtyDevice:
    def __init__(self, model, link: str):
        self.model = model
        self.link = link
        self.master = self.slave = -1
        self.plugged = threading.Event()
        self._ops: queue.Queue = queue.Queue()
        self._stop = threading.Event()
        self.rx = bytearray()  # everything the driver wrote, across plugs
        self.plugs = 0
        self._plug()
        self.thread = threading.Thread(target=self._run, name=f"pty {link}", daemon=True)
        self.thread.start()

    # called from the owning thread (or before it starts)
    def _plug(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no line editing until the driver configures it
        tmp = f"{self.link}.tmp"
        if os.path.lexists(tmp):
            os.unlink(tmp)
        os.symlink(os.ttyname(self.slave), tmp)
        os.replace(tmp, self.link)
        self.plugs += 1
        self.plugged.set()

    def _unplug(self) -> None:
        self.plugged.clear()
        if os.path.lexists(self.link):
            os.unlink(self.link)
        for fd in (self.master, self.slave):
            if fd >= 0:
                os.close(fd)
        self.master = self.slave = -1

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                op, done = self._ops.get_nowait()
                op()
                done.set()
                continue
            except queue.Empty:
                pass
            if self.master < 0:
                self._stop.wait(0.01)
                continue
            r, _, _ = select.select([self.master], [], [], 0.01)
            if not r:
                continue
            try:
                data = os.read(self.master, 4096)
            except OSError:
                continue
            self.rx += data
            out = self.model.feed(data)
            if out:
                try:
                    os.write(self.master, out)
                except OSError:
                    pass

    def _call(self, op, timeout: float = 5.0) -> None:
        done = threading.Event()
        self._ops.put((op, done))
        if not done.wait(timeout):
            raise TimeoutError("pty thread did not answer")

    def unplug(self) -> None:
        """The device disappears: the driver's reads and writes fail, the path is gone."""
        self._call(self._unplug)

    def replug(self) -> None:
        """A new pseudo-terminal behind the same path."""
        self._call(self._plug)

    def close(self) -> None:
        if self.thread.is_alive():
            self._call(self._unplug)
            self._stop.set()
            self.thread.join(5)
        else:
            self._unplug()
