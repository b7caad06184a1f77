"""A segmentation that is not a plausible knee is review with its reasons (checked on labels made
implausible on purpose, in the ways a network trained on synthetic images fails on real DESS)."""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk

from conftest import SAMPLE
from kneemesh_core.knee import load_knee
from kneemesh_core.segmentation.plausibility import check, figures
from kneemesh_core.tissues import LABEL


def _with(labels: sitk.Image, array: np.ndarray) -> sitk.Image:
    out = sitk.GetImageFromArray(array)
    out.CopyInformation(labels)
    return out


def test_a_real_knee_is_plausible_and_broken_ones_are_review_with_reasons():
    labels = load_knee(SAMPLE).labels
    f = figures(labels)
    assert check(f) == ("ok", []), check(f)
    assert 0.9 < f["on_bone"]["femoral_cartilage"] <= 1.0 and 5 < f["patella_anterior_mm"] < 80

    a = sitk.GetArrayFromImage(labels)
    # air in front of the knee read as femur: a block far from the bone
    air = a.copy()
    air[:40, :100, :100] = LABEL["femur"]  # about 37 ml, a sixth of the femur
    status, reasons = check(figures(_with(labels, air)))
    assert status == "review" and any(r.startswith("femur: in pieces") for r in reasons), reasons

    # the patella left as background (calf muscle read as patella elsewhere): the patellar cartilage floats
    floating = a.copy()
    floating[floating == LABEL["patella"]] = 0
    status, reasons = check(figures(_with(labels, floating)))
    assert status == "review" and any("patella: 0.00 ml" in r and "(missing)" in r for r in reasons)
    assert any(r.startswith("patellar cartilage: only 0%") for r in reasons), reasons

    # the femur and tibia swapped: each cartilage off its bone
    swapped = a.copy()
    swapped[a == LABEL["femur"]], swapped[a == LABEL["tibia"]] = LABEL["tibia"], LABEL["femur"]
    status, reasons = check(figures(_with(labels, swapped)))
    assert status == "review" and any(r.startswith("femoral cartilage: only") for r in reasons), reasons

    # the patella's front read as patellar cartilage, its true cartilage as bone (#51's plain rendering: patella
    # voxels and tissue in front called patellar cartilage): the cartilage faces away from the trochlea
    fc = np.argwhere(a == LABEL["femoral_cartilage"]).mean(0)
    patella = np.argwhere(a == LABEL["patella"])
    away = patella[np.linalg.norm(patella - fc, axis=1) > np.percentile(np.linalg.norm(patella - fc, axis=1), 85)]
    front = a.copy()
    front[a == LABEL["patellar_cartilage"]] = LABEL["patella"]
    front[tuple(away.T)] = LABEL["patellar_cartilage"]
    f = figures(_with(labels, front))
    status, reasons = check(f)
    assert f["patellar_cartilage_facing_mm"] < 0 < figures(labels)["patellar_cartilage_facing_mm"]
    assert status == "review" and any(r.startswith("patellar cartilage: its centre") for r in reasons), reasons
