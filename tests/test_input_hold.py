"""The input over a sample interval: what a log declares its torques did between two samples (``input_hold``, held
or linear) and the observer's step taking it (docs/held_step.md, "The input over a sample interval").

- The linear system's RK4 sub-steps with the torques linear over the interval against the exact solution (the
  matrix exponential of the system with the input's ramp as states): RK4's order holds, where the torque held at
  the interval's start misses by the half-interval lag.
- The cached step's Jacobian with a linear input against central differences of the step, entry by entry (each
  entry against its own size and its row's and column's natural scale, ``test_step_jacobian.entry_error``): the
  input terms (the motion's geometric stiffness at the interval's midpoint torques, the input matrix's change with
  the elastic coordinates stage by stage) match the step; the Jacobian with the held input's terms does not.
- The compiled sample loop against the filter's ``step`` with a linear input, bit for bit (plain and augmented).
- The reference step with a linear input on the reduced truth (the model's own equations under the truth's torque
  table): its error is the table's own hold, a fraction of the held input's.
- The log's field: written by the truth writer, read and checked by the loader (one-line error), its default for
  a log without it.
"""

from __future__ import annotations

import json
from pathlib import Path

import _oracles as oracle
import numpy as np
import pytest
import scipy.linalg
from test_sample_loop import _same, _step_by_step, sixbar_log  # noqa: F401 (a fixture)
from test_step_jacobian import _central4, entry_error, held_interval_at

from exuflex.errors import LogFormatError
from exuflex.mechanism import load_mechanism
from exuflex.observer import expansion as ex
from exuflex.observer.reduced import ReducedObserverModel
from exuflex.observer.session import ObserverConfig, make_observer
from exuflex.runs import input_hold_of, read_run, write_run
from exuflex.truth.engines import plan_drive, reduced_truth

ROOT = Path(__file__).resolve().parents[1]


def _linear_system(r=6, nq=2, nm=2, seed=0):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(r, r))
    Mr = A @ A.T + r * np.eye(r)
    K = rng.normal(size=(r, r))
    Kr = 4e2 * K @ K.T
    Kr[:nq] = Kr[:, :nq] = 0.0  # rigid coordinates
    Cr = 1e-3 * Kr + 0.1 * np.eye(r)
    Gr = rng.normal(size=(r, nm))
    return Mr, Kr, Cr, Gr, rng.normal(size=r)


def _exact(z, u, du, Mr, Kr, Cr, Gr, f, T):
    """``M p'' + C p' + K p = G (u + (t / T) du) + f`` over ``T`` exactly: the matrix exponential of the system with
    the constant input and the ramp's time as states."""
    r = Mr.shape[0]
    Mi = np.linalg.inv(Mr)
    A = np.zeros((2 * r + 2, 2 * r + 2))
    A[:r, r : 2 * r] = np.eye(r)
    A[r : 2 * r, :r] = -Mi @ Kr
    A[r : 2 * r, r : 2 * r] = -Mi @ Cr
    A[r : 2 * r, 2 * r] = Mi @ (Gr @ u + f)  # times the constant state 1
    A[r : 2 * r, 2 * r + 1] = Mi @ Gr @ du / T  # times the time t
    A[2 * r + 1, 2 * r] = 1.0  # t' = 1
    return (scipy.linalg.expm(A * T) @ np.concatenate([z, [1.0, 0.0]]))[: 2 * r]


def test_rk4_with_a_linear_input_is_the_exact_solution():
    """A linear system with the torques linear over 1 ms (10 sub-steps): the RK4 step within 1e-9 of the change the
    ramp causes (RK4's own error, fourth order), where holding the torque at the start misses by half the ramp's
    effect."""
    Mr, Kr, Cr, Gr, f = _linear_system()
    r = Mr.shape[0]
    rng = np.random.default_rng(1)
    z = np.concatenate([1e-3 * rng.normal(size=r), 1e-2 * rng.normal(size=r)])
    u, du = rng.normal(size=2), rng.normal(size=2)
    T, n = 1e-3, 10
    exact = _exact(z, u, du, Mr, Kr, Cr, Gr, f, T)
    ramp_effect = np.abs(exact - _exact(z, u, 0 * du, Mr, Kr, Cr, Gr, f, T)).max()
    linear = ex._rk4_linear(z, u, du, Mr, Kr, Cr, Gr, f, T / n, n)
    held = ex._rk4_linear(z, u, np.zeros(2), Mr, Kr, Cr, Gr, f, T / n, n)
    assert np.abs(linear - exact).max() < 1e-6 * ramp_effect
    assert np.abs(held - exact).max() > 0.3 * ramp_effect
    # the compiled wrapper the reference step calls is the same kernel
    np.testing.assert_array_equal(ex.held_ramp(z, u, du, Mr, Kr, Cr, Gr, f, T / n, n), linear)


#: models whose step has input terms in its Jacobian (the motion's geometric stiffness, the input matrix's change
#: with the elastic coordinates), and the fresh double pendulum under gravity
INPUT_MODELS = ("serial_arm", "slider_crank", "three_link_arm", "fresh")


def input_entries(name: str, seed: int = 0) -> dict:
    """The cached step of model ``name`` at a moving state with the torques linear over the interval (``du`` of the
    torques' own size) against central differences of the step with its matrices held at its configuration (as
    ``test_step_jacobian.jacobian_entries``, whose ``exact`` this is with the ramp): ``linear``, the largest entry
    error of the filter's ``F`` (``entry_error``, rtol 1e-6, eta 1e-8); ``held_terms``, that of ``F`` with the
    held input's terms (the Jacobian of ``du = 0``) against the same differences."""
    mech, m, z, u, dt, iv, n, h = held_interval_at(name, seed)
    du = np.random.default_rng(seed + 7).normal(size=len(u))
    r, nq = m.r, m.nq
    hs = iv.system
    dl0 = z[:nq] - iv.q0
    um = u + 0.5 * du

    def forces(x):  # the held forces at x, the motion's geometric forces at the midpoint torques
        f = oracle.quadratic_forces(x[:r], x[r:], nq, hs.fg, hs.T2, hs.V2, hs.C2)
        f -= oracle.motion_stiffness(um, x, nq, oracle.motion_form(hs, x[:nq] - iv.q0))[0] @ (x[:r] + 0.5 * dt * x[r:])
        if hs.pG.shape[0]:
            f[:nq] += (x[nq:r] @ hs.pG).reshape(nq, -1)[:, -1]
        if hs.Wg.shape[0]:  # the weight at the interval's midpoint configuration (a linear input)
            f += hs.Wg[:, :nq] @ (x[:nq] - iv.q0 + 0.5 * dt * x[r : r + nq])
        if hs.We.shape[0]:
            f[:nq] += np.einsum("m,mij,j->i", x[nq:r], hs.We.reshape(-1, nq, nq),
                                x[:nq] - iv.q0 + 0.5 * dt * x[r : r + nq])
        if hs.pT.shape[0]:
            f += oracle.velocity_terms(x[nq:r], x[r:], nq, hs.pT, hs.pC2)[0]
        if hs.dT2.shape[0]:  # the forms' change with q (gravity)
            f += oracle.forms_gradient(x[:r], x[r:], nq, hs.dT2, hs.dV2, hs.dC2) @ (x[:nq] - iv.q0)
        return f

    def held_matrices_step(x):
        f = forces(x) + held_matrices_step.extra @ (x[:nq] - z[:nq])
        M, K, C, G = ex.held_system(dl0, 0.0, x[nq:r] + 0.5 * h * n * x[r + nq :], tuple(hs))
        return ex._rk4_linear(x, u, du, M, K, C, G, f, h, n)

    held_matrices_step.extra = np.zeros((r, nq))
    _, Mr, Kr, Cr, Gr = ex.held_step(z, u, dl0, 0.0, h, n, hs, du)
    Pn, S, _, _ = ex.step_maps_noise(Mr, Kr, Cr, Gr, h, n, m.torque_var)
    tensors = iv.forces.jacobian_tensors()
    if hs.Wg.shape[0]:
        z1 = ex.held_step(z, u, dl0, 0.0, h, n, hs, du)[0]
        Fp = ex.position_forces(z, z1, dt, hs.Wg, hs.dM, hs.dK, hs.beta)
        ex._mass_curvature_forces(Fp, z, z1, h * n, 0.5 * h * n, nq, hs.Me)  # ... and M_r's cross term at the sag
        held_matrices_step.extra = (Fp - hs.Wg)[:, :nq]
    Fd = _central4(held_matrices_step, z, r)  # (the slider-crank's 2.4 kHz mode: fourth order)
    F = ex.held_interval(z, u, du, dl0, 0.0, h, n, *tensors, Pn, S, tuple(hs))[1]
    F_start = ex.held_interval(z, u, np.empty(0), dl0, 0.0, h, n, *tensors, Pn, S, tuple(hs))[1]
    return {"linear": float(entry_error(F, Fd, 1e-6, 1e-8).max()),
            "held_terms": float(entry_error(F_start, Fd, 1e-6, 1e-8).max())}


@pytest.mark.parametrize("name", INPUT_MODELS)
def test_step_jacobian_input_terms_entry_by_entry(name):
    """With the torques linear over the interval the filter's ``F`` is the derivative of its step entry by entry
    (the motion's geometric stiffness at the midpoint torques, the input matrix's change stage by stage, under
    gravity the weight at the midpoint configuration); with the held input's terms it is not."""
    e = input_entries(name)
    print(name, e)
    assert e["linear"] <= 1.0, e
    assert e["held_terms"] > 3.0, e


@pytest.fixture(scope="module")
def linear_sixbar(sixbar_log):  # noqa: F811
    mech, obs, t, U, Y = sixbar_log
    return mech, obs, t, U, Y


@pytest.mark.parametrize("estimator", ["ekf", "ekf-input", "ekf-payload"])
def test_loop_is_step_with_a_linear_input(linear_sixbar, estimator):
    """The compiled sample loop with the torques linear between samples gives the numbers of the filter's ``step``
    (the model's ``predict`` with the next sample), bit for bit, with a torque step (a jump, no longer tested with a
    linear input) and a late sample; and a linear input changes the estimates."""
    mech, obs, t, U, Y = linear_sixbar
    o = make_observer(mech, ObserverConfig(estimator=estimator), cb=obs.model.rm.cb)
    o.use_input_hold("linear")
    ekf = o.ekf
    n = 500
    t2, U2, Y2 = t[:n].copy(), U[:n].copy(), Y[:n].copy()
    U2[300:, 0] += 0.5
    t2[400:] += 0.3 * (t2[1] - t2[0])
    looped = ekf.run(t2, U2, Y2)
    _same(looped, _step_by_step(ekf, t2, U2, Y2))
    o.use_input_hold("zoh")
    held = ekf.run(t2, U2, Y2)
    assert not np.array_equal(held.x_hat, looped.x_hat)


@pytest.mark.slow
def test_reference_step_follows_the_reduced_truth_with_a_linear_input():
    """The shaken link's reduced truth under its manoeuvre's torque table (10 kHz, held over each table step)
    against the reference step from its sampled torques (1 kHz), from the truth's start over 0.5 s (the lift and
    the first strokes, the torque changing by up to 2.4 N m per sample): linear between the samples and delayed by
    half the table's step, the largest angle error is a small fraction of the held torque's (which lags the table
    by half an interval) and of the linear one's without the delay."""
    mech = load_mechanism(ROOT / "benchmarks/models/shaken_link.toml")
    T, h = 0.5, 1e-4
    drive = plan_drive(mech, T, h)
    truth = reduced_truth(mech, drive, T, h).truth
    dt = 1.0 / mech.sample_rate_hz
    k_tab = int(round(dt / h))
    rm = make_observer(mech).model.rm
    errs = {}
    for hold, delay in (("zoh", 0.0), ("linear", 0.0), ("linear", 0.5 * h)):
        som = ReducedObserverModel(rm, h=h, method="rk4", input_hold=hold, input_delay=delay)
        z = som.initial_state(drive.q0, drive.qd0)
        q = [z[0]]
        for k in range(len(truth.t) - 1):
            z = som.predict(z, drive.tau[k * k_tab], dt, drive.tau[(k + 1) * k_tab]).x
            q.append(z[0])
        errs[(hold, delay)] = float(np.abs(np.array(q) - truth["q1"]).max())
    print(errs)
    exact = errs[("linear", 0.5 * h)]
    assert exact < 0.05 * errs[("zoh", 0.0)] and exact < 0.2 * errs[("linear", 0.0)], errs


def test_log_declares_its_input_hold(tmp_path):
    """``input_hold`` and ``input_delay_s`` in ``meta.json``: the loader reads them, refuses other values naming the
    file and the field; a log without them is "zoh" (as every log was filtered before the field) with no delay."""
    from exuflex.sensors import Signals

    S = Signals(np.arange(3) * 1e-3, ("T1", "q1"), np.zeros((3, 2)), ("N m", "rad"))
    for meta, want in (({"engine": "erls"}, ("zoh", 0.0)), ({"engine": "lab", "input_hold": "linear"}, ("linear", 0.0)),
                       ({"input_hold": "linear", "input_delay_s": 5e-5}, ("linear", 5e-5))):
        out = tmp_path / f"run{len(list(tmp_path.iterdir()))}"
        write_run(out, S, None, meta, motors=("T1",))
        written = json.loads((out / "meta.json").read_text())
        assert (written["input_hold"], written["input_delay_s"]) == want
        assert read_run(out).input_hold == want
    mp = out / "meta.json"
    raw = json.loads(mp.read_text())
    del raw["input_hold"], raw["input_delay_s"]
    mp.write_text(json.dumps(raw))
    assert read_run(out).input_hold == ("zoh", 0.0)
    for field, bad, message in (("input_hold", "cubic", r"meta.json: field 'input_hold' must be one of 'zoh', 'linear'"),
                                ("input_delay_s", -1.0, r"meta.json: field 'input_delay_s' must be a number of seconds")):
        mp.write_text(json.dumps({**raw, field: bad}))
        with pytest.raises(LogFormatError, match=message):
            read_run(out)
    assert input_hold_of({"input_hold": "linear"}) == ("linear", 0.0)
    with pytest.raises(ValueError, match="input_hold must be one of"):
        ReducedObserverModel.input_hold.fset(object.__new__(ReducedObserverModel), "ramp")


def test_truth_writer_declares_its_input(tmp_path):
    """``exuflex simulate`` declares the torques between two samples: its table held over the table's step (a delay
    of half of it), linear where the planned torque is continuous (a quintic time law), held where a trapezoid's
    acceleration steps at its switches."""
    from exuflex.truth import simulate_run

    src = ROOT / "models" / "single_link.toml"
    out = simulate_run(src, tmp_path / "trapezoid", seed=1, engine="erls", duration=0.02)
    assert read_run(out).input_hold == ("zoh", 5e-5)
    text = src.read_text()
    assert 'time_law = "trapezoid"\nramp_time = 0.3\n' in text
    quintic = tmp_path / "single_link_quintic.toml"
    quintic.write_text(text.replace('time_law = "trapezoid"\nramp_time = 0.3\n', 'time_law = "quintic"\n'))
    out = simulate_run(quintic, tmp_path / "quintic", seed=1, engine="erls", duration=0.02)
    assert read_run(out).input_hold == ("linear", 5e-5)
