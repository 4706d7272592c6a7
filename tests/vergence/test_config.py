"""Settings (vergence.config): a TOML file read into typed settings; a bad value, an unknown key or an
unreadable file is an error naming the field or the file."""

from __future__ import annotations

import dataclasses
import typing

import pytest

from vergence.config import ConfigError, Settings, from_dict, load
from vergence.ranges import numeric_fields


def test_settings_from_toml(tmp_path):
    p = tmp_path / "v.toml"
    p.write_text('rig = "left-head"\n[network]\nwindow = 21\nfaithful = 1\n')
    with pytest.raises(ConfigError, match=r"network\.faithful: unknown setting"):
        load(p)
    p.write_text('rig = "left-head"\n[network]\nwindow = 21\n[control]\ngain = 0.5\n')
    s = load(p)
    assert (s.rig, s.network.window, s.control.gain) == ("left-head", 21, 0.5)
    assert s.network.vsearch == Settings().network.vsearch


@pytest.mark.parametrize("data,says", [
    ({"network": {"window": "big"}}, r"network\.window: expected `int`, got `str`"),
    ({"capture": {"rate_hz": True}}, r"capture\.rate_hz: expected `float`, got `bool`"),
    ({"actuator": {"motor": {"retries": 0}}}, r"actuator\.motor\.retries: must be a whole number from 1 to 100, got 0"),
    ({"rig": {"gimbal": "x"}}, r"rig\.gimbal='x': must be helmholtz or fick"),
    ({"control": 3}, "control: expected a table"),
    ({"supervise": {"heartbeat_s": 0}}, r"supervise\.heartbeat_s: must be above 0 and at most 3600 \(seconds\), got 0"),
    ({"supervise": {"stall_s": 1.0}}, r"supervise\.stall_s: must exceed heartbeat_s \(1\.5\) or be 0, got 1\.0"),
    ({"supervise": {"heartbeat": 1}}, r"supervise\.heartbeat: unknown setting; known here: heartbeat_s, "
                                      "restart_max_s, restart_s, stall_s, start_grace_s"),
    ({"supervise": {"restart_max_s": 0.1}}, r"supervise\.restart_max_s: must be at least restart_s \(0\.2\), "
                                            r"got 0\.1"),
    ({"actuator": {"motor": {"silent_s": -1}}}, r"actuator\.motor\.silent_s: must be from 0 to 3600, got -1"),
    ({"colour": 1}, "colour: unknown setting; known here: actuator, camera, capture, control, limits, network, "
                    "reducer, rig, ros2, supervise$"),
    (5, "settings: expected a table, got `int`"),
    ({"control": {"min_deg": -20}}, r"control\.min_deg: moved to \[actuator\.motor\] min_deg"),
    ({"control": {"gain": 1, "max_step_deg": 3}}, r"control\.max_step_deg: moved to \[actuator\.motor\] max_step_deg"),
    ({"control": {"gain": 2.0}}, r"control\.gain: must be above 0 and below 2 \(at 2 and above"),
    ({"camera": {"latency_s": 1.5}}, r"camera\.latency_s: must be from 0 to 1 \(seconds\), got 1\.5"),
    ({"camera": {"skew_s": "x"}}, r"camera\.skew_s: expected `float`, got `str`"),
    ({"ros2": {"look_at": "yes"}},
     r"ros2\.look_at: expected `bool` \(true or false; left out: the default\), got `str`"),
    ({"ros2": {"discovery": "lan"}}, r"ros2\.discovery: must be one of localhost, subnet, environment, got 'lan'"),
    ({"ros2": {"lookat": True}}, r"ros2\.lookat: unknown setting; known here: discovery, look_at$"),
])
def test_bad_settings_name_the_field(data, says):
    with pytest.raises(ConfigError, match=says):
        from_dict(data)


def test_old_settings_with_control_limits_say_where_they_live_now(tmp_path):
    """The pan limits moved from [control] to [actuator.motor]: a file of before says so, naming the field
    (an error, not a warning: two values for one limit would leave the reader guessing which one holds)."""
    p = tmp_path / "old.toml"
    p.write_text("[control]\ngain = 1.0\nmin_deg = -30.0\nmax_deg = 30.0\n[actuator.motor]\nid = 1\n")
    with pytest.raises(ConfigError, match=r"old\.toml: control\.min_deg: moved to \[actuator\.motor\] min_deg"):
        load(p)
    p.write_text("[control]\ngain = 1.0\n[actuator.motor]\nmin_deg = -30.0\nmax_deg = 30.0\n")
    assert (load(p).actuator.motor.min_deg, load(p).actuator.motor.max_deg) == (-30.0, 30.0)


def test_ros2_settings_look_at_unset_true_or_false(tmp_path):
    """[ros2] look_at: left out, None (the bridge decides: on unless a deployed ACL is in force); true or false as
    written. discovery: localhost unless widened."""
    p = tmp_path / "v.toml"
    p.write_text("[ros2]\ndiscovery = \"subnet\"\n")
    assert (load(p).ros2.look_at, load(p).ros2.discovery) == (None, "subnet")
    for text, want in (("true", True), ("false", False)):
        p.write_text(f"[ros2]\nlook_at = {text}\n")
        assert (load(p).ros2.look_at, load(p).ros2.discovery) == (want, "localhost")
    assert (Settings().ros2.look_at, Settings().ros2.discovery) == (None, "localhost")


def test_unreadable_or_bad_toml_says_which_file(tmp_path):
    with pytest.raises(ConfigError, match="cannot read settings file"):
        load(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("rig = \n")
    with pytest.raises(ConfigError, match="bad.toml: not valid TOML"):
        load(bad)


def _tables(cls=Settings, path=()):
    """(TOML path, settings class) of every table, nested ones too ([actuator.motor]); Settings' geometry is [rig]."""
    for f in dataclasses.fields(cls):
        t = typing.get_type_hints(cls)[f.name]
        if dataclasses.is_dataclass(t):
            here = path + ("rig" if cls is Settings and f.name == "geometry" else f.name,)
            yield ".".join(here), t
            yield from _tables(t, here)


def _nest(path: str, value) -> dict:
    out = value
    for part in reversed(path.split(".")):
        out = {part: out}
    return out


TABLES = list(_tables())
NUMBERS = [(table, cls, name) for table, cls in TABLES for name in numeric_fields(cls)]


def test_every_numeric_setting_has_a_range():
    """Each int or float field of every settings table is in its class's RANGES (a new number without a range
    fails here), and every default is within its range."""
    assert {t for t, _ in TABLES} >= {"rig", "network", "capture", "camera", "reducer", "control", "actuator",
                                      "actuator.motor", "limits", "supervise"}
    assert len(NUMBERS) > 60
    for table, cls, name in NUMBERS:
        assert name in getattr(cls, "RANGES", {}), f"{table}.{name} has no range ({cls.__name__}.RANGES)"
        assert getattr(cls(), name) in cls.RANGES[name], f"{table}.{name}'s default is outside its range"


@pytest.mark.parametrize("table,cls,name", NUMBERS, ids=[f"{t}.{n}" for t, _, n in NUMBERS])
def test_a_setting_out_of_its_range_is_refused_naming_table_key_and_range(table, cls, name):
    r = cls.RANGES[name]
    assert r.outside()
    for bad in r.outside():
        with pytest.raises(ConfigError) as e:
            from_dict(_nest(f"{table}.{name}", bad))
        assert str(e.value).startswith(f"{table}.{name}: must be {r.text()}, got "), str(e.value)


def test_a_settings_file_with_a_negative_rate_is_refused_naming_capture_rate_hz(tmp_path):
    p = tmp_path / "v.toml"
    p.write_text("[capture]\nrate_hz = -5\n")
    with pytest.raises(ConfigError, match=r"v\.toml: capture\.rate_hz: must be from 0 to 1000 .*got -5"):
        load(p)
    p.write_text("[capture]\nrate_hz = nan\n")
    with pytest.raises(ConfigError, match=r"capture\.rate_hz: must be .*got nan"):
        load(p)


@pytest.mark.parametrize("text", ['rig = "x"\n[geometry]\nbaseline_m = 0.1\n', "[geometry]\nbaseline_m = 0.1\n",
                                  "[rig]\nbaseline_m = 0.1\n[geometry]\nbaseline_m = 0.2\n"])
def test_geometry_is_not_a_second_name_of_the_rig_table(tmp_path, text):
    """One name per table: [rig] (Settings.geometry is the field it fills, not a table's name)."""
    p = tmp_path / "v.toml"
    p.write_text(text)
    with pytest.raises(ConfigError, match=r"geometry: unknown setting; the rig's geometry is the \[rig\] table"):
        load(p)
    p.write_text("[rig]\nbaseline_m = 0.1\n")
    assert load(p).geometry.baseline_m == 0.1


def test_docs_settings_lists_every_range():
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[2] / "docs" / "SETTINGS.md").read_text()
    rows = {line.split(" | ")[0]: line for line in doc.splitlines() if line.startswith("| `")}
    for table, cls, name in NUMBERS:
        row = rows.get(f"| `{table}.{name}`", "")
        assert row.endswith(f" | {cls.RANGES[name].text()} |"), f"docs/SETTINGS.md: {table}.{name}: {row!r}"
