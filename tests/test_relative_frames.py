"""Relative angle coordinates: each link's ERLS frame on its own tangent, the relative encoder read through its row.

A relative coordinate's link has its ERLS frame on its own tangent at the joint (:func:`exuflex.mechanism.
elastic_dofs` fixes that node's rotation, as for an absolute coordinate), so ``q`` is the difference of the two
links' ERLS frames and the relative encoder reads ``q`` plus the difference of the two nodes' elastic rotations at the
joint (``ErlsModel.coordinate_reading_rows``; docs/long_arms.md). Checked here:

- the encoder channel's row on ``[q; u]`` against central differences of the reading the truths compute (the slopes
  of :func:`exuflex.sensors.erls_probe_record` through :func:`exuflex.sensors.true_states`), entry by entry;
- the observer's physical ``q`` (the reading) and tip against the truths' definitions at the full state its reduced
  state expands to;
- a relative and an absolute declaration of the same arm are the same model in other coordinates: the same elastic
  dofs and clamped modes, and on a very stiff arm (elastic rotations negligible) the same estimates;
- closed chains with absolute coordinates keep their dofs;
- the elastic rotations a relative encoder reads are masters, so that the reduced model's quasi-static sag under
  the weight reads, in the estimated quantities, the full model's static sag.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg

from exuflex.erls.model import ErlsModel
from exuflex.erls.validity import weight_sag
from exuflex.manoeuvre import plan
from exuflex.erls.sensing import channel_matrix
from exuflex.mechanism import elastic_dofs, load_mechanism
from exuflex.observer.session import ObserverConfig, make_observer
from exuflex.sensors import erls_probe_record, true_states

ROOT = Path(__file__).resolve().parents[1]
LONG = ROOT / "benchmarks" / "models" / "long_two_link.toml"
LONG_ABS = ROOT / "benchmarks" / "models" / "long_two_link_abs.toml"


def _reading(model: ErlsModel, x: np.ndarray) -> np.ndarray:
    """The truths' coordinates (the encoders' readings) at the full state ``x = [q; u]`` at rest."""
    y = np.concatenate([x, np.zeros_like(x)])[None]
    rec = erls_probe_record(model, np.zeros(1), y)
    return np.asarray(true_states(model.mech, rec, kinematics=model.kin).data)[0, : model.nq]


@pytest.fixture(scope="module")
def long_model():
    return ErlsModel(load_mechanism(LONG))


def test_relative_coordinate_fixes_its_node_and_reads_the_other_links_rotation(long_model):
    """The forearm's node at the elbow has no elastic rotation; the upper arm's has, and the reading row is minus it."""
    m = long_model
    dofs = m.dofs
    G = m.coordinate_reading_rows()
    assert not np.any(G[0])
    k = dofs.index(f"node{m.mech.node_at('upper', 0.8)}.theta")
    assert G[1, k] == -1.0 and np.count_nonzero(G[1]) == 1
    with pytest.raises(KeyError, match=r"fixed by a joint or coordinate"):
        dofs.locate(f"node{m.mech.node_at('fore', 0.0)}.theta")


@pytest.mark.parametrize("seed", [0, 1])
def test_encoder_row_against_finite_differences_entry_by_entry(long_model, seed):
    """``channel_matrix``'s relative-encoder row (rigid link angles' weights times S_z, plus the elastic row) against
    central differences of the truths' reading at a bent state, each entry against its own size."""
    m = long_model
    rng = np.random.default_rng(seed)
    x = np.concatenate([np.asarray(m.mech.q_ref, float) + 0.1 * rng.normal(size=m.nq), 1e-3 * rng.normal(size=m.ne)])
    cfg = m.configuration(x[: m.nq])
    C = channel_matrix(m, cfg, m.mech, ("q1", "q2"))
    h = 1e-6
    D = np.empty_like(C)
    for j in range(m.n):
        e = np.zeros(m.n)
        e[j] = h
        D[:, j] = (_reading(m, x + e) - _reading(m, x - e)) / (2 * h)
    # an entry is 0 or 1 up to the links' second order in u (the slope's w_theta: 1e-3 of an entry at u ~ 1e-3)
    err = np.abs(C - D) / (1e-6 + 1e-2 * np.abs(D))
    assert err.max() <= 1.0, (np.unravel_index(err.argmax(), err.shape), C, D)
    assert D[1, m.nq + m.dofs.index(f"node{m.mech.node_at('upper', 0.8)}.theta")] == pytest.approx(-1.0, abs=1e-2)


def test_observer_reports_the_reading_and_the_tip_from_it(tmp_path):
    """At a reduced state off rest, the observer's physical q, dq, tip e against the truths' definitions at the full
    state it expands to (``[q; H_u p]``): q exactly (a linear row), e to third order in the readings' elastic part
    (the rigid tip's move to the readings to second order, ``ReducedObserverModel._tip_from_reading``): at elastic
    coordinates of 3e-3 and the upper arm's elastic rotation at the elbow (a master) of 1.5e-2 rad, within 1e-3 of e (the first order alone misses by
    several 1e-3 of it)."""
    mech = load_mechanism(ROOT / "models" / "serial_arm.toml")
    obs = make_observer(mech, ObserverConfig())
    som = obs.model
    assert som.reading_G is not None
    rng = np.random.default_rng(3)
    z = som.initial_state(np.asarray(mech.q_ref, float) + 0.05 * rng.normal(size=som.nq))
    z[som.nq : som.r] = 3e-3 * rng.normal(size=som.r - som.nq)
    # the elbow's reading is a master (the upper arm's elastic rotation there): turn it by 1.5e-2 rad
    im = list(som.rm.cb.im)
    for k in np.flatnonzero(np.any(som.model.coordinate_reading_rows() != 0.0, axis=0)):
        z[som.nq + im.index(k)] = 1.5e-2
    phys = np.asarray(obs.physical(np.zeros(1), z[None]).data)[0]
    q = z[: som.nq]
    rc = som.rm.cb.at(q)
    u = rc.H[som.nq :] @ z[: som.r]
    model = som.model
    x = np.concatenate([q, u])
    y = np.concatenate([x, np.zeros_like(x)])[None]
    truth = np.asarray(true_states(mech, erls_probe_record(model, np.zeros(1), y), kinematics=model.kin).data)[0]
    nq = som.nq
    reading = q + model.coordinate_reading_rows() @ u
    assert np.max(np.abs(phys[:nq] - truth[:nq])) <= 1e-9 * np.max(np.abs(reading - q)) + 1e-13
    assert np.max(np.abs(phys[:nq] - reading)) <= 1e-12
    e_t, e_o = truth[2 * nq : 2 * nq + 2], phys[2 * nq : 2 * nq + 2]
    assert np.max(np.abs(reading - q)) > 1e-2  # the second order matters at this size
    assert np.max(np.abs(e_o - e_t)) <= 1e-3 * np.max(np.abs(e_t)), (e_o, e_t)


def test_relative_and_absolute_declarations_are_one_model():
    """long_two_link and its absolute twin: the same elastic dofs and, at the same configuration, the same mass and
    stiffness in the elastic block (clamped modes equal to 1e-10)."""
    rel, ab = ErlsModel(load_mechanism(LONG)), ErlsModel(load_mechanism(LONG_ABS))
    assert rel.dofs.free == ab.dofs.free
    cr, ca = rel.configuration(np.array([0.2, 0.8])), ab.configuration(np.array([0.2, 1.0]))
    fr = scipy.linalg.eigh(rel.stiffness(cr)[2:, 2:], rel.mass(cr)[2:, 2:], eigvals_only=True)
    fa = scipy.linalg.eigh(ab.stiffness(ca)[2:, 2:], ab.mass(ca)[2:, 2:], eigvals_only=True)
    assert np.allclose(fr, fa, rtol=1e-10)


@pytest.mark.parametrize("name", ["fourbar", "sixbar", "fivebar"])
def test_closed_chains_keep_their_dofs(name):
    """The closed chains' coordinates are absolute: their relative encoders are sensors, not coordinates, and their
    elastic dofs are what the coordinates' fixed rotations and the joints leave (no reading row)."""
    mech = load_mechanism(ROOT / "models" / f"{name}.toml")
    assert all(c.relative_to is None for c in mech.coordinates)
    m = ErlsModel(mech)
    assert not np.any(m.coordinate_reading_rows())
    assert elastic_dofs(mech).n == m.ne


def _stiff(path: Path) -> str:
    """The model file's text with its aluminium 100 times stiffer (E)."""
    text, n = re.subn(r"E = 69\.0e9", "E = 6.9e12", path.read_text())
    assert n == 1
    return text


@pytest.mark.slow
def test_stiff_arm_relative_and_absolute_declarations_give_the_same_estimates(tmp_path):
    """A very stiff long_two_link (E x 100: the elastic rotations at the elbow far below the encoders' 1e-3 rad
    noise), one ERLS truth log of 0.6 s, filtered by the relative and by the absolute declaration: the elbow
    reading of the one and the other's model reading that encoder at its estimates agree within 10 % of the bound
    after the start-up, the shoulder within 5 %. The two are one model in other coordinates (the test above), but
    the filters differ where the coordinates enter: the prior's standard deviation per coordinate and the held
    matrices' refresh radius in q, which falls at other times."""
    from exuflex.runs import Run, read_run
    from exuflex.scoring.run import observe_run
    from exuflex.truth.run import simulate_run

    (tmp_path / "rel.toml").write_text(_stiff(LONG))
    (tmp_path / "abs.toml").write_text(_stiff(LONG_ABS))
    mrel, mabs = load_mechanism(tmp_path / "rel.toml"), load_mechanism(tmp_path / "abs.toml")
    run = read_run(simulate_run(tmp_path / "rel.toml", tmp_path / "run", seed=1, engine="erls", duration=0.6))
    out_r = observe_run(mrel, run, keep="physical")
    # the same measurements filtered in absolute coordinates (the truth's columns are the relative model's: unused)
    obs_a = make_observer(mabs, ObserverConfig())
    out_a = observe_run(mabs, Run(run.path, run.sensors, None, run.meta), observer=obs_a, with_bound=False)
    er = out_r.estimate.physical
    sel = np.asarray(er.t) >= 0.3
    qr = np.asarray(er.data)[sel, :2]
    xa = out_a.estimate.result.x_hat[sel]
    # the absolute declaration's elbow reading: its model's encoder channel at its estimates
    ra = np.array([obs_a.model.measure(x, ("q2",)).y[0] for x in xa])
    d1 = np.sqrt(np.mean((qr[:, 0] - xa[:, 0]) ** 2))
    d2 = np.sqrt(np.mean((qr[:, 1] - ra) ** 2))
    b = out_r.summary["bound_rms"]
    assert d1 <= 0.05 * b["q1"], (d1, b)
    assert d2 <= 0.1 * b["q2"], (d2, b)


@pytest.mark.parametrize("name", ["crane_arm", "upright_two_link"])
def test_reduced_sag_reads_the_full_sag_in_the_estimated_quantities(name):
    """Two-link arms in a vertical plane with a relative elbow, at rest at the manoeuvre's start, middle and end: the
    observer's physical quantities (:meth:`~exuflex.observer.session.Observer.physical`) at the reduced model's
    quasi-static sag under the weight and the holding torques (``ReducedModel.quasi_static``) against the truths'
    definitions (:func:`exuflex.sensors.true_states`) at the full model's static sag
    (:func:`exuflex.erls.validity.weight_sag`). The elbow encoder's reading within 5e-3 of its elastic part and
    the tip's elastic displacement within 3e-3 of its size (measured: 1.6e-3 and 8.3e-4 on the crane arm, 1.0e-3 and
    2.4e-3 on the upright link). With the upper link's elastic rotation at the elbow a slave (the masters the files
    name), the reduced sag missed 5.1e-2 of the crane's mast rotation there and 8.5e-3 of its boom tip's sag, a
    constant bias of 5.6 times the tip's bound under the filter (docs/long_arms.md)."""
    mech = load_mechanism(ROOT / "benchmarks" / "models" / f"{name}.toml")
    obs = make_observer(mech, ObserverConfig())
    som = obs.model
    rm, model, nq, r = som.rm, som.model, som.nq, som.r
    G = model.coordinate_reading_rows()
    read = np.flatnonzero(np.any(G != 0.0, axis=0))
    assert set(read) <= set(rm.cb.im.tolist())  # the readings' elastic rotations are masters
    for q in plan(mech, dt=mech.manoeuvre.duration / 2).q:
        cfg = model.configuration(q)
        u, tau = weight_sag(model, model.static_geometric(cfg))
        y = np.concatenate([q, u, np.zeros(model.n)])[None]
        truth = np.asarray(true_states(mech, erls_probe_record(model, np.zeros(1), y), kinematics=model.kin).data)[0]
        z = np.concatenate([q, rm.quasi_static(q, np.zeros(nq), tau), np.zeros(r)])
        est = np.asarray(obs.physical(np.zeros(1), z[None]).data)[0]
        j = int(np.flatnonzero(np.any(G != 0.0, axis=1))[0])
        assert abs(est[j] - truth[j]) <= 5e-3 * abs(G[j] @ u), (q, est[j], truth[j], G[j] @ u)
        e_t, e_o = truth[2 * nq : 2 * nq + 2], est[2 * nq : 2 * nq + 2]
        assert np.linalg.norm(e_o - e_t) <= 3e-3 * np.linalg.norm(e_t), (q, e_o, e_t)
