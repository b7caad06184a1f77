"""Sweep the quad mesh through the cartilage: bone-side nodes, columns along the normal, layers between.

1. Each quad-mesh node goes onto the bone-side surface along its domain ray.
2. Its column leaves the bone side along the (smoothed) normal of the
   bone-side quad surface and ends where it leaves the cartilage (an Embree
   ray): columns stand perpendicular to the bone, so a plate inclined to the
   projection direction is not sheared.  Where that ray misses (the rim), the
   domain ray's articular height is used.
3. Every column keeps a minimum height, ``layers x longest adjacent edge /
   EDGE_RATIO_AIM``, so no element's edge ratio exceeds it (the reconstructed rim tapers
   to nothing; a final guard also checks the articular faces), and the
   thickness of the two outer rings is smoothed so the articular surface does
   not drop over a single element.
4. Each node's column direction is chosen among blends of the bone normal
   and the domain ray to maximise the worst element around it
   (:mod:`.optimize`: the elements of every layer, scaled Jacobian
   first, then edge ratio); where an element stays below the gate, the column may
   be shortened or lengthened by up to 20%, and at last (untangling) its
   articular node may step off the surface by up to 0.4 mm or its bone-side
   node slide along the bone surface, carrying the column.
5. Where the cartilage ends in a wall, the contour's columns lean with it:
   foot on the wall's foot, head where the wall meets the articular surface
   (:func:`_to_wall`; the next ring follows half-way), as far as the elements
   around them allow (:func:`.optimize.settle`).
6. Articular nodes off the surface settle back onto it wherever the elements
   around them stay good (:func:`.optimize.settle`).
7. ``layers`` element layers are interpolated linearly along each column.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pyvista as pv

from kneemesh_core.geometry import interpolate_layers, quad_node_normals, unique_rows, unit
from kneemesh_core.hexmesh.footprint import Footprint
from kneemesh_core.hexmesh.optimize import choose_columns, choose_tops, settle
from kneemesh_core.hexmesh.quadmesh import EIGHT_DIRECTIONS, QuadMesh, quad_edges, quad_rings
from kneemesh_core.hexmesh.rays import crossings, first_crossing, intersector
from kneemesh_core.hexmesh.targets import EDGE_RATIO_AIM, MIN_SCALED_JACOBIAN
from kneemesh_core.surfaces.distance import closest_points



@dataclass
class HexMesh:
    """Hexahedra in LPS mm, node order that of VTK and Abaqus C3D8 (bottom face, then top face).

    Attributes
    ----------
    points : (P * (L + 1), 3) node coordinates, layer by layer from the bone side.
    hexes : (Q * L, 8) node indices.
    layer : (Q * L,) 0 at the bone, L - 1 at the joint.
    ring : (Q * L,) perimeter ring of the element's column (0 = outermost).
    node_layer : (P * (L + 1),) 0 = bone side, L = articular.
    node_edge : (P * (L + 1),) bool, nodes on the cartilage edge (the footprint contour).
    node_piece : (P * (L + 1),) int, 0 on the main lattice, k on the k-th piece meshed on a finer
        lattice of its own (:attr:`.quadmesh.QuadMesh.piece`).
    """

    points: np.ndarray
    hexes: np.ndarray
    layer: np.ndarray
    ring: np.ndarray
    node_layer: np.ndarray
    node_edge: np.ndarray
    node_piece: np.ndarray


def _over_neighbours(values: np.ndarray, edges: np.ndarray, source: np.ndarray, target: np.ndarray,
                     ufunc=np.add) -> tuple[np.ndarray, np.ndarray]:
    """Per node (P, ...), ``ufunc`` (add or maximum) folded over the ``values`` (P, ...) of its
    edge neighbours flagged ``source`` (P,) bool, for the nodes flagged ``target`` (P,) bool (zero
    elsewhere), and how many neighbours each folded (P,)."""
    acc = np.zeros_like(values, dtype=float)
    count = np.zeros(len(values))
    for a, b in ((0, 1), (1, 0)):
        use = source[edges[:, b]] & target[edges[:, a]]
        ufunc.at(acc, edges[use, a], values[edges[use, b]])
        np.add.at(count, edges[use, a], 1.0)
    return acc, count


def _node_mean(values: np.ndarray, edges: np.ndarray, n: int) -> np.ndarray:
    """Mean of each node's neighbours' values over the edge graph."""
    every = np.ones(n, bool)
    acc, count = _over_neighbours(values, edges, every, every)
    return acc / np.maximum(count, 1).reshape((n,) + (1,) * (values.ndim - 1))


def _edge_ratio_guard(bone: np.ndarray, top: np.ndarray, quads: np.ndarray, layers: int) -> np.ndarray:
    """Lengthen the columns whose layer height would give an element an edge ratio above the target.

    The longest edge of an element can lie on its articular face (tilted or
    diverging columns stretch it), which the bone-side floor does not see.
    """
    start = np.linalg.norm(top - bone, axis=1)
    cap = np.minimum(2.0 * start + 0.5, 2.0 * np.median(start))  # never let a column run away
    for _ in range(3):
        ring_edges = np.concatenate([
            np.linalg.norm(bone[quads] - bone[np.roll(quads, -1, axis=1)], axis=2),
            np.linalg.norm(top[quads] - top[np.roll(quads, -1, axis=1)], axis=2)], axis=1).max(1)
        need = np.zeros(len(bone))
        np.maximum.at(need, quads.ravel(), np.repeat(layers * ring_edges / EDGE_RATIO_AIM, 4))
        need = np.minimum(need, cap)
        length = np.linalg.norm(top - bone, axis=1)
        short = length < need
        if not short.any():
            break
        top = np.where(short[:, None], bone + (top - bone) * (need / np.maximum(length, 1e-12))[:, None], top)
    return top


def _onto_contour(qm: QuadMesh, st: np.ndarray) -> np.ndarray:
    """Parameter points (P, 2), one per node of ``qm``, those of its contour moved back onto it
    (Newton steps on the signed distance of each node's own piece)."""
    st = st.copy()
    on = qm.contour
    for _ in range(2):
        g = qm.sdf_gradient(st[on], on)
        st[on] -= (qm.sdf(st[on], on) / np.maximum((g * g).sum(1), 1e-6))[:, None] * g
    return st


#: A rim column follows its cartilage's wall where the wall stands within this angle of the column
#: (steeper walls end the cartilage; a flatter "wall" is the tapering rim, which ends at the contour).
WALL_MAX_LEAN_DEG = 35.0


def _to_wall(tm, bone: np.ndarray, top: np.ndarray, edges: np.ndarray, contour: np.ndarray,
             reach_mm: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Where the contour's columns would stand on the cartilage's wall: bone-side and articular
    nodes (P, 3 each; the others' unchanged but the next ring's).

    The footprint's contour runs at one 2-D point per node, where the rim grows steep or thin; a
    cartilage that ends in a wall leaning over its bone (a lesion's edge, a cut plate's rim) reaches
    beyond it at the bone and stops short of it at the joint, and a column standing at that point
    leaves a wedge uncovered on one side and meshes empty space on the other (Gibbons et al. 2022
    slant their edge columns the same way).  The wall is found by rays leaving the column outwards
    (away from its inner neighbours, across the column) at 15 % and 85 % of its height, each to
    where it leaves the cartilage (or, started outside, back to where it enters), at most
    ``reach_mm``: the line through the two crossings gives the column's foot on the bone side, and
    a ray up the wall from there its head, where the wall meets the articular surface (the contour
    may run part-way up a wall, and the column stop on it).  Where the line leans more than
    :data:`WALL_MAX_LEAN_DEG` off the column, or a ray finds no wall, the column stays: that is a
    tapering rim, which ends where the contour runs.  The next ring's nodes follow half-way (their
    mean neighbour's move), so the outer ring's elements lean with the wall rather than shear.
    """
    out_bone, out_top = bone.copy(), top.copy()
    everywhere = np.ones(len(bone), bool)
    inner_sum, inner_count = _over_neighbours(bone, edges, ~contour, everywhere)
    at = np.flatnonzero(contour & (inner_count > 0))
    if not at.size:
        return out_bone, out_top
    col = top[at] - bone[at]
    length = np.linalg.norm(col, axis=1)
    axis = col / np.maximum(length, 1e-12)[:, None]
    out = bone[at] - inner_sum[at] / inner_count[at, None]
    out = unit(out - np.einsum("ij,ij->i", out, axis)[:, None] * axis)
    fracs = np.array([0.15, 0.85])
    starts = (bone[at][None] + fracs[:, None, None] * col[None]).reshape(-1, 3)
    dirs = np.tile(out, (2, 1))
    ahead, leaving = first_crossing(tm, starts, dirs)
    behind, _ = first_crossing(tm, starts, -dirs)
    # inside: the wall is the first crossing ahead; outside: the crossing behind, where the ray came in
    s = np.where(leaving, ahead, -behind).reshape(2, -1)
    s[np.abs(s) > reach_mm] = np.nan
    slope = (s[1] - s[0]) / (np.diff(fracs)[0] * np.maximum(length, 1e-12))
    wall = np.isfinite(slope) & (np.abs(slope) <= np.tan(np.deg2rad(WALL_MAX_LEAN_DEG)))
    at, out, axis, length, s, slope = at[wall], out[wall], axis[wall], length[wall], s[:, wall], slope[wall]
    foot = bone[at] + (s[0] - fracs[0] * slope * length)[:, None] * out
    rise = unit(axis + slope[:, None] * out)
    cos = np.maximum(np.einsum("ij,ij->i", rise, axis), 0.5)
    ahead, leaving = first_crossing(tm, foot - 0.1 * out + 0.1 * rise, rise)
    # (never shorter than the column was, nor longer than its inner neighbours' columns reach)
    reach, _ = _over_neighbours(np.linalg.norm(top - bone, axis=1), edges, ~contour, everywhere, np.maximum)
    along = np.clip(np.where(leaving, ahead + 0.1, 0.0), length / cos, 1.25 * reach[at] / cos)
    out_bone[at] = foot
    out_top[at] = foot + along[:, None] * rise
    moved = np.zeros(len(bone), bool)
    moved[at] = True
    move_bone, count = _over_neighbours(out_bone - bone, edges, moved, ~contour)
    move_top, _ = _over_neighbours(out_top - top, edges, moved, ~contour)
    near = count > 0
    out_bone[near] += 0.5 * move_bone[near] / count[near, None]
    out_top[near] += 0.5 * move_top[near] / count[near, None]
    return out_bone, out_top


#: The directions a column may leave the bone along: blends of the bone-side normal (this weight) and the
#: domain ray (the rest), the normal first.
NORMAL_WEIGHTS = (1.0, 0.75, 0.5, 0.25, 0.0)
#: Rounds of smoothing the articular surface, each column taking its neighbours' mean direction, or
#: tilting by this much (a share of a unit vector) in any of four directions, re-cast onto the surface.
SMOOTHING_ROUNDS, TILT = 4, 0.15
#: The lengths a column still poor may take, as fractions of its length (it leaves the articular
#: surface by a fraction of the local thickness, there only).
LENGTH_FACTORS = (1.0, 0.9, 1.1, 0.8, 1.2)
#: Rounds of untangling, how far an articular node may step off the surface in each (mm, either way
#: along the bone normal and two tangents), and how far a bone-side node may slide along the bone
#: (fractions of the element size, in eight directions).
UNTANGLE_ROUNDS = 8
STEP_OFF_MM = (0.4, 0.2, 0.1, 0.05)
SLIDE_FRACTIONS = (0.3, 0.12)
#: A column's height is at most this many times the median thickness, however stretched its bone-side
#: quads (the floor for the edge ratio would otherwise raise it to absurd heights).
FLOOR_CAP = 2.0


@dataclass
class _Columns:
    """The columns of an extrusion before they are chosen: each quad-mesh node's bone-side point
    (P, 3, LPS mm), the smoothed bone-side normal and the domain ray's direction (P, 3), the domain
    ray's thickness (P,), the floor each column keeps (P,, mm) and which lie in the two outer rings."""

    tm: object
    quads: np.ndarray
    edges: np.ndarray
    layers: int
    bone: np.ndarray
    normal: np.ndarray
    ray_dir: np.ndarray
    fallback: np.ndarray
    floor: np.ndarray
    rim: np.ndarray

    @classmethod
    def start(cls, qm: QuadMesh, fp: Footprint, domain, layers: int, tm, probe: np.ndarray) -> "_Columns":
        """The columns of the quad mesh ``qm`` over the footprint's height field, heights read at ``probe``
        (P, 2: the contour's nodes inside it, where a fallback asks)."""
        n, quads = len(qm.points), qm.quads
        bone = domain.position(qm.points, fp.sample(fp.bone, probe))
        ray_top = domain.position(qm.points, fp.sample(fp.joint, probe))
        edges = quad_edges(quads)
        # bone-side normals (quads are counter-clockwise seen from the joint: normals point to the joint)
        normal = quad_node_normals(bone, quads)
        for _ in range(3):
            normal = 0.5 * unit(normal)
            normal = normal + _node_mean(normal, edges, n)
        fallback = np.linalg.norm(ray_top - bone, axis=1)
        # rim: a minimum column height for the edge ratio, and smoothing of the outer rings
        node_ring = np.full(n, np.iinfo(np.int64).max)
        np.minimum.at(node_ring, quads.ravel(), np.repeat(qm.ring, 4))
        node_ring[qm.contour] = -1
        quad_longest = np.linalg.norm(bone[quads] - bone[np.roll(quads, -1, axis=1)], axis=2).max(1)
        longest = np.zeros(n)
        np.maximum.at(longest, quads.ravel(), np.repeat(quad_longest, 4))
        floor = np.minimum(layers * longest / EDGE_RATIO_AIM, FLOOR_CAP * np.median(fallback))
        return cls(tm, quads, edges, layers, bone, unit(normal), unit(ray_top - bone), fallback, floor, node_ring <= 1)

    def cast(self, direction: np.ndarray) -> np.ndarray:
        """Articular nodes (P, 3) along unit directions (P, 3) from the bone side: where the ray leaves the
        cartilage (else, or where it finds an implausible thickness, the domain ray's), at least the floor,
        the outer rings' thickness smoothed."""
        eps = 0.05  # the rays start this far inside the bone side, mm
        n = len(self.bone)
        _, leave = crossings(self.tm, self.bone - eps * direction, direction)
        along = leave - eps
        ok = np.isfinite(along) & (along > 0.5 * self.fallback) & (along < 2.0 * self.fallback + 0.5)
        thick = np.minimum(np.where(ok, along, self.fallback), 1.5 * self.fallback + 0.3)
        for _ in range(3):
            thick = np.maximum(thick, self.floor)
            thick = np.where(self.rim, 0.5 * thick + 0.5 * _node_mean(thick, self.edges, n), thick)
        return self.bone + direction * np.maximum(thick, self.floor)[:, None]

    def choose(self, candidates: list[np.ndarray], good: float | None = None) -> np.ndarray:
        """Per node, the candidate articular node (each (P, 3)) that maximises the worst element around it."""
        if good is None:
            return choose_tops(self.bone, np.stack(candidates), self.quads, self.layers)
        return choose_tops(self.bone, np.stack(candidates), self.quads, self.layers, good=good)

    def tangents(self) -> tuple[np.ndarray, np.ndarray]:
        """Two unit tangents (P, 3 each) of the bone-side normal."""
        t1 = unit(np.cross(self.normal, np.where(np.abs(self.normal[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])))
        return t1, np.cross(self.normal, t1)

    def smoothed_tops(self) -> np.ndarray:
        """Articular nodes along the best blend of normal and ray, then smoothed on the articular surface:
        each column may take the mean direction of its neighbours' columns or tilt a little, re-cast onto it."""
        n, edges = len(self.bone), self.edges
        top = self.choose([self.cast(unit(w * self.normal + (1 - w) * self.ray_dir)) for w in NORMAL_WEIGHTS])
        t1, t2 = self.tangents()
        for _ in range(SMOOTHING_ROUNDS):
            d = unit(top - self.bone)
            tries = [top, self.cast(unit(d + _node_mean(d, edges, n))), self.cast(unit(_node_mean(top, edges, n) - self.bone))]
            tries += [self.cast(unit(d + a * t)) for a in (TILT, -TILT) for t in (t1, t2)]
            top = self.choose(tries)
        # last resort where a column is still poor: a slightly shorter or taller column
        length_now = np.linalg.norm(top - self.bone, axis=1, keepdims=True)
        variants = [self.bone + unit(top - self.bone) * np.maximum(length_now * f, self.floor[:, None]) for f in LENGTH_FACTORS]
        return self.choose(variants, good=MIN_SCALED_JACOBIAN)


def _untangle(qm: QuadMesh, fp: Footprint, domain, cols: _Columns, top: np.ndarray, h_mm: float,
              inward: np.ndarray, probe_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Where an element is still below the gate (a handful of nodes; the others stay put): an articular
    node may step off the surface by fractions of a millimetre, or a bone-side node slide along the bone
    (contour nodes along the contour), its column carried along.  Returns the bone-side and articular
    nodes (P, 3 each)."""
    n, edges, bone = len(qm.points), cols.edges, cols.bone
    t1, t2 = cols.tangents()
    u = qm.points.copy()
    at = np.arange(n)
    for _ in range(UNTANGLE_ROUNDS):
        col = top - bone
        length = np.linalg.norm(col, axis=1, keepdims=True)
        tops = [top, _node_mean(top, edges, n), bone + unit(_node_mean(unit(col), edges, n)) * length]
        tops += [top + a * t for s in STEP_OFF_MM for a in (s, -s) for t in (t1, t2, cols.normal)]
        slides = [_onto_contour(qm, u + a * h_mm * d) for a in SLIDE_FRACTIONS for d in EIGHT_DIRECTIONS]
        lifted = [domain.position(v, fp.sample(fp.bone, np.where(qm.contour[:, None], v + probe_mm * inward, v)))
                  for v in slides]
        bottoms = np.stack([bone] * len(tops) + lifted)
        columns = np.stack(tops + [b + col for b in lifted])
        k = choose_columns(bottoms, columns, cols.quads, cols.layers, good=MIN_SCALED_JACOBIAN)
        if not k.any():  # nothing moved: another pass would offer the same candidates
            break
        slid = k >= len(tops)
        u[slid] = np.stack(slides)[k[slid] - len(tops), at[slid]]
        top, bone = columns[k, at], bottoms[k, at]
    return bone, top


def extrude(qm: QuadMesh, fp: Footprint, domain, layers: int, surface: pv.PolyData, h_mm: float,
            probe_mm: float = 0.0) -> HexMesh:
    """Hex mesh of the cartilage over the quad mesh ``qm`` of element size ``h_mm``, between the
    bone-side and articular sides of the reconstructed cartilage ``surface``.

    ``probe_mm``: contour nodes read their heights that far inside the contour,
    where a folded rim makes the height field jump right on it (a fallback: it costs coverage).
    """
    tm = intersector(surface)
    inward = unit(-qm.sdf_gradient(qm.points))
    probe = np.where(qm.contour[:, None], qm.points + probe_mm * inward, qm.points)
    cols = _Columns.start(qm, fp, domain, layers, tm, probe)
    bone, top = _untangle(qm, fp, domain, cols, cols.smoothed_tops(), h_mm, inward, probe_mm)
    top = _edge_ratio_guard(bone, top, qm.quads, layers)
    # the contour's columns out to the cartilage's wall, where it ends in one, as far as the elements allow
    bone_wall, top_wall = _to_wall(tm, bone, top, cols.edges, qm.contour)
    bone, top = settle(bone, top, top_wall, qm.quads, layers, bottom_target=bone_wall, sweeps=8)
    # articular nodes the rim floor or the untangling lifted off the surface go back onto it
    # wherever the elements around them stay good
    _, top = settle(bone, top, closest_points(top, surface), qm.quads, layers)
    return _stack(qm, bone, top, layers)


def _stack(qm: QuadMesh, bone: np.ndarray, top: np.ndarray, layers: int) -> HexMesh:
    """The hexahedra of ``layers`` element layers interpolated along the columns from ``bone`` to ``top``
    (P, 3 each), layer by layer from the bone side."""
    n, quads = len(qm.points), qm.quads
    points = interpolate_layers(bone, top, layers)
    offsets = (np.arange(layers) * n)[:, None, None]
    hexes = np.concatenate([quads[None] + offsets, quads[None] + offsets + n], axis=2).reshape(-1, 8)
    q = len(quads)
    return HexMesh(
        points=points,
        hexes=hexes,
        layer=np.repeat(np.arange(layers), q),
        ring=np.tile(qm.ring, layers),
        node_layer=np.repeat(np.arange(layers + 1), n),
        node_edge=np.tile(qm.contour, layers + 1),
        node_piece=np.tile(qm.piece, layers + 1),
    )


def keep_columns(hm: HexMesh, quads: np.ndarray, keep: np.ndarray) -> HexMesh:
    """``hm``, extruded from ``quads`` (Q, 4), with only the columns of elements over the quads flagged
    ``keep`` (Q,) bool, and their nodes (still layer by layer)."""
    levels = int(hm.node_layer.max()) + 1
    node = np.zeros(len(hm.points) // levels, bool)
    node[quads[keep]] = True
    keep_nodes = np.tile(node, levels)
    index = np.cumsum(keep_nodes) - 1
    kept = np.tile(keep, len(hm.hexes) // len(quads))
    return HexMesh(hm.points[keep_nodes], index[hm.hexes[kept]], hm.layer[kept], hm.ring[kept], hm.node_layer[keep_nodes],
                   hm.node_edge[keep_nodes], hm.node_piece[keep_nodes])


def trim_columns(hm: HexMesh, keep: np.ndarray) -> tuple[HexMesh, np.ndarray]:
    """:func:`keep_columns` over ``hm``'s own bone-side quads, keep (Q,) bool, with the edge and the rings
    measured again on what is left: ``node_edge`` the nodes of edges that one quad uses, ``ring`` 0 for
    the columns over a quad with such an edge and one more per quad crossed beyond.  Returns the mesh and
    which bone-side nodes (P,) it kept."""
    levels = int(hm.node_layer.max()) + 1
    quads = hm.hexes[hm.layer == 0][:, :4]
    kept_nodes = np.zeros(len(hm.points) // levels, bool)
    kept_nodes[quads[keep]] = True
    out = keep_columns(hm, quads, keep)
    quads = out.hexes[out.layer == 0][:, :4]
    sides = np.sort(quad_edges(quads, unique=False), 1)  # side k of quad q at k * Q + q
    _, side, count = unique_rows(sides, return_inverse=True, return_counts=True)
    open_side = count[side.ravel()] == 1
    edge = np.zeros(int(kept_nodes.sum()), bool)
    edge[sides[open_side].ravel()] = True
    ring = np.maximum(quad_rings(quads, open_side.reshape(4, -1).any(0)), 0).astype(hm.ring.dtype)
    return replace(out, ring=np.tile(ring, levels - 1), node_edge=np.tile(edge, levels)), kept_nodes
