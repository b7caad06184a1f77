"""CalculiX results to ``results.json`` and ``contact.png``.

The .dat file holds, per converged increment: the contact statistics of each pair (total force,
area, normal force), the contact stress at each slave integration point, and the displacements of
the reference, rotation and ligament-end nodes.  Forces in the ligaments are not printed by ccx
for SPRINGA elements; they follow from the ends' positions and the fibres' law.  Hand-written: no
package reads ccx 2.20's .dat tables (ccx2paraview reads the .frd only).
"""

from __future__ import annotations

import re
from collections import defaultdict
from pathlib import Path

import numpy as np

from kneemesh_core.fe.cartilage_fields import read_frd, summaries, write_fields
from kneemesh_core.fe.model import deck_to_lps
from kneemesh_core.fe.physics import (MAX_BALANCE_ERROR, MAX_PRELOAD_STRAIN, MIN_PLATE_SHARE,
                                      MIN_PLATES_AREA_MM2, ligament_force, plate_peak_limit_mpa)
from kneemesh_core.fe.pressure_map import element_pressure, write_maps
from kneemesh_core.io.files import atomic_write_json

RESULTS_FILE, CONTACT_FIGURE = "results.json", "contact.png"
#: The contacts an increment reports (the surrogates' where the model has them): the tibiofemoral ones
#: (the plates and the meniscus surrogates), then the patella's on the femur (its cartilage and the
#: prefemoral sheet).
TIBIOFEMORAL = ("medial", "lateral", "medial_meniscus", "lateral_meniscus")
CONTACTS = (*TIBIOFEMORAL, "patellofemoral")
_STATS = re.compile(r"^\s*statistics for slave set (\S+), master set (\S+) and time\s+(\S+)")
_TABLE = re.compile(r"^\s*(displacements|forces|total force|contact stress)\b.*?(?:for set (\S+)|for all contact elements)\s+and time\s+(\S+)")


def parse_dat(path: Path, stopped: bool = False) -> dict:
    """{"contact": {time: {slave: {force, moment, centre, normal, area, normal_force}}}, "stress": {time:
    [(element, pressure)]},
    "nodes": {(table, set): {time: {node or "total": (3,)}}}}.  ``stopped``: ccx did not finish (a
    time limit, a kill), so the last increment in the file may be cut short anywhere, even inside a
    number: it is dropped, as is a block found cut short in any file."""
    contact: dict = defaultdict(dict)
    stress: dict = defaultdict(list)
    nodes: dict = defaultdict(lambda: defaultdict(dict))
    lines = Path(path).read_text().splitlines()
    i, current, cut_at = 0, None, None
    while i < len(lines):
        line = lines[i]
        m = _STATS.match(line)
        if m:
            numbers = []
            j = i + 1
            while j < len(lines) and len(numbers) < 4:
                parts = lines[j].split()
                if parts and all(re.fullmatch(r"[-+0-9.Ee]+|NaN|nan|-?Infinity|-?inf", p) for p in parts):
                    numbers.append([float(p) for p in parts])
                j += 1
            if len(numbers) < 4 or len(numbers[0]) < 6 or len(numbers[1]) < 6 or len(numbers[3]) < 2:
                cut_at = float(m.group(3))
                break
            force, centre, _, anf = numbers
            contact[float(m.group(3))][m.group(1)] = {"force": force[:3], "moment": force[3:6], "centre": centre[:3],
                                                      "normal": centre[3:6], "area": anf[0], "normal_force": anf[1]}
            i, current = j, None
            continue
        m = _TABLE.match(line)
        if m:
            current = (m.group(1), m.group(2), float(m.group(3)))
        elif current is not None and line.strip():
            parts = line.split()
            try:
                if current[0] == "contact stress":
                    stress[current[2]].append((int(parts[0]), float(parts[2])))
                elif current[0] == "total force":  # a set's summed reaction: no node id
                    nodes[(current[0], current[1])][current[2]]["total"] = np.array([float(p) for p in parts[:3]], float)
                else:
                    row = np.array([float(p) for p in parts[1:4]])
                    if row.shape != (3,):
                        raise ValueError(line)
                    nodes[(current[0], current[1])][current[2]][int(parts[0])] = row
            except (ValueError, IndexError):  # a line cut short
                cut_at = current[2]
                break
        i += 1
    times = [*contact, *stress, *(t for table in nodes.values() for t in table)]
    drop = {cut_at} if cut_at is not None else set()  # increments that may be incomplete
    if stopped and times:
        drop.add(max(times))
    for t in drop:
        contact.pop(t, None)
        stress.pop(t, None)
        for table in nodes.values():
            table.pop(t, None)
    return {"contact": dict(contact), "stress": dict(stress), "nodes": nodes}


def centre_of_pressure(force: np.ndarray, moment: np.ndarray, centre: np.ndarray, normal: np.ndarray) -> np.ndarray | None:
    """Where a contact's resultant acts (3,), mm: its line of action, from the total ``force`` (3,), N, and
    its ``moment`` about the origin (3,), N mm (ccx's CF statistics), met by the plane through the contact
    area's ``centre`` (3,), mm, normal to its mean ``normal`` (3,): the pressure-weighted centroid of the
    contact where the pressure acts along the normal.  None without contact (ccx prints NaN)."""
    f, mo, c, n = (np.asarray(v, float) for v in (force, moment, centre, normal))
    if not (np.isfinite(f).all() and np.isfinite(mo).all() and np.isfinite(c).all() and np.isfinite(n).all()):
        return None
    ff = float(f @ f)
    if ff <= 0.0 or abs(f @ n) < 1e-9 * np.sqrt(ff):
        return None
    nearest = np.cross(f, mo) / ff  # the line's point nearest the origin
    return nearest + f * float((c - nearest) @ n) / float(f @ n)


def located(contact: dict, frame: dict, pair: str) -> dict:
    """A contact's centre of pressure (:func:`centre_of_pressure`, from the deck frame) in the input's LPS
    frame (``cop_lps_mm``) and, for a tibiofemoral contact, in the tibial frame (``cop_tibia_mm``: lateral,
    anterior and proximal of the tibial frame's origin, mm; ``frame["tibia"]``, from the anatomy);
    None without contact."""
    cop = centre_of_pressure(*(contact.get(k, [np.nan] * 3) for k in ("force", "moment", "centre", "normal")))
    lps = None if cop is None else deck_to_lps(frame, cop)
    out = {"cop_lps_mm": None if lps is None else np.round(lps, 3).tolist()}
    if pair in TIBIOFEMORAL and "tibia" in frame:
        tibia = frame["tibia"]
        out["cop_tibia_mm"] = None if lps is None else np.round(
            [(lps - tibia["origin_lps_mm"]) @ np.asarray(tibia["axes_lps"][a]) for a in ("lateral", "anterior", "proximal")],
            3).tolist()
    return out


#: The total time (ccx's) at which the seating step ends with the whole joint load on, where ``model.json``
#: does not say (``loaded_at``: decks before deformable cartilage's start pose): the increments from there on
#: are loaded; those before are ccx's cut-back seating increments, not trusted.
LOADED_AT = 1.0


def loaded(increments: list[dict]) -> list[dict]:
    """The increments of a run with the whole joint load on and the bodies free (``loaded``; results before
    it was written: ``time`` >= :data:`LOADED_AT`)."""
    return [r for r in increments if r.get("loaded", r["time"] >= LOADED_AT)]


def joint_load_at(meta: dict, t: float) -> float:
    """The joint load (N) at ccx's total time ``t``: whole from the first step on, then as the run's legs
    take it (``joint_load_schedule``, :func:`kneemesh_core.fe.deck.load_schedule`; runs before it: held)."""
    schedule = np.asarray(meta.get("joint_load_schedule") or [[0.0, meta["joint_load_n"]]], float)
    return float(np.interp(t, schedule[:, 0], schedule[:, 1]))


def summarise(dat: dict, meta: dict) -> list[dict]:
    """One entry per converged increment: flexion, per-pair contact, ligament forces by bundle, and
    the femur's force balance."""
    pairs = meta["pairs"]  # name -> slave surface name
    elements = {name: (lo, hi) for name, (lo, hi) in meta["slave_elements"].items()}
    refs = dat["nodes"].get(("displacements", "REFS"), {})
    rots = dat["nodes"].get(("displacements", "ROTS"), {})
    ends = dat["nodes"].get(("displacements", "LIGAMENT_ENDS"), {})
    out = []
    image = meta["frame"].get("image_flexion_deg")
    for t in sorted(dat["contact"]):
        flexion = round(float(np.degrees(rots[t][meta["rot"]["femur"]][0])), 3) if t in rots else None
        load_n = joint_load_at(meta, t)
        row: dict = {"time": t, "loaded": t >= meta.get("loaded_at", LOADED_AT), "flexion_deg": flexion,
                     "anatomical_flexion_deg": None if flexion is None or image is None else round(image + flexion, 3),
                     "joint_load_n": round(load_n, 3)}
        femur_force = load_n * np.asarray(meta["joint_load_direction"])
        pressures = dat["stress"].get(t, [])
        for name, slave in pairs.items():
            c = dat["contact"][t].get(slave, {"force": [0, 0, 0], "area": 0.0, "normal_force": 0.0})
            force = -c["normal_force"] if np.isfinite(c["normal_force"]) else 0.0
            area = c["area"] if np.isfinite(c["area"]) else 0.0
            lo, hi = elements[name]
            peak = float(element_pressure(pressures, lo, hi - lo + 1).max())
            row[name] = {"force_n": round(force, 3), "area_mm2": round(area, 3),
                         "mean_pressure_mpa": round(force / area, 4) if area > 0 else 0.0,
                         "peak_pressure_mpa": round(max(peak, 0.0), 4), **located(c, meta["frame"], name)}
            femur_force -= np.nan_to_num(np.asarray(c["force"], float))  # the femur feels the opposite
        bundles: dict = defaultdict(float)
        if t in ends:
            u = ends[t]
            for f in meta["fibres"]:
                a, b = f["nodes"]
                pa, pb = np.asarray(f["start"][0]) + u[a], np.asarray(f["start"][1]) + u[b]
                length = float(np.linalg.norm(pa - pb)) + f.get("beyond", 0.0)
                force = float(ligament_force(f["k"], length / f["slack"] - 1.0))
                bundles[f["bundle"]] += force
                if f["femur_end"] is not None and force > 0:  # pulls the femur towards the other end
                    fe, other = (pa, pb) if f["femur_end"] == 0 else (pb, pa)
                    femur_force += force * (other - fe) / np.linalg.norm(other - fe)
            q = meta["quadriceps"]  # pulls its origin on the femur towards the patella
            if q is not None:
                pa, pb = (np.asarray(p) + u[n] for p, n in zip(q["start"], q["nodes"]))
                stretch = float(np.linalg.norm(pa - pb) - np.linalg.norm(np.subtract(*q["start"])))
                law = np.asarray(q["law"])
                femur_force += float(np.interp(stretch, law[:, 1], law[:, 0])) * (pa - pb) / np.linalg.norm(pa - pb)
        if t in refs:
            femur_force -= np.asarray(meta["femur_springs_n_mm"]) * refs[t][meta["ref"]["femur"]]
            if t in ends and meta["patella_anchor"] is not None:  # the patella's springs pull their anchor on the femur
                femur_force += np.asarray(meta["patella_springs_n_mm"]) * (refs[t][meta["ref"]["patella"]]
                                                                           - ends[t][meta["patella_anchor"]])
        row["ligaments_n"] = {b: round(v, 2) for b, v in sorted(bundles.items())}
        row["femur_force_balance_n"] = np.round(femur_force, 3).tolist()
        row["balance_error"] = round(float(np.linalg.norm(femur_force) / load_n), 4)
        out.append(row)
    return out


def tibiofemoral_n(row: dict) -> float:
    """The tibiofemoral contact force of an increment (N): the plates and the meniscus surrogates."""
    return sum(row[k]["force_n"] for k in TIBIOFEMORAL if k in row)


def physical(increment: dict) -> bool:
    """Whether a loaded increment is physics: ccx can 'converge' on an increment whose femur has lost
    the tibia (no tibiofemoral contact under the joint load) and whose forces do not balance."""
    return increment["balance_error"] <= MAX_BALANCE_ERROR and tibiofemoral_n(increment) > 0


def first_invalid(increments: list[dict]) -> str | None:
    """Why the run stops being physics (:func:`physical`), or None.  Only the loaded increments are
    judged: ccx's cut-back increments of the seating step are not trusted."""
    for r in loaded(increments):
        if not physical(r):
            tf = tibiofemoral_n(r)
            return (f"at {r['flexion_deg']:.1f} deg of flexion the femur's forces no longer balance the joint load "
                    f"(error {r['balance_error']:.1%}, tibiofemoral contact {tf:.0f} N)"
                    + (": it lost the tibia" if tf <= 0 else ""))
    return None


def plate_peak(row: dict, plate: str) -> float:
    """A tibial plate's peak pressure in an increment, MPa: its contact's, or with deformable cartilage its
    cartilage's largest compression (:mod:`.cartilage_fields`: there the contact's peak at single integration
    points runs far above the pressure the tissue carries)."""
    cartilage = row.get("cartilage", {}).get(f"{plate}_tibial_cartilage")
    return cartilage["peak_compressive_stress_mpa"] if cartilage else row[plate]["peak_pressure_mpa"]


def plates_peak(increments: list[dict]) -> tuple[float, str, float]:
    """The tibial plates' peak pressure (:func:`plate_peak`) over a run's loaded increments (:func:`loaded`):
    (MPa, plate, flexion deg); (0, "", 0) before the joint load is on."""
    return max(((plate_peak(r, k), k, r["flexion_deg"] or 0.0) for r in loaded(increments)
                for k in ("medial", "lateral")), default=(0.0, "", 0.0))


def physiology(increments: list[dict], load_n: float) -> list[str]:
    """Where a run's loaded increments (:func:`loaded`) leave physiology, one reason each; empty when
    within every target."""
    on = loaded(increments)
    if not on:
        return []
    out = []
    over = [(plate_peak(r, k) / plate_peak_limit_mpa(r.get("joint_load_n", load_n)), plate_peak(r, k), k, r)
            for r in on for k in ("medial", "lateral")]
    ratio, peak, side, r = max(over, key=lambda o: o[0])
    if ratio > 1.0:
        what = "contact pressure" if not on[0].get("cartilage") else "cartilage compression"
        load = r.get("joint_load_n", load_n)
        out.append(f"the tibial plates' peak {what} reaches {peak:.1f} MPa ({side}, at {r['flexion_deg'] or 0:.0f} deg "
                   f"under {load:.0f} N; physiological: below {plate_peak_limit_mpa(load):.3g} MPa)")
    first = on[0]
    for k in ("medial", "lateral"):
        if first[k]["force_n"] < MIN_PLATE_SHARE * load_n:
            out.append(f"in extension the {k} plate carries {first[k]['force_n']:.0f} N of the {load_n:g} N joint load "
                       f"(physiological: at least {MIN_PLATE_SHARE:.0%})")
    area = first["medial"]["area_mm2"] + first["lateral"]["area_mm2"]
    if area < MIN_PLATES_AREA_MM2:
        out.append(f"in extension the plates touch over {area:.0f} mm^2 (physiological: at least {MIN_PLATES_AREA_MM2:g} mm^2)")
    return out


def flexion_key(meta: dict) -> str:
    """The flexion a run's target means: from the image pose (``flexion_deg``), or for the knee bend, which starts
    at anatomical extension, anatomical (``anatomical_flexion_deg``)."""
    return "anatomical_flexion_deg" if meta.get("activity") == "knee_bend" else "flexion_deg"


def activity_start(meta: dict) -> float:
    """ccx's total time at which a run's flexion counts towards its target: from the start, or for the knee bend
    once it has come to anatomical extension (the end of the leg before its bend: ``joint_load_schedule`` holds
    the load at the end of each leg, :func:`kneemesh_core.fe.physics.legs` ending with the bend and the way back);
    before it the knee stands in the image pose, flexed by an angle that is not the bend's."""
    schedule = meta.get("joint_load_schedule") or []
    return schedule[-3][0] if meta.get("activity") == "knee_bend" and len(schedule) >= 3 else 0.0


def write_results(folder: Path, run, meta: dict, dat_path: Path) -> dict:
    """``results.json`` (and ``contact.png``, and the pressure maps of :mod:`.pressure_map`) in ``folder``
    from a run and its .dat file.  ``completed``
    needs ccx to finish and every loaded increment to be physics (:func:`first_invalid`);
    ``reached_flexion_deg`` is the last trusted increment's flexion; ``physiological`` whether the
    trusted increments meet the targets of :func:`physiology` (``physiology_reasons`` when not)."""
    dat = parse_dat(dat_path, stopped=not run.completed) if dat_path.exists() else None
    increments = summarise(dat, meta) if dat else []
    invalid = first_invalid(increments)
    cut = next((i for i, r in enumerate(increments) if r["loaded"] and not physical(r)), len(increments))
    trusted = increments[:cut]
    key, start = flexion_key(meta), activity_start(meta)
    reached = max((r[key] or 0.0 for r in trusted if r["time"] >= start), default=0.0)
    completed = run.completed and invalid is None
    reason = run.reason or invalid
    seat = meta["seating"]
    if not completed and seat.get("preload_strain", 0.0) > MAX_PRELOAD_STRAIN:
        reason = (f"{reason}; the seated femur sank {seat['preload_depth_mm']} mm into the cartilage "
                  f"({seat['preload_strain']:.0%} of the tibiofemoral layers' thickness) before they carried the joint load: "
                  "they meet over a small area, where bone would touch bone through denuded or unmeshed cartilage, "
                  "which the model leaves out")
    fields = _cartilage(folder, meta, increments, loaded(trusted)) if increments else []
    off_physiology = physiology(trusted, meta["joint_load_n"])
    result = {"solver": run.version, "completed": completed, "reason": reason, "seconds": round(run.seconds, 2),
              "physiological": not off_physiology, "physiology_reasons": off_physiology,
              "applied_load_n": meta["joint_load_n"], "quadriceps_n": meta["quadriceps_n"],
              "activity": meta.get("activity", "flexion"),
              "peak_load_n": max(load for _, load in meta.get("joint_load_schedule") or [[0.0, meta["joint_load_n"]]]),
              "joint_load": meta.get("joint_load"),
              "target_flexion_deg": meta["flexion_deg"], "reached_flexion_deg": round(reached, 3),
              "contact_stiffness_n_mm3": meta["contact_k"], "seating": meta["seating"],
              "pressure_maps": write_maps(folder, meta, dat["stress"], loaded(trusted)) if dat else [],
              "cartilage_fields": fields, "increments": increments}
    atomic_write_json(folder / RESULTS_FILE, result, indent=1)
    if increments:
        plot(result, folder / CONTACT_FIGURE)
    return result


def _cartilage(folder: Path, meta: dict, increments: list[dict], trusted: list[dict]) -> list[str]:
    """Deformable cartilage's stress and strain (:mod:`.cartilage_fields`) from the run's ``.frd``: each
    increment's ``cartilage`` peaks (in place) and the fields of the ``trusted`` loaded increments as
    ``cartilage_<tissue>.vtu``; returns the files written (none where the cartilage is rigid)."""
    parts, frd_path = meta.get("deformable_elements") or {}, folder / "knee_ccx.frd"
    if not parts or not frd_path.exists():
        return []
    frd = read_frd(frd_path)
    times = np.array([s["time"] for s in frd["steps"]], float)

    def frd_time(t: float) -> float | None:  # the .dat prints times to 7 digits, the .frd to 10
        near = np.flatnonzero(np.abs(times - t) < 1e-5)
        return float(times[near[0]]) if len(near) else None

    peaks = summaries(frd, parts)
    for row in increments:
        if frd_time(row["time"]) in peaks:
            row["cartilage"] = peaks[frd_time(row["time"])]
    return write_fields(folder, frd, parts, [{**r, "time": frd_time(r["time"])} for r in trusted],
                        lambda p: deck_to_lps(meta["frame"], p))


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    along = flexion_key(result)
    inc = [r for r in loaded(result["increments"]) if r[along] is not None]
    x = [r[along] for r in inc]
    tissues = sorted({t for r in inc for t in r.get("cartilage", {})})  # deformable cartilage's own panels
    fig, axs = plt.subplots(3 if tissues else 2, 2, figsize=(10, 10.5 if tissues else 7), dpi=80)
    for name, style in zip(CONTACTS, ("-o", "-s", ":o", ":s", "-^")):
        if not inc or name not in inc[0]:
            continue
        for ax, key, label in ((axs[0, 0], "force_n", "contact force, N"), (axs[0, 1], "area_mm2", "contact area, mm^2"),
                               (axs[1, 0], "peak_pressure_mpa", "peak (solid) and mean (dashed) pressure, MPa")):
            ax.plot(x, [r[name][key] for r in inc], style, ms=3, label=name)
            ax.set_ylabel(label)
        axs[1, 0].plot(x, [r[name]["mean_pressure_mpa"] for r in inc], "--", color=axs[1, 0].lines[-1].get_color())
    for bundle in sorted({b for r in inc for b in r["ligaments_n"]}):
        axs[1, 1].plot(x, [r["ligaments_n"].get(bundle, 0.0) for r in inc], label=bundle)
    axs[1, 1].set_ylabel("ligament force, N")
    for tissue in tissues:
        at = [r for r in inc if tissue in r.get("cartilage", {})]
        peaks = [r["cartilage"][tissue] for r in at]
        axs[2, 0].plot([r[along] for r in at], [p["peak_compressive_stress_mpa"] for p in peaks], "-o", ms=3,
                       label=tissue)
        axs[2, 0].plot([r[along] for r in at], [p["peak_von_mises_mpa"] for p in peaks], "--",
                       color=axs[2, 0].lines[-1].get_color())
        axs[2, 1].plot([r[along] for r in at], [p["peak_compressive_strain"] for p in peaks], "-o", ms=3, label=tissue)
        axs[2, 1].plot([r[along] for r in at], [p["peak_shear_strain"] for p in peaks], "--",
                       color=axs[2, 1].lines[-1].get_color())
    if tissues:
        axs[2, 0].set_ylabel("cartilage: peak compressive (solid)\nand von Mises (dashed) stress, MPa")
        axs[2, 1].set_ylabel("cartilage: peak compressive (solid)\nand shear (dashed) strain")
        axs[2, 0].legend(fontsize=7)
    axs[0, 0].legend(fontsize=8)
    axs[1, 1].legend(fontsize=6, ncol=2)
    for ax in axs.ravel():
        ax.set_xlabel("anatomical flexion, deg" if along != "flexion_deg" else "flexion from the image pose, deg")
        ax.grid(alpha=0.3)
    fig.suptitle(f"{result['solver']}: {'completed' if result['completed'] else 'stopped: ' + str(result['reason'])}; "
                 f"joint load {result['applied_load_n']:g} N"
                 + (f" rising to {result['peak_load_n']:g} N" if result["peak_load_n"] != result["applied_load_n"] else ""),
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
