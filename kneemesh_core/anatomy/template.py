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
