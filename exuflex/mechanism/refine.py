"""Mesh refinement of a mechanism (for convergence studies and fine-mesh truths).

- :func:`refine_mechanism`: split every element into ``factor`` equal parts;
- :func:`remesh_mechanism`: split every element into the fewest equal parts such that no element is
  longer than ``length / elements_per_link`` of its link (at least that many elements per link);
- :func:`gauge_mesh`: the elements next to each curvature gauge no longer than a length: the static sag's
  :func:`gauge_sag_length` or the lengths given (the filter's rule, :mod:`exuflex.reduction.gauge_rule`, which the
  observer and the ERLS truth apply; ``docs/gauge_mesh.md``), nodes added at that distance on either side.

The first two refuse meshes of more than :data:`~exuflex.mechanism.limits.MAX_ELEMENTS` elements (``ValueError``).

All keep the original nodes and their ids (so masses, gauges and node-based dof names such as
``node14.x`` keep their meaning); new nodes get ids above the largest existing one.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

from .dofs import elastic_dofs
from .limits import element_count_error, remeshed_element_count
from .spec import Mechanism

__all__ = ["GAUGE_SAG_TOL", "gauge_mesh", "gauge_sag_length", "refine_mechanism", "remesh_mechanism",
           "split_segments"]

#: the gauge rule's tolerance: the mesh's error in a curvature gauge's reading of the static sag, in the gauge's
#: noise standard deviations (:func:`gauge_sag_length`)
GAUGE_SAG_TOL = 0.1


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

    def inner(lk, i, a, b):
        n = parts(lk, i)
        return [a + (b - a) * k / n for k in range(1, n)]

    return _insert(mech, inner)


def _insert(mech: Mechanism, inner) -> Mechanism:
    """Add the stations ``inner(lk, i, a, b)`` (ascending, strictly between ``a`` and ``b``) inside element ``i =
    [a, b]`` of link ``lk``, new nodes numbered after the last."""
    # index-based master names (x14) refer to the unrefined numbering: make them node-based first
    dofs = elastic_dofs(mech)
    masters = tuple(dofs.node_name(m) for m in mech.reduction.masters)
    next_id = max(mech.node_ids) + 1
    links = []
    for lk in mech.links:
        st, ids = [lk.stations[0]], [lk.node_ids[0]]
        for i, ((a, b), nb) in enumerate(zip(itertools.pairwise(lk.stations), lk.node_ids[1:], strict=True)):
            for x in inner(lk, i, a, b):
                st.append(x)
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


def gauge_sag_length(mech: Mechanism, sensor, tol: float = GAUGE_SAG_TOL) -> float:
    """The longest element next to a curvature gauge whose reading of the link's static sag errs by at most
    ``tol`` gauge noise standard deviations: ``h_g = sqrt(12 EI tol sigma / w)``, ``w = rho A |g|`` the link's
    weight per length (its largest transverse share: the link across gravity); ``inf`` without gravity, for
    another sensor kind or a noiseless gauge.

    Why (``docs/gauge_mesh.md``): under a distributed transverse load ``w`` the Euler-Bernoulli deflection is a
    quartic (its fourth derivative ``w / EI``); the two-node cubic element with the consistent load holds the
    nodal values and slopes exactly (the point load's deflection is cubic between nodes), so within an element of
    length ``h`` the error is the quartic bubble ``w / (24 EI) x^2 (h - x)^2``, whose curvature error ``w / (12 EI)
    (h^2 - 6 h x + 6 x^2)`` is largest at the nodes, ``w h^2 / (12 EI)``. Only the elements next to the gauge
    enter its reading; the rest of the mesh holds the nodal values exactly. The deflection's error is ``O(h^4)``
    and the slope's ``O(h^3)``, so the foreshortening (second order in the slope) and the tip readings need
    nothing finer.
    """
    g = math.hypot(*mech.gravity)
    if sensor.kind != "curvature" or not g or not sensor.noise_std > 0:
        return math.inf
    lk = mech.link(sensor.link)
    w = lk.material.rho * lk.section.A * g
    return math.sqrt(12.0 * lk.material.E * lk.section.I * tol * sensor.noise_std / w)


def gauge_mesh(mech: Mechanism, tol: float = GAUGE_SAG_TOL, lengths: dict[str, float] | None = None) -> Mechanism:
    """The mesh with the elements next to every curvature gauge no longer than its ``h_g``: :func:`gauge_sag_length`
    (``tol``), or ``lengths[gauge name]`` where given (then only the gauges named there; the filter's rule,
    :func:`exuflex.reduction.gauge_rule.gauge_lengths`). For a gauge at a node, a node on either side where the
    element there is longer, at ``h_g`` from the gauge (halfway to the next node where that is within ``2 h_g``, so
    that no added element is shorter than ``h_g / 2``); for a gauge inside an element, that element split into the
    fewest equal parts no longer than ``h_g``. The mechanism itself where nothing is added (no gravity, no gauge,
    or a mesh fine enough)."""
    add: dict[str, set] = {}
    for sn in mech.sensors:
        if lengths is None:
            h = gauge_sag_length(mech, sn, tol)
        elif sn.kind == "curvature" and sn.name in lengths:
            h = float(lengths[sn.name])
        else:
            continue
        if not math.isfinite(h):
            continue
        lk = mech.link(sn.link)
        s, st, eps = float(sn.station), lk.stations, 1e-9 * lk.length
        new = add.setdefault(lk.name, set())
        lower = max((x for x in st if x < s - eps), default=None)
        upper = min((x for x in st if x > s + eps), default=None)
        if not any(abs(x - s) <= eps for x in st):  # the gauge inside an element: that element in equal parts
            n = math.ceil((upper - lower) / h - 1e-9)
            new.update(lower + (upper - lower) * k / n for k in range(1, n))
            continue
        # a node at h from the gauge, or halfway where that would leave an element shorter than h beyond it
        if lower is not None and s - lower > h * (1 + 1e-9):
            new.add(s - h if s - lower > 2.0 * h else 0.5 * (lower + s))
        if upper is not None and upper - s > h * (1 + 1e-9):
            new.add(s + h if upper - s > 2.0 * h else 0.5 * (s + upper))
    if not any(add.values()):
        return mech

    def inner(lk, i, a, b):
        eps = 1e-9 * lk.length
        return sorted(x for x in add.get(lk.name, ()) if a + eps < x < b - eps)

    return _insert(mech, inner)
