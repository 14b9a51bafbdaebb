"""``stack-train SUBCOMMAND ...``: a thin dispatcher.

Each subcommand is a module with ``add_arguments(parser)`` and ``main(args) -> int`` (argument
parsing there, the work in plain functions taking a config). To add one, add a line to
:data:`SUBCOMMANDS`; keep heavy imports (torch, ...) inside the module's ``main`` so that
``stack-train --help`` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from . import EXIT_BAD_INPUT, PROG, InputError

#: subcommand -> module (``add_arguments(parser)``, ``main(args) -> int``)
SUBCOMMANDS: dict[str, str] = {
    "qlearn": "stack.train.qlearn",
    "drl": "stack.train.drl",
    "fuzzy": "stack.train.fuzzy",
}


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit 2
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        sys.exit(EXIT_BAD_INPUT)


def parser() -> argparse.ArgumentParser:
    ap = _Parser(prog=PROG, description="Offline training and planning experiments.")
    sub = ap.add_subparsers(dest="command", required=True, parser_class=_Parser, metavar="COMMAND")
    for name, modname in SUBCOMMANDS.items():
        mod = importlib.import_module(modname)
        doc = (mod.__doc__ or "").strip().splitlines()
        p = sub.add_parser(name, help=doc[0] if doc else None, description=mod.__doc__,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        mod.add_arguments(p)
        p.set_defaults(_module=mod, _parser=p)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        return int(args._module.main(args) or 0)
    except InputError as e:
        print(f"{PROG}: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
