"""vergence.wire.status: the one decoding of a status and of the workers report; what the services encode decodes to the
same values, and what is not a status (or not a report) is refused with why."""

from __future__ import annotations

import json

import msgspec
import pytest

from services.runtime.health import Health
from vergence.wire.messages import MessageError
from vergence.wire.status import WorkerEvidence, WorkersReport, decode_report, decode_status, status_of


def test_a_services_status_decodes_to_its_values():
    h = Health("capture", "c-1")
    h.count("frames", 5)
    h.reject("command", "bad")
    st = decode_status(json.dumps(h.status(clipped={"master": 0.0, "slave": 0.07}, published_hz=250.0,
                                           fixate_rejection={"t_ns": 1_800_000_000_000_000_042,
                                                             "why": "outside the image"},
                                           gatherer={"frames": 9, "dropped": -1, "late": True})).encode())
    assert (st.role, st.id, st.counters, st.bad, st.exiting) == ("capture", "c-1", {"frames": 5}, {"command": 1}, False)
    assert st.pid > 0 and st.t_ns > 1.7e18 and st.bad_total == 1
    assert st.clipped() == {"master": 0.0, "slave": 0.07} and st.number("published_hz", 0, 1e4) == 250.0
    assert st.fixate_rejection() == (1_800_000_000_000_000_042, "outside the image")
    assert st.gatherer() == {"frames": 9}  # the plausible counters only
    assert st.number("published_hz", 0, 100) is None and st.get("nothing", "x") == "x"
    assert status_of(st.to_dict()) == st  # to_dict is the wire's object
    assert st.search() is None  # not searching
    assert status_of(dict(st.to_dict(), searching=True, sweeps_empty=2)).search() == 2
    assert status_of(dict(st.to_dict(), searching=True)).search() == 0
    assert status_of(dict(st.to_dict(), searching=True, sweeps_empty=-1)).search() is None
    assert status_of(dict(st.to_dict(), searching="yes", sweeps_empty=2)).search() is None
    assert decode_status(json.dumps(dict(st.to_dict(), exiting=True)).encode()).exiting


@pytest.mark.parametrize("payload,says", [
    (b"[1]", "not a JSON object"), (b"{nope", "not JSON"), (b'{"id": "x"}', "role"),
    (b'{"role": "capture", "id": ""}', "id"), (b'{"role": "c", "id": "x", "counters": {"frames": -1}}', "counters"),
    (b'{"role": "c", "id": "x", "bad": {"frame": 1.5}}', "bad"), (b'{"role": "c", "id": "x", "t_ns": "now"}', "t_ns"),
    (b'{"role": "c", "id": "x", "exiting": 1}', "exiting"), (b'{"role": "' + b"r" * 200 + b'", "id": "x"}', "role"),
    (b'{"role": "c", "id": "x", "pad": "' + b" " * 70000 + b'"}', "over"), (b"[" * 5000, "not JSON"),
], ids=lambda v: str(v)[:24])
def test_what_is_not_a_status_is_refused_with_why(payload, says):
    with pytest.raises(MessageError, match=says):
        decode_status(payload)


def test_the_reducers_report_round_trips():
    rep = WorkersReport(rig="head", id="r-1", t_ns=5, frame=77, complete=70,
                        workers={"w1": WorkerEvidence(0.01, 0), "w2": WorkerEvidence(None, 4)})
    wire = msgspec.json.encode(rep)
    assert json.loads(wire)["workers"]["w2"] == {"age_s": None, "misses": 4}
    assert decode_report(wire) == rep
    old = b'{"frame": 3, "workers": {"w1": {"age_s": 0.5, "misses": 2}}}'  # a report without who and when
    assert decode_report(old).workers == {"w1": WorkerEvidence(0.5, 2)} and decode_report(old).complete is None
