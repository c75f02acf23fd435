"""Automatic master dofs for a model that names none: the transverse dofs at its joints and tips.

Masters are what the reduced coordinates measure directly (:mod:`.basis`); in a planar mechanism the slow
elastic motion is bending, so the masters are chosen across the links, in their own frames
(``node{n}.transverse``, :mod:`exuflex.mechanism.dofs`), where that motion shows:

- every **free tip** (a link end in no joint): the transverse dof of its node;
- every **joint off the ground**: one transverse dof, of the link along whose transverse direction the joint
  is most compliant. The joint's translation is shared by its links; across one link it is usually that
  link's bending, across another it can be nearly that link's axial direction, which the rest of the
  mechanism holds stiffly (a master there is a Guyan shape of kilohertz frequency). The compliance along a
  unit direction ``d`` is ``d^T C d`` with ``C`` the joint's 2 x 2 block of ``K_uu^-1`` (the static
  deflection under a unit force there, every other elastic dof free); the link kept is the one whose smallest
  compliance over the given configurations (q* and the manoeuvre's) is largest, so that the master stays
  compliant along the whole motion. Ground joints carry no translation.

Interior modes then complete the basis (:mod:`.path`); rotations are left to them, but for one kind, whatever the
masters named (:func:`reading_masters`):

- the **elastic rotations a coordinate's encoder reads**: a relative angle coordinate's encoder reads ``q + G u``,
  ``G u`` minus the other link's elastic rotation at the joint (each link's ERLS frame is its own tangent there,
  :meth:`~exuflex.erls.model.ErlsModel.coordinate_reading_rows`), and the motor between the two links puts its
  reaction on that same rotation dof. As a slave it is the point where a concentrated moment acts and a reading
  is taken that only the interior modes reach: the Craig-Bampton basis reproduces the static response to loads
  at its masters exactly (the Guyan shapes) but to a load at a slave only in the part its interior modes span,
  and the encoder sees the rest at a few hundredths of its noise, so no channel asks for it, while the estimated
  tip, a link length further out, moves by that length times the missing rotation: a constant bias under the
  weight's static moment (measured in ``docs/long_arms.md``). As masters, the readings are reduced coordinates
  like q and the motor's reaction a master load.
"""

from __future__ import annotations

import numpy as np

from ..erls.model import ErlsModel

__all__ = ["automatic_masters", "reading_masters"]


def automatic_masters(model: ErlsModel, qs) -> tuple[str, ...]:
    """Transverse master names at the joints and tips of ``model`` (module docstring); ``qs`` (n, nq) the
    configurations the joint choice is made over."""
    mech, dofs = model.mech, model.dofs
    pos = {n: i for i, n in enumerate(mech.node_ids)}
    in_joint = {mech.node_at(p.link, p.station) for j in mech.joints for p in j.points}
    names: list[str] = []
    joint_nodes = []  # per joint off the ground: the node of each of its links
    for j in mech.joints:
        if j.ground is not None:
            continue
        nodes = [mech.node_at(p.link, p.station) for p in j.points]
        if dofs.locate(f"node{nodes[0]}.transverse").pair is not None:
            joint_nodes.append(nodes)
    if joint_nodes:
        worst = {n: np.inf for nodes in joint_nodes for n in nodes}
        for q in np.atleast_2d(np.asarray(qs, float)):
            cfg = model.configuration(q)
            C = np.linalg.inv(model.stiffness(cfg)[model.nq:, model.nq:])
            for nodes in joint_nodes:
                ux, uy = dofs.locate(f"node{nodes[0]}.transverse").pair
                Cp = C[np.ix_([ux, uy], [ux, uy])]
                for n in nodes:
                    phi = cfg.pose.r[3 * pos[n] + 2]
                    d = np.array([-np.sin(phi), np.cos(phi)])
                    worst[n] = min(worst[n], float(d @ Cp @ d))
        for nodes in joint_nodes:
            best = max(nodes, key=lambda n: worst[n])  # ties: the joint's first link
            names.append(f"node{best}.transverse")
    for lk in mech.links:
        for n in (lk.node_ids[0], lk.node_ids[-1]):
            if n not in in_joint:
                names.append(f"node{n}.transverse")
    return tuple(names)


def reading_masters(model: ErlsModel) -> tuple[str, ...]:
    """The names of the elastic dofs the coordinates' encoder readings hold beyond q (the non-zero columns of
    :meth:`~exuflex.erls.model.ErlsModel.coordinate_reading_rows`: at each relative angle coordinate's joint the
    other link's elastic rotation), in dof order; empty without a relative angle coordinate (module docstring)."""
    G = model.coordinate_reading_rows()
    return tuple(model.dofs.names[k] for k in np.flatnonzero(np.any(G != 0.0, axis=0)))
