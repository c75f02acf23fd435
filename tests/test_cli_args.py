"""Every argument error is one line on stderr with exit code 2 (no traceback), ``--version``, ``--debug``
anywhere; the public functions check their arguments the same way. The 21 cases of issue 17 are listed by name.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from exuflex.cli import main
from exuflex.errors import UsageError

ROOT = Path(__file__).resolve().parents[1]
SIXBAR = str(ROOT / "models" / "sixbar.toml")
RUN = str(ROOT / "tests" / "data" / "sixbar_short")
TEXT = Path(SIXBAR).read_text()


def _model(tmp_path: Path, name: str, text: str) -> str:
    p = tmp_path / f"{name}.toml"
    p.write_text(text)
    return str(p)


def _no_sensors(tmp_path):
    return _model(tmp_path, "nosensors", re.sub(r"\[\[sensors\]\]\n(?:[^\[\n][^\n]*\n|\n)*", "", TEXT))


def _short_manoeuvre(tmp_path):
    return _model(tmp_path, "short", TEXT.replace("duration = 3.0", "duration = 1e-6").replace("ramp_time = 0.08",
                                                                                           "ramp_time = 2e-7"))


def _two_motors(tmp_path):
    # the third motor removed: two motors for three coordinates
    blocks = TEXT.split("[[motors]]")
    return _model(tmp_path, "twomotors", "[[motors]]".join(blocks[:-1]) + "[[" + blocks[-1].split("[[", 1)[1])


def _lab_csv(tmp_path):
    p = tmp_path / "lab.csv"
    p.write_text((ROOT / RUN / "sensors.csv").read_text())
    return str(p)


# (id, argv builder, a phrase the one line must contain)
CASES = [
    ("channels q1,foo", lambda tp: ["observe", SIXBAR, RUN, "--channels", "q1,foo"], "'foo'"),
    ("duplicate channels", lambda tp: ["observe", SIXBAR, RUN, "--channels", "q1,q1"], "repeated"),
    ("channel without noise", lambda tp: ["observe", SIXBAR, RUN, "--channels", "q1,tip_x"], "noise_std"),
    ("n-interior abc", lambda tp: ["observe", SIXBAR, RUN, "--n-interior", "abc"], "--n-interior"),
    ("n-interior -3", lambda tp: ["observe", SIXBAR, RUN, "--n-interior", "-3"], "--n-interior"),
    ("n-interior 1000", lambda tp: ["observe", SIXBAR, RUN, "--n-interior", "1000"], "n_interior"),
    ("masters typo", lambda tp: ["observe", SIXBAR, RUN, "--masters", "x14,yy15"], "yy15"),
    ("payload-nominal-p 2", lambda tp: ["observe", SIXBAR, RUN, "--payload-nominal-p", "2"], "--payload-nominal-p"),
    ("empty masters", lambda tp: ["observe", SIXBAR, RUN, "--masters", ","], "--masters"),
    ("model with no sensors", lambda tp: ["observe", _no_sensors(tp), RUN], "no sensor"),
    ("duration 1e-9", lambda tp: ["simulate", SIXBAR, "--out", str(tp / "r"), "--duration", "1e-9"],
     "--duration"),
    ("duration inf", lambda tp: ["simulate", SIXBAR, "--out", str(tp / "r"), "--duration", "inf"], "--duration"),
    ("duration 1e6", lambda tp: ["simulate", SIXBAR, "--out", str(tp / "r"), "--duration", "1e6"], "--duration"),
    ("1 us manoeuvre", lambda tp: ["simulate", _short_manoeuvre(tp), "--out", str(tp / "r")],
     "manoeuvre.duration"),
    ("h longer than the duration", lambda tp: ["simulate", SIXBAR, "--out", str(tp / "r"), "--duration", "0.01",
                                               "--h", "0.1"], "--h"),
    ("seed -1", lambda tp: ["simulate", SIXBAR, "--out", str(tp / "r"), "--seed", "-1"], "--seed"),
    ("time-scale 0", lambda tp: ["observe", SIXBAR, _lab_csv(tp), "--time-scale", "0"], "--time-scale"),
    ("motors cannot actuate", lambda tp: ["simulate", _two_motors(tp), "--out", str(tp / "r"), "--engine", "erls",
                                          "--duration", "0.01"], "actuate"),
    ("sweep of an unknown link", lambda tp: ["study", "sweep", SIXBAR, "--out", str(tp / "s"), "--set",
                                             "links.L9.diameter=0.03", "--quick"], "L9"),
    ("refine 0", lambda tp: ["modes", SIXBAR, "--refine", "0"], "--refine"),
    ("refine -3", lambda tp: ["modes", SIXBAR, "--refine", "-3"], "--refine"),
    ("channels ''", lambda tp: ["observe", SIXBAR, RUN, "--channels", ""], "--channels"),
    ("out ''", lambda tp: ["observe", SIXBAR, RUN, "--out", ""], "--out"),
]


def _one_line(capsys, argv):
    rc = main(argv)
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("exuflex observe: ") or "error" in ln]
    return rc, err, lines


@pytest.mark.parametrize("argv,needle", [(c[1], c[2]) for c in CASES], ids=[c[0] for c in CASES])
def test_issue_cases_give_one_line(tmp_path, capsys, argv, needle):
    rc, err, _ = _one_line(capsys, argv(tmp_path))
    errors = [ln for ln in err.splitlines() if ": error: " in ln]
    assert rc == 2, err
    assert "Traceback" not in err and "internal error" not in err
    assert len(errors) == 1, err
    assert needle in errors[0], err
    # nothing but stage messages beside the error line
    assert all(ln.startswith("exuflex ") for ln in err.splitlines() if ln.strip()), err
    assert not (tmp_path / "r").exists()


def test_version(capsys):
    import exuflex

    assert main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"exuflex {exuflex.__version__}"


def test_debug_anywhere_raises_with_traceback(tmp_path):
    with pytest.raises(ValueError):
        main(["modes", SIXBAR, "--fmax", "1", "--debug", "--q", "1,2"])


def test_usage_errors_name_the_command_and_the_help(capsys):
    assert main(["observe", SIXBAR]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("exuflex observe: error: ") and "--help" in err
    assert main(["nosuch"]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_python_api_says_a_path_is_not_a_mechanism():
    from exuflex.observer.session import ObserverConfig, make_observer
    from exuflex.scoring.run import observe_run

    with pytest.raises(UsageError, match=r"mech: expected an exuflex.mechanism.Mechanism, got str \(a path: load it"):
        make_observer(SIXBAR)
    from exuflex.mechanism import load_mechanism

    mech = load_mechanism(SIXBAR)
    with pytest.raises(UsageError, match=r"run: expected an exuflex.runs.Run, got str \(a path: read it"):
        observe_run(mech, RUN)
    with pytest.raises(UsageError, match=r"channels \(--channels\): \['foo'\] not sensor"):
        make_observer(mech, ObserverConfig(channels=("foo",)))
    with pytest.raises(UsageError, match=r"h \(--substep\)"):
        make_observer(mech, ObserverConfig(h=0.01))


def test_simulate_run_checks_its_arguments(tmp_path):
    from exuflex.truth import simulate_run

    with pytest.raises(UsageError, match=r"seed \(--seed\)"):
        simulate_run(SIXBAR, tmp_path / "r", seed=-1)
    with pytest.raises(UsageError, match=r"out \(--out\)"):
        simulate_run(SIXBAR, "")
    with pytest.raises(UsageError, match=r"payload_scale"):
        simulate_run(SIXBAR, tmp_path / "r", payload_scale=float("nan"))


def test_readers_say_what_they_expected():
    from exuflex.runs import read_csv_log, read_run

    run = read_run(RUN)
    with pytest.raises(UsageError, match=r"run_dir: expected a path .*got Run \(already read"):
        read_run(run)
    with pytest.raises(UsageError, match=r"path: expected a path .*got int"):
        read_csv_log(3)
