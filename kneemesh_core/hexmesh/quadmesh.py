"""All-quad mesh of the footprint: a regular lattice inside, one pillowed ring on the contour.

1. Lattice cells whose four corners lie at least ``inset * h`` inside the
   footprint are kept (a staircase region).
2. The staircase is made a clean 2-manifold: one-cell spikes, diagonal-only
   (pinch) contacts and tiny islands are removed, so every boundary vertex has
   exactly one boundary edge in and one out.
3. Every staircase boundary vertex gets a partner on the smoothed contour
   (the signed distance's root along its outward normal, then placed along
   the contour polyline in loop order so partners never cross), and every
   boundary edge a->b becomes the quad
   (b, a, a', b'): the pillow ring.  No staircase, no collapsed quads, and
   holes (full-thickness defects) get their own ring facing inwards.
4. Coordinate ascent on the worst quad around each node smooths the
   transition (contour nodes slide along the contour).
5. What the lattice and its ring leave of the footprint (a fragment of cartilage
   between denuded areas, a tip or tail narrower than two elements) is meshed the
   same way, in pieces, each on its own finer lattice.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi
from skimage.measure import find_contours

from kneemesh_core.geometry import unique_rows, unit
from kneemesh_core.hexmesh.footprint import Footprint, enclosed_holes
from kneemesh_core.hexmesh.optimize import MoveScores, independent, node_min


#: Unit steps in the parameter plane that the node optimisers try.
EIGHT_DIRECTIONS = np.array([[1, 0], [-1, 0], [0, 1], [0, -1], [0.7, 0.7], [-0.7, 0.7], [0.7, -0.7], [-0.7, -0.7]])


@dataclass
class QuadMesh:
    """Quads in the parameter plane.

    Attributes
    ----------
    points : (P, 2) parameter coordinates, mm.
    quads : (Q, 4) node indices, counter-clockwise in (s, t).
    contour : (P,) bool, nodes on the footprint contour.
    ring : (Q,) int, 0 for the pillow ring, 1 for the quads next to it, ...
    pieces : the footprints meshed apart (the whole, then each piece on a finer lattice).
    piece : (P,) int, the one of ``pieces`` each node belongs to.
    """

    points: np.ndarray
    quads: np.ndarray
    contour: np.ndarray
    ring: np.ndarray
    pieces: tuple[Footprint, ...]
    piece: np.ndarray

    @property
    def finer_pieces(self) -> int:
        """How many pieces of the footprint have a finer lattice of their own."""
        return len(np.unique(self.piece[self.piece > 0]))

    def sdf(self, st: np.ndarray, nodes: np.ndarray | None = None) -> np.ndarray:
        """(N,) signed distance, mm, of positions st (N, 2) of the nodes flagged ``nodes`` (P,) bool
        (default: every node), each to the contour of the node's own piece."""
        return self._per_piece(st, nodes, (), lambda fp, x: fp.sample(fp.sdf, x))

    def sdf_gradient(self, st: np.ndarray, nodes: np.ndarray | None = None) -> np.ndarray:
        """(N, 2) gradient of :meth:`sdf`."""
        return self._per_piece(st, nodes, (2,), lambda fp, x: fp.gradient(x))

    def _per_piece(self, st: np.ndarray, nodes: np.ndarray | None, shape: tuple, f) -> np.ndarray:
        piece = self.piece if nodes is None else self.piece[nodes]
        out = np.zeros((len(st),) + shape)
        for k in np.unique(piece):
            on = piece == k
            out[on] = f(self.pieces[k], st[on])
        return out


def quad_edges(quads: np.ndarray, unique: bool = True) -> np.ndarray:
    """The edges (E, 2) of quads (Q, 4): all 4Q in quad order, or the unique ones sorted."""
    e = np.concatenate([quads[:, [0, 1]], quads[:, [1, 2]], quads[:, [2, 3]], quads[:, [3, 0]]])
    return unique_rows(np.sort(e, 1)) if unique else e


def quad_quality(points: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Scaled Jacobian of 2-D quads (Q,): min over corners of sin(corner angle), negative if inverted."""
    return _quality_of(points[quads])


def _clean_cells(cells: np.ndarray, min_cells: int = 4) -> np.ndarray:
    """Remove one-cell spikes, pinch (diagonal-only) contacts and islands until none is left."""
    cells = cells.copy()
    four = np.array([[0, 1, 0], [1, 0, 1], [0, 1, 0]])
    for _ in range(200):
        changed = False
        nb = ndi.convolve(cells.astype(np.int8), four, mode="constant")
        spikes = cells & (nb <= 1)
        if spikes.any():
            cells[spikes] = False
            changed = True
        # 2x2 windows around each interior lattice vertex: a=(i-1,j-1) b=(i,j-1) c=(i,j) d=(i-1,j)
        a, b, c, d = cells[:-1, :-1], cells[1:, :-1], cells[1:, 1:], cells[:-1, 1:]
        nb = ndi.convolve(cells.astype(np.int8), four, mode="constant")
        for pattern, p_off, q_off in (((a & c & ~b & ~d), (0, 0), (1, 1)), ((b & d & ~a & ~c), (1, 0), (0, 1))):
            for i, j in np.argwhere(pattern):
                p, q = (i + p_off[0], j + p_off[1]), (i + q_off[0], j + q_off[1])
                if cells[p] and cells[q]:  # keep the better connected of the two diagonal cells
                    cells[p if nb[p] <= nb[q] else q] = False
                    changed = True
        lab, n = ndi.label(cells, structure=four)
        if n:
            sizes = np.bincount(lab.ravel())
            small = (sizes < min_cells) & (np.arange(n + 1) > 0)
            if small.any():
                cells[small[lab]] = False
                changed = True
        if not changed:
            return cells
    return cells


def _fill_false_holes(cells: np.ndarray, fp: Footprint, origin: np.ndarray, h: float) -> np.ndarray:
    """Fill the holes of the cell set that hold no contour (a thin spot of the signed distance,
    not a defect): a pillow ring there would have no contour to reach, and fold.

    ``cells`` (ni-1, nj-1) bool; ``origin`` (2,) parameter position of lattice node (0, 0).
    """
    lab, holes = enclosed_holes(cells)
    sub = (np.arange(5) + 0.5) / 5  # 5 x 5 samples per cell: the ray grid is h / 4
    cells = cells.copy()
    for k in holes:
        ci, cj = np.nonzero(lab == k)
        s = origin[0] + h * (ci[:, None, None] + sub[None, :, None])
        t = origin[1] + h * (cj[:, None, None] + sub[None, None, :])
        st = np.stack(np.broadcast_arrays(s, t), -1).reshape(-1, 2)
        if (fp.sample(fp.sdf, st) < 0).all():
            cells[lab == k] = True
    return cells


def _root_along(fp: Footprint, p: np.ndarray, d: np.ndarray, reach: float, back: bool = False,
                iterations: int = 20) -> np.ndarray:
    """Signed step t along directions d (N, 2) from points p (N, 2) to the contour, by bisection.

    Searches t in [0, reach] (or [-reach, reach] with ``back``); where the
    contour is not bracketed the step is the nearest end of the range.
    """
    lo = np.full(len(p), -reach if back else 0.0)
    hi = np.full(len(p), reach)
    f_lo = fp.sample(fp.sdf, p + d * lo[:, None])
    f_hi = fp.sample(fp.sdf, p + d * hi[:, None])
    bracketed = (f_lo <= 0) & (f_hi >= 0)
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        f = fp.sample(fp.sdf, p + d * mid[:, None])
        inside = f < 0
        lo = np.where(inside, mid, lo)
        hi = np.where(inside, hi, mid)
    t = 0.5 * (lo + hi)
    return np.where(bracketed, t, np.where(f_hi < 0, reach, -reach if back else 0.0))


#: What the lattice leaves of the footprint (a fragment of cartilage between denuded areas, a tip or
#: a tail narrower than two elements) is meshed on a lattice of its own this many times finer, the
#: first that holds an element ...
FINER = (2, 4)
#: ... where that piece is at least this many elements in area (smaller: slivers along the contour).
MIN_PIECE_ELEMENTS = 1.0
#: A gap of this many grid steps of the footprint separates such a piece from the mesh beside it,
#: so that the two never overlap.
PIECE_GAP_STEPS = 2


def quad_mesh(fp: Footprint, h: float, *, inset: float = 0.5) -> QuadMesh:
    """Quad mesh of a footprint with element size ``h`` (mm); see the module notes.  What the lattice
    and its ring leave of the footprint (of its finer-smoothed contour, ``fp.fine``) is meshed in
    pieces on finer lattices (:data:`FINER`): they share no node with the rest, so the element size
    may change from piece to piece."""
    meshes = []
    main = _lattice_mesh(fp, h, inset)
    covered = np.zeros_like(fp.inside)
    if main is not None:
        meshes.append(main)
        covered = ndi.binary_dilation(_covered(main, fp), iterations=PIECE_GAP_STEPS)
    pieces, n = ndi.label(fp.fine & ~covered)
    area = np.bincount(pieces.ravel(), minlength=n + 1) * fp.grid.step**2
    area[0] = 0.0  # the background
    for k in np.flatnonzero(area >= MIN_PIECE_ELEMENTS * h * h):
        piece = fp.only(pieces == k)
        for factor in FINER:
            qm = _lattice_mesh(piece, h / factor, inset)
            if qm is not None:
                meshes.append(qm)
                break
    if not meshes:
        raise ValueError("the footprint holds no complete element")
    offsets = np.cumsum([0] + [len(m.points) for m in meshes[:-1]])
    return QuadMesh(np.vstack([m.points for m in meshes]), np.vstack([m.quads + o for m, o in zip(meshes, offsets)]),
                    np.concatenate([m.contour for m in meshes]), np.concatenate([m.ring for m in meshes]),
                    (fp,) + tuple(m.pieces[0] for m in meshes[main is not None:]),
                    np.concatenate([np.full(len(m.points), k + (main is None)) for k, m in enumerate(meshes)]))


def _covered(qm: QuadMesh, fp: Footprint) -> np.ndarray:
    """The footprint's grid points (ns, nt) bool inside a quad mesh: the even-odd rule over the
    mesh's boundary edges, one grid row at a time (holes come out as holes)."""
    e = quad_edges(qm.quads, unique=False)
    _, inverse, count = unique_rows(np.sort(e, 1), return_inverse=True, return_counts=True)
    b = e[count[inverse.ravel()] == 1]
    p = fp.grid.index(qm.points)
    a, c = p[b[:, 0]], p[b[:, 1]]
    ns, nt = fp.inside.shape
    rows = np.arange(ns, dtype=float)[:, None]
    crosses = (np.minimum(a[:, 0], c[:, 0]) <= rows) & (rows < np.maximum(a[:, 0], c[:, 0]))
    ds = np.where(c[:, 0] != a[:, 0], c[:, 0] - a[:, 0], 1.0)
    at = a[:, 1] + (rows - a[:, 0]) / ds * (c[:, 1] - a[:, 1])  # (ns, E) column of each crossing
    cols = np.arange(nt)
    out = np.zeros((ns, nt), bool)
    for i in np.flatnonzero(crosses.any(1)):
        out[i] = np.searchsorted(np.sort(at[i, crosses[i]]), cols, side="right") % 2 == 1
    return out


def _lattice_mesh(fp: Footprint, h: float, inset: float) -> QuadMesh | None:
    """The lattice and its pillow ring over a footprint, at element size ``h`` (mm); None where the
    footprint holds no complete element."""
    grid = fp.grid
    ns, nt = fp.inside.shape
    ni = int((ns - 1) * grid.step // h) + 1
    nj = int((nt - 1) * grid.step // h) + 1
    lattice = np.stack(np.meshgrid(grid.s0 + h * np.arange(ni), grid.t0 + h * np.arange(nj), indexing="ij"), -1)
    node_sdf = fp.sample(fp.sdf, lattice.reshape(-1, 2)).reshape(ni, nj)
    deep = node_sdf <= -inset * h
    cells = deep[:-1, :-1] & deep[1:, :-1] & deep[1:, 1:] & deep[:-1, 1:]
    cells = _clean_cells(_fill_false_holes(cells, fp, lattice[0, 0], h))
    if not cells.any():
        return None

    ci, cj = np.nonzero(cells)
    corners = np.stack([ci * nj + cj, (ci + 1) * nj + cj, (ci + 1) * nj + cj + 1, ci * nj + cj + 1], 1)
    used, inverse = np.unique(corners, return_inverse=True)
    quads = inverse.reshape(-1, 4)
    points = lattice.reshape(-1, 2)[used]

    # boundary edges, directed with the region on their left (CCW cell order)
    padded = np.pad(cells, 1)
    across = [padded[ci + 1, cj], padded[ci + 2, cj + 1], padded[ci + 1, cj + 2], padded[ci, cj + 1]]
    edges = []
    for k in range(4):
        out = ~across[k]
        edges.append(np.stack([quads[out, k], quads[out, (k + 1) % 4]], 1))
    edges = np.concatenate(edges)
    nxt = dict(zip(edges[:, 0].tolist(), edges[:, 1].tolist()))
    prv = dict(zip(edges[:, 1].tolist(), edges[:, 0].tolist()))
    bverts = np.array(sorted(nxt))

    # partners on the contour: the root of the signed distance along the outward
    # normal (bisection: it cannot jump across a narrow gap the way a closest-point
    # projection can), then smoothing along the loop, kept on the contour
    pos = points[bverts]
    tangent = points[[nxt[v] for v in bverts]] - points[[prv[v] for v in bverts]]
    normal = unit(np.stack([tangent[:, 1], -tangent[:, 0]], 1))
    partner = pos + normal * _root_along(fp, pos, normal, 2.0 * h)[:, None]
    slot = {v: i for i, v in enumerate(bverts.tolist())}
    partner, on_poly, polys = _spread_on_contour(fp, partner, bverts, nxt, slot, h)

    n0 = len(points)
    points = np.vstack([points, partner])
    new = n0 + np.arange(len(bverts))
    pa = new[[slot[a] for a in edges[:, 0]]]
    pb = new[[slot[b] for b in edges[:, 1]]]
    pillow = np.stack([edges[:, 1], edges[:, 0], pa, pb], 1)
    quads = np.vstack([quads, pillow])
    contour = np.zeros(len(points), bool)
    contour[n0:] = True
    on_poly_all = np.full(len(points), -1)
    on_poly_all[n0:] = on_poly
    points = _optimise(points, quads, contour, h, on_poly_all, polys)
    return QuadMesh(points, quads, contour, quad_rings(quads, np.arange(len(quads)) >= len(quads) - len(pillow)), (fp,), np.zeros(len(points), int))


def _contour_polylines(fp: Footprint) -> list[np.ndarray]:
    """Closed zero-level polylines of the footprint's signed distance, (M, 2) parameter coordinates."""
    g = fp.grid
    out = []
    for c in find_contours(fp.sdf, 0.0):
        pts = np.array([g.s0, g.t0]) + c * g.step
        if len(pts) > 3 and np.allclose(pts[0], pts[-1]):
            out.append(pts[:-1])
    return out


def _arc_project(poly: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arc-length coordinate (N,) on a closed polyline (M, 2) of the closest point to each of p (N, 2),
    and the distance to it."""
    a = poly
    b = np.roll(poly, -1, axis=0)
    seg = b - a
    seg_len = np.linalg.norm(seg, axis=1)
    cum = np.r_[0.0, np.cumsum(seg_len)[:-1]]
    rel = p[:, None, :] - a[None]  # (N, M, 2)
    t = np.clip((rel * seg[None]).sum(-1) / np.maximum(seg_len**2, 1e-12)[None], 0, 1)
    d = np.linalg.norm(rel - t[..., None] * seg[None], axis=-1)
    k = np.argmin(d, axis=1)
    return cum[k] + t[np.arange(len(p)), k] * seg_len[k], d[np.arange(len(p)), k]


def _arc_point(poly: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Points (N, 2) at arc lengths u (N,) along a closed polyline."""
    seg = np.roll(poly, -1, axis=0) - poly
    seg_len = np.linalg.norm(seg, axis=1)
    cum = np.r_[0.0, np.cumsum(seg_len)]
    u = np.mod(u, cum[-1])
    k = np.clip(np.searchsorted(cum, u, side="right") - 1, 0, len(poly) - 1)
    return poly[k] + ((u - cum[k]) / np.maximum(seg_len[k], 1e-12))[:, None] * seg[k]


def _match_along(poly: np.ndarray, guess: np.ndarray, min_step: float, closed: bool) -> tuple[np.ndarray, float]:
    """Arc lengths (m,) on a closed polyline (M, 2) for the guesses (m, 2) of a loop (``closed``)
    or of a run of one, in order.

    A monotone matching by dynamic programming: consecutive guesses take
    points at least ``min_step`` mm further along the contour, and the sum of
    squared distances from the guesses is the least.  A closed loop goes once
    round; a run takes any stretch of the contour.  Returns the arc lengths
    and the root-mean-square distance.  (Hand-written: no library matches an
    ordered point sequence to a closed curve under an order constraint.)
    """
    seg_len = np.linalg.norm(np.roll(poly, -1, axis=0) - poly, axis=1)
    length = float(seg_len.sum())
    delta = min(min_step / 2.0, length / (4 * len(guess)))
    u = np.arange(0.0, length, delta)
    samples = _arc_point(poly, u)
    d2 = ((guess[:, None, :] - samples[None]) ** 2).sum(-1)  # (m, M)
    m, n = d2.shape
    s = max(int(round(min_step / delta)), 1)
    if m * s > n:
        s = max(n // m, 1)
    if closed:
        # a closed loop starts at the guess closest to the contour, on its closest sample
        a = int(np.argmin(d2.min(1)))
        anchors = [(a, int(np.argmin(d2[a])))]
    else:
        # a run takes a stretch of the contour that may cross the polyline's seam: it starts a little
        # before its first guess's closest sample, or is centred on its middle guess's (a run that skips
        # a long excursion of the contour, round a narrow neck its lattice left out, needs the first;
        # a first guess off on the wrong stretch, the second)
        slack = int(round(2.0 * min_step / delta))
        anchors = [(0, (int(np.argmin(d2[0])) - slack) % n), (0, (int(np.argmin(d2[m // 2])) - n // 2) % n)]
    best = None
    for a, j0 in anchors:
        idx, total = _monotone_path(np.roll(np.roll(d2, -a, axis=0), -j0, axis=1), s, closed)
        if best is None or total < best[1]:
            best = np.roll(u[(idx + j0) % n], a), total
    return best[0], float(np.sqrt(best[1] / m))


def _monotone_path(d2: np.ndarray, s: int, closed: bool) -> tuple[np.ndarray, float]:
    """The least sum of d2 (m, n) over sample indices (m,) that rise by at least ``s`` from one
    guess to the next (a closed loop starts on sample 0 and ends ``s`` before the end); the path
    and its cost, by dynamic programming."""
    m, n = d2.shape
    if closed:
        cost = np.full(n, np.inf)
        cost[0] = d2[0, 0]
    else:
        cost = d2[0].copy()
    back = np.zeros((m, n), dtype=np.int64)
    cols = np.arange(n)
    for i in range(1, m):
        prefix = np.minimum.accumulate(cost)
        arg = np.maximum.accumulate(np.where(cost == prefix, cols, 0))
        new = np.full(n, np.inf)
        new[s:] = d2[i, s:] + prefix[:-s]
        back[i, s:] = arg[:-s]
        cost = new
    if closed:
        cost[n - s + 1:] = np.inf  # the last guess stays a step before the anchor (the loop closes)
    j = int(np.argmin(cost))
    total = float(cost[j])
    idx = np.empty(m, dtype=np.int64)
    for i in range(m - 1, -1, -1):
        idx[i] = j
        j = back[i, j]
    return idx, total


def _runs(labels: np.ndarray) -> list[np.ndarray]:
    """Index runs (cyclic) of equal consecutive labels (m,) of a loop."""
    m = len(labels)
    change = np.flatnonzero(labels != np.roll(labels, 1))
    if not len(change):
        return [np.arange(m)]
    return [np.arange(a, a + (b - a) % m or m) % m for a, b in zip(change, np.roll(change, -1))]


def _spread_on_contour(fp: Footprint, partner: np.ndarray, bverts: np.ndarray, nxt: dict, slot: dict,
                       h: float) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Place each boundary loop's partners on the contour polylines in loop order.

    Each first guess (``partner``, N x 2) belongs to its nearest contour
    polyline (a majority vote along the loop settles flickers).  A loop that
    follows one polyline is matched to it whole; a loop that follows several
    (where a narrow neck between a hole and the outer edge dropped the cells
    between them) is matched run by run.  :func:`_match_along` keeps the
    partners in the loop's order and at least a quarter element apart, so
    pillow quads cannot fold over one another.  Returns the partners, the
    index of each one's polyline (-1: left at its guess), and the polylines,
    oriented the way their loops run.
    """
    polys = _contour_polylines(fp)
    on_poly = np.full(len(partner), -1)
    if not polys:
        return partner, on_poly, polys
    partner = partner.copy()
    oriented: set[int] = set()  # polylines already turned the way their loops run
    seen: set[int] = set()
    for start in bverts.tolist():
        if start in seen:
            continue
        loop = [start]
        while nxt[loop[-1]] != start:
            loop.append(nxt[loop[-1]])
        seen.update(loop)
        idx = np.array([slot[v] for v in loop])
        guess = partner[idx]
        dist = np.stack([_arc_project(poly, guess)[1] for poly in polys])  # (K, m)
        label = np.argmin(dist, axis=0)
        if len(polys) > 1 and len(label) >= 5:
            votes = np.stack([ndi.convolve1d((label == k).astype(float), np.ones(5), mode="wrap")
                              for k in range(len(polys))])
            label = np.argmax(votes, axis=0)
        runs = _runs(label)
        for run in runs:
            k = int(label[run[0]])
            if np.median(dist[k, run]) > 2.0 * h or (len(runs) > 1 and len(run) < 2):
                continue
            closed = len(runs) == 1
            choices = (1,) if k in oriented else (1, -1)
            fits = {o: _match_along(polys[k][::o], guess[run], 0.25 * h, closed) for o in choices}
            o = min(fits, key=lambda c: fits[c][1])
            if o == -1:
                polys[k] = np.ascontiguousarray(polys[k][::-1])
            oriented.add(k)
            partner[idx[run]] = _arc_point(polys[k], fits[o][0])
            on_poly[idx[run]] = k
    return partner, on_poly, polys


def _optimise(points: np.ndarray, quads: np.ndarray, contour: np.ndarray, h: float, on_poly: np.ndarray,
              polys: list[np.ndarray], sweeps: int = 20, good: float = 0.85) -> np.ndarray:
    """Maximise the worst quad around every node by coordinate ascent.

    Each sweep offers every node whose worst adjacent quad is below ``good`` a
    few moves - the mean of its neighbours, short steps in eight directions, or
    for contour nodes short steps along their contour polyline - scores each
    with the neighbours held still, and applies the best gains on an
    independent set (no two moved nodes share a quad).  Nothing gets worse.
    """
    n = len(points)
    e = quad_edges(quads)
    deg = np.maximum(np.bincount(e.ravel(), minlength=n), 1)[:, None]
    slid = [np.flatnonzero(on_poly == k) for k in range(len(polys))]
    arc = {k: _arc_project(polys[k], points[idx])[0] for k, idx in enumerate(slid) if len(idx)}
    stuck = contour & (on_poly < 0)
    steps = (0.3, -0.3, 0.1, -0.1)  # contour nodes slide along their polyline
    n_plain = 1 + 2 * len(EIGHT_DIRECTIONS)
    moves = MoveScores(quads, n_plain + len(steps), n, _shape_of)
    for _ in range(sweeps):
        corners = points[quads]
        current = node_min(_shape_of(corners), quads, n)
        todo = (current < good) & ~stuck
        if not todo.any():
            break
        acc = np.zeros_like(points)
        np.add.at(acc, e[:, 0], points[e[:, 1]])
        np.add.at(acc, e[:, 1], points[e[:, 0]])
        cands = [acc / deg] + [points + step * h * d for step in (0.2, 0.06) for d in EIGHT_DIRECTIONS]
        for c in cands:
            c[contour] = points[contour]
        for step in steps:
            c = points.copy()
            for k, idx in enumerate(slid):
                if len(idx):
                    c[idx] = _arc_point(polys[k], arc[k] + step * h)
            cands.append(c)
        cands = np.stack(cands)
        best, pick = moves.best(corners, cands, todo, current)
        move = independent(np.where(pick >= 0, best - current, 0.0), quads)
        if not move.any():
            break
        points[move] = cands[pick[move], np.flatnonzero(move)]
        moves.moved(move)
        for k, idx in enumerate(slid):  # arc positions of the nodes that slid
            if len(idx):
                chosen = pick[idx]
                slid_now = move[idx] & (chosen >= n_plain)
                arc[k][slid_now] += np.array(steps)[chosen[slid_now] - n_plain] * h
    return points


def _shape_of(corners: np.ndarray) -> np.ndarray:
    """What the optimiser maximises: the quad's scaled Jacobian, or twice its shortest over
    longest edge if lower (the scaled Jacobian alone would let an edge shrink to nothing)."""
    edges = np.linalg.norm(np.roll(corners, -1, axis=1) - corners, axis=-1)
    return np.minimum(_quality_of(corners), 2.0 * edges.min(1) / np.maximum(edges.max(1), 1e-12))


def _quality_of(corners: np.ndarray) -> np.ndarray:
    """:func:`quad_quality` on corner coordinates (Q, 4, 2)."""
    nxt = np.roll(corners, -1, axis=1) - corners
    prv = np.roll(corners, 1, axis=1) - corners
    cross = nxt[..., 0] * prv[..., 1] - nxt[..., 1] * prv[..., 0]
    norm = np.linalg.norm(nxt, axis=-1) * np.linalg.norm(prv, axis=-1)
    return (cross / np.maximum(norm, 1e-12)).min(1)


def quad_rings(quads: np.ndarray, outer: np.ndarray) -> np.ndarray:
    """Distance in quads (Q,) from the ``outer`` ones (Q,) bool, ring 0, by breadth-first search over
    shared edges; -1 where none is reached."""
    owner = np.tile(np.arange(len(quads)), 4)
    key = np.sort(quad_edges(quads, unique=False), 1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    k, o = key[order], owner[order]
    same = np.all(k[1:] == k[:-1], axis=1)
    a, b = o[:-1][same], o[1:][same]
    adj: list[list[int]] = [[] for _ in range(len(quads))]
    for x, y in zip(a.tolist(), b.tolist()):
        adj[x].append(y)
        adj[y].append(x)
    ring = np.where(outer, 0, -1)
    queue = deque(np.flatnonzero(outer).tolist())
    while queue:
        q = queue.popleft()
        for r in adj[q]:
            if ring[r] < 0:
                ring[r] = ring[q] + 1
                queue.append(r)
    return ring
