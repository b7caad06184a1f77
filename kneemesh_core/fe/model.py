"""The knee model a deck describes, in the deck's frame.

**Frame.** Millimetres, origin at the femoral frame's origin (the middle of the flexion axis);
X the flexion axis pointing to the patient's right, Y anterior, Z superior (along the femur's
shaft).  The same right-handed frame for a left and a right knee, so a positive rotation about
X is flexion of the femur (its shaft turning posteriorly) on both.  ``frame`` holds the LPS
origin and axes to map results back.

**Bodies.** Femur, tibia and patella are rigid bodies, each with its bone surface and its
cartilage: the femoral cartilage with the femur; the medial and lateral tibial cartilage with
the tibia; the patellar cartilage with the patella.  Rigid cartilage (the paper's choice) keeps
only the articular layer of hexahedra (deeper layers move with the bone and change nothing; the
bone-side surface is then the articular layer's deep face), deformable cartilage every layer.

**Contact.** Linear pressure-overclosure between articular surfaces: medial and lateral tibial
on femoral, patellar on femoral.  The stiffness stands for the two cartilage layers it replaces,
springs in series, each a thin elastic layer bonded to bone (the elastic foundation of Blankevoort
et al. 1991 and Bei & Fregly 2004): K = M / (h_1 + h_2), M = (1 - nu) E / ((1 + nu)(1 - 2 nu)) the
modulus of a layer that cannot bulge sideways, E and nu the cartilage's modulus and Poisson ratio
and h the median thickness of each cartilage (N/mm^3).

**Ligaments.** Each fibre of ``attachments.json`` is a tension-only nonlinear spring with the
Blankevoort (1991) law as OpenSim implements it (strain e = L/L0 - 1; 0 for e <= 0,
k e^2 / (2 e_t) up to e_t = 0.06, k (e - e_t/2) beyond) and a slope of 1e-3 k/L0 in compression
so that a slack fibre leaves no singular tangent.

**Seating.** The image pose may start with the cartilages apart or overlapping (0.3-0.6 mm on
real OA knees); :func:`seat` moves the femur down the tibial axis until its cartilage just touches the tibial
cartilage, then on by the depth at which the contact law carries the joint load (the solver starts
next to equilibrium, not from a touch that carries nothing), and the patella along its anterior
axis until it just touches the femur's cartilage or prefemoral sheet; it reports the overlaps it removed.

**Loads.** The tibia fixed; a compressive joint load on the femur down the tibial axis; a
quadriceps force on the patella from a point up the femoral shaft that belongs to the femur (the
muscle's pull on its origin is the femur's: the quadriceps is internal to the thigh, and pulls the
patella into the trochlea without pushing the femur off the tibia); weak springs on the free degrees
of freedom keep the solve regular before contact closes: the femur's to the ground, the patella's to
the femur, which it follows through flexion (their forces are part of the equilibrium check).

**The patella above the trochlea.** In extension the patella rests partly on the anterior femur above
its trochlear cartilage (the prefemoral fat pad); a rigid sheet there, with the femur, carries it
(:mod:`kneemesh_core.fe.prefemoral`), on by default: without it the patella of OAI 9357383_00m rocked on
its distal tip on the cartilage's edge and ccx never converged past 6.6 deg.  The patellofemoral
contact's master is the cartilage and the sheet together (its force the patella's on either), and the
patella is seated against whichever it meets first.

**Menisci.** Optional rigid surrogates on the plates' rims (:mod:`kneemesh_core.fe.menisci`), on by
default: without them the lateral condyle leaves the convex lateral plate in flexion.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyvista as pv

from kneemesh_core.errors import KneeMeshError
from kneemesh_core.geometry import quad_node_areas, ray_distances
from kneemesh_core.tissues import BONE_OF, BONES, CARTILAGES

#: Cartilage modulus behind the contact stiffness, MPa (instantaneous compressive modulus of
#: human knee cartilage is 5-15 MPa; the paper's rigid-cartilage models use linear laws of this kind).
CARTILAGE_MODULUS_MPA = 10.0
#: Cartilage Poisson ratio of the elastic-foundation contact law (0.45 in Blankevoort 1991 and Bei &
#: Fregly 2004: nearly incompressible under a short load).  A thin layer that cannot bulge is 3.79 times
#: stiffer than E / h; with E / h alone (used until 2026-11-30) the sample's femur sank 0.96 mm into
#: 4.2 mm of cartilage to carry 1000 N and 4.7 mm by 30 deg of flexion, and the full flexion stopped at
#: 45 deg; with this law it seats at 0.51 mm and flexes to 90 deg.
CARTILAGE_POISSON = 0.45
#: The layer's confined modulus, MPa.
CONFINED_MODULUS_MPA = CARTILAGE_MODULUS_MPA * (1 - CARTILAGE_POISSON) / ((1 + CARTILAGE_POISSON) * (1 - 2 * CARTILAGE_POISSON))
#: Blankevoort transition strain.
TRANSITION_STRAIN = 0.06
#: The contact pairs: name -> (slave cartilage, master cartilage).
PAIRS = {"medial": ("medial_tibial_cartilage", "femoral_cartilage"),
         "lateral": ("lateral_tibial_cartilage", "femoral_cartilage"),
         "patellofemoral": ("patellar_cartilage", "femoral_cartilage")}
#: Stabilising springs on the free degrees of freedom: N/mm and N mm/rad.
STABILISER_N_MM, STABILISER_NMM_RAD = 5.0, 2000.0
#: Internal-external rotational restraint of the femur, N mm/rad (60 N m/rad, about 1 N m/deg, the
#: order of a knee's measured torsional stiffness near neutral).  It stands for the capsule and the
#: meniscal horns, which the model leaves out; without it the femur of the sample knee rotated 18-41
#: deg externally by 27-45 deg of flexion and left the lateral plate (the paper's model controlled
#: this degree of freedom with an applied torque).
IE_RESTRAINT_NMM_RAD = 60000.0
#: Anterior-posterior restraint of the femur (deck Y), N/mm, for the secondary AP restraints the
#: model leaves out (meniscal horns, capsule), the order of a knee's anterior drawer stiffness.
AP_RESTRAINT_N_MM = 40.0
#: The patella's tilt and spin restraint relative to the femur (deck Y and Z rotations), N mm/rad:
#: the retinacula.  With only the weak stabiliser the sample's patella spun 34 deg by 21 deg of flexion
#: and left the trochlea.
PATELLA_ROTATION_NMM_RAD = 30000.0
#: A seating deeper than this share of the tibiofemoral cartilage layers' combined thickness means
#: the cartilages meet over too small an area to carry the joint load as cartilage: no cartilage
#: is squeezed by three quarters.  The sample seats at 0.12 (0.51 mm).  Under the softer E / h law used
#: before, the sample seated at 0.22 and OAI 9357383_00m at 0.29, and a severity-3 phantom whose medial
#: plate was meshed over 80 % of its label needed 1.28 (4.1 mm) and did not converge.
MAX_PRELOAD_STRAIN = 0.75
#: Where the quadriceps pulls from: this far up the femoral shaft (deck Z), mm; and how much shorter
#: than its initial length it goes slack (its force then stays nearly constant as it lengthens).
QUADRICEPS_ORIGIN_MM, QUADRICEPS_SLACK_MM = 200.0, 5.0


@dataclass(frozen=True)
class LoadCase:
    """What the deck asks of the knee."""

    joint_load_n: float = 1000.0
    quadriceps_n: float = 300.0
    flexion_deg: float = 90.0
    max_increment_deg: float = 3.0
    cartilage: str = "rigid"  # or "deformable" (Abaqus deck)
    menisci: bool = True  # the meniscus surrogates (fe/menisci.py)
    prefemoral: bool = True  # the patella's rest above the trochlea (fe/prefemoral.py)


@dataclass
class Part:
    """One cartilage's hexahedra in the deck: element ids, their nodes (global ids, C3D8 order)."""

    name: str
    body: str
    elements: np.ndarray  # (E,) ids
    connectivity: np.ndarray  # (E, 8) global node ids
    articular: np.ndarray  # (A,) element ids whose S2 face is articular
    bone_side: np.ndarray  # (B,) element ids whose S1 face lies on the bone side
    thickness_mm: float


@dataclass
class Spring:
    name: str
    bundle: str
    element: int
    nodes: tuple[int, int]
    stiffness_n: float
    slack_length_mm: float
    length_mm: float  # in the deck's initial pose, with beyond_mm
    beyond_mm: float = 0.0  # the fibre's path beyond its two nodes (constant; the ITB's to the pelvis)


@dataclass
class Model:
    nodes: dict[int, np.ndarray] = field(default_factory=dict)  # id -> (3,) deck frame, mm
    bone_nodes: dict[str, np.ndarray] = field(default_factory=dict)  # bone -> ids
    bone_triangles: dict[str, np.ndarray] = field(default_factory=dict)  # bone -> (T, 3) ids
    parts: dict[str, Part] = field(default_factory=dict)
    springs: list[Spring] = field(default_factory=list)
    ref: dict[str, int] = field(default_factory=dict)  # body -> reference node
    body_nodes: dict[str, list[int]] = field(default_factory=dict)  # body -> nodes that must move with it
    pairs: dict[str, tuple[str, str]] = field(default_factory=lambda: dict(PAIRS))  # name -> (slave, master)
    surfaces: dict[str, tuple[str, ...]] = field(default_factory=dict)  # a master of several parts -> its parts
    contact_k: dict[str, float] = field(default_factory=dict)  # pair -> N/mm^3
    quadriceps: Spring | None = None
    patella_anchor: int = 0  # a femur node where the patella's reference node starts (its stabilisers' other end)
    patella_anterior: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tibial_axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))  # deck frame, proximal
    seating: dict = field(default_factory=dict)
    frame: dict = field(default_factory=dict)
    load: LoadCase = LoadCase()
    side: str = "right"
    next_id: int = 1
    next_element: int = 1

    def add_nodes(self, points: np.ndarray) -> np.ndarray:
        ids = np.arange(self.next_id, self.next_id + len(points))
        for i, p in zip(ids, points):
            self.nodes[int(i)] = np.asarray(p, float)
        self.next_id += len(points)
        return ids


def deck_frame(attachments: dict) -> tuple[np.ndarray, np.ndarray]:
    """Origin (3,) and rotation (3, 3) whose columns are the deck's X (patient's right along the
    flexion axis), Y (anterior) and Z (superior along the femoral shaft), all in LPS."""
    femur = attachments["frames"]["femur"]
    lateral = np.asarray(femur["axes"]["lateral"])
    x = lateral if attachments["side"] == "right" else -lateral
    z = np.asarray(femur["axes"]["proximal"])
    z = z - (z @ x) * x
    z /= np.linalg.norm(z)
    return np.asarray(femur["origin_mm"], float), np.stack([x, np.cross(z, x), z], axis=1)


def blankevoort(k: float, slack: float, length: float, points: int = 48) -> list[tuple[float, float]]:
    """(force N, elongation mm) pairs of a fibre of stiffness ``k`` (N per unit strain), slack length
    ``slack`` and initial length ``length`` (mm), elongation measured from the initial length.

    ccx holds a nonlinear spring's force constant beyond its table (a fibre past the last pair pulls
    no harder however far it stretches), so the table runs to a strain of 2 - twice any fibre's
    rupture - with ``points`` pairs in the quadratic toe and the exact straight lines either side."""
    et = TRANSITION_STRAIN
    strain = np.concatenate([[-0.9], np.linspace(0.0, et, points), [2.0]])
    force = np.where(strain <= 0, 1e-3 * k * strain,
                     np.where(strain < et, k * strain ** 2 / (2 * et), k * (strain - et / 2)))
    return [(float(f), float(slack * (1.0 + e) - length)) for f, e in zip(force, strain)]


def quadriceps_law(force_n: float, length_mm: float) -> list[tuple[float, float]]:
    """(force N, elongation mm) of the quadriceps: ``force_n`` at its initial length, +1 N/mm as it
    lengthens, falling to 0 over :data:`QUADRICEPS_SLACK_MM` of shortening."""
    return [(-1e-3 * force_n, -length_mm), (0.0, -QUADRICEPS_SLACK_MM), (force_n, 0.0), (force_n + length_mm, length_mm)]


def build(out_dir: Path, load: LoadCase = LoadCase()) -> Model:
    """The model of a meshed job folder (``meshes/``, ``attachments.json``)."""
    out = Path(out_dir)
    att_file = out / "attachments.json"
    if not att_file.exists():
        raise KneeMeshError("anatomy_missing", "the decks need the attachment sites and frames (attachments.json): "
                            "run the whole job (bones, cartilage and anatomy) first.")
    att = json.loads(att_file.read_text())
    missing = [f"{t}.vtu" for t in CARTILAGES if not (out / "meshes" / f"{t}.vtu").exists()]
    missing += [f"{b}.vtp" for b in BONES if not (out / "meshes" / f"{b}.vtp").exists()]
    if missing:
        raise KneeMeshError("mesh_missing", f"the decks need every bone and cartilage mesh; missing: {', '.join(missing)}.")
    origin, rot = deck_frame(att)

    def to_deck(p) -> np.ndarray:
        return (np.asarray(p, float) - origin) @ rot

    m = Model(load=load, side=att["side"],
              frame={"origin_lps_mm": origin.round(4).tolist(),
                     "axes_lps": {"X_right": rot[:, 0].round(6).tolist(), "Y_anterior": rot[:, 1].round(6).tolist(),
                                  "Z_superior": rot[:, 2].round(6).tolist()}})
    for bone in BONES:
        mesh = pv.read(out / "meshes" / f"{bone}.vtp")
        ids = m.add_nodes(to_deck(mesh.points))
        m.bone_nodes[bone] = ids
        m.bone_triangles[bone] = ids[mesh.regular_faces]
        m.body_nodes[bone] = []
    element = 1
    for tissue in CARTILAGES:
        grid = pv.read(out / "meshes" / f"{tissue}.vtu")
        layer = np.asarray(grid.cell_data["layer"])
        top = int(layer.max())
        keep = layer == top if load.cartilage == "rigid" else np.ones(len(layer), bool)
        conn = np.asarray(grid.cells_dict[pv.CellType.HEXAHEDRON])[keep]
        used = np.unique(conn)
        ids = m.add_nodes(to_deck(grid.points[used]))
        lookup = np.zeros(grid.n_points, int)
        lookup[used] = ids
        elements = np.arange(element, element + len(conn))
        element += len(conn)
        kept_layer = layer[keep]
        pts = np.asarray(grid.points)
        art_nodes = np.asarray(grid.point_data["articular"], bool)
        bone_nodes = np.asarray(grid.point_data["bone_side"], bool)
        thick = np.linalg.norm(pts[art_nodes] - pts[bone_nodes], axis=1)  # the columns: nodes stacked layer by layer
        m.parts[tissue] = Part(tissue, BONE_OF[tissue], elements, lookup[conn], elements[kept_layer == top],
                               elements[kept_layer == (top if load.cartilage == "rigid" else 0)], float(np.median(thick)))
        m.body_nodes[BONE_OF[tissue]].extend(ids.tolist())
    for name, (slave, master) in PAIRS.items():
        m.contact_k[name] = round(CONFINED_MODULUS_MPA / (m.parts[slave].thickness_mm + m.parts[master].thickness_mm), 4)
    # reference nodes: femur and patella at their frames' origins, tibia at the tibial frame's
    for body in BONES:
        m.ref[body] = int(m.add_nodes(to_deck(np.asarray(att["frames"][body]["origin_mm"])[None]))[0])
    m.patella_anchor = int(m.add_nodes(m.nodes[m.ref["patella"]][None])[0])
    m.body_nodes["femur"].append(m.patella_anchor)
    # ligaments: one node per fibre end, moving with the body of its bone
    for fibre in att["fibres"]:
        ends = fibre["ends"]
        if any(e["lps_mm"] is None for e in ends):
            continue
        a, b = (int(m.add_nodes(to_deck(np.asarray(e["lps_mm"])[None]))[0]) for e in ends)
        for e, n in zip(ends, (a, b)):
            m.body_nodes[e["bone"]].append(n)
        beyond = float(fibre.get("path_beyond_mm", 0.0))
        length = float(np.linalg.norm(m.nodes[a] - m.nodes[b])) + beyond
        m.springs.append(Spring(fibre["name"], fibre["bundle"], element, (a, b), fibre["stiffness_n"],
                                fibre["slack_length_mm"], length, beyond))
        element += 1
    # the quadriceps: from the patella's proximal pole to a point up the femoral shaft, on the femur
    patella = att["frames"]["patella"]
    pole = to_deck(np.asarray(patella["origin_mm"]) + 15.0 * np.asarray(patella["axes"]["proximal"]))
    shaft = np.array([0.0, 0.0, QUADRICEPS_ORIGIN_MM])
    a, b = (int(i) for i in m.add_nodes(np.stack([pole, shaft])))
    m.body_nodes["patella"].append(a)
    m.body_nodes["femur"].append(b)
    m.quadriceps = Spring("QUADRICEPS", "QUAD", element, (a, b), 0.0, 0.0, float(np.linalg.norm(pole - shaft)))
    m.next_element = element + 1
    m.patella_anterior = np.asarray(patella["axes"]["anterior"]) @ rot
    m.tibial_axis = np.asarray(att["frames"]["tibia"]["axes"]["proximal"], float) @ rot
    m.seating = seat(m)
    if load.menisci:
        add_menisci(m, load.flexion_deg)
    return m


def _surface(m: Model, tissue: str) -> tuple[np.ndarray, np.ndarray]:
    """A cartilage's articular surface as points (P, 3) and triangles (T, 3), deck frame."""
    quads, ids = _articular_faces(m, tissue)
    local = np.searchsorted(ids, quads)
    return np.stack([m.nodes[int(i)] for i in ids]), np.concatenate([local[:, [0, 1, 2]], local[:, [0, 2, 3]]])


def add_menisci(m: Model, flexion_deg: float) -> None:
    """The meniscus surrogates (:mod:`kneemesh_core.fe.menisci`) of the seated model: a ring of
    hexahedra on each tibial plate, rigid with the tibia, in contact with the femoral cartilage
    under the contact law of its compartment, clear of the femoral cartilage as it turns about the
    flexion axis (deck X through the femur's reference node) from 0 to ``flexion_deg``."""
    from scipy.spatial.transform import Rotation

    from kneemesh_core.fe.menisci import LAYER_MM, POSE_STEP_DEG, wedge

    points, triangles = _surface(m, "femoral_cartilage")
    centre = m.nodes[m.ref["femur"]]
    femoral = [((points - centre) @ Rotation.from_rotvec([np.radians(a), 0.0, 0.0]).as_matrix().T + centre, triangles)
               for a in np.arange(0.0, flexion_deg + 1e-9, POSE_STEP_DEG)]
    plates = {side: _surface(m, f"{side}_tibial_cartilage") for side in ("medial", "lateral")}
    for side, other in (("medial", "lateral"), ("lateral", "medial")):
        nodes, hexes = wedge(plates[side], femoral, m.tibial_axis, plates[other][0].mean(0))
        if not len(hexes):
            continue
        ids = m.add_nodes(nodes)
        elements = np.arange(m.next_element, m.next_element + len(hexes))
        m.next_element += len(hexes)
        name = f"{side}_meniscus"
        m.parts[name] = Part(name, "tibia", elements, ids[hexes], elements, elements, LAYER_MM)
        m.body_nodes["tibia"].extend(ids.tolist())
        m.pairs[name] = (name, "femoral_cartilage")
        m.contact_k[name] = m.contact_k[side]


def add_prefemoral(m: Model) -> None:
    """The prefemoral sheet (:mod:`kneemesh_core.fe.prefemoral`) of the seated femur: rigid with the
    femur, part of the patellofemoral contact's master surface (the patellar track: the femoral
    cartilage and the sheet), under the patellofemoral contact law.  (A pair of its own, the sheet its
    slave, cost the sample's smoke run 14 s of its 70 for 216 faces that carried 1 N.)"""
    from kneemesh_core.fe.prefemoral import LAYER_MM, sheet

    bone = m.bone_nodes["femur"]
    bone_points = np.stack([m.nodes[int(i)] for i in bone])
    nodes, hexes = sheet(_surface(m, "patellar_cartilage"), -m.patella_anterior,
                         (bone_points, np.searchsorted(bone, m.bone_triangles["femur"])), _surface(m, "femoral_cartilage"),
                         m.parts["femoral_cartilage"].thickness_mm)
    if not len(hexes):
        return
    ids = m.add_nodes(nodes)
    elements = np.arange(m.next_element, m.next_element + len(hexes))
    m.next_element += len(hexes)
    m.parts["prefemoral"] = Part("prefemoral", "femur", elements, ids[hexes], elements, elements, LAYER_MM)
    m.body_nodes["femur"].extend(ids.tolist())
    m.surfaces["patellar_track"] = ("femoral_cartilage", "prefemoral")
    m.pairs["patellofemoral"] = ("patellar_cartilage", "patellar_track")


def _articular_faces(m: Model, tissue: str) -> tuple[np.ndarray, np.ndarray]:
    """The articular (S2) faces of a cartilage (or meniscus surrogate) as quads (Q, 4) of global node ids, and those ids."""
    part = m.parts[tissue]
    quads = part.connectivity[np.searchsorted(part.elements, part.articular)][:, [4, 7, 6, 5]]
    return quads, np.unique(quads)


def gaps(m: Model, slave: str, master: str, direction: np.ndarray) -> np.ndarray:
    """Distance (mm) from each articular node of ``slave`` along unit ``direction`` to the articular
    surface of ``master``: negative where the two overlap, NaN where the ray misses it."""
    back = 20.0  # rays start this far behind each node, so an overlap is found too
    return ray_distances(_surface(m, slave)[0] - back * direction, direction, *_surface(m, master)) - back


def _move(m: Model, body: str, shift: np.ndarray) -> None:
    for n in {*m.body_nodes[body], *m.bone_nodes[body].tolist(), m.ref[body]}:
        m.nodes[int(n)] = m.nodes[int(n)] + shift


def _node_areas(m: Model, tissue: str) -> np.ndarray:
    """Tributary area (mm^2) of each articular node of ``tissue``, in the order of
    :func:`_articular_faces`'s ids."""
    quads, ids = _articular_faces(m, tissue)
    return quad_node_areas(np.stack([m.nodes[int(i)] for i in ids]), np.searchsorted(ids, quads))


def preload_depth(gaps_mm: list[np.ndarray], areas_mm2: list[np.ndarray], k_n_mm3: list[float], load_n: float) -> float:
    """How far (mm) a rigid body must move along the gaps' direction, from first touch, for linear
    pressure-overclosure contact (p = K d on each node's area) to carry ``load_n``.  Gaps (mm, NaN
    where a ray missed) are measured from the first touch; bisection on a monotone force."""
    def force(d: float) -> float:
        return sum(k * float(np.sum(a * np.clip(d - np.nan_to_num(g, nan=np.inf), 0.0, None)))
                   for g, a, k in zip(gaps_mm, areas_mm2, k_n_mm3))

    lo, hi = 0.0, 5.0
    if force(hi) < load_n:
        return hi
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if force(mid) < load_n else (lo, mid)
    return 0.5 * (lo + hi)


def seat(m: Model) -> dict:
    """Seat the bones before any load: the femur moves down the tibial axis until its cartilage just touches the
    tibial cartilage (down across a gap, up out of an overlap) and then on by the depth at which the
    contact carries the joint load (:func:`preload_depth`), so that the solver starts next to
    equilibrium; then the patella along its anterior axis until it just touches the femoral
    cartilage or the prefemoral sheet (:func:`add_prefemoral`, built once the femur is seated).  The
    overlaps of the image pose are reported."""
    z = m.tibial_axis
    before = {pair: gaps(m, PAIRS[pair][0], PAIRS[pair][1], z) for pair in ("medial", "lateral")}
    g = np.concatenate(list(before.values()))
    touch = -float(np.nanmin(g)) if np.isfinite(g).any() else 0.0
    depth = preload_depth([v + touch for v in before.values()],
                          [_node_areas(m, PAIRS[p][0]) for p in before], [m.contact_k[p] for p in before], m.load.joint_load_n)
    femur_shift = touch - depth
    _move(m, "femur", femur_shift * z)
    toward = -m.patella_anterior  # the patella's articular side faces posterior, towards the trochlea
    if m.load.prefemoral:
        add_prefemoral(m)
    pf = np.fmin.reduce([gaps(m, "patellar_cartilage", master, toward)
                         for master in ("femoral_cartilage", "prefemoral") if master in m.parts])
    patella_shift = float(np.nanmin(pf)) if np.isfinite(pf).any() else 0.0
    _move(m, "patella", patella_shift * toward)
    pf_before = pf  # measured after the femur was seated, along the patella's axis
    for s in m.springs:
        s.length_mm = float(np.linalg.norm(m.nodes[s.nodes[0]] - m.nodes[s.nodes[1]])) + s.beyond_mm
    q = m.quadriceps
    q.length_mm = float(np.linalg.norm(m.nodes[q.nodes[0]] - m.nodes[q.nodes[1]]))

    def overlap(v: np.ndarray) -> float:
        return round(float(max(0.0, -np.nanmin(v))) if np.isfinite(v).any() else 0.0, 3)

    return {"initial_overlap_mm": {"medial": overlap(before["medial"]), "lateral": overlap(before["lateral"]),
                                   "patellofemoral": overlap(pf_before)},
            "initial_overlap_nodes": {k: int((v < 0).sum()) for k, v in (*before.items(), ("patellofemoral", pf_before))},
            "femur_shift_mm": round(femur_shift, 3), "preload_depth_mm": round(depth, 3),
            "preload_strain": round(depth / float(np.mean([m.parts[s].thickness_mm + m.parts[f].thickness_mm
                                                           for s, f in (PAIRS["medial"], PAIRS["lateral"])])), 3),
            "patella_shift_mm": round(patella_shift, 3)}
