"""Command line: ``exuflex <command> ...``. Each command lives in its own module with
``add_parser(subparsers)`` and ``run(args) -> int``; this dispatcher only wires them up and turns
expected errors (bad arguments, bad model files, bad logs, kinematics failures) into one-line messages.

Exit codes: 0 success; 2 an error in the input (arguments, model file, log), one line on stderr; 1 an
internal error (a bug: one line, ``--debug`` shows the traceback); 130 interrupted. ``--debug`` may stand
anywhere on the command line.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import logging
import sys
from contextlib import contextmanager

__all__ = ["main", "setting_up"]

COMMANDS = ("modes", "simulate", "observe", "plot", "study", "reproduce", "bench", "design")


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line: ``exuflex CMD: error: ... (exuflex CMD --help)``."""

    def error(self, message: str):  # noqa: D401 - argparse's hook
        msg = " ".join(message.split())
        self.exit(2, f"{self.prog}: error: {msg} (see {self.prog} --help)\n")


def _build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command, or of ``command`` alone (what a command line naming it needs: the other
    commands' modules, and what they import, stay unimported)."""
    from .. import __version__

    p = _Parser(prog="exuflex", description=__doc__.split("\n")[0])
    p.add_argument("--version", action="version", version=f"exuflex {__version__}")
    p.add_argument("--debug", action="store_true",
                   help="show tracebacks and debug logging (may stand anywhere on the command line)")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for name in (command,) if command in COMMANDS else COMMANDS:
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
    if isinstance(exc, KeyError) and len(exc.args) == 1 and isinstance(exc.args[0], str):
        msg = " ".join(exc.args[0].split())  # KeyError's str() quotes its message
    return msg if len(msg) <= 2000 else msg[:2000] + " ..."


class _NisFlagFilter(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith("EKF diverged")


def _split_debug(argv: list[str]) -> tuple[list[str], bool]:
    """``--debug`` anywhere before a ``--`` switches debugging on; it is removed from the arguments."""
    stop = argv.index("--") if "--" in argv else len(argv)
    debug = "--debug" in argv[:stop]
    return [a for i, a in enumerate(argv) if not (i < stop and a == "--debug")], debug


@contextmanager
def setting_up():
    """Python's cyclic garbage collector paused while a command makes what lives until it ends (the modules it
    imports, the compiled kernels loaded from numba's cache, the model): a bounded amount of memory that is not
    garbage, which each collection of the oldest generation would otherwise traverse again (importing SciPy and
    loading numba's kernels create many objects, and so trigger many collections). On leaving, what exists is
    frozen (:func:`gc.freeze`: left out of later collections) and the collector resumes: the work that grows with
    the log (filtering, writing) runs with it on. :func:`main` gives the frozen objects back to the collector when
    it returns to a caller in Python. (Cyclic garbage made in here is frozen with the rest: little with numba's
    cache warm; on a first use, the compiler's garbage of the kernels compiled in here stays until the command
    ends.)"""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if was:
            gc.enable()


def main(argv: list[str] | None = None) -> int:
    """The command line (``argv`` without the program's name; default ``sys.argv``). Called as the program (no
    ``argv``), what the command made stays frozen out of the interpreter's collections until it exits
    (:func:`gc.freeze`: its last collections would traverse every object of numba's and the model's once more);
    called from Python, the objects frozen while the command set up are given back to the collector
    (:func:`gc.unfreeze`)."""
    try:
        return _main(argv)
    finally:
        gc.freeze() if argv is None else gc.unfreeze()


def _main(argv: list[str] | None) -> int:
    argv, debug = _split_debug(list(sys.argv[1:] if argv is None else argv))
    with setting_up():  # a command first: its parser alone (its module imported); else (--help) all
        parser = _build_parser(argv[0] if argv else None)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version, or a usage error already printed in one line
        return int(exc.code or 0) if not isinstance(exc.code, str) else 2
    args.debug = debug
    logging.basicConfig(level=logging.DEBUG if debug else logging.WARNING, format="%(levelname)s: %(message)s")
    if not debug:  # the filter's NIS window flag is an inconsistency, reported once by the command, not a divergence
        logging.getLogger("exuflex.observer.ekf").addFilter(_NisFlagFilter())
    if debug:
        return int(args.func(args) or 0)
    with setting_up():
        from ..errors import EXPECTED_ERRORS
        from ..observer.base import FilterDivergedError

    prog = f"exuflex {args.command}"
    try:
        return int(args.func(args) or 0)
    except FilterDivergedError as exc:
        print(f"{prog}: error: the filter diverged (its estimates became non-finite or unbounded): {_one_line(exc)}; "
              "check the log's units and channels against the model file (--debug for details)", file=sys.stderr)
        return 2
    except (*EXPECTED_ERRORS, ValueError, KeyError, OSError) as exc:
        # bad input: arguments, model files, logs, unreadable or unwritable paths
        print(f"{prog}: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except MemoryError:
        print(f"{prog}: error: out of memory; use a shorter --duration or a coarser step", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; finished results are kept", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - a bug: one line here, the traceback with --debug
        print(f"{prog}: internal error: {type(exc).__name__}: {_one_line(exc)} (a bug; rerun with --debug for the "
              "traceback and report it)", file=sys.stderr)
        return 1
