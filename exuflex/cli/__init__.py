"""Command line: ``exuflex <command> ...``. Each command lives in its own module with
``add_parser(subparsers)`` and ``run(args) -> int``; this dispatcher only wires them up and turns
expected errors (bad model files, bad logs, kinematics failures) into one- or two-line messages."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

__all__ = ["main"]

COMMANDS = ("modes", "simulate", "observe", "study", "reproduce", "bench")


def _build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="exuflex", description=__doc__.split("\n")[0])
    p.add_argument("--debug", action="store_true", help="show tracebacks and debug logging")
    sub = p.add_subparsers(dest="command", required=True)
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f".{name}", __name__)
        except ModuleNotFoundError as exc:
            if exc.name and exc.name.endswith(f"cli.{name}"):
                continue  # command not available in this build
            raise
        mod.add_parser(sub)
    return p


def _one_line(exc: BaseException) -> str:
    """The message of an expected error on one line (a long message keeps its first 2000 characters)."""
    msg = " ".join(str(exc).split()) or type(exc).__name__
    return msg if len(msg) <= 2000 else msg[:2000] + " ..."


def main(argv: list[str] | None = None) -> int:
    parser = _build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.debug else logging.WARNING, format="%(levelname)s: %(message)s")
    if args.debug:
        return int(args.func(args) or 0)
    from ..errors import EXPECTED_ERRORS

    try:
        return int(args.func(args) or 0)
    except EXPECTED_ERRORS as exc:
        print(f"exuflex {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except OSError as exc:  # unreadable or unwritable paths (permissions, a folder given for a file, ...)
        print(f"exuflex {args.command}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except RuntimeError as exc:
        from ..observer.base import FilterDivergedError

        if not isinstance(exc, FilterDivergedError):
            raise
        print(f"exuflex {args.command}: error: the filter diverged: {_one_line(exc)}\n"
              "  check the log's units and channels against the model file (--debug for details)", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"exuflex {args.command}: interrupted; finished results are kept", file=sys.stderr)
        return 130
