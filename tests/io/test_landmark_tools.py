"""Landmark files as 3D Slicer (3, 4 and 5), statismo and scalismo write them: columns named by
the ``# columns`` line, unplaced points skipped with a warning naming them, a cut row refused."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from o3dreg import read_landmarks

COLUMNS = "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID"
ROWS = [
    "vtkMRMLMarkupsFiducialNode_0,-7.16592,116.932,223,0,0,0,1,1,1,0,chin,,vtkMRMLScalarVolumeNode2",
    "vtkMRMLMarkupsFiducialNode_1,41.6039,41.1211,289,0,0,0,1,1,1,0,mand_r,,vtkMRMLScalarVolumeNode2",
    "vtkMRMLMarkupsFiducialNode_2,-47.5,43.25,-9.875,0,0,0,1,1,1,0,mand_l,,vtkMRMLScalarVolumeNode2",
]
RAS = np.array([[-7.16592, 116.932, 223], [41.6039, 41.1211, 289], [-47.5, 43.25, -9.875]])
FLIP = np.array([-1.0, -1.0, 1.0])


def _write(tmp_path, name, lines):
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


def test_an_fcsv_cut_inside_its_last_row_is_an_error(tmp_path):
    head = ["# Markups fiducial file version = 4.3", "# CoordinateSystem = 0", COLUMNS]
    whole = "\n".join([*head, *ROWS]) + "\n"
    # Cut inside the last row's z: "-9." stays, the label and the rest are gone.
    cut = whole[: whole.rindex("-9.875") + 3]
    path = tmp_path / "cut.fcsv"
    path.write_text(cut)
    with pytest.raises(ValueError, match=r"line 6 is short: 14 fields expected .* truncated"):
        read_landmarks(path)
    # The whole file reads, labels where Slicer put them.
    path.write_text(whole)
    labels, points = read_landmarks(path)
    assert labels == ("chin", "mand_r", "mand_l")
    np.testing.assert_allclose(points, RAS * FLIP)


def test_slicer5_fcsv_skips_undefined_and_missing_points(tmp_path):
    # Slicer 5 appends positionStatus (0 undefined, 1 preview, 2 defined, 3 missing) and
    # autoCreated to each row; its columns line does not name them.
    rows = [ROWS[0] + ",2,0", ROWS[1] + ",0,0", ROWS[2] + ",3,0"]
    path = _write(
        tmp_path,
        "s5.fcsv",
        ["# Markups fiducial file version = 5.6", "# CoordinateSystem = LPS", COLUMNS, *rows],
    )
    with pytest.warns(
        UserWarning,
        match=r"2 control point\(s\) not placed.*'mand_r' \(undefined\), 'mand_l' \(missing\)",
    ):
        labels, points = read_landmarks(path)
    assert labels == ("chin",)
    np.testing.assert_allclose(points, RAS[:1])  # declared LPS: taken as written


def test_slicer3_fcsv_columns_line_gives_the_labels(tmp_path):
    lines = [
        "# Fiducial List file /data/old.fcsv",
        "# name = old",
        "# numPoints = 2",
        "# symbolScale = 5",
        "# columns = label,x,y,z,sel,vis",
        "nasion,1.5,-2.25,3,1,1",
        "gonion_l,-4,5.5,-6.125,1,1",
    ]
    path = _write(tmp_path, "s3.fcsv", lines)
    with pytest.warns(UserWarning, match="taken as RAS"):
        labels, points = read_landmarks(path)
    assert labels == ("nasion", "gonion_l")
    np.testing.assert_allclose(points, np.array([[1.5, -2.25, 3], [-4, 5.5, -6.125]]) * FLIP)


def test_mrk_json_with_an_unplaced_point(tmp_path):
    # As Slicer writes a point list with a point not yet placed (markups schema v1.0.3).
    doc = {
        "@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/"
        "Markups/Resources/Schema/markups-schema-v1.0.3.json#",
        "markups": [
            {
                "type": "Fiducial",
                "coordinateSystem": "LPS",
                "coordinateUnits": "mm",
                "controlPoints": [
                    {
                        "id": "1",
                        "label": "chin",
                        "position": [1.0, 2.0, 3.0],
                        "orientation": [-1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0],
                        "selected": True,
                        "locked": False,
                        "visibility": True,
                        "positionStatus": "defined",
                    },
                    {
                        "id": "2",
                        "label": "condyle",
                        "position": "",
                        "positionStatus": "undefined",
                    },
                ],
            }
        ],
    }
    path = tmp_path / "p.mrk.json"
    path.write_text(json.dumps(doc))
    with pytest.warns(UserWarning, match=r"'condyle' \(undefined\)"):
        labels, points = read_landmarks(path)
    assert labels == ("chin",)
    np.testing.assert_array_equal(points, [[1.0, 2.0, 3.0]])


def test_statismo_landmark_csv_without_a_header(tmp_path):
    # statismo's and scalismo's landmark files: label,x,y,z rows, no header.
    path = _write(tmp_path, "lm.csv", ["A,585.14,490.43,-242.97", "B,1e2,-3.5,0"])
    with pytest.warns(UserWarning, match="coordinate system not stated"):
        labels, points = read_landmarks(path)
    assert labels == ("A", "B")
    np.testing.assert_array_equal(points, [[585.14, 490.43, -242.97], [100.0, -3.5, 0.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_landmarks(path, file_coordinate_system="LPS")
    bad = _write(tmp_path, "bad.csv", ["A,1,2,3", "B,1,2"])
    with pytest.raises(ValueError, match="line 2: label,x,y,z expected"):
        read_landmarks(bad)
    # Comment lines (# first), which scalismo's reader skips, and a header file's too; a row's
    # line number stays its line in the file.
    commented = _write(tmp_path, "c.csv", ["# landmarks of patient 7", "A,585.14,490.43,-242.97",
                                           "  # placed twice", "B,1e2,-3.5,0"])  # fmt: skip
    labels, points = read_landmarks(commented, file_coordinate_system="LPS")
    assert labels == ("A", "B") and points[1].tolist() == [100.0, -3.5, 0.0]
    headed = _write(tmp_path, "h.csv", ["# exported", "label,l,p,s", "A,1,2,3", "# end"])
    assert read_landmarks(headed)[1].tolist() == [[1.0, 2.0, 3.0]]
    bad = _write(tmp_path, "bad2.csv", ["# header", "A,1,2,3", "B,1,2"])
    with pytest.raises(ValueError, match="line 3: label,x,y,z expected"):
        read_landmarks(bad)


def test_scalismo_landmark_json(tmp_path):
    # scalismo's LandmarkIO.writeLandmarksJson (Scalismo UI's save): a list of id and
    # coordinates, with optional description and uncertainty. It was refused as "not a 3D
    # Slicer markups file (a non-empty `markups` list expected, got none)".
    doc = [
        {"id": "chin", "coordinates": [585.14, 490.43, -242.97]},
        {
            "id": "mand_r",
            "coordinates": [1e2, -3.5, 0.0],
            "description": "right condyle",
            "uncertainty": {"stddevs": [1.0, 1.0, 1.0], "pcvectors": np.eye(3).tolist()},
        },
    ]
    path = _write(tmp_path, "lm.json", [json.dumps(doc)])
    with pytest.warns(UserWarning, match="coordinate system not stated"):
        labels, points = read_landmarks(path)
    assert labels == ("chin", "mand_r")
    np.testing.assert_array_equal(points, [[585.14, 490.43, -242.97], [100.0, -3.5, 0.0]])
    labels, points = read_landmarks(path, file_coordinate_system="RAS")
    np.testing.assert_array_equal(points[0], np.array([585.14, 490.43, -242.97]) * FLIP)
    bad = _write(tmp_path, "bad.json", [json.dumps([{"id": "A", "coordinates": [1, 2]}])])
    with pytest.raises(ValueError, match="scalismo landmark file; its entry 1"):
        read_landmarks(bad)


def test_the_pddca_landmark_files_read(shared_data):
    files = sorted((shared_data / "mandibles" / "landmarks").glob("*.fcsv"))
    assert files
    for path in files:
        labels, points = read_landmarks(path)
        assert {"chin", "mand_r", "mand_l"} <= set(labels)
        assert np.all(np.isfinite(points))
