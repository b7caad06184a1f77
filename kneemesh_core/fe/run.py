"""A job folder's decks and simulations: the model read from the job's meshes and anatomy, the decks
written, CalculiX run for the flexion asked for, and the report's entry of the run.

``full`` runs the job's own ``fe/knee_ccx.inp`` (0-90 deg in 3 deg increments); ``smoke`` writes a
wrapper over the same shared model to 15 deg in two increments, in ``fe/smoke/``, and runs that.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyvista as pv

from kneemesh_core.errors import KneeMeshError
from kneemesh_core.fe import deck
from kneemesh_core.fe.calculix import StartPose, rot_nodes
from kneemesh_core.fe.model import PATELLOFEMORAL, Model, build
from kneemesh_core.fe.physics import SMOKE_FLEXION_DEG, SMOKE_INCREMENT_DEG, LoadCase
from kneemesh_core.fe.results import CONTACT_FIGURE, CONTACTS, RESULTS_FILE, parse_dat, write_results
from kneemesh_core.fe.simulate import DEFORMABLE_STALL_CPU_S, STALL_CPU_S, run_ccx
from kneemesh_core.tissues import BONES, CARTILAGES

#: The job folder's meshes (the job's layout, kneemesh_core.job.outputs, which imports this package).
MESHES_DIR = "meshes"

FE_DIR, SMOKE_DIR = "fe", "smoke"
#: Where, beside a deformable model's CalculiX deck, the rigid model's seating that gives its start pose ran.
POSE_DIR = "rigid_pose"
#: How long that seating may take, s (the sample's: 3 s).
POSE_TIMEOUT_S = 300.0
#: Where a job's results lie, relative to the job folder: the full flexion first, then the smoke run.
RESULT_FILES = (f"{FE_DIR}/{RESULTS_FILE}", f"{FE_DIR}/{SMOKE_DIR}/{RESULTS_FILE}")


def read_model(out_dir: Path, load: LoadCase = LoadCase()) -> Model:
    """The model (:func:`kneemesh_core.fe.model.build`) of a meshed job folder: ``meshes/`` and
    ``attachments.json``; a clear error where the job has not written them."""
    out = Path(out_dir)
    att_file = out / "attachments.json"
    if not att_file.exists():
        raise KneeMeshError("anatomy_missing", "the decks need the attachment sites and frames (attachments.json): "
                            "run the whole job (bones, cartilage and anatomy) first.")
    files = {t: out / MESHES_DIR / f"{t}.{'vtp' if t in BONES else 'vtu'}" for t in (*BONES, *CARTILAGES)}
    missing = [f.name for t, f in files.items() if not f.exists() and t not in PATELLOFEMORAL]
    if missing:
        raise KneeMeshError("mesh_missing", f"the decks need every bone and cartilage mesh (a tibiofemoral model at "
                            f"least: all but the patella's); missing: {', '.join(missing)}.")
    present = {t: pv.read(f) for t, f in files.items() if f.exists()}
    return build({b: present[b] for b in BONES if b in present}, {t: present[t] for t in CARTILAGES if t in present},
                 json.loads(att_file.read_text()), load)


def tibiofemoral_reasons(m: Model) -> list[str]:
    """Why a model is tibiofemoral only (the knee has no patella or no patellar cartilage meshed); empty when
    it is the whole knee."""
    if "patella" in m.ref:
        return []
    return ["a tibiofemoral model: the knee has no meshed patella and patellar cartilage, so the decks have no "
            "patellofemoral joint, quadriceps or patellar ligaments"]


def rigid_start_pose(out_dir: Path, m: Model, folder: Path) -> StartPose:
    """Where a deformable model ``m`` of a job starts its CalculiX run (:func:`kneemesh_core.fe.calculix.deck`):
    the seated equilibrium of the same knee with rigid cartilage (its elastic-foundation contact stands for
    the same layers), found by running that model's seating in ``folder`` (a few seconds).  Returned as each
    moving body's displacement and rotation from ``m``'s own seated pose; ``deformable_unposed`` where the
    rigid seating does not converge."""
    rigid = read_model(out_dir, replace(m.load, cartilage="rigid"))
    deck.write(rigid, folder, flexion_deg=0.0)
    run = run_ccx(folder, Path(deck.CCX_FILE).stem, POSE_TIMEOUT_S)
    dat = parse_dat(folder / f"{Path(deck.CCX_FILE).stem}.dat") if run.completed else None
    refs, rots = ((dat["nodes"].get(("displacements", s), {}).get(1.0) for s in ("REFS", "ROTS")) if dat else (None, None))
    if refs is None or rots is None:
        raise KneeMeshError("deformable_unposed", "deformable cartilage starts from the rigid model's seated equilibrium, "
                            f"and the rigid model's seating did not converge ({run.reason or 'no seated pose written'}; "
                            f"{folder}): the knee can be run with rigid cartilage only.")
    return {b: (rigid.nodes[rigid.ref[b]] + refs[rigid.ref[b]] - m.nodes[m.ref[b]], rots[n])
            for b, n in rot_nodes(rigid).items()}


def saved_pose(folder: Path) -> StartPose | None:
    """The start pose a deck folder's CalculiX deck was written with (its ``model.json``), None without one."""
    pose = json.loads((Path(folder) / deck.META_FILE).read_text()).get("start_pose")
    return None if not pose else {b: (np.asarray(v["translation_mm"], float), np.asarray(v["rotation_rad"], float))
                                  for b, v in pose.items()}


def write_decks(out_dir: Path, load: LoadCase = LoadCase()) -> dict:
    """The decks of a meshed job in ``out_dir/fe``; returns what the report says of them (``review`` for a
    tibiofemoral model, with the reason).  Deformable cartilage's CalculiX deck starts from the rigid model's
    seated pose (:func:`rigid_start_pose`)."""
    m = read_model(out_dir, load)
    fe = Path(out_dir) / FE_DIR
    pose = rigid_start_pose(out_dir, m, fe / POSE_DIR) if load.cartilage == "deformable" else None
    files = deck.write(m, fe, start_pose=pose)
    reasons = tibiofemoral_reasons(m)
    return {"status": "review" if reasons else "ok", "reasons": reasons, "model": "tibiofemoral" if reasons else "knee",
            "files": [f"{FE_DIR}/{f.name}" for f in files], "nodes": len(m.nodes),
            "elements": {t: int(sum(len(p.elements) for p in m.parts.values() if p.element_type == t))
                         for t in sorted({p.element_type for p in m.parts.values()})}, "springs": len(m.springs),
            "contact_stiffness_n_mm3": m.contact_k, "seating": m.seating, "cartilage": load.cartilage,
            "flexion_deg": load.flexion_deg, "activity": load.activity, "joint_load_n": load.joint_load_n,
            "peak_load_n": load.peak_load_n if load.activity == "knee_bend" else load.joint_load_n,
            "medial_offset_mm": load.medial_offset_mm}


def run_folder(smoke: bool = False, flexion_deg: float | None = None, load: LoadCase | None = None,
               activity_load: LoadCase | None = None) -> str:
    """Where a run's deck and results lie, relative to the job folder: ``fe`` (the job's own decks), ``fe/smoke``,
    ``fe/flexion_<deg>`` or, for a load case with another activity than the decks' (``activity_load``),
    ``fe/knee_bend_<deg>_<peak>N``, the name followed by ``_<joint load>N_<quadriceps>N_<medial offset>mm_<cartilage>``
    for a load case with another model than the decks' (``load``)."""
    flexion = flexion_deg if flexion_deg is not None else (load or activity_load or LoadCase()).flexion_deg
    if smoke:
        name = SMOKE_DIR
    elif activity_load is not None and activity_load.activity == "knee_bend":
        name = f"knee_bend_{flexion:g}_{activity_load.peak_load_n:g}N"
    elif flexion_deg is not None or load is not None or activity_load is not None:
        name = f"flexion_{flexion:g}"
    else:
        return FE_DIR
    if load is not None:
        name += f"_{load.joint_load_n:g}N_{load.quadriceps_n:g}N_{load.medial_offset_mm:g}mm_{load.cartilage}"
    return f"{FE_DIR}/{name}"


def deck_load(fe: Path) -> LoadCase | None:
    """The load case of a job's decks, from their ``model.json``; None where there are no decks."""
    meta_file = Path(fe) / deck.META_FILE
    if not meta_file.exists():
        return None
    meta = json.loads(meta_file.read_text())
    return LoadCase(joint_load_n=meta["joint_load_n"], quadriceps_n=meta["quadriceps_n"], flexion_deg=meta["flexion_deg"],
                    cartilage=meta["cartilage"], activity=meta.get("activity", "flexion"),
                    peak_load_n=meta.get("peak_load_n", LoadCase.peak_load_n),
                    medial_offset_mm=(meta.get("joint_load") or {}).get("medial_offset_mm", 0.0))  # (0: decks before it)


#: What a run's model holds of its load case: another value of any needs a model of its own.
MODEL_LOAD = ("joint_load_n", "quadriceps_n", "medial_offset_mm", "cartilage")
#: What only a run's wrapper holds (the steps after the seating): another value needs a folder of its own.
WRAPPER_LOAD = ("activity", "peak_load_n")


def differs(decks: LoadCase | None, load: LoadCase | None, fields: tuple[str, ...]) -> bool:
    """Whether a run under ``load`` asks another value of any of ``fields`` than the job's decks hold:
    :data:`MODEL_LOAD` (a model of its own beside the decks: they are in the shared model and its seating)
    or :data:`WRAPPER_LOAD` (a wrapper of its own)."""
    return decks is not None and load is not None and any(getattr(load, k) != getattr(decks, k) for k in fields)


def simulate(out_dir: Path, flexion_deg: float | None = None, smoke: bool = False, timeout_s: float = 1800.0,
             load: LoadCase | None = None) -> dict:
    """Run ccx on the job's decks (writing them first if absent); ``results.json`` and ``contact.png`` land
    beside the deck that ran.  ``load``: the load case (default: the decks'); another load, quadriceps force or
    cartilage than the decks' gets a shared model of its own in its run folder (:func:`run_folder`).  Returns
    the results."""
    fe = Path(out_dir) / FE_DIR
    decks = deck_load(fe)
    if decks is None:
        write_decks(out_dir, load or LoadCase())
        decks = deck_load(fe)
    load = load or decks
    if smoke:  # a smoke run flexes from the image pose whatever the activity: a quick proof that the deck runs
        load = replace(load, activity="flexion", peak_load_n=decks.peak_load_n)
        decks = replace(decks, activity="flexion")
    own = differs(decks, load, MODEL_LOAD)
    where = run_folder(smoke, flexion_deg, load if own else None, load if differs(decks, load, WRAPPER_LOAD) else None)
    folder = Path(out_dir) / where
    if folder != fe:
        flex, step = ((SMOKE_FLEXION_DEG, SMOKE_INCREMENT_DEG) if smoke else
                      (load.flexion_deg if flexion_deg is None else flexion_deg, load.max_increment_deg))
        model = read_model(out_dir, load)
        pose = None
        if load.cartilage == "deformable":  # over the job's own model, the pose its decks start from
            pose = (None if own else saved_pose(fe)) or rigid_start_pose(out_dir, model, folder / POSE_DIR)
        deck.write(model, folder, flex, step, include=None if own else f"../{deck.MODEL_FILE}", start_pose=pose)
    meta_file = folder / deck.META_FILE
    if not meta_file.exists():
        raise KneeMeshError("deck_missing", f"{meta_file} is missing: write the decks again (kneemesh mesh).")
    meta = json.loads(meta_file.read_text())
    run = run_ccx(folder, Path(deck.CCX_FILE).stem, timeout_s,
                  DEFORMABLE_STALL_CPU_S if meta["cartilage"] == "deformable" else STALL_CPU_S)
    return {**write_results(folder, run, meta, folder / "knee_ccx.dat"), "folder": where}


def simulation_entry(results: dict, kind: str, folder: str) -> dict:
    """The report's ``simulation`` entry of a run's ``results`` (:func:`simulate`): ``kind`` smoke, full or
    a flexion, the results lying in ``folder`` (relative to the job folder).  A run stopped part-way is
    ``review`` with the flexion it reached (its increments are results), one that reached none is
    ``failed``, one completed outside physiology ``review``."""
    r = results
    last = r["increments"][-1] if r["increments"] else {}
    reasons = ([] if r["completed"] else [f"stopped at {r['reached_flexion_deg']:g} of {r['target_flexion_deg']:g} deg: "
                                          f"{r['reason']}"]) + r["physiology_reasons"]
    status = "failed" if not r["completed"] and r["reached_flexion_deg"] <= 0 else "review" if reasons else "ok"
    return {"status": status, "reasons": reasons, "kind": kind, "activity": r.get("activity", "flexion"),
            "completed": r["completed"],
            "physiological": r["physiological"], "reason": r["reason"], "solver": r["solver"],
            "solver_seconds": r["seconds"], "reached_flexion_deg": r["reached_flexion_deg"],
            "target_flexion_deg": r["target_flexion_deg"],
            "final": {k: v for k, v in last.items() if k in ("anatomical_flexion_deg", "balance_error", *CONTACTS)},
            "files": [f"{folder}/{f}" for f in (RESULTS_FILE, CONTACT_FIGURE, *results.get("pressure_maps", []),
                                                 *results.get("cartilage_fields", []))]}
