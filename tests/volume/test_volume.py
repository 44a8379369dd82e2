"""Tests of o3dreg.volume: the Volume value type and its readers (a round trip per format)."""

from __future__ import annotations

import shutil
import struct
from pathlib import Path

import nibabel as nib
import nrrd
import numpy as np
import pydicom
import pytest
import SimpleITK as sitk
from _helpers import write_dicom_series

from o3dreg import Volume, read_raw_slices, read_volume
from o3dreg.app.datasets import headsq_path

DATA = Path(__file__).resolve().parents[1] / "data"
HEADSQ = headsq_path().parent  # bundled with the package (o3dreg/data)

# Rotation about x by 20 degrees then about z by 30 degrees: a non-trivial direction.
_C, _S = np.cos(np.radians(20)), np.sin(np.radians(20))
_RX = np.array([[1, 0, 0], [0, _C, -_S], [0, _S, _C]])
_C, _S = np.cos(np.radians(30)), np.sin(np.radians(30))
_RZ = np.array([[_C, -_S, 0], [_S, _C, 0], [0, 0, 1]])
ROTATION = _RZ @ _RX
LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


@pytest.fixture
def ramp() -> np.ndarray:
    """A (4, 5, 6) int16 volume whose every voxel is distinct: pins the axis order."""
    return (np.arange(4 * 5 * 6, dtype=np.int16) * 7 - 50).reshape(4, 5, 6)


# -- the value type ----------------------------------------------------------------------------


def test_volume_geometry_conventions(ramp):
    v = Volume(ramp, spacing=(2.5, 1.0, 0.5), origin=(10, 20, 30))
    # array[p, r, c]: c runs along x with spacing[2], r along y, p along z.
    assert v.index_to_world([[1, 2, 4]]).tolist() == [[12.0, 22.0, 32.5]]
    affine = v.affine
    assert np.allclose(affine @ [4, 2, 1, 1], [12.0, 22.0, 32.5, 1.0])
    points = v.index_to_world([[0.5, 1.5, 2.5], [3, 4, 5]])
    assert np.allclose(v.world_to_index(points), [[0.5, 1.5, 2.5], [3, 4, 5]])
    assert v.shape == (4, 5, 6)


def test_volume_rotated_affine_and_inverse(ramp):
    v = Volume(ramp, spacing=(3.0, 2.0, 1.0), origin=(-5, 7, 1), direction=ROTATION)
    ijk = np.array([[1.0, 2.0, 3.0]])
    # (p, r, c) = (1, 2, 3): c * dx along column 0, r * dy along column 1, p * dz along column 2.
    expected = v.origin + ROTATION @ np.array([3 * 1.0, 2 * 2.0, 1 * 3.0])
    assert np.allclose(v.index_to_world(ijk)[0], expected)
    assert np.allclose(v.world_to_index(v.index_to_world(ijk)), ijk)
    assert "rotated" in repr(v)


def test_volume_is_immutable_view_and_input_untouched(ramp):
    before = ramp.copy()
    v = Volume(ramp, spacing=(1, 1, 1))
    assert np.shares_memory(v.array, ramp)  # no copy of a large scan
    with pytest.raises(ValueError):
        v.array[0, 0, 0] = 1
    with pytest.raises(ValueError):
        v.spacing[0] = 2.0
    assert ramp.flags.writeable
    assert np.array_equal(ramp, before)
    assert repr(v).count("\n") == 0
    assert repr(v).startswith("Volume(shape=(4, 5, 6), dtype=int16")


def test_volume_crop_moves_origin(ramp):
    v = Volume(ramp, spacing=(2, 3, 4), origin=(1, 1, 1), direction=ROTATION)
    sub = v.crop((1, 2, 3), (3, 5, 6))
    assert sub.shape == (2, 3, 3)
    assert np.allclose(sub.index_to_world([[0, 0, 0]]), v.index_to_world([[1, 2, 3]]))
    assert sub.array[0, 0, 0] == ramp[1, 2, 3]
    with pytest.raises(ValueError, match="`start` must be 3 integer indices, got 5"):
        v.crop(5, (3, 3, 3))
    with pytest.raises(ValueError, match="`stop` must be 3 integer indices"):
        v.crop((0, 0, 0), (3.5, 3, 3))


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"array": np.zeros((4, 4))}, ValueError, r"must be 3D .* got 2D"),
        ({"array": [[[1]]]}, TypeError, "must be a numpy array"),
        ({"array": np.zeros((2, 2, 2), complex)}, TypeError, "real numbers"),
        ({"spacing": (1, 0, 1)}, ValueError, r"`spacing` must be > 0"),
        ({"spacing": (1, 1)}, ValueError, r"`spacing` must have shape \(3,\)"),
        ({"origin": (0, np.nan, 0)}, ValueError, "`origin` must be finite"),
        ({"direction": np.ones((3, 3))}, ValueError, "`direction` must be orthonormal"),
    ],
)
def test_volume_rejects_bad_input(kwargs, error, match):
    args = {"array": np.zeros((2, 2, 2)), "spacing": (1, 1, 1), **kwargs}
    with pytest.raises(error, match=match):
        Volume(**args)


# -- round trips through each format ------------------------------------------------------------


def test_nifti_round_trip_with_rotation(tmp_path, ramp):
    # nibabel stores (i, j, k) = (column, row, plane) and a RAS affine.
    ras_affine = np.eye(4)
    ras_affine[:3, :3] = ROTATION @ np.diag([0.5, 1.0, 2.5])
    ras_affine[:3, 3] = [10.0, -20.0, 30.0]
    data_ijk = np.ascontiguousarray(ramp.transpose(2, 1, 0))
    path = tmp_path / "ramp.nii.gz"
    nib.save(nib.Nifti1Image(data_ijk, ras_affine), path)
    v = read_volume(path)
    assert v.shape == (4, 5, 6)
    assert np.array_equal(v.array, ramp)
    assert np.allclose(v.spacing, [2.5, 1.0, 0.5])
    assert np.allclose(v.affine, LPS_FROM_RAS @ ras_affine, atol=1e-5)


def test_nrrd_round_trip_attached_and_detached(tmp_path, ramp):
    directions = (ROTATION @ np.diag([0.5, 1.0, 2.5])).T  # one row per axis i, j, k
    header = {
        "space": "left-posterior-superior",
        "space directions": directions,
        "space origin": np.array([1.0, 2.0, 3.0]),
    }
    for name, detached in (("a.nrrd", False), ("b.nhdr", True)):
        path = tmp_path / name
        nrrd.write(str(path), ramp, header, index_order="C", detached_header=detached)
        v = read_volume(path)
        assert np.array_equal(v.array, ramp)
        assert np.allclose(v.spacing, [2.5, 1.0, 0.5])
        assert np.allclose(v.origin, [1, 2, 3])
        assert np.allclose(v.direction, ROTATION, atol=1e-6)


def test_nrrd_ras_space_is_converted_to_lps(tmp_path, ramp):
    path = tmp_path / "ras.nrrd"
    header = {
        "space": "right-anterior-superior",
        "space directions": np.diag([0.5, 1.0, 2.5]),
        "space origin": np.array([1.0, 2.0, 3.0]),
    }
    nrrd.write(str(path), ramp, header, index_order="C")
    v = read_volume(path)
    assert np.allclose(v.origin, [-1, -2, 3])
    assert np.allclose(v.direction, np.diag([-1.0, -1.0, 1.0]))


@pytest.mark.parametrize("suffix", [".mha", ".mhd"])
def test_metaimage_round_trip(tmp_path, ramp, suffix):
    image = sitk.GetImageFromArray(ramp)
    image.SetSpacing((0.5, 1.0, 2.5))  # ITK order: x (column), y (row), z (plane)
    image.SetOrigin((4.0, 5.0, 6.0))
    image.SetDirection(ROTATION.ravel().tolist())
    path = tmp_path / f"ramp{suffix}"
    sitk.WriteImage(image, str(path))
    v = read_volume(path)
    assert np.array_equal(v.array, ramp)
    assert v.array.dtype == np.int16
    assert np.allclose(v.spacing, [2.5, 1.0, 0.5])
    assert np.allclose(v.origin, [4, 5, 6])
    assert np.allclose(v.direction, ROTATION)


@pytest.fixture
def stored_slices() -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.integers(0, 3000, size=(5, 6, 7)).astype(np.uint16)


def test_dicom_series_rescaled_to_hu_and_sorted(tmp_path, stored_slices):
    folder = tmp_path / "series"
    write_dicom_series(
        folder, stored_slices, slope=2.0, intercept=-1024.0, positions_z=[0, 2, 4, 6, 8]
    )
    v = read_volume(folder)
    assert v.shape == (5, 6, 7)
    assert np.array_equal(v.array, stored_slices.astype(np.float64) * 2 - 1024)
    assert np.allclose(v.spacing, [2.0, 0.75, 0.5])
    assert np.allclose(v.origin, [-10.0, 20.0, 0.0])


def test_dicom_series_fractional_rescale(tmp_path, stored_slices):
    folder = tmp_path / "series"
    write_dicom_series(
        folder, stored_slices, slope=0.5, intercept=-1000.5, positions_z=[0, 2, 4, 6, 8]
    )
    v = read_volume(folder)
    assert np.allclose(v.array, stored_slices * 0.5 - 1000.5)


@pytest.mark.parametrize(
    "positions, message",
    [
        # The slice at z = 4 twice, each with its own UID and instance number: GDCM's order
        # need not put the twins side by side, where the duplicate read as "non-uniform spacing".
        ([0, 2, 4, 6, 4], r"1 slice\(s\) share a position with another slice"),
        ([0, 2, 4, 8, 10], r"non-uniform slice spacing .* missing slices"),
    ],
)
def test_dicom_series_with_a_duplicated_or_missing_slice_says_which(
    tmp_path, stored_slices, positions, message
):
    folder = tmp_path / "series"
    write_dicom_series(folder, stored_slices, slope=1.0, intercept=-1024.0, positions_z=positions)
    with pytest.raises(ValueError, match=message):
        read_volume(folder)


@pytest.mark.parametrize(
    "case, message",
    [
        ("tilt", "not stacked along their normal .* sheared"),
        ("turned", "2 slice.s. lie in another orientation"),
        ("pixels", "2 slice.s. have another pixel spacing"),
    ],
)
def test_dicom_series_that_one_grid_cannot_hold_is_refused(tmp_path, stored_slices, case, message):
    # Read from the first slice's orientation and pixel spacing and stacked along its normal, a
    # tilted gantry would shear a sphere by 4 mm, and turned or finer slices land 9.5 mm off or
    # at half size, all without a word.
    def edit(n, ds):
        if case == "tilt":  # 20 degrees: each slice 0.73 mm further along y
            ds.ImagePositionPatient = [-10.0, 20.0 + 2.0 * n * np.tan(np.radians(20)), 2.0 * n]
        elif case == "turned" and n in (2, 3):
            c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
            ds.ImageOrientationPatient = [c, s, 0, -s, c, 0]
        elif case == "pixels" and n >= 3:
            ds.PixelSpacing = [1.5, 1.0]

    folder = tmp_path / "series"
    write_dicom_series(
        folder, stored_slices, slope=1.0, intercept=-1024.0, positions_z=[0, 2, 4, 6, 8], edit=edit
    )
    with pytest.raises(ValueError, match=message):
        read_volume(folder)


def test_dicom_folder_with_two_series(tmp_path, stored_slices):
    folder = tmp_path / "mixed"
    first = write_dicom_series(
        folder, stored_slices, slope=1, intercept=-1024, positions_z=[0, 2, 4, 6, 8]
    )
    second = write_dicom_series(
        folder,
        stored_slices[:3],
        slope=1,
        intercept=0,
        positions_z=[0, 3, 6],
        prefix="other",
    )
    with pytest.raises(ValueError, match=r"holds 2 DICOM series; pass `series_uid`") as info:
        read_volume(folder)
    assert first in str(info.value) and second in str(info.value)
    v = read_volume(folder, series_uid=second)
    assert v.shape == (3, 6, 7)
    assert np.allclose(v.spacing[0], 3.0)
    with pytest.raises(ValueError, match="`series_uid` must be one of"):
        read_volume(folder, series_uid="1.2.3")


def test_raw_slices_round_trip_big_endian(tmp_path, ramp):
    paths = []
    for n, plane in enumerate(ramp):
        path = tmp_path / f"slice.{n + 1}"
        plane.astype(">i2").tofile(path)
        paths.append(path)
    v = read_raw_slices(
        paths, shape=(5, 6), dtype="int16", byte_order="big", spacing=(2, 1, 1), origin=(1, 2, 3)
    )
    assert np.array_equal(v.array, ramp)
    assert v.array.dtype == np.dtype("int16")  # native order
    assert np.allclose(v.origin, [1, 2, 3])
    # A glob pattern is sorted naturally; one file may hold the whole volume.
    if len(paths) >= 10:  # pragma: no cover - documents the natural order
        assert str(paths[1]) < str(paths[9])
    v2 = read_raw_slices(str(tmp_path / "slice.*"), shape=(5, 6), dtype="i2", byte_order="big",
                         spacing=(2, 1, 1))  # fmt: skip
    assert np.array_equal(v2.array, ramp)
    whole = tmp_path / "whole.raw"
    ramp.astype("<i2").tofile(whole)
    v3 = read_raw_slices(whole, shape=(4, 5, 6), dtype=np.int16, spacing=(1, 1, 1))
    assert np.array_equal(v3.array, ramp)


def test_raw_slices_rejects_wrong_size(tmp_path, ramp):
    path = tmp_path / "slice.1"
    ramp[0].astype("<i2").tofile(path)
    with pytest.raises(OSError, match=r"has 60 bytes, expected 72"):
        read_raw_slices([path], shape=(6, 6), dtype="int16", spacing=(1, 1, 1))
    with pytest.raises(ValueError, match="`byte_order` must be one of"):
        read_raw_slices([path], shape=(5, 6), dtype="int16", byte_order="middle", spacing=(1, 1, 1))
    with pytest.raises(ValueError, match="no file matches"):
        read_raw_slices(str(tmp_path / "none.*"), shape=(5, 6), dtype="int16", spacing=(1, 1, 1))


def test_read_volume_rejects_bad_files(tmp_path):
    with pytest.raises(OSError, match="no such file"):
        read_volume(tmp_path / "missing.nii.gz")
    empty = tmp_path / "empty.nrrd"
    empty.write_bytes(b"")
    with pytest.raises(OSError, match="is empty"):
        read_volume(empty)
    garbage = tmp_path / "garbage.mha"
    garbage.write_bytes(b"not an image at all")
    with pytest.raises(OSError, match="could not read"):
        read_volume(garbage)
    unknown = tmp_path / "scan.xyz"
    unknown.write_bytes(b"data")
    with pytest.raises(ValueError, match=r"must be a folder of DICOM slices or a file ending"):
        read_volume(unknown)
    (tmp_path / "nothing").mkdir()
    with pytest.raises(OSError, match="no DICOM series found"):
        read_volume(tmp_path / "nothing")
    with pytest.raises(TypeError, match="`path` must be a path"):
        read_volume(3)


# -- real files ---------------------------------------------------------------------------------


def test_headsq_detached_nrrd_with_slice_list():
    # SimpleITK rejects this header (spacings with a space field): read through pynrrd.
    v = read_volume(HEADSQ / "quarter.nhdr")
    assert v.shape == (93, 64, 64)
    assert np.allclose(v.spacing, [1.5, 3.2, 3.2])
    expected = np.stack(
        [np.fromfile(HEADSQ / f"quarter.{i}", "<i2").reshape(64, 64) for i in range(1, 94)]
    )
    assert np.array_equal(v.array, expected)


def test_dicom_slice_in_hounsfield_units():
    path = DATA / "dicom_slice" / "CT_small.dcm"
    v = read_volume(path)
    ds = pydicom.dcmread(path)
    assert v.shape == (1, 128, 128)
    hu = ds.pixel_array * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
    assert np.array_equal(v.array[0], hu)
    assert v.array.min() == -896  # raw minimum 128 with intercept -1024
    assert np.allclose(v.spacing[1:], [0.661468, 0.661468])
    assert np.allclose(v.origin, [float(x) for x in ds.ImagePositionPatient])


def test_dicom_slice_in_a_folder(tmp_path):
    folder = tmp_path / "one"
    folder.mkdir()
    shutil.copy(DATA / "dicom_slice" / "CT_small.dcm", folder / "CT_small.dcm")
    v = read_volume(folder)
    assert v.shape == (1, 128, 128)
    assert np.isclose(v.spacing[0], 5.0)  # the slice thickness
    # The same file read directly: the same plane spacing.
    assert np.isclose(read_volume(DATA / "dicom_slice" / "CT_small.dcm").spacing[0], 5.0)


def test_a_multi_frame_dicom_file_in_a_folder_keeps_its_plane_spacing(tmp_path):
    # One file holding 6 frames 2.5 mm apart (SimpleITK's DICOM writer, rotated): in a folder
    # it was taken for one slice and given the 1 mm default thickness, the volume squashed 2.5
    # times along its slices without a word.
    array = np.zeros((6, 7, 8), np.uint16)
    array[4, 2, 5] = 1000
    image = sitk.GetImageFromArray(array)
    image.SetSpacing((0.7, 1.1, 2.5))
    image.SetOrigin((-10.5, 20.25, 33.0))
    image.SetDirection(ROTATION.ravel().tolist())
    (tmp_path / "folder").mkdir()
    sitk.WriteImage(image, str(tmp_path / "folder" / "frames.dcm"))
    truth = np.array(image.TransformIndexToPhysicalPoint((5, 2, 4)))
    for path in (tmp_path / "folder" / "frames.dcm", tmp_path / "folder"):
        v = read_volume(path)
        assert v.shape == (6, 7, 8)
        np.testing.assert_allclose(v.spacing, [2.5, 1.1, 0.7], rtol=1e-6)
        np.testing.assert_allclose(v.index_to_world([[4, 2, 5]])[0], truth, atol=1e-4)


def test_pitched_nifti_affine_is_honoured():
    path = DATA / "pitch" / "CT_pitch.nii.gz"
    v = read_volume(path)
    image = nib.load(path)
    assert v.shape == image.shape[::-1]
    # SimpleITK stores float32 geometry: agree with nibabel to a micrometre.
    assert np.allclose(v.affine, LPS_FROM_RAS @ image.affine, atol=1e-3)
    assert not np.allclose(v.direction, np.diag(np.diag(v.direction)))  # a real rotation
    assert np.array_equal(v.array, np.asarray(image.dataobj).transpose(2, 1, 0))


def test_mandible_mask_geometry(shared_data):
    path = shared_data / "mandibles" / "masks" / "0522c0001_Mandible.nrrd"
    if not path.exists():
        pytest.skip(f"{path} is absent")
    v = read_volume(path)
    header = nrrd.read_header(str(path))
    assert v.shape == tuple(int(s) for s in header["sizes"][::-1])
    assert np.allclose(v.origin, header["space origin"])
    assert set(np.unique(v.array).tolist()) <= {0, 1}


@pytest.mark.parametrize(
    "space, axes",
    [
        ("", (1.0, -1.0, 1.0)),
        ("space: left-posterior-superior\n", (1.0, -1.0, 1.0)),
        # RAS: x and y run the other way in LPS, on top of the negative y spacing.
        ("space: right-anterior-superior\n", (-1.0, 1.0, 1.0)),
    ],
)
def test_a_negative_nrrd_spacing_runs_its_axis_the_other_way(tmp_path, space, axes):
    # With a `space` field SimpleITK rejects a spacings-only header and pynrrd reads it: the
    # sign and the file's space must both reach the direction, or the data is mirrored.
    data = np.arange(4 * 5 * 6, dtype=np.int16).reshape(4, 5, 6)
    (tmp_path / "v.raw").write_bytes(data.tobytes())
    header = tmp_path / "v.nhdr"
    header.write_text(
        "NRRD0004\ntype: short\ndimension: 3\n" + space + "sizes: 6 5 4\n"
        "spacings: 0.7 -1.1 2.5\nencoding: raw\nendian: little\ndata file: v.raw\n"
    )
    v = read_volume(header)
    np.testing.assert_allclose(v.spacing, [2.5, 1.1, 0.7])
    np.testing.assert_allclose(v.direction, np.diag(axes))
    assert np.array_equal(v.array, data)


def test_a_nrrd_in_ras_with_spacings_lands_where_its_lps_twin_does(tmp_path):
    # The same voxels described in RAS and in LPS: the same world positions (LPS).
    data = np.zeros((6, 5, 4), dtype=np.uint8)
    (tmp_path / "v.raw").write_bytes(data.tobytes())
    placed = {}
    for name, space, origin in (
        ("ras", "right-anterior-superior", "(-10,-20,30)"),
        ("lps", "left-posterior-superior", "(10,20,30)"),
    ):
        signs = "-1 -2 3" if name == "ras" else "1 2 3"
        (tmp_path / f"{name}.nhdr").write_text(
            f"NRRD0004\ntype: uchar\ndimension: 3\nspace: {space}\nsizes: 4 5 6\n"
            f"spacings: {signs}\nspace origin: {origin}\nencoding: raw\ndata file: v.raw\n"
        )
        volume = read_volume(tmp_path / f"{name}.nhdr")
        placed[name] = volume.index_to_world([[0, 0, 0], [1, 1, 1], [5, 4, 3]])
    np.testing.assert_allclose(placed["lps"][1], [11.0, 22.0, 33.0])
    np.testing.assert_allclose(placed["ras"], placed["lps"])


def test_a_nifti_with_a_zero_or_nan_voxel_size_is_refused(tmp_path):
    # SimpleITK reads such a size as 1 mm: the volume would be scaled wrong without a word.
    image = nib.Nifti1Image(np.zeros((6, 7, 8), np.int16), np.diag([1.0, 1.0, 2.0, 1.0]))
    image.set_qform(np.diag([1.0, 1.0, 2.0, 1.0]), code=1)
    image.set_sform(None, code=0)
    nib.save(image, tmp_path / "good.nii")
    raw = bytearray((tmp_path / "good.nii").read_bytes())
    for value in (0.0, np.nan):
        raw[84:88] = struct.pack("<f", value)  # pixdim[2]
        (tmp_path / "bad.nii").write_bytes(bytes(raw))
        with pytest.raises(ValueError, match=r"voxel sizes \(pixdim\[1:4\]\)"):
            read_volume(tmp_path / "bad.nii")


def test_a_nifti_whose_qform_and_sform_disagree_is_read_by_the_qform_with_a_warning(
    tmp_path, caplog
):
    # ITK places the volume by the qform unless the sform's code is 1, nibabel by the sform:
    # the same file lands 80 mm apart depending on the software. Read as ITK does, and said.
    data = np.zeros((6, 7, 8), np.int16)
    affine = np.diag([0.8, 0.9, 2.0, 1.0])
    affine[:3, 3] = [10, 20, 30]
    image = nib.Nifti1Image(data, affine)
    image.set_qform(affine, code=1)
    image.set_sform(affine, code=1)
    nib.save(image, tmp_path / "same.nii.gz")
    other = affine.copy()
    other[:3, 3] = [50, -60, 70]
    image.set_sform(other, code=2)
    nib.save(image, tmp_path / "differ.nii.gz")
    with caplog.at_level("WARNING", logger="o3dreg"):
        same = read_volume(tmp_path / "same.nii.gz")
        assert "qform and sform" not in caplog.text
        differ = read_volume(tmp_path / "differ.nii.gz")
    assert "qform and sform place the volume up to 80 mm apart" in caplog.text
    assert "read by the qform" in caplog.text
    np.testing.assert_allclose(differ.origin, same.origin)  # by the qform (LPS: x, y negated)
    np.testing.assert_allclose(same.origin, [-10.0, -20.0, 30.0])
    # An sform of code 1 (scanner anatomy) is the one ITK reads: the message names it.
    caplog.clear()
    image.set_sform(other, code=1)
    image.set_qform(affine, code=2)
    nib.save(image, tmp_path / "scanner.nii.gz")
    with caplog.at_level("WARNING", logger="o3dreg"):
        scanner = read_volume(tmp_path / "scanner.nii.gz")
    assert "read by the sform" in caplog.text
    np.testing.assert_allclose(scanner.origin, [-50.0, 60.0, 70.0])


def test_a_nifti_placed_by_its_sform_gets_the_sforms_voxel_sizes(tmp_path, caplog):
    # nibabel, given only an sform, leaves pixdim at 1: ITK places the volume by the sform's
    # directions and origin but sizes its voxels by pixdim, so a known voxel landed 8 mm off
    # and the volume shrank to a third along k, without a word. The standard (and nibabel)
    # place voxels by the sform's columns.
    data = np.zeros((8, 7, 6), np.int16)
    affine = np.eye(4)
    affine[:3, :3] = ROTATION @ np.diag([0.8, 1.2, 3.0])
    affine[:3, 3] = [12.0, -30.0, 55.0]
    image = nib.Nifti1Image(data, None)
    image.set_sform(affine, code=2)
    image.set_qform(None, code=0)
    nib.save(image, tmp_path / "sform.nii")
    assert np.allclose(nib.load(tmp_path / "sform.nii").header["pixdim"][1:4], 1.0)
    with caplog.at_level("WARNING", logger="o3dreg"):
        v = read_volume(tmp_path / "sform.nii")
    np.testing.assert_allclose(v.affine, LPS_FROM_RAS @ affine, atol=1e-5)
    assert "differ from those of the sform" in caplog.text
    # The same as a 4D file of one volume (ITK keeps its fourth spacing).
    image4 = nib.Nifti1Image(data[..., None], None)
    image4.set_sform(affine, code=2)
    image4.set_qform(None, code=0)
    nib.save(image4, tmp_path / "sform4d.nii")
    np.testing.assert_allclose(read_volume(tmp_path / "sform4d.nii").affine, v.affine, atol=1e-5)
    # Consistent headers: the same geometry, nothing said.
    caplog.clear()
    nib.save(nib.Nifti1Image(data, affine), tmp_path / "both.nii")
    with caplog.at_level("WARNING", logger="o3dreg"):
        np.testing.assert_allclose(read_volume(tmp_path / "both.nii").affine, v.affine, atol=1e-5)
    assert caplog.text == ""


def test_a_nifti_with_a_negative_voxel_size_or_in_nifti2_is_refused_clearly(tmp_path):
    data = np.zeros((8, 7, 6), np.int16)
    affine = np.diag([0.8, 1.2, 3.0, 1.0])
    nib.save(nib.Nifti1Image(data, affine), tmp_path / "scan.nii")
    raw = bytearray((tmp_path / "scan.nii").read_bytes())
    raw[80:84] = struct.pack("<f", -0.8)  # pixdim[1]: ITK and nibabel place it 8 mm apart
    (tmp_path / "negative.nii").write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=r"negative\.nii' has voxel sizes .* wants them positive"):
        read_volume(tmp_path / "negative.nii")
    nib.save(nib.Nifti2Image(data, affine), tmp_path / "two.nii")
    with pytest.raises(OSError, match="is a NIfTI-2 file, which SimpleITK cannot read"):
        read_volume(tmp_path / "two.nii")


def test_an_nrrd_space_taken_as_lps_by_guess_is_a_warning(tmp_path, caplog):
    # An anatomical space o3dreg does not know can swap left and right: a warning. The
    # format's generic frames (the bundled CT's "3D-left-handed") have no left or right.
    import logging

    import nrrd

    from o3dreg.app.datasets import headsq_path

    path = tmp_path / "v.nrrd"
    header = {"space": "left-posterior-superior", "space directions": np.eye(3)}
    nrrd.write(str(path), np.zeros((4, 5, 6), np.uint8), header)
    path.write_bytes(path.read_bytes().replace(b"left-posterior-superior", b"up-down-sideways"))
    with caplog.at_level(logging.INFO, logger="o3dreg"):
        read_volume(path)
        read_volume(headsq_path())
    warned = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warned) == 1 and "space 'up-down-sideways' is not LPS" in warned[0]
    assert any("'3d-left-handed' has no anatomical axes" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("encoding", ["raw", "ascii"])
def test_nrrd_space_units_are_taken_to_millimetres(tmp_path, encoding):
    # Neither SimpleITK nor pynrrd applies `space units`: a file in cm was read 10 times too
    # small (595 mm off at a test voxel). Both readers (raw: SimpleITK, ascii: pynrrd) agree.
    data = np.zeros((4, 5, 6), np.uint8)
    header = {
        "space": "left-posterior-superior",
        "space directions": np.diag([0.08, 0.12, 0.3]),
        "space origin": np.array([1.0, 2.0, 3.0]),
        "encoding": encoding,
    }
    nrrd.write(str(tmp_path / "mm.nrrd"), data, header)
    nrrd.write(str(tmp_path / "cm.nrrd"), data, {**header, "space units": ["cm"] * 3})
    mm, cm = read_volume(tmp_path / "mm.nrrd"), read_volume(tmp_path / "cm.nrrd")
    np.testing.assert_allclose(cm.affine[:3], mm.affine[:3] * [[10, 10, 10, 10]] * 1.0)
    nrrd.write(str(tmp_path / "mm2.nrrd"), data, {**header, "space units": ["mm"] * 3})
    np.testing.assert_allclose(read_volume(tmp_path / "mm2.nrrd").affine, mm.affine)
    nrrd.write(str(tmp_path / "in.nrrd"), data, {**header, "space units": ["inch"] * 3})
    with pytest.raises(ValueError, match=r"has space units \['inch', 'inch', 'inch'\]"):
        read_volume(tmp_path / "in.nrrd")


def test_nrrd_axis_mins_place_the_volume_whichever_reader(tmp_path):
    # The per-axis form (spacings and axis mins, no space): SimpleITK puts the first sample
    # half a spacing beyond the minimum (cell centring, the default) or on it ("node"); the
    # pynrrd path (text encodings) ignored the minima: 30 mm apart for the same header.
    values = np.zeros(4 * 5 * 6, np.uint8)
    for field, half in (("", 0.5), ("centers: node cell ???\n", [0, 0.5, 0.5])):
        for spelling in ("centers", "centerings"):
            origins = []
            for encoding, body in (("raw", values.tobytes()), ("ascii", b"0\n" * values.size)):
                path = tmp_path / f"{encoding}.nrrd"
                header = (
                    "NRRD0004\ntype: uint8\ndimension: 3\nsizes: 6 5 4\nspacings: 0.8 1.2 3\n"
                    f"axis mins: 10 20 30\n{field.replace('centers', spelling)}"
                    f"encoding: {encoding}\n\n"
                )
                path.write_bytes(header.encode() + body)
                origins.append(read_volume(path).origin)
            expected = np.array([10.0, 20.0, 30.0]) + np.multiply(half, [0.8, 1.2, 3.0])
            np.testing.assert_allclose(origins, [expected, expected], err_msg=field + spelling)


@pytest.mark.parametrize("suffix", [".mha", ".mhd"])
def test_a_metaimage_whose_compressed_data_does_not_inflate_is_refused(tmp_path, ramp, suffix):
    # ITK prints "Uncompress failed" and returns garbage voxels (+-22000 from a 0-6 image) for a
    # header that says CompressedData = True over raw bytes, or a damaged stream.
    image = sitk.GetImageFromArray(ramp)
    sitk.WriteImage(image, str(tmp_path / f"good{suffix}"), useCompression=True)
    assert np.array_equal(read_volume(tmp_path / f"good{suffix}").array, ramp)
    sitk.WriteImage(image, str(tmp_path / f"raw{suffix}"), useCompression=False)
    header = tmp_path / f"raw{suffix}"
    header.write_bytes(
        header.read_bytes().replace(b"CompressedData = False", b"CompressedData = True")
    )
    with pytest.raises(OSError, match=r"says its data is compressed .* not inflate to the"):
        read_volume(header)
    data = tmp_path / ("good.zraw" if suffix == ".mhd" else "good.mha")
    damaged = bytearray(data.read_bytes())
    damaged[-40:-20] = bytes(20)  # zeros inside the deflate stream
    data.write_bytes(bytes(damaged))
    with pytest.raises(OSError, match=r"says its data is compressed"):
        read_volume(tmp_path / f"good{suffix}")


def test_a_dicom_medium_names_the_folders_that_hold_the_series(tmp_path, stored_slices):
    # A DICOMDIR at the root, the images in PT000000/ST000000/SE000000 (the standard medium
    # layout): the root holds no series; the message names where they are.
    write_dicom_series(
        tmp_path / "PT000000",
        stored_slices,
        slope=1.0,
        intercept=-1024.0,
        positions_z=[0, 2, 4, 6, 8],
    )
    (tmp_path / "DICOMDIR").write_bytes(b"\0" * 128 + b"DICM")
    with pytest.raises(OSError, match=r"folders below it .*: PT000000 \(5 files\)"):
        read_volume(tmp_path)
    assert read_volume(tmp_path / "PT000000").shape == (5, 6, 7)
