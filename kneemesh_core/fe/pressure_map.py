"""Contact pressure maps a lab opens in ParaView: ``pressure_<tissue>.vtu`` beside ``results.json``.

For each cartilage that is a contact's slave (the tibial plates and the patellar cartilage), the articular
surface the contact ran on (a rigid cartilage's contact skin, :mod:`.contact_skin`; a deformable one's
articular hexahedral faces), LPS mm, the input's frame, with one cell array per loaded increment,
``pressure_mpa_<k>`` (k = 0, 1, ...: the largest contact pressure ccx printed at the face's slave
integration points, MPa, every contact on that face together: femur and meniscus surrogate), and in field
data the increments' ``step_time`` and ``flexion_deg``.  The surfaces are drawn in the pose the run started
from: the tibia is held, so a plate's map lies on the plate where the image put it; the patella's is drawn
where the seating put it (:func:`kneemesh_core.fe.model.seat_patella`: a fraction of a millimetre from its
image pose).
Written with pyvista (VTK XML), read back by any VTK reader.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyvista as pv

from kneemesh_core.io.files import atomic_path


def element_pressure(stress: list[tuple[int, float]], lo: int, n: int) -> np.ndarray:
    """The largest contact pressure (n,), MPa, of elements ``lo`` .. ``lo + n - 1`` from ccx's contact stress
    lines ((element, pressure) per slave integration point); 0 where none is printed."""
    out = np.zeros(n)
    if stress:
        e, p = np.asarray(stress, float).T
        inside = (e >= lo) & (e < lo + n)
        np.maximum.at(out, e[inside].astype(int) - lo, np.maximum(p[inside], 0.0))
    return out


def slave_surface(points_lps: np.ndarray, faces: np.ndarray, elements: np.ndarray) -> dict:
    """What a pressure map needs of a slave surface (``model.json``'s ``slave_surfaces``): its points (P, 3),
    LPS mm, its faces (F, 3 or 4) into them and the deck element (F,) each face belongs to."""
    return {"points_lps_mm": np.round(points_lps, 4).tolist(), "faces": np.asarray(faces).tolist(),
            "elements": np.asarray(elements).tolist()}


def write_maps(folder: Path, meta: dict, stress: dict, increments: list[dict]) -> list[str]:
    """``pressure_<tissue>.vtu`` in ``folder`` for each slave cartilage of ``meta`` (``model.json``), over
    ``increments`` (the loaded ones of ``results.json``; ``stress``: time -> ccx's contact stress lines);
    returns the file names written."""
    written = []
    if not increments:
        return written
    for tissue, surface in sorted(meta.get("slave_surfaces", {}).items()):
        faces, elements = np.asarray(surface["faces"], int), np.asarray(surface["elements"], int)
        kind = pv.CellType.TRIANGLE if faces.shape[1] == 3 else pv.CellType.QUAD
        out = pv.UnstructuredGrid({kind: faces}, np.asarray(surface["points_lps_mm"], float))
        lo, n = int(elements.min()), int(elements.max() - elements.min() + 1)
        for k, inc in enumerate(increments):
            out.cell_data[f"pressure_mpa_{k}"] = element_pressure(stress.get(inc["time"], []), lo, n)[elements - lo]
        name = f"pressure_{tissue}.vtu"
        save_series(out, increments, folder / name)
        written.append(name)
    return written


def save_series(grid: pv.UnstructuredGrid, increments: list[dict], path: Path) -> None:
    """Write ``grid``, whose arrays end in ``_<k>`` for the k-th of ``increments`` (rows of ``results.json``),
    with their ``step_time`` and ``flexion_deg`` in field data (NaN where unknown), atomically."""
    grid.field_data["step_time"] = np.array([inc["time"] for inc in increments], float)
    grid.field_data["flexion_deg"] = np.array([np.nan if inc["flexion_deg"] is None else inc["flexion_deg"]
                                               for inc in increments], float)
    with atomic_path(path) as tmp:
        grid.save(tmp)
