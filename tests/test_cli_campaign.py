"""Property-based campaign over the command line's argument space: every command with random flags and values
(good ones, bad ones, random text, paths to nothing, to folders, to the wrong kind of file) may end only in

- exit 0 (``--help``), or exit 2 with exactly one ``error`` line on stderr, no traceback, no 'internal error';
- or reach the computation: the stage right after the argument checks is replaced by a sentinel (the plan of
  the manoeuvre for ``simulate``, the observer's construction for ``observe``, the modal analysis for ``modes``,
  the study's settings record for ``study``, the whole work for ``reproduce`` and ``bench``), so that every
  case costs milliseconds; the computations themselves are tested elsewhere.

The default suite runs 150 cases; the campaign (``-m slow``) runs 6,000 and prints the tally:

    python -m pytest -m slow tests/test_cli_campaign.py -s
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from exuflex.cli import main

ROOT = Path(__file__).resolve().parents[1]
SIXBAR = str(ROOT / "models" / "sixbar.toml")
FOURBAR = str(ROOT / "models" / "fourbar.toml")
RUN = str(ROOT / "tests" / "data" / "sixbar_short")
CSV = str(ROOT / "tests" / "data" / "sixbar_short" / "sensors.csv")
META = str(ROOT / "tests" / "data" / "sixbar_short" / "meta.json")

TALLY: Counter = Counter()


class Reached(BaseException):
    """The arguments passed every check: the computation would start here."""


NUMBERS = ["0", "1", "-1", "-3", "0.5", "1e-9", "1e-4", "0.002", "0.01", "0.1", "3", "1000", "1e6", "1e300", "inf",
           "-inf", "nan", "abc", "", " ", "1,2", "0x10", "1_000", "2**3", "--", "3.0.0", "9" * 30, "-0"]
NAMES = ["q1", "q2", "q3", "c1", "c2", "c4", "q3rel", "tip_x", "tip_y", "T1", "foo", "", ",", "q1,q1", "q1,foo",
         "q1,q2,q3,c1,c2,c4", "c1,c2,c4", "x14", "yy15", "x14,y15,theta24,x25,y26", "x14,x14", "auto", " q1 ",
         "q1,,q2", "é", "q1=1", "T1=0.02", "c1=5e-5,T1=0.01", "q1=-1", "foo=1", "T1=", "=1", "T1=abc,T1=1"]
PATHS = [SIXBAR, FOURBAR, RUN, CSV, META, "/nonexistent/x.toml", "", ".", "/dev/null", str(ROOT / "README.md"),
         str(ROOT / "models"), "-"]
SETS = ["links.L1.diameter=0.03", "links.L9.diameter=0.03", "payload.mass=1,2", "links.L1.diameter=", "x=1",
        "links.L1.diameter=abc", "damping.alpha=-1", "links..diameter=1", "materials.aluminium.E=7e10",
        "links.L1.colour=red", "=", "payload.mass=0"]

FLAGS = {
    "modes": {"--q": NUMBERS + ["1.08,2.64,4.71", "1,2"], "--fmax": NUMBERS, "--refine": NUMBERS,
              "--masters": NAMES, "--n-interior": NUMBERS + ["auto"], "--qstar": NUMBERS + ["1.08,2.64,4.71"],
              "--locked": None, "--json": None, "--reduced": None, "--elements-per-link": NUMBERS + ["file"],
              "--along": NUMBERS, "--beam": ["ancf", "ge", "x"]},
    "simulate": {"--out": ["OUT", "", "/dev/null/x", "OUT/a/b"], "--engine": ["erls", "exudyn", "foo", ""],
                 "--duration": NUMBERS, "--payload-scale": NUMBERS, "--seed": NUMBERS, "--h": NUMBERS,
                 "--no-progress": None, "--manoeuvre": PATHS, "--elements-per-link": NUMBERS + ["file"],
                 "--beam": ["ancf", "ge", "x"], "--integrator": ["gen-alpha", "rk4", "euler"]},
    "observe": {"--map": NAMES + ["T1=T1,q1=q1", "q1=nosuch", "a=b=c"], "--time-column": ["time", "t", ""],
                "--time-scale": NUMBERS, "--truth": PATHS, "--out": ["OUT", ""], "--json": None,
                "--channels": NAMES, "--masters": NAMES, "--n-interior": NUMBERS + ["auto"],
                "--method": ["cached", "frozen", "rk4", "x"], "--substep": NUMBERS, "--q0": NUMBERS + ["1.08,2.64,4.71"],
                "--qd0": NUMBERS + ["0,0,0"], "--q0-std": NUMBERS, "--qd0-std": NUMBERS, "--elastic0-std": NUMBERS,
                "--elastic-rate0-std": NUMBERS, "--noise": NAMES, "--q-scale": NUMBERS, "--q-extra": NUMBERS,
                "--start-up": NUMBERS, "--bound": None, "--no-plots": None},
    "study payload": {"--out": ["OUT", ""], "--runs": NUMBERS, "--workers": NUMBERS, "--quick": None,
                      "--engine": ["erls", "reduced", "exudyn", "x"], "--duration": NUMBERS, "--seed": NUMBERS,
                      "--start-up": NUMBERS, "--h": NUMBERS, "--levels": NUMBERS + ["0,50,100", "0,-200", "a,b"],
                      "--no-progress": None, "--manoeuvre": PATHS, "--elements-per-link": NUMBERS + ["file"],
                 "--beam": ["ancf", "ge", "x"], "--integrator": ["gen-alpha", "rk4", "euler"]},
    "study sweep": {"--out": ["OUT", ""], "--runs": NUMBERS, "--quick": None, "--duration": NUMBERS,
                    "--seed": NUMBERS, "--h": NUMBERS, "--set": SETS, "--start-up": NUMBERS},
    "reproduce": {"--model": PATHS, "--out": ["OUT", ""], "--quick": None, "--workers": NUMBERS,
                  "--seed": NUMBERS, "--runs": NUMBERS, "--engine": ["erls", "exudyn", "x"]},
    "bench": {"--json": None, "--quick": None, "--duration": NUMBERS, "--no-full": None, "--seed": NUMBERS,
              "--repeat": NUMBERS},
}
POSITIONAL = {"modes": [[SIXBAR]], "simulate": [[SIXBAR]], "observe": [[SIXBAR, RUN], [SIXBAR, CSV]],
              "study payload": [[SIXBAR]], "study sweep": [[SIXBAR]], "reproduce": [[]], "bench": [[], [SIXBAR]]}


@st.composite
def argv(draw, out_dir: str):
    cmd = draw(st.sampled_from(sorted(FLAGS)))
    pos = list(draw(st.sampled_from(POSITIONAL[cmd])))
    if draw(st.integers(0, 9)) == 0:  # a wrong positional
        pos = [draw(st.sampled_from(PATHS + NAMES)) for _ in range(draw(st.integers(0, 3)))]
    words = cmd.split() + pos
    flags = FLAGS[cmd]
    for flag in draw(st.lists(st.sampled_from(sorted(flags)), max_size=5)):
        words.append(flag)
        if flags[flag] is not None:
            if draw(st.integers(0, 7)) == 0:
                words.append(draw(st.text(max_size=8)))
            else:
                v = draw(st.sampled_from(flags[flag]))
                words.append(v.replace("OUT", out_dir))
    if cmd == "study sweep" and "--set" not in words and draw(st.booleans()):
        words += ["--set", draw(st.sampled_from(SETS))]
    if cmd in ("simulate", "study payload", "study sweep", "reproduce") and "--out" not in words:
        words += ["--out", out_dir]
    if draw(st.integers(0, 19)) == 0:
        words.insert(draw(st.integers(0, len(words))), "--debug")
        words = [w for w in words if w != "--debug"]  # --debug raises by design; it is tested elsewhere
    if draw(st.integers(0, 29)) == 0:
        words.insert(draw(st.integers(0, len(words))), draw(st.sampled_from(["--help", "--version", "--bogus"])))
    return words


def _sentinels(monkeypatch):
    import exuflex.bench
    import exuflex.cli.reproduce
    import exuflex.erls.modal
    import exuflex.manoeuvre
    import exuflex.observer.session as session
    from exuflex.study.runner import StudySpec
    from exuflex.validate import check_observer_settings

    def reach(*a, **k):
        raise Reached

    def observer(mech, config=None, *a, **k):
        check_observer_settings(mech, config or session.ObserverConfig())
        raise Reached

    monkeypatch.setattr(exuflex.manoeuvre, "plan", reach)
    monkeypatch.setattr(exuflex.erls.modal, "modal_analysis", reach)
    monkeypatch.setattr(session, "make_observer", observer)
    monkeypatch.setattr(StudySpec, "settings", reach)
    monkeypatch.setattr(exuflex.cli.reproduce, "reproduce", reach)
    monkeypatch.setattr(exuflex.bench, "run_bench", reach)


def _check(words, capsys):
    try:
        rc = main(list(words))
    except Reached:
        capsys.readouterr()
        TALLY["reached the computation"] += 1
        return
    cap = capsys.readouterr()
    err = cap.err
    assert "Traceback" not in err, (words, err)
    assert "internal error" not in err, (words, err)
    if rc == 0:
        TALLY["exit 0 (help, version)"] += 1
        return
    assert rc == 2, (words, rc, err)
    errors = [ln for ln in err.splitlines() if ": error: " in ln]
    assert len(errors) == 1, (words, err)
    assert all(ln.startswith("exuflex") or ln.startswith("usage") is False for ln in err.splitlines()), (words, err)
    TALLY["one-line error, exit 2"] += 1


def _campaign(n: int, tmp_path, capsys, monkeypatch):
    _sentinels(monkeypatch)
    TALLY.clear()

    @settings(max_examples=n, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))
    @given(argv(str(tmp_path / "out")))
    def case(words):
        _check(words, capsys)

    case()
    return TALLY


def test_campaign_small(tmp_path, capsys, monkeypatch):
    tally = _campaign(150, tmp_path, capsys, monkeypatch)
    assert sum(tally.values()) >= 150


@pytest.mark.slow
def test_campaign(tmp_path, capsys, monkeypatch):
    tally = _campaign(6000, tmp_path, capsys, monkeypatch)
    with capsys.disabled():
        print(f"\nCLI campaign: {sum(tally.values())} cases, {dict(tally)}; 0 tracebacks, 0 internal errors")
    assert sum(tally.values()) >= 5000
