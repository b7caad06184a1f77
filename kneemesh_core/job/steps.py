"""What runs on one knee: each function is one step of a job, working in the job folder.

A step function takes a :class:`Step` (its name, the job folder, the options and, for the steps that
read it, the input file) and returns its result, which its record keeps and the report reads.  A
tissue step never raises: its failure is its report entry (a failed tissue never sinks the knee).
The stages that run these functions, and when, are declared in :mod:`.stages`.
"""

from __future__ import annotations

import dataclasses
import time
import traceback
from pathlib import Path

import numpy as np
import pyvista as pv

from kneemesh_core import __version__
from kneemesh_core.errors import KneeMeshError
from kneemesh_core.hexmesh import CartilageMesh, blend_cartilage, mesh_cartilage
from kneemesh_core.hexmesh.conform import conform_bone
from kneemesh_core.hexmesh.fidelity import FIGURES
from kneemesh_core.hexmesh.quality import boundary_crossings, summary
from kneemesh_core.io import read_label_map, read_volume, voxel_to_lps, write_image
from kneemesh_core.io.files import atomic_path
from kneemesh_core.job.options import INPUT_TYPES, JobOptions
from kneemesh_core.job.outputs import (ATTACHMENTS_FIGURE, ATTACHMENTS_FILE, JOB_FILE, LABELS_FILE, MESHES_DIR,
                                       SURFACES_DIR, WORK_DIR, bundle, load_unblended, read_json, read_step, save_mesh,
                                       save_unblended, write_json)
from kneemesh_core.job.verdict import tissue_verdict
from kneemesh_core.knee import canonicalise, describe, describe_image
from kneemesh_core.metrics.overlap import knee_overlaps
from kneemesh_core.surfaces.tissue import reconstruct_bone
from kneemesh_core.tissues import BONE_OF, BONES, CARTILAGES, LABEL, resolve_convention


@dataclasses.dataclass(frozen=True)
class Step:
    """One step of a job as its function sees it: ``name`` (``femur``, ``hex_femoral_cartilage``,
    ``anatomy``), the job folder ``out``, the job's ``options`` and, for the steps that read it, the
    job's ``input`` file."""

    name: str
    out: Path
    options: JobOptions
    input: Path | None = None


def hex_step(cartilage: str) -> str:
    """The name of the step that meshes a cartilage before the cartilage's own step blends it."""
    return f"hex_{cartilage}"


def cartilage_of(hex_step_name: str) -> str:
    """The cartilage a :func:`hex_step` meshes."""
    return hex_step_name.removeprefix("hex_")


def warm_up() -> None:
    """Load what the steps would load on first use: the column optimiser's compiled kernels and
    the attachments figure's matplotlib (together about 0.7 s of the first steps a worker runs).
    A job's own pool of workers does it while the job's input is read (:func:`.local.run`)."""
    from kneemesh_core.anatomy import figure
    from kneemesh_core.hexmesh import optimize

    optimize.load_kernels()
    figure.load()


def ingest(step: Step) -> dict:
    """Validate the input and write canonical labels and ``job.json``.

    Nothing is written unless the input is valid.
    """
    options = step.options
    options.tissues()
    if options.input_type not in INPUT_TYPES:
        raise KneeMeshError("bad_option", f"input type {options.input_type!r}: expected one of {', '.join(INPUT_TYPES)}.")
    if step.input is None:
        raise KneeMeshError("bad_option", "the ingest step needs the input file.")
    knee = None
    if options.input_type == "image":  # checked here, segmented by the segment step
        from kneemesh_core.segmentation.infer import SegmentationModel

        vol = read_volume(step.input)
        SegmentationModel.load(options.model)  # a missing or foreign model fails here, before anything is queued
        description = describe_image(vol.image, vol.source)
    else:
        knee = canonicalise(read_label_map(step.input), resolve_convention(options.preset, options.labels), options.side,
                            require_knee=True)
        description = describe(knee)
    step.out.mkdir(parents=True, exist_ok=True)
    if knee is not None:
        write_image(knee.labels, step.out / LABELS_FILE)
    write_json(step.out / JOB_FILE, {"kneemesh_version": __version__, "input": description, "options": options.to_dict()})
    return {"status": "ok"}


def segment(step: Step) -> dict:
    """Image inputs: segment the image into canonical labels ``labels.nrrd``; ``job.json`` gains the
    knee's description and the segmentation's facts.  Returns the report's ``segmentation`` entry:
    ``review`` with the reasons when the labels are not a plausible knee
    (:mod:`kneemesh_core.segmentation.plausibility`)."""
    from kneemesh_core.segmentation.infer import SegmentationModel, segment as run_network
    from kneemesh_core.segmentation.plausibility import check, figures

    if step.input is None:
        raise KneeMeshError("bad_option", "the segment step needs the input image.")
    model = SegmentationModel.load(step.options.model)
    result = run_network(read_volume(step.input), model, side=step.options.side)
    write_image(result.knee.labels, step.out / LABELS_FILE)
    job = read_json(step.out / JOB_FILE)
    facts = {"model": model.path.name, "model_version": model.meta.get("version"), "seconds": result.seconds,
             "image": job["input"]}
    job["input"] = {**describe(result.knee), "preset": "segmented", "segmentation": facts}
    write_json(step.out / JOB_FILE, job)
    plausibility = figures(result.knee.labels)
    status, reasons = check(plausibility)
    if status != "ok" and not step.options.force:
        raise KneeMeshError("implausible_segmentation", "the segmentation is not a plausible knee: " + "; ".join(reasons)
                            + f". Its labels are in {LABELS_FILE}; nothing was meshed. Force the job (--force, the API: "
                            "force=true) to mesh them anyway (the knee is then review).")
    return {"status": status, "reasons": reasons, "side": result.knee.side, "seconds": result.seconds["total"],
            "tissues_ml": job["input"]["tissues"], "plausibility": plausibility}


def _absent(out: Path, tissue: str) -> dict | None:
    """The report entry of a tissue the input does not label (``review``: nothing to mesh, said so; the
    knee's other tissues, its anatomy and a tibiofemoral model go on without it), or None."""
    if read_json(out / JOB_FILE)["input"]["tissues"].get(tissue, 0.0) > 0:
        return None
    return {"status": "review", "absent": True, "reasons": [f"not labelled in the input: no {tissue.replace('_', ' ')} "
                                                             "to mesh"], "seconds": 0.0}


def mesh_bone(step: Step) -> dict:
    """A bone's closed shell (``meshes/<bone>.vtp``, and ``.stl`` on request); returns its report entry,
    never raises."""
    out, tissue, opts = step.out, step.name, step.options
    if (absent := _absent(out, tissue)) is not None:
        return absent

    def work() -> dict:
        labels = read_label_map(out / LABELS_FILE).image
        (out / MESHES_DIR).mkdir(exist_ok=True)
        mesh, facts = reconstruct_bone(labels, tissue, opts.surface)
        files = [out / MESHES_DIR / f"{tissue}.vtp"] + ([out / MESHES_DIR / f"{tissue}.stl"] if opts.stl else [])
        for f in files:
            save_mesh(mesh, f)
        entry = {"status": "ok", **facts}
        entry["status"], entry["reasons"] = tissue_verdict(True, entry)
        entry["files"] = [str(f.relative_to(out)) for f in files]
        return entry

    return _guarded(work)  # a failed tissue never sinks the rest of the knee


def hex_cartilage(step: Step) -> dict:
    """The all-hex mesh of one cartilage before its blend (:func:`kneemesh_core.hexmesh.mesh_cartilage`):
    it needs only the labels, so it runs beside the bones, and the cartilage's own step blends it
    onto its bone.  Writes the reconstructed surface it was meshed from (``surfaces/<cartilage>.vtp``)
    and the unblended mesh (``work/<cartilage>.npz``); returns what the attempts gave, or the
    cartilage's failed entry (never raises)."""
    out, tissue = step.out, cartilage_of(step.name)
    if (absent := _absent(out, tissue)) is not None:
        return absent

    def work() -> dict:
        cm = mesh_cartilage(read_label_map(out / LABELS_FILE).image, tissue, step.options.hex)
        for sub in (SURFACES_DIR, WORK_DIR):
            (out / sub).mkdir(exist_ok=True)
        save_mesh(cm.surface, out / SURFACES_DIR / f"{tissue}.vtp")
        save_unblended(cm, out / WORK_DIR / f"{tissue}.npz")
        return {"status": "done", **{k: cm.facts[k] for k in ("gate_passed", "usable", "fidelity_passed", "attempts")}}

    return _guarded(work)


def finish_cartilage(step: Step) -> dict:
    """A cartilage meshed by its :func:`hex_cartilage` step, blended and fused onto the bone mesh its
    bone's step wrote, kept as ``meshes/<cartilage>.vtu`` (``.rejected.vtu`` when no attempt is usable
    for finite elements); returns its report entry, never raises."""
    out, tissue, opts = step.out, step.name, step.options
    folder = out / MESHES_DIR
    meshed = read_step(out, hex_step(tissue))
    if meshed is None or meshed["state"] != "done":
        return {"status": "failed", "code": "internal", "reason": f"the step {hex_step(tissue)} has not run.", "seconds": 0.0}
    if meshed["result"]["status"] == "failed" or meshed["result"].get("absent"):  # no mesh at all: its entry says why
        return meshed["result"]

    def work() -> dict:
        surface_file = out / SURFACES_DIR / f"{tissue}.vtp"
        cm = load_unblended(out / WORK_DIR / f"{tissue}.npz", pv.read(surface_file))
        ships = cm.facts["gate_passed"] or cm.facts["usable"]  # short of the gate but usable: for review
        if ships and opts.blend is not None:  # the bone stage ran first: fuse onto the bone mesh it wrote
            bone_file = folder / f"{BONE_OF[tissue]}.vtp"
            cm = blend_cartilage(cm, pv.read(bone_file) if bone_file.exists() else None, opts.blend)
        facts = shipped_figures(cm)
        files = [folder / f"{tissue}{'' if ships else '.rejected'}.vtu", surface_file]
        folder.mkdir(exist_ok=True)
        save_mesh(cm.grid(), files[0])
        entry = {"status": "ok" if ships else "failed", **facts}
        entry["status"], entry["reasons"] = tissue_verdict(False, entry) if ships else ("failed", [])
        if not ships:
            entry["code"] = "quality_gate"
            entry["reason"] = (f"no usable mesh after {len(facts['attempts'])} attempts: min scaled Jacobian "
                               f"{facts['min_scaled_jacobian']}, {facts['frac_sj_below_0_5']:.3%} below 0.5, "
                               f"{facts['inverted']} inverted, {facts['frac_edge_ratio_above_6']:.4%} with edge ratio > 6, "
                               f"{facts['self_intersections']} boundary edges crossing; best mesh kept as {files[0].name}")
        entry["files"] = [str(f.relative_to(out)) for f in files]
        return entry

    entry = _guarded(work)
    entry["seconds"] = round(entry["seconds"] + meshed["result"]["seconds"], 3)  # its meshing's and its blend's
    return entry


def shipped_figures(cm: CartilageMesh) -> dict:
    """A cartilage's report figures with the headline quality and fidelity of the mesh that ships
    (blended where the blend was applied); the figures the gate and the fidelity targets judged,
    before blending, move under ``gate``.  ``fidelity_passed`` is then the mesh before the blend
    meeting every fidelity target and, where the blend was applied, the blended file meeting the
    coverage and deviation targets beyond the rim the blend reshapes (``blend.beyond_rim``)."""
    facts = dict(cm.facts)
    quality_keys = ("n_elements", "min_scaled_jacobian", "frac_sj_below_0_5", "inverted", "collapsed", "max_edge_ratio",
                    "frac_edge_ratio_above_6", "shortest_edge_mm", "sj_by_ring", "self_intersections")
    facts["gate"] = {k: facts[k] for k in (*quality_keys, "gate_passed", *FIGURES, "fidelity_passed") if k in facts}
    blend = facts.get("blend", {})
    shipped = summary(cm.quality, cm.mesh.ring)
    shipped["self_intersections"] = (blend["self_intersections"] if blend.get("applied")
                                     else boundary_crossings(cm.mesh.points, cm.mesh.hexes))
    if blend.get("applied") and "fidelity" in blend:
        shipped.update({k: blend["fidelity"][k] for k in FIGURES})
        shipped["fidelity_passed"] = bool(facts.get("fidelity_passed") and blend["beyond_rim"]["passed"])
    facts.update(shipped)
    return facts


def conform_bones(step: Step) -> dict:
    """Each bone surface gives way where the accepted meshes of its cartilages still lie inside it
    (:func:`kneemesh_core.hexmesh.conform.conform_bone`); the bone's files are rewritten only where
    it changed.  Returns what was done per bone (:func:`fold_conformed` puts it in the tissues'
    report entries).  Idempotent: a second run finds no cartilage inside and changes nothing."""
    folder = step.out / MESHES_DIR
    done = {}
    for bone in BONES:
        files = [folder / f"{bone}.vtp"] + ([folder / f"{bone}.stl"] if step.options.stl else [])
        grids = {t: pv.read(folder / f"{t}.vtu") for t in CARTILAGES
                 if BONE_OF[t] == bone and (folder / f"{t}.vtu").exists()}
        if not files[0].exists() or not grids:
            continue
        try:
            surface, facts = conform_bone(pv.read(files[0]), grids)
        except Exception as exc:  # the bone stays as meshed; the knee goes on
            done[bone] = {"applied": False, "reason": f"{type(exc).__name__}: {exc}", "cartilages": {}}
            continue
        if facts["applied"]:
            for f in files:
                save_mesh(surface, f)
        done[bone] = facts
    return done


def fold_conformed(tissues: dict[str, dict], conformed: dict) -> None:
    """What :func:`conform_bones` did, in the tissues' report entries: each bone's entry gains
    ``conformed``, each of its cartilages' ``bone_conform`` and a verdict that judges it."""
    for bone, facts in conformed.items():
        if bone in tissues:
            tissues[bone]["conformed"] = {k: v for k, v in facts.items() if k != "cartilages"}
        for t, f in facts["cartilages"].items():
            if t in tissues:
                tissues[t]["bone_conform"] = f
                tissues[t]["status"], tissues[t]["reasons"] = tissue_verdict(False, tissues[t])


def place_anatomy(step: Step) -> dict:
    """The knee's frames, Grood-Suntay angles and ligament attachment sites on the job's bone meshes
    (:mod:`kneemesh_core.anatomy`): ``attachments.json`` and ``attachments.png``.  Returns the
    report's ``anatomy`` entry; never raises (a failure is the entry, and the meshes stay)."""
    import SimpleITK as sitk

    from kneemesh_core.anatomy.attachments import place
    from kneemesh_core.anatomy.figure import draw

    out = step.out

    def work() -> dict:
        knee = read_json(out / JOB_FILE)["input"]
        side, name = knee["side"], Path(knee["source"]).name  # the input's name: a service's job folder is "out"
        bones = {b: pv.read(out / MESHES_DIR / f"{b}.vtp") for b in BONES if (out / MESHES_DIR / f"{b}.vtp").exists()}
        labels = read_label_map(out / LABELS_FILE).image
        arr = sitk.GetArrayViewFromImage(labels)
        plates = tuple(voxel_to_lps(labels, np.argwhere(arr == LABEL[t])[:, ::-1])
                       for t in ("medial_tibial_cartilage", "lateral_tibial_cartilage"))
        anatomy = place(bones, side, plates)
        if anatomy.document:
            write_json(out / ATTACHMENTS_FILE, anatomy.document)
            with atomic_path(out / ATTACHMENTS_FIGURE) as tmp:
                draw(anatomy.document, anatomy.bones, anatomy.frames, Path(tmp), name)
            anatomy.report["files"] = [ATTACHMENTS_FILE, ATTACHMENTS_FIGURE]
        return anatomy.report

    return _guarded(work)


def measure_overlaps(step: Step) -> dict:
    """Where the job's final meshes overlap (:func:`kneemesh_core.metrics.overlap.knee_overlaps`): the
    report's ``overlaps`` entry; never raises (a failure is the entry)."""
    return _guarded(lambda: knee_overlaps(step.out / MESHES_DIR))


def write_decks(step: Step) -> dict:
    """The Abaqus and CalculiX decks of the knee in ``fe/`` (:mod:`kneemesh_core.fe`), under the job's load
    case; never raises."""
    from kneemesh_core.fe.run import write_decks as write

    return _guarded(lambda: write(step.out, step.options.load))


def run_simulation(step: Step) -> dict:
    """CalculiX on the decks (smoke: to 15 deg; full: the decks' activity, to 90 deg); ``fe/results.json`` and
    ``fe/contact.png``.  Never raises: a failed simulation is its entry, the meshes and decks stay."""
    from kneemesh_core.fe.run import simulate, simulation_entry

    opts = step.options
    smoke = opts.simulate == "smoke"

    def run() -> dict:
        r = simulate(step.out, smoke=smoke, load=opts.load)
        return simulation_entry(r, opts.simulate, r["folder"])

    return _guarded(run)


def bundle_outputs(step: Step) -> dict:
    """Zip the outputs (``bundle.zip``) and list every artifact with its SHA-256 (``artifacts.json``)."""
    return {"artifacts": len(bundle(step.out))}


def _guarded(work) -> dict:
    """Run ``work()`` for a step whose failure must not sink the knee (a tissue, the anatomy, the
    decks, the simulation): its report entry, or a failed entry with the reason; with its seconds."""
    t0 = time.perf_counter()
    try:
        entry = work()
    except KneeMeshError as exc:
        entry = {"status": "failed", "reason": exc.message, "code": exc.code}
    except Exception as exc:  # whatever breaks, the rest of the knee goes on
        entry = {"status": "failed", "reason": f"{type(exc).__name__}: {exc}", "code": "internal",
                 "traceback": traceback.format_exc(limit=5)}
    entry["seconds"] = round(time.perf_counter() - t0, 3)
    return entry
