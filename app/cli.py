"""`procam` command line. Every module in app/commands/ is one sub-command: it defines NAME, HELP,
`add_arguments(parser)` and `run(args) -> int`. Errors of the project's own types become a one-line
message and exit code 2; nothing else is caught."""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

import app.commands
from calib.errors import ProcamError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="procam",
        description="Projector-camera calibration through a planar mirror (Vanherck et al. 2025).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for info in sorted(pkgutil.iter_modules(app.commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"app.commands.{info.name}")
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=getattr(mod, "DESCRIPTION", mod.HELP))
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except ProcamError as e:
        print(f"procam {args.command}: error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"procam {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
