"""The command line's shared value types (services/runtime/args.py): a point, a positive number, and a number
within a range, whose refusal names the option and the range and exits 2 before anything starts (issue #28).
Every numeric option of every command has such a type."""

from __future__ import annotations

import argparse
import time

import pytest

from procs import run
from services.ops import cli
from services.runtime.args import PORT, master_point, number, pixel, positive, whole


def test_number_takes_its_range_and_refuses_the_rest_naming_it():
    rate = number(0, 1000, note="0: as fast as possible")
    assert (rate("0"), rate("30"), rate("1000"), rate("2.5e2")) == (0.0, 30.0, 1000.0, 250.0)
    for bad in ("-5", "1000.5", "nan", "inf", "x", ""):
        with pytest.raises(argparse.ArgumentTypeError,
                           match=r"^must be from 0 to 1000 \(0: as fast as possible\), got '.*'$"):
            rate(bad)
    wait = number(0, None, lo_open=True)
    assert wait("0.1") == 0.1
    with pytest.raises(argparse.ArgumentTypeError, match=r"^must be above 0, got '0'$"):
        wait("0")
    n = whole(1, 64)
    assert n("3") == 3 and isinstance(n("3"), int)
    for bad in ("0", "65", "2.0", "two"):
        with pytest.raises(argparse.ArgumentTypeError, match=r"^must be a whole number from 1 to 64, got "):
            n(bad)
    assert PORT("9090") == 9090
    with pytest.raises(argparse.ArgumentTypeError, match="from 1 to 65535"):
        PORT("70000")


def test_the_point_and_positive_types():
    assert pixel("3,4") == (3, 4) and master_point("3.5,4") == (3.5, 4.0) and positive("0.5") == 0.5
    for t, bad in ((pixel, "3"), (master_point, "nan,1"), (positive, "0"), (positive, "-1")):
        with pytest.raises(argparse.ArgumentTypeError):
            t(bad)


def _actions(parser: argparse.ArgumentParser, where: str):
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for name, sub in a.choices.items():
                yield from _actions(sub, f"{where} {name}")
        else:
            yield where, a


def _commands():
    out = []
    for name in cli.COMMANDS:
        try:
            p = cli.build_parser(name)
        except ModuleNotFoundError:  # an optional extra not installed here
            continue
        sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction)).choices[name]
        out += list(_actions(sub, name))
    return out


def test_every_numeric_option_of_every_command_checks_its_range():
    """No option is a bare int or float (a new one fails here): each has a type with a range (number, whole,
    positive, PORT, or a parser of its own)."""
    acts = _commands()
    assert len({w.split()[0] for w, _ in acts}) >= 15
    bare = [f"vergence {w} {a.option_strings[0] if a.option_strings else a.dest}" for w, a in acts
            if a.type in (int, float)]
    assert bare == []
    ranged = {f"{w} {a.option_strings[0]}" for w, a in acts if a.option_strings and hasattr(a.type, "range")}
    assert {"up --rate", "up --workers", "capture --rate", "reducer --deadline-ms", "actuator --state-hz",
            "fixate --wait", "record --duration", "sim --rate", "bench pipeline --workers"} <= ranged


@pytest.mark.parametrize("argv,says", [
    (["capture", "--rate", "-5"], "argument --rate: must be from 0 to 1000 (0: as fast as possible), got '-5'"),
    (["up", "--rate", "-5"], "argument --rate: must be from 0 to 1000"),
    (["up", "--workers", "0"], "argument --workers/-n: must be a whole number from 1 to 64, got '0'"),
    (["up", "--driver", "foo"], "argument --driver: invalid choice: 'foo' (choose from 'sim', 'dynamixel', 'line'"),
    (["reducer", "--deadline-ms", "0"], "argument --deadline-ms: must be above 0 and at most 10000, got '0'"),
    (["actuator", "--state-hz", "-1"], "argument --state-hz: must be above 0 and at most 1000"),
    (["actuator", "--baud", "0"], "argument --baud: must be a whole number from 1200 to 10000000"),
    (["fixate", "1,2", "--wait", "-1"], "argument --wait: must be from 0 to 3600 (0: only send), got '-1'"),
    (["record", "x.mcap", "--duration", "0"], "argument --duration: must be above 0, got '0'"),
    (["replay", "x.mcap", "--speed", "-1"], "argument --speed: must be from 0 to 1000"),
    (["latency", "--amplitude", "5"], "argument --amplitude: must be above 0 and at most 1"),
    (["monitor", "--refresh", "0"], "argument --refresh: must be above 0 and at most 60"),
    (["sim", "--rate", "0"], "argument --rate: must be above 0 and at most 1000, got '0'"),
    (["sim", "--frames", "-1"], "argument --frames: must be a whole number from 0 to 10000000"),
    (["match", "a", "b", "--window", "0"], "argument --window: must be a whole number from 1 to 501"),
    (["bench", "pipeline", "--workers", "1", "0"], "argument --workers: must be a whole number from 1 to 64"),
    (["bench", "kernel", "--repeats", "0"], "argument --repeats: must be a whole number from 1"),
])
def test_a_number_out_of_range_exits_2_naming_the_option_and_the_range(argv, says, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert says in err, err
    assert err.strip().splitlines()[-1].startswith(f"vergence {argv[0]}")  # one line says it, after the usage


@pytest.mark.slow
def test_capture_with_a_negative_rate_is_refused_at_once_by_the_real_command():
    t0 = time.monotonic()
    r = run("capture", "--rate", "-5", "--connect", "tcp/127.0.0.1:9", timeout=30)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines()[-1] == ("vergence capture: error: argument --rate: must be from 0 to 1000 "
                                                 "(0: as fast as possible), got '-5'")
    assert time.monotonic() - t0 < 10 and "Traceback" not in r.stderr
