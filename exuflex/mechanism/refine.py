"""Mesh refinement of a mechanism: split every element into equal parts (for convergence studies)."""

from __future__ import annotations

import dataclasses

from .dofs import elastic_dofs
from .spec import Mechanism

__all__ = ["refine_mechanism"]


def refine_mechanism(mech: Mechanism, factor: int) -> Mechanism:
    """Split every element of every link into ``factor`` equal elements.

    The original nodes keep their ids (so masses, gauges and node-based dof names such as
    ``node14.x`` keep their meaning); new nodes get ids above the largest existing one.
    """
    if factor < 1:
        raise ValueError(f"refinement factor must be >= 1, got {factor}")
    if factor == 1:
        return mech
    # index-based master names (x14) refer to the unrefined numbering: make them node-based first
    dofs = elastic_dofs(mech)
    masters = tuple(dofs.node_name(m) for m in mech.reduction.masters)
    next_id = max(mech.node_ids) + 1
    links = []
    for lk in mech.links:
        st, ids = [lk.stations[0]], [lk.node_ids[0]]
        for (a, b), nb in zip(zip(lk.stations, lk.stations[1:]), lk.node_ids[1:]):
            for k in range(1, factor):
                st.append(a + (b - a) * k / factor)
                ids.append(next_id)
                next_id += 1
            st.append(b)
            ids.append(nb)
        links.append(dataclasses.replace(lk, stations=tuple(st), node_ids=tuple(ids)))
    reduction = dataclasses.replace(mech.reduction, masters=masters)
    return dataclasses.replace(mech, links=tuple(links), reduction=reduction)
