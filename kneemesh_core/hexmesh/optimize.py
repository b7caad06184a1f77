"""Choosing each node's column to maximise the worst element around it.

Columns along the bone-side normal keep elements square where the plate is
inclined to the projection direction; columns along the domain ray never cross
one another.  Each node picks, among candidate columns (directions blended
between the two, lengths, untangling steps, slides along the bone), the one
whose surrounding elements score best (:func:`column_score`: scaled Jacobian,
then edge ratio), greedily and in a few sweeps; :func:`settle` then takes
articular nodes back onto the surface where the elements allow.
"""

from __future__ import annotations

import numpy as np

# Corner frames of the Verdict hex scaled Jacobian: node -> its three edge neighbours.
_CORNERS = np.array([[0, 1, 3, 4], [1, 2, 0, 5], [2, 3, 1, 6], [3, 0, 2, 7],
                     [4, 7, 5, 0], [5, 4, 6, 1], [6, 5, 7, 2], [7, 6, 4, 3]])


def _triple(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """a . (b x c) over the last axis (length 3), written out: numpy's cross is slow on small axes."""
    return (a[..., 0] * (b[..., 1] * c[..., 2] - b[..., 2] * c[..., 1])
            + a[..., 1] * (b[..., 2] * c[..., 0] - b[..., 0] * c[..., 2])
            + a[..., 2] * (b[..., 0] * c[..., 1] - b[..., 1] * c[..., 0]))


def _sq(v: np.ndarray) -> np.ndarray:
    """Squared length over the last axis (length 3), written out (a reduction over 3 is slow)."""
    return v[..., 0] * v[..., 0] + v[..., 1] * v[..., 1] + v[..., 2] * v[..., 2]


def scaled_jacobian(points: np.ndarray, hexes: np.ndarray | None = None) -> np.ndarray:
    """Verdict's hex scaled Jacobian (H,) on numpy arrays: min over the 8 corners and the centre.

    ``points`` (P, 3) with ``hexes`` (H, 8), or the corner coordinates (H, 8, 3) directly.

    Hand-written because it runs inside the optimisation loop on candidate node
    positions that are not a mesh yet; the reported figures come from
    pyvista/VTK (``cell_quality``), which this matches to rounding.
    """
    p = points if hexes is None else points[hexes]  # (H, 8, 3)
    e = p[:, _CORNERS[:, 1:]] - p[:, _CORNERS[:, :1]]  # (H, 8 corners, 3 edges, 3)
    length = np.sqrt(_sq(e))
    corner = _triple(e[:, :, 0], e[:, :, 1], e[:, :, 2]) / np.maximum(length.prod(-1), 1e-30)
    x1 = (p[:, 1] - p[:, 0]) + (p[:, 2] - p[:, 3]) + (p[:, 5] - p[:, 4]) + (p[:, 6] - p[:, 7])
    x2 = (p[:, 3] - p[:, 0]) + (p[:, 2] - p[:, 1]) + (p[:, 7] - p[:, 4]) + (p[:, 6] - p[:, 5])
    x3 = (p[:, 4] - p[:, 0]) + (p[:, 5] - p[:, 1]) + (p[:, 6] - p[:, 2]) + (p[:, 7] - p[:, 3])
    norm = np.sqrt(_sq(x1) * _sq(x2) * _sq(x3))
    return np.minimum(corner.min(1), _triple(x1, x2, x3) / np.maximum(norm, 1e-30))


def column_score(cols: np.ndarray, layers: int = 1) -> np.ndarray:
    """What the column optimiser maximises (H,) for single-element columns (H, 8, 3) that will be
    cut into ``layers`` layers: the worst scaled Jacobian of the layer elements (every layer: a
    middle layer can be worse than both ends, as one phantom's femoral cartilage showed), or less
    where the articular face shrinks (converging columns squeeze its edges while the Jacobian,
    blind to scale, stays fine), or where the edge ratio grows."""
    bottom = np.linalg.norm(cols[:, [1, 2, 3, 0]] - cols[:, :4], axis=2)
    top = np.linalg.norm(cols[:, [5, 6, 7, 4]] - cols[:, 4:], axis=2)
    shrink = 1.25 * top.min(1) / np.maximum(bottom.mean(1), 1e-12)
    if layers == 1:
        return np.minimum(scaled_jacobian(cols), shrink)
    rise = (cols[:, 4:] - cols[:, :4]) / layers
    k = np.arange(layers + 1)[:, None, None, None]
    levels = cols[None, :, :4] + k * rise[None]  # (L + 1, H, 4, 3)
    elements = np.concatenate([levels[:-1], levels[1:]], axis=2).reshape(-1, 8, 3)  # (L * H, 8, 3)
    score = np.minimum(scaled_jacobian(elements).reshape(layers, -1).min(0), shrink)
    # the edge ratio counts fully while it scores >= 0.5; below that only a little (never more than
    # 0.0015), so the optimiser never gives up a scaled Jacobian >= 0.5 for an edge ratio
    ratio = _edge_ratio(elements).reshape(layers, -1).max(0)
    er = 1.0 - 0.5 * (ratio - ER_FREE) / (ER_AT_HALF - ER_FREE)
    return np.minimum(score, np.where(er >= 0.5, er, 0.5 + 0.001 * np.maximum(er - 0.5, -1.5)))


#: Edge ratios up to ER_FREE cost nothing; ER_AT_HALF scores 0.5, as low as the gate lets the Jacobian go.
ER_FREE, ER_AT_HALF = 4.5, 5.8


def _edge_ratio(h8: np.ndarray) -> np.ndarray:
    """Longest over shortest edge of hexahedra (H, 8, 3)."""
    a, b = np.array([0, 1, 2, 3, 4, 5, 6, 7, 0, 1, 2, 3]), np.array([1, 2, 3, 0, 5, 6, 7, 4, 4, 5, 6, 7])
    e = _sq(h8[:, a] - h8[:, b])
    return np.sqrt(e.max(1) / np.maximum(e.min(1), 1e-24))


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


def _node_min(values: np.ndarray, quads: np.ndarray, n: int) -> np.ndarray:
    """Per node (n,), the least of the values (Q,) of the quads around it."""
    out = np.full(n, np.inf)
    np.minimum.at(out, quads.ravel(), np.repeat(values, 4))
    return out


def _score_moves(cols: np.ndarray, quads: np.ndarray, active: np.ndarray, bottom: np.ndarray, top: np.ndarray,
                 n: int, layers: int) -> np.ndarray:
    """Per node (n,), the worst :func:`column_score` around it if it alone moved to (bottom, top) (P, 3);
    only the columns ``active`` are scored (inf elsewhere)."""
    aq, acols = quads[active], cols[active]
    score = np.full(n, np.inf)
    for slot in range(4):
        trial = acols.copy()
        trial[:, slot] = bottom[aq[:, slot]]
        trial[:, 4 + slot] = top[aq[:, slot]]
        np.minimum.at(score, aq[:, slot], column_score(trial, layers))
    return score


def independent(gain: np.ndarray, quads: np.ndarray) -> np.ndarray:
    """Nodes with a positive gain that is the largest among all nodes sharing a quad with them
    (ties to the lower index): no two of them share an element, so their moves can be applied together."""
    n = len(gain)
    key = gain + 1e-9 * (n - np.arange(n)) / n
    around = np.full(n, -np.inf)
    np.maximum.at(around, quads.ravel(), np.repeat(key[quads].max(1), 4))
    return (gain > 0) & (key >= around)


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
    bottom, top = bottoms[0].copy(), tops[0].copy()
    choice = np.zeros(n, dtype=int)
    for _ in range(sweeps):
        cols = np.concatenate([bottom[quads], top[quads]], axis=1)  # (Q, 8, 3)
        current = _node_min(column_score(cols, layers), quads, n)
        todo = current < good
        if not todo.any():
            break
        best, best_k = current.copy(), choice.copy()
        active = np.flatnonzero(todo[quads].any(1))  # only columns around nodes being improved
        for k in range(len(tops)):
            score = _score_moves(cols, quads, active, bottoms[k], tops[k], n, layers)
            better = todo & (score > best + 1e-6)
            best[better], best_k[better] = score[better], k
        move = independent(np.where(best_k != choice, best - current, 0.0), quads)
        if not move.any():
            break
        choice[move] = best_k[move]
        idx = np.flatnonzero(move)
        bottom[move] = bottoms[best_k[move], idx]
        top[move] = tops[best_k[move], idx]
    return choice


def settle(bottom: np.ndarray, top: np.ndarray, target: np.ndarray, quads: np.ndarray, layers: int,
           floor: float = 0.55, sweeps: int = 4) -> np.ndarray:
    """Move articular nodes (P, 3) towards ``target`` (P, 3; their closest surface points) - the
    whole way, or 2/3 or 1/3 of it - where the worst :func:`column_score` around each stays at
    least ``floor`` (or does not drop, where it is already below).  Returns the new tops (P, 3).

    Rim floors and untangling steps lift a few articular nodes off the surface;
    this takes back whatever the elements allow.
    """
    n = len(top)
    top = top.copy()
    for _ in range(sweeps):
        gap = np.linalg.norm(target - top, axis=1)
        todo = gap > 0.02
        if not todo.any():
            break
        cols = np.concatenate([bottom[quads], top[quads]], axis=1)
        current = _node_min(column_score(cols, layers), quads, n)
        active = np.flatnonzero(todo[quads].any(1))
        best_frac = np.zeros(n)
        for frac in (1 / 3, 2 / 3, 1.0):
            cand = top + frac * (target - top)
            score = _score_moves(cols, quads, active, bottom, cand, n, layers)
            ok = todo & (score >= np.minimum(current, floor))
            best_frac[ok] = frac
        move = independent(best_frac * gap, quads)
        if not move.any():
            break
        top[move] += best_frac[move, None] * (target[move] - top[move])
    return top
