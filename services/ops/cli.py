"""The `vergence` command: each sub-command lives in its own module, imported only when it runs, so that
`vergence match` never loads zenoh. A module provides configure(parser) and run(args) -> exit code."""

from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

from services.runtime import heartbeat

# name: (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "match": ("services.offline.match", "decide where the master fovea lies in the slave image (no Zenoh)"),
    "accuracy": ("services.offline.accuracy", "accuracy on a pair with a ground-truth disparity (no Zenoh)"),
    "sim": ("services.offline.sim", "closed loop on the simulated rig, in one process (no Zenoh)"),
    "bench": ("services.offline.bench", "benchmarks: kernel, match, messages, tracking, pipeline"),
    "up": ("services.ops.up", "an embedded router and every process on this machine"),
    "router": ("services.ops.router", "a Zenoh router"),
    "capture": ("services.pipeline.capture", "read a stereo source and publish frames"),
    "worker": ("services.pipeline.worker", "compute layer 4 for a shard of each frame"),
    "reducer": ("services.pipeline.reducer", "gather shards, decide, publish profile and command"),
    "actuator": ("services.pipeline.actuator", "drive the slave pan motor"),
    "fixate": ("services.clients.fixate", "move the running capture's fovea to a master pixel"),
    "latency": ("services.clients.latency", "measure the camera's exposure-to-read latency on the running head"),
    "calibrate": ("services.clients.calibrate", "measure the running head: direction, focal length, latency, pan zero"),
    "monitor": ("services.observe.monitor", "live view of the correlation topics"),
    "record": ("services.observe.record", "record every vergence/<rig>/** message to a file"),
    "replay": ("services.clients.replay", "publish a recording again"),
    "view": ("services.observe.view", "the rig's cockpit in Rerun: images, boxes, profile, pans (the [view] extra)"),
    "ros2": ("services.bridges.ros2", "the rig as a ROS 2 node: joint states, fixation, look_at (the [ros2] extra)"),
}


def version() -> str:
    """The installed distribution's version, else (a source tree not installed) the package's __version__."""
    from importlib import metadata

    try:
        return metadata.version("vergence")
    except metadata.PackageNotFoundError:
        import vergence

        return vergence.__version__


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="vergence", description="Dynamic vergence control for active stereo vision")
    p.add_argument("--version", action="store_true", help="print `vergence VERSION` and exit")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for name, (modname, help_) in COMMANDS.items():
        sp = sub.add_parser(name, help=help_, description=help_)
        if name == only:
            importlib.import_module(modname).configure(sp)
    return p


def main(argv: list[str] | None = None) -> int:
    try:  # Ctrl-C, or `vergence up` stopping a child still starting (from its first beat on): 130, no traceback
        # first: a child of `vergence up` beats while it imports and compiles (services/runtime/heartbeat.py)
        heartbeat.start()
        argv = sys.argv[1:] if argv is None else argv
        name = next((a for a in argv if not a.startswith("-")), None)
        if "--version" in argv[:argv.index(name) if name is not None else len(argv)]:
            print(f"vergence {version()}")
            return 0
        if name not in COMMANDS:
            build_parser().print_help()
            return 0 if name is None and any(a in ("-h", "--help") for a in argv) else 2
        args = build_parser(name).parse_args(argv)
        mod = importlib.import_module(COMMANDS[name][0])
    except KeyboardInterrupt:
        return 130

    try:
        logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s", stream=sys.stderr)
        code = int(mod.run(args) or 0)
        sys.stdout.flush()  # a closed pipe shows here, not in the interpreter's own flush at exit
        return code
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        return _closed_pipe()
    except Exception as e:
        # no router within a client's wait (services.runtime.session.NoRouter): its one line, exit 1; looked up
        # in sys.modules, as below, so that a command without zenoh never imports it
        session = sys.modules.get("services.runtime.session")
        if session is not None and isinstance(e, session.NoRouter):
            print(f"vergence {name}: {e}", file=sys.stderr)
            return 1
        # a settings file or value that is wrong: the message names the field. Looked up only if the command
        # loaded the settings: importing vergence.config loads numpy and msgspec, which `vergence router` does
        # without (a router restarted by `vergence up` is back that much sooner)
        config = sys.modules.get("vergence.config")
        if config is not None and isinstance(e, config.ConfigError):
            print(f"vergence {name}: {e}", file=sys.stderr)
            return 2
        raise


def _closed_pipe() -> int:
    """stdout's reader went away (`vergence sim | head`): end quietly, no traceback, with 141 (128 + SIGPIPE),
    the status a shell reports for a command killed by SIGPIPE, as `yes | head` gives. stdout is pointed at
    /dev/null first: the interpreter's flush of it at exit would raise again (Python's documented recipe)."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # no real stdout (a test's): nothing to flush at exit either
        pass
    return 141


if __name__ == "__main__":
    sys.exit(main())
