"""`vergence router`: a Zenoh router in Python (mode "router"), listening on tcp/127.0.0.1:7447 by default."""

from __future__ import annotations

import argparse
import logging
import sys

import zenoh

from services.runtime import session

log = logging.getLogger("vergence.router")


def configure(p: argparse.ArgumentParser) -> None:
    session.add_options(p, mode="router")


def main(conf, stop: session.Stop, ready=None) -> None:
    """Run a router until stop is set; ready (an Event) is set once it listens."""
    with session.open_session(conf) as s:
        log.info("router %s listening on %s", s.zid(), conf.get_json("listen/endpoints"))
        if ready is not None:
            ready.set()
        while not stop.wait(0.5):
            pass


def router_config(args: argparse.Namespace):
    listen = args.listen
    if listen is None and not args.zenoh_config:
        listen = [session.DEFAULT_ROUTER]
    return session.zenoh_config("router", args.connect or [], listen, args.zenoh_config)


def run(args: argparse.Namespace) -> int:
    stop = session.Stop()
    conf = router_config(args)
    try:
        main(conf, stop)
    except zenoh.ZError as e:
        where = conf.get_json("listen/endpoints")
        hint = (" Another router (or `vergence up`) is probably running there: stop it, or pick another port "
                "with --listen." if "in use" in str(e) else "")
        print(f"vergence router: cannot start on {where}: {str(e).split(' at /')[0]}.{hint}", file=sys.stderr)
        return 2
    return 0
