"""Elastic degrees of freedom of a mechanism: which nodal displacements are free, tied or zero.

Each node carries three nodal displacements in the global frame, ``x``, ``y`` and ``theta``.
The ERLS-defining constraints (derived from the joints and the coordinates, never per mechanism):

- a grounded (pinned) joint fixes the translations of its nodes;
- a prismatic joint fixes their translation normal to its axis (the axis is a global x or y
  direction, so this is one nodal component);
- the nodes of a joint share their translations; the lowest node id owns them; the two nodes of a
  weld share their rotation too;
- an ERLS angle coordinate of link L at joint J, absolute or relative, fixes the rotation of L's node at J,
  so that L's ERLS frame is its own tangent there (an absolute ``q`` is the angle an encoder there reads; a
  relative ``q`` is the difference of the two links' ERLS frames, and the relative encoder reads it plus the
  other link's elastic rotation at J with a minus, :meth:`exuflex.erls.model.ErlsModel.coordinate_reading_rows`:
  docs/long_arms.md says why the frame is not the other link's turned by ``q``); a slide coordinate fixes the
  slider node's translation along the axis (so that ``q`` is what a linear encoder on the slider reads).

The free displacements, taken node by node (ascending id) and component by component, are the
elastic dofs ``u``. They are named ``x{k}``, ``y{k}``, ``theta{k}`` with ``k`` the 1-based index
in ``u`` (the paper's numbering for the six-bar: ``x14``, ``theta24``, ``x25``) and, stably under
mesh refinement, ``node{n}.x``, ``node{n}.y``, ``node{n}.theta``.

Reduction masters may also be named in a link's own frame: ``node{n}.axial`` and ``node{n}.transverse`` are
the components of node ``n``'s translation along and across the axis of ``n``'s link at the current
configuration (``axial = c x + s y``, ``transverse = -s x + c y`` with ``c, s`` the cosine and sine of the
link's ERLS angle), so they keep their meaning however far the link turns. Rotations are the same in every
planar frame: ``node{n}.theta`` serves both. Any node of a joint may be named (``node7.transverse`` is the
shared translation seen from node 7's link). :meth:`ElasticDofs.locate` resolves a name.
"""

from __future__ import annotations

from dataclasses import dataclass

from .spec import Mechanism

__all__ = ["COMPONENTS", "LINK_FRAME", "DofRef", "ElasticDofs", "elastic_dofs"]

COMPONENTS = ("x", "y", "theta")
LINK_FRAME = ("axial", "transverse")  # components of a translation in its link's frame


@dataclass(frozen=True)
class DofRef:
    """A named elastic dof, possibly in a link frame (:meth:`ElasticDofs.locate`).

    ``index``: the position in ``u`` of the dof (global names) or of the first (``axial``) or second
    (``transverse``) component of its node's translation pair; ``pair``: the ``u`` indices of that pair's
    ``x`` and ``y`` (``None`` for a rotation); ``frame_node``: the node whose link's frame the name uses
    (``None``: the global frame).
    """

    name: str
    index: int
    pair: tuple[int, int] | None
    frame_node: int | None


@dataclass(frozen=True)
class ElasticDofs:
    nodes: tuple[int, ...]  # node ids in nodal-vector order
    free: tuple[tuple[int, str], ...]  # (node, component) of each elastic dof, in u order
    nodal_to_u: tuple[int, ...]  # for nodal dof 3*i+c: index into u, or -1 if fixed at zero
    names: tuple[str, ...]  # x{k} / y{k} / theta{k}
    node_names: tuple[str, ...]  # node{n}.{c}

    @property
    def n(self) -> int:
        return len(self.free)

    def index(self, name: str) -> int:
        """Index in u of a dof given as ``x14`` or ``node8.x``."""
        if name in self.names:
            return self.names.index(name)
        if name in self.node_names:
            return self.node_names.index(name)
        raise KeyError(
            f"no elastic dof named {name!r}; expected a name such as {self.names[0]!r} or {self.node_names[0]!r}"
        )

    def node_name(self, name: str) -> str:
        """The ``node{n}.{c}`` form of a dof name (link-frame names are returned unchanged)."""
        if name.rsplit(".", 1)[-1] in LINK_FRAME:
            self.locate(name)
            return name
        return self.node_names[self.index(name)]

    def locate(self, name: str) -> DofRef:
        """Resolve a master name: ``x14``, ``node8.x`` (global frame), ``node8.theta``, or ``node8.axial`` /
        ``node8.transverse`` (node 8's link frame). Any node of a joint may be named; the dof resolves to the
        joint's shared displacement."""
        node_s, _, comp = name.partition(".")
        if comp in LINK_FRAME or (comp in COMPONENTS and name not in self.node_names and node_s.startswith("node")):
            try:
                node = int(node_s[4:]) if node_s.startswith("node") else None
            except ValueError:
                node = None
            if node is None or node not in self.nodes:
                raise KeyError(f"no elastic dof named {name!r}: no node {node_s!r}; expected a name such as "
                               f"{self.node_names[0]!r} or 'node{self.nodes[-1]}.transverse'")
            base = 3 * self.nodes.index(node)
            ux, uy = self.nodal_to_u[base], self.nodal_to_u[base + 1]
            if comp == "theta" or comp in ("x", "y"):
                k = self.nodal_to_u[base + COMPONENTS.index(comp)]
                if k < 0:
                    raise KeyError(f"no elastic dof named {name!r}: node {node}'s {comp} is fixed by a joint or "
                                   "coordinate")
                return DofRef(name, k, None if comp == "theta" else (ux, uy), None)
            if ux < 0 or uy < 0:
                raise KeyError(f"no elastic dof named {name!r}: node {node}'s translation is fixed (a ground "
                               "joint)")
            return DofRef(name, ux if comp == "axial" else uy, (ux, uy), node)
        k = self.index(name)
        node, comp = self.free[k]
        if comp == "theta":
            return DofRef(name, k, None, None)
        base = 3 * self.nodes.index(node)
        return DofRef(name, k, (self.nodal_to_u[base], self.nodal_to_u[base + 1]), None)

    def nodal_index(self, node: int, comp: str) -> int:
        return 3 * self.nodes.index(node) + COMPONENTS.index(comp)


def elastic_dofs(mech: Mechanism) -> ElasticDofs:
    nodes = mech.node_ids
    pos = {n: i for i, n in enumerate(nodes)}
    nn = 3 * len(nodes)
    ZERO = -1
    parent = list(range(nn))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    fixed: set[int] = set()

    def tie(a: int, b: int) -> None:
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)

    for j in mech.joints:
        ids = [mech.node_at(p.link, p.station) for p in j.points]
        for c in (0, 1, 2) if j.kind == "weld" else (0, 1):
            dofs = [3 * pos[n] + c for n in ids]
            for d in dofs[1:]:
                tie(dofs[0], d)
            if j.kind == "prismatic":
                if abs(j.normal[c]) > 0.5:  # the normal component
                    fixed.update(dofs)
            elif j.ground is not None:
                fixed.update(dofs)
    for co in mech.coordinates:
        j = mech.joint(co.joint)
        st = next(p.station for p in j.points if p.link == co.link)
        if co.kind == "slide":
            c = 0 if abs(j.axis[0]) > 0.5 else 1
            fixed.add(3 * pos[mech.node_at(co.link, st)] + c)
            continue
        fixed.add(3 * pos[mech.node_at(co.link, st)] + 2)  # absolute or relative: the link's frame is its tangent
    fixed_roots = {find(d) for d in fixed}
    to_u = [ZERO] * nn
    free: list[tuple[int, str]] = []
    root_index: dict[int, int] = {}
    for d in range(nn):
        r = find(d)
        if r in fixed_roots:
            continue
        if r not in root_index:
            root_index[r] = len(free)
            free.append((nodes[r // 3], COMPONENTS[r % 3]))
        to_u[d] = root_index[r]
    names = tuple(f"{c}{k + 1}" for k, (_, c) in enumerate(free))
    node_names = tuple(f"node{n}.{c}" for n, c in free)
    return ElasticDofs(nodes, tuple(free), tuple(to_u), names, node_names)
