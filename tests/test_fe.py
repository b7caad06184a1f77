"""The decks and CalculiX: an analytic contact case, deck hygiene in both dialects, and a smoke
simulation of a real knee whose forces balance and whose pressures are physiological."""

from __future__ import annotations

import json
import os
import re

import numpy as np
import pytest
import pyvista as pv

from conftest import OAI, SAMPLE, real
from kneemesh_core import KneeMeshError
from kneemesh_core.fe import deck
from kneemesh_core.fe.contact_skin import MAX_FIT_MM, articular_surface
from kneemesh_core.fe.inp import set_lines
from kneemesh_core.fe.physics import MAX_BALANCE_ERROR, MAX_PLATE_PEAK_MPA, LoadCase
from kneemesh_core.fe.results import centre_of_pressure, loaded, parse_dat
from kneemesh_core.fe.simulate import run_ccx

pytestmark = pytest.mark.xdist_group("fe")


def _block(n: int, z0: float, first_node: int, first_element: int):
    """A unit block of n^3 C3D8 hexes from z0 to z0 + 1 (node ids from first_node)."""
    idx = np.arange((n + 1) ** 3).reshape(n + 1, n + 1, n + 1) + first_node  # [k, j, i]
    g = np.linspace(0.0, 1.0, n + 1)
    nodes = {int(idx[k, j, i]): (g[i], g[j], z0 + g[k]) for k in range(n + 1) for j in range(n + 1) for i in range(n + 1)}
    hexes = {}
    for k in range(n):
        for j in range(n):
            for i in range(n):
                hexes[first_element + len(hexes)] = [idx[k, j, i], idx[k, j, i + 1], idx[k, j + 1, i + 1], idx[k, j + 1, i],
                                                     idx[k + 1, j, i], idx[k + 1, j, i + 1], idx[k + 1, j + 1, i + 1], idx[k + 1, j + 1, i]]
    top = [e for e, c in hexes.items() if all(nodes[int(x)][2] > z0 + 1 - 1e-9 for x in c[4:])]
    bottom = [e for e, c in hexes.items() if all(nodes[int(x)][2] < z0 + 1e-9 for x in c[:4])]
    return nodes, hexes, top, bottom


@pytest.mark.parametrize("turn", [None, "twist", "tilt"])
def test_two_rigid_blocks_press_with_pressure_k_times_d_over_the_exact_area(tmp_path, turn):
    """Rigid blocks pressed d = 0.01 into each other under the linear law K = 1e4: pressure K d at
    every point, force K d A and the centre of pressure at the face's centroid; twisted by 10 deg about
    the press, the area of the squares' overlap, the centre of pressure still central; tilted by
    theta = 0.005 rad about y, a pressure K (d + theta (x - 1/2)) whose centre lies at x = 1/2 + theta / (12 d)."""
    k, d = 1.0e4, 0.01
    a_nodes, a_hex, a_top, _ = _block(4, 0.0, 1, 1)
    b_nodes, b_hex, _, b_bottom = _block(4, 1.0, 1001, 101)
    w = ["*HEADING", "two rigid blocks", "*NODE"]
    w += [f"{i}, {x:.6f}, {y:.6f}, {z:.6f}" for i, (x, y, z) in {**a_nodes, **b_nodes}.items()]
    w += ["5001, 0.5, 0.5, 0.5", "5002, 0.5, 0.5, 1.5", "5003, 0.5, 0.5, 0.5", "5004, 0.5, 0.5, 1.5"]
    for name, hexes in (("A", a_hex), ("B", b_hex)):
        w.append(f"*ELEMENT, TYPE=C3D8, ELSET={name}")
        w += [f"{e}, " + ", ".join(str(int(n)) for n in c) for e, c in hexes.items()]
    w += set_lines("NSET", "A_NODES", sorted(a_nodes)) + set_lines("NSET", "B_NODES", sorted(b_nodes))
    w += set_lines("ELSET", "A_TOP", a_top) + set_lines("ELSET", "B_BOTTOM", b_bottom)
    w += ["*SURFACE, NAME=SA, TYPE=ELEMENT", "A_TOP, S2", "*SURFACE, NAME=SB, TYPE=ELEMENT", "B_BOTTOM, S1",
          "*MATERIAL, NAME=M", "*ELASTIC", "1000.0, 0.3", "*SOLID SECTION, ELSET=A, MATERIAL=M", "*SOLID SECTION, ELSET=B, MATERIAL=M",
          "*RIGID BODY, NSET=A_NODES, REF NODE=5001, ROT NODE=5003", "*RIGID BODY, NSET=B_NODES, REF NODE=5002, ROT NODE=5004",
          "*SURFACE INTERACTION, NAME=LAW", "*SURFACE BEHAVIOR, PRESSURE-OVERCLOSURE=LINEAR", f"{k:.6e}",
          "*CONTACT PAIR, INTERACTION=LAW, TYPE=SURFACE TO SURFACE", "SB, SA", "*AMPLITUDE, NAME=RAMP", "0.0, 0.0, 1.0, 1.0",
          "*STEP, NLGEOM, INC=100", "*STATIC", "0.25, 1.0", "*BOUNDARY", "5001, 1, 3, 0.0", "5003, 1, 3, 0.0",
          "5002, 1, 2, 0.0", "5004, 1, 3, 0.0", "*BOUNDARY, AMPLITUDE=RAMP", f"5002, 3, 3, {-d}",
          "*CONTACT PRINT, SLAVE=SB, MASTER=SA", "CF", "*CONTACT PRINT", "CSTR", "*END STEP"]
    twist_deg, tilt = 10.0, 0.005
    if turn:
        w += ["*STEP, NLGEOM, INC=100", "*STATIC", "0.1, 1.0", "*BOUNDARY, AMPLITUDE=RAMP",
              f"5004, 3, 3, {np.radians(twist_deg):.6f}" if turn == "twist" else f"5004, 2, 2, {tilt}",
              "*CONTACT PRINT, SLAVE=SB, MASTER=SA", "CF", "*END STEP"]
    (tmp_path / "blocks.inp").write_text("\n".join(w) + "\n")
    run = run_ccx(tmp_path, "blocks", timeout_s=120)
    assert run.completed, run.reason
    dat = parse_dat(tmp_path / "blocks.dat")
    pressed = dat["contact"][1.0]["SB"]
    assert pressed["area"] == pytest.approx(1.0, rel=1e-6)
    assert -pressed["normal_force"] == pytest.approx(k * d * 1.0, rel=1e-6)
    assert all(p == pytest.approx(k * d, rel=1e-6) for _, p in dat["stress"][1.0])
    cop = centre_of_pressure(pressed["force"], pressed["moment"], pressed["centre"], pressed["normal"])
    np.testing.assert_allclose(cop, [0.5, 0.5, 1.0 - d], atol=1e-6)
    # ccx stopped at a time limit while writing: the cut increment (and, unsure where the cut fell,
    # at most the one before) is dropped, the rest read as before
    text = (tmp_path / "blocks.dat").read_text()
    last = max(dat["contact"])
    for cut in (text.rindex("statistics for slave set") + 60, len(text) - 40, len(text)):
        (tmp_path / "cut.dat").write_text(text[:cut])
        partial = parse_dat(tmp_path / "cut.dat", stopped=True)
        assert last not in partial["contact"] and last not in partial["stress"]
        kept = partial["contact"]
        assert all(dat["contact"][t] == v for t, v in kept.items()) and len(kept) >= len(dat["contact"]) - 2
    turned = dat["contact"][max(dat["contact"])]["SB"]
    cop = centre_of_pressure(turned["force"], turned["moment"], turned["centre"], turned["normal"])
    if turn == "twist":  # the overlap of the two squares, one turned about their common centre
        assert turned["area"] == pytest.approx(_overlap(twist_deg), abs=0.01)  # pairing lags one increment
        np.testing.assert_allclose(cop[:2], [0.5, 0.5], atol=1e-3)
    if turn == "tilt":  # B's face, turned about its body's centre 0.5 above, slides by theta / 2 (0.0025)
        assert -turned["normal_force"] == pytest.approx(k * d, rel=0.01)
        assert cop[0] == pytest.approx(0.5 + tilt / (12 * d), abs=0.004) and cop[1] == pytest.approx(0.5, abs=1e-4)


def _overlap(deg: float) -> float:
    """Area where a unit square and the same square turned by ``deg`` about its centre overlap
    (Sutherland-Hodgman clipping, then the shoelace formula)."""
    square = [(-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5)]
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    poly = [(c * x - s * y, s * x + c * y) for x, y in square]
    for (x1, y1), (x2, y2) in zip(square, square[1:] + square[:1]):
        inside = lambda p: (x2 - x1) * (p[1] - y1) - (y2 - y1) * (p[0] - x1) >= 0  # noqa: E731
        clipped = []
        for p, q in zip(poly, poly[1:] + poly[:1]):
            if inside(q):
                if not inside(p):
                    clipped.append(_cross(p, q, (x1, y1), (x2, y2)))
                clipped.append(q)
            elif inside(p):
                clipped.append(_cross(p, q, (x1, y1), (x2, y2)))
        poly = clipped
    return 0.5 * abs(sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(poly, poly[1:] + poly[:1])))


def _cross(p, q, a, b):
    """Where the segment p-q meets the line through a and b."""
    d = (p[0] - q[0]) * (a[1] - b[1]) - (p[1] - q[1]) * (a[0] - b[0])
    t = ((p[0] - a[0]) * (a[1] - b[1]) - (p[1] - a[1]) * (a[0] - b[0])) / d
    return (p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1]))


def test_the_preload_depth_carries_the_load_by_the_linear_law():
    """Seating pushes the femur past first touch by d with sum(K max(0, d - gap) A) = load: a flat
    plateau (every gap 0) gives d = L / (K A); a second plateau 0.2 mm further away shares the load
    only beyond 0.2 mm; a ray that missed (NaN) carries nothing."""
    from kneemesh_core.fe.model import preload_depth

    flat, area = np.zeros(100), np.full(100, 2.0)  # 200 mm^2
    assert preload_depth([flat], [area], [4.0], 1000.0) == pytest.approx(1000.0 / (4.0 * 200.0))
    far = np.full(100, 0.2)
    d = preload_depth([flat, far], [area, area], [4.0, 4.0], 1000.0)
    assert 4.0 * 200.0 * d + 4.0 * 200.0 * (d - 0.2) == pytest.approx(1000.0) and d > 0.2
    missed = np.concatenate([flat, [np.nan]])
    assert preload_depth([missed], [np.append(area, 50.0)], [4.0], 1000.0) == pytest.approx(1.25)


def test_the_itb_strains_as_the_whole_band_not_as_its_segment_over_the_knee():
    """The ITB is cut at the knee but runs on to the pelvis: 10 mm more between its ends is 10 mm on a
    535 mm band (the toe of its law, some 15 N), not on a 77 mm fibre (about 1000 N)."""
    from kneemesh_core.anatomy import template
    from kneemesh_core.fe.physics import TRANSITION_STRAIN, ligament_table

    itb = next(f for f in template.load().fibres if f.bundle == "ITB")
    segment = float(np.linalg.norm(itb.ends[0].point - itb.ends[1].point))
    length = segment + itb.path_beyond_mm
    assert length == pytest.approx(itb.slack_length_mm, rel=0.01) and itb.reference_strain == 0
    force, elongation = np.array(ligament_table(itb.stiffness_n, length, length)).T  # slack as placed: no strain
    strain = 10.0 / length
    assert np.interp(10.0, elongation, force) == pytest.approx(itb.stiffness_n * strain ** 2 / (2 * TRANSITION_STRAIN), rel=0.05)
    assert np.interp(10.0, elongation, force) < 30


def test_a_fibre_in_the_deck_pulls_as_the_results_law_says_far_along_its_law(tmp_path):
    """ccx holds a nonlinear spring's force constant past its table: a fibre stretched to 40 % strain
    (a PCL 10 % short of slack in the image pose, pulled to 40 % past it) must still pull k (e - e_t / 2),
    or the femur's forces cannot balance in deep flexion."""
    from kneemesh_core.fe.physics import ligament_force, ligament_table

    k, slack, length = 3000.0, 40.0, 36.0
    stretch = 1.4 * slack - length  # half of it by the first increment: 15 % strain
    w = ["*HEADING", "one fibre", "*NODE, NSET=ENDS", "1, 0, 0, 0", f"2, {length}, 0, 0",
         "*ELEMENT, TYPE=SPRINGA, ELSET=FIBRE", "1, 1, 2", "*SPRING, ELSET=FIBRE, NONLINEAR", ""]
    w += [f"{f:.6e}, {d:.6e}" for f, d in ligament_table(k, slack, length)]
    w += ["*BOUNDARY", "1, 1, 3", "2, 2, 3", "*STEP, NLGEOM", "*STATIC", "0.5, 1.0", "*BOUNDARY",
          f"2, 1, 1, {stretch}", "*NODE PRINT, NSET=ENDS", "RF", "*END STEP"]
    (tmp_path / "fibre.inp").write_text("\n".join(w) + "\n")
    assert run_ccx(tmp_path, "fibre", timeout_s=60).completed
    reactions = parse_dat(tmp_path / "fibre.dat")["nodes"][("forces", "ENDS")]
    for t in (0.5, 1.0):
        assert reactions[t][2][0] == pytest.approx(ligament_force(k, (length + t * stretch) / slack - 1.0), rel=1e-3)
    assert reactions[1.0][2][0] == pytest.approx(k * (0.4 - 0.03), rel=1e-3)


def test_a_missing_ccx_and_a_skipped_card_are_clear_errors(tmp_path, monkeypatch):
    # a spring stretched by 1 mm, run to its end, behind a card ccx skips (a deck without elements made ccx
    # 2.20 crash before its warning, depending on the memory layout)
    (tmp_path / "bad.inp").write_text("*HEADING\nx\n*PART, NAME=P\n*NODE\n1, 0, 0, 0\n2, 10, 0, 0\n*ELEMENT, TYPE=SPRINGA, "
                                      "ELSET=E1\n1, 1, 2\n*SPRING, ELSET=E1\n\n5.0\n*BOUNDARY\n1, 1, 3\n2, 2, 3\n*STEP\n*STATIC\n"
                                      "*BOUNDARY\n2, 1, 1, 1.0\n*END STEP\n")
    with pytest.raises(KneeMeshError) as e:
        run_ccx(tmp_path, "bad", timeout_s=60)
    assert e.value.code == "deck_skipped" and "skipped part of the deck" in e.value.message
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(KneeMeshError) as e:
        run_ccx(tmp_path, "bad")
    assert e.value.code == "ccx_missing" and "apt-get install calculix-ccx" in e.value.message


def _fake_ccx(tmp_path, monkeypatch, body: str):
    """A ccx on the PATH that writes one converged increment to its .sta, then runs ``body`` (sh)."""
    fake = tmp_path / "bin" / "ccx"
    fake.parent.mkdir()
    fake.write_text("#!/bin/sh\n[ \"$1\" = -v ] && echo 'Version 2.20' && exit 0\nprintf ' STEP INC ATT ITRS TOT TIME STEP TIME INC TIME\\n 1 1 1 8 0.1E+01 0.1E+01 0.1E+01\\n' > knee_ccx.sta\n"
                    + body)
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", f"{fake.parent}:{os.environ['PATH']}")


def test_a_stalled_run_is_stopped_with_its_reason(tmp_path, monkeypatch):
    """A run whose increments stop converging (ccx cutting back for ever, as on a chattering contact, busy
    all the while) is stopped once it has spent the stall time's CPU without a converged increment, not at
    the time limit."""
    _fake_ccx(tmp_path, monkeypatch, "while true; do echo ' 2 1 1U 30 0.13E+01 0.33E+00 0.33E+00' >> knee_ccx.sta; "
                                     "i=0; while [ $i -lt 20000 ]; do i=$((i+1)); done; done\n")
    (tmp_path / "knee_ccx.sta").write_text(" 1 1 1 8 0.5E+01 0.5E+01 0.5E+01\n")  # an earlier run's: not progress
    run = run_ccx(tmp_path, "knee_ccx", timeout_s=60, stall_s=2)
    assert not run.completed and run.reason.startswith("stalled: no increment converged in 2 s of CPU time after step time 1")
    assert run.seconds < 15


def test_a_run_waiting_for_the_cores_is_not_stalled(tmp_path, monkeypatch):
    """A run that makes no progress because it gets no CPU (the cores busy with other runs) is not stalled:
    here it waits six seconds, three times the stall time, using no CPU, then converges and finishes."""
    _fake_ccx(tmp_path, monkeypatch, "sleep 6\necho ' 2 1 1 5 0.2E+01 0.1E+01 0.1E+01' >> knee_ccx.sta\necho ' Job finished'\n")
    run = run_ccx(tmp_path, "knee_ccx", timeout_s=60, stall_s=2)
    assert run.completed, run.reason


@pytest.fixture(scope="module")
def knee(tmp_path_factory):
    """The sample knee meshed at 2 mm (a quick model), with its decks and a smoke run."""
    from kneemesh_core.job import JobRequest, run

    out = tmp_path_factory.mktemp("knee")
    report = run(real(SAMPLE), out, JobRequest.build(element_size=2.0, simulate="smoke").job_options(), workers=2)
    return out, report


def test_each_step_of_the_job_started_once_the_steps_it_reads_from_were_done(knee):
    from datetime import datetime

    from kneemesh_core.job import JobRequest, needs, read_step

    out, _ = knee
    waits = needs(JobRequest.build(element_size=2.0, simulate="smoke").job_options())
    records = {s: read_step(out, s) for s in waits}
    assert all(r["state"] == "done" for r in records.values())
    at = {s: {k: datetime.fromisoformat(r[k]) for k in ("started_at", "finished_at")} for s, r in records.items()}
    for step, before in waits.items():
        assert all(at[b]["finished_at"] <= at[step]["started_at"] for b in before), step


def _cards(text: str) -> list[str]:
    return [line.split(",")[0].strip().upper() for line in text.splitlines() if line.startswith("*") and not line.startswith("**")]


def test_decks_are_clean_in_both_dialects(knee):
    out, report = knee
    assert report["fe"]["status"] == "ok"
    fe = out / "fe"
    shared, ccx, abq = ((fe / f).read_text() for f in (deck.MODEL_FILE, deck.CCX_FILE, deck.ABAQUS_FILE))
    for text in (shared, ccx, abq):
        for line in text.splitlines():
            if not line.startswith("*") and "," in line:
                assert len([x for x in line.split(",") if x.strip()]) <= 16, line[:80]
        cards = set(_cards(text))
        assert not cards & {"*PART", "*ASSEMBLY", "*INSTANCE", "*KINEMATIC COUPLING", "*CONNECTOR SECTION"}
    assert f"*INCLUDE, INPUT={deck.MODEL_FILE}" in ccx and f"*INCLUDE, INPUT={deck.MODEL_FILE}" in abq
    assert "ENCASTRE" not in ccx and "NAME=" not in "".join(l for l in ccx.splitlines() if l.startswith("*STEP"))
    assert "R3D3" in abq and "R3D3" not in ccx + shared and "ROT NODE" in ccx and "ROT NODE" not in abq
    assert "DYNAMIC, EXPLICIT" in abq and "*STATIC" in ccx
    # unique ids across the include and each wrapper; every set and surface used is defined
    for wrapper in (ccx, abq):
        text = shared + wrapper
        nodes, elements, block = [], [], None
        for line in text.splitlines():
            if line.startswith("*"):
                card = line.split(",")[0].strip().upper()
                block = "node" if card == "*NODE" else "element" if card == "*ELEMENT" else None
            elif block and line.strip():
                (nodes if block == "node" else elements).append(int(line.split(",")[0]))
        assert len(nodes) == len(set(nodes)) and len(elements) == len(set(elements))
        defined = set(re.findall(r"^\*(?:NSET|ELSET), (?:NSET|ELSET)=(\w+)", text, re.M)) | set(re.findall(r"ELSET=(\w+)", text))
        surfaces = set(re.findall(r"^\*SURFACE, NAME=(\w+)", text, re.M))
        for a, b in re.findall(r"^\*CONTACT PAIR.*\n(\w+), (\w+)", text, re.M):
            assert a in surfaces and b in surfaces
        for name in re.findall(r"(?:NSET|ELSET)=(\w+)", text):
            assert name in defined, name
    # the meniscus rings: in the tibia's body, in contact with the femoral cartilage in both dialects
    for side in ("MEDIAL", "LATERAL"):
        assert f"{side}_MENISCUS_ARTICULAR, FEMORAL_CARTILAGE_ARTICULAR" in ccx and f"{side}_MENISCUS_ARTICULAR" in abq
    # the prefemoral sheet: in the femur's body, with the femoral cartilage the patella's master in both dialects
    for text in (ccx, abq):
        assert "PATELLAR_CARTILAGE_ARTICULAR, PATELLAR_TRACK_ARTICULAR" in text
    assert "*SURFACE, NAME=PATELLAR_TRACK_ARTICULAR, TYPE=ELEMENT\nFEMORAL_CARTILAGE_ART, S2\nPREFEMORAL_ART, S2" in shared
    assert re.search(r"^\*ELSET, ELSET=FEMUR_RIGID\n.*\bPREFEMORAL\b", abq, re.M)
    rows = shared.split("*ELEMENT, TYPE=C3D8, ELSET=PREFEMORAL\n")[1].split("\n*")[0].splitlines()
    femur_body = shared.split("*NSET, NSET=FEMUR_BODY\n")[1].split("\n*")[0]
    assert len(rows) > 100
    assert {int(n) for r in rows for n in r.split(",")[1:]} <= {int(n) for n in femur_body.replace("\n", ",").split(",")}
    # the same model data under both: the Abaqus wrapper adds bones and bodies, not new cartilage
    assert _cards(shared).count("*ELEMENT") >= 6 and "C3D8" in shared


def test_smoke_simulation_of_a_real_knee_balances_with_physiological_contact(knee):
    out, report = knee
    sim = report["simulation"]
    assert sim["completed"], sim["reason"]
    r = json.loads((out / "fe" / "smoke" / "results.json").read_text())
    assert r["solver"].startswith("ccx") and r["reached_flexion_deg"] == pytest.approx(15.0)
    assert (out / "fe" / "smoke" / "contact.png").stat().st_size > 10_000
    on = loaded(r["increments"])  # the whole joint load on, flexing
    for inc in on:
        assert inc["balance_error"] < MAX_BALANCE_ERROR, inc  # the femur's forces balance the joint load
        for side in ("medial", "lateral"):
            c = inc[side]
            assert c["force_n"] > 100 and 100 < c["area_mm2"] < 1500 and c["peak_pressure_mpa"] < MAX_PLATE_PEAK_MPA, (side, c)
    for inc in on:  # near extension the plates carry most of the load, the meniscus rings the rest
        rings = inc["medial_meniscus"]["force_n"] + inc["lateral_meniscus"]["force_n"]
        assert rings < 0.4 * (rings + inc["medial"]["force_n"] + inc["lateral"]["force_n"]), inc
    assert r["physiological"] and report["simulation"]["status"] == "ok", r["physiology_reasons"]
    assert report["fe"]["seating"]["femur_shift_mm"] == pytest.approx(r["seating"]["femur_shift_mm"])
    # the contact pressure maps in the bundle: each plate's and the patella's, one array per loaded increment,
    # on the contact skin in LPS, on the job's mesh's articular surface, whose largest value is the
    # increment's peak in results.json
    assert r["pressure_maps"] == [f"pressure_{t}.vtu" for t in ("lateral_tibial_cartilage", "medial_tibial_cartilage",
                                                              "patellar_cartilage")]
    assert {f"fe/smoke/{name}" for name in r["pressure_maps"]} <= set(sim["files"])
    plate = pv.read(out / "fe" / "smoke" / "pressure_medial_tibial_cartilage.vtu")
    mesh = pv.read(out / "meshes" / "medial_tibial_cartilage.vtu")
    assert len(plate.field_data["flexion_deg"]) == len(on) and plate.field_data["flexion_deg"][-1] == pytest.approx(15.0, abs=1e-3)
    layer = np.asarray(mesh.cell_data["layer"])
    points, triangles, _ = articular_surface(np.asarray(mesh.points), mesh.cells_dict[pv.CellType.HEXAHEDRON][layer == layer.max()])
    surface = pv.PolyData(points, np.hstack([np.full((len(triangles), 1), 3), triangles]).ravel())
    _, on_mesh = surface.find_closest_cell(np.asarray(plate.points), return_closest_point=True)
    # on the mesh's articular surface within the skin's fit (the tibia is held), LPS
    assert np.linalg.norm(on_mesh - plate.points, axis=1).max() < MAX_FIT_MM + 1e-3
    for k, inc in enumerate(on):
        assert plate.cell_data[f"pressure_mpa_{k}"].max() == pytest.approx(inc["medial"]["peak_pressure_mpa"], abs=1e-3)
    image = json.loads((out / "attachments.json").read_text())["angles_deg"]["flexion"]
    for inc in on:  # flexion from the image pose, and anatomically: the image pose's plus the run's
        assert inc["anatomical_flexion_deg"] == pytest.approx(image + inc["flexion_deg"], abs=2e-3), inc
    # the joint load passes the default offset medial of the knee: on the sample, the medial compartment
    # (plate and ring) carries the larger share in extension, as in the paper's simulations
    first = on[0]
    medial = first["medial"]["force_n"] + first["medial_meniscus"]["force_n"]
    assert r["joint_load"]["medial_offset_mm"] == LoadCase().medial_offset_mm > 0
    assert medial > first["lateral"]["force_n"] + first["lateral_meniscus"]["force_n"], first


def test_the_bundle_holds_the_runs_results_for_a_lab_to_inspect(knee):
    """What a lab opens in ParaView or reads again comes in the bundle: the smoke run's results, contact figure,
    per-face pressure maps and ccx's own result file (.frd), beside the decks."""
    from kneemesh_core.job.outputs import bundle

    out, _ = knee
    names = {a["name"] for a in bundle(out)}
    assert {"fe/knee_ccx.inp", "fe/knee_abaqus.inp", "fe/model.json", "fe/smoke/results.json", "fe/smoke/contact.png",
            "fe/smoke/knee_ccx.frd", "fe/smoke/pressure_medial_tibial_cartilage.vtu"} <= names, sorted(names)


def test_a_run_whose_femur_loses_the_tibia_is_not_completed():
    """ccx may 'converge' after the femur slid off the tibia: such increments are not physics."""
    from kneemesh_core.fe.results import first_invalid

    def inc(t, flex, tf, err):
        return {"time": t, "flexion_deg": flex, "medial": {"force_n": tf / 2}, "lateral": {"force_n": tf / 2},
                "balance_error": err}

    good = [inc(0.5, 0.0, 0.0, 0.7), inc(1.0, 0.0, 1100.0, 0.004), inc(1.5, 45.0, 1150.0, 0.005)]
    assert first_invalid(good) is None  # the seating step is judged at its end only
    reason = first_invalid(good + [inc(1.8, 72.0, 0.0, 0.88)])
    assert reason and "72.0 deg" in reason and "lost the tibia" in reason
    reason = first_invalid(good + [inc(2.0, 90.0, 2013.0, 0.051)])  # contact kept, forces off by 5.1 %
    assert reason and "5.1%" in reason and "lost the tibia" not in reason


def test_a_completed_run_outside_physiology_is_named_so():
    """Converged is not physiological: a plate's peak above 20 MPa anywhere in the run (more under a joint load
    above 1 kN), a plate that carries almost nothing in extension, a pin-point contact: each is a reason of its own."""
    from kneemesh_core.fe.results import physiology

    def inc(t, flex, medial, lateral):
        return {"time": t, "flexion_deg": flex, **{k: {"force_n": f, "area_mm2": a, "peak_pressure_mpa": p}
                                                  for k, (f, a, p) in (("medial", medial), ("lateral", lateral))}}

    seating = inc(0.5, 0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))  # not loaded yet: never judged
    good = [seating, inc(1.0, 0.0, (560.0, 330.0, 6.0), (480.0, 210.0, 9.0)), inc(1.5, 45.0, (600.0, 250.0, 19.0), (450.0, 150.0, 12.0))]
    assert physiology(good, 1000.0) == []
    peaky = good + [inc(2.0, 90.0, (700.0, 60.0, 41.5), (400.0, 120.0, 12.0))]
    assert physiology(peaky, 1000.0) == ["the tibial plates' peak contact pressure reaches 41.5 MPa (medial, at 90 deg "
                                         "under 1000 N; physiological: below 20 MPa)"]
    # under an activity's heavier load the limit grows with its square root (an elastic foundation's peak)
    bend = good + [{**inc(2.0, 90.0, (2400.0, 400.0, 33.0), (900.0, 200.0, 14.0)), "joint_load_n": 3500.0}]
    assert physiology(bend, 1000.0) == []
    bend[-1]["medial"]["peak_pressure_mpa"] = 41.5
    assert physiology(bend, 1000.0) == ["the tibial plates' peak contact pressure reaches 41.5 MPa (medial, at 90 deg "
                                        "under 3500 N; physiological: below 37.4 MPa)"]
    one_plate = [seating, inc(1.0, 0.0, (1010.0, 60.0, 18.0), (30.0, 5.0, 6.0))]
    reasons = physiology(one_plate, 1000.0)
    assert len(reasons) == 2 and "lateral plate carries 30 N" in reasons[0] and "65 mm^2" in reasons[1]


def _disk(radius: float, centre, spacing: float = 1.0):
    """A flat triangulated disk at z = 0: points (P, 3) and triangles (T, 3)."""
    from scipy.spatial import Delaunay

    g = np.arange(-radius, radius + 1e-9, spacing)
    xy = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    xy = xy[np.hypot(*xy.T) <= radius] + np.asarray(centre)[:2]
    return np.column_stack([xy, np.zeros(len(xy))]), Delaunay(xy).simplices


def test_a_meniscus_surrogate_rings_its_plate_below_the_femur_and_leaves_the_eminence_open():
    from kneemesh_core.fe import menisci

    plate = _disk(15.0, (0.0, 0.0))
    # a femoral condyle: the lower half of a sphere of radius 25 mm resting 0.5 mm into the plate
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 120, endpoint=False), np.linspace(np.pi / 2 + 0.02, np.pi, 60))
    r, z0 = 25.0, 24.5
    sphere = np.column_stack([(r * np.sin(v) * np.cos(u)).ravel(), (r * np.sin(v) * np.sin(u)).ravel(), (z0 + r * np.cos(v)).ravel()])
    import trimesh
    femur = trimesh.convex.convex_hull(sphere)
    other = np.array([40.0, 0.0, 0.0])  # the other plate, towards +x
    nodes, hexes = menisci.wedge(plate, [(np.asarray(femur.vertices), np.asarray(femur.faces))], np.array([0.0, 0.0, 1.0]), other)
    assert len(hexes) > 100
    top = np.unique(hexes[:, 4:])
    p = nodes[top]
    # under the femur less the clearance; never above the peripheral height; the lowest at the inner edge
    below = np.sqrt(np.clip(r ** 2 - p[:, 0] ** 2 - p[:, 1] ** 2, 0, None))
    femur_z = np.where(np.hypot(p[:, 0], p[:, 1]) < r, z0 - below, np.inf)
    assert np.all(p[:, 2] <= femur_z - menisci.CLEARANCE_MM + 0.05)
    assert p[:, 2].max() <= menisci.HEIGHT_MM + 1e-6 and p[:, 2].max() > 3.0
    radius = np.hypot(p[:, 0], p[:, 1])
    assert radius.min() == pytest.approx(15.0 - menisci.INNER_MM, abs=1.2)  # the disk's lattice rim: 14.1-15 mm
    assert radius.max() == pytest.approx(15.0 + menisci.OUTER_MM, abs=1.2)
    # open where the rim faces the other plate: no node within the open sector
    angle = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
    assert np.all(np.abs(angle) > menisci.OPEN_DEG - 8.0)
    assert np.any(np.abs(angle) > 170)  # but round the far side
    # every hexahedron the right way round (positive volume), its contact face (5-8) facing up
    c = nodes[hexes]
    jac = np.einsum("ij,ij->i", np.cross(c[:, 1] - c[:, 0], c[:, 3] - c[:, 0]), c[:, 4] - c[:, 0])
    assert np.all(jac > 0)
    n = np.cross(c[:, 5] - c[:, 4], c[:, 7] - c[:, 4])
    assert np.all(n[:, 2] > 0)


def test_the_prefemoral_sheet_continues_the_trochlea_up_the_femur_from_the_cartilage_edge():
    """A flat anterior femur (y = 0, facing +y), its cartilage over z < 0 and a patella in front
    reaching above it: the sheet covers the bone above the cartilage only, rises from the bone at the
    cartilage's edge to the standoff over the taper, and faces the patella."""
    from kneemesh_core.fe import prefemoral

    def plane(x, z, y):  # a triangulated rectangle at height y, facing +y
        from scipy.spatial import Delaunay
        xz = np.stack(np.meshgrid(np.arange(*x, 0.5), np.arange(*z, 0.5)), -1).reshape(-1, 2)
        return np.column_stack([xz[:, 0], np.full(len(xz), y), xz[:, 1]]), Delaunay(xz).simplices

    bone = plane((-30, 30.1), (-30, 60.1), 0.0)
    cartilage = plane((-30, 30.1), (-30, 0.01), 2.0)
    patella = plane((-10, 10.1), (-5, 25.1), 6.0)
    standoff = 2.5
    nodes, hexes = prefemoral.sheet(patella, np.array([0.0, -1.0, 0.0]), bone, cartilage, standoff)
    top = nodes[np.unique(hexes[:, 4:])]
    assert len(hexes) > 100
    assert top[:, 2].min() >= -1.0 and top[:, 2].max() <= 25 + prefemoral.MARGIN_MM + 1.0  # above the cartilage, under the patella
    assert np.abs(top[:, 0]).max() <= 10 + prefemoral.MARGIN_MM + 1.0
    expected = standoff * np.clip(top[:, 2] / prefemoral.TAPER_MM, 0.0, 1.0)  # the edge at z = 0
    assert np.allclose(top[:, 1], expected, atol=0.5 * standoff * prefemoral.SPACING_MM / prefemoral.TAPER_MM + 1e-6)
    assert np.allclose(top[top[:, 2] > prefemoral.TAPER_MM + 1, 1], standoff)
    c = nodes[hexes]  # positive volumes, the contact face (nodes 5-8) towards the patella (+y)
    jac = np.einsum("ij,ij->i", np.cross(c[:, 1] - c[:, 0], c[:, 3] - c[:, 0]), c[:, 4] - c[:, 0])
    assert np.all(jac > 0) and np.all(c[:, 4:, 1].mean(1) > c[:, :4, 1].mean(1))


def test_a_knee_without_a_patella_gets_a_tibiofemoral_model_that_runs(tmp_path):
    """The sample knee with its patella and patellar cartilage unlabelled (a field of view that misses it):
    the two tissues are review, not failed, and the decks are a tibiofemoral model, said so, whose smoke run
    completes with the femur's forces balanced."""
    import SimpleITK as sitk

    from kneemesh_core.job import JobRequest, run
    from kneemesh_core.knee import load_knee
    from kneemesh_core.tissues import LABEL

    knee = load_knee(real(SAMPLE))
    arr = sitk.GetArrayFromImage(knee.labels)
    arr[np.isin(arr, [LABEL["patella"], LABEL["patellar_cartilage"]])] = 0
    image = sitk.GetImageFromArray(arr)
    image.CopyInformation(knee.labels)
    path = tmp_path / "no_patella_right.nrrd"
    sitk.WriteImage(image, str(path))
    report = run(path, tmp_path / "job", JobRequest.build(preset="kneemesh", element_size=2.0, simulate="smoke").job_options())
    for t in ("patella", "patellar_cartilage"):
        assert report["tissues"][t]["status"] == "review" and "not labelled" in report["tissues"][t]["reasons"][0]
    assert report["fe"]["status"] == "review" and report["fe"]["model"] == "tibiofemoral"
    assert "PATELLA" not in (tmp_path / "job" / "fe" / "knee_ccx.inp").read_text()
    sim = report["simulation"]
    assert sim["completed"] and "patellofemoral" not in sim["final"] and sim["final"]["balance_error"] < MAX_BALANCE_ERROR
    assert report["verdict"]["status"] == "review"


def test_a_load_option_changes_the_load_the_deck_applies(knee):
    """The joint load, its medial offset, the quadriceps force and the flexion are options of a job (one
    declaration, JobRequest), and of a run: a run under another load gets a model of its own beside the
    job's decks, whose deck applies that load and its moment, and the femur carries it: the plates take
    about the added 500 N, and the load 10 mm further medial moves a tenth of it to the medial compartment."""
    from dataclasses import replace

    from kneemesh_core.fe.results import tibiofemoral_n
    from kneemesh_core.fe.run import run_folder, simulate
    from kneemesh_core.job import JobRequest

    assert JobRequest.build(joint_load=1500, medial_offset=5, quadriceps=200, flexion=60).job_options().load == LoadCase(
        joint_load_n=1500.0, medial_offset_mm=5.0, quadriceps_n=200.0, flexion_deg=60.0)
    out, report = knee
    offset = LoadCase().medial_offset_mm + 10.0
    load = replace(LoadCase(), joint_load_n=1500.0, quadriceps_n=200.0, medial_offset_mm=offset)
    r = simulate(out, smoke=True, load=load)
    folder = out / run_folder(True, None, load)
    assert folder.name == f"smoke_1500N_200N_{offset:g}mm_rigid"
    ccx = (folder / "knee_ccx.inp").read_text()
    assert "*INCLUDE, INPUT=knee_model.inp" in ccx and (folder / "knee_model.inp").exists()
    meta = json.loads((folder / "model.json").read_text())
    cload = [line.split(",") for line in ccx.split("*CLOAD, AMPLITUDE=HOLD\n")[1].split("*")[0].strip().splitlines()]
    force = np.array([float(v) for n, _, v in cload if int(n) == meta["ref"]["femur"]])
    moment = {int(d): float(v) for n, d, v in cload if int(n) == meta["rot"]["femur"]}
    assert np.linalg.norm(force) == pytest.approx(1500.0, abs=0.01)
    # the load's line passes medial of the femur's node (a right knee's medial side is deck -X): the moment of
    # the force there, about the anterior axis (deck Y) the medial side down
    expected = np.cross([-offset, 0.0, 0.0], force)
    np.testing.assert_allclose([moment.get(d, 0.0) for d in (1, 2, 3)], expected, atol=0.01)
    assert expected[1] < -0.5 * 1500.0 * offset  # (deck Y: the femur's anterior axis, the image pose's flexion off the tibia's)
    assert r["joint_load"]["adduction_moment_nm"] == pytest.approx(np.linalg.norm(expected) / 1000.0, abs=0.01)
    assert "200 N at its initial length" in (folder / "knee_model.inp").read_text()
    assert r["completed"] and r["applied_load_n"] == 1500.0 and r["quadriceps_n"] == 200.0
    before = json.loads((out / "fe" / "smoke" / "results.json").read_text())
    first, base = loaded(r["increments"])[0], loaded(before["increments"])[0]
    added = tibiofemoral_n(first) - tibiofemoral_n(base)
    assert 400.0 < added < 600.0, added

    def medial_share(row):
        return (row["medial"]["force_n"] + row.get("medial_meniscus", {}).get("force_n", 0.0)) / tibiofemoral_n(row)

    assert medial_share(first) > medial_share(base) + 0.08, (medial_share(first), medial_share(base))



def test_in_anatomical_extension_the_plateau_carries_the_joint_load_not_the_ligaments_pull(knee):
    """The ligaments' slack lengths are set in anatomical extension (the reference pose of their strains), not in
    the image pose, 24 deg flexed on the sample: brought to extension under 1 kN the knee's plateau carries
    about the joint load (1.1 kN on the sample; set in the image pose, 3.5 kN: its collaterals and posterior
    capsule pulled the femur onto the plateau at 300-960 N each), and the run balances.  The meniscus rings are
    shaped clear of the femur from anatomical extension on, so there the plates carry the load, not the rings
    (shaped for the image pose's flexion onwards only, the sample's rings carried 32 % of it in extension)."""
    from dataclasses import replace

    from kneemesh_core.fe.results import tibiofemoral_n
    from kneemesh_core.fe.run import deck_load, simulate

    out, _ = knee
    load = replace(deck_load(out / "fe"), activity="knee_bend", peak_load_n=LoadCase().joint_load_n, flexion_deg=5.0)
    r = simulate(out, load=load)
    assert r["completed"] and r["reached_flexion_deg"] == pytest.approx(5.0, abs=0.01), r["reason"]
    extension = next(inc for inc in r["increments"] if inc["time"] == pytest.approx(2.0))
    assert extension["anatomical_flexion_deg"] == pytest.approx(0.0, abs=0.01)
    assert extension["balance_error"] < MAX_BALANCE_ERROR, extension
    assert 0.85 * load.joint_load_n < tibiofemoral_n(extension) < 1.3 * load.joint_load_n, tibiofemoral_n(extension)
    rings = extension["medial_meniscus"]["force_n"] + extension["lateral_meniscus"]["force_n"]
    assert rings < 0.1 * tibiofemoral_n(extension), extension


def test_the_knee_bend_starts_at_anatomical_extension_and_carries_its_peak_load_at_its_deepest_flexion(knee, tmp_path):
    """The paper's activity as an option (JobRequest ``activity``, ``peak_load``): after the seating at the image
    pose, both dialects turn the femur to anatomical extension (the image pose's flexion back), bend it to the
    flexion asked for (anatomical) while the joint load rises to its peak, and bring it back with the load falling;
    ccx's steps prescribe the flexion and the load of each leg, the Abaqus steps follow the same points, and the
    results read the load at any time from the schedule the model records.  Without an anatomical angle the
    activity is refused, not run from the image pose."""
    from dataclasses import replace

    from kneemesh_core.errors import KneeMeshError
    from kneemesh_core.fe import abaqus
    from kneemesh_core.fe.physics import legs
    from kneemesh_core.fe.results import activity_start, joint_load_at
    from kneemesh_core.fe.run import deck_load, read_model
    from kneemesh_core.job import JobRequest

    load = replace(deck_load(knee[0] / "fe"), activity="knee_bend", peak_load_n=3000.0, flexion_deg=80.0)
    assert JobRequest.build(activity="knee_bend", peak_load=3000, flexion=80).job_options().load == replace(
        LoadCase(), activity="knee_bend", peak_load_n=3000.0, flexion_deg=80.0)
    model = read_model(knee[0], load)
    image = model.frame["image_flexion_deg"]
    assert -10.0 < image < 45.0
    deck.write(model, tmp_path, 80.0, load.max_increment_deg)
    ccx = (tmp_path / deck.CCX_FILE).read_text()
    meta = json.loads((tmp_path / deck.META_FILE).read_text())
    assert meta["activity"] == "knee_bend" and meta["peak_load_n"] == 3000.0
    steps = ccx.split("*STEP")[1:]
    assert len(steps) == 1 + 3  # the seating, then the three legs
    femur, dof = meta["rot"]["femur"], 1
    want = [(-image, 1000.0), (80.0 - image, 3000.0), (-image, 1000.0)]
    for step, (flexion, joint) in zip(steps[1:], want):
        turn = [line.split(",") for line in step.split("*BOUNDARY\n")[1].split("*")[0].strip().splitlines()]
        assert [(int(n), int(d)) for n, d, _, _ in turn] == [(femur, dof)]
        assert np.degrees(float(turn[0][3])) == pytest.approx(flexion, abs=1e-3)
        if "*CLOAD" in step:
            cload = [line.split(",") for line in step.split("*CLOAD\n")[1].split("*")[0].strip().splitlines()]
            force = np.array([float(v) for n, _, v in cload if int(n) == meta["ref"]["femur"]])
            assert np.linalg.norm(force) == pytest.approx(joint, rel=1e-4)
        else:
            assert joint == load.joint_load_n  # the leg to extension keeps the seating's load
    schedule = meta["joint_load_schedule"]
    assert schedule == [[1.0, 1000.0], [2.0, 1000.0], [3.0, 3000.0], [4.0, 1000.0]]
    assert joint_load_at(meta, 0.5) == 1000.0 and joint_load_at(meta, 2.5) == pytest.approx(2000.0)
    assert joint_load_at(meta, 3.75) == pytest.approx(1500.0)
    assert activity_start(meta) == 2.0  # its flexion counts once at extension, not from the flexed image pose
    abq = abaqus.deck(model, deck.MODEL_FILE)
    assert "*STEP, NAME=KNEE_BEND" in abq
    flex = [float(v) for v in abq.split("*AMPLITUDE, NAME=FLEXION, DEFINITION=SMOOTH STEP, TIME=TOTAL TIME\n")[1]
            .split("*")[0].replace("\n", ",").split(",") if v.strip()]
    np.testing.assert_allclose(np.degrees(flex[1::2]), [0.0, -image, 80.0 - image, -image], atol=1e-3)
    with pytest.raises(KneeMeshError, match="anatomical extension"):
        legs(load, 80.0, None)


def test_a_knee_in_varus_flexes_on_its_plateau_without_sliding_off_it(tmp_path):
    """OAI 9153013 at its 96-month visit lies in 5 deg of varus, so the joint load, down the tibial axis, leans
    medially on its femur.  Held medial-laterally by a weak stabiliser only, the femur slid 16 mm medially by 18 deg
    of flexion and left the tibia at 51 deg; the medial-lateral restraint (the tibial eminence and meniscal horns
    the model leaves out) keeps it on the plateau to 60 deg, within a few millimetres of where it was seated."""
    from kneemesh_core.fe.run import simulate
    from kneemesh_core.job import JobRequest, run

    run(str(real(OAI / "OAI_AKOA_9153013_96m.nii.gz")), tmp_path, JobRequest.build().job_options(), workers=2)
    r = simulate(tmp_path, flexion_deg=60.0)
    assert r["completed"] and r["reached_flexion_deg"] == pytest.approx(60.0, abs=0.01), r["reason"]
    folder = tmp_path / r["folder"]
    femur = json.loads((folder / deck.META_FILE).read_text())["ref"]["femur"]
    shifts = parse_dat(folder / "knee_ccx.dat")["nodes"][("displacements", "REFS")]
    medial_lateral = np.array([u[femur][0] for t, u in sorted(shifts.items()) if t >= 1.0])
    assert np.abs(medial_lateral - medial_lateral[0]).max() < 5.0, medial_lateral


def test_the_joint_load_passes_medial_of_a_right_knee_and_of_its_mirror_image(tmp_path):
    """The medial offset on both sides: the sample and its mirror image through the sagittal plane (a left
    knee) place the joint load's line of action the default offset medial of the femur's flexion-axis
    middle (against the femoral frame's lateral axis), with the same adduction moment, at mirrored points."""
    import SimpleITK as sitk

    from conftest import mirror_lr
    from kneemesh_core.job import JobRequest, run

    mirrored = tmp_path / "mirrored.nrrd"
    sitk.WriteImage(mirror_lr(sitk.ReadImage(str(real(SAMPLE)))), str(mirrored))
    offset, lines = LoadCase().medial_offset_mm, {}
    for side, path in (("right", real(SAMPLE)), ("left", mirrored)):
        run(str(path), tmp_path / side, JobRequest.build(side=side).job_options(), workers=2)
        line = json.loads((tmp_path / side / "fe" / "model.json").read_text())["joint_load"]
        femur = json.loads((tmp_path / side / "attachments.json").read_text())["frames"]["femur"]
        lateral = np.subtract(line["through_lps_mm"], femur["origin_mm"]) @ np.asarray(femur["axes"]["lateral"])
        assert lateral == pytest.approx(-offset, abs=1.5), (side, line, femur)
        # the whole moment: the load's line lies the offset medial of the node (the offset is normal to the load)
        assert line["adduction_moment_nm"] == pytest.approx(offset * line["force_n"] / 1000.0, rel=0.01)
        lines[side] = np.asarray(line["through_lps_mm"])
    assert lines["left"] * [-1, 1, 1] == pytest.approx(lines["right"], abs=1.0)  # LPS x -> -x


def test_deformable_cartilage_is_solid_with_only_its_bone_side_on_the_bone(knee):
    """With deformable cartilage every cartilage hexahedron is a solid (physics.CARTILAGE_ELEMENT) of a
    neo-Hookean material, and of its nodes only the bone side rides in a rigid body (CalculiX's body NSETs,
    Abaqus's pins); the rigid model keeps its skins and puts all of them in."""
    from kneemesh_core.fe.calculix import deformable_nodes
    from kneemesh_core.fe.physics import CARTILAGE_ELEMENT, neo_hooke
    from kneemesh_core.fe.run import read_model
    from kneemesh_core.tissues import CARTILAGES

    out, _ = knee
    m = read_model(out, LoadCase(cartilage="deformable"))
    cartilages = [m.parts[t] for t in CARTILAGES if t in m.parts]
    assert cartilages and all(p.element_type == CARTILAGE_ELEMENT and p.connectivity.shape[1] == 8 for p in cartilages)
    riding = {n for nodes in m.body_nodes.values() for n in nodes}
    for p in cartilages:
        grid = pv.read(out / "meshes" / f"{p.name}.vtu")
        assert len(p.elements) == grid.n_cells
        nodes = set(np.unique(p.connectivity).tolist())
        bone_side = int(np.asarray(grid.point_data["bone_side"], bool).sum())
        assert len(nodes & riding) == bone_side < len(nodes)
    assert set(deformable_nodes(m).tolist()) == {n for p in cartilages for n in np.unique(p.connectivity).tolist()}
    model = deck.shared(m)
    c10, d1 = neo_hooke()
    assert "*HYPERELASTIC, NEO HOOKE" in model and f"{c10:.6f}, {d1:.6f}" in model
    assert f"*ELEMENT, TYPE={CARTILAGE_ELEMENT}, ELSET=FEMORAL_CARTILAGE" in model
    rigid = read_model(out, LoadCase())
    skin = {n for t in CARTILAGES if t in rigid.parts for n in np.unique(rigid.parts[t].connectivity).tolist()}
    assert skin <= {n for nodes in rigid.body_nodes.values() for n in nodes}


def _neo_hooke_uniaxial(stretch: float) -> tuple[float, float]:
    """The lateral stretch and the axial Cauchy stress (MPa) of the deck's compressible neo-Hookean cartilage
    (physics.neo_hooke: W = C10 (I1bar - 3) + (J - 1)^2 / D1) in uniaxial stress at axial ``stretch``."""
    from scipy.optimize import brentq

    from kneemesh_core.fe.physics import neo_hooke

    c10, d1 = neo_hooke()

    def stress(mu: float) -> np.ndarray:  # Cauchy: 2 C10 / J dev(Bbar) + 2 / D1 (J - 1) I
        b = np.array([mu ** 2, mu ** 2, stretch ** 2])
        j = mu * mu * stretch
        bbar = j ** (-2.0 / 3.0) * b
        return 2.0 * c10 / j * (bbar - bbar.sum() / 3.0) + 2.0 / d1 * (j - 1.0)

    mu = brentq(lambda x: stress(x)[0], 0.9, 1.1)
    return mu, float(stress(mu)[2])


def test_a_deformable_block_pressed_by_a_frictionless_rigid_plate_has_the_analytic_stress_and_strain(tmp_path):
    """A block of the deck's deformable cartilage (element, neo-Hookean material) between two frictionless
    rigid plates, the lower one held and the upper one pressed 3 % down (the faces' nodes held or moved along
    z only, free to slide): uniaxial stress.  The .frd reader's stress and strain match the analytic
    solution at every node: von Mises stress |sigma_zz|, compressive strain -E_zz and shear strain
    E_xx - E_zz (Lagrangian, as ccx writes them under NLGEOM)."""
    from kneemesh_core.fe.cartilage_fields import principal, read_frd, summaries, von_mises
    from kneemesh_core.fe.physics import CARTILAGE_ELEMENT

    nodes, hexes, _, _ = _block(2, 0.0, 1, 1)
    squeeze = 0.03
    bottom = [n for n, p in nodes.items() if p[2] < 1e-9]
    top = [n for n, p in nodes.items() if p[2] > 1 - 1e-9]
    corner = next(n for n in bottom if nodes[n][0] < 1e-9 and nodes[n][1] < 1e-9)
    beside = next(n for n in bottom if nodes[n][0] > 1 - 1e-9 and nodes[n][1] < 1e-9)
    w = ["*NODE", *(f"{n}, {p[0]:.6f}, {p[1]:.6f}, {p[2]:.6f}" for n, p in nodes.items()),
         f"*ELEMENT, TYPE={CARTILAGE_ELEMENT}, ELSET=BLOCK", *(f"{e}, " + ", ".join(str(int(x)) for x in c) for e, c in hexes.items()),
         *set_lines("NSET", "ALL", sorted(nodes)), "*MATERIAL, NAME=CARTILAGE", *deck.cartilage_law("deformable"),
         "*SOLID SECTION, ELSET=BLOCK, MATERIAL=CARTILAGE", "*STEP, NLGEOM", "*STATIC", "0.25, 1.0", "*BOUNDARY",
         *(f"{n}, 3, 3, 0.0" for n in bottom), f"{corner}, 1, 2, 0.0", f"{beside}, 2, 2, 0.0",
         *(f"{n}, 3, 3, {-squeeze}" for n in top), "*NODE FILE, NSET=ALL", "U", "*EL FILE, NSET=ALL", "S, E", "*END STEP"]
    (tmp_path / "block.inp").write_text("\n".join(w) + "\n")
    run = run_ccx(tmp_path, "block", timeout_s=120)
    assert run.completed, run.reason
    frd = read_frd(tmp_path / "block.frd")
    assert len(frd["hexes"][0]) == len(hexes) and len(frd["nodes"][0]) == len(nodes)
    last = frd["steps"][-1]
    assert last["time"] == pytest.approx(1.0)
    stretch = 1.0 - squeeze
    mu, sigma = _neo_hooke_uniaxial(stretch)
    stress, strain = last["blocks"]["STRESS"][1], last["blocks"]["TOSTRAIN"][1]
    assert von_mises(stress) == pytest.approx(abs(sigma), rel=1e-3)
    e = principal(strain)
    assert e[:, 0] == pytest.approx((stretch ** 2 - 1) / 2, rel=1e-3)  # E_zz
    assert e[:, 2] == pytest.approx((mu ** 2 - 1) / 2, rel=1e-3)  # E_xx = E_yy
    assert last["blocks"]["DISP"][1][:, 2].min() == pytest.approx(-squeeze, rel=1e-6)
    peaks = summaries(frd, {"block": [1, len(hexes)]})[last["time"]]["block"]
    assert peaks["peak_von_mises_mpa"] == pytest.approx(abs(sigma), rel=1e-3)
    assert peaks["peak_compressive_stress_mpa"] == pytest.approx(-sigma, rel=1e-3) and sigma < 0
    assert peaks["peak_compressive_strain"] == pytest.approx((1 - stretch ** 2) / 2, rel=1e-3)
    assert peaks["peak_shear_strain"] == pytest.approx((mu ** 2 - stretch ** 2) / 2, rel=1e-3)


def test_a_deformable_smoke_run_of_a_real_knee_balances_and_reports_the_cartilage_stress_and_strain(knee):
    """``kneemesh simulate --fe-cartilage deformable`` on a real knee: a model of its own whose CalculiX run
    starts from the rigid model's seated equilibrium (carried there, then released: from the seated pose it
    diverges), completes the smoke flexion with the femur's forces balanced, and reports per loaded increment
    each cartilage's peak stress and strains; their fields lie beside the results as VTU (LPS), the held
    tibia's bone side unmoved, the peaks those of the fields."""
    from dataclasses import replace

    from scipy.spatial import cKDTree

    from kneemesh_core.fe.results import plate_peak, tibiofemoral_n
    from kneemesh_core.fe.run import POSE_DIR, deck_load, run_folder, simulate, simulation_entry
    from kneemesh_core.tissues import CARTILAGES

    out, _ = knee
    load = replace(deck_load(out / "fe"), cartilage="deformable")
    r = simulate(out, smoke=True, load=load)
    folder = out / run_folder(True, None, load)
    assert folder.name.endswith("_deformable") and r["completed"], r["reason"]
    steps = (folder / "knee_ccx.inp").read_text().split("*STEP")[1:]
    meta = json.loads((folder / "model.json").read_text())
    assert len(steps) == 3 and "*BOUNDARY, AMPLITUDE=RAMP" in steps[0] and "*BOUNDARY, OP=NEW" in steps[1]
    prescribed = steps[0].split("*BOUNDARY, AMPLITUDE=RAMP\n")[1].split("*")[0].split()
    assert f"{meta['ref']['patella']}," in prescribed and f"{meta['rot']['patella']}," in prescribed
    assert (folder / POSE_DIR / "knee_ccx.dat").exists() and meta["loaded_at"] == 2.0
    on = loaded(r["increments"])
    assert on[0]["time"] == pytest.approx(2.0) and on[-1]["flexion_deg"] == pytest.approx(15.0, abs=1e-3)
    for inc in on:
        assert inc["balance_error"] < MAX_BALANCE_ERROR and tibiofemoral_n(inc) > 0.8 * load.joint_load_n, inc
        assert set(inc["cartilage"]) == set(CARTILAGES), inc
        for peaks in inc["cartilage"].values():
            assert 0 < peaks["peak_von_mises_mpa"] < 50 and 0 < peaks["peak_compressive_strain"] < 0.7, peaks
            assert 0 < peaks["peak_compressive_stress_mpa"] < 50, peaks
        # the plates' physiology reads the tibial cartilage's compression, not the contact's integration points
        assert plate_peak(inc, "medial") == inc["cartilage"]["medial_tibial_cartilage"]["peak_compressive_stress_mpa"]
    entry = simulation_entry(r, "smoke", run_folder(True, None, load))
    assert {f"{folder.relative_to(out)}/cartilage_{t}.vtu" for t in CARTILAGES} <= set(entry["files"])
    plate = pv.read(folder / "cartilage_medial_tibial_cartilage.vtu")
    mesh = pv.read(out / "meshes" / "medial_tibial_cartilage.vtu")
    assert plate.n_cells == mesh.n_cells
    np.testing.assert_allclose(np.sort(plate.points, axis=0), np.sort(np.asarray(mesh.points), axis=0), atol=1e-3)
    k = len(on) - 1
    assert plate.field_data["flexion_deg"][k] == pytest.approx(15.0, abs=1e-3)
    bone_side = np.asarray(mesh.point_data["bone_side"], bool)
    _, order = cKDTree(np.asarray(plate.points)).query(np.asarray(mesh.points)[bone_side])
    assert np.abs(plate.point_data[f"displacement_mm_{k}"][order]).max() < 1e-6  # the tibia is held
    assert np.abs(plate.point_data[f"displacement_mm_{k}"]).max() > 0.05  # its articular side is pressed
    assert plate.point_data[f"von_mises_mpa_{k}"].max() == pytest.approx(
        on[-1]["cartilage"]["medial_tibial_cartilage"]["peak_von_mises_mpa"], abs=1e-3)


def test_a_cartilage_mesh_with_an_inverted_element_is_refused_for_the_deformable_model_with_its_reason():
    """Deformable cartilage needs solid elements that cannot invert: a mesh with an inverted element (or one
    below the usable scaled Jacobian) is refused with the tissue and the figures, and the rigid model is named
    as the way to run the knee; a sound mesh passes."""
    from kneemesh_core.fe.model import build, unfit_to_deform

    nodes, hexes, _, _ = _block(2, 0.0, 0, 0)
    points = np.array([nodes[i] for i in range(len(nodes))], float)
    cells = np.array(list(hexes.values()), int)
    sound = pv.UnstructuredGrid({pv.CellType.HEXAHEDRON: cells}, points)
    assert unfit_to_deform({"medial_tibial_cartilage": sound}) == []
    bad = points.copy()
    bad[cells[0][0]] = bad[cells[0][6]] + 0.2  # the block's corner, the first element's alone, pushed through it
    reasons = unfit_to_deform({"medial_tibial_cartilage": pv.UnstructuredGrid({pv.CellType.HEXAHEDRON: cells}, bad)})
    assert len(reasons) == 1 and reasons[0].startswith("medial_tibial_cartilage has 1 inverted"), reasons
    with pytest.raises(KneeMeshError) as err:
        build({}, {"medial_tibial_cartilage": pv.UnstructuredGrid({pv.CellType.HEXAHEDRON: cells}, bad)}, {},
              LoadCase(cartilage="deformable"))
    assert err.value.code == "deformable_refused" and "--fe-cartilage rigid" in err.value.message
