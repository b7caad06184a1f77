"""Contact pressure maps a lab opens in ParaView: ``pressure_<tissue>.vtu`` beside ``results.json``.

For each cartilage that is a contact's slave (the tibial plates and the patellar cartilage), its hexahedra
from the job's mesh (``meshes/<tissue>.vtu``, LPS mm, the input's frame) in the deck (the articular layer
of a rigid cartilage, every layer of a deformable one) with one cell array per loaded increment,
``pressure_mpa_<k>`` (k = 0, 1, ...: the largest contact pressure ccx printed at the element's slave
integration points, MPa, every contact on that face together: femur and meniscus surrogate), and in field
data the increments' ``step_time`` and ``flexion_deg``.  The surfaces stay where the image put them: the
tibia is held, so a plate's map is where its contact is; the patella's is drawn on its image pose.
Written with pyvista (VTK XML), read back by any VTK reader.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyvista as pv

from kneemesh_core.fe.model import deck_cells
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


def write_maps(folder: Path, meshes: Path, meta: dict, stress: dict, increments: list[dict]) -> list[str]:
    """``pressure_<tissue>.vtu`` in ``folder`` for each slave cartilage whose mesh is in ``meshes``, over
    ``increments`` (the loaded ones of ``results.json``; ``stress``: time -> ccx's contact stress lines);
    returns the file names written."""
    written = []
    slaves = {surface.removesuffix("_ARTICULAR").lower(): tuple(meta["slave_elements"][name])
              for name, surface in meta["pairs"].items()}
    for tissue, (lo, hi) in sorted(slaves.items()):
        path = Path(meshes) / f"{tissue}.vtu"
        if not path.exists() or not increments:
            continue
        grid = pv.read(path)
        cells = deck_cells(grid, meta["cartilage"])
        if len(cells) != hi - lo + 1:  # not the mesh the deck was written from
            continue
        out = grid.extract_cells(cells)
        for k, inc in enumerate(increments):
            out.cell_data[f"pressure_mpa_{k}"] = element_pressure(stress.get(inc["time"], []), lo, len(cells))
        out.field_data["step_time"] = np.array([inc["time"] for inc in increments], float)
        out.field_data["flexion_deg"] = np.array([np.nan if inc["flexion_deg"] is None else inc["flexion_deg"]
                                                  for inc in increments], float)
        name = f"pressure_{tissue}.vtu"
        with atomic_path(folder / name) as tmp:
            out.save(tmp)
        written.append(name)
    return written
