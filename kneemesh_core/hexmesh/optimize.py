"""Choosing each node's column to maximise the worst element around it.

Columns along the bone-side normal keep elements square where the plate is
inclined to the projection direction; columns along the domain ray never cross
one another.  Each node picks, among candidate columns (directions blended
between the two, lengths, untangling steps, slides along the bone), the one
whose surrounding elements score best (:func:`column_score`: scaled Jacobian,
then edge ratio), greedily and in a few sweeps; :func:`settle` then moves
columns towards where they should stand (the rim's onto its wall, articular
nodes back onto the surface) as far as the elements allow.
"""

from __future__ import annotations

import numba
import numpy as np

from kneemesh_core.hexmesh.targets import EDGE_RATIO_AIM, MIN_SCALED_JACOBIAN as GATE


def layer_quality(cols: np.ndarray, layers: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Verdict scaled Jacobian (L, H) and edge ratio (L, H; longest over shortest edge) of the
    ``layers`` elements each single-element column (H, 8, 3; C3D8 node order, bone side first)
    is cut into, layer 0 at the bone.

    Hand-written rather than VTK's ``cell_quality`` because it is the column optimiser's inner loop,
    run on candidate node positions that are not a mesh yet; it matches Verdict to rounding (tested).
    """
    sj, ratio = np.empty((2, layers, len(cols)))
    _quality_kernel(_by_slot(cols), layers, sj, ratio)
    return sj, ratio


def column_score(cols: np.ndarray, layers: int = 1) -> np.ndarray:
    """What the column optimiser maximises (H,) for single-element columns (H, 8, 3) that will be
    cut into ``layers`` layers: the worst scaled Jacobian of the layer elements (every layer: a
    middle layer can be worse than both ends, as one phantom's femoral cartilage showed), or less
    where the articular face shrinks (converging columns squeeze its edges while the Jacobian,
    blind to scale, stays fine), or where the edge ratio grows (``layers`` > 1): the edge ratio
    counts fully while it scores >= the gate's Jacobian; below that only a little (never more than
    0.0015), so the optimiser never gives up a scaled Jacobian within the gate for an edge ratio."""
    return _column_quads(_by_slot(cols), layers)


def load_kernels() -> None:
    """Load the compiled kernels now (from numba's cache; compiled and cached on a first run)
    rather than in the first column the optimiser scores: 0.3 s that a new worker can spend while
    it waits for its first step."""
    cube = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
    layer_quality(cube[None])
    column_score(cube[None])


#: Edge ratios up to ER_FREE cost nothing; ER_AT_HALF scores the gate's Jacobian, as low as it lets
#: the Jacobian go.
ER_FREE, ER_AT_HALF = 4.5, EDGE_RATIO_AIM


def _by_slot(cols: np.ndarray) -> np.ndarray:
    """Columns (H, 8, 3) as (bottom, top) pairs per quad slot (H, 4, 2, 3): a view, not a copy."""
    cols = np.asarray(cols, dtype=np.float64)
    return cols.reshape(-1, 2, 4, 3).transpose(0, 2, 1, 3)


def _column_quads(c: np.ndarray, layers: int) -> np.ndarray:
    """:func:`column_score` of columns given per quad slot as (bottom, top) pairs (M, 4, 2, 3)."""
    out = np.empty(len(c))
    _score_kernel(np.asarray(c, dtype=np.float64), layers, GATE, ER_FREE, ER_AT_HALF, out)
    return out


# The kernels below are the optimiser's inner loop, compiled by numba (cached on disk after the first
# run): one pass per column with no temporaries, 10-25 times the speed of the same sums as whole-array
# NumPy expressions.  They keep those expressions' order of operations (sums left to right, minima in
# pairs), so their results are the NumPy version's bit for bit and the meshes did not change.
# c[h, i, 0] is the bone-side node of a column's corner i (counter-clockwise), c[h, i, 1] its articular node.

@numba.njit(cache=True, inline="always")
def _min(a: float, b: float) -> float:
    """np.minimum of two floats (NaN wins)."""
    return a if a < b or a != a else b


@numba.njit(cache=True, inline="always")
def _max(a: float, b: float) -> float:
    return a if a > b or a != a else b


@numba.njit(cache=True)
def _quality_kernel(c, layers, sj, ratio):  # pragma: no cover - compiled
    """Fills ``sj`` and ``ratio`` (L, H) for the columns ``c`` (H, 4, 2, 3) cut into L = ``layers``.

    Level by level rather than element by element: a node's corner frame at a level (its two
    in-plane edges and its column) is the same for the element above and the element below it, so
    each of the (L + 1) x 4 corner Jacobians is computed once, and the centre frame's column axis
    is the same for every layer.
    """
    nxt, prv = (1, 2, 3, 0), (3, 0, 1, 2)
    rise, lr, x3 = np.empty((4, 3)), np.empty(4), np.empty(3)
    level, ahead = np.empty((layers + 1, 4, 3)), np.empty((layers + 1, 4, 3))
    la, x1, x2 = np.empty((layers + 1, 4)), np.empty((layers + 1, 3)), np.empty((layers + 1, 3))
    corner, lmax, lmin = np.empty(layers + 1), np.empty(layers + 1), np.empty(layers + 1)
    for h in range(c.shape[0]):
        for i in range(4):  # one layer of each column edge
            for d in range(3):
                rise[i, d] = (c[h, i, 1, d] - c[h, i, 0, d]) / layers
            lr[i] = np.sqrt(rise[i, 0] * rise[i, 0] + rise[i, 1] * rise[i, 1] + rise[i, 2] * rise[i, 2])
        for d in range(3):
            x3[d] = ((rise[0, d] + rise[1, d]) + rise[2, d]) + rise[3, d]  # the column axis
        for lv in range(layers + 1):
            for i in range(4):
                for d in range(3):
                    level[lv, i, d] = c[h, i, 0, d] + float(lv) * rise[i, d]
        for lv in range(layers + 1):
            for i in range(4):  # in-plane edge to the next node of the quad
                for d in range(3):
                    ahead[lv, i, d] = level[lv, nxt[i], d] - level[lv, i, d]
                la[lv, i] = np.sqrt(ahead[lv, i, 0] * ahead[lv, i, 0] + ahead[lv, i, 1] * ahead[lv, i, 1]
                                    + ahead[lv, i, 2] * ahead[lv, i, 2])
            pair = np.empty(4)
            for i in range(4):  # corner Jacobian: (ahead, -behind, rise), normalised
                p = prv[i]
                a0, a1, a2 = ahead[lv, i, 0], ahead[lv, i, 1], ahead[lv, i, 2]
                b0, b1, b2 = -ahead[lv, p, 0], -ahead[lv, p, 1], -ahead[lv, p, 2]
                c0, c1, c2 = rise[i, 0], rise[i, 1], rise[i, 2]
                t = a0 * (b1 * c2 - b2 * c1) + a1 * (b2 * c0 - b0 * c2) + a2 * (b0 * c1 - b1 * c0)
                pair[i] = t / _max(la[lv, i] * la[lv, p] * lr[i], 1e-30)
            corner[lv] = _min(_min(pair[0], pair[1]), _min(pair[2], pair[3]))
            lmax[lv] = _max(_max(la[lv, 0], la[lv, 1]), _max(la[lv, 2], la[lv, 3]))
            lmin[lv] = _min(_min(la[lv, 0], la[lv, 1]), _min(la[lv, 2], la[lv, 3]))
            for d in range(3):  # (p1 - p0) + (p2 - p3) and (p2 - p1) + (p3 - p0) at this level
                x1[lv, d] = ahead[lv, 0, d] - ahead[lv, 2, d]
                x2[lv, d] = ahead[lv, 1, d] - ahead[lv, 3, d]
        lr_max = _max(_max(lr[0], lr[1]), _max(lr[2], lr[3]))
        lr_min = _min(_min(lr[0], lr[1]), _min(lr[2], lr[3]))
        s3 = x3[0] * x3[0] + x3[1] * x3[1] + x3[2] * x3[2]
        for lv in range(layers):  # the centre frame: principal axes of the layer element
            u0, u1, u2 = x1[lv, 0] + x1[lv + 1, 0], x1[lv, 1] + x1[lv + 1, 1], x1[lv, 2] + x1[lv + 1, 2]
            w0, w1, w2 = x2[lv, 0] + x2[lv + 1, 0], x2[lv, 1] + x2[lv + 1, 1], x2[lv, 2] + x2[lv + 1, 2]
            t = u0 * (w1 * x3[2] - w2 * x3[1]) + u1 * (w2 * x3[0] - w0 * x3[2]) + u2 * (w0 * x3[1] - w1 * x3[0])
            su, sw = u0 * u0 + u1 * u1 + u2 * u2, w0 * w0 + w1 * w1 + w2 * w2
            centre = t / _max(np.sqrt(su * sw * s3), 1e-30)
            sj[lv, h] = _min(_min(corner[lv], corner[lv + 1]), centre)
            longest = _max(_max(lmax[lv], lmax[lv + 1]), lr_max)
            shortest = _min(_min(lmin[lv], lmin[lv + 1]), lr_min)
            ratio[lv, h] = longest / _max(shortest, 1e-12)


@numba.njit(cache=True)
def _score_kernel(c, layers, gate, er_free, er_at_half, out):  # pragma: no cover - compiled
    """Fills ``out`` (H,) with :func:`column_score` of the columns ``c`` (H, 4, 2, 3).  The thresholds are
    arguments, not globals: numba would freeze a global into the cached machine code."""
    n = c.shape[0]
    sj, ratio = np.empty((layers, n)), np.empty((layers, n))
    _quality_kernel(c, layers, sj, ratio)
    for h in range(n):
        bottom_sum, top_min = 0.0, np.inf
        for i in range(4):
            j = (i + 1) % 4
            e0, e1, e2 = c[h, j, 0, 0] - c[h, i, 0, 0], c[h, j, 0, 1] - c[h, i, 0, 1], c[h, j, 0, 2] - c[h, i, 0, 2]
            f0, f1, f2 = c[h, j, 1, 0] - c[h, i, 1, 0], c[h, j, 1, 1] - c[h, i, 1, 1], c[h, j, 1, 2] - c[h, i, 1, 2]
            bottom = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
            top = np.sqrt(f0 * f0 + f1 * f1 + f2 * f2)
            bottom_sum = bottom if i == 0 else bottom_sum + bottom
            top_min = top if i == 0 else _min(top_min, top)
        score = _min(sj[0, h], 1.25 * top_min / _max(bottom_sum / 4.0, 1e-12))  # or the articular face shrinks
        worst_ratio = ratio[0, h]
        for lv in range(1, layers):
            score, worst_ratio = _min(score, sj[lv, h]), _max(worst_ratio, ratio[lv, h])
        if layers > 1:
            er = 1.0 - (1.0 - gate) * (worst_ratio - er_free) / (er_at_half - er_free)
            score = _min(score, er if er >= gate else gate + 0.001 * _max(er - gate, -1.5))
        out[h] = score


def choose_tops(bottom: np.ndarray, candidates: np.ndarray, quads: np.ndarray, layers: int = 1, sweeps: int = 8,
                good: float = 0.7) -> np.ndarray:
    """Per node, the candidate top position (of K) that maximises the worst adjacent :func:`column_score`.

    ``bottom`` (P, 3) bone-side nodes held still; ``candidates`` (K, P, 3)
    articular nodes, candidate 0 the start.  Returns the chosen (P, 3); see
    :func:`choose_columns`.
    """
    bottoms = np.broadcast_to(bottom, candidates.shape)
    k = choose_columns(bottoms, candidates, quads, layers, sweeps, good)
    return candidates[k, np.arange(len(bottom))]


def node_min(values: np.ndarray, quads: np.ndarray, n: int) -> np.ndarray:
    """Per node (n,), the least of the values (Q,) of the quads around it."""
    out = np.full(n, np.inf)
    np.minimum.at(out, quads.ravel(), np.repeat(values, 4))
    return out


def independent(gain: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Nodes with a positive gain that is the largest among all nodes sharing a quad with them
    (ties to the lower index): no two of them share an element, so their moves can be applied together."""
    n = len(gain)
    key = gain + 1e-9 * (n - np.arange(n)) / n
    around = np.full(n, -np.inf)
    np.maximum.at(around, quads.ravel(), np.repeat(key[quads].max(1), 4))
    return (gain > 0) & (key >= around)


class MoveScores:
    """What each node's candidate moves would score, for a coordinate ascent over a quad mesh
    (the column optimiser here, the quad smoother in :mod:`.quadmesh`).

    A move is scored as the worst ``score`` of the quads around the node with
    its neighbours held still.  That depends only on the nodes sharing a quad
    with it, so the scores are kept from sweep to sweep and worked out again
    only where one of those, or the node, has moved (:meth:`moved`); all
    candidates are scored in one ``score`` call per quad slot.

    ``score`` maps the per-slot node data of M quads (M, 4, ...) to (M,).
    """

    def __init__(self, quads: np.ndarray, n_candidates: int, n: int, score):
        self.quads, self.score = quads, score
        self.scores = np.full((n_candidates, n), -np.inf)
        self.fresh = np.zeros(n, dtype=bool)

    def scored(self, corners: np.ndarray, candidates: np.ndarray, todo: np.ndarray) -> np.ndarray:
        """The scores (K, n) of the candidates of the nodes ``todo`` (n,) bool (other columns stale).

        corners : (Q, 4, ...) the node data of each quad as it stands.
        candidates : (K, n, ...) where each node could move.
        """
        redo = todo & ~self.fresh
        if redo.any():
            k, quads = len(candidates), self.quads
            out = np.full((len(todo), k), np.inf)
            for slot in range(4):
                sel = np.flatnonzero(redo[quads[:, slot]])
                node = quads[sel, slot]
                trial = np.repeat(corners[sel][None], k, axis=0)  # (K, S, 4, ...)
                trial[:, :, slot] = candidates[:, node]
                np.minimum.at(out, node, self.score(trial.reshape(-1, *corners.shape[1:])).reshape(k, -1).T)
            self.scores[:, redo] = out.T[:, redo]
            self.fresh |= redo
        return self.scores

    def best(self, corners: np.ndarray, candidates: np.ndarray, todo: np.ndarray,
             current: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per node ``todo``, the best score (n,) and its candidate (n,; -1 where none beats ``current``
        by 1e-6; the first of equals); arguments as :meth:`scored`."""
        best, pick = current.copy(), np.full(len(todo), -1)
        for k, score in enumerate(self.scored(corners, candidates, todo)):
            better = todo & (score > best + 1e-6)
            best[better], pick[better] = score[better], k
        return best, pick

    def moved(self, move: np.ndarray) -> None:
        """The nodes ``move`` (n,) bool have moved: their scores and their neighbours' are stale."""
        self.fresh[self.quads[move[self.quads].any(1)].ravel()] = False


def choose_columns(bottoms: np.ndarray, tops: np.ndarray, quads: np.ndarray, layers: int = 1, sweeps: int = 8,
                   good: float = 0.7) -> np.ndarray:
    """Per node, the candidate column (of K) that maximises the worst adjacent :func:`column_score`.

    Coordinate ascent: each sweep scores every candidate of every node with its
    neighbours held where they are, then moves an independent set of the nodes
    that gain (no two sharing an element), largest gain first.  The worst
    element around a moved node never gets worse.

    Parameters
    ----------
    bottoms, tops : (K, P, 3) candidate bone-side and articular nodes; candidate 0 is the start.
    quads : (Q, 4) the quad mesh, counter-clockwise seen from the joint.
    layers : element layers each column is cut into (:func:`column_score`).
    good : nodes whose surrounding columns all reach this are left alone.

    Returns
    -------
    (P,) index of the chosen candidate per node.
    """
    n = bottoms.shape[1]
    ends = np.stack([bottoms, tops], axis=2)  # (K, P, 2, 3)
    now = ends[0].copy()
    choice = np.zeros(n, dtype=int)
    moves = MoveScores(quads, len(ends), n, lambda c: _column_quads(c, layers))
    for _ in range(sweeps):
        corners = now[quads]  # (Q, 4, 2, 3)
        current = node_min(_column_quads(corners, layers), quads, n)
        todo = current < good
        if not todo.any():
            break
        best, pick = moves.best(corners, ends, todo, current)
        move = independent(np.where((pick >= 0) & (pick != choice), best - current, 0.0), quads)
        if not move.any():
            break
        choice[move] = pick[move]
        now[move] = ends[pick[move], np.flatnonzero(move)]
        moves.moved(move)
    return choice


def settle(bottom: np.ndarray, top: np.ndarray, target: np.ndarray, quads: np.ndarray, layers: int,
           floor: float = 0.55, sweeps: int = 4, bottom_target: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Move columns towards targets - the whole way, or 2/3 or 1/3 of it - where the worst
    :func:`column_score` around each stays at least ``floor`` (or does not drop, where it is already
    below).  Returns the new (bottom, top), each (P, 3).

    ``target`` (P, 3): where the articular nodes ``top`` should go (their closest surface points:
    rim floors and untangling steps lift a few of them off the surface, and this takes back whatever
    the elements allow); ``bottom_target`` (P, 3), where the bone-side nodes should go along with
    them (by the same fraction; default: they stay).
    """
    n = len(top)
    ends = np.stack([bottom, top], axis=1)  # (P, 2, 3)
    goal = np.stack([bottom if bottom_target is None else bottom_target, target], axis=1)
    fracs = (1 / 3, 2 / 3, 1.0)
    moves = MoveScores(quads, len(fracs), n, lambda c: _column_quads(c, layers))
    for _ in range(sweeps):
        gap = np.linalg.norm(goal - ends, axis=2).max(1)
        todo = gap > 0.02
        if not todo.any():
            break
        corners = ends[quads]  # (Q, 4, 2, 3)
        current = node_min(_column_quads(corners, layers), quads, n)
        cands = np.stack([ends + frac * (goal - ends) for frac in fracs])
        best_frac = np.zeros(n)
        for frac, score in zip(fracs, moves.scored(corners, cands, todo)):
            ok = todo & (score >= np.minimum(current, floor))
            best_frac[ok] = frac
        move = independent(best_frac * gap, quads)
        if not move.any():
            break
        ends[move] += best_frac[move, None, None] * (goal[move] - ends[move])
        moves.moved(move)
    return ends[:, 0], ends[:, 1]
