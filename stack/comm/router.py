"""The fleet's Zenoh router: ``python -m stack.comm.router --listen tcp/127.0.0.1:7447``.

A zenoh session in router mode (multicast scouting off, explicit listen endpoints); it
runs until SIGINT/SIGTERM. ``stack-fleet run`` starts one on loopback per run.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading

from .session import ConfigFileError, EndpointError, SessionConfig, SessionError, open_session


def main(listen: list[str], config_file: str | None = None, allow_remote: bool = False,
         connect: list[str] | None = None) -> int:
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    cfg = SessionConfig(mode="router", listen=listen, connect=connect or [], config_file=config_file,
                        allow_remote=allow_remote)
    with open_session(cfg):
        print(f"router: listening on {', '.join(listen)}", flush=True)
        stop.wait()
    return 0


def cli(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="stack-router", description=__doc__.splitlines()[0])
    ap.add_argument("--listen", action="append", required=True, help="endpoint, e.g. tcp/127.0.0.1:7447 (repeatable)")
    ap.add_argument("--connect", action="append", default=[], help="another router to mesh with (repeatable)")
    ap.add_argument("--config", help="zenoh json5 config layered under ours (deploy/)")
    ap.add_argument("--allow-remote", action="store_true", help="accept endpoints off loopback (multi-host fleets)")
    a = ap.parse_args(argv)
    try:
        return main(a.listen, a.config, a.allow_remote, a.connect)
    except (EndpointError, ConfigFileError) as e:
        print(f"stack-router: {e}", file=sys.stderr)
        return 2
    except SessionError as e:
        print(f"stack-router: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(cli())
