"""Command -> motor_state round trip through a router, for the sim driver and the Dynamixel driver on the
emulator's pseudo-terminal. A measurement, not a test:

    python tests/emulators/measure_actuator.py [N]

Starts a router and `vergence actuator` with tests/procs.py, sends N (300) commands one at a time, each after
the state of the previous one came back, and prints answered, p50 and p99 in milliseconds per driver."""

from __future__ import annotations

import json
import sys
import tempfile
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent), str(HERE.parent.parent)]

from emulators.dynamixel import DynamixelEmulator  # noqa: E402
from emulators.pty import PtyDevice  # noqa: E402
from procs import Procs, wait_for  # noqa: E402

from vergence.wire.messages import Command, MotorState  # noqa: E402


def round_trips(tmp: Path, driver_args: list[str], n: int) -> dict:
    with Procs(tmp) as P:
        P.router()
        P.start("actuator", "actuator", *driver_args)
        s = P.session()
        got: dict[int, float] = {}
        ev = threading.Event()

        def on(sample):
            m = MotorState.from_bytes(sample.payload.to_bytes())
            if m.frame >= 0 and m.frame not in got:
                got[m.frame] = time.perf_counter()
                ev.set()

        s.declare_subscriber(P.key("motor_state"), on)
        P.wait_alive(s, "actuator")
        pub = s.declare_publisher(P.key("command"))
        wait_for(lambda: pub.matching_status.matching, 10, "the actuator's command subscriber", logs=P.logs)
        rtt = []
        for i in range(n):
            ev.clear()
            t0 = time.perf_counter()
            pub.put(Command(rig=P.rig, frame=i, t_capture_ns=time.time_ns(), pan_rad=0.001 * (i % 50),
                            correction_rad=0.0, direction=0, magnitude_px=0.0, confidence=1.0).to_bytes())
            end = t0 + 1.0
            while i not in got and time.perf_counter() < end:
                ev.wait(0.1)
            if i in got:
                rtt.append((got[i] - t0) * 1e3)
        rtt.sort()
        return {"answered": len(rtt), "sent": n, "p50_ms": round(rtt[len(rtt) // 2], 3),
                "p99_ms": round(rtt[max(0, int(len(rtt) * 0.99) - 1)], 3)}


def main() -> None:
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 300
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        (tmp / "sim").mkdir()
        print(json.dumps({"driver": "sim", **round_trips(tmp / "sim", ["--driver", "sim"], n)}))
        (tmp / "dxl").mkdir()
        dev = PtyDevice(DynamixelEmulator(), str(tmp / "ttyDXL"))
        try:
            print(json.dumps({"driver": "dynamixel (emulator on a pty)",
                              **round_trips(tmp / "dxl", ["--driver", "dynamixel", "--port", dev.link], n)}))
        finally:
            dev.close()


if __name__ == "__main__":
    main()
