"""The compiled kernels in named groups, and their first compilation split over processes.

numba compiles a kernel (``cache=True``) at its first call in a process, or loads it from its on-disk cache
(``__pycache__`` beside the source, or ``NUMBA_CACHE_DIR``) where an earlier process compiled the same source.
The first use with an empty cache therefore compiles every kernel the observer runs, one after the other on one
core. :func:`prepare` compiles the groups whose cache is missing in ``jobs`` processes at once: one share in the
calling process, each other share in a subprocess (``python -m exuflex._compile GROUP ...``) that writes numba's
cache, which the calling process then loads from. A kernel that calls another group's kernels (the sample loop
calls the interval's, the step map's and the Kalman kernels) would compile them again with itself unless they
are cached: its group ``needs`` theirs and waits for their cache when another process compiles them. The shares
and their order are those that finish soonest (:func:`plan`) by each group's :attr:`KernelGroup.cost`, the CPU
seconds of compiling it (``python benchmarks/first_compile.py --groups`` measures them; a subprocess also pays
:data:`START_COST` for starting Python, importing the package and setting numba's compiler up).

:func:`start` begins the same and returns at once (the other processes compiling while the caller checks its
input); :func:`prepare` then finishes it.

With a warm cache :func:`prepare` reads one small index file per kernel and starts nothing. It never fails the
caller: a subprocess that fails or does not finish, or a cache folder that cannot be written, leaves the missing
kernels to be compiled in the calling process (at their first call, as without :func:`prepare`).

``EXUFLEX_COMPILE_JOBS`` sets the number of processes (default: 2, or 1 on a one-core machine; 1 compiles in the
calling process only). ``NUMBA_DISABLE_JIT=1``: nothing to compile, :func:`prepare` does nothing.

A group is one :class:`KernelGroup` line in :func:`groups`: its name, its warm-up (a function that compiles or
loads its kernels by calling them on small arguments of the types the observer passes), the kernels that warm-up
compiles (their cache entries are what :func:`prepare` checks), its cost and the groups it needs.
"""

from __future__ import annotations

import atexit
import itertools
import logging
import math
import os
import subprocess
import sys
import sysconfig
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

__all__ = ["CHECKS_GROUP", "JOBS_ENV", "KernelGroup", "groups", "jobs", "missing", "plan", "prepare", "start"]

log = logging.getLogger(__name__)

#: the environment variable that sets the number of compiling processes
JOBS_ENV = "EXUFLEX_COMPILE_JOBS"
#: CPU seconds a compiling subprocess spends before its first compilation (Python, NumPy, numba, the package,
#: numba's compiler set up)
START_COST = 1.1
#: seconds to wait for a compiling subprocess before compiling its share here
TIMEOUT_S = 900.0
#: seconds between two looks at the other processes' progress (a line per group compiled)
PROGRESS_S = 0.5


@dataclass(frozen=True)
class KernelGroup:
    """Kernels compiled together: ``warm_up()`` compiles (or loads) them, ``kernels`` are the numba dispatchers
    it compiles, ``cost`` the CPU seconds of compiling them in a process that has the kernels they call (the
    split's weights), ``needs`` the groups whose kernels they call: numba compiles a called kernel with its caller
    unless it is compiled or cached already, so a group waits for the cache of the groups it needs that another
    process compiles (:func:`plan`)."""

    name: str
    warm_up: Callable[[], None]
    kernels: tuple
    cost: float
    needs: tuple[str, ...] = ()

    def cached(self) -> bool:
        """Whether numba's cache holds every kernel of the group for its current source (one compiled version
        at least: the warm-up's)."""
        return all(_cached(k) for k in self.kernels)


def groups() -> tuple[KernelGroup, ...]:
    """The observer's kernel groups. A new kernel joins a group by being called in its warm-up and listed in its
    ``kernels``; a new group is one line here (``needs``: the groups whose kernels its kernels call)."""
    from .erls import _assembly, _closure
    from .observer import augmented, expansion, kalman, loop
    from .reduction import _compiled, model

    return (
        KernelGroup(CHECKS_GROUP, _warm_up_kinematics, (_closure.closure_newton, _closure.pose_sensitivities,
                    _closure.coordinate_rates), cost=4.6),
        KernelGroup("reduction", model.warm_up, (_assembly.configuration, _compiled.pair_rotations,
                    _compiled.basis_at, _compiled.basis_derivative, _compiled.held_matrices,
                    _compiled._force_terms_shared, _compiled.force_terms), cost=20.3, needs=(CHECKS_GROUP,)),
        KernelGroup("held", expansion.warm_up_held, (expansion.prediction_error,), cost=2.7),
        KernelGroup("interval", expansion.warm_up_interval, (expansion.held_interval, expansion.step_jacobian),
                    cost=7.8),
        KernelGroup("step_map", expansion.warm_up_maps, (expansion.step_maps_noise, expansion.secant_factor,
                    expansion.rebuild_map, expansion.map_error, expansion.next_map_radius, expansion.measurement_rows),
                    cost=7.8),
        KernelGroup("kalman", _warm_up_kalman, (kalman.predict_cov, kalman.update, kalman.predict_update,
                    kalman.apply_gain, kalman.settle, kalman.normalise, kalman.step_statistic, kalman.window_seen,
                    kalman.window_push, kalman.condition_on, kalman.gate, kalman.fix_cov), cost=5.3),
        KernelGroup("sample_loop", partial(loop.warm_up, "plain"), (loop.samples, loop.screen, loop.given,
                    loop._one_sample), cost=15.1,
                    needs=("interval", "step_map", "kalman")),
        KernelGroup("payload", augmented.warm_up, (expansion.scaled_steps, expansion.payload_interval,
                    expansion.extra_interval), cost=48.3,
                    needs=("interval", "step_map", "kalman")),
    )


def _warm_up_kinematics() -> None:
    """The closure's kernels (:mod:`.erls._closure`: Newton, the pose's sensitivities, the coordinate rates), by
    solving the pose of :mod:`.reduction.model`'s warm-up rod."""
    import numpy as np

    from .erls.kinematics import Kinematics
    from .mechanism import parse_mechanism
    from .reduction.model import _WARM_UP_MODEL

    kin = Kinematics(parse_mechanism(_WARM_UP_MODEL, "warm_up"))
    kin.coordinate_rates(kin.pose(np.zeros(kin.nq)))


def _warm_up_kalman() -> None:
    """The Kalman kernels (:func:`.observer.kalman.warm_up`) and the covariance repair the bound's recursion
    calls (:func:`.observer.kalman.fix_cov`)."""
    import numpy as np

    from .observer import kalman

    kalman.warm_up()
    kalman.fix_cov(np.eye(3), np.zeros(3))


def _cached(kernel) -> bool:
    """Whether numba's cache index of ``kernel`` holds an entry for this machine and its current code (numba's
    own key: signature, target, bytecode hash; the index is void when the source file changed). Not a caching
    dispatcher (e.g. under ``NUMBA_DISABLE_JIT``), or a numba whose cache internals differ: True (nothing for
    :func:`prepare` to do, the kernel compiles at its first call as without it)."""
    cache = getattr(kernel, "_cache", None)
    index = getattr(cache, "_cache_file", None)
    if index is None:
        return True
    try:
        codegen = kernel.targetctx.codegen()
        return any(cache._index_key(key[0], codegen) == key for key in index._load_index())
    except Exception as exc:  # noqa: BLE001 - numba's private cache API: unknown means "as without prepare"
        log.debug("numba cache index of %s unreadable (%s)", getattr(kernel, "__name__", kernel), exc)
        return True


def _writable(kernel) -> bool:
    """Whether the folder numba caches ``kernel`` in can be written (else a subprocess's work would be lost)."""
    path = getattr(getattr(kernel, "_cache", None), "cache_path", None)
    return path is not None and os.path.isdir(path) and os.access(path, os.W_OK | os.X_OK)


def missing(selected: tuple[KernelGroup, ...] | None = None) -> list[KernelGroup]:
    """The groups whose kernels numba's cache does not hold (all of them on a first run; none under
    ``NUMBA_DISABLE_JIT`` or without numba)."""
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a core dependency
        return []
    if numba.config.DISABLE_JIT:
        return []
    return [g for g in (groups() if selected is None else selected) if not g.cached()]


def jobs(requested: int | None = None) -> int:
    """The number of compiling processes: ``requested``, else ``EXUFLEX_COMPILE_JOBS``, else 2 (1 where this
    process may use one core only)."""
    if requested is None:
        raw = os.environ.get(JOBS_ENV, "").strip()
        if raw:
            try:
                requested = int(raw)
            except ValueError:
                raise ValueError(f"{JOBS_ENV}: expected a whole number of processes >= 1, got {raw!r}") from None
    if requested is not None:
        if requested < 1:
            raise ValueError(f"{JOBS_ENV} (jobs): expected a whole number of processes >= 1, got {requested}")
        return int(requested)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return min(2, cores)


def _finish(shares: list[list[KernelGroup]]) -> float:
    """When the last share is done if each runs its groups in order from 0 (share 0) or :data:`START_COST` (the
    others), a group starting once the groups it needs from other shares are done (inf: they wait on each
    other)."""
    where = {g.name: k for k, share in enumerate(shares) for g in share}
    clock = [0.0] + [START_COST] * (len(shares) - 1)
    done: dict[str, float] = {}
    nxt = [0] * len(shares)
    while any(nxt[k] < len(share) for k, share in enumerate(shares)):
        moved = False
        for k, share in enumerate(shares):
            while nxt[k] < len(share):
                g = share[nxt[k]]
                other = [n for n in g.needs if where.get(n, k) != k]
                if any(n not in done for n in other):
                    break
                clock[k] = max([clock[k], *(done[n] for n in other)]) + g.cost
                done[g.name] = clock[k]
                nxt[k] += 1
                moved = True
        if not moved:
            return math.inf
    return max(clock)


def plan(todo: list[KernelGroup], n: int, here: tuple[str, ...] = ()) -> list[list[KernelGroup]]:
    """``todo`` in at most ``n`` ordered shares that finish soonest (:func:`_finish`; share 0 for the calling
    process): every assignment of groups to shares is tried while there are at most ``10**5`` (else all in share
    0); in a share, the groups another share needs come first (cheapest first), those that need others last.
    The groups named in ``here`` are in share 0, before all others. Empty shares are left out, share 0 first
    (possibly empty)."""
    n = max(1, min(n, len(todo)))

    def shares_of(assign) -> list[list[KernelGroup]]:
        shares: list[list[KernelGroup]] = [[] for _ in range(n)]
        for g, k in zip(todo, assign, strict=True):
            shares[k].append(g)
        wanted = {nd for k, share in enumerate(shares) for g in share for nd in g.needs
                  if not any(x.name == nd for x in share)}
        shares = [sorted(share, key=lambda g: (g.name not in here, g.name not in wanted, bool(g.needs), g.cost))
                  for share in shares]
        return [shares[0]] + [share for share in shares[1:] if share]

    if n ** len(todo) > 10**5:
        return shares_of([0] * len(todo))
    choices = [range(1) if g.name in here else range(n) for g in todo]
    best = min(itertools.product(*choices), key=lambda a: (_finish(shares_of(a)), len(set(a))))
    return shares_of(best)


def _needs_first(share: list[KernelGroup]) -> list[KernelGroup]:
    """``share`` with every group after the groups of ``share`` it needs (otherwise in its order)."""
    names = {g.name for g in share}
    out: list[KernelGroup] = []
    rest = list(share)
    while rest:
        ready = next((g for g in rest if all(n not in names or n in {x.name for x in out} for n in g.needs)), rest[0])
        out.append(ready)
        rest.remove(ready)
    return out


def _await_needs(group: KernelGroup, local: set[str], known: dict[str, KernelGroup],
                 alive: Callable[[], bool] = lambda: True) -> None:
    """Wait until numba's cache holds the groups ``group`` needs that another process compiles (not in
    ``local``), at most about twice their cost (then numba compiles them here, with ``group``'s kernels)."""
    others = [known[n] for n in group.needs if n not in local and n in known]
    if not others:
        return
    deadline = time.monotonic() + 10.0 + 2.0 * sum(g.cost for g in others)
    while not all(g.cached() for g in others) and time.monotonic() < deadline and alive():
        time.sleep(0.1)


def _worker_env() -> dict[str, str]:
    """The environment of a compiling subprocess: this one's, with this process's copy of exuflex first on the
    path, numba's cache folder as this process's numba uses it, and no further subprocesses."""
    import numba

    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[1])
    installed = {str(Path(sysconfig.get_path(k)).resolve()) for k in ("purelib", "platlib")}
    if root not in installed:  # a source tree (an installed package is found by the subprocess as it is)
        env["PYTHONPATH"] = os.pathsep.join([root] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    if numba.config.CACHE_DIR:
        env["NUMBA_CACHE_DIR"] = str(numba.config.CACHE_DIR)
    env[JOBS_ENV] = "1"
    return env


def _warm(group: KernelGroup) -> None:
    """``group.warm_up()`` in this process; an error is reported and left to the kernels' first call."""
    try:
        group.warm_up()
    except Exception as exc:  # noqa: BLE001 - the kernels then compile at their first call, as without prepare
        log.warning("compiling the %s kernels ahead failed (%s: %s); they compile at their first use",
                    group.name, type(exc).__name__, exc)


#: the groups only the augmented estimators (``ekf-payload``, ``ekf-input``) use: :func:`prepare` compiles them
#: for those alone, so that a plain filter's first use does not wait for them
AUGMENTED_GROUPS = ("payload",)
#: the group whose kernels a command's checks call before :func:`prepare` (a model file's loops closed): after
#: :func:`start` this process compiles it first, at those calls
CHECKS_GROUP = "kinematics"

_prepared: set[str] = set()  # what prepare() did or start() began in this process: "plain", "augmented"


@dataclass
class _Started:
    """The compilation :func:`start` began: this process's share, the subprocesses with their shares, the
    clock and the progress callback."""

    here: list[KernelGroup]
    workers: list[tuple]  # (Popen, stderr file, share)
    t0: float
    say: Callable[[str], None]


_started: _Started | None = None


def start(n_jobs: int | None = None, progress: Callable[[str], None] | None = None,
          augmented: bool = False) -> None:
    """Begin :func:`prepare` and return at once: the groups numba's cache lacks are planned over ``n_jobs``
    processes and the other processes' shares start compiling, while this process goes on (a command's checks of
    its input, reading a log); :func:`prepare` then compiles this process's share and waits for the others. The
    share of this process holds :data:`CHECKS_GROUP` first, as the checks call its kernels (they compile at those
    calls). With a warm cache it reads one small index file per kernel and starts nothing. A process that ends
    before :func:`prepare` stops the subprocesses (what they finished stays cached)."""
    global _started
    if "augmented" in _prepared or (not augmented and "plain" in _prepared):
        return
    n = jobs(n_jobs)
    _prepared.add("augmented" if augmented else "plain")
    todo = [g for g in missing() if augmented or g.name not in AUGMENTED_GROUPS]
    if not todo:
        return
    say = progress or (lambda msg: log.info("%s", msg))
    if n > 1 and not all(_writable(k) for g in todo for k in g.kernels):
        log.info("numba's cache folder is not writable: compiling in this process")
        n = 1
    shares = plan(todo, n, here=(CHECKS_GROUP,))
    t0 = time.perf_counter()
    say(f"compiling numba kernels (first run, {len(shares)} process{'es' if len(shares) > 1 else ''}) ...")
    here = list(shares[0])
    workers = []
    try:
        if len(shares) > 1:
            env = _worker_env()
            for share in shares[1:]:
                err = tempfile.TemporaryFile()  # noqa: SIM115 - closed by prepare() or _stop()
                cmd = [sys.executable, "-m", "exuflex._compile", *(g.name for g in share)]
                try:
                    proc = subprocess.Popen(cmd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                            stderr=err)
                except OSError as exc:
                    log.info("could not start a compiling process (%s): compiling its kernels here", exc)
                    err.close()
                    here += share
                    continue
                workers.append((proc, err, share))
    except BaseException:
        _stop(workers)
        raise
    _started = _Started(here, workers, t0, say)
    if workers:
        atexit.register(_stop_started)


def _stop(workers: list[tuple]) -> None:
    """Stop the subprocesses that still run and close their error files."""
    for proc, err, _ in workers:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        err.close()


def _stop_started() -> None:
    """At exit: the subprocesses :func:`start` began that :func:`prepare` did not wait for (the command failed
    in between) are stopped."""
    global _started
    if _started is not None:
        _stop(_started.workers)
        _started = None


def prepare(n_jobs: int | None = None, progress: Callable[[str], None] | None = None,
            augmented: bool = False) -> float:
    """Compile the kernel groups that numba's cache lacks, in ``n_jobs`` processes (:func:`jobs`), so that this
    process then loads them from the cache: the groups of :data:`AUGMENTED_GROUPS` only with ``augmented`` (an
    augmented estimator's observer). Once per process and kind; returns the wall seconds it compiled for (0 with a
    warm cache), from :func:`start` where that began it. ``progress``: one line when compiling starts, one per
    group compiled (here or in another process) and one when done (default: the log, INFO)."""
    global _started
    if _started is None:
        start(n_jobs, progress, augmented)
    elif augmented and "augmented" not in _prepared:  # a plain start, now an augmented observer: its groups too
        prepare(n_jobs, progress)
        start(n_jobs, progress, augmented)
    if _started is None:
        return 0.0
    st, _started = _started, None
    known = {g.name: g for g in groups()}
    workers = st.workers
    todo = st.here + [g for _, _, share in workers for g in share]
    done: set[str] = set()

    def tick() -> None:
        """A line for each group compiled since the last look (here, or cached by another process)."""
        for g in todo:
            if g.name not in done and g.cached():
                done.add(g.name)
                st.say(f"compiled the {g.name} kernels ({len(done)} of {len(todo)} groups, "
                       f"{time.perf_counter() - st.t0:.0f} s)")

    def alive() -> bool:
        tick()
        return all(p.poll() in (None, 0) for p, _, _ in workers)

    try:
        here = _needs_first(st.here)
        local = {g.name for g in here}
        for g in here:
            _await_needs(g, local, known, alive=alive)
            _warm(g)
            tick()
        for proc, err, share in workers:
            deadline = st.t0 + TIMEOUT_S
            while True:
                try:
                    rc = proc.wait(timeout=min(PROGRESS_S, max(0.01, deadline - time.perf_counter())))
                    break
                except subprocess.TimeoutExpired:
                    tick()
                    if time.perf_counter() >= deadline:
                        proc.kill()
                        proc.wait()
                        rc = "timeout"
                        break
            if rc != 0:
                err.seek(0)
                tail = err.read().decode(errors="replace").strip().splitlines()[-1:] or [""]
                log.info("the process compiling %s ended with %s (%s): compiling them here",
                         ", ".join(g.name for g in share), rc, tail[0])
    finally:
        _stop(workers)  # interrupted: stop the subprocesses this process started
    for _, _, share in workers:  # loaded from the cache the subprocesses wrote (or compiled here if they did not)
        for g in share:
            _warm(g)
    tick()
    wall = time.perf_counter() - st.t0
    st.say(f"numba kernels compiled in {wall:.0f} s (cached on disk for later runs)")
    return wall


def main(argv: list[str] | None = None) -> int:
    """``python -m exuflex._compile GROUP ...``: compile (or load) the named groups in this process, writing
    numba's cache (what :func:`prepare`'s subprocesses run). Without names: :func:`prepare` (every missing group,
    in :func:`jobs` processes; e.g. ahead of the first use when building a container image)."""
    names = sys.argv[1:] if argv is None else argv
    logging.basicConfig(level=logging.INFO, format="exuflex._compile: %(message)s", stream=sys.stderr)
    if not names:
        prepare(augmented=True)
        return 0
    known = {g.name: g for g in groups()}
    unknown = [n for n in names if n not in known]
    if unknown:
        log.error("unknown kernel group(s) %s; expected some of %s", unknown, sorted(known))
        return 2
    for name in names:
        _await_needs(known[name], set(names), known)
        known[name].warm_up()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
