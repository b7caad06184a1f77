"""Build the anatomy template shipped in ``kneemesh_core/anatomy/data`` (run once; the product
only reads what this writes).

    .venv/bin/python scripts/build_anatomy_template.py [--lenhart ../shared/data/templates/lenhart2015]

1. **Lenhart 2015** (Apache-2.0): the 76 ``Blankevoort1991Ligament`` fibres of ``lenhart2015.osim``
   (stiffness, slack length, and each end's body and location, metres -> mm) and the tibia,
   patella and fibula surfaces (STL, metres -> mm, decimated to about 1.5 mm spacing), all in the
   model's body frames (x anterior, y superior, z lateral, right knee).  The tibia, fibula and the
   tibial ends are in ``tibia_proximal_r``; the ITB's point on ``tibia_r`` is moved into it (the
   weld offset, 6 mm anterior).  Tibial ends nearer the fibula than the tibia are marked as lying
   on the fibula (LCL, popliteofibular ligament); they move with the tibia.
2. **The femur**, whose Lenhart surface is not available: the femur of KneeMesh's bundled sample
   knee (``kneemesh/data/right_knee_example.nrrd``, pymskt, MIT), meshed with KneeMesh's bone
   recipe at 2 mm, is brought into Lenhart's femoral frame like this.  Lenhart's tibia is
   registered onto the sample's tibia (similarity ICP and refinement), which places Lenhart's tibial
   frame in the sample; in the model's neutral pose the femoral frame coincides with the tibial
   frame, so Lenhart's femoral frame in the sample is the tibial one turned by the sample's own
   femur-to-tibia rotation (from :mod:`kneemesh_core.anatomy.frames`: femoral flexion axis and
   shaft, tibial plateau axis and shaft), about the origin of the sample's femoral frame (the
   middle of its flexion axis), at the tibia's scale.  The sample femur, its distal 80 mm, is
   written in that frame; each of Lenhart's femoral fibre ends is moved to the nearest point of it
   (the build prints how far).
3. **The ITB** runs to the pelvis in Lenhart's model; a knee model keeps the part over the knee:
   its femoral end is where the ITB's line (Gerdy's tubercle towards its femoral via point) is
   45 mm above the joint centre, on the femur.  It keeps Lenhart's slack length, and the rest of its
   path (to the pelvis, unchanged by the knee's motion) is ``path_beyond_mm``: a millimetre of the
   knee's segment is then the whole ITB's strain, not a 77 mm fibre's (7 times more; with that, the
   ITB of the sample pulled 750 N by 45 deg of flexion).  No strain at the neutral pose.
"""

from __future__ import annotations

import argparse
import json
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pyvista as pv

from kneemesh_core.anatomy.frames import coarse_axes, femur_frame, tibia_frame
from kneemesh_core.anatomy.register import register
from kneemesh_core.anatomy.template import DATA, FIBRES_FILE, SURFACE_FILES
from kneemesh_core.knee import load_knee
from kneemesh_core.surfaces.tissue import SurfaceOptions, reconstruct_bone
from kneemesh_core.tissues import LABEL

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "kneemesh" / "data" / "right_knee_example.nrrd"
BODY = {"femur_distal_r": "femur", "tibia_proximal_r": "tibia", "patella_r": "patella"}
#: Weld offsets of Lenhart's model (mm): femur_r -> femur_distal_r and tibia_r -> tibia_proximal_r.
FEMUR_R_TO_DISTAL = np.array([5.5513564376633642, 374.18143637169787, 1.1706232813375212])
TIBIA_R_TO_PROXIMAL = np.array([6.0, 0.0, 0.0])
ITB_FEMORAL_HEIGHT_MM = 45.0


def _surface(path: Path, spacing_mm: float = 1.5) -> pv.PolyData:
    mesh = pv.read(path).scale(1000.0).clean()
    target = max(0.0, 1.0 - mesh.area / (spacing_mm ** 2 * 0.9) / mesh.n_points)
    return mesh.decimate_pro(target, preserve_topology=True).clean().compute_normals(auto_orient_normals=True)


def reference_strains(msl: Path) -> dict[str, float]:
    """Each fibre's ``ReferenceStrain`` in the SIMM file the model came from (its strain in the model's
    reference pose, along its wrapped path), by muscle name."""
    out, name = {}, None
    for line in msl.read_text(errors="replace").splitlines():
        words = line.split()
        if words[:1] == ["beginmuscle"]:
            name = words[1]
        elif words[:1] == ["ReferenceStrain"] and name and len(words) > 1:
            out[name] = float(words[1])
    return out


def lenhart_fibres(osim: Path) -> list[dict]:
    root = ET.parse(osim).getroot()
    out = []
    for lig in root.iter("Blankevoort1991Ligament"):
        name = lig.get("name")
        pts = [(p.findtext("socket_parent_frame").rsplit("/", 1)[-1], np.array(p.findtext("location").split(), float) * 1000)
               for p in lig.iter("PathPoint")]
        fibre = {"name": name, "bundle": name.rstrip("0123456789"), "stiffness_n": float(lig.findtext("linear_stiffness")),
                 "slack_length_mm": round(float(lig.findtext("slack_length")) * 1000, 4)}
        if name.startswith("ITB"):
            gerdy = dict(pts)["tibia_r"] + TIBIA_R_TO_PROXIMAL
            via = dict(pts)["femur_r"] - FEMUR_R_TO_DISTAL
            t = (ITB_FEMORAL_HEIGHT_MM - gerdy[1]) / (via[1] - gerdy[1])
            femoral = gerdy + t * (via - gerdy)
            fibre["ends"] = [{"body": "femur_distal_r", "lenhart_mm": femoral}, {"body": "tibia_proximal_r", "lenhart_mm": gerdy}]
            segment = float(np.linalg.norm(femoral - gerdy))
            fibre["path_beyond_mm"] = round(fibre["slack_length_mm"] - segment, 4)
            fibre["note"] = (f"Lenhart's ITB runs to the pelvis (slack length {fibre['slack_length_mm']:.1f} mm); its ends here are "
                             f"Gerdy's tubercle and where its line is {ITB_FEMORAL_HEIGHT_MM:.0f} mm above the joint centre "
                             f"({segment:.1f} mm apart), and the {fibre['path_beyond_mm']:.1f} mm of its path beyond that point, which "
                             "the knee's motion leaves unchanged, count in its strain (path_beyond_mm)")
        else:
            fibre["ends"] = [{"body": b, "lenhart_mm": p} for b, p in pts]
        out.append(fibre)
    return out


def add_reference_strains(fibres: list[dict], msl: Path) -> None:
    """``reference_strain`` of each fibre from the SIMM file; the ITB, cut at the knee, has 0 by
    construction (its whole path in the template's neutral pose is its slack length)."""
    strains = reference_strains(msl)
    for f in fibres:
        f["reference_strain"] = 0.0 if f["name"].startswith("ITB") else strains[f["name"]]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--lenhart", type=Path, default=ROOT.parent / "shared" / "data" / "templates" / "lenhart2015")
    args = ap.parse_args()
    geo = args.lenhart / "Geometry"
    DATA.mkdir(exist_ok=True)
    shutil.copy(args.lenhart / "LICENSE", DATA / "LICENSE-lenhart2015")
    surfaces = {b: _surface(geo / f"lenhart2015-R-{b}-bone.stl") for b in ("tibia", "patella", "fibula")}

    # the femur template: the sample's femur in Lenhart's femoral frame
    knee = load_knee(SAMPLE)
    opts = SurfaceOptions(bone_edge_mm=2.0, articular_edge_mm=2.0)  # uniform, as the template was built
    bones = {b: np.asarray(reconstruct_bone(knee.labels, b, opts)[0].points) for b in ("femur", "tibia", "patella")}
    femur_mesh = reconstruct_bone(knee.labels, "femur", opts)[0]
    axes = coarse_axes(bones["femur"], bones["tibia"], bones["patella"])
    reg = register("tibia", np.asarray(surfaces["tibia"].points), bones["tibia"], axes, mirrored=False)
    from kneemesh_core.io import voxel_to_lps
    import SimpleITK as sitk

    arr = sitk.GetArrayViewFromImage(knee.labels)
    plates = tuple(voxel_to_lps(knee.labels, np.argwhere(arr == LABEL[t])[:, ::-1])
                   for t in ("medial_tibial_cartilage", "lateral_tibial_cartilage"))
    ff = femur_frame(bones["femur"], axes, "right")
    tf = tibia_frame(bones["tibia"], axes, "right", plates)
    a_f = np.stack([ff.anterior, ff.proximal, ff.lateral], 1)
    a_t = np.stack([tf.anterior, tf.proximal, tf.lateral], 1)
    rot_f = a_f @ a_t.T @ reg.similarity.rotation
    scale = reg.similarity.scale
    femur_t = femur_mesh.copy()
    femur_t.points = (np.asarray(femur_mesh.points) - ff.origin) @ rot_f / scale
    femur_t = femur_t.clip_box([-200, 200, 80.0, 400, -200, 200], invert=True).extract_surface(algorithm="dataset_surface")
    surfaces["femur"] = femur_t.clean().compute_normals(auto_orient_normals=True)
    print(f"tibia registration: scale {scale:.3f}, rms {reg.rms_mm:.2f} mm; femoral origin {np.round(ff.origin, 1)} "
          f"vs Lenhart's origin through the tibia {np.round(reg.similarity.translation, 1)} "
          f"({np.linalg.norm(ff.origin - reg.similarity.translation):.1f} mm apart)")

    fibres = lenhart_fibres(args.lenhart / "lenhart2015.osim")
    add_reference_strains(fibres, args.lenhart / "JKRLfbkid.msl")
    for f in fibres:
        for end in f["ends"]:
            bone = BODY[end["body"]]
            p = np.asarray(end["lenhart_mm"])
            on = bone
            if bone == "tibia":
                d_t = surfaces["tibia"].find_closest_point(p)
                d_f = surfaces["fibula"].find_closest_point(p)
                if np.linalg.norm(surfaces["fibula"].points[d_f] - p) < np.linalg.norm(surfaces["tibia"].points[d_t] - p):
                    on = "fibula"
            _, closest = surfaces[on].find_closest_cell(p[None], return_closest_point=True)
            end.update({"bone": bone, "surface": on, "point_mm": np.round(closest[0], 4).tolist(),
                        "lenhart_mm": np.round(p, 4).tolist(),
                        "moved_to_surface_mm": round(float(np.linalg.norm(closest[0] - p)), 3)})
            del end["body"]
    moved = {b: [e["moved_to_surface_mm"] for f in fibres for e in f["ends"] if e["bone"] == b] for b in ("femur", "tibia", "patella")}
    for b, m in moved.items():
        print(f"{b}: {len(m)} ends moved onto the surface by median {np.median(m):.2f} mm, max {max(m):.2f} mm")
    for b, path in SURFACE_FILES.items():
        surfaces[b].save(path)
    FIBRES_FILE.write_text(json.dumps({
        "source": {
            "model": "Lenhart 2015 knee (Lenhart RL, Kaiser J, Smith CR, Thelen DG, Ann Biomed Eng 2015;43:2675-2685)",
            "files": "opensim-jam-org/jam-resources, commit 73306a0f8dce2e31fea2095a27dd449bcd14d9b7, "
                     "models/knee_healthy/lenhart2015 (lenhart2015.osim, Geometry/*-bone.stl)",
            "licence": "Apache-2.0 (LICENSE-lenhart2015); derived: units mm, decimated surfaces, ends on the surfaces, ITB cut at the knee",
            "femur": "KneeMesh's sample knee (pymskt right_knee_example, MIT) in Lenhart's femoral frame; see scripts/build_anatomy_template.py",
            "frame": "mm, right knee: x anterior, y superior, z lateral; origin at the knee joint centre (patella: its own centre)",
            "tibia_registration_to_sample": {"scale": round(scale, 4), "rms_mm": round(reg.rms_mm, 3)},
        },
        "fibres": fibres}, indent=1))
    print(f"wrote {FIBRES_FILE} ({len(fibres)} fibres) and {', '.join(p.name for p in SURFACE_FILES.values())}")


if __name__ == "__main__":
    main()
