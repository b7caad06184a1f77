"""Volume I/O: geometry survives every format; bad input gives one clear error."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest
import SimpleITK as sitk

from kneemesh_core import KneeMeshError
from kneemesh_core.io import read_label_map, read_volume, voxel_to_lps, write_image


def _volume(dtype=np.uint8) -> sitk.Image:
    rng = np.random.default_rng(0)
    arr = rng.integers(0, 8, size=(12, 20, 24)).astype(dtype)
    im = sitk.GetImageFromArray(arr)
    im.SetSpacing((0.3645833333, 0.3645833333, 0.7000001))
    im.SetOrigin((-24.3212345, -87.7198765, 71.9412345))
    th = np.deg2rad(8.0)  # OAI-like oblique sagittal: PIR rotated in the axial plane
    im.SetDirection((np.sin(th), 0.0, -np.cos(th), np.cos(th), 0.0, np.sin(th), 0.0, -1.0, 0.0))
    return im


def _same_geometry(a: sitk.Image, b: sitk.Image, tol=1e-6):
    assert a.GetSize() == b.GetSize()
    np.testing.assert_allclose(a.GetSpacing(), b.GetSpacing(), atol=tol)
    np.testing.assert_allclose(a.GetOrigin(), b.GetOrigin(), atol=tol)
    np.testing.assert_allclose(a.GetDirection(), b.GetDirection(), atol=tol)
    np.testing.assert_array_equal(sitk.GetArrayViewFromImage(a), sitk.GetArrayViewFromImage(b))


@pytest.mark.parametrize("suffix", [".nrrd", ".mha", ".nii.gz", ".nii"])
def test_round_trip_keeps_geometry(tmp_path, suffix):
    im = _volume()
    path = write_image(im, tmp_path / f"labels{suffix}")
    back = read_label_map(path).image
    # NIfTI stores the affine in float32: sub-micrometre rounding, nothing more
    _same_geometry(im, back, tol=1e-6 if suffix in (".nrrd", ".mha") else 2e-5)
    corner = np.array([[23, 19, 11]])
    np.testing.assert_allclose(voxel_to_lps(back, corner), voxel_to_lps(im, corner), atol=1e-4)


def _write_dicom_series(im: sitk.Image, folder, description="SAG_3D_DESS_RIGHT", uid="1.2.826.0.1.3680043.2.1125.1"):
    folder.mkdir(parents=True, exist_ok=True)
    im16 = sitk.Cast(im, sitk.sitkInt16)
    writer = sitk.ImageFileWriter()
    writer.KeepOriginalImageUIDOn()
    d = im.GetDirection()
    for k in range(im.GetDepth()):
        sl = im16[:, :, k]
        pos = im.TransformIndexToPhysicalPoint((0, 0, k))
        for tag, value in {
            "0008|0060": "MR",
            "0008|103e": description,
            "0020|000e": uid,
            "0020|000d": "1.2.826.0.1.3680043.2.1125.9",
            "0020|0013": str(k + 1),
            "0020|0032": "\\".join(f"{p:.6f}" for p in pos),
            "0020|0037": "\\".join(f"{v:.9f}" for v in (d[0], d[3], d[6], d[1], d[4], d[7])),
            "0018|0050": f"{im.GetSpacing()[2]:.6f}",
            "0028|0030": f"{im.GetSpacing()[1]:.9f}\\{im.GetSpacing()[0]:.9f}",
            "0008|0018": f"{uid}.{k + 1}",
        }.items():
            sl.SetMetaData(tag, value)
        writer.SetFileName(str(folder / f"IM{k:04d}.dcm"))
        writer.Execute(sl)


def test_dicom_folder_and_zip_keep_geometry(tmp_path):
    im = _volume(np.int16)
    _write_dicom_series(im, tmp_path / "series")
    vol = read_volume(tmp_path / "series")
    _same_geometry(im, vol.image, tol=1e-4)
    assert vol.meta["series_description"] == "SAG_3D_DESS_RIGHT"
    with zipfile.ZipFile(tmp_path / "series.zip", "w") as zf:
        for f in sorted((tmp_path / "series").iterdir()):
            zf.write(f, f"DICOM/{f.name}")
    _same_geometry(im, read_volume(tmp_path / "series.zip").image, tol=1e-4)


def test_dicom_picks_dess_among_series_and_lists_when_ambiguous(tmp_path):
    im = _volume(np.int16)
    _write_dicom_series(im, tmp_path / "study" / "a", "SAG_3D_DESS_LEFT", uid="1.2.3.4.1")
    _write_dicom_series(im[:, :, :5], tmp_path / "study" / "b", "COR_IW_TSE", uid="1.2.3.4.2")
    vol = read_volume(tmp_path / "study")
    assert vol.image.GetSize() == im.GetSize()
    _write_dicom_series(im, tmp_path / "study" / "c", "SAG_3D_DESS_WE", uid="1.2.3.4.3")
    with pytest.raises(KneeMeshError) as e:
        read_volume(tmp_path / "study")
    assert e.value.code == "dicom_ambiguous" and "COR_IW_TSE" in e.value.message


def test_real_dicom_series_reads(tmp_path):
    from conftest import REAL, real

    vol = read_volume(real(REAL / "pymskt" / "dicom" / "MESE_T2_echo1"))
    assert vol.image.GetSize() == (256, 256, 24)
    np.testing.assert_allclose(vol.image.GetSpacing()[2], 4.0, atol=1e-3)


def _expect(code, path, reader=read_label_map, **kw):
    with pytest.raises(KneeMeshError) as e:
        reader(path, **kw)
    assert e.value.code == code, e.value.message
    assert len(e.value.message) > 20
    return e.value.message


def test_bad_inputs_have_clear_errors(tmp_path):
    (tmp_path / "notes.txt").write_text("not an image at all\n")
    _expect("not_an_image", tmp_path / "notes.txt")
    (tmp_path / "empty.nii.gz").write_bytes(b"")
    _expect("not_an_image", tmp_path / "empty.nii.gz")
    _expect("not_found", tmp_path / "missing.nrrd")

    good = write_image(_volume(), tmp_path / "good.nii")
    data = good.read_bytes()
    (tmp_path / "truncated.nii").write_bytes(data[: len(data) // 2])
    _expect("corrupt", tmp_path / "truncated.nii")

    flat = sitk.GetImageFromArray(np.ones((20, 24), np.uint8))
    assert "3-D" in _expect("not_3d", write_image(flat, tmp_path / "slice.nrrd"))
    one = sitk.GetImageFromArray(np.ones((1, 24, 20), np.uint8))  # one file of a DICOM series: a volume one slice thick
    message = _expect("not_3d", write_image(one, tmp_path / "one_slice.nrrd"))
    assert "a single slice (20 x 24 pixels)" in message and "not one file of it" in message
    four = sitk.GetImageFromArray(np.ones((2, 3, 20, 24), np.uint8), isVector=False)
    _expect("not_3d", write_image(four, tmp_path / "series4d.nii.gz"))

    _expect("empty_labels", write_image(sitk.Image(10, 10, 10, sitk.sitkUInt8), tmp_path / "zero.nrrd"))
    prob = sitk.GetImageFromArray(np.random.default_rng(1).random((6, 7, 8)).astype(np.float32))
    assert "integer" in _expect("float_labels", write_image(prob, tmp_path / "prob.nrrd"))

    odd = _volume()
    odd.SetSpacing((0.36, 0.36, 25.0))
    _expect("bad_spacing", write_image(odd, tmp_path / "odd.nrrd"))
    _expect("too_large", write_image(_volume(), tmp_path / "big.nrrd"), max_voxels=1000)


def test_integral_float_labels_are_accepted(tmp_path):
    arr = np.zeros((6, 7, 8), np.float32)
    arr[2:4, 2:5, 3:6] = 5.0
    vol = read_label_map(write_image(sitk.GetImageFromArray(arr), tmp_path / "f.nrrd"))
    assert sitk.GetArrayViewFromImage(vol.image).max() == 5
