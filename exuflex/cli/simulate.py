"""``exuflex simulate MODEL --out DIR``: simulate the "real mechanism" along the model's manoeuvre.

The library does the work (:func:`exuflex.truth.simulate_run`: the model's manoeuvre or ``--manoeuvre FILE``,
planned, with the computed torque of the nominal model or measured torques; the truth engine with its mesh and
solver; seeded measurement; the run folder ``sensors.csv``, ``truth.csv``, ``meta.json``); this module parses the
arguments and shows progress.
"""

from __future__ import annotations

import argparse
import sys
import time

from ..truth import BEAMS, ENGINES, EXUDYN_ELEMENTS_PER_LINK, INTEGRATORS, simulate_run
from .args import add_overwrite, out_path, positive_float
from .args import seed as seed_type

__all__ = ["PhaseBars", "ProgressBar", "add_parser", "elements_per_link_arg", "run"]


class ProgressBar:
    """Progress on stderr: on a terminal a one-line bar ``label [#####.....]  45%`` redrawn in place; otherwise
    (a log file, a pipe, a CI job) a plain line every 10 %, ``label  40%  12.3 s``. Silent if disabled."""

    def __init__(self, label: str, enabled: bool = True, width: int = 30, stream=None):
        self.label, self.enabled, self.width = label, enabled, width
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._last = -1
        self._t0 = time.perf_counter()

    def __call__(self, frac: float) -> None:
        if not self.enabled:
            return
        pct = int(100 * min(max(frac, 0.0), 1.0))
        if not self.tty:
            pct = pct // 10 * 10
        if pct == self._last:
            return
        self._last = pct
        el = time.perf_counter() - self._t0
        if not self.tty:
            self.stream.write(f"{self.label:<12s} {pct:3d}% {el:6.1f} s\n")
            self.stream.flush()
            return
        n = self.width * pct // 100
        self.stream.write(f"\r{self.label:<12s} [{'#' * n}{'.' * (self.width - n)}] {pct:3d}% {el:6.1f} s")
        self.stream.flush()

    def close(self) -> None:
        if self.enabled and self.tty and self._last >= 0:
            self.stream.write("\n")
            self.stream.flush()


def _erls_step_arg(text: str):
    if text == "auto":
        return "auto"
    try:
        v = float(text)
    except ValueError:
        v = 0.0
    if not v > 0:
        raise argparse.ArgumentTypeError(f"expected a positive step in s or 'auto', got {text!r}")
    return v


def elements_per_link_arg(text: str):
    """``--elements-per-link``: a positive integer or ``file`` (the model file's own mesh)."""
    if text == "file":
        return "file"
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer or 'file', got {text!r}")
    return n


def add_parser(sub) -> argparse.ArgumentParser:
    p = sub.add_parser(
        "simulate",
        help="simulate the mechanism along its manoeuvre and write a run folder",
        description=__doc__.split("\n")[0],
    )
    p.add_argument("model", help="model file (TOML), e.g. models/sixbar.toml")
    p.add_argument("--out", required=True, type=out_path, help="run folder to write (created if needed)")
    add_overwrite(p)
    p.add_argument(
        "--engine", choices=ENGINES, default="exudyn",
        help="truth engine: exudyn (independent, default), erls (full-order ERLS model), reduced (the observer's "
        "own reduced model)"
    )
    p.add_argument(
        "--duration", type=positive_float, default=None, help="simulated time (s); default: the manoeuvre's"
    )
    p.add_argument(
        "--payload-scale", type=positive_float, default=1.0, help="tip payload multiplier of the truth (default 1)"
    )
    p.add_argument(
        "--seed", type=seed_type, default=None, help="measurement noise seed (default: random, recorded)"
    )
    p.add_argument("--h", type=positive_float, default=1e-4,
                   help="integration step (s), also the torque table step; at most the model's sample interval")
    p.add_argument(
        "--manoeuvre", default=None, metavar="FILE",
        help="manoeuvre instead of the model's: a TOML file with a [manoeuvre] table, or a CSV table "
        "(t and coordinates or tip_x, tip_y: a trajectory; t and motor names: measured torques)",
    )
    p.add_argument(
        "--elements-per-link",
        type=elements_per_link_arg,
        default=None,
        metavar="N|file",
        help="truth mesh: no element longer than 1/N of its link (joints and masses on nodes; the ERLS engine keeps "
        f"the file's nodes too) or 'file', the model file's mesh (default: {EXUDYN_ELEMENTS_PER_LINK} for Exudyn, "
        "or the file's most refined link's element count if larger; the file's for ERLS)",
    )
    p.add_argument(
        "--beam",
        choices=tuple(BEAMS),
        default="ancf",
        help="Exudyn model: ANCF cable (default), geometrically exact beam (linear, needs 16-32 elements per link), "
        "or ffrf (alias solid): floating-frame bodies from solid meshes (netgen, Hurty-Craig-Bampton; cached)",
    )
    p.add_argument(
        "--integrator",
        choices=INTEGRATORS,
        default="gen-alpha",
        help="ERLS engine: implicit generalized-alpha (default) or the explicit RK4 reference",
    )
    p.add_argument(
        "--erls-step", type=_erls_step_arg, default="auto", metavar="S|auto",
        help="generalized-alpha step of the ERLS engine (s): a multiple of --h that divides the sample interval; "
        "auto (default): the truth step rule, the largest sample interval / n that keeps the phase error each "
        "mode below the model's band_hz accumulates over the cycles it rings within 0.004 (and the frequency "
        "error at band_hz within 0.5 %%; docs/theory/truth_step.md); it may be below --h",
    )
    p.add_argument(
        "--write-plan", action="store_true",
        help="also write the planned q, q', q'' as plan.csv (a trajectory file: --manoeuvre plan.csv plans it again)",
    )
    p.add_argument(
        "--no-progress", action="store_true",
        help="no progress (a bar on a terminal, a line every 10 %% otherwise)"
    )
    p.set_defaults(func=run)
    return p


class PhaseBars:
    """A :class:`ProgressBar` per phase of :func:`exuflex.truth.simulate_run` (called with phase, fraction)."""

    def __init__(self, enabled: bool):
        self.enabled, self.label, self.bar = enabled, None, None

    def __call__(self, label: str, frac: float) -> None:
        if label != self.label:
            self.close()
            self.label, self.bar = label, ProgressBar(label, self.enabled)
        self.bar(frac)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def run(args) -> int:
    bars = PhaseBars(not args.no_progress)
    try:
        out = simulate_run(
            args.model,
            args.out,
            engine=args.engine,
            duration=args.duration,
            payload_scale=args.payload_scale,
            seed=args.seed,
            h=args.h,
            progress=bars,
            manoeuvre=args.manoeuvre,
            write_plan=args.write_plan,
            elements_per_link=args.elements_per_link,
            beam=args.beam,
            integrator=args.integrator,
            erls_step=args.erls_step,
            messages=None if args.no_progress else (lambda msg: print(msg, file=sys.stderr)),
            overwrite=args.overwrite,
        )
    finally:
        bars.close()
    print(f"wrote {out}/sensors.csv, truth.csv, meta.json")
    return 0
