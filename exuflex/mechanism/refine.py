"""Mesh refinement of a mechanism (for convergence studies and fine-mesh truths).

- :func:`refine_mechanism`: split every element into ``factor`` equal parts;
- :func:`remesh_mechanism`: split every element into the fewest equal parts such that no element is
  longer than ``length / elements_per_link`` of its link (at least that many elements per link).

Both refuse meshes of more than :data:`~exuflex.mechanism.limits.MAX_ELEMENTS` elements (``ValueError``).

Both keep the original nodes and their ids (so masses, gauges and node-based dof names such as
``node14.x`` keep their meaning); new nodes get ids above the largest existing one.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

from .dofs import elastic_dofs
from .limits import element_count_error, remeshed_element_count
from .spec import Mechanism

__all__ = ["refine_mechanism", "remesh_mechanism", "split_segments"]


def split_segments(stations, h_max: float) -> list[float]:
    """Stations with every segment ``[a, b]`` split into ``ceil((b - a) / h_max)`` equal parts."""
    out = [float(stations[0])]
    for a, b in itertools.pairwise(stations):
        n = max(1, math.ceil((b - a) / h_max - 1e-9))
        out.extend(a + (b - a) * k / n for k in range(1, n))
        out.append(float(b))
    return out


def _resplit(mech: Mechanism, parts) -> Mechanism:
    """Split element a of link lk into ``parts(lk, a)`` equal elements, new nodes numbered after the last."""
    # index-based master names (x14) refer to the unrefined numbering: make them node-based first
    dofs = elastic_dofs(mech)
    masters = tuple(dofs.node_name(m) for m in mech.reduction.masters)
    next_id = max(mech.node_ids) + 1
    links = []
    for lk in mech.links:
        st, ids = [lk.stations[0]], [lk.node_ids[0]]
        for i, ((a, b), nb) in enumerate(zip(itertools.pairwise(lk.stations), lk.node_ids[1:], strict=True)):
            n = parts(lk, i)
            for k in range(1, n):
                st.append(a + (b - a) * k / n)
                ids.append(next_id)
                next_id += 1
            st.append(b)
            ids.append(nb)
        links.append(dataclasses.replace(lk, stations=tuple(st), node_ids=tuple(ids)))
    reduction = dataclasses.replace(mech.reduction, masters=masters)
    return dataclasses.replace(mech, links=tuple(links), reduction=reduction)


def refine_mechanism(mech: Mechanism, factor: int) -> Mechanism:
    """Split every element of every link into ``factor`` equal elements."""
    if factor < 1:
        raise ValueError(f"refinement factor must be >= 1, got {factor}")
    if factor == 1:
        return mech
    why = element_count_error(factor * sum(lk.n_elements for lk in mech.links))
    if why is not None:
        raise ValueError(f"refinement factor {factor}: expected {why}")
    return _resplit(mech, lambda lk, a: factor)


def remesh_mechanism(mech: Mechanism, elements_per_link: int) -> Mechanism:
    """Split elements so that no element of a link is longer than ``length / elements_per_link``.

    Every element ``[a, b]`` of the model file's mesh becomes ``ceil((b - a) N / L)`` equal elements, so a link
    has at least ``N`` elements and keeps all its nodes (joints, masses, gauges, masters).
    """
    if isinstance(elements_per_link, bool) or not isinstance(elements_per_link, int) or elements_per_link < 1:
        raise ValueError(f"elements per link must be an integer >= 1, got {elements_per_link!r}")

    why = element_count_error(remeshed_element_count(mech, elements_per_link))
    if why is not None:
        raise ValueError(f"{elements_per_link} elements per link: expected {why}")

    def parts(lk, a):
        h_max = lk.length / elements_per_link
        return max(1, math.ceil((lk.stations[a + 1] - lk.stations[a]) / h_max - 1e-9))

    return _resplit(mech, parts)
