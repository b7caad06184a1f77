"""The knee model a deck describes, assembled from the knee's meshes and anatomy, in the deck's frame.

**Frame.** Millimetres, origin at the femoral frame's origin (the middle of the flexion axis); X the
flexion axis pointing to the patient's right, Y anterior, Z superior (along the femur's shaft): the
same right-handed frame for a left and a right knee, so a positive rotation about X is flexion of the
femur on both.  ``frame`` holds the LPS origin and axes to map results back.

**Bodies.** Femur, tibia and patella are rigid bodies, each with its bone shell and its cartilage
(rigid cartilage, the paper's choice, keeps only the articular layer of hexahedra); the ligament fibres
of ``attachments.json`` and the quadriceps are springs between them; the cartilages touch through
linear pressure-overclosure contact (:func:`kneemesh_core.fe.physics.contact_stiffness`).  Two rigid
surrogates join them: the menisci on the plates' rims (:mod:`.menisci`) and the prefemoral sheet under
the patella in extension (:mod:`.prefemoral`).

**Seating.** The image pose may start with the cartilages apart or overlapping (0.3-0.6 mm on real OA
knees): :func:`seat_femur` and :func:`seat_patella` move the femur and the patella until they touch (the
femur on by the depth that carries the joint load), and the report keeps the overlaps they removed.

The materials, laws, loads and restraints are those of :mod:`.physics`; ``docs/fe-model.md`` describes
the whole model and why each part is there.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pyvista as pv

from kneemesh_core.fe.contact_skin import articular_surface, skin
from kneemesh_core.fe.physics import (CARTILAGE_ELEMENT, QUADRICEPS_ORIGIN_MM, QUADRICEPS_POLE_MM, LoadCase, contact_stiffness,
                                      penalty_stiffness)
from kneemesh_core.errors import KneeMeshError
from kneemesh_core.geometry import RAY_BACKOFF_MM, quad_node_areas, ray_distances, triangle_node_areas
from kneemesh_core.hexmesh.quality import articular_quads, hex_quality, summary
from kneemesh_core.hexmesh.targets import USABLE_MIN_SCALED_JACOBIAN
from kneemesh_core.tissues import BONE_OF, BONES, CARTILAGES

#: The contact pairs: name -> (slave cartilage, master cartilage).
PAIRS = {"medial": ("medial_tibial_cartilage", "femoral_cartilage"),
         "lateral": ("lateral_tibial_cartilage", "femoral_cartilage"),
         "patellofemoral": ("patellar_cartilage", "femoral_cartilage")}


@dataclass
class Part:
    """One cartilage (or surrogate) in the deck: element ids and their nodes (global ids), hexahedra in C3D8
    order or, for a rigid cartilage's contact skin (:mod:`.contact_skin`), wedges in C3D6 order.  A
    ``deformable`` cartilage's hexahedra are solid (:data:`~kneemesh_core.fe.physics.CARTILAGE_ELEMENT`); the
    rest are rigid with their body."""

    name: str
    body: str
    elements: np.ndarray  # (E,) ids
    connectivity: np.ndarray  # (E, 8) or (E, 6) global node ids
    articular: np.ndarray  # (A,) element ids whose S2 face is articular
    bone_side: np.ndarray  # (B,) element ids whose S1 face lies on the bone side
    thickness_mm: float
    deformable: bool = False

    @property
    def element_type(self) -> str:
        return CARTILAGE_ELEMENT if self.deformable else {8: "C3D8", 6: "C3D6"}[self.connectivity.shape[1]]

    def articular_faces(self) -> np.ndarray:
        """The articular (S2) faces of its articular elements, (A, 4) quads or (A, 3) triangles of global ids."""
        conn = self.connectivity[np.searchsorted(self.elements, self.articular)]
        return articular_quads(conn) if conn.shape[1] == 8 else conn[:, 3:]


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
    # cartilage -> its hex mesh's own articular surface, deck frame: points (P, 3), triangles (T, 3) (the
    # contact runs on a rigid cartilage's skin; the meniscus surrogates follow the mesh's outline)
    articular: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    springs: list[Spring] = field(default_factory=list)
    ref: dict[str, int] = field(default_factory=dict)  # body -> reference node
    body_nodes: dict[str, list[int]] = field(default_factory=dict)  # body -> nodes that must move with it
    pairs: dict[str, tuple[str, str]] = field(default_factory=lambda: dict(PAIRS))  # name -> (slave, master)
    surfaces: dict[str, tuple[str, ...]] = field(default_factory=dict)  # a master of several parts -> its parts
    contact_k: dict[str, float] = field(default_factory=dict)  # pair -> N/mm^3
    quadriceps: Spring | None = None
    # body -> the node of the body it is tied to (physics.RESTRAINTS) where its reference node starts
    anchors: dict[str, int] = field(default_factory=dict)
    patella_anterior: np.ndarray = field(default_factory=lambda: np.zeros(3))
    tibial_axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))  # deck frame, proximal
    seating: dict = field(default_factory=dict)
    frame: dict = field(default_factory=dict)
    load: LoadCase = LoadCase()
    side: str = "right"
    next_id: int = 1
    next_element: int = 1

    @property
    def medial(self) -> np.ndarray:
        """The medial direction (3,), deck frame: deck X is the patient's right, so -X in a right knee."""
        return np.array([-1.0 if self.side == "right" else 1.0, 0.0, 0.0])

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


def deck_rotation(frame: dict) -> np.ndarray:
    """(3, 3) whose columns are the deck's X, Y, Z in LPS; ``frame`` is :attr:`Model.frame`."""
    axes = frame["axes_lps"]
    return np.column_stack([axes["X_right"], axes["Y_anterior"], axes["Z_superior"]])


def deck_to_lps(frame: dict, points) -> np.ndarray:
    """Points (..., 3) of the deck frame in the input's LPS frame, mm; ``frame`` is :attr:`Model.frame`."""
    return np.asarray(frame["origin_lps_mm"], float) + np.asarray(points, float) @ deck_rotation(frame).T


#: What a tibiofemoral model leaves out where the knee has no patella (or no patellar cartilage) labelled.
PATELLOFEMORAL = ("patella", "patellar_cartilage")


def build(bones: dict[str, pv.PolyData], cartilages: dict[str, pv.UnstructuredGrid], attachments: dict,
          load: LoadCase = LoadCase()) -> Model:
    """The seated model of a knee: its bone shells (LPS mm, one per bone of ``BONES``), its cartilage
    hex meshes (LPS mm, one per cartilage of ``CARTILAGES``, with the cell data ``layer`` and point data
    ``articular`` and ``bone_side`` of :class:`kneemesh_core.hexmesh.CartilageMesh`) and its frames and
    fibres (``attachments.json``), under ``load``.  Without the patella or its cartilage
    (:data:`PATELLOFEMORAL`) the model is tibiofemoral: no patella, patellofemoral contact, quadriceps or
    prefemoral sheet, and the fibres that end on the patella are left out."""
    if load.cartilage == "deformable":
        refused = unfit_to_deform(cartilages)
        if refused:
            raise KneeMeshError("deformable_refused", "deformable cartilage needs solid elements that cannot invert: "
                                + "; ".join(refused) + ". The knee runs with rigid cartilage (--fe-cartilage rigid).")
    patellofemoral = all(t in bones or t in cartilages for t in PATELLOFEMORAL)
    if not patellofemoral:
        bones = {b: v for b, v in bones.items() if b not in PATELLOFEMORAL}
        cartilages = {t: v for t, v in cartilages.items() if t not in PATELLOFEMORAL}
    origin, rot = deck_frame(attachments)

    def to_deck(p) -> np.ndarray:
        return (np.asarray(p, float) - origin) @ rot

    m = Model(load=load, side=attachments["side"],
              frame={"origin_lps_mm": origin.round(4).tolist(),
                     "axes_lps": {"X_right": rot[:, 0].round(6).tolist(), "Y_anterior": rot[:, 1].round(6).tolist(),
                                  "Z_superior": rot[:, 2].round(6).tolist()}})
    frames = attachments["frames"]
    # the image pose's anatomical flexion (Grood-Suntay, deg): a run's flexion about X adds to it
    m.frame["image_flexion_deg"] = attachments.get("angles_deg", {}).get("flexion")
    m.frame["tibia"] = {"origin_lps_mm": np.round(frames["tibia"]["origin_mm"], 4).tolist(),
                        "axes_lps": {a: np.round(frames["tibia"]["axes"][a], 6).tolist() for a in ("lateral", "anterior", "proximal")}}
    present = [b for b in BONES if b in bones]
    _add_bones(m, {b: to_deck(bones[b].points) for b in present}, {b: bones[b].regular_faces for b in present})
    for tissue in (t for t in CARTILAGES if t in cartilages):
        _add_cartilage(m, tissue, cartilages[tissue], to_deck)
    m.pairs = {name: pair for name, pair in PAIRS.items() if all(t in m.parts for t in pair)}
    law = penalty_stiffness if load.cartilage == "deformable" else contact_stiffness
    for name, (slave, master) in m.pairs.items():
        m.contact_k[name] = law(m.parts[slave].thickness_mm, m.parts[master].thickness_mm)
    # reference nodes: femur and patella at their frames' origins, tibia at the tibial frame's
    for body in present:
        m.ref[body] = int(m.add_nodes(to_deck(np.asarray(frames[body]["origin_mm"])[None]))[0])
    if patellofemoral:
        m.anchors["patella"] = int(m.add_nodes(m.nodes[m.ref["patella"]][None])[0])
        m.body_nodes["femur"].append(m.anchors["patella"])
    _add_ligaments(m, [f for f in attachments["fibres"] if all(e["bone"] in m.ref for e in f["ends"])], to_deck)
    if patellofemoral:
        _add_quadriceps(m, to_deck(np.asarray(frames["patella"]["origin_mm"])
                                   + QUADRICEPS_POLE_MM * np.asarray(frames["patella"]["axes"]["proximal"])))
        m.patella_anterior = np.asarray(frames["patella"]["axes"]["anterior"]) @ rot
    m.tibial_axis = np.asarray(frames["tibia"]["axes"]["proximal"], float) @ rot
    femur = seat_femur(m)
    patella = None
    if patellofemoral:
        if load.prefemoral:
            add_prefemoral(m)
        patella = seat_patella(m)
    _measure_springs(m)
    m.seating = _seating_record(m, femur, patella)
    if load.menisci:
        add_menisci(m, *ring_path(load.flexion_deg, m.frame.get("image_flexion_deg")))
    return m


def ring_path(flexion_deg: float, image_flexion_deg: float | None) -> tuple[float, float]:
    """The femur's flexion from the image pose (deg, least and most) that the meniscus surrogates must clear:
    from anatomical extension (``-image_flexion_deg``: every activity may stand the knee there, the knee bend
    starts there) or the image pose, whichever is less flexed, to ``flexion_deg`` read either way, from the
    image pose (the flexion activity) or anatomically (the knee bend).  The image pose alone where its
    anatomical flexion is unknown."""
    image = image_flexion_deg or 0.0
    return min(0.0, -image), max(flexion_deg, flexion_deg - image)


def unfit_to_deform(cartilages: dict[str, pv.UnstructuredGrid]) -> list[str]:
    """Why cartilage hex meshes cannot deform as solids, one reason per mesh: an element inverted or
    collapsed, or one below the usable scaled Jacobian (:data:`~kneemesh_core.hexmesh.targets.USABLE_MIN_SCALED_JACOBIAN`,
    the floor every shipped mesh keeps; the blended edge's elements below the gate's 0.5 deform well enough);
    empty when every mesh is fit."""
    out = []
    for tissue, grid in cartilages.items():
        s = summary(hex_quality(np.asarray(grid.points), np.asarray(grid.cells_dict[pv.CellType.HEXAHEDRON])))
        if s["inverted"] or s["collapsed"] or s["min_scaled_jacobian"] < USABLE_MIN_SCALED_JACOBIAN:
            out.append(f"{tissue} has {s['inverted']} inverted and {s['collapsed']} collapsed elements, the worst at a "
                       f"scaled Jacobian of {s['min_scaled_jacobian']:g} (at least {USABLE_MIN_SCALED_JACOBIAN:g} needed)")
    return out


def _add_bones(m: Model, points: dict[str, np.ndarray], triangles: dict[str, np.ndarray]) -> None:
    """Each bone's shell: its nodes (P, 3) in the deck frame and triangles (T, 3) into them."""
    for bone in (b for b in BONES if b in points):
        ids = m.add_nodes(points[bone])
        m.bone_nodes[bone] = ids
        m.bone_triangles[bone] = ids[triangles[bone]]
        m.body_nodes[bone] = []


def _add_cartilage(m: Model, tissue: str, grid: pv.UnstructuredGrid, to_deck) -> None:
    """One cartilage in the deck, with its bone's body: a rigid cartilage as the contact skin of its
    articular layer (:mod:`.contact_skin`), all of it moving with the bone; a deformable one as all its
    hexahedra (in the mesh's order), their articular layer's S2 faces in contact and the deepest layer's S1
    faces on the bone, only its bone-side nodes moving with the bone.  Its thickness for the contact law is
    the median length of its columns (their nodes are stacked layer by layer)."""
    layer = np.asarray(grid.cell_data["layer"])
    top = int(layer.max())
    hexes = np.asarray(grid.cells_dict[pv.CellType.HEXAHEDRON])
    pts = to_deck(grid.points)
    points, triangles, outward = articular_surface(pts, hexes[layer == top])
    m.articular[tissue] = (points, triangles)
    if m.load.cartilage == "rigid":
        nodes, conn = skin(points, triangles, outward)
        ids = m.add_nodes(nodes)
        conn, articular, bone_side = ids[conn], np.ones(len(conn), bool), np.ones(len(conn), bool)
        carried = ids
    else:
        conn = hexes
        used = np.unique(conn)
        ids = m.add_nodes(pts[used])
        lookup = np.zeros(grid.n_points, int)
        lookup[used] = ids
        conn, articular, bone_side = lookup[conn], layer == top, layer == 0
        carried = lookup[np.flatnonzero(np.asarray(grid.point_data["bone_side"], bool))]
    elements = np.arange(m.next_element, m.next_element + len(conn))
    m.next_element += len(conn)
    thick = np.linalg.norm(pts[np.asarray(grid.point_data["articular"], bool)]
                           - pts[np.asarray(grid.point_data["bone_side"], bool)], axis=1)
    m.parts[tissue] = Part(tissue, BONE_OF[tissue], elements, conn, elements[articular], elements[bone_side],
                           float(np.median(thick)), deformable=m.load.cartilage == "deformable")
    m.body_nodes[BONE_OF[tissue]].extend(carried.tolist())


def _add_ligaments(m: Model, fibres: list[dict], to_deck) -> None:
    """One spring per fibre of ``attachments.json`` with both ends placed, a node at each end moving
    with the body of its bone."""
    for fibre in fibres:
        ends = fibre["ends"]
        if any(e["lps_mm"] is None for e in ends):
            continue
        a, b = (int(m.add_nodes(to_deck(np.asarray(e["lps_mm"])[None]))[0]) for e in ends)
        for e, n in zip(ends, (a, b)):
            m.body_nodes[e["bone"]].append(n)
        beyond = float(fibre.get("path_beyond_mm", 0.0))
        length = float(np.linalg.norm(m.nodes[a] - m.nodes[b])) + beyond
        m.springs.append(Spring(fibre["name"], fibre["bundle"], m.next_element, (a, b), fibre["stiffness_n"],
                                fibre["slack_length_mm"], length, beyond))
        m.next_element += 1


def _add_quadriceps(m: Model, pole: np.ndarray) -> None:
    """The quadriceps: from the patella's proximal ``pole`` (3,), deck frame, to its origin up the
    femoral shaft, which moves with the femur."""
    shaft = np.array([0.0, 0.0, QUADRICEPS_ORIGIN_MM])
    a, b = (int(i) for i in m.add_nodes(np.stack([pole, shaft])))
    m.body_nodes["patella"].append(a)
    m.body_nodes["femur"].append(b)
    m.quadriceps = Spring("QUADRICEPS", "QUAD", m.next_element, (a, b), 0.0, 0.0, float(np.linalg.norm(pole - shaft)))
    m.next_element += 1


def _measure_springs(m: Model) -> None:
    """Every spring's initial length in the seated pose."""
    for s in m.springs:
        s.length_mm = float(np.linalg.norm(m.nodes[s.nodes[0]] - m.nodes[s.nodes[1]])) + s.beyond_mm
    q = m.quadriceps
    if q is not None:
        q.length_mm = float(np.linalg.norm(m.nodes[q.nodes[0]] - m.nodes[q.nodes[1]]))


def _surface(m: Model, tissue: str) -> tuple[np.ndarray, np.ndarray]:
    """The articular surface of a part of the deck (the contact runs on it) as points (P, 3) and triangles
    (T, 3), deck frame."""
    faces, ids = _articular_faces(m, tissue)
    local = np.searchsorted(ids, faces)
    triangles = local if local.shape[1] == 3 else np.concatenate([local[:, [0, 1, 2]], local[:, [0, 2, 3]]])
    return np.stack([m.nodes[int(i)] for i in ids]), triangles


def add_menisci(m: Model, least_deg: float, most_deg: float) -> None:
    """The meniscus surrogates (:mod:`kneemesh_core.fe.menisci`) of the seated model: a ring of
    hexahedra on each tibial plate, rigid with the tibia, in contact with the femoral cartilage
    under the contact law of its compartment, clear of the femoral cartilage as it turns about the
    flexion axis (deck X through the femur's reference node) from ``least_deg`` to ``most_deg``
    (:func:`ring_path`; 0 is the image pose)."""
    from scipy.spatial.transform import Rotation

    from kneemesh_core.fe.menisci import LAYER_MM, POSE_STEP_DEG, wedge

    points, triangles = _surface(m, "femoral_cartilage")
    centre = m.nodes[m.ref["femur"]]
    femoral = [((points - centre) @ Rotation.from_rotvec([np.radians(a), 0.0, 0.0]).as_matrix().T + centre, triangles)
               for a in np.unique(np.r_[np.arange(0.0, most_deg, POSE_STEP_DEG), np.arange(0.0, least_deg, -POSE_STEP_DEG),
                                        least_deg, most_deg])]
    plates = {side: m.articular[f"{side}_tibial_cartilage"] for side in ("medial", "lateral")}
    for side, other in (("medial", "lateral"), ("lateral", "medial")):
        nodes, hexes = wedge(plates[side], femoral, m.tibial_axis, plates[other][0].mean(0))
        if not len(hexes):
            continue
        name = f"{side}_meniscus"
        _add_surrogate(m, name, "tibia", nodes, hexes, LAYER_MM)
        m.pairs[name] = (name, "femoral_cartilage")
        m.contact_k[name] = layers_k(m, side)


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
    _add_surrogate(m, "prefemoral", "femur", nodes, hexes, LAYER_MM)
    m.surfaces["patellar_track"] = ("femoral_cartilage", "prefemoral")
    m.pairs["patellofemoral"] = ("patellar_cartilage", "patellar_track")


def _add_surrogate(m: Model, name: str, body: str, nodes: np.ndarray, hexes: np.ndarray, layer_mm: float) -> None:
    """A rigid surrogate (a meniscus, the prefemoral sheet) of hexahedra (E, 8) on ``nodes`` (N, 3),
    deck frame, moving with ``body``; its upper faces (nodes 5-8) are its contact surface."""
    ids = m.add_nodes(nodes)
    elements = np.arange(m.next_element, m.next_element + len(hexes))
    m.next_element += len(hexes)
    m.parts[name] = Part(name, body, elements, ids[hexes], elements, elements, layer_mm)
    m.body_nodes[body].extend(ids.tolist())


def _articular_faces(m: Model, tissue: str) -> tuple[np.ndarray, np.ndarray]:
    """The articular (S2) faces of a part of the deck (:meth:`Part.articular_faces`) and their node ids."""
    faces = m.parts[tissue].articular_faces()
    return faces, np.unique(faces)


def gaps(m: Model, slave: str, master: str, direction: np.ndarray) -> np.ndarray:
    """Distance (mm) from each articular node of ``slave`` along unit ``direction`` to the articular
    surface of ``master``: negative where the two overlap, NaN where the ray misses it."""
    back = RAY_BACKOFF_MM  # rays start behind each node, so an overlap is found too
    return ray_distances(_surface(m, slave)[0] - back * direction, direction, *_surface(m, master)) - back


def layers_k(m: Model, pair: str) -> float:
    """The elastic-foundation stiffness (N/mm^3) of a cartilage pair's two layers
    (:func:`~kneemesh_core.fe.physics.contact_stiffness`): the contact law of rigid cartilage, what seats the
    femur, and the meniscus surrogates' law, whether or not the cartilage itself deforms."""
    slave, master = PAIRS[pair]
    return contact_stiffness(m.parts[slave].thickness_mm, m.parts[master].thickness_mm)


def _move(m: Model, body: str, shift: np.ndarray) -> None:
    """Move a body by ``shift`` (3,), mm: its bone, reference node, the nodes that ride on it and its parts'."""
    nodes = {*m.body_nodes[body], *m.bone_nodes[body].tolist(), m.ref[body]}
    for part in (p for p in m.parts.values() if p.body == body):
        nodes.update(np.unique(part.connectivity).tolist())
    for n in nodes:
        m.nodes[int(n)] = m.nodes[int(n)] + shift


def _node_areas(m: Model, tissue: str) -> np.ndarray:
    """Tributary area (mm^2) of each articular node of ``tissue``, in the order of
    :func:`_articular_faces`'s ids."""
    faces, ids = _articular_faces(m, tissue)
    points, local = np.stack([m.nodes[int(i)] for i in ids]), np.searchsorted(ids, faces)
    return (quad_node_areas if local.shape[1] == 4 else triangle_node_areas)(points, local)


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


def seat_femur(m: Model) -> dict:
    """Seat the femur before any load: down the tibial axis until its cartilage just touches the tibial
    cartilage (down across a gap, up out of an overlap), then on by the depth at which the contact
    carries the joint load (:func:`preload_depth`), so that the solver starts next to equilibrium, not
    from a touch that carries nothing.  Returns the gaps of the image pose per plate, the shift and the
    depth."""
    z = m.tibial_axis
    before = {pair: gaps(m, PAIRS[pair][0], PAIRS[pair][1], z) for pair in ("medial", "lateral")}
    g = np.concatenate(list(before.values()))
    touch = -float(np.nanmin(g)) if np.isfinite(g).any() else 0.0
    depth = preload_depth([v + touch for v in before.values()],
                          [_node_areas(m, PAIRS[p][0]) for p in before], [layers_k(m, p) for p in before], m.load.joint_load_n)
    shift = touch - depth
    _move(m, "femur", shift * z)
    return {"gaps": before, "shift_mm": shift, "depth_mm": depth}


def seat_patella(m: Model) -> dict:
    """Seat the patella along its anterior axis until it just touches the femoral cartilage or the
    prefemoral sheet (:func:`add_prefemoral`), whichever it meets first.  Returns its gaps to them, measured
    after the femur was seated, and the shift."""
    toward = -m.patella_anterior  # the patella's articular side faces posterior, towards the trochlea
    pf = np.fmin.reduce([gaps(m, "patellar_cartilage", master, toward)
                         for master in ("femoral_cartilage", "prefemoral") if master in m.parts])
    shift = float(np.nanmin(pf)) if np.isfinite(pf).any() else 0.0
    _move(m, "patella", shift * toward)
    return {"gaps": pf, "shift_mm": shift}


def _seating_record(m: Model, femur: dict, patella: dict | None) -> dict:
    """What the seating did, for the report: the overlaps of the image pose it removed, the shifts, the
    preload depth and its share of the tibiofemoral layers' thickness."""
    def overlap(v: np.ndarray) -> float:
        return round(float(max(0.0, -np.nanmin(v))) if np.isfinite(v).any() else 0.0, 3)

    before = {**femur["gaps"], **({"patellofemoral": patella["gaps"]} if patella is not None else {})}
    depth = femur["depth_mm"]
    return {"initial_overlap_mm": {k: overlap(v) for k, v in before.items()},
            "initial_overlap_nodes": {k: int((v < 0).sum()) for k, v in before.items()},
            "femur_shift_mm": round(femur["shift_mm"], 3), "preload_depth_mm": round(depth, 3),
            "preload_strain": round(depth / float(np.mean([m.parts[s].thickness_mm + m.parts[f].thickness_mm
                                                           for s, f in (PAIRS["medial"], PAIRS["lateral"])])), 3),
            **({"patella_shift_mm": round(patella["shift_mm"], 3)} if patella is not None else {})}
