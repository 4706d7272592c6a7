"""`vergence bench start [--runs N] [--json]`: how long `vergence up` with no options takes to show its job on
this machine, the first start (an empty numba cache: it compiles) against the later ones (the baseline).

Each start is `vergence up` as README's first command runs it (the demo: a target moving in depth; only
--listen on a free port of 127.0.0.1), with NUMBA_CACHE_DIR a folder of the benchmark's own, empty for the
first start and filled by it for the N later ones. Timed from the process's start: the first decision on
vergence/head/decision, and "following", the first frame ending a run of FOLLOW frames in a row whose slave pan
is within FOLLOW_PX of the simulator's truth; up's own "compiled in" line gives the compile, and its lines of a
child killed for its heartbeat or restarted are given as "trouble" (none on a good start). Each start ends with
SIGINT, as Ctrl-C does.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import statistics
import tempfile
import threading
import time
from pathlib import Path

from services.runtime.args import whole
from services.ops.launch import Proc, free_port, vergence

FOLLOW, FOLLOW_PX = 30, 1.5
WAIT_S = 180.0  # the longest wait for a start to follow


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--runs", type=whole(1, 20), default=2, help="later starts, after the first (default 2)")
    p.add_argument("--json", action="store_true", help="one JSON object per start")


def start_once(workdir: Path, cache: Path, name: str) -> dict:
    """One `vergence up`: the seconds to its first decision, to following, and its compile (None: none)."""
    import zenoh

    from vergence.wire.messages import Frame
    from services.runtime import session

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    t0 = time.monotonic()
    up = Proc(name, vergence("up", "--listen", endpoint), log=workdir / f"{name}.log",
              env=dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONUNBUFFERED="1"))
    got: dict = {}
    run = [0]
    done = threading.Event()

    def on_decision(_sample) -> None:
        got.setdefault("decision_s", time.monotonic() - t0)

    def on_frame(sample) -> None:
        f = Frame.from_bytes(sample.payload.to_bytes())
        if f.truth_pan_rad is None or done.is_set():
            return
        run[0] = run[0] + 1 if abs(f.focal_px * math.tan(f.pan_rad - f.truth_pan_rad)) <= FOLLOW_PX else 0
        if run[0] >= FOLLOW:
            got["following_s"] = time.monotonic() - t0
            done.set()

    z = None
    try:
        while z is None and up.alive() and time.monotonic() - t0 < WAIT_S:
            try:  # up's router listens only after the compile
                z = zenoh.open(session.zenoh_config("client", [endpoint]))
            except Exception:  # noqa: BLE001 - zenoh raises its own ZError: not there yet
                time.sleep(0.1)
        if z is not None:
            z.declare_subscriber("vergence/head/decision", on_decision)
            z.declare_subscriber("vergence/head/frame", on_frame)
            done.wait(max(0.0, WAIT_S - (time.monotonic() - t0)))
    finally:
        if z is not None:
            z.close()
        up.stop()
    text = up.text()
    m = re.search(r"compiled in (\d+\.\d) s", text)
    if "following_s" not in got:
        raise RuntimeError(f"{name}: the slave did not follow within {WAIT_S:.0f} s\n{up.tail()}")
    # up's lines about a child killed for its heartbeat or restarted: none on a good start, compiling or not
    trouble = [ln for ln in text.splitlines() if "vergence.up" in ln and ("heartbeat" in ln or "restart" in ln)
               and "no restarts" not in ln]
    return dict(start=name, compile_s=float(m[1]) if m else None, **got, trouble=trouble)


def run(args: argparse.Namespace) -> int:
    with tempfile.TemporaryDirectory(prefix="vergence-bench-start-") as tmp:
        workdir = Path(tmp)
        rows = [start_once(workdir, workdir / "numba", "first")]
        rows += [start_once(workdir, workdir / "numba", f"later{i + 1}") for i in range(args.runs)]
    base = statistics.median(r["following_s"] for r in rows[1:])
    for r in rows:
        r["ratio_vs_later"] = r["following_s"] / base
        if args.json:
            print(json.dumps(r), flush=True)
        else:
            comp = f"compiled in {r['compile_s']:.1f} s, " if r["compile_s"] is not None else "no compile, "
            print(f"{r['start']:8s} {comp}first decision {r['decision_s']:.1f} s, following {r['following_s']:.1f} s "
                  f"after `vergence up` ({r['ratio_vs_later']:.2f} x the later starts' median)", flush=True)
            for line in r["trouble"]:
                print(f"         {line}", flush=True)
    return 0
