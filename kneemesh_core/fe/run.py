"""A simulation of a job's knee: the CalculiX wrapper for the flexion asked for, the run, the results.

``full`` runs the job's own ``fe/knee_ccx.inp`` (0-90 deg in 3 deg increments); ``smoke`` writes a
wrapper over the same shared model to 15 deg in two increments, in ``fe/smoke/``, and runs that.
"""

from __future__ import annotations

import json
from pathlib import Path

from kneemesh_core.errors import KneeMeshError
from kneemesh_core.fe import deck
from kneemesh_core.fe.model import LoadCase, build
from kneemesh_core.fe.results import RESULTS_FILE, write_results
from kneemesh_core.fe.simulate import run_ccx

FE_DIR, SMOKE_DIR = "fe", "smoke"
#: Where a job's results lie, relative to the job folder: the full flexion first, then the smoke run.
RESULT_FILES = (f"{FE_DIR}/{RESULTS_FILE}", f"{FE_DIR}/{SMOKE_DIR}/{RESULTS_FILE}")
#: The smoke run: flexion and increment, deg (two increments: the sample's run took 53 s of CPU in three
#: of 5 deg, 43 s in two, with the same contact at 15 deg within 3 % of force).
SMOKE = (15.0, 7.5)


def write_decks(out_dir: Path, load: LoadCase = LoadCase()) -> dict:
    """The decks of a meshed job in ``out_dir/fe``; returns what the report says of them."""
    m = build(out_dir, load)
    files = deck.write(m, Path(out_dir) / FE_DIR)
    return {"files": [f"{FE_DIR}/{f.name}" for f in files], "nodes": len(m.nodes),
            "c3d8": int(sum(len(p.elements) for p in m.parts.values())), "springs": len(m.springs),
            "contact_stiffness_n_mm3": m.contact_k, "seating": m.seating, "cartilage": load.cartilage,
            "flexion_deg": load.flexion_deg, "joint_load_n": load.joint_load_n}


def simulate(out_dir: Path, flexion_deg: float | None = None, smoke: bool = False, timeout_s: float = 1800.0,
             load: LoadCase = LoadCase()) -> dict:
    """Run ccx on the job's decks (writing them first if absent); ``results.json`` and ``contact.png``
    land beside the deck that ran.  Returns the results."""
    fe = Path(out_dir) / FE_DIR
    m = None
    if not (fe / deck.MODEL_FILE).exists():
        m = build(out_dir, load)
        deck.write(m, fe)
    folder = fe
    if smoke or flexion_deg is not None:
        flex, step = SMOKE if smoke else (flexion_deg, load.max_increment_deg)
        folder = fe / (SMOKE_DIR if smoke else f"flexion_{flex:g}")
        deck.write(m or build(out_dir, load), folder, flex, step, include=f"../{deck.MODEL_FILE}")
    meta_file = folder / deck.META_FILE
    if not meta_file.exists():
        raise KneeMeshError("deck_missing", f"{meta_file} is missing: write the decks again (kneemesh mesh).")
    run = run_ccx(folder, Path(deck.CCX_FILE).stem, timeout_s)
    return write_results(folder, run, json.loads(meta_file.read_text()), folder / "knee_ccx.dat")
