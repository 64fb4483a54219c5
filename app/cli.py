"""`procam` command line. Every module in app/commands/ is one sub-command: it defines NAME, HELP,
`add_arguments(parser)` and `run(args) -> int`.

What the user sees when something goes wrong:
- an error of the project's own types (calib/errors.py, drivers/errors.py): one line, exit code 2;
- any other exception: one line saying what failed and where the full traceback was written (a file
  in the temporary folder), exit code 2;
- an option that does not parse or is out of range (app/commands/_types.py): one line naming it, exit
  code 2, before the command does anything;
- Ctrl-C: "interrupted", exit code 130.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys
import tempfile
import traceback

import app.commands
from calib.errors import OptionError, ProcamError

PACKAGE = "procam-station"


def version_text() -> str:
    """`procam --version`: the package version, Python's and OpenCV's."""
    try:
        from importlib.metadata import PackageNotFoundError, version

        v = version(PACKAGE)
    except PackageNotFoundError:
        v = "unknown (not installed)"
    try:
        import cv2

        cv = f", OpenCV {cv2.__version__}"
    except ImportError:
        cv = ""
    py = ".".join(str(x) for x in sys.version_info[:3])
    return f"procam {v} ({PACKAGE}; Python {py}{cv})"


class _VersionAction(argparse.Action):
    """--version, computed only when asked (importing OpenCV for every command would slow them)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(version_text())
        parser.exit(0)


class _Parser(argparse.ArgumentParser):
    """argparse raising OptionError instead of printing the usage and exiting: a wrong option is one line,
    like every other error, and `main()` returns 2 instead of raising SystemExit."""

    def error(self, message):
        raise OptionError(message, self.prog)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="procam",
        description="Projector-camera calibration through a planar mirror (Vanherck et al. 2025).",
    )
    parser.add_argument("--version", action=_VersionAction, help="print the version and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for info in sorted(pkgutil.iter_modules(app.commands.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"app.commands.{info.name}")
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=getattr(mod, "DESCRIPTION", mod.HELP))
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def write_traceback(command: str, exc: BaseException) -> str | None:
    """Write the full traceback of `exc` to a new file in the temporary folder; its path, or None."""
    try:
        fd, path = tempfile.mkstemp(prefix=f"procam-{command}-", suffix=".log", text=True)
        with open(fd, "w", encoding="utf-8") as f:
            f.write(f"procam {' '.join(sys.argv[1:])}\n\n")
            traceback.print_exception(type(exc), exc, exc.__traceback__, file=f)
        return path
    except OSError:
        return None


def terminal_safe(text: str) -> str:
    """`text` with every control character but newline and tab shown as an escape (\\x1b, \\r, ...):
    an error message can quote a file name or a session file's value, and neither may drive the terminal
    (colour, cursor moves, a line overwritten by a carriage return)."""
    out = []
    for ch in str(text):
        o = ord(ch)
        if ch in "\n\t" or not (o < 32 or 127 <= o < 160):
            out.append(ch)
        else:
            out.append(repr(ch)[1:-1] if o < 256 else f"\\u{o:04x}")
    return "".join(out)


def unexpected_error_line(command: str, exc: BaseException) -> str:
    """One line for an exception procam does not expect: what failed and where the traceback went."""
    path = write_traceback(command, exc)
    if isinstance(exc, OSError) and exc.strerror:
        name = f" {exc.filename}" if exc.filename else ""
        what = f"cannot access{name}: {exc.strerror}"
    else:
        text = str(exc).strip().splitlines()
        what = f"unexpected {type(exc).__name__}" + (f": {text[0]}" if text else "")
    if path is None:
        where = "the traceback could not be saved (temporary folder not writable); run again with PYTHONDEVMODE=1"
    else:
        where = f"full traceback in {path} (please include it when reporting this)"
    return f"procam {command}: error: {what}; {where}"


def main(argv: list[str] | None = None) -> int:
    from app.blas_threads import limit_blas_threads

    limit_blas_threads()  # before any command computes (app/blas_threads.py says why)
    try:
        args = build_parser().parse_args(argv)
    except OptionError as e:
        print(terminal_safe(f"{e.prog}: error: {e} (see {e.prog} --help)"), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("procam: interrupted", file=sys.stderr)
        return 130
    try:
        return int(args._run(args) or 0)
    except ProcamError as e:
        print(terminal_safe(f"procam {args.command}: error: {e}"), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"procam {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `procam ... | head`: the reader left; nothing to report
        import os

        try:
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        except (OSError, ValueError):
            pass
        return 141
    except Exception as e:  # noqa: BLE001  (the last line of defence: never a bare traceback)
        print(terminal_safe(unexpected_error_line(args.command, e)), file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
