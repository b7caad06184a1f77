"""Synthetic knee anatomy: signed distance fields of bones and cartilage shells.

All shapes live in a local knee frame, in mm: ``u`` lateral, ``v`` anterior,
``w`` superior, origin at the joint line.  The femur and patella are posed by
flexion about the condylar axis and a varus/valgus tilt about a condylar
contact; the tibia and fibula stay put.  :func:`build_knee` returns the tissue
labels and the fields the contrast model needs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from kneemesh_core.phantom import sdf
from kneemesh_core.tissues import LABEL


@dataclass
class KneeParams:
    """Population and pathology parameters of one phantom knee (mm, degrees)."""

    scale: float
    condyle_radius: float  # medial; lateral is smaller by ``lateral_delta``
    lateral_delta: float
    fc_mm: float  # nominal thicknesses
    tc_mm: float
    pc_mm: float
    gap_mm: float
    flexion_deg: float
    varus_deg: float  # + opens the lateral compartment
    rotation_deg: float  # external rotation of the knee in the scanner
    severity: int
    wave: np.ndarray  # (4, 5) random smooth thickness field coefficients
    # OA and habitus features drawn by :meth:`sample_features` (their own random stream, so that
    # a phantom's other draws stay what they were):
    thickness_factor: float = 1.0  # very thin (< 1) or very thick (> 1) cartilage
    trochlea: str = "normal"  # "thin" (40 % of its thickness) or "absent" (no trochlear cartilage)
    #: full-thickness femoral lesions: (condyle -1 medial / +1 lateral, offset along the condyle mm,
    #: angle from distal towards posterior deg, radius mm); two close ones leave a narrow strip
    femoral_lesions: tuple = ()

    def cartilage_mm(self) -> tuple[float, float, float]:
        """Femoral, tibial and patellar cartilage thicknesses (mm) that set the joint space: the nominal
        ones times ``thickness_factor`` (a knee of very thick cartilage has a wide joint space)."""
        return self.fc_mm * self.thickness_factor, self.tc_mm * self.thickness_factor, self.pc_mm * self.thickness_factor

    @classmethod
    def sample(cls, rng: np.random.Generator, severity: int) -> "KneeParams":
        s = rng.uniform(0.88, 1.12)
        return cls(
            scale=s,
            condyle_radius=rng.uniform(19.5, 22.5) * s,
            lateral_delta=rng.uniform(0.3, 0.8),
            fc_mm=rng.uniform(2.0, 2.6),
            tc_mm=rng.uniform(2.0, 2.6),
            pc_mm=rng.uniform(2.3, 2.9),
            gap_mm=rng.uniform(0.0, 0.3),
            flexion_deg=rng.uniform(0.0, 30.0),
            varus_deg=rng.uniform(-3.0, 3.0),
            rotation_deg=rng.uniform(-10.0, 10.0),
            severity=severity,
            wave=rng.uniform(-1, 1, size=(4, 5)),
        )


def sample_features(p: KneeParams, rng: np.random.Generator) -> KneeParams:
    """The phantom's OA and habitus features, more and larger with severity: cartilage very thin or
    very thick for the whole knee (any severity); a thin or absent trochlear cartilage, a large
    denuded area on a femoral condyle, and a narrow strip of cartilage between two lesions (severity
    2-3).  Seen on real OA knees where the mesher was not tuned."""
    import dataclasses

    u = rng.random()
    factor = rng.uniform(0.55, 0.75) if u < 0.15 else rng.uniform(1.2, 1.4) if u < 0.3 else 1.0
    trochlea, lesions = "normal", []
    if p.severity >= 2:
        t = rng.random()
        trochlea = "absent" if t < 0.1 * p.severity else "thin" if t < 0.25 * p.severity else "normal"
        if p.severity == 3 or rng.random() < 0.5:  # a denuded area in the weight-bearing zone
            lesions.append((float(rng.choice([-1.0, 1.0])), rng.uniform(-5, 5), rng.uniform(-10, 35), rng.uniform(7, 11)))
        if rng.random() < 0.5:  # two lesions with a narrow strip of cartilage between them
            side, along, angle = float(rng.choice([-1.0, 1.0])), rng.uniform(-4, 4), rng.uniform(-15, 20)
            r1, r2, strip = rng.uniform(4, 6), rng.uniform(4, 6), rng.uniform(1.5, 3.0)
            lesions += [(side, along, angle, r1), (side, along, angle + np.degrees((r1 + r2 + strip) / p.condyle_radius), r2)]
    return dataclasses.replace(p, thickness_factor=factor, trochlea=trochlea, femoral_lesions=tuple(lesions))


def _rotate(a, b, angle_deg, ca, cb):
    """Rotate coordinates (a, b) about (ca, cb) by -angle (maps world to a posed frame)."""
    t = np.deg2rad(angle_deg)
    c, s = np.float32(np.cos(t)), np.float32(np.sin(t))
    da, db = a - ca, b - cb
    return ca + c * da + s * db, cb - s * da + c * db


def _thickness(p: KneeParams, u, v, w, nominal: float, k: int) -> np.ndarray:
    """Smoothly varying cartilage thickness (mm), 1.5-3.5 before OA thinning."""
    c = p.wave[k]
    f = 1.0 + 0.22 * np.sin(c[0] * 0.09 * u + c[1] * 2) * np.cos(c[2] * 0.08 * v + c[3] * 0.07 * w + c[4])
    t = np.clip(nominal * f, 1.5, 3.5)
    thin = 1.0 - 0.12 * p.severity
    return (t * thin * p.thickness_factor).astype(np.float32)


@dataclass
class KneeFields:
    """Labels and the fields the contrast model needs, all on the full voxel grid."""

    labels: np.ndarray  # uint8 canonical labels, (K, J, I)
    bone_sdf: dict  # bone name -> float32 SDF (mm)
    fibula: np.ndarray  # bool
    envelope_sdf: np.ndarray  # float32 SDF of the leg's skin (mm)
    meniscus: np.ndarray  # bool


@dataclass(frozen=True)
class _Layout:
    """Where a phantom knee's parts stand, mm, in the knee frame (u medial-lateral, v anterior, w
    superior): the condyles' centre line (``u_c``, ``v_c``, ``w_c``) and radius, the tibial plateau's
    top ``w_t``, the trochlea's ``v_tr``, the patella's centre (``v_p``, ``w_p``), the cartilage thicknesses."""

    s: float
    R_m: float
    fc_mm: float
    tc_mm: float
    pc_mm: float
    w_t: float
    v_c: float
    w_c: float
    u_c: float
    v_tr: float
    v_p: float
    w_p: float

    @classmethod
    def of(cls, p: KneeParams) -> "_Layout":
        # the bones stand as far apart as their cartilages are thick (with the nominal spacing, a 1.4 x
        # knee's femoral cartilage ran through the patellar cartilage onto the patella, and its cartilages
        # met in walls no knee has)
        s, R_m = p.scale, p.condyle_radius
        fc_mm, tc_mm, pc_mm = p.cartilage_mm()
        v_c, w_c = -6.0 * s, fc_mm + p.gap_mm + R_m
        v_tr = v_c + 0.55 * R_m
        return cls(s, R_m, fc_mm, tc_mm, pc_mm, w_t=-tc_mm, v_c=v_c, w_c=w_c, u_c=20.0 * s, v_tr=v_tr,
                   v_p=v_tr + 13.5 * s + fc_mm + pc_mm + 9.5 * s - 2.0, w_p=w_c + 0.45 * R_m + 6 * s)


def _femur(uf, vf, wf, p: KneeParams, k: _Layout) -> tuple[np.ndarray, np.ndarray]:
    """The femur's field in its own frame, and its intercondylar notch's."""
    s, R_m, u_c, v_c, w_c = k.s, k.R_m, k.u_c, k.v_c, k.w_c
    med = sdf.rounded_cylinder_u(uf, vf, wf, (-u_c, v_c, w_c), R_m, 12.5 * s, 5.0)
    lat = sdf.rounded_cylinder_u(uf, vf, wf, (u_c, v_c, w_c + p.lateral_delta), R_m - p.lateral_delta, 12.5 * s, 5.0)
    troch = sdf.ellipsoid(uf, vf, wf, (0.0, k.v_tr, w_c + 0.45 * R_m), (31 * s, 13.5 * s, 21 * s))
    meta = sdf.ellipsoid(uf, vf, wf, (0.0, v_c + 5, w_c + R_m + 8), (34 * s, 19 * s, 26 * s))
    shaft = sdf.capsule_w(uf, vf, wf, (0.0, v_c + 5), 13.5 * s, w_c + 25, 400.0)
    femur = sdf.smooth_union(sdf.smooth_union(med, lat, 4.0), troch, 6.0)
    femur = sdf.smooth_union(sdf.smooth_union(femur, meta, 8.0), shaft, 10.0)
    notch = sdf.ellipsoid(uf, vf, wf, (0.0, v_c - 12 * s, w_c - 9 * s), (6.5 * s, 22 * s, 14 * s))
    groove = sdf.capsule_w(uf, vf, wf, (0.0, k.v_tr + 13.5 * s + 3.0), 6.0 * s, -100.0, 400.0)
    return sdf.subtract(sdf.subtract(femur, notch), groove), notch


def _tibia_and_fibula(u, v, w, k: _Layout) -> tuple[np.ndarray, np.ndarray]:
    """The tibia's and the fibula's fields in the knee frame."""
    s, w_t = k.s, k.w_t
    plateau = sdf.elliptic_slab_w(u, v, w, (0.0, 0.0), 38 * s, 26 * s, w_t - 16, w_t, 2.5)
    eminence = sdf.ellipsoid(u, v, w, (0.0, -2 * s, w_t), (6 * s, 14 * s, 7 * s))
    tmeta = sdf.ellipsoid(u, v, w, (0.0, 0.0, w_t - 22 * s), (33 * s, 24 * s, 20 * s))
    tshaft = sdf.capsule_w(u, v, w, (0.0, -2 * s), 13.5 * s, -400.0, w_t - 25 * s)
    tuber = sdf.ellipsoid(u, v, w, (3 * s, 17 * s, w_t - 28 * s), (9 * s, 7 * s, 12 * s))
    tibia = sdf.smooth_union(plateau, eminence, 3.0)
    tibia = sdf.smooth_union(sdf.smooth_union(tibia, tmeta, 8.0), tshaft, 10.0)
    tibia = sdf.smooth_union(tibia, tuber, 5.0)
    fib = np.minimum(
        sdf.capsule_w(u, v, w, (31 * s, -14 * s), 6.5 * s, -400.0, w_t - 18 * s),
        sdf.ellipsoid(u, v, w, (31 * s, -14 * s, w_t - 18 * s), (9 * s, 9 * s, 8 * s)),
    )
    return tibia, fib


def _osteophytes(femur, tibia, u, v, w, uf, vf, wf, p: KneeParams, k: _Layout, rng: np.random.Generator):
    """Severity 2 and 3: osteophytes at the articular margins, on the femur or the tibia."""
    s = k.s
    for _ in range(2 * p.severity if p.severity >= 2 else 0):
        side = rng.choice([-1.0, 1.0])
        r = (rng.uniform(1.5, 3.5),) * 3
        if rng.random() < 0.5:
            c = (side * (k.u_c + 12.5 * s), k.v_c + rng.uniform(-10, 5), k.w_c - k.R_m * rng.uniform(0.2, 0.6))
            femur = np.minimum(femur, sdf.ellipsoid(uf, vf, wf, c, r))
        else:
            ang = rng.uniform(0, 2 * np.pi)
            c = (37 * s * np.cos(ang), 25 * s * np.sin(ang), k.w_t - 1.0)
            tibia = np.minimum(tibia, sdf.ellipsoid(u, v, w, c, r))
    return femur, tibia


def _femoral_region(uf, vf, wf, region, p: KneeParams, k: _Layout) -> np.ndarray:
    """Where the femur carries cartilage (negative inside): the condyles but their inner faces, the
    trochlea (unless absent), less the full-thickness lesions."""
    s, R_m, u_c, v_c, w_c = k.s, k.R_m, k.u_c, k.v_c, k.w_c
    condyles = region(wf - (w_c + 0.3 * R_m), np.abs(uf) - (u_c + 11.0 * s),
                      # the condyles' inner faces (|u| = 7.5 s, rounded over 5 mm) face the notch: bare
                      -np.maximum(np.abs(uf) - (7.5 * s + 2.0), vf - (v_c + 6)))
    trochlea = region((v_c + 0.25 * R_m) - vf, wf - (w_c + 0.75 * R_m), np.abs(uf) - 27 * s)
    fem_region = np.maximum(np.minimum(condyles, trochlea if p.trochlea != "absent" else np.float32(np.inf)),
                            -np.maximum(vf - (v_c - 0.2 * R_m), (w_c + 0.2 * R_m) - wf))
    for side, along, angle, r in p.femoral_lesions:  # full thickness: no cartilage within r of a point on the condyle
        lateral = side > 0
        radius = R_m - (p.lateral_delta if lateral else 0.0)
        a = np.radians(angle)
        centre = (side * u_c + along * s, v_c - radius * np.sin(a), w_c + (p.lateral_delta if lateral else 0.0) - radius * np.cos(a))
        ball = np.sqrt((uf - centre[0]) ** 2 + (vf - centre[1]) ** 2 + (wf - centre[2]) ** 2) - r
        fem_region = np.maximum(fem_region, -ball)
    return fem_region


def knee_fields(u, v, w, p: KneeParams, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Continuous fields (mm, negative inside) of every tissue, on broadcastable coordinates.

    Cartilage fields are negative inside the cartilage shell on its articular
    region; region limits enter as a +/-1 mm ramp so that they interpolate.
    """
    k = _Layout.of(p)
    s, R_m, u_c, v_c, w_c, w_t = k.s, k.R_m, k.u_c, k.v_c, k.w_c, k.w_t
    # pose: varus/valgus about a condylar contact, then flexion about the condylar axis
    pivot_u = -u_c if p.varus_deg >= 0 else u_c
    uf, wf = _rotate(u, w, -p.varus_deg, pivot_u, k.fc_mm + p.gap_mm)
    vf, wf = _rotate(v, wf, p.flexion_deg, v_c, w_c)
    femur, notch = _femur(uf, vf, wf, p, k)
    tibia, fib = _tibia_and_fibula(u, v, w, k)
    # patella rides in the trochlear groove, moving with the femur
    patella = sdf.ellipsoid(uf, vf, wf, (1.5 * s, k.v_p, k.w_p), (21 * s, 9.5 * s, 22 * s))
    femur, tibia = _osteophytes(femur, tibia, u, v, w, uf, vf, wf, p, k, rng)

    def region(*conds):  # signed ramp: negative inside all conditions (each "expr < 0")
        return np.maximum.reduce([np.broadcast_to(c, femur.shape) for c in conds]).astype(np.float32)

    # cartilage shells on the articular regions
    # femoral cartilage thins to nothing over 3 mm towards the intercondylar notch (whose walls carry
    # the cruciate ligaments, not cartilage)
    t_f = _thickness(p, uf, vf, wf, p.fc_mm, 0) * np.clip(notch / 3.0, 0.0, 1.0).astype(np.float32)
    troch_zone = np.float32(1.0) / (1 + np.exp(-(vf - (v_c + 0.35 * R_m)) / 1.5))  # 0 on the condyles, 1 on the trochlea
    if p.trochlea == "thin":
        t_f = t_f * (1.0 - 0.6 * troch_zone).astype(np.float32)
    t_t = _thickness(p, u, v, w, p.tc_mm, 1) + np.where(u > 0, np.float32(p.lateral_delta), np.float32(0))
    t_p = _thickness(p, uf, vf, wf, p.pc_mm, 2)
    fem_region = _femoral_region(uf, vf, wf, region, p, k)
    tib_region = region((w_t - 1.5) - w, 6.5 * s - np.abs(u),
                        # the medial plateau is longer antero-posteriorly than the lateral one
                        10 * (np.sqrt((u / (35 * s)) ** 2 + (v / np.where(u < 0, 24 * s, 20 * s)) ** 2) - 1.0))
    pat_region = region(vf - (k.v_p - 2.0),
                        10 * (np.sqrt(((uf - 1.5 * s) / (18 * s)) ** 2 + ((wf - k.w_p) / (19 * s)) ** 2) - 1.0))
    rho = np.sqrt(((np.abs(u) - u_c) / (15 * s)) ** 2 + (v / (21 * s)) ** 2)
    meniscus = region(10 * (0.72 - rho), 10 * (rho - 1.15), w_t - w, (w - w_t) - 14 * (rho - 0.68), 6 * s - np.abs(u))
    return {
        "femur": femur,
        "tibia": tibia,
        "patella": patella,
        "fibula": fib,
        "fc": np.maximum(femur - t_f, fem_region),
        "tc": np.maximum(tibia - t_t, tib_region),
        "pc": np.maximum(patella - t_p, pat_region),
        "meniscus": meniscus,
    }


def build_knee(grid, p: KneeParams, rng: np.random.Generator) -> KneeFields:
    """Tissue labels of one knee on the full grid.

    Parameters
    ----------
    grid : object with ``uvw(k, j, i)`` mapping 1-D voxel index positions per numpy
        axis to broadcastable knee-frame coordinates (mm), and ``shape``.

    The smooth fields are evaluated on a grid twice as coarse in every axis
    and upsampled linearly; thresholds are taken at full resolution.
    """
    K, J, I = grid.shape
    coarse = [np.arange(n // 2, dtype=np.float32) * 2 + 0.5 for n in (K, J, I)]
    f = {k: _upsample2(v) for k, v in knee_fields(*grid.uvw(*coarse), p, rng).items()}
    u = grid.uvw(*(np.arange(n, dtype=np.float32) for n in (K, J, I)))[0]

    labels = np.zeros((K, J, I), dtype=np.uint8)
    tibia, femur, patella = f["tibia"] < 0, f["femur"] < 0, f["patella"] < 0
    labels[tibia] = LABEL["tibia"]
    labels[femur & ~tibia] = LABEL["femur"]
    labels[patella & ~femur & ~tibia] = LABEL["patella"]
    fibula = (f["fibula"] < 0) & (f["tibia"] > 0.8)
    free = (labels == 0) & ~fibula
    tc = free & (f["tc"] < 0)
    # where two cartilages' shells overlap, the nearer bone's cartilage takes the voxel: they meet
    # half-way, and neither reaches the other's bone
    fc = free & (f["fc"] < 0) & ~(tc & (f["tibia"] < f["femur"]))
    pc = free & (f["pc"] < 0) & ~(fc & (f["femur"] < f["patella"]))
    tc &= ~fc
    fc &= ~pc
    labels[fc] = LABEL["femoral_cartilage"]
    labels[tc & (u < 0)] = LABEL["medial_tibial_cartilage"]
    labels[tc & (u >= 0)] = LABEL["lateral_tibial_cartilage"]
    labels[pc] = LABEL["patellar_cartilage"]
    bone_sdf = {b: f[b] for b in ("femur", "tibia", "patella")}
    _oa_defects(labels, bone_sdf, grid, p, rng)
    meniscus = (f["meniscus"] < 0) & (labels == 0) & ~fibula & (f["femur"] > 0)
    ii = np.arange(I, dtype=np.float32)
    jj = np.zeros(1, dtype=np.float32)
    eu, ev, _ = grid.uvw(np.arange(K, dtype=np.float32), jj, ii)
    envelope = sdf.elliptic_slab_w(eu, ev, np.float32(0), (0.0, -4 * p.scale), 56 * p.scale, 50 * p.scale, -1.0, 1.0, 0.0)
    return KneeFields(labels, bone_sdf, fibula, np.broadcast_to(envelope, labels.shape), meniscus)


def _upsample2(a: np.ndarray) -> np.ndarray:
    """Linear upsampling by 2 in every axis; coarse sample c sits at fine position 2c + 0.5.

    Hand-written: scipy.ndimage.zoom and SimpleITK's Expand take 4x longer here.
    """
    for axis in range(a.ndim):
        a = np.moveaxis(a, axis, -1)
        prev = np.concatenate([a[..., :1], a[..., :-1]], -1)
        nxt = np.concatenate([a[..., 1:], a[..., -1:]], -1)
        out = np.empty(a.shape[:-1] + (2 * a.shape[-1],), np.float32)
        out[..., 0::2] = 0.75 * a + 0.25 * prev
        out[..., 1::2] = 0.75 * a + 0.25 * nxt
        a = np.moveaxis(out, -1, axis)
    return np.ascontiguousarray(a)


_CART_BONE = {
    LABEL["femoral_cartilage"]: "femur",
    LABEL["medial_tibial_cartilage"]: "tibia",
    LABEL["lateral_tibial_cartilage"]: "tibia",
    LABEL["patellar_cartilage"]: "patella",
}


def _oa_defects(labels, bone_sdf, grid, p: KneeParams, rng: np.random.Generator) -> None:
    """Focal partial- and full-thickness defects, and a denuded area at severity 3, in place."""
    if p.severity == 0:
        return
    n_focal = 2 * p.severity
    for i in range(n_focal + (1 if p.severity == 3 else 0)):
        denuded = i == n_focal
        lab = LABEL["medial_tibial_cartilage"] if denuded else int(rng.choice(list(_CART_BONE)))
        idx = np.flatnonzero(labels == lab)
        if idx.size < 100:
            continue
        centre = np.unravel_index(idx[rng.integers(idx.size)], labels.shape)
        r = (rng.uniform(8, 12) if denuded else rng.uniform(2, 5)) + 3.0
        full = denuded or rng.random() < 0.5
        # a box around the centre wide enough for the ball at the finest spacing
        half = int(np.ceil(r / min(grid.spacing_zyx)))
        box = tuple(slice(max(c - half, 0), min(c + half + 1, n)) for c, n in zip(centre, labels.shape))
        cu, cv, cw = grid.uvw(*(np.array([c], dtype=np.float32) for c in centre))
        bu, bv, bw = grid.uvw(*(np.arange(s.start, s.stop, dtype=np.float32) for s in box))
        hit = (((bu - cu) ** 2 + (bv - cv) ** 2 + (bw - cw) ** 2) < r * r) & (labels[box] == lab)
        if not full:  # partial thickness: keep the deep half
            hit &= bone_sdf[_CART_BONE[lab]][box] > 0.5 * p.cartilage_mm()[1]
        labels[box][hit] = 0
