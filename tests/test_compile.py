"""The kernel registry and the parallel first compilation (:mod:`exuflex._compile`): the groups cover every kernel
the observer compiles, the plan is balanced and waits for what a group needs, a failed or impossible parallel compilation falls back to this
process, and the estimates do not depend on which process compiled the kernels."""

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from exuflex import _compile
from exuflex._compile import KernelGroup

ROOT = Path(__file__).resolve().parents[1]

# A fresh process: the groups' warm-ups (compiled, or loaded from numba's cache), then the six-bar's observer on a
# short log and two other mechanisms' observers built; every numba dispatcher of the package that gains a compiled
# signature after the warm-ups is reported (none may: the registry is complete), with the estimates.
COVERAGE = textwrap.dedent(r"""
    import json, sys
    import numpy as np
    from numba.core.registry import CPUDispatcher
    from exuflex import _compile

    def signatures():
        out = {}
        for name, mod in list(sys.modules.items()):
            if name.startswith("exuflex"):
                for k, v in vars(mod).items():
                    if isinstance(v, CPUDispatcher):
                        out[f"{v.py_func.__module__}.{v.py_func.__qualname__}"] = {str(s) for s in v.signatures}
        return out

    missing_before = [g.name for g in _compile.missing()]
    if sys.argv[1] == "prepare":
        _compile.prepare(int(sys.argv[2]), augmented=True)
    else:
        for g in _compile.groups():
            g.warm_up()
    unlisted = [f"{g.name}: {k.py_func.__qualname__}" for g in _compile.groups() for k in g.kernels
                if not k.signatures]
    missing_after = [g.name for g in _compile.missing()]
    from exuflex.mechanism import load_mechanism
    from exuflex.observer.session import ObserverConfig, estimate, make_observer
    from exuflex.runs import held_torques
    from exuflex.runs import read_run
    before = signatures()
    mech = load_mechanism(sys.argv[3] + "/models/sixbar.toml")
    S = read_run(sys.argv[3] + "/tests/data/sixbar_short").sensors
    obs = make_observer(mech, ObserverConfig.for_model(mech))
    est = estimate(obs, S.t, held_torques(S.select(mech.motor_names).data), S.select(obs.channels).data)
    for name in ("single_link", "serial_arm"):
        make_observer(load_mechanism(sys.argv[3] + f"/models/{name}.toml"))
    after = signatures()
    grew = sorted(k for k in after if after[k] - before.get(k, set()))
    print(json.dumps({"missing_before": missing_before, "missing_after": missing_after, "unlisted": unlisted,
                      "compiled_after_warm_up": grew, "x": np.asarray(est.result.x_hat).tolist()}))
""")


def _coverage(mode: str, jobs: int = 1, env: dict | None = None) -> dict:
    env = dict(os.environ if env is None else env, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", COVERAGE, mode, str(jobs), str(ROOT)], env=env, check=True,
                         capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _sixbar_estimates() -> np.ndarray:
    from exuflex.mechanism import load_mechanism
    from exuflex.observer.session import ObserverConfig, estimate, make_observer
    from exuflex.runs import held_torques
    from exuflex.runs import read_run

    mech = load_mechanism(ROOT / "models" / "sixbar.toml")
    S = read_run(ROOT / "tests" / "data" / "sixbar_short").sensors
    obs = make_observer(mech, ObserverConfig.for_model(mech))
    est = estimate(obs, S.t, held_torques(S.select(mech.motor_names).data), S.select(obs.channels).data)
    return np.asarray(est.result.x_hat)


def test_the_groups_compile_every_kernel_the_observer_compiles():
    """In a fresh process (numba's cache as the suite uses it), after the groups' warm-ups building observers and
    filtering a log compiles no further kernel or signature, every listed kernel was compiled by its group's
    warm-up, and the cache then holds every group."""
    rec = _coverage("warm_up")
    assert rec["compiled_after_warm_up"] == []
    assert rec["unlisted"] == []
    assert rec["missing_after"] == []
    assert np.array_equal(np.array(rec["x"]), _sixbar_estimates())


@pytest.mark.slow
def test_parallel_first_compile_from_an_empty_cache(tmp_path):
    """An empty cache folder: every group is missing, ``prepare`` compiles them in two processes into it, and the
    observer then compiles nothing more and gives the estimates of this process (kernels compiled elsewhere)."""
    rec = _coverage("prepare", 2, dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path)))
    assert sorted(rec["missing_before"]) == sorted(g.name for g in _compile.groups())
    assert rec["missing_after"] == []
    assert rec["compiled_after_warm_up"] == []
    assert np.array_equal(np.array(rec["x"]), _sixbar_estimates())
    assert any(tmp_path.rglob("*.nbi"))


def _group(name, cost, calls, needs=()):
    return KernelGroup(name, lambda: calls.append(name), (f"{name}_kernel",), cost, needs)


def _names(shares):
    return [[x.name for x in s] for s in shares]


def test_the_plan_balances_the_groups_by_cost(monkeypatch):
    monkeypatch.setattr(_compile, "START_COST", 1.5)
    calls = []
    g = [_group(n, c, calls) for n, c in (("a", 1.0), ("b", 18.0), ("c", 12.5), ("d", 5.0))]
    assert _names(_compile.plan(g, 2)) == [["a", "b"], ["d", "c"]]  # 19 here, 1.5 + 17.5 in a subprocess
    assert _compile._finish(_compile.plan(g, 2)) == 19.0
    assert _names(_compile.plan(g, 1)) == [["a", "d", "c", "b"]]
    assert _names(_compile.plan(g[:2], 8)) == [["b"], ["a"]]  # no empty shares: two groups, two processes
    assert _compile._finish(_compile.plan(g, 3)) == 18.0
    # every assignment is tried: 3 + 4 against 4 + 2 + 2 (costs 4, 3, 3, 2, 2 in two shares)
    monkeypatch.setattr(_compile, "START_COST", 0.0)
    g = [_group(n, c, calls) for n, c in (("p", 3.0), ("q", 3.0), ("r", 2.0), ("s", 2.0), ("t", 4.0))]
    assert sorted(sum(x.cost for x in s) for s in _compile.plan(g, 2)) == [7.0, 7.0]


def test_a_group_waits_for_the_groups_it_needs(monkeypatch):
    """The sample loop's case: ``loop`` calls the kernels of ``x``, ``m`` and ``k``. Best: ``x`` first in this
    process, then ``red`` (8 + 20 = 28); in the other, ``h``, ``m``, ``k`` from 1.5 to 16.5, then ``loop``, whose
    ``x`` is cached since 8, to 27.5."""
    monkeypatch.setattr(_compile, "START_COST", 1.5)
    calls = []
    g = [_group("red", 20.0, calls), _group("h", 5.0, calls), _group("x", 8.0, calls), _group("m", 5.0, calls),
         _group("k", 5.0, calls), _group("loop", 11.0, calls, needs=("x", "m", "k"))]
    shares = _compile.plan(g, 2)
    assert _names(shares) == [["x", "red"], ["h", "m", "k", "loop"]]
    assert _compile._finish(shares) == 28.0
    late = [[g[0], g[2]], [g[1], g[3], g[4], g[5]]]  # x after red: the loop waits until 28, ends at 39
    assert _compile._finish(late) == 39.0
    wait = [_group("w1", 1.0, calls, needs=("w2",))], [_group("w2", 1.0, calls, needs=("w1",))]
    assert _compile._finish(list(wait)) == float("inf")  # two groups waiting on each other


def test_waiting_for_a_needed_group_ends_when_it_is_cached_or_its_process_ended():
    class Compiling:  # another process's group, in numba's cache from the third look on
        name, cost, looks = "x", 0.0, 0

        def cached(self):
            self.looks += 1
            return self.looks >= 3

    loop = _group("loop", 1.0, [], needs=("x",))
    other = Compiling()
    _compile._await_needs(loop, set(), {"x": other})
    assert other.looks == 3
    _compile._await_needs(loop, {"x"}, {"x": other})  # compiled in this process: no look
    assert other.looks == 3
    other.looks = -10**6
    _compile._await_needs(loop, set(), {"x": other}, alive=lambda: False)  # its process ended: no wait
    assert other.looks == -10**6 + 1


def test_the_number_of_processes(monkeypatch):
    monkeypatch.setenv(_compile.JOBS_ENV, "3")
    assert _compile.jobs() == 3
    assert _compile.jobs(1) == 1
    monkeypatch.delenv(_compile.JOBS_ENV)
    assert _compile.jobs() == min(2, len(os.sched_getaffinity(0)))
    for bad in ("two", "0"):
        monkeypatch.setenv(_compile.JOBS_ENV, bad)
        with pytest.raises(ValueError, match=r"^EXUFLEX_COMPILE_JOBS.*expected a whole number of processes >= 1"):
            _compile.jobs()


def _fake(monkeypatch, groups, writable=True):
    monkeypatch.setattr(_compile, "_prepared", set())
    monkeypatch.setattr(_compile, "_started", None)
    monkeypatch.setattr(_compile, "missing", lambda: list(groups))
    monkeypatch.setattr(_compile, "_writable", lambda kernel: writable)


def test_a_failed_compiling_process_leaves_its_groups_to_this_one(monkeypatch, caplog):
    """The subprocess is asked for groups it does not know (they exist in this process only), so it fails; this
    process then compiles them itself, says so in the log, and raises nothing."""
    calls, lines = [], []
    _fake(monkeypatch, [_group("here_only_a", 2.0, calls), _group("here_only_b", 1.0, calls)])
    monkeypatch.setattr(_compile, "START_COST", 0.0)
    with caplog.at_level("INFO", logger="exuflex._compile"):
        _compile.prepare(2, progress=lines.append)
    assert calls == ["here_only_a", "here_only_b"]
    assert lines[0] == "compiling numba kernels (first run, 2 processes) ..."
    assert lines[-1].startswith("numba kernels compiled in ")
    assert any("the process compiling here_only_b ended with 2" in r.message for r in caplog.records)
    assert _compile.prepare(2) == 0.0  # once per process


def test_no_subprocess_without_a_writable_cache_or_with_one_job(monkeypatch):
    def no_subprocess(*a, **k):
        raise AssertionError("no subprocess expected")

    monkeypatch.setattr(_compile.subprocess, "Popen", no_subprocess)
    for writable, jobs in ((False, 2), (True, 1)):
        calls, lines = [], []
        _fake(monkeypatch, [_group("a", 2.0, calls), _group("b", 1.0, calls)], writable)
        _compile.prepare(jobs, progress=lines.append)
        assert sorted(calls) == ["a", "b"]
        assert lines[0] == "compiling numba kernels (first run, 1 process) ..."


def test_a_process_that_cannot_start_leaves_its_groups_to_this_one_in_order(monkeypatch):
    def cannot_start(*a, **k):
        raise OSError("no more processes")

    monkeypatch.setattr(_compile.subprocess, "Popen", cannot_start)
    monkeypatch.setattr(_compile, "START_COST", 0.0)
    calls = []
    _fake(monkeypatch, [_group("a", 10.0, calls), _group("loop", 5.0, calls, needs=("b",)), _group("b", 5.0, calls)])
    assert _names(_compile.plan(_compile.missing(), 2)) == [["a"], ["b", "loop"]]
    _compile.prepare(2, progress=lambda msg: None)
    assert calls == ["a", "b", "loop"]


def test_the_augmented_groups_are_compiled_for_the_augmented_estimators_only(monkeypatch):
    """A plain observer's first use leaves the augmented estimators' groups to theirs; a later augmented one
    compiles them then (once)."""
    calls = []
    monkeypatch.setattr(_compile.subprocess, "Popen", lambda *a, **k: (_ for _ in ()).throw(OSError("none")))
    _fake(monkeypatch, [_group("a", 1.0, calls), _group(_compile.AUGMENTED_GROUPS[0], 1.0, calls)])
    _compile.prepare(1, progress=lambda msg: None)
    assert calls == ["a"]
    assert _compile.prepare(1, progress=lambda msg: None) == 0.0 and calls == ["a"]
    monkeypatch.setattr(_compile, "missing", lambda: [_group(_compile.AUGMENTED_GROUPS[0], 1.0, calls)])
    _compile.prepare(1, progress=lambda msg: None, augmented=True)
    assert calls == ["a", _compile.AUGMENTED_GROUPS[0]]
    assert _compile.prepare(1, progress=lambda msg: None, augmented=True) == 0.0
    assert _compile.prepare(1, progress=lambda msg: None) == 0.0


def test_every_needed_group_is_registered():
    names = [g.name for g in _compile.groups()]
    assert len(set(names)) == len(names)
    assert all(n in names for g in _compile.groups() for n in g.needs)


def test_a_failed_warm_up_is_reported_and_left_to_the_first_call(monkeypatch, caplog):
    def broken():
        raise RuntimeError("no such signature")

    _fake(monkeypatch, [KernelGroup("broken", broken, (), 1.0)])
    with caplog.at_level("WARNING", logger="exuflex._compile"):
        _compile.prepare(1, progress=lambda msg: None)
    assert "compiling the broken kernels ahead failed (RuntimeError: no such signature)" in caplog.text


def test_nothing_to_compile_without_the_jit_or_with_a_warm_cache(monkeypatch):
    import numba

    monkeypatch.setattr(numba.config, "DISABLE_JIT", True)
    assert _compile.missing() == []
    monkeypatch.setattr(numba.config, "DISABLE_JIT", False)
    calls = []
    monkeypatch.setattr(_compile, "_prepared", set())
    monkeypatch.setattr(_compile, "_started", None)
    monkeypatch.setattr(_compile, "missing", list)
    assert _compile.prepare(2, progress=calls.append) == 0.0
    assert calls == []


def test_the_cache_check_reads_numbas_index(tmp_path, monkeypatch):
    """A kernel's cache entry is missing before its first call and present after (numba's own index, in the
    ``__pycache__`` beside a module's source)."""
    (tmp_path / "tiny_kernel.py").write_text("import numba\n\n@numba.njit(cache=True)\ndef twice(x):\n"
                                             "    return 2.0 * x\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    import numba

    if numba.config.CACHE_DIR:
        pytest.skip("numba's cache folder is set for this process: the index is not beside the source")
    import tiny_kernel

    assert not _compile._cached(tiny_kernel.twice)
    assert tiny_kernel.twice(1.5) == 3.0
    assert _compile._cached(tiny_kernel.twice)
    assert _compile._writable(tiny_kernel.twice)
    assert _compile._cached(tiny_kernel.twice.py_func)  # not a dispatcher (NUMBA_DISABLE_JIT): nothing to do


def test_the_checks_group_is_compiled_here_first(monkeypatch):
    """The group a command's checks call before ``prepare`` is in this process's share, before the rest, whatever
    the costs (here the cheaper split would send it to the other process)."""
    monkeypatch.setattr(_compile, "START_COST", 0.0)
    calls = []
    g = [_group("a", 10.0, calls), _group("b", 9.0, calls), _group("kin", 1.0, calls)]
    assert _names(_compile.plan(g, 2)) == [["a"], ["kin", "b"]]
    assert _names(_compile.plan(g, 2, here=("kin",))) == [["kin", "b"], ["a"]]
    assert _names(_compile.plan(g, 1, here=("kin",))) == [["kin", "b", "a"]]  # then cheapest first


class _Running:
    """A compiling subprocess that runs until it is killed or waited for (then it ends with 0)."""

    def __init__(self, log, share):
        self.log, self.share, self.rc = log, share, None

    def poll(self):
        return self.rc

    def kill(self):
        self.log.append(("kill", self.share))
        self.rc = -9

    def wait(self, timeout=None):
        if self.rc is None:
            self.log.append(("done", self.share))
            self.rc = 0
        return self.rc


def _fake_popen(monkeypatch, log):
    def popen(cmd, **kw):
        share = tuple(cmd[3:])
        log.append(("start", share))
        return _Running(log, share)

    monkeypatch.setattr(_compile.subprocess, "Popen", popen)


def test_start_returns_at_once_and_prepare_finishes(monkeypatch):
    """``start`` plans and starts the other process's share, and returns: what this process runs before
    ``prepare`` (the checks) comes first; ``prepare`` compiles this process's share, waits for the other and
    loads its groups; a second ``prepare`` does nothing."""
    monkeypatch.setattr(_compile, "START_COST", 0.0)
    calls, log, lines = [], [], []
    _fake(monkeypatch, [_group("a", 10.0, calls), _group("b", 9.0, calls), _group(_compile.CHECKS_GROUP, 1.0, calls)])
    _fake_popen(monkeypatch, log)
    _compile.start(2, progress=lines.append)
    assert log == [("start", ("a",))] and calls == []
    assert lines == ["compiling numba kernels (first run, 2 processes) ..."]
    calls.append("checks")
    assert _compile.prepare(2, progress=lines.append) >= 0.0
    assert calls == ["checks", _compile.CHECKS_GROUP, "b", "a"]  # "a" loaded from the other process's cache
    assert log == [("start", ("a",)), ("done", ("a",))]
    assert lines[1:-1] == [f"compiled the {name} kernels ({k} of 3 groups, 0 s)"
                           for k, name in enumerate((_compile.CHECKS_GROUP, "b", "a"), 1)]
    assert lines[-1].startswith("numba kernels compiled in ")
    n = len(lines)
    assert _compile.prepare(2, progress=lines.append) == 0.0 and len(lines) == n


def test_a_start_without_prepare_is_stopped_at_exit(monkeypatch):
    """The command fails between ``start`` and ``prepare`` (a bad log): at the interpreter's exit the subprocesses
    still compiling are stopped."""
    monkeypatch.setattr(_compile, "START_COST", 0.0)
    calls, log = [], []
    _fake(monkeypatch, [_group("a", 10.0, calls), _group("b", 9.0, calls)])
    _fake_popen(monkeypatch, log)
    _compile.start(2, progress=lambda msg: None)
    assert log == [("start", ("b",))]
    _compile._stop_started()
    assert log == [("start", ("b",)), ("kill", ("b",))]
    assert _compile._started is None and calls == []
