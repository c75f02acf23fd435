"""Argument types shared by the commands: each turns a command-line word into a value or rejects it with
one line naming what was expected (``argparse`` adds the flag's name)."""

from __future__ import annotations

import argparse
import math

__all__ = ["add_overwrite", "channel_list", "finite_float", "n_interior", "name_list", "nonneg_int", "nonneg_float", "out_path",
           "positive_float", "positive_int", "probability", "seed", "unit_probability"]


def _float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None


def finite_float(text: str) -> float:
    v = _float(text)
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return v


def positive_float(text: str) -> float:
    v = _float(text)
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"expected a positive finite number, got {text!r}")
    return v


def nonneg_float(text: str) -> float:
    v = _float(text)
    if not (math.isfinite(v) and v >= 0):
        raise argparse.ArgumentTypeError(f"expected a non-negative finite number, got {text!r}")
    return v


def probability(text: str) -> float:
    """A false-alarm probability in (0, 0.5)."""
    v = _float(text)
    if not 0.0 < v < 0.5:
        raise argparse.ArgumentTypeError(f"expected a probability in (0, 0.5), got {text!r}")
    return v


def unit_probability(text: str) -> float:
    """A probability in [0, 1]."""
    v = _float(text)
    if not 0.0 <= v <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a probability in [0, 1], got {text!r}")
    return v


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None


def positive_int(text: str) -> int:
    v = _int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def nonneg_int(text: str) -> int:
    v = _int(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected a non-negative integer, got {text!r}")
    return v


def n_interior(text: str):
    """The number of interior modes: a non-negative integer or ``auto``."""
    if text == "auto":
        return "auto"
    try:
        n = int(text)
    except ValueError:
        n = -1
    if n < 0:
        raise argparse.ArgumentTypeError(f"expected a non-negative integer or 'auto', got {text!r}")
    return n


def seed(text: str) -> int:
    """A noise seed: an integer 0 <= seed < 2**63 (NumPy's generators take no negative seed)."""
    v = _int(text)
    if not 0 <= v < 2**63:
        raise argparse.ArgumentTypeError(f"expected an integer seed in 0 .. 2**63 - 1, got {text!r}")
    return v


def name_list(what: str):
    """Comma-separated names, at least one, none empty, none repeated."""

    def parse(text: str) -> tuple[str, ...]:
        names = [s.strip() for s in text.split(",")]
        if not text.strip() or all(not n for n in names):
            raise argparse.ArgumentTypeError(f"expected one or more {what} separated by commas, got {text!r}")
        if any(not n for n in names):
            raise argparse.ArgumentTypeError(f"empty {what[:-1] if what.endswith('s') else what} name in {text!r}")
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise argparse.ArgumentTypeError(f"{what} repeated: {', '.join(dup)}")
        return tuple(names)

    return parse


channel_list = name_list("channels")


def out_path(text: str) -> str:
    if not text.strip():
        raise argparse.ArgumentTypeError("expected a folder path, got an empty string")
    return text


def add_overwrite(p: argparse.ArgumentParser) -> None:
    """``--overwrite``: the one flag that lets a command replace an earlier exuflex result in its ``--out`` folder
    (a folder holding anything exuflex did not write is refused whatever it says:
    :func:`exuflex.runs.output_folder`)."""
    p.add_argument("--overwrite", action="store_true",
                   help="replace an earlier exuflex result in --out (a folder holding files exuflex did not write "
                   "is refused all the same)")
