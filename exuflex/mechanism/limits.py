"""Size and conditioning limits of a mechanism, checked when it is loaded (before anything is built).

Three limits, each refusing input that would otherwise spend minutes (or fail deep inside a solver) with no
message:

- :data:`MAX_ELEMENTS` beam elements in all. The ERLS model's mass, stiffness and sensitivity matrices are dense
  in the ``n = 3 (nodes - constrained)`` dofs: ``8 n^2`` bytes each and ``n^3 / 3`` operations per
  factorisation, so memory grows with the square and time with the cube of the mesh. At 1000 elements
  (n about 3000) one matrix is 72 MB and a modal analysis is already a matter of a minute.
- :data:`MAX_STIFFNESS_RATIO` between the stiffest element frequency and the band of interest. The highest
  frequency of the assembled model is bounded by the highest frequency of any of its elements (Irons'
  element eigenvalue theorem: ``lambda_max(K, M) <= max_e lambda_max(k_e, m_e)``; lumped masses and joints
  only lower it). For the two-node Euler-Bernoulli element with consistent mass the element eigenvalues are
  closed-form: axial ``12 E / (rho L^2)``, bending at most ``8400 E I / (rho A L^4)``. The ratio
  ``omega_max / omega_band`` is the stiffness ratio of the equations of motion: the condition number of the
  dynamic matrices grows as its square, and an explicit integrator needs that many steps per band period.
  At 1e5 the condition number reaches 1e10, leaving the band's modes about six significant digits in double
  precision. The gallery's models lie between 15 and 400; an element a hundred times shorter than the link, a
  section in mm^2 typed as m^2 or a modulus a thousand times too high pushes the ratio past the limit.
- :data:`MAX_DAMPING_RATIO` for the Rayleigh damping ``C = alpha M + beta K`` at the band's upper edge
  ``omega_b = 2 pi band_hz``: the modal damping ratio ``zeta(omega) = alpha / (2 omega) + beta omega / 2``. A
  flexible mechanism's structural damping is a few percent; above 1 every mode near the band's edge is
  overdamped, which is not what the reduction and the observer describe (oscillating modes in the band), and
  values such as ``beta = 1e12`` (a damping ratio of about 1e15) make the integrators' Newton iterations
  and step-size control fail or crawl. Typical slips: a damping ratio in percent, or ``alpha`` and ``beta``
  swapped.

Pure functions of the frozen :class:`~exuflex.mechanism.spec.Mechanism`; they import nothing from the rest of
exuflex.
"""

from __future__ import annotations

import math

from .spec import Link, Mechanism

__all__ = ["MAX_DAMPING_RATIO", "MAX_ELEMENTS", "MAX_STIFFNESS_RATIO", "band_damping_ratio", "element_count_error",
           "element_frequency_bound", "limit_errors", "remeshed_element_count"]

MAX_ELEMENTS = 1000
"""Most beam elements a mechanism may have in all (dense ERLS matrices; see the module docstring)."""

MAX_STIFFNESS_RATIO = 1e5
"""Largest ratio of the stiffest element's frequency bound to the band's upper edge (``reduction.band_hz``)."""

MAX_DAMPING_RATIO = 1.0
"""Largest Rayleigh damping ratio at the band's upper edge (critical damping)."""


def element_frequency_bound(link: Link, length: float) -> float:
    """Upper bound (rad/s) of the frequencies of an element of ``link`` that is ``length`` long:
    ``sqrt(max(12 E / (rho L^2), 8400 E I / (rho A L^4)))``, the largest eigenvalue of the free two-node
    Euler-Bernoulli element with consistent mass (axial and bending)."""
    E, rho = link.material.E, link.material.rho
    A, I = link.section.A, link.section.I
    return math.sqrt(max(12.0 * E / (rho * length**2), 8400.0 * E * I / (rho * A * length**4)))


def band_damping_ratio(mech: Mechanism) -> float:
    """``zeta(omega_b) = alpha / (2 omega_b) + beta omega_b / 2`` at ``omega_b = 2 pi reduction.band_hz``."""
    wb = 2.0 * math.pi * mech.reduction.band_hz
    return mech.damping.alpha / (2.0 * wb) + mech.damping.beta * wb / 2.0


def element_count_error(n_elements: int) -> str | None:
    """None if ``n_elements`` is within :data:`MAX_ELEMENTS`, else what was expected (for an error message)."""
    if n_elements <= MAX_ELEMENTS:
        return None
    return (f"at most {MAX_ELEMENTS} beam elements in all links (the ERLS matrices are dense: memory grows with the "
            f"square and time with the cube of the dofs); that makes {n_elements}")


def remeshed_element_count(mech: Mechanism, elements_per_link: int) -> int:
    """Elements after :func:`~exuflex.mechanism.remesh_mechanism` (every element ``[a, b]`` of a link of length
    ``L`` split into ``ceil((b - a) N / L)`` parts), counted without building the mesh."""
    n = 0
    for lk in mech.links:
        for a, b in zip(lk.stations, lk.stations[1:]):
            n += max(1, math.ceil((b - a) * elements_per_link / lk.length - 1e-9))
    return n


def limit_errors(mech: Mechanism) -> list[tuple[str, str, object]]:
    """The limits ``mech`` breaks, as ``(field, expected, got)`` for a
    :class:`~exuflex.mechanism.ModelFileError`; empty if it is within all three."""
    out: list[tuple[str, str, object]] = []
    n_el = sum(lk.n_elements for lk in mech.links)
    if n_el > MAX_ELEMENTS:
        i = max(range(len(mech.links)), key=lambda k: mech.links[k].n_elements)
        out.append((f"links[{i}].stations", element_count_error(n_el), mech.links[i].n_elements))
        return out  # the other limits would scan every element
    wb = 2.0 * math.pi * mech.reduction.band_hz
    worst = (0.0, 0, 0.0)
    for i, lk in enumerate(mech.links):
        for a, b in zip(lk.stations, lk.stations[1:]):
            w = element_frequency_bound(lk, b - a)
            if w > worst[0]:
                worst = (w, i, b - a)
    w, i, le = worst
    if w / wb > MAX_STIFFNESS_RATIO:
        lk = mech.links[i]
        out.append((f"links[{i}]",
                    f"a stiffness ratio (stiffest element frequency / band edge) of at most {MAX_STIFFNESS_RATIO:.0e}"
                    f" (the dynamic matrices' condition number grows with its square); link {lk.name!r}'s "
                    f"{le:.3g} m element with E = {lk.material.E:.3g} Pa, rho = {lk.material.rho:.3g} kg/m^3, "
                    f"A = {lk.section.A:.3g} m^2 reaches {w:.3g} rad/s, {w / wb:.3g} x the "
                    f"{mech.reduction.band_hz:g} Hz band: a unit slip or a far too short element?",
                    float(f"{w / wb:.3g}")))
    zeta = band_damping_ratio(mech)
    if not zeta <= MAX_DAMPING_RATIO:
        d = mech.damping
        out.append(("damping",
                    f"Rayleigh coefficients alpha (1/s) and beta (s) giving a damping ratio alpha / (2 w) + beta w /"
                    f" 2 of at most {MAX_DAMPING_RATIO:g} at the band edge w = 2 pi x {mech.reduction.band_hz:g} Hz"
                    f" (structural damping is a few percent); alpha = {d.alpha:g}, beta = {d.beta:g} give "
                    f"{zeta:.3g}: a ratio in percent, or alpha and beta swapped?", {"alpha": d.alpha, "beta": d.beta}))
    return out
