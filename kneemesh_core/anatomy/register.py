"""Template onto subject: similarity ICP, a smooth non-rigid refinement, and the side by shape.

:func:`register` places a template bone (template frame, mm; see :mod:`.template`) on a
subject's bone (points in LPS mm): a start from the knee's coarse axes, a trimmed similarity ICP
(Umeyama's closed form each round, the subject's points paired with their nearest template
points, the worst 10 % of pairs left out, so a shaft that one field of view shows and the
other does not pulls nothing), then a non-rigid refinement, a displacement field smoothed with
Gaussians of decreasing width, kept only where it lowers the residual.

:func:`side_by_shape` registers the template and its mirror image and compares the residuals:
a proper rotation cannot turn a left tibia into a right one, so the wrong side fits worse.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from kneemesh_core.anatomy.frames import CoarseAxes

#: The part of each bone that is registered, by distance along the knee's superior axis: the
#: proximal tibia, the distal femur, the whole patella (mm from the bone's joint end).
CROP_MM = {"tibia": 55.0, "femur": 55.0, "patella": None}
#: At most this many times the subject is cut again square to the long axis just found and registered anew.
RECROPS = 4
#: Pairs kept each ICP round: the closest fraction.
TRIM = 0.9
#: Relative difference of the right and mirrored residuals needed to call a side by shape.
SIDE_MIN_RELATIVE_GAP = 0.08


@dataclass(frozen=True)
class Similarity:
    """x -> scale * R x + t (R a proper rotation)."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, p: np.ndarray) -> np.ndarray:
        return self.scale * p @ self.rotation.T + self.translation

    def inverse(self, q: np.ndarray) -> np.ndarray:
        return ((q - self.translation) @ self.rotation) / self.scale


def umeyama(src: np.ndarray, dst: np.ndarray) -> Similarity:
    """Least-squares similarity taking points ``src`` (N, 3) to ``dst`` (N, 3) (Umeyama 1991)."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    u, d, vt = np.linalg.svd(b.T @ a / len(src))
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2, 2] = -1.0
    rot = u @ s @ vt
    scale = float(np.trace(np.diag(d) @ s) / (a ** 2).sum(1).mean())
    return Similarity(scale, rot, md - scale * rot @ ms)


@dataclass
class Registration:
    """A template bone placed on a subject's bone."""

    bone: str
    mirrored: bool  # the template was mirrored (a left knee)
    similarity: Similarity
    rms_similarity_mm: float
    rms_mm: float  # after the non-rigid refinement (equal to the above where it did not help)
    # the refinement: template control points in subject space (K, 3) and their displacements
    controls: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    moves: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    sigma_mm: float = 0.0

    def place(self, template_points: np.ndarray) -> np.ndarray:
        """Template-frame points (N, 3) -> subject LPS mm (similarity, then the smooth field)."""
        p = _mirror(template_points) if self.mirrored else template_points
        x = self.similarity.apply(p)
        return x + _field(x, self.controls, self.moves, self.sigma_mm)

    def direction(self, v: np.ndarray) -> np.ndarray:
        """A template-frame direction (3,) placed on the subject by the similarity's rotation: a unit
        vector (3,), LPS (the mirrored template's z is the subject's -z, so a named direction means
        the same on either side)."""
        d = self.similarity.rotation @ (_mirror(v[None])[0] if self.mirrored else v)
        return d / np.linalg.norm(d)

    def facts(self) -> dict:
        return {"scale": round(self.similarity.scale, 4), "rms_similarity_mm": round(self.rms_similarity_mm, 3),
                "rms_mm": round(self.rms_mm, 3), "non_rigid": bool(len(self.controls)), "mirrored": self.mirrored}


def _mirror(p: np.ndarray) -> np.ndarray:
    return p * np.array([1.0, 1.0, -1.0])


def _field(x: np.ndarray, controls: np.ndarray, moves: np.ndarray, sigma: float) -> np.ndarray:
    """The smooth displacement (N, 3) at points ``x``: Gaussian-weighted mean of the control moves."""
    if not len(controls):
        return np.zeros_like(x)
    d2 = ((x[:, None, :] - controls[None]) ** 2).sum(-1)
    w = np.exp(-0.5 * d2 / sigma ** 2)
    return (w @ moves) / np.maximum(w.sum(1, keepdims=True), 1e-9)


def _crop(points: np.ndarray, direction: np.ndarray, from_top: bool, length: float | None) -> np.ndarray:
    """The ``length`` mm of a bone nearest its joint end along ``direction``."""
    if length is None:
        return points
    h = points @ direction
    return points[h >= h.max() - length] if from_top else points[h <= h.min() + length]


def _rms_to(subject: np.ndarray, tree: cKDTree, sim: Similarity, trim: float = TRIM) -> float:
    d, _ = tree.query(sim.inverse(subject))
    d = np.sort(d * sim.scale)[: max(3, int(trim * len(d)))]
    return float(np.sqrt((d ** 2).mean()))


def register(bone: str, template: np.ndarray, subject: np.ndarray, axes: CoarseAxes, mirrored: bool,
             refine: bool = True, iterations: int = 40) -> Registration:
    """Place a template bone (points (N, 3), template frame) on the subject's bone (points (M, 3),
    LPS mm), right-knee template or (``mirrored``) its mirror image."""
    tmpl = _mirror(template) if mirrored else template
    up = np.array([0.0, 1.0, 0.0])
    joint_end_top = bone == "tibia"  # the tibia's joint end is its top, the femur's its bottom
    t_crop = _crop(tmpl, up, joint_end_top, CROP_MM[bone])
    s_crop = _crop(subject, axes.superior, joint_end_top, CROP_MM[bone])
    # start: the template's anterior, superior and (mirror) lateral axes on the knee's, centroids together
    rot = axes.basis()
    spread_t = np.sqrt(((t_crop - t_crop.mean(0)) ** 2).sum(1).mean())
    spread_s = np.sqrt(((s_crop - s_crop.mean(0)) ** 2).sum(1).mean())
    scale = float(spread_s / spread_t)
    sim = Similarity(scale, rot, s_crop.mean(0) - scale * rot @ t_crop.mean(0))
    tree = cKDTree(t_crop)
    sim = _icp(tree, t_crop, s_crop, sim, iterations)
    for _ in range(RECROPS if CROP_MM[bone] is not None else 0):
        # the subject cut again square to the bone's own long axis as placed, not the knee's superior:
        # a bone cut obliquely pulls the template towards the cut (a tibia swung 20 deg read 15)
        axis = sim.rotation @ up
        s_crop = _crop(subject, axis, joint_end_top, CROP_MM[bone])
        sim = _icp(tree, t_crop, s_crop, sim, iterations)
        if (sim.rotation @ up) @ axis > np.cos(np.radians(0.5)):
            break
    rms_sim = _rms_to(s_crop, tree, sim)
    reg = Registration(bone, mirrored, sim, rms_sim, rms_sim)
    if refine:
        _refine(reg, t_crop, s_crop)
    return reg


def _icp(tree: cKDTree, t_crop: np.ndarray, s_crop: np.ndarray, sim: Similarity, iterations: int) -> Similarity:
    """Trimmed similarity ICP from ``sim``: the subject's points (N, 3) paired with their nearest template
    points (``tree`` over ``t_crop``), the worst pairs (1 - :data:`TRIM`) left out, Umeyama each round."""
    last = np.inf
    for _ in range(iterations):
        d, j = tree.query(sim.inverse(s_crop))
        keep = d <= np.quantile(d, TRIM)
        sim = umeyama(t_crop[j[keep]], s_crop[keep])
        rms = float(np.sqrt(((d[keep] * sim.scale) ** 2).mean()))
        if last - rms < 1e-4:
            break
        last = rms
    return sim


def _refine(reg: Registration, t_crop: np.ndarray, s_crop: np.ndarray, sigmas=(12.0, 8.0, 5.0),
            reach_mm: float = 6.0, controls: int = 300) -> None:
    """A smooth non-rigid correction after the similarity: at each width, every template point and
    every subject point within ``reach_mm`` of the other surface pull the two together; the pulls,
    averaged at ``controls`` template points, are smoothed with a Gaussian of that width.  Kept only
    if the trimmed residual falls."""
    x0 = reg.similarity.apply(t_crop)
    idx = np.arange(0, len(x0), max(1, len(x0) // controls))
    d2 = ((x0[idx][:, None] - x0[None]) ** 2).sum(-1)  # controls x template points, once for every width
    s_tree = cKDTree(s_crop)
    x = x0
    best = (reg.rms_mm, None, None, 0.0)
    for sigma in sigmas:
        d, j = s_tree.query(x)
        pull = np.zeros_like(x)
        count = np.zeros(len(x))
        near = d < reach_mm
        pull[near] += s_crop[j[near]] - x[near]
        count[near] += 1
        d_back, i_back = cKDTree(x).query(s_crop)
        back = d_back < reach_mm
        np.add.at(pull, i_back[back], s_crop[back] - x[i_back[back]])
        np.add.at(count, i_back[back], 1)
        pull /= np.maximum(count, 1)[:, None]
        total = (x - x0) + pull  # where each template point should go, from the similarity's place
        w = np.exp(-0.5 * d2 / sigma ** 2)
        moves = ((w * (count > 0)[None]) @ total) / np.maximum((w * (count > 0)[None]).sum(1, keepdims=True), 1e-9)
        x = x0 + (w.T @ moves) / np.maximum(w.sum(0)[:, None], 1e-9)  # as _field evaluates it
        d_sub = np.sort(cKDTree(x).query(s_crop)[0])[: max(3, int(TRIM * len(s_crop)))]
        rms = float(np.sqrt((d_sub ** 2).mean()))
        if rms < best[0]:
            best = (rms, x0[idx].copy(), moves.copy(), sigma)
    if best[1] is not None:
        reg.rms_mm, reg.controls, reg.moves, reg.sigma_mm = best


def side_by_shape(templates: dict[str, np.ndarray], subject: dict[str, np.ndarray], axes: CoarseAxes) -> dict:
    """Left or right from how well the template and its mirror image fit, bone by bone.

    ``templates`` and ``subject``: points per bone (``tibia``, ``femur``).  Returns ``side``
    (None when the fits are too close to tell), the summed trimmed RMS residuals of each
    hypothesis (mm) and their relative gap.
    """
    rms = {"right": 0.0, "left": 0.0}
    for bone in ("tibia", "femur"):
        if bone not in subject or len(subject[bone]) < 100:
            continue
        for side, mirrored in (("right", False), ("left", True)):
            rms[side] += register(bone, templates[bone], subject[bone], axes, mirrored, refine=False).rms_mm
    if not rms["right"] and not rms["left"]:
        return {"side": None, "reason": "no femur or tibia to compare"}
    return shape_verdict(rms["right"], rms["left"])


def shape_verdict(rms_right: float, rms_left: float) -> dict:
    """The side whose template fits clearly better (None when the residuals are too close)."""
    gap = abs(rms_right - rms_left) / max(rms_right, rms_left)
    side = ("right" if rms_right < rms_left else "left") if gap >= SIDE_MIN_RELATIVE_GAP else None
    return {"side": side, "rms_right_mm": round(rms_right, 3), "rms_left_mm": round(rms_left, 3),
            "relative_gap": round(gap, 3)}
