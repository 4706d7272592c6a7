"""vergence.wire.keys: every key expression built and parsed in one place. The literal keys below are the wire
format (what a router, an ACL or another implementation sees): they must not change."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh

from vergence.wire import keys

DEPLOY = Path(__file__).resolve().parents[3] / "deploy"

# (built, the key on the wire, kind, rest, role, ident)
CASES = [
    (keys.frame("head"), "vergence/head/frame", "frame", "frame", "", ""),
    (keys.preview("head"), "vergence/head/preview", "preview", "preview", "", ""),
    (keys.fixate("head"), "vergence/head/fixate", "fixate", "fixate", "", ""),
    (keys.hold("head"), "vergence/head/hold", "hold", "hold", "", ""),
    (keys.decision("head"), "vergence/head/decision", "decision", "decision", "", ""),
    (keys.profile("head"), "vergence/head/profile", "profile", "profile", "", ""),
    (keys.command("left"), "vergence/left/command", "command", "command", "", ""),
    (keys.workers("head"), "vergence/head/workers", "workers", "workers", "", ""),
    (keys.motor_state("left"), "vergence/left/motor_state", "motor_state", "motor_state", "", ""),
    (keys.correlation("head", "h-12"), "vergence/head/correlation/h-12", "correlation", "correlation/h-12",
     "", "h-12"),
    (keys.status("head", "reducer", "r-3"), "vergence/head/status/reducer/r-3", "status", "status/reducer/r-3",
     "reducer", "r-3"),
    (keys.alive("head", "worker", "h-12"), "vergence/head/alive/worker/h-12", "alive", "alive/worker/h-12",
     "worker", "h-12"),
]


@pytest.mark.parametrize("built,wire,kind,rest,role,ident", CASES, ids=[c[2] for c in CASES])
def test_build_parse_round_trip(built, wire, kind, rest, role, ident):
    assert built == wire
    k = keys.parse(wire)
    assert k == (wire.split("/")[1], kind, rest)
    assert (k.kind, k.role, k.ident) == (kind, role, ident)
    assert keys.kind_of(rest) == kind
    assert k.under("replay") == "vergence/replay/" + rest and keys.parse(k.under("replay")).kind == kind


def test_every_kind_has_a_case():
    assert sorted({c[2] for c in CASES}) == sorted(keys.KINDS)
    assert [keys.key("head", k) for k in keys.SIMPLE] == [f"vergence/head/{k}" for k in keys.SIMPLE]


def test_wildcards_subscribers_use():
    assert keys.everything("head") == "vergence/head/**"
    assert keys.alives("head") == "vergence/head/alive/**"
    assert keys.alives("head", "worker") == "vergence/head/alive/worker/*"
    assert keys.correlations("head") == "vergence/head/correlation/*"
    assert keys.statuses("head") == "vergence/head/status/**"
    assert keys.prefix("head") == "vergence/head/" and keys.REPLAY_RIG == "replay"
    assert keys.fixate("*") == "vergence/*/fixate"  # a put to every rig's capture
    for w in (keys.everything("head"), keys.alives("head"), keys.alives("head", "worker"),
              keys.correlations("head"), keys.statuses("head")):
        zenoh.KeyExpr(w)  # valid key expressions
    assert zenoh.KeyExpr(keys.correlations("head")).includes(zenoh.KeyExpr(keys.correlation("head", "w-1")))
    assert zenoh.KeyExpr(keys.statuses("head")).includes(zenoh.KeyExpr(keys.status("head", "worker", "w-1")))
    assert not zenoh.KeyExpr(keys.everything("head")).includes(zenoh.KeyExpr(keys.frame("other")))


@pytest.mark.parametrize("key", [
    "other/head/frame", "vergence", "vergence/head", "vergence/head/", "vergence//frame", "vergence/head/whatever",
    "vergence/head/frame/x", "vergence/head/motor", "vergence/head/correlation", "vergence/head/correlation/",
    "vergence/head/status/worker", "vergence/head/alive/worker", "vergence/head/alive//x", "",
], ids=lambda k: k or "empty")
def test_a_bad_key_parses_to_none(key):
    assert keys.parse(key) is None


def test_a_name_with_more_chunks_is_kept_whole():
    """A claim from the wire (no service builds one): the callers get all of it and decide."""
    k = keys.parse("vergence/head/alive/worker/a/b")
    assert (k.kind, k.role, k.ident) == ("alive", "worker", "a/b")
    assert keys.parse("vergence/head/correlation/a/b").ident == "a/b"


@pytest.mark.parametrize("build", [
    lambda: keys.frame(""), lambda: keys.frame("a/b"), lambda: keys.correlation("head", ""),
    lambda: keys.status("head", "worker/x", "1"), lambda: keys.alive("head", "worker", "a/b"),
    lambda: keys.key("head", "correlation"), lambda: keys.key("head", "nonsense"), lambda: keys.frame(None),
], ids=["empty-rig", "slash-rig", "empty-worker", "slash-role", "slash-id", "named-kind", "unknown", "none"])
def test_a_bad_part_raises_clearly(build):
    with pytest.raises(ValueError, match="key chunk|not one of"):
        build()


# what each deployed role publishes (put) and declares (liveliness token), as the services build it (the
# monitor and the cockpit only subscribe)
def _role_keys(rig: str) -> dict[str, list[str]]:
    r = keys.REPLAY_RIG
    return {
        "capture": [keys.frame(rig), keys.preview(rig), keys.status(rig, "capture", "c-1"),
                    keys.alive(rig, "capture", "c-1")],
        "worker": [keys.correlation(rig, "w-1"), keys.status(rig, "worker", "w-1"), keys.alive(rig, "worker", "w-1")],
        "reducer": [keys.decision(rig), keys.profile(rig), keys.command(rig), keys.workers(rig),
                    keys.status(rig, "reducer", "r-1"), keys.alive(rig, "reducer", "r-1")],
        "actuator": [keys.motor_state(rig), keys.alive(rig, "actuator", "a-1")],
        "monitor": [keys.alive(rig, "record", "m-1")],  # the recorder runs as the monitor role
        "replay": [keys.frame(r), keys.preview(r), keys.correlation(r, "w-1"), keys.decision(r), keys.profile(r),
                   keys.alive(r, "replay", "p-1")],
        "fixate": [keys.fixate(rig)],
    }


@pytest.mark.parametrize("transport", ["tls", "tcp"])
def test_the_acl_allows_every_key_a_role_builds_and_only_its_own(transport):
    acl = json.loads(zenoh.Config.from_file(str(DEPLOY / f"router-{transport}.json5")).get_json("access_control"))
    rules = {r["id"]: r for r in acl["rules"]}

    def allowed(policy: str) -> list[zenoh.KeyExpr]:
        p = next(p for p in acl["policies"] if p["id"] == policy)
        return [zenoh.KeyExpr(k) for r in p["rules"] if "ingress" in rules[r]["flows"]
                and {"put", "liveliness_token"} & set(rules[r]["messages"]) for k in rules[r]["key_exprs"]]

    roles = _role_keys("head")
    for role, built in roles.items():
        ok = allowed(role)
        for k in built:
            assert any(a.includes(zenoh.KeyExpr(k)) for a in ok), f"{role} may not publish {k}"
        # and none of another role's keys on the live rig (any role that puts frames may put them under the
        # replay rig too: the capture's rule is vergence/*/frame)
        for other, theirs in roles.items():
            for k in {k for k in theirs if k.startswith(keys.prefix("head"))} - set(built):
                assert not any(a.includes(zenoh.KeyExpr(k)) for a in ok), f"{role} may publish {other}'s {k}"


def test_a_message_kind_is_its_key_kind():
    """One name per concept (docs/NAMES.md): each message's KIND is the kind of the key it travels on."""
    from vergence.wire.messages import KINDS as MESSAGE_KINDS

    assert set(MESSAGE_KINDS) <= set(keys.KINDS)
    for kind, cls in MESSAGE_KINDS.items():
        assert cls.KIND == kind
        key = keys.correlation("head", "w-1") if kind == keys.CORRELATION else keys.key("head", kind)
        assert keys.parse(key).kind == kind, key
    assert set(keys.KINDS) - set(MESSAGE_KINDS) == {"workers", "status", "alive"}  # JSON, JSON, liveliness
