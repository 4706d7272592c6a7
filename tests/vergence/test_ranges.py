"""vergence.ranges: the one range check of every numeric setting, its message naming the setting and the range."""

from __future__ import annotations

import math

import pytest

from vergence.ranges import Range, check, numeric_fields


@pytest.mark.parametrize("r,inside,outside,text", [
    (Range(0, 1000, note="0: as fast as the source"), [0, 0.5, 1000], [-1e-9, 1000.001, math.nan, math.inf],
     "from 0 to 1000 (0: as fast as the source)"),
    (Range(0, 10, lo_open=True), [1e-9, 10], [0, -1, 10.1], "above 0 and at most 10"),
    (Range(0, 2, lo_open=True, hi_open=True), [1, 1.999], [0, 2], "above 0 and below 2"),
    (Range(1, None, integer=True), [1, 10**9], [0, 1.5, True], "a whole number at least 1"),
    (Range(), [-1e300, 0], [math.nan, -math.inf], "a finite number"),
])
def test_a_range_says_what_it_holds(r, inside, outside, text):
    assert all(v in r for v in inside)
    assert not any(v in r for v in outside)
    assert r.text() == text
    assert not any(v in r for v in r.outside())


def test_check_names_the_first_field_out_of_its_range():
    class S:
        rate_hz, width = -5.0, 3

    check(S, {"width": Range(1, 10, integer=True)})
    with pytest.raises(ValueError, match=r"^rate_hz: must be from 0 to 1000, got -5\.0$"):
        check(S, {"width": Range(1, 10, integer=True), "rate_hz": Range(0, 1000)})


def test_numeric_fields_are_the_ints_and_floats():
    from dataclasses import dataclass

    @dataclass
    class D:
        a: int = 1
        b: float = 2.0
        c: bool = True
        d: str = ""

    assert numeric_fields(D) == ["a", "b"]
