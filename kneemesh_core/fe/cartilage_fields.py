"""Deformable cartilage's stress and strain: ccx's ``.frd`` read, summarised per cartilage and increment, and
written as ``cartilage_<tissue>.vtu`` beside ``results.json`` (ParaView opens it).

A run with deformable cartilage writes the cartilage's displacement (``DISP``), Cauchy stress (``STRESS``)
and total strain (``TOSTRAIN``: Lagrangian under NLGEOM, tensor components), extrapolated to the nodes, to
the ``.frd`` (:data:`kneemesh_core.fe.calculix.CARTILAGE_NODES`).  Per cartilage and increment:

- ``peak_von_mises_mpa``: the largest von Mises stress over its nodes, MPa;
- ``peak_compressive_strain``: the largest compression, minus the smallest principal strain (0 where none);
- ``peak_shear_strain``: the largest engineering shear strain, the largest less the smallest principal strain;
- ``peak_compressive_stress_mpa``: the largest compression, minus the smallest principal stress, MPa: the
  pressure the tissue carries.  Between deforming layers ccx's contact pressure at single slave integration
  points of faceted faces runs far above it (the sample in extension: the medial plate's contact peak 20.4 MPa,
  its cartilage's largest compression 6.1 MPa, the rigid model's contact peak 6.2 MPa).

Hand-written: ccx2paraview converts a whole ``.frd`` to VTU files but is no dependency here and gives
neither the cartilage's own element ranges nor the summaries; the format is ccx's documented fixed-width
one (``-1`` rows of a 10-character id and 12-character values).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyvista as pv

from kneemesh_core.fe.pressure_map import save_series

#: The ``.frd`` result blocks read, by ccx's name.
FIELDS = ("DISP", "STRESS", "TOSTRAIN")
#: ccx's element type code of an 8-node hexahedron in the ``.frd``.
FRD_HEX = 1


def _rows(lines: list[bytes], width: int) -> tuple[np.ndarray, np.ndarray]:
    """The ids (R,) and values (R, width) of ``.frd`` ``-1`` rows: a 3-character key, a 10-character id,
    then ``width`` values of 12 characters, which may run into each other (``-1.3E+00-1.7E-01``)."""
    n = 13 + 12 * width
    raw = np.frombuffer(b"".join(line[:n].ljust(n) for line in lines), np.uint8).reshape(len(lines), n)
    ids = raw[:, 3:13].tobytes()
    values = raw[:, 13:].reshape(len(lines), width, 12)
    spaced = np.concatenate([np.full((len(lines), width, 1), ord(" "), np.uint8), values], axis=2)
    return (np.array(ids.split(), int), np.array(spaced.tobytes().split(), float).reshape(len(lines), width))


def read_frd(path: Path) -> dict:
    """A ccx ``.frd`` file: ``nodes`` (ids (N,), coordinates (N, 3), mm), ``hexes`` (ids (E,), nodes (E, 8))
    and ``steps``: per result set, its total time and the blocks of :data:`FIELDS` it holds, each as node
    ids (R,) and values (R, 3) for DISP, (R, 6) for STRESS and TOSTRAIN (xx, yy, zz, xy, yz, zx).  A block
    cut short (a run that was stopped) ends the reading."""
    lines = Path(path).read_bytes().splitlines()
    out: dict = {"nodes": (np.zeros(0, int), np.zeros((0, 3))), "hexes": (np.zeros(0, int), np.zeros((0, 8), int)),
                 "steps": []}
    i, time = 0, None
    while i < len(lines):
        line = lines[i]
        key = line[:7].strip()
        if key == b"2C":
            j = i + 1
            while j < len(lines) and lines[j].startswith(b" -1"):
                j += 1
            out["nodes"] = _rows(lines[i + 1:j], 3)
            i = j
            continue
        if key == b"3C":
            ids, conn, j = [], [], i + 1
            while j + 1 < len(lines) and lines[j].startswith(b" -1"):
                head, nodes = lines[j].split(), lines[j + 1].split()
                if int(head[2]) == FRD_HEX and nodes[0] == b"-2":
                    ids.append(int(head[1]))
                    conn.append([int(v) for v in nodes[1:9]])
                j += 2
            out["hexes"] = (np.array(ids, int), np.array(conn, int).reshape(-1, 8))
            i = j
            continue
        if key == b"100CL":
            time = float(line[12:24])
            name = lines[i + 1].split()[1].decode() if i + 1 < len(lines) else ""
            j = i + 2
            while j < len(lines) and lines[j].startswith(b" -5"):
                j += 1
            k = j
            while k < len(lines) and lines[k].startswith(b" -1"):
                k += 1
            if k >= len(lines) or not lines[k].startswith(b" -3"):
                break  # cut short
            if name in FIELDS:
                if not out["steps"] or out["steps"][-1]["time"] != time:
                    out["steps"].append({"time": time, "blocks": {}})
                out["steps"][-1]["blocks"][name] = _rows(lines[j:k], 3 if name == "DISP" else 6)
            i = k + 1
            continue
        i += 1
    return out


def _tensor(v: np.ndarray) -> np.ndarray:
    """(R, 3, 3) symmetric tensors from ccx's (R, 6) components xx, yy, zz, xy, yz, zx."""
    xx, yy, zz, xy, yz, zx = v.T
    return np.stack([np.stack([xx, xy, zx], -1), np.stack([xy, yy, yz], -1), np.stack([zx, yz, zz], -1)], -2)


def von_mises(stress: np.ndarray) -> np.ndarray:
    """Von Mises stress (R,), MPa, of (R, 6) stress components xx, yy, zz, xy, yz, zx."""
    xx, yy, zz, xy, yz, zx = stress.T
    return np.sqrt(0.5 * ((xx - yy) ** 2 + (yy - zz) ** 2 + (zz - xx) ** 2) + 3.0 * (xy ** 2 + yz ** 2 + zx ** 2))


def principal(tensor6: np.ndarray) -> np.ndarray:
    """Principal values (R, 3), ascending, of (R, 6) symmetric tensor components."""
    return np.linalg.eigvalsh(_tensor(tensor6))


def _on(block: tuple[np.ndarray, np.ndarray], nodes: np.ndarray) -> np.ndarray:
    """A block's values at ``nodes`` (sorted ids), NaN where the block has none."""
    ids, values = block
    order = np.argsort(ids)
    at = np.clip(np.searchsorted(ids[order], nodes), 0, len(ids) - 1)
    found = ids[order][at] == nodes
    out = np.full((len(nodes), values.shape[1]), np.nan)
    out[found] = values[order][at[found]]
    return out


def _part(frd: dict, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
    """A part's hexahedra (E, 8), node ids, and its node ids (sorted), from its element ids ``lo`` to ``hi``."""
    elements, conn = frd["hexes"]
    hexes = conn[(elements >= lo) & (elements <= hi)]
    return hexes, np.unique(hexes)


def summaries(frd: dict, parts: dict[str, list[int]]) -> dict[float, dict[str, dict]]:
    """Per result set (total time) and cartilage, the peaks of the module's docstring; ``parts``:
    cartilage -> its first and last element id in the deck."""
    nodes_of = {tissue: _part(frd, lo, hi)[1] for tissue, (lo, hi) in parts.items()}
    out: dict = {}
    for step in frd["steps"]:
        if "STRESS" not in step["blocks"] or "TOSTRAIN" not in step["blocks"]:
            continue
        row = {}
        for tissue, nodes in nodes_of.items():
            stress, strain = _on(step["blocks"]["STRESS"], nodes), _on(step["blocks"]["TOSTRAIN"], nodes)
            ok = np.isfinite(stress).all(1) & np.isfinite(strain).all(1)
            if not ok.any():
                continue
            e = principal(strain[ok])
            row[tissue] = {"peak_von_mises_mpa": round(float(von_mises(stress[ok]).max()), 4),
                           "peak_compressive_stress_mpa": round(float(max(0.0, -principal(stress[ok])[:, 0].min())), 4),
                           "peak_compressive_strain": round(float(max(0.0, -e[:, 0].min())), 5),
                           "peak_shear_strain": round(float((e[:, 2] - e[:, 0]).max()), 5)}
        out[step["time"]] = row
    return out


def write_fields(folder: Path, frd: dict, parts: dict[str, list[int]], increments: list[dict], to_lps) -> list[str]:
    """``cartilage_<tissue>.vtu`` in ``folder`` for each cartilage of ``parts`` (cartilage -> first and last
    element id): its hexahedra in the undeformed pose the run started from, LPS mm (``to_lps``: deck frame
    points (P, 3) to LPS), and per increment ``k`` of ``increments`` (the loaded ones of ``results.json``)
    the point arrays ``displacement_mm_<k>`` (LPS), ``von_mises_mpa_<k>``, ``min_principal_stress_mpa_<k>``,
    ``min_principal_strain_<k>`` and ``max_shear_strain_<k>``; field data ``step_time`` and ``flexion_deg``.
    Returns the names written."""
    written = []
    steps = {s["time"]: s["blocks"] for s in frd["steps"]}
    increments = [inc for inc in increments if inc["time"] in steps]
    if not increments:
        return written
    node_ids, coords = frd["nodes"]
    order = np.argsort(node_ids)
    origin = to_lps(np.zeros((1, 3)))[0]
    for tissue, (lo, hi) in sorted(parts.items()):
        hexes, nodes = _part(frd, lo, hi)
        points = coords[order][np.searchsorted(node_ids[order], nodes)]
        grid = pv.UnstructuredGrid({pv.CellType.HEXAHEDRON: np.searchsorted(nodes, hexes)}, to_lps(points))
        for k, inc in enumerate(increments):
            blocks = steps[inc["time"]]
            if "DISP" in blocks:  # a displacement is a vector: rotated, not moved
                grid.point_data[f"displacement_mm_{k}"] = to_lps(_on(blocks["DISP"], nodes)) - origin
            if "STRESS" in blocks:
                stress = _on(blocks["STRESS"], nodes)
                grid.point_data[f"von_mises_mpa_{k}"] = von_mises(stress)
                grid.point_data[f"min_principal_stress_mpa_{k}"] = principal(np.nan_to_num(stress))[:, 0]
            if "TOSTRAIN" in blocks:
                e = principal(np.nan_to_num(_on(blocks["TOSTRAIN"], nodes)))
                grid.point_data[f"min_principal_strain_{k}"] = e[:, 0]
                grid.point_data[f"max_shear_strain_{k}"] = e[:, 2] - e[:, 0]
        name = f"cartilage_{tissue}.vtu"
        save_series(grid, increments, folder / name)
        written.append(name)
    return written
