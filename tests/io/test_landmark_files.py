"""Landmark files: CSV, Slicer .mrk.json and .fcsv, MeshLab .pp; RAS <-> LPS where files say.

The fixtures are written here by hand following the published formats: Slicer's markups JSON
schema (``markups[0].coordinateSystem``, ``controlPoints[i].position``, ``positionStatus``),
Slicer's fiducial CSV (``# Markups fiducial file version``, ``# CoordinateSystem``, columns
``id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID``; Slicer 4.x wrote the system
as 0 = RAS, 1 = LPS), Slicer's markups CSV export (``label,r,a,s,...``) and MeshLab's
``PickedPoints`` XML.
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from o3dreg import read_landmarks, write_landmarks
from o3dreg.io.landmark_files import LANDMARK_SUFFIXES

LABELS = ("nasion", "gonion, left", 'menton "M"')
LPS = np.array([[1.5, -20.25, 30.0], [-40.0, 5.5, -7.125], [0.0, 0.0, 12.0]])
RAS = LPS * [-1, -1, 1]  # RAS = (-L, -P, S)


@pytest.mark.parametrize("suffix", LANDMARK_SUFFIXES)
def test_round_trip_in_every_format(tmp_path, suffix):
    path = write_landmarks(tmp_path / f"lm{suffix}", LABELS, LPS)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        labels, points = read_landmarks(path, file_coordinate_system="LPS")
    assert not caught  # our files say LPS (or, .pp, the caller says)
    assert labels == LABELS
    np.testing.assert_array_equal(points, LPS)


@pytest.mark.parametrize("suffix", [".csv", ".mrk.json", ".fcsv"])
def test_written_in_ras_read_back_in_lps_and_ras(tmp_path, suffix):
    path = write_landmarks(tmp_path / f"lm{suffix}", LABELS, RAS, coordinate_system="RAS")
    np.testing.assert_array_equal(read_landmarks(path)[1], LPS)
    np.testing.assert_array_equal(read_landmarks(path, coordinate_system="RAS")[1], RAS)


def test_slicer_mrk_json_in_ras_is_converted(tmp_path):
    doc = {
        "@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/"
        "Markups/Resources/Schema/markups-schema-v1.0.3.json#",
        "markups": [
            {
                "type": "Fiducial",
                "coordinateSystem": "RAS",
                "coordinateUnits": "mm",
                "controlPoints": [
                    {"id": "1", "label": LABELS[0], "position": RAS[0].tolist()},
                    {"id": "2", "label": LABELS[1], "position": RAS[1].tolist()},
                    {"id": "3", "label": "unplaced", "positionStatus": "missing"},
                    {"id": "4", "label": LABELS[2], "position": RAS[2].tolist()},
                ],
            }
        ],
    }
    path = tmp_path / "ras.mrk.json"
    path.write_text(json.dumps(doc))
    with pytest.warns(UserWarning, match="1 control point"):
        labels, points = read_landmarks(path)
    assert labels == LABELS
    np.testing.assert_allclose(points, LPS)
    # No coordinateSystem: LPS, as Slicer reads it.
    del doc["markups"][0]["coordinateSystem"]
    del doc["markups"][0]["controlPoints"][2]
    path.write_text(json.dumps(doc))
    np.testing.assert_array_equal(read_landmarks(path)[1], RAS)


def _fcsv(system_line, points):
    lines = ["# Markups fiducial file version = 4.10", *system_line]
    lines.append("# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID")
    for k, p in enumerate(points):
        label = LABELS[k].replace('"', '""')
        lines.append(
            f'vtkMRMLMarkupsFiducialNode_{k},{p[0]},{p[1]},{p[2]},0,0,0,1,1,1,0,"{label}",,'
            "vtkMRMLScalarVolumeNode1"
        )
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize(
    ("line", "points"),
    [
        ("# CoordinateSystem = RAS", RAS),
        ("# CoordinateSystem = 0", RAS),  # Slicer 4.x enum: 0 = RAS
        ("# CoordinateSystem = LPS", LPS),
        ("# CoordinateSystem = 1", LPS),
    ],
)
def test_slicer_fcsv_declared_systems(tmp_path, line, points):
    path = tmp_path / "f.fcsv"
    path.write_text(_fcsv([line], points))
    labels, got = read_landmarks(path)
    assert labels == LABELS
    np.testing.assert_allclose(got, LPS)


def test_slicer_fcsv_without_a_system_is_ras_with_a_warning(tmp_path):
    path = tmp_path / "old.fcsv"
    path.write_text(_fcsv([], RAS))
    with pytest.warns(UserWarning, match=r"taken as RAS .*Slicer < 4.11"):
        _, got = read_landmarks(path)
    np.testing.assert_allclose(got, LPS)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_allclose(read_landmarks(path, file_coordinate_system="LPS")[1], RAS)


def test_slicer_markups_csv_export_columns(tmp_path):
    # Slicer's "export control points to CSV": label,r,a,s (or l,p,s),defined,... .
    rows = ["label,r,a,s,defined,selected,visible,locked,description"]
    rows += [f'"{lab}",{p[0]},{p[1]},{p[2]},1,1,1,0,' for lab, p in zip(LABELS[:2], RAS[:2])]
    path = tmp_path / "export.csv"
    path.write_text("\n".join(rows) + "\n")
    labels, points = read_landmarks(path)
    assert labels == LABELS[:2]
    np.testing.assert_allclose(points, LPS[:2])


def test_plain_xyz_csv_warns_and_is_taken_as_given(tmp_path):
    path = tmp_path / "xyz.csv"
    path.write_text("label,x,y,z\nA,1,2,3\n")
    with pytest.warns(UserWarning, match="coordinate system not stated; taken as LPS"):
        _, points = read_landmarks(path)
    np.testing.assert_array_equal(points, [[1.0, 2.0, 3.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, points = read_landmarks(path, file_coordinate_system="RAS")
    np.testing.assert_array_equal(points, [[-1.0, -2.0, 3.0]])


def test_meshlab_picked_points(tmp_path):
    text = """<!DOCTYPE PickedPoints>
<PickedPoints>
 <DocumentData>
  <DateTime time="10:11:12" date="2024-05-06"/>
  <User name="someone"/>
  <DataFileName name="mandible.ply"/>
  <templateName name="mandible"/>
 </DocumentData>
 <point x="1.5" y="-20.25" z="30" active="1" name="nasion"/>
 <point x="9" y="9" z="9" active="0" name="not placed"/>
 <point x="-40" y="5.5" z="-7.125" active="1" name="gonion, left"/>
</PickedPoints>
"""
    path = tmp_path / "p.pp"
    path.write_text(text)
    with pytest.warns(UserWarning) as record:
        labels, points = read_landmarks(path)
    messages = " ".join(str(w.message) for w in record)
    assert "1 inactive point" in messages and "not stated" in messages
    assert labels == LABELS[:2]
    np.testing.assert_array_equal(points, LPS[:2])


def test_bad_landmark_files(tmp_path):
    with pytest.raises(ValueError, match="must end with one of"):
        read_landmarks(tmp_path / "lm.txt")
    with pytest.raises(OSError, match="no such file"):
        read_landmarks(tmp_path / "missing.fcsv")
    bad = tmp_path / "bad.fcsv"
    bad.write_text("# CoordinateSystem = IJK\nid,1,2,3\n")
    with pytest.raises(ValueError, match="CoordinateSystem 'IJK'"):
        read_landmarks(bad)
    wrong = tmp_path / "ras.fcsv"
    wrong.write_text(_fcsv(["# CoordinateSystem = RAS"], RAS))
    with pytest.raises(ValueError, match="says its points are in RAS"):
        read_landmarks(wrong, file_coordinate_system="LPS")
    with pytest.raises(ValueError, match="`coordinate_system` must be 'LPS' or 'RAS'"):
        read_landmarks(wrong, coordinate_system="IJK")
    notpp = tmp_path / "x.pp"
    notpp.write_text("<Other/>")
    with pytest.raises(ValueError, match="not a MeshLab picked-points file"):
        read_landmarks(notpp)
    text = tmp_path / "t.csv"
    text.write_text("label,l,p,s\nA,1,two,3\n")
    with pytest.raises(ValueError, match="row 2: coordinates are not numbers"):
        read_landmarks(text)
    with pytest.raises(ValueError, match="`labels` must hold 3 labels"):
        write_landmarks(tmp_path / "w.fcsv", ["a"], LPS)


def test_nan_or_infinite_coordinates_are_refused_naming_the_file_and_landmarks(tmp_path):
    markup = {
        "markups": [
            {
                "type": "Fiducial",
                "coordinateSystem": "LPS",
                "controlPoints": [
                    {"label": "a", "position": [1.0, 2.0, 3.0]},
                    {"label": "b", "position": [float("nan"), 2.0, 3.0]},
                ],
            }
        ]
    }
    files = {
        "lm.csv": "label,x,y,z\na,1,2,3\nb,nan,2,3\n",
        "lm.mrk.json": json.dumps(markup),  # json writes NaN, which Python reads back
        "lm.fcsv": "# CoordinateSystem = LPS\n"
        "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
        "1,1,2,3,0,0,0,1,1,1,0,a,,\n2,inf,2,3,0,0,0,1,1,1,0,b,,\n",
    }
    for name, text in files.items():
        path = tmp_path / name
        path.write_text(text)
        with pytest.raises(
            ValueError, match=r"holds NaN or infinite coordinates \(landmarks 'b'\)"
        ):
            read_landmarks(path)


def test_a_label_of_several_lines_is_kept_or_refused(tmp_path):
    # The .fcsv writer dropped the line break ("a\nb" read back as "ab").
    for suffix in LANDMARK_SUFFIXES:
        path = tmp_path / f"lm{suffix}"
        if suffix == ".fcsv":
            with pytest.raises(ValueError, match="single lines in an .fcsv"):
                write_landmarks(path, ["a\nb", "c"], LPS[:2])
            assert not path.exists()
        else:
            write_landmarks(path, ["a\nb", "c"], LPS[:2])
            assert read_landmarks(path, file_coordinate_system="LPS")[0] == ("a\nb", "c")


@pytest.mark.parametrize(("columns", "points"), [("l,p,s", LPS), ("r,a,s", RAS)])
def test_slicer_markups_csv_export_skips_points_not_defined(tmp_path, columns, points):
    # Slicer's control point export writes an unplaced point as defined = 0 at (0, 0, 0).
    rows = [f"label,{columns},defined,selected,visible,locked,description"]
    rows += [f"A,{points[0][0]},{points[0][1]},{points[0][2]},1,1,1,0,"]
    rows += ["B,0,0,0,0,1,1,0,", "C,0,0,0,false,1,1,0,"]
    rows += [f"D,{points[1][0]},{points[1][1]},{points[1][2]},1,1,1,0,"]
    path = tmp_path / "export.csv"
    path.write_text("\n".join(rows) + "\n")
    with pytest.warns(UserWarning) as record:
        labels, got = read_landmarks(path)
    assert len(record) == 1
    message = str(record[0].message)
    assert repr(str(path)) in message
    assert "2 control point(s) not placed, skipped: 'B' (undefined), 'C' (undefined)" in message
    assert record[0].filename == __file__  # the caller's line, as the other readers warn
    assert labels == ("A", "D")
    np.testing.assert_allclose(got, LPS[:2])


def _markup(kind, name, labels, points, **extra):
    control = [{"label": lab, "position": list(p)} for lab, p in zip(labels, points)]
    markup = {"type": kind, "name": name, "coordinateSystem": "LPS", "controlPoints": control}
    return {**markup, **extra}


def _markups_file(tmp_path, *markups):
    path = tmp_path / "m.mrk.json"
    path.write_text(json.dumps({"@schema": "markups-schema-v1.0.3.json#", "markups": markups}))
    return path


def test_mrk_json_with_several_point_lists_is_refused_listing_them(tmp_path):
    path = _markups_file(
        tmp_path,
        _markup("Fiducial", "left", LABELS[:2], LPS[:2].tolist()),
        _markup("Fiducial", "right", LABELS[2:], LPS[2:].tolist()),
    )
    with pytest.raises(ValueError) as info:
        read_landmarks(path)
    message = str(info.value)
    assert "holds 2 point lists" in message
    assert "markups[0] 'left' (Fiducial, 2 control point(s))" in message
    assert "markups[1] 'right' (Fiducial, 1 control point(s))" in message
    assert "save the one wanted in a file of its own" in message


@pytest.mark.parametrize("kind", ["Curve", "ClosedCurve", "Line", "Angle", "Plane", "ROI"])
def test_mrk_json_of_a_markup_that_is_not_a_point_list_is_refused(tmp_path, kind):
    path = _markups_file(tmp_path, _markup(kind, "M", LABELS, LPS.tolist()))
    with pytest.raises(
        ValueError,
        match=rf"markups\[0\] 'M' \({kind}, 3 control point\(s\)\) and no "
        r"point list \(markup type 'Fiducial'\)",
    ):
        read_landmarks(path)


def test_mrk_json_reads_its_one_point_list_and_warns_about_the_other_markups(tmp_path):
    path = _markups_file(
        tmp_path,
        _markup("Curve", "centreline", ["c1", "c2"], [[0, 0, 0], [1, 1, 1]]),
        _markup("Fiducial", "landmarks", LABELS, RAS.tolist(), coordinateSystem="RAS"),
        _markup("Plane", "cut", ["p"], [[5, 5, 5]]),
    )
    with pytest.warns(UserWarning) as record:
        labels, points = read_landmarks(path)
    assert len(record) == 1
    message = str(record[0].message)
    assert "read the point list markups[1] 'landmarks' (Fiducial, 3 control point(s))" in message
    assert "ignored markups[0] 'centreline' (Curve, 2 control point(s))" in message
    assert "markups[2] 'cut' (Plane, 1 control point(s))" in message
    assert labels == LABELS
    np.testing.assert_allclose(points, LPS)


@pytest.mark.parametrize(
    ("units", "scale"),
    [("mm", 1.0), ("um", 1e3), ("cm", 0.1), ("m", 1e-3), (["um", "UCUM", "micrometer"], 1e3)],
)
def test_mrk_json_coordinate_units_are_converted_to_mm(tmp_path, units, scale):
    path = _markups_file(
        tmp_path,
        _markup("Fiducial", "F", LABELS, (LPS * scale).tolist(), coordinateUnits=units),
    )
    labels, points = read_landmarks(path)
    assert labels == LABELS
    np.testing.assert_allclose(points, LPS, rtol=1e-12)


def test_mrk_json_of_unknown_units_is_refused(tmp_path):
    path = _markups_file(
        tmp_path, _markup("Fiducial", "F", LABELS, LPS.tolist(), coordinateUnits="in")
    )
    with pytest.raises(ValueError, match=r"coordinateUnits 'in'; a length unit \(mm, um, cm, m\)"):
        read_landmarks(path)


def test_spaces_around_a_label_are_dropped_in_every_format(tmp_path):
    # A hand-edited file's " chin " must pair with another file's "chin" and be chosen by
    # --labels chin (which drops such spaces), whatever the format. A label of spaces only is no label (L<k>).
    names = [" chin ", "\tmand r", "   "]
    markups = {
        "markups": [
            {
                "type": "Fiducial",
                "coordinateSystem": "LPS",
                "controlPoints": [
                    {"label": n, "position": list(p), "positionStatus": "defined"}
                    for n, p in zip(names, LPS)
                ],
            }
        ]
    }
    (tmp_path / "lm.mrk.json").write_text(json.dumps(markups))
    points = "".join(
        f'<point x="{x}" y="{y}" z="{z}" active="1" name="{n}"/>\n'
        for n, (x, y, z) in zip(names, LPS)
    )
    (tmp_path / "lm.pp").write_text(f"<PickedPoints>\n{points}</PickedPoints>\n")
    for suffix in (".csv", ".fcsv"):
        write_landmarks(tmp_path / f"lm{suffix}", names, LPS)
    for suffix in (".csv", ".fcsv", ".mrk.json", ".pp"):
        labels, read = read_landmarks(tmp_path / f"lm{suffix}", file_coordinate_system="LPS")
        assert labels == ("chin", "mand r", "L3"), suffix
        np.testing.assert_allclose(read, LPS, atol=1e-9)
