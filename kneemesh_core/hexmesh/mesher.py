"""The cartilage mesher's orchestration: attempts, the fallback chain, and the checked blend.

:func:`mesh_cartilage` runs the steps of :mod:`kneemesh_core.hexmesh` (domain, rays, footprint,
quad mesh, extrusion, quality, fidelity) once with the default options and then, while the
result misses the gate or a fidelity target, once per fallback; each try is an
:class:`Attempt`.  :func:`blend_cartilage` blends and fuses an accepted mesh onto its bone and
keeps the result only where it meets the blend targets of :mod:`.targets`.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pyvista as pv
import SimpleITK as sitk

from kneemesh_core.errors import KneeMeshError
from kneemesh_core.hexmesh.blend import BlendOptions, blend
from kneemesh_core.hexmesh.domain import CylinderDomain, PlaneDomain
from kneemesh_core.hexmesh.extrude import HexMesh, extrude, keep_columns, trim_columns
from kneemesh_core.hexmesh.fidelity import (FIGURES, beyond_rim_checks, fidelity, fidelity_checks, passes_fidelity,
                                            short_of_footprint)
from kneemesh_core.hexmesh.footprint import Footprint, find_footprint
from kneemesh_core.hexmesh.quadmesh import quad_mesh
from kneemesh_core.hexmesh.quality import boundary_crossings, crossing_nodes, hex_quality, passes_gate, summary, to_grid, usable
from kneemesh_core.hexmesh.rays import height_field
from kneemesh_core.hexmesh.targets import (BLEND_FRAC_GOOD, BLEND_MIN_SCALED_JACOBIAN, EDGE_RATIO_AIM, ELEMENT_SIZE_TOL,
                                           FUSED_TOL_MM, MAX_ATTEMPT_VOLUME_ERROR, MAX_EDGE_RATIO, MAX_FLOOR_EXCESS,
                                           MIN_SCALED_JACOBIAN)
from kneemesh_core.io import voxel_to_lps
from kneemesh_core.surfaces.masks import CleanMask, clean_mask, label_box
from kneemesh_core.surfaces.distance import signed_distance
from kneemesh_core.surfaces.tissue import cartilage_surface
from kneemesh_core.tissues import BONE_OF, LABEL


@dataclasses.dataclass(frozen=True)
class HexOptions:
    """Cartilage meshing parameters (the paper's: ~1 mm in-plane, 4 layers)."""

    element_size: float = 1.0
    layers: int = 4
    # The paper closes cartilage with a 5-voxel kernel; on manual OAI segmentations that adds
    # ~7% volume. The footprint already fills sub-millimetre cracks, so closing is a fallback here.
    closing_voxels: int = 0
    min_component_ml: float = 0.005
    ray_step_fraction: float = 0.25  # ray grid spacing as a fraction of the element size
    inset: float = 0.5  # lattice cells sit this many elements inside the contour
    min_thickness: float = 0.2
    edge_fraction: float = 0.2  # the contour runs where thickness is this fraction of the median
    max_slope_deg: float = 65.0  # or where the rim rolls over steeper than this
    fold_slope_deg: float = 80.0  # the footprint is cut where the rays jump this steeply (folds)
    pass_band: float = 0.02  # windowed-sinc smoothing of the cartilage surface (smaller: smoother)
    probe_inset: float = 0.0  # contour nodes read heights this many elements inside (folded rims)
    fallbacks: bool = True  # try the FALLBACKS when the first attempt misses the gate or a fidelity target
    # once an attempt is usable, no fallback starts that would end (at the chain's mean attempt time) after
    # this many seconds: the best ships, for review.  With a knee's start-up, ingest, blends and report (4-5 s
    # beside it) the job stays within 30 s (phantom 7133 left severity 2: a femoral cartilage short of coverage in
    # every attempt ran 9 attempts, 35 s, and its knee 38 s on an idle machine)
    chain_budget_s: float = 25.0


#: The fallback chain: each entry changes some options; the first attempt within the gate and the
#: fidelity targets wins, else the best (gate, then most fidelity targets met, then worst element).
FALLBACKS: tuple[tuple[str, dict], ...] = (
    # (ordered by how often each rescued a cartilage of the 42 real knees: 14, 5, ..., each
    # refinement of a fallback right after it)
    ("rim_heights_inside", {"probe_inset": 0.3}),
    # and the rim trimmed where it rolls over past 60 deg, not 65: femoral cartilages where
    # neither alone is within the gate (phantoms 8 and 48, right, severity 0: coverage 0.962-0.966
    # after trimmed_rim -> 0.973-0.978 with every target met)
    ("rim_inside_trimmed", {"probe_inset": 0.3, "max_slope_deg": 60.0}),
    # the rim out to where the cartilage ends, steep or walled, with its heights read half an
    # element inside: the phantom plates' walls and OA rims (tried only when short of coverage)
    ("rim_to_wall", {"probe_inset": 0.5, "max_slope_deg": 89.0, "fold_slope_deg": 90.0}),
    # further out still, down to a tenth of the median thickness, with the lattice closer to the
    # contour: the thin lateral facet of a patella (OAI 9086407_96m, 9135902_00m PC: 0.967-0.970
    # coverage -> 0.974-0.976)
    ("thin_rim_to_wall", {"probe_inset": 0.5, "max_slope_deg": 89.0, "fold_slope_deg": 90.0,
                          "edge_fraction": 0.1, "inset": 0.3}),
    ("trimmed_rim", {"edge_fraction": 0.35, "max_slope_deg": 55.0}),  # less coverage, squarer rim elements
    ("smoother_surface", {"pass_band": 0.01}),
    ("finer_rays", {"ray_step_fraction": 0.125}),
    ("deeper_inset", {"inset": 0.8}),
    # The smallest elements that still ship the size asked (ELEMENT_SIZE_TOL), before smaller ones that do
    # not.  A plate's rim lies where its bone falls away from the projection plane: its bone-side quads are
    # stretched there (median 1.5 mm at 1 mm elements on OAI 9153013_00m MTC), and the columns' floor for the
    # edge ratio stands its articular nodes 0.5-1 mm above the tapering rim (the articular deviation's p95
    # misses 0.5 mm).  A lattice 10 % finer lowers that floor enough on 7 such OAI plates, each with its rim's
    # heights read inside or out to its wall (5 and 6 of them; every one with one of the two).
    ("smallest_within_size_rim_inside", {"element_size_factor": 1.0 - ELEMENT_SIZE_TOL, "probe_inset": 0.3}),
    ("smallest_within_size_rim_to_wall", {"element_size_factor": 1.0 - ELEMENT_SIZE_TOL, "probe_inset": 0.5,
                                          "max_slope_deg": 89.0, "fold_slope_deg": 90.0}),
    ("smaller_elements", {"element_size_factor": 0.75}),
    ("closed_mask", {"closing_voxels": 3}),
    # Last, for fidelity: smaller elements follow a thin rim and a curved surface closer, and
    # reading the rim's heights inside keeps them valid where smaller elements alone dip below
    # 0.5 (OAI 9171097_96m FC and 9364232_96m LTC pass every fidelity target only this way).
    ("smaller_elements_rim_inside", {"element_size_factor": 0.75, "probe_inset": 0.3}),
    # Last resort for a mesh at all: the rim trimmed where it rolls over past 45 deg.  Thick cartilage
    # on a bone that falls away steeply under it (the notch roof of a thick knee: 3.7 mm of cartilage
    # on bone at 56 deg to the rays, phantom 30585 left FC) makes columns that cross in every attempt
    # above; without that rim the mesh is usable and within the gate, if short of coverage (review).
    ("steep_rim_trimmed", {"edge_fraction": 0.35, "max_slope_deg": 45.0}),
)

#: Fallbacks that shrink the footprint for squarer rim elements: once an attempt is within the
#: gate and short of coverage or volume, they can only fall further short, so they are skipped
#: (a third of the time of a cartilage that runs the whole chain).
NARROWING = frozenset({"rim_inside_trimmed", "trimmed_rim", "deeper_inset", "steep_rim_trimmed"})
#: Fallbacks that widen the footprint: tried only then, when an attempt is within the gate and
#: short of coverage or volume (they rarely help an attempt that is outside the gate).
WIDENING = frozenset({"rim_to_wall", "thin_rim_to_wall"})


@dataclasses.dataclass
class CartilageMesh:
    """A meshed cartilage: the hexahedra, their quality arrays, the report entry, and the
    reconstructed surface it was built from."""

    mesh: HexMesh
    quality: dict
    facts: dict
    surface: pv.PolyData

    def grid(self) -> pv.UnstructuredGrid:
        """VTK hexahedra (C3D8 node order) with cell data ``scaled_jacobian``, ``layer``, ``ring``
        and point data ``bone_side``, ``articular``, ``edge`` (uint8 flags)."""
        g = to_grid(self.mesh.points, self.mesh.hexes)
        g.cell_data["scaled_jacobian"] = self.quality["scaled_jacobian"]
        g.cell_data["layer"] = self.mesh.layer.astype(np.int32)
        g.cell_data["ring"] = self.mesh.ring.astype(np.int32)
        top = self.mesh.node_layer.max()
        g.point_data["bone_side"] = (self.mesh.node_layer == 0).astype(np.uint8)
        g.point_data["articular"] = (self.mesh.node_layer == top).astype(np.uint8)
        g.point_data["edge"] = self.mesh.node_edge.astype(np.uint8)
        return g


def _bone_centre(labels: sitk.Image, tissue: str) -> np.ndarray:
    """The centroid (3,) in LPS mm of the bone under a cartilage (every 97th voxel)."""
    bone = sitk.GetArrayViewFromImage(labels) == LABEL[BONE_OF[tissue]]
    box = label_box(bone)
    if box is None:
        raise KneeMeshError("bone_missing", f"{tissue}: its bone ({BONE_OF[tissue]}) is not labelled; "
                            "the projection needs it to tell the bone side from the joint side.")
    # every 97th voxel in C order, as np.argwhere(...)[::97] lists them, at a third of its cost
    inside = bone[box]
    ijk = np.unravel_index(np.flatnonzero(inside)[::97], inside.shape)
    return voxel_to_lps(labels, (np.stack(ijk, 1) + [s.start for s in box])[:, ::-1]).mean(0)


def _domain(tissue: str, points: np.ndarray, bone_centre: np.ndarray):
    """The projection domain of a cartilage from its surface points (N, 3) and the centroid (3,)
    of its bone.

    Femoral: a cylinder about the condylar (medial-lateral) axis.  Patellar: a
    cylinder about the patella's superior-inferior axis: its articular surface
    curves medio-laterally over the ridge, and radial rays meet the periphery
    far less obliquely than the rays of a plane.  Tibial plates: a plane.
    The bone must lie on the rays' starting side, and the fitted cylinder must
    be plausible (axis within 20 deg of the anatomical hint, radius at least
    18 mm: real knees give 23-51 mm), or the plane is used.
    """
    axis_hint = {"femoral_cartilage": [1.0, 0.0, 0.0], "patellar_cartilage": [0.0, 0.0, 1.0]}.get(tissue)
    if axis_hint is not None:
        cyl = CylinderDomain.fit(points, ml_hint=np.array(axis_hint))
        v = bone_centre - cyl.origin
        bone_r = np.linalg.norm(v - (v @ cyl.axis) * cyl.axis)
        plausible = abs(cyl.axis @ np.asarray(axis_hint)) >= np.cos(np.deg2rad(20.0)) and cyl.radius >= 18.0
        if bone_r < cyl.radius and plausible:
            return cyl
    return PlaneDomain.fit(points, bone_centre)


def _ray_key(opts: HexOptions, h: float) -> tuple:
    """What the cleaned mask, the surface and the rays of an attempt depend on (:func:`_rays`): the
    closing and the smallest component, the smoothing, the rays' spacing."""
    return opts.closing_voxels, opts.min_component_ml, opts.pass_band, h * opts.ray_step_fraction


def _rays(labels: sitk.Image, tissue: str, opts: HexOptions, h: float, cache: dict):
    """The cleaned mask, reconstructed surface, domain and height field of an attempt.

    Each step is computed once per cartilage for the options it depends on and shared by the
    attempts that agree on them (most fallbacks change only later steps): the mask on the closing
    and the smallest component, the surface also on the smoothing, the domain on the surface and
    the bone, the rays also on their spacing.
    """
    ray_key = _ray_key(opts, h)
    mask_key, surface_key = ray_key[:2], ray_key[:3]
    if ray_key not in cache:
        if mask_key not in cache:
            cache[mask_key] = clean_mask(labels, LABEL[tissue], opts.closing_voxels, tissue,
                                         min_component_ml=opts.min_component_ml)
        if surface_key not in cache:
            surface = cartilage_surface(cache[mask_key], opts.pass_band)
            pts = np.asarray(surface.points)
            if "bone_centre" not in cache:
                cache["bone_centre"] = _bone_centre(labels, tissue)
            cache[surface_key] = surface, _domain(tissue, pts, cache["bone_centre"]), pts
        surface, domain, pts = cache[surface_key]
        cache[ray_key] = (cache[mask_key], surface, domain,
                          height_field(surface, domain, domain.to_2d(pts), step=ray_key[-1]))
    return cache[ray_key]


#: Rounds of leaving out a finer piece's columns where its boundary crosses the rest's (:func:`_attempt`).
PIECE_CROSSING_ROUNDS = 3
#: Rings of rim columns short of the gate left out, one after the other (:func:`_trim_short_rim`), ...
RIM_TRIM_ROUNDS = 2
#: ... as long as they are at most this fraction of the outer ring's columns.  Phantom rims that taper over a
#: falling bone lose 0.2-3.7 % of them; a thin cartilage (median 0.52 mm) would lose 5.5-11.5 % in every
#: attempt in four layers, and a thick one on a steep notch roof 10 %: their chains find a thinner rim or
#: fewer layers instead (tests: thick cartilage on steep bone, thin cartilage in fewer layers).
RIM_TRIM_MAX_FRACTION = 0.05


@dataclasses.dataclass
class Attempt:
    """One try at a cartilage: its options' name, the mesh, and everything it was judged on."""

    name: str
    mesh: HexMesh
    quality: dict  # per-element arrays (:func:`.quality.hex_quality`)
    summary: dict  # the report's quality figures (:func:`.quality.summary`) and self-intersections
    fidelity: dict  # :func:`.fidelity.fidelity`
    domain: CylinderDomain | PlaneDomain
    mask: CleanMask
    surface: pv.PolyData
    footprint: Footprint
    finer_pieces: int  # footprint pieces on a finer lattice (:data:`.quadmesh.FINER`)

    @property
    def within_gate(self) -> bool:
        return passes_gate(self.summary)

    @property
    def usable(self) -> bool:
        return usable(self.summary)

    @property
    def faithful(self) -> bool:
        return passes_fidelity(self.fidelity)

    def score(self) -> tuple:
        """How attempts rank: usable for FE first, then faithful to the label, then the most fidelity
        targets met, then within the gate, then the best worst element.  An attempt within the gate
        and faithful ends the chain; when none is, a mesh that stands for the whole cartilage with a
        few elements short of the gate beats a hollow one within it (both ship for review)."""
        return (self.usable, self.faithful, sum(fidelity_checks(self.fidelity).values()), self.within_gate,
                self.summary["min_scaled_jacobian"])


def _quads(hf, domain, opts: HexOptions, h: float, cache: dict):
    """The footprint and quad mesh of an attempt, shared (like :func:`_rays`' steps) by the attempts
    that agree on the options they depend on: a fallback that changes only the extrusion (the rim's
    heights read inside) reuses them."""
    fp_key = _ray_key(opts, h) + ("footprint", h, opts.min_thickness, opts.edge_fraction, opts.max_slope_deg, opts.fold_slope_deg)
    if fp_key not in cache:
        s_scale = (domain.radius / np.maximum(np.nan_to_num(hf.joint, nan=domain.radius), 1.0)
                   if isinstance(domain, CylinderDomain) else 1.0)
        cache[fp_key] = find_footprint(hf, min_thickness=opts.min_thickness, edge_fraction=opts.edge_fraction,
                                       max_slope_deg=opts.max_slope_deg, fold_slope_deg=opts.fold_slope_deg,
                                       s_scale=s_scale, min_hole=2.0 * h * h)
    quad_key = fp_key + (opts.inset,)
    if quad_key not in cache:
        cache[quad_key] = quad_mesh(cache[fp_key], h, inset=opts.inset)
    return cache[fp_key], cache[quad_key]


def _attempt(name: str, labels: sitk.Image, tissue: str, opts: HexOptions, h: float, cache: dict) -> Attempt:
    cm, surface, domain, hf = _rays(labels, tissue, opts, h, cache)
    fp, qm = _quads(hf, domain, opts, h, cache)
    hm = extrude(qm, fp, domain, opts.layers, surface, h, probe_mm=opts.probe_inset * h)
    q = hex_quality(hm.points, hm.hexes)
    # the pieces on finer lattices (tips, tails, fragments) are there for coverage and never cost the
    # cartilage its mesh: a column of theirs with an element short of the gate is left out, and so are
    # its columns where its boundary crosses the rest's (0.5 mm apart at the bone, their columns can
    # lean into each other over a curved bone), a few rounds over; a piece still crossing after that
    # is left out whole.  (Left out whole at once, a long thin horn that crossed its plate where the two
    # meet cost phantom 31022 right severity 3 MTC 14 % of its cartilage.)
    column = np.arange(len(hm.hexes)) % len(qm.quads)
    drop = _columns_short_of_gate(q, len(qm.quads))
    quad_piece = qm.piece[qm.quads[:, 0]]
    drop &= quad_piece > 0
    for round_ in range(PIECE_CROSSING_ROUNDS + 1 if (quad_piece > 0).any() else 0):
        crossing = crossing_nodes(hm.points, hm.hexes[~drop[column]]) % len(qm.points)
        crossing = crossing[qm.piece[crossing] > 0]  # (a piece's nodes belong to its own quads only)
        if not crossing.size:
            break
        if round_ < PIECE_CROSSING_ROUNDS:
            drop |= np.isin(qm.quads, crossing).any(1)
        else:
            drop |= np.isin(quad_piece, qm.piece[crossing])
    if drop.any():
        hm = keep_columns(hm, qm.quads, ~drop)
        q = hex_quality(hm.points, hm.hexes)
    elements = len(hm.hexes)
    hm, q = _trim_short_rim(hm, q)
    s = summary(q, hm.ring)
    s["self_intersections"] = boundary_crossings(hm.points, hm.hexes)
    s["rim_columns_left_out"] = (elements - len(hm.hexes)) // opts.layers
    finer = np.unique(qm.piece[qm.quads[~drop, 0]])
    return Attempt(name, hm, q, s, fidelity(hm, surface, cm.label_ml), domain, cm, surface, fp, int((finer > 0).sum()))


def _columns_short_of_gate(q: dict, n_quads: int) -> np.ndarray:
    """(n_quads,) bool: the columns that hold an element short of the gate (scaled Jacobian or edge ratio), from
    the per-element quality ``q`` of a mesh stacked layer by layer (element k stands on bone-side quad
    k % n_quads)."""
    short = (q["scaled_jacobian"] < MIN_SCALED_JACOBIAN) | (q["max_edge_ratio"] > MAX_EDGE_RATIO)
    out = np.zeros(n_quads, bool)
    np.logical_or.at(out, np.arange(len(short)) % n_quads, short)
    return out


def _trim_short_rim(hm: HexMesh, q: dict) -> tuple[HexMesh, dict]:
    """``hm`` and its quality ``q`` without the columns of its outermost ring that hold an element short of
    the gate, a ring at a time, at most :data:`RIM_TRIM_ROUNDS` rings deep.

    Where the rim tapers over a bone that falls away under it, a handful of its columns shear past a scaled
    Jacobian of 0.5 or the edge ratio (phantom 7009 left FC: 28 of 14300 elements, 20 in the outer ring, 7
    in the next, min 0.42; every attempt missed the gate but the last, which trims the rim where it rolls
    over past 45 deg and covers 96 %; now the rim trimmed past 55 deg, 2 elements short in its outer ring,
    is within it and covers 97.7 %).  Without them the mesh is within the gate and its edge a column or two
    in there; its coverage and volume are judged as ever.  A column short of the gate further in stays (and
    the attempt misses the gate).  Where more than :data:`RIM_TRIM_MAX_FRACTION` of the outer ring's columns
    would go, nothing goes: the rim as a whole is too thin or too steep for the elements, which is for the
    fallbacks to answer (a thinner rim trimmed, fewer layers), not for a rim with a tenth of it missing."""
    untrimmed, total = (hm, q), 0
    allowed = RIM_TRIM_MAX_FRACTION * int((hm.ring[hm.layer == 0] == 0).sum())
    for _ in range(RIM_TRIM_ROUNDS):
        n_quads = int((hm.layer == 0).sum())
        cut = _columns_short_of_gate(q, n_quads) & (hm.ring[:n_quads] == 0)
        if not cut.any():
            break
        total += int(cut.sum())
        if total > allowed:
            return untrimmed
        hm = trim_columns(hm, ~cut)[0]
        q = hex_quality(hm.points, hm.hexes)
    return hm, q


class _Chain:
    """The attempts at one cartilage: each is recorded in ``tried`` and kept as ``best`` when it ranks
    higher (:meth:`Attempt.score`); the steps they share are computed once (``cache``)."""

    def __init__(self, labels: sitk.Image, tissue: str, opts: HexOptions):
        self.labels, self.tissue, self.opts = labels, tissue, opts
        self.tried: list[str] = []
        self.best: Attempt | None = None
        self.last: Attempt | None = None  # the latest attempt that gave a mesh of the cartilage
        self.cache: dict = {}
        self.t0 = time.perf_counter()
        self.stopped_after_s: float | None = None

    def out_of_time(self) -> bool:
        """Whether another attempt, as long as the mean attempt so far, would end past the chain's budget with a
        usable attempt in hand (then it stops: ``stopped_after_s``)."""
        elapsed = time.perf_counter() - self.t0
        expected = elapsed / max(len(self.tried), 1)
        if elapsed + expected > self.opts.chain_budget_s and self.best is not None and self.best.usable:
            self.stopped_after_s = round(elapsed, 1)
        return self.stopped_after_s is not None

    def attempt(self, name: str, o: HexOptions, h: float) -> bool:
        """One attempt; whether it ends the chain (within the gate and faithful)."""
        self.last = None
        try:
            a = _attempt(name, self.labels, self.tissue, o, h, self.cache)
        except KneeMeshError:
            raise
        except Exception as exc:  # a geometric failure: record it and fall back
            self.tried.append(f"{name} ({type(exc).__name__}: {exc})")
            return False
        if abs(a.fidelity["volume_error"]) > MAX_ATTEMPT_VOLUME_ERROR:
            self.tried.append(f"{name} (volume off by {a.fidelity['volume_error']:.0%})")
            return False
        self.last = a
        if self.best is None or a.score() > self.best.score():
            self.best = a
        self.tried.append(name)
        return a.within_gate and a.faithful

    def floor_excess_of_default(self, base: HexOptions, factor: float = 1.0) -> float:
        """:func:`floor_excess` of the default attempt's footprint (cached) in ``base``'s layers, for elements
        ``factor`` times the size asked; 0 where it has none (its rays failed: the fallbacks keep their order)."""
        h = self.opts.element_size
        try:
            _, _, domain, hf = _rays(self.labels, self.tissue, base, h, self.cache)
            fp, _ = _quads(hf, domain, base, h, self.cache)
        except Exception:  # recorded by the attempt itself
            return 0.0
        return floor_excess(fp, base.layers, h * factor)

    def run(self, base: HexOptions, prefix: str = "") -> bool:
        """The default attempt and then the fallbacks on ``base``, until one ends the chain; the fallbacks
        with smaller elements first where the columns' floor would make the cartilage too thick."""
        h = self.opts.element_size
        if self.attempt(prefix + "default", base, h):
            return True
        default_short = self.last is not None and short_of_footprint(self.last.fidelity)
        order = FALLBACKS if self.opts.fallbacks else ()
        if order and self.floor_excess_of_default(base) > MAX_FLOOR_EXCESS:
            # smaller elements first, those whose floor fits the cartilage before those whose floor does not
            def key(fallback: tuple[str, dict]) -> tuple[bool, bool]:
                factor = fallback[1].get("element_size_factor")
                return (factor is None or self.floor_excess_of_default(base, factor) > MAX_FLOOR_EXCESS,
                        factor is None)

            order = sorted(order, key=key)  # stable
        for name, change in order:
            if self.out_of_time():
                return False
            best = self.best
            short = best is not None and short_of_footprint(best.fidelity)
            # narrowing cannot help a mesh within the gate that already covers too little, nor, once the
            # default footprint covered too little, beat a usable and faithful mesh (a footprint narrower
            # still covers less: the real DESS series' femoral cartilage spent 6 of its 30 s on two such
            # attempts after its rim out to the wall was faithful); widening is worth a try for any usable
            # mesh short of the cartilage
            narrowing_futile = short and best.within_gate or default_short and best.usable and best.faithful
            if (name in NARROWING and narrowing_futile) or (name in WIDENING and not (short and best.usable)):
                continue
            change = dict(change)
            factor = change.pop("element_size_factor", 1.0)
            if self.attempt(prefix + name, dataclasses.replace(base, **change), h * factor):
                return True
        return False

    def in_fewer_layers(self) -> str:
        """Last, for a cartilage too thin for its layers: the chain again in as many layers as fit.  Returns
        why, for the report: ``median_thickness`` (thin by its median) or ``no_usable_mesh`` (a median that
        fits, and no usable mesh in the layers asked).

        Every column keeps a floor of layers x edge / EDGE_RATIO_AIM, so 4 layers of 1 mm elements cannot
        follow cartilage under ~0.7 mm (phantom 30567 left severity 3 FC, median 0.51 mm: 3.9 % of elements
        above the edge ratio in every attempt, no usable mesh); real knees' cartilages are thicker: it never
        runs on them.  The whole chain, since thin cartilage varies at its rim as much as thick (phantom 30782
        right severity 3 FC, median 0.52 mm: in 2 layers only the smoother surface kept its rim from folding
        over itself).  A cartilage left with no usable mesh tries at least one layer fewer: a median can hide
        a thin half (phantom 30805 left severity 2 FC: median 0.73 mm, a quarter under 0.36 mm; 1-5 % of
        elements beyond the edge ratio and its rim crossing itself in every attempt in 4 layers)."""
        opts = self.opts
        layers = layers_that_fit(self.best.footprint, opts.element_size)
        because = "median_thickness" if layers < opts.layers else "no_usable_mesh"
        if not self.best.usable:
            layers = min(layers, opts.layers - 1)
        if 1 <= layers < opts.layers:
            self.run(dataclasses.replace(opts, layers=layers), prefix=f"{layers}_layers_")
        return because


def mesh_cartilage(labels: sitk.Image, tissue: str, opts: HexOptions = HexOptions()) -> CartilageMesh:
    """Hex mesh of one cartilage from canonical labels, trying the fallbacks (unless
    ``opts.fallbacks`` is off) until the gate and the fidelity targets are met.

    The best attempt is returned even when it misses the gate (``facts["gate_passed"]`` says so,
    and ``facts["usable"]`` whether it is still usable for finite elements); the caller decides
    what that means.

    Raises
    ------
    KneeMeshError
        ``tissue_missing``/``bone_missing``/``bad_option``, or ``meshing_failed``
        when no attempt produced a mesh at all.
    """
    if opts.layers < 1 or not 0.2 <= opts.element_size <= 5:
        raise KneeMeshError("bad_option", "layers must be >= 1 and element size 0.2-5 mm.")
    t0 = time.perf_counter()
    chain = _Chain(labels, tissue, opts)
    fewer_because = None
    if not chain.run(opts) and opts.fallbacks and chain.best is not None and not chain.out_of_time():
        fewer_because = chain.in_fewer_layers()
    best = chain.best
    if best is None:
        raise KneeMeshError("meshing_failed", f"{tissue}: every attempt failed: {'; '.join(chain.tried)}.")
    layers = int(best.mesh.node_layer.max())
    facts = {
        "n_layers": layers,
        # (the layers that fit are judged for the element size asked; a fallback may ship smaller elements)
        **({"layers_asked": opts.layers, "fewer_layers_because": fewer_because,
            "median_thickness_mm": round(median_thickness(best.footprint), 3)} if layers != opts.layers else {}),
        "element_size_mm": round(float(np.median(_inplane_edges(best.mesh))), 4),
        "element_size_asked_mm": opts.element_size,
        **best.summary,
        **best.fidelity,
        "discarded_ml": round(best.mask.discarded_ml, 4),
        "defect_holes": best.footprint.holes(),
        "finer_pieces": best.finer_pieces,
        "fallbacks": [] if best.name == "default" else [best.name],
        "attempts": chain.tried,
        "chain_stopped_after_s": chain.stopped_after_s,
        "domain": best.domain.describe(),
        "gate_passed": bool(best.within_gate),
        "usable": bool(best.usable),
        "fidelity_passed": bool(best.faithful),
        "mesh_seconds": round(time.perf_counter() - t0, 3),
    }
    return CartilageMesh(best.mesh, best.quality, facts, best.surface)


def blend_cartilage(cm: CartilageMesh, bone: pv.PolyData | None, opts: BlendOptions = BlendOptions()) -> CartilageMesh:
    """Fuse the bone side onto ``bone`` and blend the edge (:mod:`.blend`), then check the result
    against the blend targets of :mod:`.targets`.

    The report gains ``fused_fraction`` and ``blend`` (what was done, the quality after it per ring,
    self-intersections, bone penetration, ``passed``). A blend that misses its targets, or fails,
    leaves the unblended mesh in place and says why; the gate figures stay those before blending.
    Where the pieces on finer lattices stand in the way (a blend that misses its targets with them
    and meets them without), they are left out, and the fidelity figures are measured again.
    """
    out = _blend_checked(cm, bone, opts)
    pieces = cm.mesh.node_piece > 0
    if out.facts["blend"]["applied"] or not pieces.any():
        return out
    quads = cm.mesh.hexes[cm.mesh.layer == 0][:, :4]
    main = keep_columns(cm.mesh, quads, cm.mesh.node_piece[quads[:, 0]] == 0)
    q = hex_quality(main.points, main.hexes)
    f = fidelity(main, cm.surface, cm.facts["label_volume_ml"])
    s = {**summary(q, main.ring), "self_intersections": boundary_crossings(main.points, main.hexes)}
    facts = {**cm.facts, **s, **f, "finer_pieces": 0, "finer_pieces_left_out": int(len(np.unique(cm.mesh.node_piece[pieces]))),
             "gate_passed": passes_gate(s), "usable": usable(s), "fidelity_passed": passes_fidelity(f)}
    without = _blend_checked(CartilageMesh(main, q, facts, cm.surface), bone, opts)
    return without if without.facts["blend"]["applied"] else out


def _blend_checked(cm: CartilageMesh, bone: pv.PolyData | None, opts: BlendOptions) -> CartilageMesh:
    t0 = time.perf_counter()
    try:
        hm, done, kept = blend(cm.mesh, bone, opts)
    except Exception as exc:  # the unblended mesh is still a good mesh
        return dataclasses.replace(cm, facts={**cm.facts, "fused_fraction": 0.0, "blend": {
            "applied": False, "passed": False, "reason": f"{type(exc).__name__}: {exc}"}})
    q = hex_quality(hm.points, hm.hexes)
    s = summary(q, hm.ring)
    sj = q["scaled_jacobian"]
    inner = hm.ring >= 2
    depth = (lambda pts: round(float(max(0.0, -signed_distance(pts, bone).min())), 4)) if bone is not None else None
    penetration = depth(hm.points) if depth else None
    checks = {
        "min_scaled_jacobian": s["min_scaled_jacobian"],
        "frac_sj_at_least_0_5": round(float((sj >= MIN_SCALED_JACOBIAN).mean()), 6),
        "min_scaled_jacobian_beyond_ring_1": round(float(sj[inner].min()), 4) if inner.any() else None,
        "sj_by_ring": s["sj_by_ring"],
        "inverted": s["inverted"],
        "collapsed": s["collapsed"],
        "self_intersections": boundary_crossings(hm.points, hm.hexes),
        "bone_penetration_mm": penetration,
    }
    quality_ok = (checks["min_scaled_jacobian"] >= BLEND_MIN_SCALED_JACOBIAN
                  and checks["frac_sj_at_least_0_5"] >= BLEND_FRAC_GOOD
                  and (checks["min_scaled_jacobian_beyond_ring_1"] or 1.0) >= MIN_SCALED_JACOBIAN
                  and not s["inverted"] and not s["collapsed"] and not checks["self_intersections"])
    before = depth(cm.mesh.points) if depth else None
    report = {**done, **checks, "bone_penetration_unblended_mm": before,
              "passed": bool(quality_ok and (penetration is None or penetration <= FUSED_TOL_MM)),
              "seconds": round(time.perf_counter() - t0, 3)}
    fused = report.pop("fused_fraction")
    if bone is None:
        report["reason"] = "no bone surface: blended without fusion"
    # a blend that keeps the quality is kept even where some node stays inside the bone, as long as
    # it is no deeper than before: the unblended mesh would be the worse of the two
    if not quality_ok or (penetration is not None and penetration > max(FUSED_TOL_MM, before)):
        report["applied"] = False
        report["reason"] = "blended mesh missed the quality targets; the unblended mesh is kept"
        return dataclasses.replace(cm, facts={**cm.facts, "fused_fraction": 0.0, "blend": report})
    # the fidelity figures of the file that ships; the 45 deg edge reshapes the outer rings on purpose, so
    # the targets judge the mesh before the blend and, on the blended file, what lies beyond those rings
    # (the rim columns the blend trimmed off count as uncovered: the mesh before the blend without them)
    unblended = cm.mesh if kept.all() else trim_columns(cm.mesh, kept)[0]
    shipped = fidelity(hm, cm.surface, cm.facts["label_volume_ml"], unblended=unblended, rings=opts.rings)
    report["fidelity"] = {**{k: shipped[k] for k in FIGURES}, "passed": passes_fidelity(shipped)}
    rim = shipped["beyond_rim"]
    report["beyond_rim"] = {**rim, "passed": all(beyond_rim_checks(rim).values())}
    if not report["passed"]:
        report["reason"] = (f"nodes up to {penetration} mm inside the bone remain (unblended: {before} mm): "
                            "the bone mesh and the cartilage labels disagree there")
    return CartilageMesh(hm, q, {**cm.facts, "fused_fraction": fused, "blend": report}, cm.surface)


def median_thickness(fp: Footprint) -> float:
    """Median cartilage thickness (mm) along the rays inside a footprint."""
    return float(np.median(fp.thickness()))


def floor_excess(fp: Footprint, layers: int, h: float) -> float:
    """The volume that the columns' floor (``layers`` x ``h`` / :data:`.targets.EDGE_RATIO_AIM`, mm) adds
    where the cartilage is thinner than it, as a fraction of the cartilage's volume, along the rays inside
    a footprint."""
    t = fp.thickness()
    return float(np.clip(layers * h / EDGE_RATIO_AIM - t, 0.0, None).sum() / max(t.sum(), 1e-9))


def layers_that_fit(fp: Footprint, h: float) -> int:
    """The most element layers (at least 1) whose height over the footprint's median thickness keeps
    an element of in-plane size ``h`` (mm) within :data:`.targets.EDGE_RATIO_AIM`."""
    return max(1, int(EDGE_RATIO_AIM * median_thickness(fp) / h))


def _inplane_edges(hm: HexMesh) -> np.ndarray:
    bottom = hm.hexes[hm.layer == 0][:, :4]
    p = hm.points
    return np.linalg.norm(p[bottom] - p[np.roll(bottom, -1, axis=1)], axis=2).ravel()
