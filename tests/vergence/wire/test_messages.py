"""Every message kind: round trip, and garbage in any shape raises MessageError and nothing else."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vergence.wire import messages as M


def frame(**kw) -> M.Frame:
    base = dict(rig="head", frame=7, t_capture_ns=123, pan_rad=0.1, width=40, height=30, x=20, y=15, window=5,
                vsearch=1, focal_px=50.0, fovea=bytes(49), band=bytes(9 * 42), plan=[["a-1", 0, 20], ["b-2", 20, 36]])
    base.update(kw)
    return M.Frame(**base)


SAMPLES = {
    "frame": frame(),
    "correlation": M.Correlation(rig="head", frame=7, t_capture_ns=1, worker="a-1", k0=0, k1=4, rows=2,
                         scores=np.arange(8, dtype="<f8").tobytes()),
    "decision": M.Decision(rig="head", frame=7, t_capture_ns=1, t_reduced_ns=2, window=5, k=3, k_sub=3.2, v_shift=0,
                          k_centre=3, direction=0, magnitude=0, offset_px=0.2, confidence=0.5, confident=True,
                          texture=9.0, pan_rad=0.0, x=320, y=240, converged=True, depth_m=1.25, depth_sigma_m=0.01),
    "profile": M.Profile(rig="head", frame=7, t_capture_ns=1, t_reduced_ns=2, width=10, window=5, rows=1,
                         scores=np.zeros(6).tobytes(), k=3, k_sub=3.2, v_shift=0, k_centre=3, direction=0,
                         magnitude=0, offset_px=0.2, confidence=0.5, confident=True, texture=9.0, pan_rad=0.0,
                         x=5, y=4, converged=False, depth_m=2.0, depth_sigma_m=0.5),
    "command": M.Command(rig="head", frame=7, t_capture_ns=1, pan_rad=0.2, correction_rad=0.01, direction=1,
                         magnitude_px=3.0, confidence=0.4),
    "motor_state": M.MotorState(rig="head", t_ns=5, pan_rad=0.1, goal_rad=0.2, min_rad=-0.7, max_rad=0.7,
                                status="ok"),
    "preview": M.Preview(rig="head", frame=1, t_capture_ns=1, width=4, height=2, scale=0.1, master=bytes(8),
                         slave=bytes(8)),
    "fixate": M.Fixate(x=100.0, y=80.5, t_ns=9, source="test"),
}


@pytest.mark.parametrize("kind", list(SAMPLES))
def test_round_trip(kind):
    msg = SAMPLES[kind]
    data = msg.to_bytes()
    assert msgpack.unpackb(data)["v"] == M.SCHEMA
    assert M.KINDS[kind].from_bytes(data) == msg


def test_a_correlation_of_an_older_worker_still_decodes():
    """An older worker sent `texture` (never read, since removed): the field is ignored, the rest decodes."""
    d = SAMPLES["correlation"].to_dict()
    d["texture"] = 3.5
    p = M.Correlation.from_bytes(msgpack.packb(d, use_bin_type=True))
    assert p == SAMPLES["correlation"] and not hasattr(p, "texture")
    assert p.array().tolist() == [[0.0, 1.0, 2.0, 3.0], [4.0, 5.0, 6.0, 7.0]]


@pytest.mark.parametrize("kind", ["decision", "profile"])
def test_a_decision_of_an_older_reducer_still_decodes(kind):
    """Without the fovea and depth fields (an older reducer, an older recording): x = y = -1, not converged,
    NaN depth; a newer one's NaN depth travels as NaN."""
    d = SAMPLES[kind].to_dict()
    for name in ("x", "y", "converged", "depth_m", "depth_sigma_m"):
        del d[name]
    v = M.KINDS[kind].from_bytes(msgpack.packb(d, use_bin_type=True))
    assert (v.x, v.y, v.converged) == (-1, -1, False)
    assert math.isnan(v.depth_m) and math.isnan(v.depth_sigma_m)
    d["depth_m"] = math.nan
    assert math.isnan(M.KINDS[kind].from_bytes(msgpack.packb(d, use_bin_type=True)).depth_m)
    # a NaN depth survives a round trip equal (every NaN decodes to the one math.nan)
    msg = M.replace(SAMPLES[kind], depth_m=float("nan"), depth_sigma_m=math.nan, converged=False)
    assert M.KINDS[kind].from_bytes(msg.to_bytes()) == M.replace(msg, depth_m=math.nan)


@pytest.mark.parametrize("change,says", [
    (dict(x=math.nan), "fixate.x: not a finite"),
    (dict(y=math.inf), "fixate.x: not a finite"),
    (dict(x="12"), r"fixate: Expected `float`, got `str` - at `\$\.x`"),
    (dict(t_ns=1.5), r"Expected `int`, got `float` - at `\$\.t_ns`"),
    (dict(v=2), r"schema version: .*this build speaks 1"),
    (dict(source="s" * 201), "longer than 200"),
])
def test_fixate_validation_names_the_field(change, says):
    d = SAMPLES["fixate"].to_dict()
    d.update(change)
    with pytest.raises(M.MessageError, match=says):
        M.Fixate.from_bytes(msgpack.packb(d, use_bin_type=True))


def test_arrays_travel_as_binary():
    p = M.Correlation.from_bytes(SAMPLES["correlation"].to_bytes())
    assert p.array().tolist() == [[0, 1, 2, 3], [4, 5, 6, 7]]
    raw = msgpack.unpackb(SAMPLES["correlation"].to_bytes())
    assert isinstance(raw["scores"], bytes)


@pytest.mark.parametrize("change,says", [
    (dict(fovea=bytes(48)), "fovea"),
    (dict(band=bytes(10)), "band"),
    (dict(window=4), "odd"),
    (dict(plan=[["a", 0, 10]]), "covers"),
    (dict(plan=[["a", 0, 10], ["b", 12, 36]]), "partition"),
    (dict(plan=[["a", 0]]), "plan entry"),
    (dict(pan_rad=math.nan), "finite"),
    (dict(focal_px=-1.0), "positive"),
])
def test_frame_validation_names_the_field(change, says):
    d = frame().to_dict()
    d.update(change)
    with pytest.raises(M.MessageError, match=says):
        M.Frame.from_bytes(msgpack.packb(d, use_bin_type=True))


@pytest.mark.parametrize("change,says", [(dict(offset_px=math.nan), "decision.offset_px"),
                                         (dict(pan_rad=math.inf), "decision.pan_rad"), (dict(window=0), "window")])
def test_decision_validation_names_the_field(change, says):
    d = SAMPLES["decision"].to_dict()
    d.update(change)
    with pytest.raises(M.MessageError, match=says):
        M.Decision.from_bytes(msgpack.packb(d, use_bin_type=True))


@pytest.mark.parametrize("kind", list(SAMPLES))
@pytest.mark.parametrize("mutation", ["missing", "wrong-type", "old-schema", "no-schema", "not-a-map", "list"])
def test_wrong_types_and_fields_raise_message_error(kind, mutation):
    d = SAMPLES[kind].to_dict()
    name = next(iter(k for k in d if k != "v"))
    if mutation == "missing":
        del d[name]
    elif mutation == "wrong-type":
        d[name] = {"x": 1}
    elif mutation == "old-schema":
        d["v"] = 0
    elif mutation == "no-schema":
        del d["v"]
    elif mutation == "not-a-map":
        d = "frame"
    else:
        d = [1, 2, 3]
    with pytest.raises(M.MessageError):
        M.KINDS[kind].from_bytes(msgpack.packb(d, use_bin_type=True))


@settings(max_examples=300, deadline=None)
@given(data=st.binary(max_size=300), kind=st.sampled_from(sorted(SAMPLES)))
def test_random_bytes_only_ever_raise_message_error(data, kind):
    try:
        M.KINDS[kind].from_bytes(data)
    except M.MessageError:
        pass


@settings(max_examples=200, deadline=None)
@given(kind=st.sampled_from(sorted(SAMPLES)), key=st.text(max_size=8),
       value=st.one_of(st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1), st.floats(), st.text(max_size=5),
                       st.binary(max_size=5), st.lists(st.integers(-2**63, 2**63 - 1), max_size=3)))
def test_any_field_value_only_ever_raises_message_error(kind, key, value):
    d = SAMPLES[kind].to_dict()
    d[key if key else next(iter(d))] = value
    try:
        M.KINDS[kind].from_bytes(msgpack.packb(d, use_bin_type=True))
    except M.MessageError:
        pass


@pytest.mark.parametrize("field", ["pan_rad", "goal_rad"])
def test_motor_state_with_a_non_finite_pan_is_rejected(field):
    """The capture renders the simulated slave at the reported pan: a NaN must never get that far."""
    d = SAMPLES["motor_state"].to_dict()
    d[field] = math.nan
    with pytest.raises(M.MessageError, match="finite"):
        M.MotorState.from_bytes(msgpack.packb(d, use_bin_type=True))


@pytest.mark.parametrize("kw,says", [({"skew_ns": 600_000_000}, "skew_ns"), ({"skew_ns": -600_000_000}, "skew_ns"),
                                     ({"t_read_ns": 1}, "t_read_ns"), ({"t_read_ns": 10**18 + 2 * 10**9}, "t_read_ns"),
                                     ({"t_read_ns": 10**18 + 4_000_000, "skew_ns": 8_000_000}, "t_read_ns")])
def test_a_frame_whose_times_cannot_be_is_refused(kw, says):
    with pytest.raises(M.MessageError, match=says):
        M.Frame.from_bytes(frame(t_capture_ns=10**18, **kw).to_bytes())
    ok = frame(t_capture_ns=10**18, skew_ns=8_000_000, t_read_ns=10**18 + 66_000_000)
    assert M.Frame.from_bytes(ok.to_bytes()).t_slave_ns == 10**18 + 8_000_000
