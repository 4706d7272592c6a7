"""vergence.spec: the one parser of a spec's key=value items: each kind typed and checked, every refusal naming
the key (or the item) and what it wants, and the specs that use it (motion, sim source, ROS 2 source and driver)."""

from __future__ import annotations

import pytest

from vergence.spec import Key, SpecError, parse, split

KEYS = [Key("noise", default=0.0, lo=0.0), Key("seed", "int", 0),
        Key("mode", "choice", "p", choices=("p", "predictive")), Key("reverse", "flag"), Key("joints", "list", ()),
        Key("size", "pair", (640, 480), sep="x", whole=True), Key("window", "range", unit="s"),
        Key("reach", default=0.05, above=0.0, hi=2.0, unit="s"), Key("path", "str"), Key("motion", "spec")]


def test_every_kind_is_typed_and_defaults_fill_the_rest():
    got = parse("noise=2.5:seed=7:mode=predictive:reverse:joints=a, b:size=320x240:window=1.5-3:reach=2:path=/x.png",
                KEYS, "test")
    assert got == {"noise": 2.5, "seed": 7, "mode": "predictive", "reverse": True, "joints": ["a", "b"],
                   "size": (320, 240), "window": (1.5, 3.0), "reach": 2.0, "path": "/x.png", "motion": None}
    assert parse("", KEYS, "test") == {"noise": 0.0, "seed": 0, "mode": "p", "reverse": False, "joints": (),
                                        "size": (640, 480), "window": None, "reach": 0.05, "path": None,
                                        "motion": None}
    assert type(parse("seed=3", KEYS, "t")["seed"]) is int and type(parse("noise=3", KEYS, "t")["noise"]) is float


def test_a_nested_spec_takes_its_own_items_up_to_the_next_key():
    got = parse("motion=sine:z=0.8,amp=0.3,hz=0.5:seed=2", KEYS, "test")
    assert got["motion"] == "sine:z=0.8,amp=0.3,hz=0.5" and got["seed"] == 2
    assert parse("a=1, b = 2,,c=x", [Key("a"), Key("b"), Key("c", "str")], "t", sep=",") == {"a": 1.0, "b": 2.0,
                                                                                            "c": "x"}
    assert split(" a = 1 ::b") == [("a", True, "1"), ("b", False, "")]


@pytest.mark.parametrize("text,says", [
    ("colour=red", "test: unknown key 'colour' (item 'colour=red'); keys: noise=X, seed=X, mode=p|predictive, "
                   "reverse, joints=A,B, size=AxB, window=A-B, reach=X, path=X, motion=X"),
    ("noise", "test: item 'noise' is not key=value"),
    ("reverse=yes", "test: reverse is a flag: give it bare, without a value"),
    ("noise=abc", "test: noise='abc' is not a number"),
    ("noise=nan", "test: noise='nan' is not a number"),
    ("seed=1.5", "test: seed='1.5' is not a whole number"),
    ("noise=-1", "test: noise='-1' must be >= 0"),
    ("reach=0", "test: reach='0' must be > 0 s"),
    ("reach=3", "test: reach='3' must be <= 2 s"),
    ("reach=x", "test: reach='x' is not a number of seconds"),
    ("mode=pid", "test: mode='pid': want one of p, predictive"),
    ("size=320", "test: size='320' must be two numbers as AxB"),
    ("size=3.5x2", "test: size='3.5x2' must be two numbers as AxB"),
    ("window=3-1", "test: window='3-1': the range's start is past its end"),
    ("path=", "test: path= is empty"),
], ids=lambda v: str(v)[:16])
def test_refusals_name_the_key_and_what_it_wants(text, says):
    with pytest.raises(SpecError) as e:
        parse(text, KEYS, "test")
    assert str(e.value).startswith(says)
    assert isinstance(e.value, ValueError)


def test_a_required_key_missing_is_named():
    with pytest.raises(SpecError, match="missing b, c"):
        parse("a=1", [Key("a", required=True), Key("b", required=True), Key("c", required=True)], "t", sep=",")
    with pytest.raises(ValueError, match="kind 'number'"):
        Key("x", "number")


def test_the_specs_that_use_it_refuse_through_it():
    from vergence.io.images import SourceError
    from vergence.motors.base import PortError
    from vergence.motors.ros2 import parse_port
    from vergence.ros2.source import parse_spec
    from vergence.sim import Rig
    from vergence.sim.motion import parse_motion
    from vergence.io.sources import open_source

    assert parse_spec("/l,/r:slop=0.01") == ("/l", "/r", {"slop": 0.01, "wait": 10.0, "skew": 2.0})
    with pytest.raises(SourceError, match=r"source ros2: wait='-1' must be >= 0 s"):
        parse_spec("/l,/r:wait=-1")
    assert parse_port("ctl:joints=t,slave_pan:mode=trajectory")["joints"] == ["t", "slave_pan"]
    with pytest.raises(PortError, match="ros2 driver: mode='velocity': want one of forward, trajectory"):
        parse_port("ctl:mode=velocity")
    assert parse_motion("ramp:z0=1,z1=0.5,speed=0.2")["speed"] == 0.2
    with pytest.raises(ValueError, match=r"motion 'ramp:z0=1,z1=2': missing speed"):
        parse_motion("ramp:z0=1,z1=2")
    with pytest.raises(ValueError, match="sim source: unknown key 'colour'"):
        Rig.from_spec("colour=red")
    src = open_source("sim:motion=still:z=0.7:latency=0.03:stamps=no:size=160x120")
    assert src.timing.latency_s == 0.03 and not src.stamps and src.size == (160, 120)
    with pytest.raises(SourceError, match="sim source: stamps='maybe': want one of yes, no"):
        open_source("sim:stamps=maybe")
