"""The tests' `vergence ...` processes forked from one preloaded parent, as `vergence up` forks its children.

A fresh `vergence worker` spends about 1.3 s of CPU before its first frame (imports 0.5 s, numba's registries 0.35,
its kernels from the cache 0.2-0.5) and a test starting a router, a capture, two workers and a reducer waits for
all of it on 2 cores; forked from a parent that loaded them once (services/runtime/warm.py's preload, the same as
up's), a worker starts in about 0.3 s. So Procs.start runs its commands through this parent, the zygote: a
process of its own, started on first use from pytest's main thread, in a session of its own (a Ctrl-C to the run's
process group is the reaper's to pass on, not the zygote's to die of; it dies with pytest: PR_SET_PDEATHSIG), with
no thread and no Zenoh session, that forks each child with services/ops/launch.py's _fork (the child's own
process group, command line, descriptors, signals and environment; it dies with the zygote) and reaps it.

What a fresh start would do differently is not forked: a command given its own environment (Procs.spawn's env,
e.g. an empty NUMBA_CACHE_DIR to time a first compile), one whose environment differs from the zygote's where an
interpreter reads it only at its start (PYTHON*, LD_*, NUMBA_*), one started off the main thread, and everything
not `vergence ...`. Tests of what a user types (tests/services/ops/test_cli.py) run the command fresh.

The protocol, on the zygote's stdin and stdout, one JSON object a line each way:
    {"op": "spawn", "argv": [...], "log": PATH, "append": bool, "env": {...}, "cwd": DIR, "err": PATH or null}
        -> {"pid": N} or {"error": TEXT}
    {"op": "poll", "pid": N} -> {"rc": CODE or null}
    EOF -> the zygote exits (its children get SIGTERM).
"""

from __future__ import annotations

import json
import os
import select
import subprocess
import sys
import threading
from pathlib import Path

if __name__ == "__main__":  # the zygote itself: the path `python -m services.ops.cli` has, not tests/ (whose
    sys.path[0] = os.getcwd()  # folder services/ would be a namespace package of that name)

from services.ops.launch import _Forked  # noqa: E402

FRESH_ONLY = ("PYTHON", "LD_", "NUMBA_")  # read by an interpreter at its start only


def _fresh_only(env: dict) -> dict:
    return {k: v for k, v in env.items() if k.startswith(FRESH_ONLY)}


class _Child(_Forked):
    """What subprocess.Popen gives of a child, for one the zygote forked: pid, poll (asked of the zygote, which reaped
    it), wait, returncode."""

    def __init__(self, zygote: "Zygote", pid: int):
        super().__init__(pid)
        self.zygote = zygote

    def poll(self) -> int | None:
        if self.returncode is None:
            self.returncode = self.zygote.call({"op": "poll", "pid": self.pid})["rc"]
        return self.returncode


class Zygote:
    """The client: pytest's end of the pipe to the zygote process."""

    def __init__(self):
        from services.ops.launch import _die_with_parent, _prctl

        _prctl()
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.env = _fresh_only(env)
        self.lock = threading.Lock()
        self.p = subprocess.Popen([sys.executable, __file__], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                  stderr=subprocess.DEVNULL, env=env, text=True, bufsize=1,
                                  start_new_session=True, preexec_fn=_die_with_parent)
        self.call({"op": "poll", "pid": 0}, timeout=120)  # it answers once it has loaded everything

    def call(self, msg: dict, timeout: float = 30) -> dict:
        """One request, its answer (RuntimeError if none comes within timeout s: the zygote is then killed)."""
        with self.lock:
            self.p.stdin.write(json.dumps(msg) + "\n")
            self.p.stdin.flush()
            # one line answers each request, so nothing is ever left in the reader's buffer to wait on
            line = self.p.stdout.readline() if select.select([self.p.stdout], [], [], timeout)[0] else None
        if not line:
            if line is None:
                self.p.kill()
            raise RuntimeError(f"the tests' zygote (pid {self.p.pid}) is gone or hung: "
                               f"{'no answer within %g s' % timeout if line is None else 'exit %s' % self.p.poll()}")
        return json.loads(line)

    def fits(self, argv: list[str], env: dict) -> bool:
        """Whether argv with env can be forked: a vergence(...) command with the zygote's start-only environment."""
        return argv[1:3] == ["-m", "services.ops.cli"] and _fresh_only(env) == self.env

    def spawn(self, argv: list[str], log: Path, env: dict, append: bool = False, err: Path | None = None) -> _Child:
        """argv forked, its stdout and stderr into log (stderr into err if given)."""
        r = self.call({"op": "spawn", "argv": argv, "log": str(log), "append": append, "env": env,
                       "cwd": os.getcwd(), "err": None if err is None else str(err)})
        if "error" in r:
            raise RuntimeError(f"the tests' zygote could not start {argv}: {r['error']}")
        return _Child(self, r["pid"])

    def close(self) -> None:
        if self.p.poll() is None:
            self.p.stdin.close()
            try:
                self.p.wait(10)
            except subprocess.TimeoutExpired:
                self.p.kill()
                self.p.wait(5)


_ZYGOTE: list[Zygote] = []


def get() -> Zygote | None:
    """The run's zygote (started on first use, again if it died), or None off pytest's main thread (it would die
    with that thread: PR_SET_PDEATHSIG)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    if not _ZYGOTE or _ZYGOTE[0].p.poll() is not None:
        _ZYGOTE[:] = [Zygote()]
    return _ZYGOTE[0]


def pids() -> set[int]:
    return {z.p.pid for z in _ZYGOTE if z.p.poll() is None}


def close() -> None:
    """End the zygote (the session's end, before the reaper looks for what is left)."""
    for z in _ZYGOTE:
        z.close()
    _ZYGOTE.clear()


def serve() -> int:
    """The zygote's loop: load what every child needs, then answer spawn and poll requests until EOF."""
    from services.ops import launch
    from services.runtime import warm
    from vergence import config

    warm.preload(config.load(None))
    children: dict[int, launch._Forked] = {}
    for line in sys.stdin:
        msg = json.loads(line)
        if msg["op"] == "spawn":
            try:
                os.chdir(msg["cwd"])
                mode = os.O_WRONLY | os.O_CREAT | (os.O_APPEND if msg["append"] else os.O_TRUNC)
                fds = [os.open(path, mode, 0o644) for path in (msg["log"], msg.get("err")) if path]
                try:
                    child = launch._fork(msg["argv"], fds[0], msg["env"], True, (), *fds[1:])
                finally:
                    for fd in fds:
                        os.close(fd)
            except Exception as e:  # noqa: BLE001  (said to the test, which raises it)
                answer = {"error": repr(e)}
            else:
                children[child.pid] = child
                answer = {"pid": child.pid}
        else:
            child = children.get(msg["pid"])
            answer = {"rc": child.poll() if child is not None else None}
            if child is not None and child.returncode is not None:
                children.pop(msg["pid"])
        sys.stdout.write(json.dumps(answer) + "\n")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(serve())
