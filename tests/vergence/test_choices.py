"""vergence.choices: the one-of-a-few-words settings as StrEnums, each member its word (so settings files, JSON,
msgspec and the CLIs see plain strings), and every place that checks such a setting takes its words from them."""

from __future__ import annotations

import json

import msgspec
import pytest

from vergence import config
from vergence.head import control, depth
from vergence.network import params
from vergence.choices import ControlMode, Gimbal, Photometric, Side, check
from vergence.sim import optics


def test_members_are_their_words_everywhere():
    assert [str(m) for m in Side] == ["left", "right"] and Gimbal.FICK == "fick" and f"{ControlMode.P}" == "p"
    assert json.dumps([Photometric.AFFINE]) == '["affine"]' and msgspec.json.encode(Gimbal.FICK) == b'"fick"'
    assert depth.GIMBALS == optics.GIMBALS == ("helmholtz", "fick") and control.MODES == ("p", "predictive")
    assert params.PHOTOMETRIC == ("none", "affine", "histogram")
    assert "right" in tuple(Side) and "up" not in tuple(Side)


def test_check_and_the_settings_refuse_other_words_naming_them():
    check(Gimbal, "fick", "gimbal")
    with pytest.raises(ValueError, match="gimbal='euler': must be one of helmholtz, fick"):
        check(Gimbal, "euler", "gimbal")
    with pytest.raises(config.ConfigError, match="master"):
        config.from_dict({"capture": {"master": "up"}})
    with pytest.raises(config.ConfigError, match="mode"):
        config.from_dict({"control": {"mode": "pid"}})
    with pytest.raises(ValueError, match="photometric"):
        params.Params(photometric="gamma")
    assert config.from_dict({"capture": {"master": "right"}}).capture.master == "right"
