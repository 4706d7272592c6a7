"""Settings (vergence.config): a TOML file read into typed settings; a bad value, an unknown key or an
unreadable file is an error naming the field or the file."""

from __future__ import annotations

import pytest

from vergence.config import ConfigError, Settings, from_dict, load


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
    ({"actuator": {"motor": {"retries": 0}}}, r"actuator\.motor: retries must be >= 1"),
    ({"rig": {"gimbal": "x"}}, r"rig: gimbal='x': must be helmholtz or fick"),
    ({"control": 3}, "control: expected a table"),
    ({"supervise": {"heartbeat_s": 0}}, r"supervise: heartbeat_s must be a positive number of seconds, got 0"),
    ({"supervise": {"stall_s": 1.0}}, r"supervise: stall_s \(1\.0\) must exceed heartbeat_s \(1\.5\), or be 0"),
    ({"supervise": {"heartbeat": 1}}, r"supervise\.heartbeat: unknown setting; known here: heartbeat_s, "
                                      "stall_s, start_grace_s"),
    ({"actuator": {"motor": {"silent_s": -1}}}, r"actuator\.motor: silent_s must be >= 0, got -1"),
    ({"colour": 1}, "colour: unknown setting; known here: actuator, camera, capture, control, geometry"),
    (5, "settings: expected a table, got `int`"),
    ({"control": {"min_deg": -20}}, r"control\.min_deg: moved to \[actuator\.motor\] min_deg"),
    ({"control": {"gain": 1, "max_step_deg": 3}}, r"control\.max_step_deg: moved to \[actuator\.motor\] max_step_deg"),
    ({"control": {"gain": 2.0}}, r"control: gain=2.0: must be above 0 and below 2"),
    ({"camera": {"latency_s": 1.5}}, r"camera: latency_s=1.5: must be a number of seconds from 0 to 1"),
    ({"camera": {"skew_s": "x"}}, r"camera\.skew_s: expected `float`, got `str`"),
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


def test_unreadable_or_bad_toml_says_which_file(tmp_path):
    with pytest.raises(ConfigError, match="cannot read settings file"):
        load(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("rig = \n")
    with pytest.raises(ConfigError, match="bad.toml: not valid TOML"):
        load(bad)
