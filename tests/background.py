"""The slow tests' long in-process computations, done ahead in the background (issue #33).

A test module registers, at import, the calls its slow tests will make and the tests that make them:

    background.ahead(sweeps.late, "sine:z=0.8,amp=0.3,hz=1", 0.066, tests="test_the_default_controller_tracks_...")

and a test asks for the result as it would call the function:

    steps = background.get(sweeps.late, "sine:z=0.8,amp=0.3,hz=1", 0.066)

Once collection is over (tests/conftest.py calls start), the calls of the selected tests go, in the order of those
tests, to as many worker processes as the machine has cores, at idle priority (SCHED_IDLE: they run only on a core
nothing else wants, so they take nothing from the processes and the timings under test); the tests of real
processes, which mostly wait, leave the cores to them. get() returns the worker's result (waiting for it, at most
WAIT_S); for a call nobody registered, without workers, or when its worker died, it computes it here: the result is
the same either way (the functions are deterministic: tests/sweeps.py). A registered function is a top-level function
of a helper module of tests/ (a worker imports it by name). The workers are children of pytest (the reaper ends
them with the run) and leave when their pipe closes."""

from __future__ import annotations

import concurrent.futures
import os
import pickle
import subprocess
import sys
import threading

HERE = os.path.dirname(os.path.abspath(__file__))
WAIT_S = 1800.0  # the longest get() waits for one result

# a worker: idle priority (os.nice where SCHED_IDLE is not to be had), the real packages first (before tests/ is on
# the path: see tests/conftest.py), then serve
_BOOT = ("import os\ntry:\n    os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))\n"
         "except (AttributeError, OSError):\n    os.nice(19)\n"
         f"import vergence, services, sys\nsys.path.append({HERE!r})\nimport background\nbackground._serve()\n")

_jobs: dict[tuple, tuple] = {}  # key -> (fn, args, kwargs)
_needs: dict[tuple, set[tuple[str, str]]] = {}  # key -> {(test file, test function name)}
_futures: dict[tuple, concurrent.futures.Future] = {}
_queue: list[tuple] = []  # the keys not yet handed to a worker, in order
_lock = threading.Lock()
_workers: list[subprocess.Popen] = []
_threads: list[threading.Thread] = []


def _key(fn, args, kwargs) -> tuple:
    return fn.__module__, fn.__qualname__, args, tuple(sorted(kwargs.items()))


def ahead(fn, *args, tests: str | tuple[str, ...], **kwargs) -> None:
    """Register fn(*args, **kwargs) as a call the named tests of the calling module make (function names, without
    parameters): done ahead in the background when one of them is selected."""
    caller = os.path.abspath(sys._getframe(1).f_globals["__file__"])
    key = _key(fn, args, kwargs)
    _jobs[key] = (fn, args, kwargs)
    _needs.setdefault(key, set()).update((caller, t) for t in ((tests,) if isinstance(tests, str) else tests))


def get(fn, *args, **kwargs):
    """fn(*args, **kwargs): the background's result when the call was done ahead, else computed here."""
    fut = _futures.get(_key(fn, args, kwargs))
    if fut is not None:
        try:
            return fut.result(timeout=WAIT_S)
        except _WorkerDied:
            pass  # its worker died (killed): compute it here
    return fn(*args, **kwargs)


class _WorkerDied(Exception):
    pass


# -- the parent's side ----------------------------------------------------------------------------------------------

def start(items) -> int:
    """Hand the registered calls of the selected test items to the workers, in the items' order; how many."""
    wanted: dict[tuple[str, str], list[tuple]] = {}
    for key, needs in _needs.items():
        for n in needs:
            wanted.setdefault(n, []).append(key)
    order: list[tuple] = []
    for item in items:
        name = getattr(item, "originalname", None) or item.name.split("[")[0]
        for key in wanted.get((os.path.abspath(str(item.path)), name), []):
            if key not in order:
                order.append(key)
    if not order:
        return 0
    for key in order:
        _futures[key] = concurrent.futures.Future()
    _queue[:] = order
    for _ in range(min(os.cpu_count() or 2, len(order))):
        w = subprocess.Popen([sys.executable, "-c", _BOOT], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             stderr=subprocess.DEVNULL)
        _workers.append(w)
        t = threading.Thread(target=_feed, args=(w,), name="background worker", daemon=True)
        t.start()
        _threads.append(t)
    return len(order)


def _next() -> tuple | None:
    with _lock:
        return _queue.pop(0) if _queue else None


def _feed(w: subprocess.Popen) -> None:
    """Give worker w the next call, set its future from the answer; until none is left or w is gone."""
    while (key := _next()) is not None:
        fut = _futures[key]
        if not fut.set_running_or_notify_cancel():
            continue
        try:
            pickle.dump(_jobs[key], w.stdin)
            w.stdin.flush()
            ok, value = pickle.load(w.stdout)
        except (OSError, EOFError, pickle.UnpicklingError, ValueError):
            fut.set_exception(_WorkerDied(f"background worker {w.pid} died"))
            break
        if ok:
            fut.set_result(value)
        else:
            fut.set_exception(value)
    with _lock:  # w died: what is left goes to the others, or, with none left, to get() (computed there)
        if not any(t.is_alive() for t in _threads if t is not threading.current_thread()):
            for k in _queue:
                if _futures[k].set_running_or_notify_cancel():
                    _futures[k].set_exception(_WorkerDied("no background worker left"))
            _queue.clear()


def stop() -> None:
    """Close the workers' pipes (they leave); kill those still computing (a run cut short)."""
    with _lock:
        for key in _queue:
            _futures[key].cancel()
        _queue.clear()
    for w in _workers:
        try:
            w.stdin.close()
        except OSError:
            pass
    for w in _workers:
        try:
            w.wait(1.0)
        except subprocess.TimeoutExpired:
            w.kill()
            w.wait(5.0)
    for t in _threads:
        t.join(5.0)
    _workers.clear()
    _threads.clear()
    _futures.clear()


# -- the worker's side -------------------------------------------------------------------------------------------------

def _serve() -> None:
    """Read (fn, args, kwargs) from stdin, write (True, result) or (False, exception) to stdout; until end of file.
    Anything the computations print goes to stderr (stdout carries the answers)."""
    import cv2

    cv2.setNumThreads(1)  # the workers are the parallelism
    answers = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    jobs = sys.stdin.buffer
    while True:
        try:
            fn, args, kwargs = pickle.load(jobs)
        except EOFError:
            return
        try:
            out = (True, fn(*args, **kwargs))
        except Exception as e:  # noqa: BLE001 (the test that asked gets it)
            out = (False, e)
        try:
            data = pickle.dumps(out)
        except Exception as e:  # noqa: BLE001 (an exception that does not pickle)
            data = pickle.dumps((False, RuntimeError(repr(e))))
        answers.write(data)
        answers.flush()
