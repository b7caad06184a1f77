"""Phantoms: deterministic, OAI geometry, anatomically sane, left/right correct."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from scipy import ndimage as ndi

from kneemesh_core.io import Volume
from kneemesh_core.knee import canonicalise
from kneemesh_core.phantom import make_phantom
from kneemesh_core.tissues import BONE_OF, CARTILAGES, LABEL


def test_same_seed_same_knee_and_seeds_differ(phantoms):
    image, labels = phantoms("right", 0)
    image2, labels2, _ = make_phantom(7, "right", 0)
    assert np.array_equal(sitk.GetArrayViewFromImage(labels), sitk.GetArrayViewFromImage(labels2))
    assert np.array_equal(sitk.GetArrayViewFromImage(image), sitk.GetArrayViewFromImage(image2))
    _, other = phantoms("right", 0, seed=8)
    assert not np.array_equal(sitk.GetArrayViewFromImage(labels), sitk.GetArrayViewFromImage(other))


def test_oai_geometry(phantoms):
    image, labels = phantoms("right", 0)
    assert image.GetSize() == (384, 384, 160) and labels.GetSize() == (384, 384, 160)
    np.testing.assert_allclose(image.GetSpacing(), (0.3645833, 0.3645833, 0.7), atol=1e-6)
    assert sitk.DICOMOrientImageFilter.GetOrientationFromDirectionCosines(image.GetDirection()) == "PIR"
    assert image.GetPixelID() == sitk.sitkInt16


@pytest.mark.parametrize("side,severity", [("right", 0), ("left", 3)])
def test_anatomy_sane(phantoms, side, severity):
    _, labels = phantoms(side, severity)
    knee = canonicalise(Volume(labels, "phantom.nii.gz"))
    assert knee.convention.name == "kneemesh" and knee.side == side
    arr = knee.array
    sp = np.asarray(labels.GetSpacing())[::-1]
    vols = knee.volumes_ml()
    assert 80 < vols["femur"] < 300 and 60 < vols["tibia"] < 250 and 8 < vols["patella"] < 35
    for cart in CARTILAGES:
        c = arr == LABEL[cart]
        assert 0.3 < vols[cart] < 25, cart
        # every cartilage sits on its own bone
        touching = ndi.binary_dilation(c) & (arr == LABEL[BONE_OF[cart]])
        assert touching.sum() > 0.2 * c.sum() ** (2 / 3), cart
        # thickness 1.5-3.5 mm when healthy: twice the inscribed distance on the medial surface
        box = ndi.find_objects(c.astype(np.uint8))[0]
        box = tuple(slice(max(b.start - 2, 0), b.stop + 2) for b in box)
        dist = ndi.distance_transform_edt(c[box], sampling=sp)
        ridge = (dist > 0) & (dist == ndi.maximum_filter(dist, 3))
        thick = 2 * dist[ridge] - sp.mean()  # EDT reaches background voxel centres: half a voxel each side
        low = 1.2 if severity == 0 else 0.6  # OA thins cartilage by up to a third
        assert low < np.median(thick) < 3.5 and np.percentile(thick, 95) < 4.2, (cart, np.percentile(thick, [50, 95]))
    # the femur stays above the tibia, the patella in front of the femur
    z = lambda lab: np.argwhere(arr == LABEL[lab])[:, 1].mean()  # j runs inferior
    assert z("femur") < z("tibia")
    a = lambda lab: np.argwhere(arr == LABEL[lab])[:, 2].mean()  # i runs posterior
    assert a("patella") < a("femur")


def test_severity_removes_cartilage(phantoms):
    _, healthy = phantoms("left", 0)
    _, severe = phantoms("left", 3)
    h = canonicalise(Volume(healthy, "p.nii.gz")).volumes_ml()
    s = canonicalise(Volume(severe, "p.nii.gz")).volumes_ml()
    assert s["medial_tibial_cartilage"] < 0.8 * h["medial_tibial_cartilage"]
    assert sum(s[c] for c in CARTILAGES) < sum(h[c] for c in CARTILAGES)


@pytest.mark.parametrize("seed,side,severity", [(30969, "left", 0), (30801, "left", 0)])
def test_cartilages_meet_half_way_and_never_reach_the_other_bone(seed, side, severity):
    """Where two cartilages meet, each stays on its own bone: a very thick knee (cartilage 1.3 x
    nominal, seed 30969) stands its bones apart by its cartilage, and the nearer bone's cartilage
    takes a voxel both shells reach (before, its femoral cartilage ran through the patellar cartilage
    onto the patella in 205 voxels, and a nominal knee's, seed 30801, in 77)."""
    _, labels, _ = make_phantom(seed, side, severity)
    arr = sitk.GetArrayViewFromImage(labels)
    near = lambda lab: ndi.binary_dilation(arr == LABEL[lab])
    fc = arr == LABEL["femoral_cartilage"]
    tc = np.isin(arr, [LABEL["medial_tibial_cartilage"], LABEL["lateral_tibial_cartilage"]])
    assert not (fc & near("patella")).any() and not (fc & near("tibia")).any()
    assert not (tc & near("femur")).any()
    assert (fc & near("patellar_cartilage")).sum() > 100  # they do meet
