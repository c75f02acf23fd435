"""Property-based fuzzing: random mutations of models/sixbar.toml and of a sensor log may only produce the
documented errors (ModelFileError, LogFormatError, FileNotFoundError, FilterDivergedError), never another
exception type, and never a silent NaN (a loaded model is all finite; a filter result holds NaN only when it
is flagged non-finite).

The default suite runs a few hundred cases (seconds); the campaign (``-m slow``) runs >= 10,000 per target:

    /tmp/venv/bin/python -m pytest -m slow tests/test_fuzz.py -s
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import shutil
import tempfile
import tomllib
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from exuflex.errors import LogFormatError
from exuflex.mechanism import Mechanism, ModelFileError, load_mechanism, parse_mechanism
from exuflex.observer import FilterDivergedError
from exuflex.observer.session import default_channels
from exuflex.runs import read_run
from exuflex.validate import check_configurations, check_run

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "models" / "sixbar.toml"
RUN = ROOT / "tests" / "data" / "sixbar_short"
with open(MODEL, "rb") as _fh:
    DOC = tomllib.load(_fh)
SENSORS_TEXT = (RUN / "sensors.csv").read_text()
META_TEXT = (RUN / "meta.json").read_text()

STATS: Counter = Counter()


# ------------------------------------------------------------------------------ model-file mutations
def _paths(node, prefix=()):
    """Every addressable place in the document: table keys and list items, depth first."""
    out = []
    if isinstance(node, dict):
        for k, v in node.items():
            out.append(prefix + (k,))
            out += _paths(v, prefix + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out.append(prefix + (i,))
            out += _paths(v, prefix + (i,))
    return out


PATHS = _paths(DOC)
REPLACEMENTS = ["", "L1", "L6", "O", "E", "q1", "q9", "x14", "x999", "aluminium", "steel", "encoder", "tip_arc",
                True, 0, -1, 3, 0.0, 1e-12, 1e300, float("nan"), float("inf"), [], [1.0], [0.0, 0.0], ["x14"], {},
                {"link": "L1", "station": 0.0}]


def _get(doc, path):
    node = doc
    for k in path:
        node = node[k]
    return node


def _mutate(doc, path, op, value):
    parent = _get(doc, path[:-1])
    key = path[-1]
    old = parent[key]
    if op == "delete":
        del parent[key]
    elif op == "scale":
        if isinstance(old, bool) or not isinstance(old, (int, float)):
            parent[key] = value
        else:
            parent[key] = old * value if not (isinstance(value, float) and math.isnan(value)) else value
    elif op == "rename":
        parent[key] = (old + "X") if isinstance(old, str) else value
    elif op == "retype":
        parent[key] = value
    elif op == "add_key" and isinstance(old, dict):
        old["bogus_key"] = value
    else:
        parent[key] = value


mutation = st.tuples(
    st.sampled_from(PATHS),
    st.sampled_from(["delete", "scale", "rename", "retype", "add_key"]),
    st.one_of(st.sampled_from([0, -1, 1e9, float("nan"), 1e-9, 1000.0, 0.001]), st.sampled_from(REPLACEMENTS)),
)


def _all_finite(obj) -> bool:
    if isinstance(obj, float):
        return math.isfinite(obj)
    if isinstance(obj, (list, tuple)):
        return all(_all_finite(x) for x in obj)
    if isinstance(obj, dict):
        return all(_all_finite(x) for x in obj.values())
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return all(_all_finite(getattr(obj, f.name)) for f in dataclasses.fields(obj))
    return True


def _check_model(muts, with_configurations: bool) -> None:
    doc = copy.deepcopy(DOC)
    for path, op, value in muts:
        try:
            _mutate(doc, path, op, value)
        except (KeyError, IndexError, TypeError):
            pass  # the path vanished after an earlier mutation
    try:
        mech = parse_mechanism(doc, "sixbar.toml")
    except ModelFileError as exc:
        msg = str(exc)
        assert msg.startswith("sixbar.toml: ") and ": expected " in msg and "\n" not in msg, msg
        STATS["model: ModelFileError"] += 1
        return
    assert isinstance(mech, Mechanism)
    assert _all_finite(mech), "a loaded model holds a non-finite number"
    if with_configurations:
        try:
            check_configurations(mech)
        except ModelFileError as exc:
            assert str(exc).startswith("sixbar.toml: ")
            STATS["model: ModelFileError (configuration)"] += 1
            return
    STATS["model: accepted"] += 1


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(mutation, min_size=1, max_size=3))
def test_fuzz_model_file(muts):
    _check_model(muts, with_configurations=False)


@settings(max_examples=40, deadline=None)
@given(st.lists(mutation, min_size=1, max_size=2))
def test_fuzz_model_file_configurations(muts):
    _check_model(muts, with_configurations=True)


# ------------------------------------------------------------------------------ log mutations
CELLS = ["", "nan", "NaN", "inf", "-inf", "1e308", "-1e308", "abc", "0", "1e6", "-0.0", "0x10", " ", "1,2"]


@st.composite
def log_mutation(draw):
    lines = SENSORS_TEXT.splitlines()
    n = len(lines)
    kind = draw(st.sampled_from(["cell", "delete_row", "dup_row", "swap_rows", "time_scale", "time_offset",
                                 "jitter", "drop_col", "dup_header", "truncate", "bom", "garbage_line",
                                 "empty_rows", "scale_col", "meta"]))
    i = draw(st.integers(1, n - 1))
    j = draw(st.integers(0, 12))
    return kind, i, j, draw(st.sampled_from(CELLS)), draw(st.sampled_from([1e-3, 1e3, -1.0, 0.5, 2.0, 57.3, 1e9]))


def _apply_log(muts):
    lines = SENSORS_TEXT.splitlines()
    meta = json.loads(META_TEXT)
    raw_tail = None
    for kind, i, j, cell, x in muts:
        n = len(lines)
        i = min(i, n - 1) if n > 1 else 0
        rows = [ln.split(",") for ln in lines]
        if kind == "cell" and n > 1:
            r = rows[i]
            r[min(j, len(r) - 1)] = cell
        elif kind == "delete_row" and n > 1:
            del rows[i]
        elif kind == "dup_row" and n > 1:
            rows.insert(i, list(rows[i]))
        elif kind == "swap_rows" and n > 2:
            k = max(1, i - 1)
            rows[k], rows[i] = rows[i], rows[k]
        elif kind in ("time_scale", "time_offset", "jitter"):
            for k, r in enumerate(rows[1:]):
                try:
                    t = float(r[0])
                except ValueError:
                    continue
                if kind == "time_scale":
                    t *= x
                elif kind == "time_offset":
                    t += x
                elif k % 3 == 1:
                    t += 1e-4 * x
                r[0] = repr(t)
        elif kind == "drop_col":
            rows = [r[:j] + r[j + 1 :] for r in rows]
        elif kind == "dup_header" and rows:
            rows[0][min(j, len(rows[0]) - 1)] = rows[0][0 if j else 1]
        elif kind == "truncate":
            text = "\n".join(",".join(r) for r in rows)
            raw_tail = text[: int(len(text) * (i / max(n, 1)) * 0.9)]
        elif kind == "bom" and rows:
            rows[0][0] = "\ufeff" + rows[0][0]
        elif kind == "garbage_line":
            rows.insert(i, ["#", cell, "\x00"] if j % 2 else [cell])
        elif kind == "empty_rows":
            for r in rows[i : i + 1 + j]:
                r[4:] = [""] * (len(r) - 4)
        elif kind == "scale_col" and n > 1:
            for r in rows[1:]:
                try:
                    r[j] = repr(float(r[j]) * x)
                except (ValueError, IndexError):
                    pass
        elif kind == "meta":
            key = ["motors", "sensors", "truth", "units"][j % 4]
            meta[key] = [None, "q1", {}, [1], ["T1"], ["zz"]][i % 6]
        lines = [",".join(r) for r in rows]
    text = raw_tail if raw_tail is not None else "\n".join(lines) + "\n"
    return text, meta


@pytest.fixture(scope="module")
def observer_env():
    from exuflex.observer.session import make_observer

    mech = load_mechanism(MODEL)
    return mech, make_observer(mech)


def _check_log(muts, mech, observer) -> None:
    from exuflex.scoring.run import observe_run

    text, meta = _apply_log(muts)
    d = Path(tempfile.mkdtemp(prefix="fuzzrun"))
    try:
        shutil.copy(RUN / "truth.csv", d / "truth.csv")
        (d / "sensors.csv").write_text(text, encoding="utf-8")
        (d / "meta.json").write_text(json.dumps(meta))
        try:
            run = read_run(d)
        except (LogFormatError, FileNotFoundError) as exc:
            assert str(d) in str(exc), str(exc)
            STATS["log: rejected by read_run"] += 1
            return
        try:
            check_run(mech, run, default_channels(mech))
        except LogFormatError as exc:
            assert str(d) in str(exc), str(exc)
            STATS["log: rejected by check_run"] += 1
            return
        if observer is None:
            STATS["log: accepted (observer not run)"] += 1
            return
        try:
            out = observe_run(mech, run, observer=observer, with_bound=False)
        except FilterDivergedError:
            STATS["log: observer raised FilterDivergedError"] += 1
            return
        except LogFormatError as exc:  # a truth that does not cover the (shifted, cut) log: refused, named
            assert "truth.csv: the truth covers" in str(exc)
            STATS["log: truth does not cover it (observe_run)"] += 1
            return
        res = out.estimate.result
        if not res.nonfinite:
            assert np.all(np.isfinite(res.x_hat)), "silent NaN in the estimates"
            assert np.all(np.isfinite(out.estimate.physical.data)), "silent NaN in the physical estimates"
        else:
            assert res.diverged and res.diverged_at is not None
        STATS["log: observed" + (" (diverged flagged)" if res.diverged else "")] += 1
    finally:
        shutil.rmtree(d, ignore_errors=True)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(muts=st.lists(log_mutation(), min_size=1, max_size=3))
def test_fuzz_log_reading(muts, observer_env):
    _check_log(muts, observer_env[0], None)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                 HealthCheck.function_scoped_fixture])
@given(muts=st.lists(log_mutation(), min_size=1, max_size=2))
def test_fuzz_log_through_the_observer(muts, observer_env):
    _check_log(muts, *observer_env)


# ------------------------------------------------------------------------------ the campaign
@pytest.mark.slow
def test_fuzz_campaign(observer_env):
    """>= 10,000 model mutations, >= 10,000 log mutations (reader + observer check), 500 through the observer."""
    STATS.clear()
    mech, obs = observer_env

    @settings(max_examples=10_000, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    @given(st.lists(mutation, min_size=1, max_size=4))
    def models(muts):
        _check_model(muts, with_configurations=False)

    @settings(max_examples=500, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    @given(st.lists(mutation, min_size=1, max_size=2))
    def configurations(muts):
        _check_model(muts, with_configurations=True)

    @settings(max_examples=10_000, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    @given(st.lists(log_mutation(), min_size=1, max_size=4))
    def logs(muts):
        _check_log(muts, mech, None)

    @settings(max_examples=500, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    @given(st.lists(log_mutation(), min_size=1, max_size=3))
    def observed(muts):
        _check_log(muts, mech, obs)

    for f in (models, configurations, logs, observed):
        f()
    total = sum(STATS.values())
    print(f"\nfuzz campaign: {total} cases")
    for k, v in sorted(STATS.items()):
        print(f"  {k:45s} {v:6d}")
    assert total >= 21_000
