"""Solid links for the FFRF truth: a link's cross-section swept along its axis, meshed by netgen with quadratic
tetrahedra, reduced to Hurty-Craig-Bampton modes by :mod:`exudyn.FEM`, cached on disk.

Geometry (link frame): the axis runs along x from 0 to the link's length ``L``; the mechanism's plane is x-y,
z points out of it. A ``round`` section is a cylinder of the link's ``diameter``, a ``tube`` the same minus its
bore, a ``rectangle`` a box of ``height`` (y) and ``width`` (z). The solid is cut into pieces at the interface
stations so that the mesh has nodes on those cross-sections.

Interfaces: every joint station and every station that carries a lumped mass is an interface, the whole
cross-section there (the face at a link end). Following Hurty-Craig-Bampton with rigid interfaces
(``HCBstaticModeSelection.RBE2``), each interface moves as a rigid body in every mode: the basis is

- 6 static modes per interface but the first (a unit rigid translation or rotation of that interface, the others
  held, the interior in static equilibrium). The first interface carries the floating frame: it is clamped in
  every mode, so the body's reference frame *is* its rigid motion;
- the fixed-interface eigenmodes (all interfaces clamped) up to ``mode_factor x band_hz``.

Because each interface is rigid in the whole basis, a joint marker over any three or more of its nodes (not on
one line) sees the same rigid motion as one over all of them: the markers use a few nodes (cheaper per step).

Section read-out (``SolidLink.sections``): at a station ``s`` the displacement field of each mode is sampled at
points of the cross-section (ngsolve's point evaluation of the quadratic field) and fitted, by least squares
over the section, with ``u_x = a + b y + c z``: the section's mean displacement ``(u_x, u_y)`` (its centre
line) and its rotation ``theta = -b`` (plane sections: ``u_x = -theta y``). The bending curvature is the mean
over a gauge length ``g`` centred at ``s`` (:func:`gauge_length`, half the section's height):
``kappa = (theta(s + g/2) - theta(s - g/2)) / g``, which is the mean of ``-d eps_xx / dy`` over the gauge's
grid, what a pair of strain gauges of that length on opposite faces measures. It is read from displacements
because the strain of quadratic tetrahedra at one point carries a mesh-dependent error (it moves between
meshes, both ways, as ``docs/ffrf_gap.md`` measures; the rotation's difference does not), and the beam
observer's gauge model is that sensitive (``docs/ffrf_slenderness.md``). Each read-out is a linear function of
the modal coordinates. These are what a tip sensor, an encoder on a rigid hub and the gauge pair measure; in a
slender link they are beam theory's axis displacement, tangent angle and curvature (the gauge's mean differs
from the curvature at ``s`` by ``g^2 kappa'' / 24``).

The cache key is a hash of everything that defines the modes (geometry, material, mesh size and order,
interfaces, read-out stations, mode rule, the format version); a changed model file or setting misses the
cache, an unchanged one skips meshing and modes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import io
import json
import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..mechanism import Mechanism

__all__ = [
    "CACHE_ENV",
    "GAUGE_FRACTION",
    "MESH_ORDER",
    "MODE_FACTOR",
    "SolidLink",
    "SolidSpec",
    "default_mesh_size",
    "gauge_length",
    "link_interfaces",
    "solid_link",
    "solid_specs",
]

log = logging.getLogger(__name__)

CACHE_ENV = "EXUFLEX_CACHE"
"""Environment variable: the cache folder (default ``~/.cache/exuflex``); solid links go in ``ffrf/`` there."""
MESH_ORDER = 2
"""Quadratic tetrahedra: linear ones lock in bending (a slender rod's first mode comes out about a third high)."""
MODE_FACTOR = 4.0
"""Fixed-interface eigenmodes are kept up to this multiple of the model's band (``reduction.band_hz``)."""
MIN_EIGEN_MODES = 4
GAUGE_FRACTION = 0.5
"""The curvature read-out's gauge length as a fraction of the section's height (:func:`gauge_length`)."""
MARKER_NODES = 8  # nodes per joint marker (a rigid interface: any three off a line give the same motion)
FORMAT = 3  # cache format version (part of the key): 3, the curvature over a gauge length


def default_mesh_size(section) -> float:
    """Default largest tetrahedron edge (m): the section's in-plane height (diameter, or height of a rectangle);
    quadratic tetrahedra and netgen's curvature grading resolve the section itself (``benchmarks/ffrf_modes.py``
    refines it: ``docs/ffrf_modes.md``)."""
    if section.shape in ("round", "tube"):
        return float(section.diameter)
    if section.shape == "rectangle":
        return float(min(section.height, max(section.width, section.height / 2)))
    raise ValueError("a solid section is needed")


@dataclass(frozen=True)
class SolidSpec:
    """Everything that defines a solid link's mesh and modes (its hash is the cache key)."""

    link: str
    length: float
    shape: str
    diameter: float | None
    inner_diameter: float | None
    width: float | None
    height: float | None
    E: float
    rho: float
    nu: float
    mesh_size: float
    interfaces: tuple[float, ...]  # stations; the first carries the floating frame
    stations: tuple[float, ...]  # read-out stations (sections)
    band_hz: float
    mode_factor: float = MODE_FACTOR
    mesh_order: int = MESH_ORDER

    def key(self) -> str:
        blob = json.dumps({"format": FORMAT, **dataclasses.asdict(self)}, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()


@dataclass
class SolidLink:
    """A solid link's reduced model: the arrays of ``ObjectFFRFreducedOrder``, its interfaces and read-outs.

    ``sections[s]`` is an ``(4, n_modes)`` array: the rows give ``u_x``, ``u_y`` (the section's centre line),
    ``theta`` and ``kappa`` at station ``s`` per unit modal coordinate (link frame). ``markers[k]`` holds the mesh
    nodes of interface ``k``'s joint marker and the offset (link frame) from their mean to the axis point.
    """

    spec: SolidSpec
    arrays: dict[str, np.ndarray]
    markers: list[tuple[np.ndarray, np.ndarray]]
    sections: dict[float, np.ndarray]
    fixed_interface_hz: np.ndarray
    n_nodes: int
    n_tets: int
    setup_s: float = 0.0
    cached: bool = False

    @property
    def n_modes(self) -> int:
        return int(self.arrays["modeBasis"].shape[1])

    def section(self, station: float) -> np.ndarray:
        for s, rows in self.sections.items():
            if abs(s - station) <= 1e-9 * max(1.0, self.spec.length):
                return rows
        raise KeyError(f"link {self.spec.link!r}: no section read-out at station {station} m")

    def interface_index(self, station: float) -> int:
        for k, s in enumerate(self.spec.interfaces):
            if abs(s - station) <= 1e-9 * max(1.0, self.spec.length):
                return k
        raise KeyError(f"link {self.spec.link!r}: no interface at station {station} m")


def link_interfaces(mech: Mechanism, link: str) -> tuple[float, ...]:
    """The link's interface stations: its joint stations and the stations of its lumped masses and payload,
    the frame's first (the first grounded joint's station if the link has one, else its first joint's)."""
    lk = mech.link(link)
    joints = [(jt.grounded, p.station) for jt in mech.joints for p in jt.points if p.link == link]
    if not joints:
        raise ValueError(f"{mech.source or mech.name}: link {link!r} takes part in no joint")
    first = next((s for g, s in joints if g), joints[0][1])
    st = {s for _, s in joints}
    for m in mech.all_masses():
        name, s = mech.node_location(m.node)
        if name == link:
            st.add(s)
    tol = 1e-9 * max(1.0, lk.length)
    rest = sorted(s for s in st if abs(s - first) > tol)
    return (float(first), *(float(s) for s in rest))


def solid_specs(mech: Mechanism, stations: dict[str, tuple[float, ...]] | None = None,
                mesh_scale: float = 1.0, mode_factor: float = MODE_FACTOR) -> dict[str, SolidSpec]:
    """One :class:`SolidSpec` per link: the model file's section, material and ``mesh_size`` (default
    :func:`default_mesh_size`, times ``mesh_scale``), the interfaces of :func:`link_interfaces`, and read-outs at
    the interfaces plus ``stations[link]``. A link without a solid section is an error naming it."""
    out = {}
    for i, lk in enumerate(mech.links):
        sec = lk.section
        if sec.shape is None:
            raise ValueError(f"{mech.source or mech.name}: links[{i}] ({lk.name}): the FFRF truth needs a solid "
                             "section (diameter; diameter and inner_diameter; or width and height), got only A and I")
        h = (lk.mesh_size if lk.mesh_size is not None else default_mesh_size(sec)) * mesh_scale
        inter = link_interfaces(mech, lk.name)
        extra = tuple(stations.get(lk.name, ())) if stations else ()
        tol = 1e-9 * max(1.0, lk.length)
        reads = sorted(set(inter))
        for s in extra:
            if all(abs(s - r) > tol for r in reads):
                reads.append(float(s))
        out[lk.name] = SolidSpec(lk.name, lk.length, sec.shape, sec.diameter, sec.inner_diameter, sec.width,
                                 sec.height, lk.material.E, lk.material.rho, lk.material.nu, float(h), inter,
                                 tuple(sorted(reads)), float(mech.reduction.band_hz), float(mode_factor))
    return out


def cache_dir() -> Path:
    root = os.environ.get(CACHE_ENV)
    base = Path(root) if root else Path.home() / ".cache" / "exuflex"
    return base / "ffrf"


# ---------------------------------------------------------------------------------------------- geometry
def _geometry(spec: SolidSpec):
    from netgen.occ import Box, Cylinder, Glue, OCCGeometry, Pnt, X

    cuts = sorted({0.0, spec.length, *spec.interfaces})
    parts = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        if b - a <= 1e-9 * spec.length:
            continue
        if spec.shape == "rectangle":
            h, w = spec.height, spec.width
            parts.append(Box(Pnt(a, -h / 2, -w / 2), Pnt(b, h / 2, w / 2)))
        else:
            piece = Cylinder(Pnt(a, 0, 0), X, r=spec.diameter / 2, h=b - a)
            if spec.shape == "tube":
                piece = piece - Cylinder(Pnt(a, 0, 0), X, r=spec.inner_diameter / 2, h=b - a)
            parts.append(piece)
    return OCCGeometry(Glue(parts) if len(parts) > 1 else parts[0])


def _section_points(spec: SolidSpec, x: float) -> np.ndarray:
    """Sample points (n, 3) of the cross-section at ``x``, symmetric in y and z (their mean is on the axis)."""
    pts = []
    if spec.shape == "rectangle":
        for fy in np.linspace(-0.9, 0.9, 7):
            for fz in np.linspace(-0.9, 0.9, 5):
                pts.append((x, fy * spec.height / 2, fz * spec.width / 2))
    else:
        ro = spec.diameter / 2
        ri = spec.inner_diameter / 2 if spec.shape == "tube" else 0.0
        radii = ri + (ro - ri) * np.array([0.15, 0.5, 0.85]) if ri > 0 else ro * np.array([0.3, 0.6, 0.9])
        for r in radii:
            for a in np.arange(16) * 2 * np.pi / 16:
                pts.append((x, r * math.cos(a), r * math.sin(a)))
    return np.array(pts)


def gauge_length(spec: SolidSpec) -> float:
    """The curvature read-out's gauge length (m): :data:`GAUGE_FRACTION` of the section's in-plane height (the
    diameter of a round or tube section), at most the link's length."""
    h = spec.height if spec.shape == "rectangle" else spec.diameter
    return min(GAUGE_FRACTION * float(h), spec.length)


def _section_rows(mesh, fes, modes_ng: np.ndarray, spec: SolidSpec, station: float) -> np.ndarray:
    """(4, n_modes): u_x, u_y, theta, kappa of the section at ``station`` per unit modal coordinate.

    ``u_x, u_y, theta`` from the displacements sampled over the section at ``station``; ``kappa`` the mean
    curvature over the gauge length ``g`` (:func:`gauge_length`) centred there (moved inside the link near an
    end): ``(theta(s + g/2) - theta(s - g/2)) / g``, the mean of ``-d eps_xx / dy`` over the gauge's grid, from
    displacements, not from the strain at one point (the module docstring says why)."""
    import ngsolve as ngs

    eps = 1e-6 * spec.length
    g = gauge_length(spec)
    x = min(max(station, eps), spec.length - eps)
    a = min(max(x - g / 2, eps), spec.length - eps - g)
    a = max(a, eps)
    b = min(a + g, spec.length - eps)
    gf = ngs.GridFunction(fes)

    def fit(xs):  # (3, n_modes): mean u_x, mean u_y and theta of the section at xs
        P = _section_points(spec, xs)
        mp = mesh(P[:, 0], P[:, 1], P[:, 2])
        pinv = np.linalg.pinv(np.column_stack([np.ones(len(P)), P[:, 1], P[:, 2]]))
        out = np.empty((3, modes_ng.shape[1]))
        for i in range(modes_ng.shape[1]):
            gf.vec.FV().NumPy()[:] = modes_ng[:, i]
            u = np.asarray(gf(mp)).reshape(len(P), 3)
            out[:, i] = (u[:, 0].mean(), u[:, 1].mean(), -(pinv @ u[:, 0])[1])
        return out

    rows = np.empty((4, modes_ng.shape[1]))
    rows[:3] = fit(x)
    rows[3] = (fit(b)[2] - fit(a)[2]) / (b - a)
    return rows


def _interface_rows(basis: np.ndarray, nodes: np.ndarray, idx: np.ndarray, station: float) -> np.ndarray:
    """(4, n_modes): u_x, u_y of the axis point and theta of a rigid interface per unit modal coordinate, by the
    exact rigid fit ``u_i = t + w x (p_i - c)`` of its nodes' displacements (the kappa row is not used)."""
    p = nodes[idx]
    c = np.array([station, 0.0, 0.0])
    r = p - c
    # rows of u_i = t + w x r_i  ->  [I, -skew(r_i)] [t; w]
    A = np.zeros((3 * len(idx), 6))
    for k, (x, y, z) in enumerate(r):
        A[3 * k : 3 * k + 3, :3] = np.eye(3)
        A[3 * k : 3 * k + 3, 3:] = -np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    dofs = (3 * idx[:, None] + np.arange(3)[None, :]).ravel()
    sol = np.linalg.lstsq(A, basis[dofs, :], rcond=None)[0]
    return np.vstack([sol[0], sol[1], sol[5], np.zeros(basis.shape[1])])


def _marker_nodes(nodes: np.ndarray, idx: np.ndarray, station: float) -> tuple[np.ndarray, np.ndarray]:
    """A few interface nodes spread around the section (outermost in ``MARKER_NODES`` directions) and the
    offset from their mean to the axis point."""
    p = nodes[idx]
    ang = np.arctan2(p[:, 2], p[:, 1])
    rad = np.hypot(p[:, 1], p[:, 2])
    chosen = []
    for a in np.arange(MARKER_NODES) * 2 * np.pi / MARKER_NODES:
        d = np.abs(np.angle(np.exp(1j * (ang - a))))
        score = d - 1e-3 * rad / max(rad.max(), 1e-12)
        k = int(np.argmin(score + 10.0 * np.isin(np.arange(len(idx)), chosen)))
        chosen.append(k)
    sel = idx[np.array(sorted(set(chosen)))]
    offset = np.array([station, 0.0, 0.0]) - nodes[sel].mean(axis=0)
    return sel.astype(np.int64), offset


# ---------------------------------------------------------------------------------------------- build / cache
_ARRAYS = ("modeBasis", "xRef", "massMatrixReduced", "stiffnessMatrixReduced", "inertiaLocal", "chiU",
           "mPsiTildePsi", "mPsiTildePsiTilde", "mPhitTPsi", "mPhitTPsiTilde", "mXRefTildePsi", "mXRefTildePsiTilde")


def _compute(spec: SolidSpec, progress: Callable[[str], None]) -> SolidLink:
    try:
        import ngsolve as ngs
    except ImportError as exc:
        raise ImportError("the FFRF truth meshes its links with netgen and ngsolve: pip install 'exuflex[ffrf]' "
                          f"(or ngsolve), missing: {exc.name}") from None
    from exudyn.FEM import FEMinterface, HCBstaticModeSelection, ObjectFFRFreducedOrderInterface, ResortIndicesExudyn2NGvector

    t0 = time.perf_counter()
    progress(f"meshing link {spec.link} (netgen, mesh size {spec.mesh_size * 1e3:.3g} mm, quadratic tetrahedra)")
    with contextlib.redirect_stdout(io.StringIO()):
        ngmesh = _geometry(spec).GenerateMesh(maxh=spec.mesh_size)
        mesh = ngs.Mesh(ngmesh)
        fem = FEMinterface()
        _, _, fes = fem.ImportMeshFromNGsolve(mesh, density=spec.rho, youngsModulus=spec.E, poissonsRatio=spec.nu,
                                              meshOrder=spec.mesh_order, createBoundaryNodeSets=False)
    nodes = fem.GetNodePositionsAsArray()
    tol = 1e-7 * spec.length
    interfaces = [np.flatnonzero(np.abs(nodes[:, 0] - s) <= tol) for s in spec.interfaces]
    for s, idx in zip(spec.interfaces, interfaces):
        if len(idx) < 3:
            raise RuntimeError(f"link {spec.link}: the mesh has {len(idx)} nodes on the section at {s} m")
    n_eig = max(MIN_EIGEN_MODES, 8)
    cutoff = spec.mode_factor * spec.band_hz
    while True:
        progress(f"link {spec.link}: {len(nodes)} nodes; Hurty-Craig-Bampton modes ({len(interfaces)} interfaces, "
                 f"{n_eig} fixed-interface modes)")
        with contextlib.redirect_stdout(io.StringIO()):
            fem.ComputeHurtyCraigBamptonModes([list(i) for i in interfaces], nEigenModes=n_eig, useSparseSolver=True,
                                              computationMode=HCBstaticModeSelection.RBE2)
        f_fixed = np.sqrt(np.abs(fem.eigenValues)) / (2 * np.pi)
        if f_fixed[-1] >= cutoff or n_eig >= 200:
            break
        n_eig *= 2
    keep = 6 * (len(interfaces) - 1) + int(np.count_nonzero(f_fixed <= cutoff))
    keep = max(keep, 6 * (len(interfaces) - 1) + min(MIN_EIGEN_MODES, n_eig))
    fem.modeBasis["matrix"] = np.ascontiguousarray(fem.modeBasis["matrix"][:, :keep])
    f_fixed = f_fixed[: keep - 6 * (len(interfaces) - 1)]
    progress(f"link {spec.link}: reduced FFRF matrices ({keep} modes)")
    with contextlib.redirect_stdout(io.StringIO()):
        cms = ObjectFFRFreducedOrderInterface(fem)
    arrays = {k: np.asarray(getattr(cms, k), float) for k in _ARRAYS}
    arrays["totalMass"] = np.array(float(cms.totalMass))
    arrays["trigList"] = np.asarray(cms.trigList, dtype=np.int64)
    basis = fem.modeBasis["matrix"]
    modes_ng = np.column_stack([ResortIndicesExudyn2NGvector(basis[:, i]) for i in range(keep)])
    tol_s = 1e-9 * max(1.0, spec.length)
    sections = {}
    for s in spec.stations:
        k = next((k for k, si in enumerate(spec.interfaces) if abs(si - s) <= tol_s), None)
        sections[s] = _section_rows(mesh, fes, modes_ng, spec, s)
        if k is not None:  # displacement and rotation of a rigid interface: exact from its nodes
            sections[s][:3] = _interface_rows(basis, nodes, interfaces[k], s)[:3]
    markers = [_marker_nodes(nodes, idx, s) for s, idx in zip(spec.interfaces, interfaces)]
    return SolidLink(spec, arrays, markers, sections, f_fixed, len(nodes), int(mesh.ne),
                     time.perf_counter() - t0, False)


def _save(sl: SolidLink, path: Path) -> None:
    data = {f"a_{k}": v for k, v in sl.arrays.items()}
    for k, (nodes, off) in enumerate(sl.markers):
        data[f"marker{k}_nodes"], data[f"marker{k}_offset"] = nodes, off
    data["section_stations"] = np.array(sorted(sl.sections))
    data["sections"] = np.stack([sl.sections[s] for s in sorted(sl.sections)])
    data["fixed_interface_hz"] = sl.fixed_interface_hz
    data["counts"] = np.array([sl.n_nodes, sl.n_tets])
    data["setup_s"] = np.array(sl.setup_s)
    data["spec"] = np.array(json.dumps(dataclasses.asdict(sl.spec)))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
    np.savez(tmp, **data)
    os.replace(tmp, path)


def _load(spec: SolidSpec, path: Path) -> SolidLink:
    with np.load(path, allow_pickle=False) as z:
        arrays = {k[2:]: z[k] for k in z.files if k.startswith("a_")}
        markers = [(z[f"marker{k}_nodes"], z[f"marker{k}_offset"]) for k in range(len(spec.interfaces))]
        sections = {float(s): z["sections"][i] for i, s in enumerate(z["section_stations"])}
        n_nodes, n_tets = (int(v) for v in z["counts"])
        return SolidLink(spec, arrays, markers, sections, z["fixed_interface_hz"], n_nodes, n_tets,
                         float(z["setup_s"]), True)


def solid_link(spec: SolidSpec, progress: Callable[[str], None] | None = None, cache: bool = True) -> SolidLink:
    """The solid link of ``spec``: read from the cache (:func:`cache_dir`, keyed by :meth:`SolidSpec.key`) or
    meshed and reduced (then written there). ``progress`` receives one-line messages (default: the log)."""
    say = progress or log.info
    path = cache_dir() / f"{spec.link}-{spec.key()[:20]}.npz"
    if cache and path.exists():
        try:
            sl = _load(spec, path)
            say(f"link {spec.link}: solid modes from the cache ({path})")
            return sl
        except (OSError, KeyError, ValueError) as exc:  # a broken cache file is rebuilt, not trusted
            log.warning("ignoring unreadable cache file %s: %s", path, exc)
    sl = _compute(spec, say)
    if cache:
        _save(sl, path)
        say(f"link {spec.link}: cached in {path} ({sl.setup_s:.1f} s)")
    return sl
