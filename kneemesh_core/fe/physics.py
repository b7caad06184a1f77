"""The physics of the knee model in one place: materials, the ligament law, loads, restraints,
boundary conditions and the limits a run is judged by.  Units: mm, N, MPa, s (and tonne/mm^3 for
density, the consistent mass unit).

The model (:mod:`.model`), both deck dialects (:mod:`.calculix`, :mod:`.abaqus`) and the results
reader (:mod:`.results`) read them here, so the two decks model the same knee and the results are
read with the law the deck applied.  ``docs/fe-model.md`` describes the model as a whole.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from kneemesh_core.errors import KneeMeshError

# -- cartilage ---------------------------------------------------------------------------------
#: Cartilage modulus behind the contact stiffness, MPa: the instantaneous compressive modulus of human
#: knee cartilage is 5-15 MPa; the paper's rigid-cartilage models use linear contact laws of this kind.
CARTILAGE_MODULUS_MPA = 10.0
#: Cartilage Poisson ratio (0.45 in Blankevoort et al. 1991 and Bei & Fregly 2004: nearly incompressible
#: under a short load).  A thin layer that cannot bulge is 3.79 times stiffer than E / h; with E / h alone
#: the sample's femur sank 0.96 mm into 4.2 mm of cartilage to carry 1000 N and 4.7 mm by 30 deg of
#: flexion, and the full flexion stopped at 45 deg; with the confined layer it seats at 0.51 mm and flexes
#: to 90 deg.
CARTILAGE_POISSON = 0.45
#: Cartilage density, tonne/mm^3 (1100 kg/m^3; only the Abaqus/Explicit deck uses it).
CARTILAGE_DENSITY_T_MM3 = 1.1e-9
#: The confined modulus of a thin layer bonded to bone, MPa: M = (1 - nu) E / ((1 + nu)(1 - 2 nu)).
CONFINED_MODULUS_MPA = CARTILAGE_MODULUS_MPA * (1 - CARTILAGE_POISSON) / ((1 + CARTILAGE_POISSON) * (1 - 2 * CARTILAGE_POISSON))


#: The element of deformable cartilage: the fully integrated trilinear hexahedron C3D8 (no hourglass modes,
#: which C3D8R has, held only by hourglass control).  Not C3D8I: ccx 2.20's incompatible-mode element diverged
#: in the sample knee's seating step (tibiofemoral model, penalty 1x: its internal nodes' residual 5e6 N after
#: four iterations, 2e12 N after six) where C3D8 converged in five to seven iterations.  Locking is small at
#: nu 0.45: a 2 mm layer pressed by a rigid sphere (1 mm elements) travelled 0.4754 mm with C3D8, 0.4813 with
#: C3D8I, 0.4839 with C3D8R (C3D8 1.8 % stiffer); all three give a uniform compression exactly.  ccx has no
#: hybrid (C3D8H) element.
CARTILAGE_ELEMENT = "C3D8"


def neo_hooke() -> tuple[float, float]:
    """The compressible neo-Hookean constants (C10 MPa, D1 1/MPa) of deformable cartilage whose small-strain
    modulus and Poisson ratio are :data:`CARTILAGE_MODULUS_MPA` and :data:`CARTILAGE_POISSON`: C10 = G / 2,
    D1 = 2 / K (Abaqus's and ccx's ``*HYPERELASTIC, NEO HOOKE``)."""
    e, nu = CARTILAGE_MODULUS_MPA, CARTILAGE_POISSON
    return e / (4 * (1 + nu)), 6 * (1 - 2 * nu) / e


#: Deformable cartilages touch through a penalty this many times stiffer than the two layers it joins
#: (:func:`contact_stiffness`), so that the surfaces overlap by 1/20 of the layers' own compression: the
#: cartilage, not the contact law, carries the compliance.
DEFORMABLE_PENALTY = 20.0


def contact_stiffness(thickness_a_mm: float, thickness_b_mm: float) -> float:
    """The linear pressure-overclosure stiffness (N/mm^3) of two cartilage layers in contact: each a
    thin elastic layer on bone (the elastic foundation of Blankevoort et al. 1991 and Bei & Fregly
    2004), springs in series, K = M / (h_a + h_b), rounded as the deck states it."""
    return round(CONFINED_MODULUS_MPA / (thickness_a_mm + thickness_b_mm), 4)


def penalty_stiffness(thickness_a_mm: float, thickness_b_mm: float) -> float:
    """The linear pressure-overclosure stiffness (N/mm^3) between two deformable cartilages:
    :data:`DEFORMABLE_PENALTY` times the layers' own (:func:`contact_stiffness`)."""
    return round(DEFORMABLE_PENALTY * contact_stiffness(thickness_a_mm, thickness_b_mm), 4)


# -- ligaments ---------------------------------------------------------------------------------
#: Blankevoort (1991) transition strain, as OpenSim implements the law.
TRANSITION_STRAIN = 0.06
#: A slack fibre's slope in compression, a fraction of its stiffness k per unit strain: a tension-only
#: spring would leave a singular tangent while slack.  The results read a slack fibre as 0 N.
SLACK_SLOPE = 1e-3


def ligament_force(stiffness_n: float, strain):
    """Blankevoort force (N) of a fibre of ``stiffness_n`` (N per unit strain) at ``strain``
    (L / L0 - 1; a scalar or an array): 0 when slack, k e^2 / (2 e_t) up to e_t, k (e - e_t / 2) beyond."""
    e, et = np.asarray(strain, float), TRANSITION_STRAIN
    return np.where(e <= 0, 0.0, np.where(e < et, stiffness_n * e ** 2 / (2 * et), stiffness_n * (e - et / 2)))


def ligament_table(stiffness_n: float, slack_mm: float, length_mm: float, points: int = 48) -> list[tuple[float, float]]:
    """(force N, elongation mm) pairs of a fibre's nonlinear spring, elongation from its initial
    ``length_mm``; :func:`ligament_force` with :data:`SLACK_SLOPE` in compression.

    ccx holds a nonlinear spring's force constant beyond its table (a fibre past the last pair pulls
    no harder however far it stretches), so the table runs to a strain of 2, twice any fibre's
    rupture, with ``points`` pairs in the quadratic toe and the exact straight lines either side."""
    strain = np.concatenate([[-0.9], np.linspace(0.0, TRANSITION_STRAIN, points), [2.0]])
    force = np.where(strain <= 0, SLACK_SLOPE * stiffness_n * strain, ligament_force(stiffness_n, strain))
    return [(float(f), float(slack_mm * (1.0 + e) - length_mm)) for f, e in zip(force, strain)]


# -- the quadriceps ----------------------------------------------------------------------------
#: Where the quadriceps pulls from: this far up the femoral shaft (deck Z), mm; the origin belongs to
#: the femur, so the muscle pulls the patella into the trochlea without pushing the femur off the tibia.
QUADRICEPS_ORIGIN_MM = 200.0
#: How much shorter than its initial length the quadriceps goes slack, mm.
QUADRICEPS_SLACK_MM = 5.0
#: Where it pulls on the patella: this far up the patella's proximal axis from its frame's origin, mm.
QUADRICEPS_POLE_MM = 15.0


def quadriceps_table(force_n: float, length_mm: float) -> list[tuple[float, float]]:
    """(force N, elongation mm) of the quadriceps: ``force_n`` at its initial length, +1 N/mm as it
    lengthens, falling to 0 over :data:`QUADRICEPS_SLACK_MM` of shortening."""
    return [(-SLACK_SLOPE * force_n, -length_mm), (0.0, -QUADRICEPS_SLACK_MM), (force_n, 0.0),
            (force_n + length_mm, length_mm)]


# -- loads -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LoadCase:
    """What a run asks of the knee.

    The tibia is held; the joint load pushes the femur down the tibial axis, its line of action
    ``medial_offset_mm`` medial of the femoral frame's origin (the middle of the flexion axis) in the
    frontal plane: on the femur's reference node with the moment ``joint_load_n`` x ``medial_offset_mm``
    (the knee adduction moment of a loaded limb, whose load passes medial of the knee); the quadriceps
    pulls the patella towards its origin up the femoral shaft; the femur is then flexed about the flexion
    axis (deck X) to ``flexion_deg``, at most ``max_increment_deg`` an increment, the loads held.

    ``activity`` ``knee_bend`` (:func:`legs`) goes from anatomical extension to ``flexion_deg`` of
    anatomical flexion and back instead, the joint load rising to ``peak_load_n`` at the deepest flexion."""

    joint_load_n: float = 1000.0
    # 12 mm: the medial share of the tibial load at the end of seating met the paper's own simulations of
    # the same knees at its first frame (median 0.73) on the tune half of bench/paper_fe.py (7 knees:
    # ours 0.56 at 0 mm, 0.68 at 10, 0.73 at 14, 0.79 at 18 mm); 12 N m per 1000 N, about a third
    # of the peak adduction moment of gait at two to three times the load (Kutzner 2013).
    medial_offset_mm: float = 12.0
    quadriceps_n: float = 300.0
    flexion_deg: float = 90.0
    max_increment_deg: float = 3.0
    cartilage: Literal["rigid", "deformable"] = "rigid"
    menisci: bool = True  # the meniscus surrogates (fe/menisci.py)
    prefemoral: bool = True  # the patella's rest above the trochlea (fe/prefemoral.py)
    activity: Literal["flexion", "knee_bend"] = "flexion"
    peak_load_n: float = 3500.0  # the knee bend's joint load at its deepest flexion


@dataclass(frozen=True)
class Leg:
    """One step of a run after the seating: the femur turned to ``flexion_deg`` about the flexion axis
    (from the image pose) while the joint load goes linearly to ``joint_load_n``."""

    name: str
    flexion_deg: float
    joint_load_n: float


#: The knee bend's load at its deepest flexion is ``peak_load_n``: telemetric knee implants measured
#: 2.5-3.5 times body weight in a knee bend (Kutzner et al. 2010, the data behind the paper's activity,
#: whose knees carried 0.9-1.4 kN at its first frame and 3.0-4.0 kN at its peak: paper_fe.md).
ACTIVITIES = {"flexion": "from the image pose to the flexion asked for, the joint load held",
              "knee_bend": "from anatomical extension to the flexion asked for (anatomical) and back, the joint load "
                           "rising linearly with flexion to its peak at the deepest flexion and falling back"}


def legs(load: LoadCase, flexion_deg: float, image_flexion_deg: float | None) -> list[Leg]:
    """The steps of a run after the seating (at the image pose, under ``load.joint_load_n``).

    ``flexion``: one leg to ``flexion_deg`` from the image pose.  ``knee_bend``: to anatomical extension
    (the image pose is ``image_flexion_deg`` of anatomical flexion: Grood-Suntay, :mod:`kneemesh_core.anatomy`),
    down to ``flexion_deg`` of anatomical flexion with the load rising to ``load.peak_load_n``, and back
    to extension with it falling to ``load.joint_load_n``."""
    if load.activity == "flexion":
        return [Leg("flex", flexion_deg, load.joint_load_n)] if flexion_deg > 0 else []
    if image_flexion_deg is None:
        raise KneeMeshError("activity_needs_anatomy", "the knee bend starts at anatomical extension, and this knee's "
                            "anatomy gave no flexion angle of its image pose (attachments.json angles_deg).")
    extension = -image_flexion_deg
    out = [Leg("to anatomical extension", extension, load.joint_load_n)] if abs(extension) >= 0.5 else []
    return out + [Leg("bend", flexion_deg + extension, load.peak_load_n),
                  Leg("back to extension", extension, load.joint_load_n)]


#: Deformable cartilage's largest flexion increment, deg, every increment of a leg the same size.  From the sample's
#: seated equilibrium a first increment of 7.5 deg diverged (the femur's residual moment 16 N m, then 2e5 N m), one
#: of 1.5 deg converged in 10 Newton iterations and the next ones in 6-7, up to 3.4 deg; one of 5.1 deg failed twice
#: (8 and 5 iterations, 5 minutes) before ccx cut it back.  Increments of 3 deg converged or not by chance (ccx's
#: threads sum in varying order): a fresh-clone CI run's sixth one, 11.25 to 14.25 deg, diverged (residual 3.5e3 to
#: 1e17 N) and ccx stopped on a singular matrix where the same deck converged alone.  A first increment smaller
#: than the rest left ccx a sliver to end the step with (an increment more).
DEFORMABLE_MAX_INCREMENT_DEG = 2.0

#: The smoke run: flexion and largest increment, deg (two increments: the sample's run took 53 s of CPU
#: in three of 5 deg, 43 s in two, with the same contact at 15 deg within 3 % of force).
SMOKE_FLEXION_DEG, SMOKE_INCREMENT_DEG = 15.0, 7.5

# -- boundary conditions and restraints ----------------------------------------------------------
#: The body held still (every node of it, all translations).
FIXED_BODY = "tibia"
#: The bodies that move: rigid bodies with a reference node (translations) and rotations.
MOVING_BODIES = ("femur", "patella")
#: The driven degree of freedom: the femur's rotation about deck X, the flexion axis.
FLEXION = ("femur", "rotation", 0)


@dataclass(frozen=True)
class Restraint:
    """A linear spring on one degree of freedom of a moving body, to the ground or to another body.

    ``kind`` translation (N/mm, of the body's reference node) or rotation (N mm/rad); ``axis`` 0, 1, 2
    for deck X, Y, Z; ``to`` None (the ground) or the body it ties to (for a translation, the node of
    that body where the moving body's reference node starts)."""

    body: str
    kind: Literal["translation", "rotation"]
    axis: int
    stiffness: float
    to: str | None = None


#: Weak springs on the free degrees of freedom, to keep the solve regular before contact closes:
#: N/mm and N mm/rad.
STABILISER_N_MM, STABILISER_NMM_RAD = 5.0, 2000.0
#: Internal-external rotational restraint of the femur, N mm/rad (60 N m/rad, about 1 N m/deg, the
#: order of a knee's measured torsional stiffness near neutral): the capsule and the meniscal horns,
#: which the model leaves out.  Without it the femur of the sample knee rotated 18-41 deg externally by
#: 27-45 deg of flexion and left the lateral plate (the paper's model controlled this degree of freedom
#: with an applied torque).
IE_RESTRAINT_NMM_RAD = 60000.0
#: Anterior-posterior restraint of the femur (deck Y), N/mm: the secondary AP restraints the model leaves
#: out (meniscal horns, capsule), the order of a knee's anterior drawer stiffness.
AP_RESTRAINT_N_MM = 40.0
#: Medial-lateral restraint of the femur (deck X), N/mm: the tibial eminence and the meniscal horns, which
#: the model leaves out (its contact is cartilage on cartilage, and the plates are nearly flat across).
#: With only the weak stabiliser, knees in varus slid medially down the tilted line of the joint load:
#: OAI 9153013_96m (5 deg varus) 16 mm by 18 deg of flexion, until the femur left the tibia at 51 deg.
ML_RESTRAINT_N_MM = 40.0
#: The patella's tilt and spin restraint relative to the femur (deck Y and Z rotations), N mm/rad: the
#: retinacula.  With only the weak stabiliser the sample's patella spun 34 deg by 21 deg of flexion and
#: left the trochlea.
PATELLA_ROTATION_NMM_RAD = 30000.0

#: Every restraint of the model, in deck order.  The femur's to the ground (its flexion is driven, not
#: sprung); the patella's to the femur, which it follows through flexion (grounded, they would pull back a
#: patella that moves 30-50 mm with the femur: 150-250 N on the sample at 50 deg).
RESTRAINTS = (
    Restraint("femur", "translation", 0, ML_RESTRAINT_N_MM),
    Restraint("femur", "translation", 1, AP_RESTRAINT_N_MM),
    Restraint("femur", "translation", 2, STABILISER_N_MM),
    Restraint("femur", "rotation", 1, STABILISER_NMM_RAD),
    Restraint("femur", "rotation", 2, IE_RESTRAINT_NMM_RAD),
    *(Restraint("patella", "translation", axis, STABILISER_N_MM, to="femur") for axis in range(3)),
    Restraint("patella", "rotation", 0, STABILISER_NMM_RAD, to="femur"),
    Restraint("patella", "rotation", 1, PATELLA_ROTATION_NMM_RAD, to="femur"),
    Restraint("patella", "rotation", 2, PATELLA_ROTATION_NMM_RAD, to="femur"),
)


def spring_stiffness(body: str, kind: str, to: str | None = None) -> np.ndarray:
    """The stiffness (3,) of ``body``'s springs on its ``kind`` degrees of freedom (deck X, Y, Z) to the
    ground (``to`` None) or to the body ``to``, 0 where it has none: what the results subtract to balance
    the body's forces."""
    k = np.zeros(3)
    for r in RESTRAINTS:
        if (r.body, r.kind, r.to) == (body, kind, to):
            k[r.axis] += r.stiffness
    return k


# -- limits a run is judged by -------------------------------------------------------------------
#: A seating deeper than this share of the tibiofemoral cartilage layers' combined thickness means the
#: cartilages meet over too small an area to carry the joint load as cartilage: no cartilage is squeezed
#: by three quarters.  The sample seats at 0.12 (0.51 mm); under the softer E / h law the sample seated
#: at 0.22 and OAI 9357383_00m at 0.29, and a severity-3 phantom whose medial plate was meshed over 80 %
#: of its label needed 1.28 (4.1 mm) and did not converge.
MAX_PRELOAD_STRAIN = 0.75
#: An increment is trusted only if the femur's forces balance within this fraction of the joint load.
MAX_BALANCE_ERROR = 0.05
#: A completed run is physiology only within these (a knee under a 1000 N joint load: cadaver and model
#: studies put tibiofemoral peaks at a few to 15-20 MPa over hundreds of mm^2, both compartments loaded in
#: extension).  Tibial plates only: the meniscus surrogates are rigid rings whose edge concentrates
#: pressure by construction.  The plates' peak over the run, MPa ...
MAX_PLATE_PEAK_MPA = 20.0
#: ... that limit under a joint load of this (N) or less; under a heavier one (an activity's peak) it grows with
#: the load's square root, as the peak of a rounded body on an elastic foundation does (the paper's own models
#: peaked at 21 / 29 / 46 MPa, 10th / 50th / 90th percentile, over its activity's 3.0-4.0 kN: paper_fe.md) ...
PLATE_PEAK_REFERENCE_N = 1000.0

#: ... each plate's share of the joint load in extension (the end of seating) ...
MIN_PLATE_SHARE = 0.1
#: ... and the plates' contact area in extension, mm^2.
MIN_PLATES_AREA_MM2 = 100.0


def plate_peak_limit_mpa(joint_load_n: float) -> float:
    """The plates' physiological peak (MPa) under a joint load (N): :data:`MAX_PLATE_PEAK_MPA`, growing as the
    load's square root above :data:`PLATE_PEAK_REFERENCE_N`."""
    return MAX_PLATE_PEAK_MPA * float(np.sqrt(max(joint_load_n, PLATE_PEAK_REFERENCE_N) / PLATE_PEAK_REFERENCE_N))
