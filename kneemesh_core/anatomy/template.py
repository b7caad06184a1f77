"""The anatomy template: ligament fibres and bone surfaces of the Lenhart 2015 knee, and a femur.

Lenhart RL, Kaiser J, Smith CR, Thelen DG. Prediction and validation of load-dependent behavior
of the tibiofemoral and patellofemoral joints during movement. Ann Biomed Eng 2015;43:2675-2685.
Files from ``opensim-jam-org/jam-resources`` (commit 73306a0f), Apache License 2.0: see
``data/LICENSE-lenhart2015`` and ``data/NOTICE``; what was derived and how is in
``scripts/build_anatomy_template.py``.

Everything here is in one **template frame**, millimetres, of a right knee: x anterior,
y superior, z lateral, origin at the knee joint centre (Lenhart's ``femur_distal_r`` and
``tibia_proximal_r`` frames, which coincide in the model's neutral pose).  A left knee is the
mirror image: the same coordinates read as (anterior, superior, lateral) of a left knee, which
is how :mod:`.register` places the template, so nothing here is ever flipped by hand.
"""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyvista as pv

DATA = Path(__file__).resolve().parent / "data"
FIBRES_FILE = DATA / "lenhart2015_fibres.json"
#: Surface files per template bone (template frame, mm).
SURFACE_FILES = {"femur": DATA / "femur_template.vtp", "tibia": DATA / "lenhart2015_tibia.vtp",
                 "patella": DATA / "lenhart2015_patella.vtp", "fibula": DATA / "lenhart2015_fibula.vtp"}
#: The bones a fibre end can sit on (the fibula moves with the tibia: its ends belong to the tibia).
BONES = ("femur", "tibia", "patella")

#: The femur template's long axis leans this far posterior of its frame's y axis, deg (about its z).
#: The template's y axis is the sample femur's shaft as its field of view showed it (the line through
#: its cross-sections, which the metaphysis's posterior flare tilts forward), and through it the image
#: poses of OAI knees read 12 deg of hyperextension (median; -19 to +1 deg), which no knee lying in a
#: coil holds.  The anterior cortex of the distal femoral shaft (35 mm above the flexion axis up to the
#: field of view's edge: no flare in front, the line surgeons align a femoral component to) is the
#: distal anatomical axis a knee image shows; measured on each knee of the tune half of the paper's
#: cohort through its registered template (42 maps), it leans 23.8 deg posterior of the template's y
#: axis (median; 10th-90th percentile 17.7-32.4 deg per knee, too loose for one knee's own, stable for
#: the template's).  Against the femoral frame this axis gives, the cortex leans 2.3 deg posterior on
#: the tune half, 2.2 on the held-out half and -3.4 on the 40 OAI maps (median; ``bench/anatomy.py``),
#: and the image poses of all 126 real maps read 4.5 to 24.7 deg of flexion.  The femoral bow puts the
#: mechanical axis (hip to knee) a few degrees anterior of it at the knee.
FEMUR_ANTERIOR_CORTEX_TILT_DEG = 23.8
_TILT = np.radians(FEMUR_ANTERIOR_CORTEX_TILT_DEG)
#: Each bone's long axis, proximal, in the template frame (unit): Lenhart's
#: tibial y axis (his model has the whole tibia), the femur's anterior cortex (above).
LONG_AXES = {"tibia": np.array([0.0, 1.0, 0.0]), "femur": np.array([-np.sin(_TILT), np.cos(_TILT), 0.0])}


@dataclass(frozen=True)
class FibreEnd:
    bone: str  # femur, tibia or patella: the rigid body it moves with
    surface: str  # the template surface it lies on: the bone, or the fibula for tibial ends on it
    point: np.ndarray  # (3,) template frame, mm


@dataclass(frozen=True)
class Fibre:
    name: str  # e.g. "MCLs1"
    bundle: str  # e.g. "MCLs"
    stiffness_n: float  # Blankevoort linear stiffness, N per unit strain
    slack_length_mm: float  # in the template knee
    reference_strain: float  # in the model's reference pose (extension), from its SIMM file
    ends: tuple[FibreEnd, FibreEnd]
    note: str | None = None
    # the part of the fibre's path beyond its two ends that the knee's motion leaves unchanged (mm):
    # the ITB, cut at the knee, runs on to the pelvis; 0 for a fibre whose ends are its ends
    path_beyond_mm: float = 0.0


@dataclass(frozen=True)
class Template:
    source: dict
    fibres: tuple[Fibre, ...]
    surfaces: dict  # bone -> pv.PolyData (template frame, mm)

    def points(self, bone: str) -> np.ndarray:
        return np.asarray(self.surfaces[bone].points, float)


@functools.lru_cache(maxsize=1)
def load() -> Template:
    """The packaged template (read once per process)."""
    raw = json.loads(FIBRES_FILE.read_text())
    fibres = tuple(
        Fibre(f["name"], f["bundle"], f["stiffness_n"], f["slack_length_mm"], f["reference_strain"],
              tuple(FibreEnd(e["bone"], e["surface"], np.asarray(e["point_mm"], float)) for e in f["ends"]),
              f.get("note"), f.get("path_beyond_mm", 0.0))
        for f in raw["fibres"])
    surfaces = {bone: pv.read(path) for bone, path in SURFACE_FILES.items()}
    return Template(raw["source"], fibres, surfaces)
