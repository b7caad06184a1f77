"""Label conventions, left/right and medial/lateral on real, mirrored and phantom knees."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from conftest import OAI, PYMSKT_LEFT, PYMSKT_RIGHT, mirror_lr, real
from kneemesh_core import KneeMeshError
from kneemesh_core.io import Volume, read_label_map, voxel_to_lps
from kneemesh_core.knee import canonicalise, load_knee
from kneemesh_core.tissues import LABEL, PRESETS, parse_custom

MTC, LTC = LABEL["medial_tibial_cartilage"], LABEL["lateral_tibial_cartilage"]


def _x(knee, label):
    idx = np.argwhere(knee.array == label)[:, ::-1].mean(0, keepdims=True)
    return voxel_to_lps(knee.labels, idx)[0, 0]


def _neutral(path) -> Volume:
    """The label map with a file name that says nothing about the side."""
    vol = read_label_map(real(path))
    vol.source = "knee.nrrd"
    return vol


def _dice(a, b):
    return 2 * np.logical_and(a, b).sum() / (a.sum() + b.sum())


@pytest.mark.parametrize("path,side", [(PYMSKT_RIGHT, "right"), (PYMSKT_LEFT, "left")])
def test_pymskt_maps_preset_side_and_medial_position(path, side):
    knee = canonicalise(_neutral(path))
    assert knee.convention.name == "pymskt"
    assert knee.side == side and knee.side_method == "labels_medial_lateral"
    # medial faces +x (patient's left) in a right knee
    assert (_x(knee, MTC) > _x(knee, LTC)) == (side == "right")
    v = knee.volumes_ml()
    assert 150 < v["femur"] < 260 and 1.5 < v["medial_tibial_cartilage"] < 3.5


def test_file_name_hint_wins_over_anatomy():
    knee = load_knee(real(PYMSKT_RIGHT))
    assert knee.side == "right" and knee.side_method == "file_name"


def _as_oai_zib(knee) -> sitk.Image:
    """Canonical labels re-coded as oai-zib (tibial plates merged)."""
    a = knee.array
    lut = np.zeros(256, np.uint8)
    for t, v in {"femur": 1, "femoral_cartilage": 2, "tibia": 3, "medial_tibial_cartilage": 4,
                 "lateral_tibial_cartilage": 4, "patella": 5, "patellar_cartilage": 6}.items():
        lut[LABEL[t]] = v
    out = sitk.GetImageFromArray(lut[a])
    out.CopyInformation(knee.labels)
    return out


@pytest.mark.parametrize("path", [PYMSKT_RIGHT, PYMSKT_LEFT])
@pytest.mark.parametrize("mirrored", [False, True])
def test_merged_plates_split_correctly_on_left_right_and_mirrored(path, mirrored):
    truth = canonicalise(_neutral(path))
    merged = _as_oai_zib(truth)
    if mirrored:
        merged = mirror_lr(merged)
        truth_arr = sitk.GetArrayFromImage(mirror_lr(truth.labels))
    else:
        truth_arr = truth.array
    knee = canonicalise(Volume(merged, "knee.nii.gz"))
    assert knee.convention.name == "oai-zib"
    expected = {"right": "left", "left": "right"}[truth.side] if mirrored else truth.side
    assert knee.side == expected
    assert knee.side_method.startswith("shape")
    for lab in (MTC, LTC):
        assert _dice(knee.array == lab, truth_arr == lab) > 0.97


def test_touching_plates_are_split_at_the_gap():
    truth = canonicalise(_neutral(PYMSKT_RIGHT))
    arr = sitk.GetArrayFromImage(_as_oai_zib(truth))
    mtc, ltc = truth.array == MTC, truth.array == LTC
    # bridge the plates: fill the gap between them along the left-right voxel axis
    axis = 2 - int(np.argmax(np.abs(np.asarray(truth.labels.GetDirection()).reshape(3, 3)[0])))
    both = np.moveaxis(mtc | ltc, axis, 0)
    meet = np.moveaxis(mtc, axis, 0).any(0) & np.moveaxis(ltc, axis, 0).any(0)
    pos = np.arange(both.shape[0])[:, None, None]
    first = np.where(both, pos, both.shape[0]).min(0)
    last = np.where(both, pos, -1).max(0)
    bridge = np.moveaxis((pos >= first) & (pos <= last) & meet, 0, axis)
    bridge &= ~(mtc | ltc) & (arr == 0)
    assert bridge.sum() > 50
    arr[bridge] = 4
    im = sitk.GetImageFromArray(arr)
    im.CopyInformation(truth.labels)
    knee = canonicalise(Volume(im, "knee.nrrd"))
    assert knee.side == "right"
    keep = ~bridge  # the bridge belongs to neither plate; judge the plates themselves
    assert _dice((knee.array == MTC) & keep, mtc) > 0.97 and _dice((knee.array == LTC) & keep, ltc) > 0.97


@pytest.mark.parametrize("name", ["OAI_ZIB-UQ_9001104.nii.gz", "OAI_AKOA_9302260_00m.nii.gz", "OAI_AKOA_9014797_00m.nii.gz"])
def test_oai_maps_are_right_knees_with_medial_plate_medial(name):
    knee = load_knee(real(OAI / name))
    assert knee.convention.name == "oai-zib" and knee.side == "right"
    assert _x(knee, MTC) > _x(knee, LTC)
    assert knee.volumes_ml()["femur"] > 100  # lesion labels merged into the bone


def test_weak_evidence_that_disagrees_without_strong_evidence_asks_for_side():
    """No bones to read the shape from, plates merged: plateau length against scanner position."""
    truth = canonicalise(_neutral(PYMSKT_RIGHT))
    merged = sitk.GetArrayFromImage(_as_oai_zib(truth))
    merged[np.isin(merged, [1, 3, 5])] = 0  # cartilage only (oai-zib values), so no shape to fit
    a = int(np.argmax(np.abs(np.asarray(truth.labels.GetDirection()).reshape(3, 3)[0])))
    flipped = sitk.GetImageFromArray(np.flip(merged, axis=2 - a).copy())  # voxels mirrored, header kept
    flipped.CopyInformation(truth.labels)
    conv = PRESETS["oai-zib"]
    with pytest.raises(KneeMeshError) as e:
        canonicalise(Volume(flipped, "knee.nrrd"), conv)
    assert e.value.code == "side_conflict" and "--side" in e.value.message
    assert canonicalise(Volume(flipped, "knee.nrrd"), conv, side="left").side == "left"


def test_imorphics_cartilage_only_is_ambiguous_until_preset_given():
    truth = canonicalise(_neutral(PYMSKT_RIGHT))
    lut = np.zeros(256, np.uint8)
    lut[[LABEL["femoral_cartilage"], LTC, MTC, LABEL["patellar_cartilage"]]] = [1, 2, 3, 4]
    im = sitk.GetImageFromArray(lut[truth.array])
    im.CopyInformation(truth.labels)
    with pytest.raises(KneeMeshError) as e:
        canonicalise(Volume(im, "knee.nrrd"))
    assert e.value.code == "ambiguous_preset" and "--preset" in e.value.message
    knee = canonicalise(Volume(im, "knee.nrrd"), PRESETS["imorphics"])
    assert knee.side == "right" and not knee.convention.has_bones
    assert _dice(knee.array == MTC, truth.array == MTC) == 1.0


def test_custom_mapping_and_unknown_labels(tmp_path):
    conv = parse_custom("femoral_cartilage=1,medial_tibial_cartilage=2,lateral_tibial_cartilage=3,"
                        "patellar_cartilage=4,femur=5,tibia=6,patella=7")
    knee = canonicalise(_neutral(PYMSKT_RIGHT), conv)
    assert knee.volumes_ml() == pytest.approx(canonicalise(_neutral(PYMSKT_RIGHT)).volumes_ml())
    (tmp_path / "map.json").write_text('{"femur": [5], "tibia": 6}')
    with pytest.raises(KneeMeshError) as e:
        canonicalise(_neutral(PYMSKT_RIGHT), parse_custom(str(tmp_path / "map.json")))
    assert e.value.code == "unknown_labels" and "[1, 2, 3, 4, 7]" in e.value.message
    for bad in ("femur", "femur=x", "bone=3", "femur=1,tibia=1"):
        with pytest.raises(KneeMeshError):
            parse_custom(bad)


def test_one_pass_centroids_and_label_boxes_match_a_direct_count():
    """The ingest's centroids (one pass over the labelled voxels) and the masks' bounding boxes
    (from projections) are those that listing every voxel gives, on an oblique, anisotropic grid."""
    from scipy import ndimage as ndi

    from kneemesh_core.knee import _centroids
    from kneemesh_core.surfaces.masks import label_box

    rng = np.random.default_rng(3)
    arr = np.zeros((30, 40, 50), np.uint8)
    for value in (1, 2, 5):  # blobs; label 3 absent
        lo = rng.integers(0, 20, 3)
        arr[lo[0]:lo[0] + 9, lo[1]:lo[1] + 15, lo[2]:lo[2] + 25][rng.random((9, 15, 25)) < 0.5] = value
    image = sitk.GetImageFromArray(arr)
    image.SetSpacing((0.36, 0.36, 0.7))
    image.SetOrigin((-20.0, 15.0, 3.0))
    c, s = np.cos(0.3), np.sin(0.3)
    image.SetDirection((c, 0.0, s, 0.0, -1.0, 0.0, s, 0.0, -c))
    centre = _centroids(image, arr)
    assert sorted(centre) == [0, 1, 2, 5]
    for value in (0, 1, 2, 5):
        mask = arr > 0 if value == 0 else arr == value
        expected = voxel_to_lps(image, np.asarray(ndi.center_of_mass(mask))[None, ::-1])[0]
        np.testing.assert_allclose(centre[value], expected, atol=1e-9)
        idx = np.argwhere(mask)
        for margin in (0, 2, 30):
            box = label_box(mask, margin)
            assert [(b.start, b.stop) for b in box] == [
                (max(lo - margin, 0), min(hi + margin + 1, n)) for lo, hi, n in zip(idx.min(0), idx.max(0), arr.shape)]
    assert label_box(arr == 3) is None
