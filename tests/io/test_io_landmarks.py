"""Landmark files: CSV and NPY layouts, and every way they can be wrong."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

from torchface.io import InputError, check_landmarks, read_landmarks


def _points() -> np.ndarray:
    rng = np.random.default_rng(1)
    return rng.uniform(10, 90, size=(68, 2))


def test_csv_with_header_and_comments(tmp_path):
    pts = _points()
    body = "\n".join(f"{x},{y}" for x, y in pts)
    (tmp_path / "lm.csv").write_text("# note\nx,y\n" + body + "\n")
    np.testing.assert_allclose(read_landmarks(tmp_path / "lm.csv", 100, 100), pts)


def test_csv_as_spreadsheets_and_numpy_write_it(tmp_path):
    """A byte order mark without a header (Excel's "CSV UTF-8"), np.savetxt's space-separated rows, a tab-separated
    file with a header, and quoted cells all read as the same 68 points; a second non-numeric line before the
    numbers is named rather than skipped (it used to be skipped silently, and the BOM cost the first point)."""
    pts = _points()
    np.savetxt(tmp_path / "savetxt.csv", pts)  # "x y" rows, '%.18e'
    (tmp_path / "bom.csv").write_bytes(b"\xef\xbb\xbf" + "\n".join(f"{x},{y}" for x, y in pts).encode())
    (tmp_path / "tabs.csv").write_text("x\ty\n" + "\n".join(f"{x}\t{y}" for x, y in pts) + "\n")
    (tmp_path / "quoted.csv").write_text('"x","y"\n' + "\n".join(f'"{x}","{y}"' for x, y in pts) + "\r\n")
    for name in ("savetxt.csv", "bom.csv", "tabs.csv", "quoted.csv"):
        np.testing.assert_allclose(read_landmarks(tmp_path / name, 100, 100), pts, err_msg=name)
    (tmp_path / "two.csv").write_text("landmarks of clip.mp4\nx,y\n" + "\n".join(f"{x},{y}" for x, y in pts))
    with pytest.raises(InputError, match=r"line 2 is not numbers: 'x,y'"):
        read_landmarks(tmp_path / "two.csv", 100, 100)


def test_csv_single_row_in_the_order_its_header_names(tmp_path):
    """OpenFace writes one row of ``x_0..x_67, y_0..y_67``: read as interleaved ``x0, y0, ...`` it gave other points,
    all inside the frame, with no error. A header naming every cell places them; an interleaved header, one
    that does not name them, or one from 1 reads as before."""
    pts = _points()
    xs_then_ys = ",".join(f"{v}" for v in np.r_[pts[:, 0], pts[:, 1]])
    (tmp_path / "openface.csv").write_text(
        ", ".join([f"x_{k}" for k in range(68)] + [f"y_{k}" for k in range(68)]) + "\n" + xs_then_ys + "\n"
    )
    np.testing.assert_allclose(read_landmarks(tmp_path / "openface.csv", 100, 100), pts)
    (tmp_path / "from1.csv").write_text(
        ",".join([f"X{k}" for k in range(1, 69)] + [f"Y{k}" for k in range(1, 69)]) + "\n" + xs_then_ys + "\n"
    )
    np.testing.assert_allclose(read_landmarks(tmp_path / "from1.csv", 100, 100), pts)
    interleaved = ",".join(f"{v}" for v in pts.reshape(-1))
    (tmp_path / "xy.csv").write_text(",".join(f"{c}{k}" for k in range(68) for c in "xy") + "\n" + interleaved)
    (tmp_path / "other.csv").write_text(",".join(f"p{k}" for k in range(136)) + "\n" + interleaved)
    for name in ("xy.csv", "other.csv"):
        np.testing.assert_allclose(read_landmarks(tmp_path / name, 100, 100), pts, err_msg=name)


def _openface_csv(pts: np.ndarray, rows: int, success: int = 1, three_d: bool = True) -> str:
    """OpenFace 2's FeatureExtraction layout: ', ' between cells, 2D x_k then y_k among other columns."""
    head = ["frame", "face_id", "timestamp", "confidence", "success", "pose_Tx", "pose_Rx"]
    head += [f"x_{k}" for k in range(68)] + [f"y_{k}" for k in range(68)]
    head += [f"X_{k}" for k in range(68)] + [f"Y_{k}" for k in range(68)] if three_d else []
    head += ["AU01_r", "AU45_c"]
    lines = [", ".join(head)]
    for f in range(rows):
        vals = [f + 1, 0, f / 30, 0.98, success if f == 0 else 1, 12.5, 0.1]
        vals += list(pts[:, 0] + f) + list(pts[:, 1] + f)
        vals += list(-pts[:, 0] - 40.0) + list(pts[:, 1] * 3.0) if three_d else []
        vals += [1.5, 1]
        lines.append(", ".join(repr(float(v)) for v in vals))
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("rows, three_d", [(1, False), (3, False), (4, True)])
def test_openfaces_per_frame_csv_gives_its_first_frames_points(tmp_path, rows, three_d):
    """An OpenFace FeatureExtraction CSV (the module docstring names OpenFace's x_k, y_k columns) used to be refused
    ("expected rows of 'x, y'" / "got an array of shape (143,)"): its first row's 2D points are read, not the 3D X_k."""
    pts = _points()
    (tmp_path / "of.csv").write_text(_openface_csv(pts, rows, three_d=three_d))
    np.testing.assert_allclose(read_landmarks(tmp_path / "of.csv", 100, 100), pts)


def test_openfaces_csv_whose_first_frame_failed_is_refused(tmp_path):
    (tmp_path / "of.csv").write_text(_openface_csv(_points(), 2, success=0))
    with pytest.raises(InputError, match="success 0"):
        read_landmarks(tmp_path / "of.csv", 100, 100)


def test_csv_single_row_and_npy_layouts(tmp_path):
    pts = _points()
    (tmp_path / "row.csv").write_text(",".join(f"{v}" for v in pts.reshape(-1)) + "\n")
    np.testing.assert_allclose(read_landmarks(tmp_path / "row.csv", 100, 100), pts)
    for shape in ((68, 2), (1, 68, 2), (136,)):
        np.save(tmp_path / "lm.npy", pts.reshape(shape))
        np.testing.assert_allclose(read_landmarks(tmp_path / "lm.npy", 100, 100), pts)


def test_a_flat_vector_all_x_then_all_y_is_refused(tmp_path):
    """A flat vector is read x0, y0, x1, y1, ...; one written all x then all y (``points.T.reshape(-1)``) passed the
    shape check and tracked junk. It is refused where its planar reading is a face and its interleaved one is not
    (planar_layout_problem's docstring: no genuine vector refused in 14040 faces of every pose)."""
    from torchface.io.landmarks import _IBUG_FRONTAL, planar_layout_problem

    turn = np.deg2rad(25.0)
    rotation = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    face = _IBUG_FRONTAL * [-1.0, 1.0] @ rotation.T * 250.0 + 50.0  # (mirrored, turned, centred on x = y)
    face += np.random.default_rng(3).normal(0.0, 1.0, face.shape)
    said = r"read as all x then all y they do: pass points.reshape\(2, 68\).T"
    planar = face.T.reshape(-1)
    np.save(tmp_path / "planar.npy", planar)
    (tmp_path / "planar.json").write_text(str(planar.tolist()))
    (tmp_path / "planar.csv").write_text(",".join(repr(v) for v in planar.tolist()) + "\n")
    for name in ("planar.npy", "planar.json", "planar.csv"):
        with pytest.raises(InputError, match=said):
            read_landmarks(tmp_path / name, 100, 100)
    for scale in (1.0, 1e300, 1e-300):  # (coordinates near float64's range judged alike, without an overflow warning)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert planar_layout_problem(planar * scale) is not None
            assert planar_layout_problem(face.reshape(-1) * scale) is None
    with pytest.raises(InputError, match="lm: the 136 values read as x0, y0, x1, y1"):
        check_landmarks(planar, 100, 100, "lm")
    np.testing.assert_allclose(check_landmarks(face.reshape(-1), 100, 100, "lm"), face)  # the same face, interleaved
    np.save(tmp_path / "lm.npy", face.reshape(-1))
    np.testing.assert_allclose(read_landmarks(tmp_path / "lm.npy", 100, 100), face)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda p: p[:67], "expected 68 iBUG landmarks, got 67"),
        (lambda p: np.vstack([p, p[:1]]), "got 69"),
        (lambda p: np.where(np.arange(68)[:, None] == 5, [np.nan, 5.0], p), r"landmark\(s\) \[5\] have one coord"),
        (lambda p: np.where(np.arange(68)[:, None] == 5, [np.inf, 5.0], p), r"landmark\(s\) \[5\] are infinite"),
        # (more than half of the points outside: a face at the edge may have fewer out, FILE_MIN_INSIDE)
        (lambda p: np.where(np.arange(68)[:, None] >= 33, 150.0, p), "35 landmark.s. outside the 100x100 frame, e.g. "
                                                                     "point 33"),
        (lambda p: np.where(np.arange(68)[:, None] < 35, [-3.0, 50.0], p), "point 0 at \\(-3.0, 50.0\\)"),
    ],
)
def test_bad_landmarks(tmp_path, edit, message):
    np.save(tmp_path / "lm.npy", edit(_points()))
    with pytest.raises(InputError, match=message) as info:
        read_landmarks(tmp_path / "lm.npy", 100, 100)
    assert "\n" not in str(info.value)


def test_a_files_points_may_cross_the_frames_edge_as_initialise_takes_them(tmp_path):
    """A landmarks file's points, as a detector's, may lie partly outside the frame (a face at the edge: an annotated
    chin a pixel below it), as ``FaceTracker.initialise`` takes them: a file's had to lie all inside
    (``torchface track`` refused a point 1 px out that the Python API fitted). More than half of the points given
    outside (another frame size's?) is refused, saying how to give a point the frame does not show as missing;
    ``min_inside=1.0`` still asks for all of them."""
    from torchface.io.landmarks import FILE_MIN_INSIDE

    assert FILE_MIN_INSIDE == 0.5
    points = _points()
    points[:3] = [[50.0, 100.5], [60.0, 101.0], [-1.0, 50.0]]
    assert np.array_equal(check_landmarks(points, 100, 100, "file"), points)
    assert np.array_equal(check_landmarks(points, 100, 100, "detector", min_inside=0.5), points)
    np.savetxt(tmp_path / "lm.csv", points, delimiter=",")
    assert np.array_equal(read_landmarks(tmp_path / "lm.csv", 100, 100), points)
    with pytest.raises(InputError, match="3 landmark.s. outside the 100x100 frame"):
        check_landmarks(points, 100, 100, "file", min_inside=1.0)
    # More than half outside: refused, told how to leave a point out, in the file's way.
    far = points.copy()
    far[:40] += 500.0
    np.savetxt(tmp_path / "far.csv", far, delimiter=",")
    with pytest.raises(InputError, match=r"pixel centres at integers\); at most half of the points given may lie "
                                         r"outside it \(a face at the frame's edge\); a point the frame does not show "
                                         r"is given as missing \(.*nan.*\)$"):  # fmt: skip
        read_landmarks(tmp_path / "far.csv", 100, 100)
    with pytest.raises(InputError, match=r"edge\)$"):  # (all must be given: no way out to tell)
        check_landmarks(far, 100, 100, "file", missing=False)
    with pytest.raises(InputError, match="68 landmark.s. outside"):
        check_landmarks(points + 500.0, 100, 100, "detector", min_inside=0.5)


def test_mediapipe_face_mesh_points_are_told_the_68_ibug_points_are_wanted(tmp_path):
    """MediaPipe's 478 (468) face mesh points, in a CSV or an array, were told "expected 68 iBUG landmarks, got 478"
    and nothing more: the message says which points are wanted."""
    rng = np.random.default_rng(0)
    for n in (468, 478):
        pts = rng.uniform(10, 90, (n, 2))
        (tmp_path / "mesh.csv").write_text("x,y\n" + "".join(f"{x},{y}\n" for x, y in pts))
        for call in (lambda: read_landmarks(tmp_path / "mesh.csv", 100, 100),
                     lambda: check_landmarks(pts, 100, 100, "detector")):  # fmt: skip
            with pytest.raises(InputError, match=rf"expected 68 iBUG landmarks, got {n} \(MediaPipe's face mesh "
                                                 r"points\? The 68 iBUG / 300-W landmarks are wanted"):  # fmt: skip
                call()
    with pytest.raises(InputError, match=r"got 67 \(a missing point"):  # (other counts: as before)
        check_landmarks(rng.uniform(10, 90, (67, 2)), 100, 100, "clip.mp4: landmarks", missing=True)


def test_other_landmark_sets_are_told_what_they_are_and_openposes_to_keep_its_first_68(tmp_path):
    """Another set's points (WFLW's 98, a 106-point set's, a 5-point set's, OpenPose's 70) where the 68 iBUG points
    are wanted were told "expected 68 iBUG landmarks, got 98 (a missing point stays, as a NaN row)", the rule of a
    set that leaves points out. They are named, and OpenPose's 70, whose first 68 are the iBUG points in order, told
    to keep those: what it names reads."""
    rng = np.random.default_rng(0)
    for n, said in ((98, r"WFLW's 98 points\? The 68 iBUG / 300-W landmarks are wanted, in their order .*: another "
                         r"set's points are other points"),
                    (106, r"a 106-point set's .*\? The 68 iBUG / 300-W landmarks are wanted"),
                    (5, r"a 5-point set's .*\? .*the nose tip and the mouth corners alone are iBUG points \(30, 48, "
                        r"54\), fewer than the 4 a start takes\)$"),
                    (70, r"OpenPose's 70 face points\? Its first 68 are the iBUG points, in their order \(then the "
                         r"pupils\): points\[:68\]\)$")):  # fmt: skip
        points = rng.uniform(10, 90, (n, 2))
        np.save(tmp_path / "lm.npy", points)
        for call in (lambda: read_landmarks(tmp_path / "lm.npy", 100, 100),
                     lambda: check_landmarks(points, 100, 100, "detector")):  # fmt: skip
            with pytest.raises(InputError, match=rf"expected 68 iBUG landmarks, got {n} \({said}"):
                call()
    np.save(tmp_path / "lm.npy", points[:68])  # (the 70's, as told)
    np.testing.assert_array_equal(read_landmarks(tmp_path / "lm.npy", 100, 100), points[:68])
    # A text file's reader (torchface track's user) is told to keep the file's rows, not the Python of an array.
    np.savetxt(tmp_path / "lm.csv", points, delimiter=",")
    with pytest.raises(InputError, match=r"Its first 68 are the iBUG points, in their order \(then the pupils\): keep "
                                         r"the file's first 68 rows\)$"):  # fmt: skip
        read_landmarks(tmp_path / "lm.csv", 100, 100)


def test_a_wrong_count_says_how_the_callers_source_writes_a_missing_point(tmp_path):
    """With ``missing``, a wrong count's error says a missing point stays as a NaN row, in the words of the source:
    a CSV's empty cells, a ``.pts`` line ``nan nan``, an NPY's or an array's NaN row. An array (the Python API,
    training_hooks' VideoDataset) was told about files: "(a missing point stays, as a NaN row: empty cells, 'nan
    nan')"."""
    pts = _dyadic_points()[:67]
    with pytest.raises(InputError) as info:
        check_landmarks(pts, 100, 100, "clip.mp4: landmarks", missing=True)
    expected = "expected 68 iBUG landmarks, got 67 (a missing point stays, as a NaN row"
    assert str(info.value) == f"clip.mp4: landmarks: {expected})"
    np.save(tmp_path / "short.npy", pts)
    (tmp_path / "short.csv").write_text("x,y\n" + "".join(f"{x},{y}\n" for x, y in pts))
    (tmp_path / "short.pts").write_text(_pts_text(pts))
    for name, how in (("short.npy", ""), ("short.csv", ": empty cells or nan"), ("short.pts", ": a line 'nan nan'")):
        with pytest.raises(InputError) as info:
            read_landmarks(tmp_path / name, 100, 100)
        assert str(info.value) == f"{tmp_path / name}: {expected}{how})"
    with pytest.raises(InputError) as info:  # (without missing points: no hint)
        check_landmarks(pts, 100, 100, "detector")
    assert str(info.value) == "detector: expected 68 iBUG landmarks, got 67"


def test_missing_and_garbled_files(tmp_path):
    with pytest.raises(InputError, match="no such landmarks file"):
        read_landmarks(tmp_path / "nope.csv", 100, 100)
    (tmp_path / "bad.csv").write_text("x,y\n1,2\nfoo,bar\n")
    with pytest.raises(InputError, match="line 3 is not numbers"):
        read_landmarks(tmp_path / "bad.csv", 100, 100)
    (tmp_path / "empty.npy").write_bytes(b"")  # an interrupted np.save: it raised EOFError
    with pytest.raises(InputError, match="not a readable .npy array"):
        read_landmarks(tmp_path / "empty.npy", 100, 100)
    (tmp_path / "three.csv").write_text("1,2,3\n4,5,6\n")
    with pytest.raises(InputError, match="rows of 'x, y'"):
        read_landmarks(tmp_path / "three.csv", 100, 100)
    (tmp_path / "lm.csv").mkdir()  # a folder was "no such landmarks file", though there is one by that name
    with pytest.raises(InputError, match=r"lm\.csv: a folder, not a landmarks file"):
        read_landmarks(tmp_path / "lm.csv", 100, 100)


def test_check_landmarks_returns_its_own_contiguous_copy():
    """A detector's points as a view with a negative stride (``yx[:, ::-1]``), read-only, or a buffer it reuses:
    the checked points are a C-contiguous copy (torch refuses negative strides, and the job and the datasets turn
    them into tensors; they keep them, so a detector writing into its buffer later must not change them)."""
    points = _points()
    yx = np.ascontiguousarray(points[:, ::-1])
    view = yx[:, ::-1]
    view.flags.writeable = False
    checked = check_landmarks(view, 100, 100, "detector", min_inside=0.5)
    assert np.array_equal(checked, points) and checked.flags.c_contiguous and checked.flags.writeable
    yx[0] = 0.0
    assert np.array_equal(checked, points)


def _dyadic_points() -> np.ndarray:
    """Points on a 1/64 pixel grid: ``x + 1`` and ``x - 1`` are exact in float64, so a round trip compares exactly."""
    return np.round(_points() * 64.0) / 64.0


def _pts_text(pts: np.ndarray, n_points: int | None = None, newline: str = "\n") -> str:
    """An iBUG / 300-W ``.pts`` file of 0-based ``pts``: 1-based, as the 300-W files are."""
    lines = ["version: 1", f"n_points:  {len(pts) if n_points is None else n_points}", "{"]
    lines += [f"{x + 1} {y + 1}" for x, y in pts] + ["}"]
    return newline.join(lines) + newline


def test_ibug_pts_files_are_read_one_based(tmp_path):
    """An iBUG / 300-W ``.pts`` file was refused ("line 2 is not numbers: 'n_points:  68'"). Its 1-based points read
    exactly as the 0-based points written (pixel centre (1, 1) is torchface's (0, 0)), as a ``.pts`` name or any
    name whose text starts with ``version:`` / ``n_points:``, with CRLF line ends or a byte order mark."""
    pts = _dyadic_points()
    pts[0] = [0.0, 0.0]  # the top-left pixel's centre: (1, 1) in the file
    (tmp_path / "lm.pts").write_text(_pts_text(pts))
    assert np.array_equal(read_landmarks(tmp_path / "lm.pts", 100, 100), pts)
    assert "1.0 1.0" in (tmp_path / "lm.pts").read_text()
    (tmp_path / "LM.PTS").write_bytes(b"\xef\xbb\xbf" + _pts_text(pts, newline="\r\n").encode())
    (tmp_path / "lm.txt").write_text(_pts_text(pts)[len("version: 1\n"):])  # (no version line: n_points first)
    for name in ("LM.PTS", "lm.txt"):
        assert np.array_equal(read_landmarks(tmp_path / name, 100, 100), pts), name


def test_a_pts_file_written_zero_based_is_told_so_where_it_shows(tmp_path):
    """A ``.pts`` written 0-based (its top-left pixel's centre at (0, 0)) with a point at a coordinate under 0.5
    (0: the first column or row) is refused saying the file looks 0-based and what to do (it was refused as a point
    "outside the frame at (-1.0, ...)", without a word of ``.pts``' 1-based convention); one whose points all lie at
    0.5 or more cannot be told, and reads 1-based. A point truly outside the frame (also read 0-based), normalised
    coordinates and another count are refused as before."""
    pts = _dyadic_points()
    pts[5] = [0.0, 37.0]
    (tmp_path / "zero.pts").write_text(_pts_text(pts - 1))  # (the 0-based points as they are: 0 in the file)
    with pytest.raises(InputError) as info:
        read_landmarks(tmp_path / "zero.pts", 100, 100)
    assert str(info.value) == (
        f"{tmp_path / 'zero.pts'}: 1 point left of or above the 100x100 frame as a .pts is read, 1-based (the top-left "
        "pixel's centre at (1, 1): 1 is subtracted), e.g. (0.0, 37.0) in the file, but every point inside it as "
        "written: is the file 0-based (the top-left pixel's centre at (0, 0), as OpenCV counts)? Add 1 to its "
        "coordinates, or save the points as a CSV (x,y), read as they are"), info.value  # fmt: skip
    inside = _dyadic_points()
    (tmp_path / "inside.pts").write_text(_pts_text(inside))
    assert np.array_equal(read_landmarks(tmp_path / "inside.pts", 100, 100), inside)
    out = pts.copy()
    out[30:, 0] -= 300.0  # (more than half of them outside read either way: FILE_MIN_INSIDE)
    (tmp_path / "out.pts").write_text(_pts_text(out - 1))
    with pytest.raises(InputError, match=r"landmark\(s\) outside the 100x100 frame") as info:
        read_landmarks(tmp_path / "out.pts", 100, 100)
    assert "0-based" not in str(info.value)
    (tmp_path / "unit.pts").write_text(_pts_text(_dyadic_points() / 100 - 1))  # (normalised, as written)
    with pytest.raises(InputError, match="outside the 100x100 frame"):
        read_landmarks(tmp_path / "unit.pts", 100, 100)
    (tmp_path / "short.pts").write_text(_pts_text(pts[:60] - 1))
    with pytest.raises(InputError, match="expected 68 iBUG landmarks, got 60"):
        read_landmarks(tmp_path / "short.pts", 100, 100)


def test_pts_coordinates_lose_one_exactly_in_decimal(tmp_path):
    """``1.1`` in a ``.pts`` is the ``0.1`` a CSV would hold (float ``1.1 - 1`` is 0.10000000000000009)."""
    pts = _dyadic_points()
    text = _pts_text(pts).splitlines()
    text[3] = "1.1 2.3"
    (tmp_path / "lm.pts").write_text("\n".join(text) + "\n")
    got = read_landmarks(tmp_path / "lm.pts", 100, 100)
    assert got[0].tolist() == [0.1, 1.3] and np.array_equal(got[1:], pts[1:])


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda t: t.replace(t.splitlines()[-2] + "\n", ""), r"line 71: 67 points before '\}', but n_points \(line 2"),
        (lambda t: t.replace("{\n", ""), r"line 3: expected 'version: 1', 'n_points: 68' or '\{' of a \.pts file"),
        (lambda t: "version: 1\nn_points: 68\n", r"no '\{' line: not a \.pts file"),
        (lambda t: t.replace("}\n", ""), r"line 71: the \.pts points end without their closing '\}'"),
        (lambda t: t.replace(t.splitlines()[5], "12.5 abc"), r"line 6 is not a \.pts point 'x y': '12.5 abc'"),
        (lambda t: t.replace(t.splitlines()[5], "12.5 13.5 1"), r"line 6 is not a \.pts point 'x y'"),
        (lambda t: t.replace(t.splitlines()[5], "12.5,13.5"), r"line 6 is not a \.pts point 'x y'"),
        (lambda t: t + "{\n", r"line 73: text after the closing '\}'"),
        (lambda t: t.replace("version: 1", "version: 2"), r"line 1: \.pts version '2', only version 1 is read"),
        (lambda t: t.replace("n_points:  68", "n_points: many"), r"line 2: n_points is not a count: 'many'"),
        (lambda t: t.replace("n_points:  68", "68 points"), r"line 2: expected 'version: 1', 'n_points: 68' or '\{'"),
        (lambda t: t.replace(t.splitlines()[5], "nan 13.5"), r"landmark\(s\) \[2\] have one coordinate NaN"),
        (lambda t: t.replace(t.splitlines()[5], "1e999999999 13.5"), r"landmark\(s\) \[2\] are infinite"),
        (lambda t: t.replace(t.splitlines()[5], "sNaN 13.5"), r"line 6 is not a \.pts point 'x y'"),
    ],
)
def test_malformed_pts_files_name_the_file_and_line(tmp_path, edit, message):
    (tmp_path / "bad.pts").write_text(edit(_pts_text(_dyadic_points())))
    with pytest.raises(InputError, match=message) as info:
        read_landmarks(tmp_path / "bad.pts", 100, 100)
    assert str(info.value).startswith(str(tmp_path / "bad.pts")) and "\n" not in str(info.value)


def test_pts_files_of_another_scheme_are_refused_by_count(tmp_path):
    """A 39-point profile ``.pts`` (menpo's), well formed: refused as not the 68 iBUG points."""
    (tmp_path / "profile.pts").write_text(_pts_text(_dyadic_points()[:39]))
    with pytest.raises(InputError, match="expected 68 iBUG landmarks, got 39"):
        read_landmarks(tmp_path / "profile.pts", 100, 100)


def test_one_row_per_point_csv_with_an_index_column(tmp_path):
    """``ibug_index,x,y,meaning`` (the layout of the package's own ``astronaut_landmarks.csv``) was refused ("line 4
    is not numbers"): its rows, in any order, place the points by index; the text columns are ignored."""
    pts = _points()
    order = np.random.default_rng(2).permutation(68)
    rows = [f'{k},{pts[k, 0]},{pts[k, 1]},"point {k}, by eye"' for k in order]
    (tmp_path / "long.csv").write_text("# hand-marked\nibug_index,x,y,meaning\n" + "\n".join(rows) + "\n")
    assert np.array_equal(read_landmarks(tmp_path / "long.csv", 100, 100), pts)
    rows = [f"{pts[k, 1]};{k};{pts[k, 0]}" for k in order]
    (tmp_path / "semi.csv").write_text("Y;Point;X\n" + "\n".join(rows) + "\n")
    assert np.array_equal(read_landmarks(tmp_path / "semi.csv", 100, 100), pts)


def test_one_row_per_point_csv_refusals_say_what_is_wrong(tmp_path):
    """An index repeated, out of 0-67 or not a number names its line."""
    body = "\n".join(f"{k},{10 + k * 0.5},{20 + k * 0.25}" for k in range(68))
    for edit, message in [
        (lambda b: b + "\n5,1,2", r"line 70: point 5 again \(first on line 7\)"),
        (lambda b: b.replace("0,10.0,20.0", "68,10.0,20.0"), "line 2: point index 68 is not an iBUG index 0-67"),
        (lambda b: b.replace("0,10.0,20.0", "zero,10.0,20.0"), "line 2 is not 'index, x, y' numbers"),
        (lambda b: b.replace("0,10.0,20.0", "0,10.0"), "line 2 is not 'index, x, y' numbers"),
    ]:
        (tmp_path / "bad.csv").write_text("index,x,y\n" + edit(body) + "\n")
        with pytest.raises(InputError, match=message) as info:
            read_landmarks(tmp_path / "bad.csv", 100, 100)
        assert "\n" not in str(info.value)
    # a named index counted from 1 (as many annotation tools number the points): said so (it was "point index 68 is
    # not an iBUG index 0-67" alone); not where the file has an index 0 (a 0-based file with a stray 68)
    one_based = "\n".join(f"{k + 1},{10 + k * 0.5},{20 + k * 0.25}" for k in range(68))
    (tmp_path / "one.csv").write_text("point,x,y\n" + one_based + "\n")
    said = r"line 69: point index 68 is not an iBUG index 0-67: numbered from 1\? The index column counts the points "
    with pytest.raises(InputError, match=said + r"from 0 \(0-67\): subtract 1 from each index$"):
        read_landmarks(tmp_path / "one.csv", 100, 100)
    (tmp_path / "stray.csv").write_text("point,x,y\n" + body + "\n68,1,2\n")
    with pytest.raises(InputError, match=r"line 70: point index 68 is not an iBUG index 0-67$"):
        read_landmarks(tmp_path / "stray.csv", 100, 100)
    # (its 0 written "00", which is read as 0: it was told it was numbered from 1)
    (tmp_path / "stray.csv").write_text("point,x,y\n" + body.replace("0,", "00,", 1) + "\n68,1,2\n")
    with pytest.raises(InputError, match=r"line 70: point index 68 is not an iBUG index 0-67$"):
        read_landmarks(tmp_path / "stray.csv", 100, 100)
    (tmp_path / "id.csv").write_text("id,x,y\n" + body + "\n")  # an index column of another name: says which
    with pytest.raises(InputError, match=r"rows of 'x, y' \(or, one row per point, a header naming ibug_index, x"):
        read_landmarks(tmp_path / "id.csv", 100, 100)


#: The points left out in the missing-point tests (an occluded jaw side, an eye corner, the mouth's corner).
_MISSING = [0, 1, 2, 3, 36, 48, 67]


def _with_missing(pts: np.ndarray) -> np.ndarray:
    out = pts.copy()
    out[_MISSING] = np.nan
    return out


def test_missing_points_read_as_nan_rows_in_every_layout(tmp_path):
    """A landmarks file with points left out (a detector's occluded ones) was refused ("landmark(s) [0, 1, ...] are
    NaN or infinite"; an empty CSV cell was dropped, shifting the cells after it; a one-row-per-point CSV without
    some points: "gives 61 of the 68 iBUG points"): every layout now gives a NaN row for each missing point, the
    others as written, as the tracker's Python API takes them."""
    pts = _dyadic_points()
    want = _with_missing(pts)
    gone = set(_MISSING)

    def cells(k: int, empty: str = "") -> list[str]:
        return [empty, empty] if k in gone else [repr(float(pts[k, 0])), repr(float(pts[k, 1]))]

    files = {
        "rows.csv": "x,y\n" + "".join(",".join(cells(k)) + "\n" for k in range(68)),
        "rows_trailing.csv": "".join(",".join(cells(k)) + ",\n" for k in range(68)),  # x,y, (a spreadsheet's)
        "rows_nan.csv": "x;y\n" + "".join(";".join(cells(k, "NaN")) + "\n" for k in range(68)),
        "rows_na.tsv": "".join("\t".join(cells(k, "NA")) + "\n" for k in range(68)),
        "rows_null.csv": "".join(",".join(cells(k, "null")) + "\n" for k in range(68)),
        "rows_quoted.csv": "".join(",".join(f'"{c}"' for c in cells(k)) + "\n" for k in range(68)),
        "rows_spaces.txt": "".join(" ".join(cells(k, "nan")) + "\n" for k in range(68)),
        "one_row.csv": ",".join(c for k in range(68) for c in cells(k)) + "\n",
        "one_row_trailing.csv": ",".join(c for k in range(68) for c in cells(k)) + ",\n",
        "named.csv": ",".join([f"x_{k}" for k in range(68)] + [f"y_{k}" for k in range(68)]) + "\n"
        + ",".join([cells(k)[0] for k in range(68)] + [cells(k)[1] for k in range(68)]) + "\n",
        "long.csv": "ibug_index,x,y\n" + "".join(f"{k},{pts[k, 0]},{pts[k, 1]}\n" for k in range(68) if k not in gone),
        "long_empty.csv": "index;x;y\n" + "".join(f"{k};{';'.join(cells(k))}\n" for k in range(68)),
        "lm.pts": _pts_text(want),  # (nan + 1: "nan nan")
    }
    lines = _openface_csv(want, 2).splitlines()  # OpenFace's per-frame CSV, its first frame's points empty cells
    files["openface.csv"] = "\n".join([lines[0]] + [line.replace("nan", "") for line in lines[1:]]) + "\n"
    assert ", , " in files["openface.csv"] and "nan nan" in files["lm.pts"]
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    np.save(tmp_path / "lm.npy", want)
    for name in [*files, "lm.npy"]:
        got = read_landmarks(tmp_path / name, 100, 100)
        np.testing.assert_array_equal(got, want, err_msg=name)  # (NaN where NaN, the rest exactly)
    with pytest.raises(InputError, match=r"landmark\(s\) \[0, 1, 2, 3, 36, 48, 67\] are NaN or infinite"):
        read_landmarks(tmp_path / "rows.csv", 100, 100, missing=False)  # (all 68 asked for)


def test_complete_files_read_as_before_with_empty_cells_in_place(tmp_path):
    """A separator ending every line (``x,y,``) is no cell; an empty cell between two is one, in its place (it was
    dropped: ``1,,2`` read as the point (1, 2))."""
    pts = _points()
    (tmp_path / "trailing.csv").write_text("x,y,\n" + "".join(f"{x},{y},\n" for x, y in pts))
    (tmp_path / "one_row.csv").write_text(",".join(repr(float(v)) for v in pts.reshape(-1)) + ",\n")
    for name in ("trailing.csv", "one_row.csv"):
        np.testing.assert_array_equal(read_landmarks(tmp_path / name, 100, 100), pts, err_msg=name)
    (tmp_path / "gap.csv").write_text("".join(f"{x},{y}\n" for x, y in pts[:-1]) + "1,,2\n")
    with pytest.raises(InputError, match=r"rows of \[2, 3\] values"):
        read_landmarks(tmp_path / "gap.csv", 100, 100)


def test_a_separator_ending_every_line_under_a_header_of_other_words_is_no_cell(tmp_path):
    """Rows ``x,y,`` under a header line that does not name the cells (a title of three words or more, ``x,y,note``
    with the note left empty) were read as before the missing points, ``x, y``; since, the header's width decided
    which empty cells at a row's end were cells: "expected rows of 'x, y' ..., got rows of [3] values". A missing
    point under such a header stays a NaN row."""
    pts = _points()
    rows = [f"{x},{y}," for x, y in pts]
    for name, header in (("title.csv", "first frame landmarks"), ("note.csv", "x,y,note"),
                         ("semicolons.csv", "landmarks of frame 0")):  # fmt: skip
        body = [r.replace(",", ";") for r in rows] if name == "semicolons.csv" else rows
        (tmp_path / name).write_text(header + "\n" + "\n".join(body) + "\n")
        np.testing.assert_array_equal(read_landmarks(tmp_path / name, 100, 100), pts, err_msg=name)
    want = pts.copy()
    want[:2] = np.nan
    (tmp_path / "gap.csv").write_text("first frame landmarks\n,,\n,\n" + "\n".join(rows[2:]) + "\n")
    np.testing.assert_array_equal(read_landmarks(tmp_path / "gap.csv", 100, 100), want)


def test_too_few_points_given_are_refused_naming_the_file_and_the_count(tmp_path):
    """Fewer than the landmark fit's MIN_FIT_LANDMARKS (4) points given: refused, naming the file and the count; 4
    are read (the fit decides whether they hold a pose). Infinite values, a point with one coordinate missing, a
    given point outside the frame and another count are refused as before."""
    from torchface.tracker.fit import MIN_FIT_LANDMARKS

    pts = _points()
    for given in (0, MIN_FIT_LANDMARKS - 1, MIN_FIT_LANDMARKS):
        lm = np.full((68, 2), np.nan)
        lm[10 : 10 + given] = pts[10 : 10 + given]
        path = tmp_path / f"lm{given}.npy"
        np.save(path, lm)
        if given >= MIN_FIT_LANDMARKS:
            np.testing.assert_array_equal(read_landmarks(path, 100, 100), lm)
            continue
        with pytest.raises(InputError) as info:
            read_landmarks(path, 100, 100)
        message = str(info.value)
        assert message.startswith(f"{path}: {given} of the 68 iBUG points given") and "\n" not in message
        assert f"the landmark fit needs at least {MIN_FIT_LANDMARKS}" in message
    (tmp_path / "three.csv").write_text("index,x,y\n" + "".join(f"{k},{pts[k, 0]},{pts[k, 1]}\n" for k in (4, 9, 30)))
    with pytest.raises(InputError, match=r"three\.csv: 3 of the 68 iBUG points given"):
        read_landmarks(tmp_path / "three.csv", 100, 100)
    # (more than half of the points given outside: FILE_MIN_INSIDE; here 3 of 4, points 6 and 7 far out)
    outside = np.full((68, 2), np.nan)
    outside[5:9] = pts[5:9]
    outside[6:8] = [[300.0, 50.0], [50.0, -200.0]]
    outside[5] = [150.0, 50.0]
    np.save(tmp_path / "outside.npy", outside)
    with pytest.raises(InputError, match=r"3 landmark\(s\) outside the 100x100 frame, e.g. point 5"):
        read_landmarks(tmp_path / "outside.npy", 100, 100)
    # just outside the frame's edge (pixel centres at integers: it spans -0.5 to 99.5): the point as given, and the
    # frame's span (it was written to 0.1, "at (-0.5, 50.0)", which reads as inside); the edge itself is inside
    # (one outside by less than 10 digits show, 99.50000000001, was "at (99.5, 50.0)": all its digits)
    for x, said in ((-0.51, "-0.51"), (99.5001, "99.5001"), (99.50000000001, "99.50000000001"),
                    (-0.5000000000001, "-0.5000000000001")):  # fmt: skip
        outside[5] = [x, 50.0]
        np.save(tmp_path / "edge.npy", outside)
        span = (r"\(the frame spans x -0\.5 to 99\.5, y -0\.5 to 99\.5: pixel centres at integers\); at most half "
                r"of the points given may lie outside it \(a face at the frame's edge\); a point the frame does not "
                r"show is given as missing, a NaN row$")  # (an array's way)
        with pytest.raises(InputError, match=rf"e\.g\. point 5 at \({re.escape(said)}, 50\.0\) " + span):
            read_landmarks(tmp_path / "edge.npy", 100, 100)
        outside[5] = [round(x + 0.01) - 0.5 if x > 0 else -0.5, 50.0]
        np.save(tmp_path / "edge.npy", outside)
        assert read_landmarks(tmp_path / "edge.npy", 100, 100)[5, 0] == outside[5, 0]
    (tmp_path / "short.pts").write_text(_pts_text(_dyadic_points()[:60]))  # which 8 are missing is not known
    with pytest.raises(InputError, match=r"expected 68 iBUG landmarks, got 60 \(a missing point stays, as a NaN row"):
        read_landmarks(tmp_path / "short.pts", 100, 100)


def test_the_packages_hand_marked_22_points_are_read_with_the_others_missing():
    """``astronaut_landmarks.csv`` (22 iBUG points, one row each) was refused ("gives 22 of the 68 iBUG points"):
    its points are read in place, the other 46 NaN."""
    import csv

    from torchface.synth.subjects import _data_path

    path = _data_path("photos", "astronaut_landmarks.csv")
    with open(path, newline="") as f:
        rows = [r for r in csv.DictReader(line for line in f if not line.startswith("#"))]
    got = read_landmarks(path, 512, 512)
    given = {int(r["ibug_index"]): (float(r["x"]), float(r["y"])) for r in rows}
    assert len(given) == 22 and int(np.isfinite(got).all(1).sum()) == 22
    for k, xy in given.items():
        assert tuple(got[k]) == xy


def test_a_column_empty_on_every_row_of_x_y_rows_is_no_cell(tmp_path):
    """A spreadsheet's export of cells from its column B (``,x,y`` rows) was read before the missing points (every
    empty cell dropped), then refused ("got rows of [3] values"): a column empty on every row is no cell (leading, in
    between, trailing), a row of empty cells a missing point; a column empty on some rows only is refused as before."""
    pts = _points()
    want = pts.copy()
    want[[3, 40]] = np.nan
    rows = [f"{x},{y}" for x, y in pts]
    files = {
        "column_b.csv": "".join(f",{r}\n" for r in rows),
        "column_b_header.csv": ",x,y\n" + "".join(f",{r},\n" for r in rows),
        "column_c.csv": "".join(f";;{r.replace(',', ';')}\n" for r in rows),
        "between.csv": "".join(f"{x},,{y}\n" for x, y in pts),
    }
    for name, text in files.items():
        (tmp_path / name).write_text(text)
        np.testing.assert_array_equal(read_landmarks(tmp_path / name, 100, 100), pts, err_msg=name)
    gaps = [",,," if k == 3 else "," if k == 40 else f",{r}" for k, r in enumerate(rows)]  # (missing: 3 and 40)
    (tmp_path / "gaps.csv").write_text("\n".join(gaps) + "\n")
    np.testing.assert_array_equal(read_landmarks(tmp_path / "gaps.csv", 100, 100), want)
    (tmp_path / "some.csv").write_text("".join(f",{r}\n" for r in rows[:-1]) + "1,2,3\n")
    with pytest.raises(InputError, match=r"got rows of \[3\] values") as info:
        read_landmarks(tmp_path / "some.csv", 100, 100)
    assert "\n" not in str(info.value)


def test_one_row_with_an_empty_column_before_its_136_values_is_read(tmp_path):
    """One row ``,x0,y0,...,x67,y67`` (a spreadsheet's export with an index column left empty) was read before the
    missing points (every empty cell dropped), then refused ("an array of shape (137,)"): an empty column before one
    row's 136 values is no cell, as a column empty on every row of ``x, y`` rows; the 136 values keep their missing
    points. A row of 136 cells is all values: its empty first cell is point 0's ``x`` missing, refused as before."""
    pts = _dyadic_points()
    want = _with_missing(pts)
    values = [repr(float(v)) for v in pts.reshape(-1)]
    gaps = ["" if k // 2 in set(_MISSING) else v for k, v in enumerate(values)]
    named = [f"x_{k}" for k in range(68)] + [f"y_{k}" for k in range(68)]
    files = {
        "index_empty.csv": ("," + ",".join(values) + "\n", pts),
        "index_empty_trailing.csv": ("," + ",".join(values) + ",\r\n", pts),
        "column_c.csv": (";;" + ";".join(values) + "\n", pts),
        "index_empty_gaps.csv": ("," + ",".join(gaps) + "\n", want),
        "index_empty_header.csv": ("," + ",".join(f"{c}{k}" for k in range(68) for c in "xy") + "\n,"
                                   + ",".join(values) + "\n", pts),  # fmt: skip
        "index_empty_named.csv": ("," + ",".join(named) + "\n," + ",".join(values[0::2] + values[1::2]) + "\n", pts),
    }
    for name, (text, expected) in files.items():
        (tmp_path / name).write_text(text)
        np.testing.assert_array_equal(read_landmarks(tmp_path / name, 100, 100), expected, err_msg=name)
    (tmp_path / "x0_missing.csv").write_text("," + ",".join(values[1:]) + "\n")  # 136 cells: x0 missing
    with pytest.raises(InputError, match=r"landmark\(s\) \[0\] have one coordinate NaN"):
        read_landmarks(tmp_path / "x0_missing.csv", 100, 100)
    (tmp_path / "both_ends.csv").write_text(",," + ",".join(values[:-2]) + ",,\n")  # point 0 or point 67 missing?
    with pytest.raises(InputError, match=r"one row of 138 cells, empty at both ends: which 136 are the x, y values"):
        read_landmarks(tmp_path / "both_ends.csv", 100, 100)
    (tmp_path / "id.csv").write_text("id," + ",".join(named) + "\n," + ",".join(values[0::2] + values[1::2]) + "\n")
    np.testing.assert_array_equal(read_landmarks(tmp_path / "id.csv", 100, 100), pts)  # a named column: OpenFace's way


def test_spreadsheets_other_text_encodings_are_read(tmp_path):
    """Excel's "Unicode Text" (UTF-16 after a byte order mark, tab-separated) and an 8-bit export (Windows-1252: a
    header or comment with an accent) were refused: "cannot read landmarks (UnicodeDecodeError)"; their numbers are
    read as from UTF-8. A binary file (a PNG given as landmarks) is refused in one line as no text."""
    pts = _points()
    rows = "".join(f"{x}\t{y}\r\n" for x, y in pts)
    (tmp_path / "unicode_text.txt").write_bytes(("\ufeffx\ty\r\n" + rows).encode("utf-16-le"))
    (tmp_path / "unicode_text_be.txt").write_bytes(("\ufeffx\ty\r\n" + rows).encode("utf-16-be"))
    (tmp_path / "cp1252.csv").write_bytes(("# visage, côté gauche – frame 0\nx;y\n" + rows).encode("cp1252"))
    for name in ("unicode_text.txt", "unicode_text_be.txt", "cp1252.csv"):
        np.testing.assert_array_equal(read_landmarks(tmp_path / name, 100, 100), pts, err_msg=name)
    (tmp_path / "face.png").write_bytes(b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\x00\x00\x00\x10")
    with pytest.raises(InputError, match=r"face\.png: not a text file \(NUL bytes\): landmarks are a CSV") as info:
        read_landmarks(tmp_path / "face.png", 100, 100)
    assert "\n" not in str(info.value)


def test_decimal_commas_of_a_european_spreadsheet_are_read(tmp_path):
    """A spreadsheet of a decimal-comma locale writes ``12,5;40,25`` (semicolons, or tabs in its "Unicode Text"):
    refused ("got rows of [4] values"; a one-row-per-point file: "not 'index, x, y' numbers"). Where cells are
    separated by semicolons or tabs and no number has a decimal point, a comma between digits is one; a decimal
    point anywhere keeps commas as they were (separators: ``1,234.5;56.5`` is 3 cells, refused)."""
    pts = _dyadic_points()
    want = _with_missing(pts)

    def comma(v: float) -> str:
        return repr(float(v)).replace(".", ",")

    rows = [["", ""] if k in _MISSING else [comma(x), comma(y)] for k, (x, y) in enumerate(pts)]
    files = {
        "semicolons.csv": "x;y\n" + "".join(";".join(r) + "\n" for r in rows),
        "tabs.txt": "x\ty\r\n" + "".join("\t".join(r) + "\r\n" for r in rows),
        "one_row.csv": ";".join(c for r in rows for c in r) + "\n",
        "quoted.csv": "".join(";".join(f'"{c}"' for c in r) + "\n" for r in rows),
        "long.csv": "# frame 0\nibug_index;x;y;meaning\n"
        + "".join(f"{k};{';'.join(r)};a, b\n" for k, r in enumerate(rows)),
    }
    for name, text in files.items():
        (tmp_path / name).write_text(text)
        np.testing.assert_array_equal(read_landmarks(tmp_path / name, 100, 100), want, err_msg=name)
    (tmp_path / "grouped.csv").write_text("x;y\n" + "".join(f"{x:,.1f};{y:.1f}\n" for x, y in pts * 100))
    with pytest.raises(InputError, match=r"got rows of \[3\] values"):  # (1,234.5: a thousands separator, no cell)
        read_landmarks(tmp_path / "grouped.csv", 10000, 10000)


def test_tab_separated_empty_cells_at_a_lines_ends_are_cells(tmp_path):
    """A tab-separated file (a spreadsheet's "Unicode Text") writes a missing point as empty cells, ``\\t``: the line
    was stripped of its tabs, so a missing point's row vanished ("expected 68 iBUG landmarks, got 61"), one row's
    leading missing point shifted the cells after it, and a one-row-per-point ``5\\t\\t`` was refused ("not 'index,
    x, y' numbers"). Tabs at a line's ends now separate cells, as commas do."""
    pts = _dyadic_points()
    want = _with_missing(pts)
    rows = [["", ""] if k in _MISSING else [repr(float(x)), repr(float(y))] for k, (x, y) in enumerate(pts)]
    files = {
        "rows.tsv": "x\ty\n" + "".join("\t".join(r) + "\n" for r in rows),
        "one_row.tsv": "\t".join(c for r in rows for c in r) + "\n",
        "long.tsv": "index\tx\ty\n" + "".join(f"{k}\t{chr(9).join(r)}\n" for k, r in enumerate(rows)),
        "column_b.tsv": "".join("\t" + "\t".join(r) + "\n" for r in rows),  # (an empty column: no cell)
    }
    for name, text in files.items():
        (tmp_path / name).write_text(text)
        np.testing.assert_array_equal(read_landmarks(tmp_path / name, 100, 100), want, err_msg=name)


def test_npy_landmarks_that_are_no_real_points_array_say_so(tmp_path):
    """An ``.npz`` archive under an ``.npy`` name (``np.savez``) was refused as "landmarks must be numbers, got <U5"
    (its file names), with the archive left open; complex points were read with their imaginary part dropped (a
    ``ComplexWarning``). Now each is a one-line InputError; float16, int and ``(1, 68, 2)`` arrays are read."""
    pts = _dyadic_points()
    np.savez(tmp_path / "lm.npz", pts)
    (tmp_path / "lm.npz").rename(tmp_path / "archive.npy")
    np.save(tmp_path / "complex.npy", pts.astype(np.complex128))
    with pytest.raises(InputError, match=r"archive\.npy: an \.npz archive of arrays \(arr_0\), not one \.npy array"):
        read_landmarks(tmp_path / "archive.npy", 100, 100)
    with pytest.raises(InputError, match=r"complex\.npy: landmarks must be real numbers, got complex128"):
        read_landmarks(tmp_path / "complex.npy", 100, 100)
    with pytest.raises(InputError, match=r"detector: landmarks must be real numbers, got bool"):
        check_landmarks(pts > 50, 100, 100, "detector")
    for name, array in (("f16.npy", pts.astype(np.float16)[None]), ("int.npy", pts.astype(np.int32))):
        np.save(tmp_path / name, array)
        np.testing.assert_array_equal(read_landmarks(tmp_path / name, 100, 100), array.reshape(68, 2), err_msg=name)


def test_pandas_to_csv_with_its_index_is_read(tmp_path):
    """``pd.DataFrame(points).to_csv(path)`` (pandas' default keeps its index: a header ``,0,1`` or, with named
    columns, ``,x,y``, then rows ``k,x,y``) was refused ("got rows of [3] values"): its index is the point's, as in a
    one-row-per-point CSV (a missing point: empty cells, or no row after ``dropna()`` while the index keeps 0 or
    68; without both it may be R's 1-based row names: :func:`test_r_write_csv_with_its_1_based_row_names_is_read`)."""
    pts = _dyadic_points()
    want = _with_missing(pts)

    def rows(empty: bool, kept: frozenset[int] = frozenset()) -> str:
        gone = set(_MISSING) - kept
        return "".join(f"{k},," + "\n" if k in gone and empty else "" if k in gone else f"{k},{x!r},{y!r}\n"
                       for k, (x, y) in enumerate(pts.tolist()))  # fmt: skip

    with_0 = _with_missing(pts)
    with_0[0] = pts[0]
    files = {"numbered.csv": (",0,1\n" + rows(True), want), "named.csv": (",x,y\n" + rows(False, {0}), with_0),
             "semicolons.csv": (";x;y\n" + rows(True).replace(",", ";"), want),
             "crlf.csv": (",0,1\r\n" + rows(False, {0}), with_0)}  # fmt: skip
    for name, (text, expected) in files.items():
        (tmp_path / name).write_text(text)
        np.testing.assert_array_equal(read_landmarks(tmp_path / name, 100, 100), expected, err_msg=name)
    (tmp_path / "dropped.csv").write_text(",x,y\n" + rows(False))  # (points 0 and 67 without rows: 1..66)
    with pytest.raises(InputError, match=r"has neither 0 nor 68, so whether it counts the points from 0"):
        read_landmarks(tmp_path / "dropped.csv", 100, 100)
    (tmp_path / "no_index.csv").write_text(",x,y\n" + "".join(f",{x!r},{y!r}\n" for x, y in pts.tolist()))
    np.testing.assert_array_equal(read_landmarks(tmp_path / "no_index.csv", 100, 100), pts)  # (column B, as before)


def test_json_landmarks_and_a_torchface_sidecar_are_read(tmp_path):
    """A ``.json`` of ``[x, y]`` pairs (as the sidecar's ``initial_landmarks_px``, ``[null, null]`` a missing point)
    was read as CSV text and refused as "expected 68 iBUG landmarks, got 0 (... empty cells or nan)"; a list of
    pairs, a flat list of 136 numbers and a torchface sidecar (a run started from the landmarks another one did) are
    read; other JSON is refused in one line."""
    import json

    pts = _dyadic_points()
    want = _with_missing(pts)
    pairs = [None if np.isnan(p).any() else p.tolist() for p in want]
    pairs = [[None, None] if p is None else p for p in pairs]
    files = {
        "pairs.json": pairs,
        "flat.json": [c for p in pairs for c in p],
        "sidecar.json": {"torchface_output": "track", "initial_landmarks_px": pairs, "frames": 3},
    }
    for name, value in files.items():
        (tmp_path / name).write_text(json.dumps(value))
        np.testing.assert_array_equal(read_landmarks(tmp_path / name, 100, 100), want, err_msg=name)
    bad = {
        "broken.json": ("[[1, 2],", r"broken\.json: not valid JSON \(Expecting value, line 1\)"),
        "other.json": ('{"points": []}', r"other\.json: a JSON object without initial_landmarks_px"),
        "text.json": (json.dumps([["1", "2"]] * 68), r"text\.json: expected a JSON list of 68 \[x, y\] pairs"),
        "triples.json": (json.dumps([[1, 2, 3]] * 68), r"triples\.json: expected a JSON list of 68 \[x, y\] pairs"),
        "short.json": (json.dumps(pairs[:60]), r"got 60 \(a missing point stays, as a NaN row: \[null, null\]\)"),
    }
    for name, (text, message) in bad.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(InputError, match=message) as info:
            read_landmarks(tmp_path / name, 100, 100)
        assert "\n" not in str(info.value)


def test_decimal_comma_reading_leaves_comma_separated_files_as_they_were(tmp_path):
    """Files of integer pixels whose commas separate cells and that hold a semicolon elsewhere were read before the
    decimal commas, then refused: a title line ``Landmarks; frame 0`` over ``x,y`` rows ("got rows of [1] values":
    each ``12,40`` read as 12.40) and one row of pairs ``x0,y0;x1,y1;...`` ("got 34"). A comma is a decimal one only
    on lines whose cells semicolons or tabs separate, and where only the comma-separated reading gives 68 points,
    that reading is kept."""
    pts = np.round(_points()).astype(int)
    rows = "".join(f"{x},{y}\n" for x, y in pts)
    files = {
        "title.csv": "Landmarks; frame 0\n" + rows,
        "pairs.csv": ";".join(f"{x},{y}" for x, y in pts) + "\n",
        "pairs_tabs.txt": "\t".join(f"{x},{y}" for x, y in pts) + "\n",
    }
    for name, text in files.items():
        (tmp_path / name).write_text(text)
        np.testing.assert_array_equal(read_landmarks(tmp_path / name, 100, 100), pts, err_msg=name)


def test_thousands_separators_are_refused_not_read_as_decimal_commas(tmp_path):
    """A tab- or semicolon-separated export of integer pixels formatted with thousands separators (``3,402\\t2,536``,
    a 4K frame) was refused before the decimal commas ("got rows of [2, 3, 4] values"), then read as decimal commas:
    every such point silently 1000 times nearer the corner (3.402, 2.536). Where every comma has three digits after
    it and 1-3 before (a thousands group or a decimal comma), the file is refused, saying so."""
    pts = np.round(_points() * 40).astype(int)  # up to about 4000 x 3000
    assert (pts >= 1000).any() and (pts < 1000).any()
    for name, sep in (("tabs.txt", "\t"), ("semicolons.csv", ";")):
        (tmp_path / name).write_text("".join(f"{x:,}{sep}{y:,}\n" for x, y in pts))
        with pytest.raises(InputError, match=r"a thousands separator or a decimal comma"):
            read_landmarks(tmp_path / name, 4096, 4096)
    (tmp_path / "three_decimals.csv").write_text("".join(f"{x / 8:.3f};{y / 8:.3f}\n" for x, y in pts).replace(".", ","))
    with pytest.raises(InputError, match=r"a thousands separator or a decimal comma"):
        read_landmarks(tmp_path / "three_decimals.csv", 4096, 4096)
    (tmp_path / "mixed.csv").write_text("".join(f"{x / 8:.3f};{y / 8:.2f}\n" for x, y in pts).replace(".", ","))
    want = np.column_stack([pts[:, 0] / 8, [float(f"{y / 8:.2f}") for y in pts[:, 1]]])  # (a decimal comma, 2 digits)
    np.testing.assert_array_equal(read_landmarks(tmp_path / "mixed.csv", 4096, 4096), want)


def test_pandas_and_one_row_per_point_files_with_decimal_commas_are_read(tmp_path):
    """``DataFrame.to_csv(path, sep=";", decimal=",")`` (a decimal-comma locale's pandas: ``;x;y`` then rows
    ``0;16,75;29,0``) was refused with "line 2 is not 'index, x, y' numbers" (it is): the index layout split the rows
    at their first comma, the decimal one; a one-row-per-point header with a comma in a column name (``meaning,
    notes``) was split there too ("line 2 is not numbers"). The decimal commas' separator, ``;`` or a tab, is now
    the cells'."""
    pts = _dyadic_points()

    def comma(v: float) -> str:
        return repr(float(v)).replace(".", ",")

    files = {
        "pandas.csv": ";x;y\n" + "".join(f"{k};{comma(x)};{comma(y)}\n" for k, (x, y) in enumerate(pts)),
        "pandas_tabs.tsv": "\t0\t1\n" + "".join(f"{k}\t{comma(x)}\t{comma(y)}\n" for k, (x, y) in enumerate(pts)),
        "long.csv": "ibug_index;x;y;meaning, notes\n"
        + "".join(f"{k};{comma(x)};{comma(y)};jaw\n" for k, (x, y) in enumerate(pts)),
    }
    for name, text in files.items():
        (tmp_path / name).write_text(text)
        np.testing.assert_array_equal(read_landmarks(tmp_path / name, 100, 100), pts, err_msg=name)


def test_a_sidecar_of_a_run_started_after_frame_0_is_refused(tmp_path):
    """A sidecar's ``initial_landmarks_px`` are those of the frame its run started at, ``start.first_frame``: 0, or
    with a detector the first frame where it found a face. Such a sidecar given as ``--landmarks`` (the first frame's)
    was read without a word: frame 12's points placed on frame 0's face. It is refused, naming the frame."""
    import json

    pts = _dyadic_points()
    sidecar = {"torchface_output": "track", "initial_landmarks_px": pts.tolist(), "start": {"first_frame": 12}}
    (tmp_path / "late.json").write_text(json.dumps(sidecar))
    with pytest.raises(InputError, match=r"late\.json: that run started at frame 12 .* not the first frame's"):
        read_landmarks(tmp_path / "late.json", 100, 100)
    sidecar["start"]["first_frame"] = 0
    (tmp_path / "first.json").write_text(json.dumps(sidecar))
    np.testing.assert_array_equal(read_landmarks(tmp_path / "first.json", 100, 100), pts)


def test_json_of_one_frame_of_points_is_read_as_an_npy_of_that_shape(tmp_path):
    """A ``.json`` ``[[[x, y], ...]]`` (one frame's points, shape ``(1, 68, 2)``, as
    ``json.dump(points[None].tolist())`` writes them) was refused ("expected a JSON list of 68 [x, y] pairs"), though an ``.npy`` of that shape is read.
    It is read the same; ``(1, 136)``, refused as an ``.npy``, and two frames stay refused."""
    import json

    pts = _dyadic_points()
    want = _with_missing(pts)
    pairs = [[None, None] if np.isnan(p).any() else p.tolist() for p in want]
    for name, value in (("frame.json", [pairs]), ("sidecar.json", {"initial_landmarks_px": [pairs]})):
        (tmp_path / name).write_text(json.dumps(value))
        np.testing.assert_array_equal(read_landmarks(tmp_path / name, 100, 100), want, err_msg=name)
    np.save(tmp_path / "flat.npy", pts.reshape(1, 136))
    with pytest.raises(InputError, match=r"got an array of shape \(1, 136\)"):  # (the .npy path refuses it too)
        read_landmarks(tmp_path / "flat.npy", 100, 100)
    bad = {"flat.json": [[c for p in pts.tolist() for c in p]], "two.json": [pts.tolist(), pts.tolist()]}
    for name, value in bad.items():
        (tmp_path / name).write_text(json.dumps(value))
        with pytest.raises(InputError, match=r"expected a JSON list of 68 \[x, y\] pairs"):
            read_landmarks(tmp_path / name, 100, 100)


def test_r_write_csv_with_its_1_based_row_names_is_read(tmp_path):
    """R's ``write.csv(points)`` (a header ``"","x","y"``, rows ``"1",x,y`` ... ``"68",x,y``: its row names, 1-based)
    was taken for pandas' 0-based index and refused: "point index 68 is not an iBUG index 0-67". An unnamed index
    with 0 is 0-based; one reaching 68 without 0 cannot be (0-67 has no 68): 1 is subtracted, also with rows left out
    (``na.omit``: R keeps the other rows' names) or reordered, which were refused. One with neither 0 nor 68 is
    refused: R's 1..67 (point 68 left out) was read as pandas' 0-based 1..67 (point 0 left out), every point one
    place off, silently; the two files differ only in R's quotes, which neither always writes. A missing point's NA
    row (``"68",NA,NA``) keeps the index unambiguous, as does a named ``ibug_index``."""
    pts = _dyadic_points()
    want = pts.copy()
    want[5] = np.nan
    cells = [("NA", "NA") if k == 5 else (repr(x), repr(y)) for k, (x, y) in enumerate(pts.tolist())]
    rows = [f'"{k + 1}",{x},{y}\n' for k, (x, y) in enumerate(cells)]
    last_na = [f'"{k + 1}",{x!r},{y!r}\n' for k, (x, y) in enumerate(pts[:67].tolist())] + ['"68",NA,NA\n']
    want_last = pts.copy()
    want_last[67] = np.nan
    pandas = [f"{k},{x},{y}\n" for k, (x, y) in enumerate(cells)]
    files = {"r.csv": ('"","x","y"\n' + "".join(rows), want),
             "r_semicolons.csv": ('"";"x";"y"\n' + "".join(rows).replace(",", ";"), want),
             "pandas_from_1.csv": (",x,y\n" + "".join(r.replace('"', "") for r in rows), want),
             "r_last_na.csv": ('"","x","y"\n' + "".join(last_na), want_last),  # (point 68 missing, its row kept)
             "r_omitted.csv": ('"","x","y"\n' + "".join(rows[:4] + rows[6:]), np.where(np.arange(68)[:, None] == 4,
                                                                                        np.nan, want)),  # (na.omit)
             "r_swapped.csv": ('"","x","y"\n' + "".join(rows[:66] + rows[67:] + rows[66:67]), want),
             "pandas.csv": (",x,y\n" + "".join(pandas), want),  # (0-based, as before)
             "pandas_without_67.csv": (",x,y\n" + "".join(pandas[:67]), np.where(np.arange(68)[:, None] == 67,
                                                                                   np.nan, want))}  # fmt: skip
    for name, (text, expected) in files.items():
        (tmp_path / name).write_text(text)
        np.testing.assert_array_equal(read_landmarks(tmp_path / name, 100, 100), expected, err_msg=name)
    ambiguous = {"r_without_68.csv": '"","x","y"\n' + "".join(rows[:67]),
                 "pandas_without_0.csv": ",x,y\n" + "".join(pandas[1:])}  # fmt: skip
    for name, text in ambiguous.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(InputError, match=r"index column \(unnamed: pandas' index or R's row names\) has neither 0 "
                                             r'nor 68, .* \(R: "68",NA,NA\), or name the column ibug_index') as info:
            read_landmarks(tmp_path / name, 100, 100)
        assert "\n" not in str(info.value)
    bad = {"both.csv": (",x,y\n" + "".join(pandas) + "68,1.0,2.0\n", r"line 70: point index 68 is not an iBUG index "
                        r"0-67: the index has 0 and 68, neither 0-based \(pandas: 0-67\) nor 1-based"),
           "r_69.csv": ('"","x","y"\n' + "".join(rows[:67]) + '"69",1.0,2.0\n', r"line 69: row name 69 is not 1-68 "
                        r"\(an index reaching 68 without 0 counts the points from 1, as R's row names do\)$")}
    for name, (text, message) in bad.items():
        (tmp_path / name).write_text(text)
        with pytest.raises(InputError, match=message):
            read_landmarks(tmp_path / name, 100, 100)


def test_count_reads_a_face_models_landmarks(tmp_path):
    """``count``: another model's K points (torchface track --model); a file of another count is refused naming the
    count expected (every layout: :func:`test_every_layout_holds_a_face_models_count`)."""
    points = _points()[:26]
    np.savetxt(tmp_path / "a.csv", points, delimiter=",")
    np.save(tmp_path / "a.npy", points)
    (tmp_path / "a.pts").write_text("version: 1\nn_points: 26\n{\n" + "".join(f"{x + 1} {y + 1}\n" for x, y in points)
                                    + "}\n")  # fmt: skip
    for name in ("a.csv", "a.npy", "a.pts"):
        np.testing.assert_array_equal(read_landmarks(tmp_path / name, 640, 480, count=26), points)
    with pytest.raises(InputError, match=r"expected 68 iBUG landmarks, got 26"):
        read_landmarks(tmp_path / "a.csv", 640, 480)
    np.savetxt(tmp_path / "b.csv", _points(), delimiter=",")
    with pytest.raises(InputError, match=r"expected 26 landmarks \(the face model's\), got 68"):
        read_landmarks(tmp_path / "b.csv", 640, 480, count=26)
    few = np.full((26, 2), np.nan)
    few[:3] = points[:3]
    with pytest.raises(InputError, match="3 of the 26 landmarks given"):
        check_landmarks(few, 640, 480, "x", missing=True, count=26)


@pytest.mark.parametrize(
    "text, message",
    [
        ("version: 1\nn_points: 26\n26 pairs follow\n", r"expected 'version: 1', 'n_points: 26' or '\{' of a \.pts"),
        ("version: 1\nn_points: 26\n", r"not a \.pts file \(version: 1, n_points: 26, \{, 26 lines 'x y', \}\)$"),
    ],
    ids=["a line not of the header", "no opening brace"],
)  # fmt: skip
def test_a_broken_pts_header_names_the_models_count(tmp_path, text, message):
    """A ``.pts`` file of a face model's K landmarks (``count``) whose header is broken: the message names K's layout,
    not the 68 iBUG points' (it said ``n_points: 68`` and ``68 lines`` for a 26-landmark model)."""
    (tmp_path / "a.pts").write_text(text)
    with pytest.raises(InputError, match=message):
        read_landmarks(tmp_path / "a.pts", 640, 480, count=26)
    with pytest.raises(InputError, match=message.replace("26", "68")):  # (the default: the iBUG points')
        read_landmarks(tmp_path / "a.pts", 640, 480)


def test_a_header_naming_the_columns_y_x_is_read_in_that_order(tmp_path):
    """Image coordinates are often written as (row, column): ``DataFrame(points[:, ::-1], columns=["y", "x"])``'s
    ``to_csv`` (a header ``y,x``; with its index ``,y,x``, as R's ``"","y","x"``) was read as ``x, y``, every point
    transposed (94 px off on a rendered clip's first frame, whose start then failed or fitted another face). The
    header says which column is which; ``x,y`` and no header read as before."""
    pts = _points()
    files = {
        "yx.csv": "y,x\n" + "".join(f"{y!r},{x!r}\n" for x, y in pts.tolist()),
        "YX_tabs.csv": "Y\tX\n" + "".join(f"{y!r}\t{x!r}\n" for x, y in pts.tolist()),
        "yx_column_b.csv": ",y,x\n" + "".join(f",{y!r},{x!r}\n" for x, y in pts.tolist()),
        "yx_indexed.csv": ",y,x\n" + "".join(f"{k},{y!r},{x!r}\n" for k, (x, y) in enumerate(pts.tolist())),
        "yx_r.csv": '"","y","x"\n' + "".join(f'"{k + 1}",{y!r},{x!r}\n' for k, (x, y) in enumerate(pts.tolist())),
        "xy.csv": "x,y\n" + "".join(f"{x!r},{y!r}\n" for x, y in pts.tolist()),
        "xy_indexed.csv": ",x,y\n" + "".join(f"{k},{x!r},{y!r}\n" for k, (x, y) in enumerate(pts.tolist())),
        "plain.csv": "".join(f"{x!r},{y!r}\n" for x, y in pts.tolist()),
    }
    for name, text in files.items():
        (tmp_path / name).write_text(text)
        np.testing.assert_array_equal(read_landmarks(tmp_path / name, 100, 100), pts, err_msg=name)


def test_a_header_naming_y_first_in_other_words_is_refused(tmp_path):
    """A two-column header naming the y (row) column first in words other than exactly ``y,x`` (``y_px,x_px``,
    ``lm_y,lm_x``, ``row,col``) was read as ``x, y`` without a word, every point swapped: it is refused, naming the
    header; the same words x first (``x_px,y_px``, ``col,row`` is not read as a y-first pair) read as before."""
    pts = _points()
    for header in ("y_px,x_px", "lm_y,lm_x", "row,col", "Y (px),X (px)", "rows,columns"):
        (tmp_path / "a.csv").write_text(header + "\n" + "".join(f"{y!r},{x!r}\n" for x, y in pts.tolist()))
        with pytest.raises(InputError, match=r"names the y \(row\) column first: name the columns exactly 'x,y'"):
            read_landmarks(tmp_path / "a.csv", 100, 100)
    for header in ("x_px,y_px", "lm_x,lm_y", "u,v", "px,py"):
        (tmp_path / "b.csv").write_text(header + "\n" + "".join(f"{x!r},{y!r}\n" for x, y in pts.tolist()))
        np.testing.assert_array_equal(read_landmarks(tmp_path / "b.csv", 100, 100), pts, err_msg=header)


def test_every_layout_holds_a_face_models_count(tmp_path):
    """``count`` (a face model's K landmarks, ``torchface track --model``) is the count of every layout: one row per
    point with an index ``0``..``K - 1`` (a point without a row missing), pandas' ``to_csv`` with its index, R's
    ``write.csv`` with its row names ``1``..``K``, one row of ``2 K`` values with an empty column before them, and a
    row of integer pairs ``x0,y0;x1,y1;...``. The one-row-per-point layouts were read as the 68 iBUG points: a file of
    the model's 26 points was refused as "expected 26 landmarks (the face model's), got 68"; an index past the
    model's landmarks is refused naming them."""
    K = 26
    points = np.round(_points()[:K])  # (integers: the pairs row below)
    want = points.copy()
    want[5] = np.nan
    given = [(k, x, y) for k, (x, y) in enumerate(points.tolist()) if k != 5]
    files = {
        "index.csv": ("landmark,x,y\n" + "".join(f"{k},{x},{y}\n" for k, x, y in given), want),
        "pandas.csv": (",x,y\n" + "".join(f"{k},{x},{y}\n" for k, (x, y) in enumerate(points.tolist())), points),
        "r.csv": ('"","x","y"\n' + "".join(f'"{k + 1}",{x},{y}\n' for k, (x, y) in enumerate(points.tolist())),
                  points),
        "row_column_b.csv": ("," + ",".join(repr(v) for v in points.reshape(-1).tolist()) + "\n", points),
        "pairs.csv": (";".join(f"{int(x)},{int(y)}" for x, y in points.tolist()) + "\n", points),
    }  # fmt: skip
    for name, (text, expected) in files.items():
        (tmp_path / name).write_text(text)
        np.testing.assert_array_equal(read_landmarks(tmp_path / name, 640, 480, count=K), expected, err_msg=name)
    (tmp_path / "ibug.csv").write_text("ibug_index,x,y\n" + "".join(f"{k},{x},{y}\n" for k, (x, y) in
                                                                  enumerate(_points().tolist())))  # fmt: skip
    with pytest.raises(InputError, match=r"line 28: point index 26 is not an index of the face model's 26 landmarks, "
                                         r"0-25$"):  # fmt: skip
        read_landmarks(tmp_path / "ibug.csv", 640, 480, count=K)
    np.testing.assert_array_equal(read_landmarks(tmp_path / "ibug.csv", 640, 480), _points())  # (68: as before)


# ----------------------------------------------------------------------------------------------- mirror_landmarks


def test_mirror_landmarks_tracks_a_flipped_frame_as_the_mirrored_head():
    """``mirror_landmarks``: there was no public way to give the landmarks of a flipped frame (a flip augmentation);
    its x coordinates flipped alone are a mirrored face, which the landmark fit fails (NO_POSE; the Python-API audit
    of session 63). A rendered head (yaw 12, pitch -6, roll 5 degrees) and its flipped frame, started from the
    ground-truth landmarks and from their mirror: the flipped one's yaw and roll are the head's negated, its pitch
    the same; the x coordinates flipped alone fail."""
    import torch

    from torchface.geometry.camera import Intrinsics
    from torchface.geometry.so3 import euler_to_matrix
    from torchface.io import mirror_landmarks
    from torchface.model.candide import load_candide3
    from torchface.synth.background import BackgroundSpec
    from torchface.synth.scenarios import default_light
    from torchface.synth.sequence import SequenceSpec, render_sequence
    from torchface.tracker import FaceTracker, StartFailure, TrackerConfig

    W, H, D = 200, 150, torch.float64
    spec = SequenceSpec(
        name="mirror", subject="candide3", intrinsics=Intrinsics.default(W, H),
        rotation=euler_to_matrix(torch.tensor([[12.0, -6.0, 5.0]], dtype=D)),
        translation=torch.tensor([[15.0, -8.0, 420.0]], dtype=D),
        anim=torch.zeros(1, load_candide3().num_animation, dtype=D), light=default_light(1),
        background=BackgroundSpec(seed=5),
    )  # fmt: skip
    frames, gt = render_sequence(spec)
    frames, lm = frames.float(), gt.landmarks_px[:1].float()
    flipped = frames.flip(-1)
    config = TrackerConfig(num_levels=2, max_points=400, iterations=(6, 4))
    plain = FaceTracker(config, refine_first=None).initialise(frames, lm)
    mirrored = FaceTracker(config, refine_first=None).initialise(flipped, mirror_landmarks(lm, W))
    assert bool(plain.success[0]) and bool(mirrored.success[0])
    yaw, pitch, roll = plain.ypr_deg[0].tolist()
    assert abs(yaw - 12.0) < 2.0 and abs(roll - 5.0) < 2.0  # (the landmark fit's: the scene is what it was)
    torch.testing.assert_close(mirrored.ypr_deg[0], torch.tensor([-yaw, pitch, -roll]), rtol=0, atol=0.5)
    x_only = torch.stack([(W - 1) - lm[..., 0], lm[..., 1]], -1)
    failed = FaceTracker(config, refine_first=None).initialise(flipped, x_only)
    assert failed.start_failure.tolist() == [int(StartFailure.NO_POSE)]


def test_mirror_landmarks_keeps_type_and_gradient_and_refuses_what_it_cannot_mirror():
    """Twice is the identity (to float rounding), a NaN row moves with its point, a tensor's gradient flows, a NumPy
    array stays one of its dtype; other shapes, integer points and a width that is no positive int are refused."""
    import torch

    from torchface.conventions import IBUG68_MIRROR
    from torchface.io import mirror_landmarks

    assert sorted(IBUG68_MIRROR) == list(range(68))
    assert all(IBUG68_MIRROR[IBUG68_MIRROR[k]] == k for k in range(68))
    assert (IBUG68_MIRROR[0], IBUG68_MIRROR[36], IBUG68_MIRROR[48], IBUG68_MIRROR[8]) == (16, 45, 54, 8)
    p = (torch.rand(3, 68, 2, dtype=torch.float64) * 150).requires_grad_()
    with torch.no_grad():
        p[1, 5] = float("nan")
    q = mirror_landmarks(p, 160)
    assert q.shape == (3, 68, 2) and q.dtype == torch.float64
    assert torch.isnan(q[1, 11]).all() and int(torch.isnan(q).sum()) == 2
    torch.testing.assert_close(q[0, 0], torch.stack([159 - p[0, 16, 0], p[0, 16, 1]]))
    torch.testing.assert_close(mirror_landmarks(q, 160), p, equal_nan=True)
    q[0].nansum().backward()
    assert torch.equal(p.grad[0, :, 0], -torch.ones(68, dtype=torch.float64))
    a = np.random.default_rng(0).random((68, 2)).astype(np.float32) * 100
    b = mirror_landmarks(a, 100)
    assert isinstance(b, np.ndarray) and b.dtype == np.float32 and b.shape == (68, 2)
    np.testing.assert_allclose(mirror_landmarks(b, 100), a, rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match=r"\(\.\.\., 68, 2\)"):
        mirror_landmarks(torch.zeros(5, 2), 100)
    with pytest.raises(TypeError, match="floating"):
        mirror_landmarks(np.zeros((68, 2), dtype=np.int64), 100)
    for bad in (0, 99.5, True):
        with pytest.raises(TypeError, match="positive int"):
            mirror_landmarks(a, bad)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="tensor or NumPy array"):
        mirror_landmarks(a.tolist(), 100)  # type: ignore[type-var]


def test_points_transposed_a_row_of_x_and_a_row_of_y_are_refused_saying_so(tmp_path):
    """``np.save(path, points.T)`` and ``np.savetxt(path, points.T)``, a row of x and a row of y, were refused with
    the shape or the row width alone ("got an array of shape (2, 68)", "got rows of [68] values"); an array of 3D
    points or of a set per frame is told what to take, in training_hooks' words (one rule, landmarks_shape_hint)."""
    points = _points()
    np.save(tmp_path / "t.npy", points.T)
    np.savetxt(tmp_path / "t.csv", points.T, delimiter=",")
    with pytest.raises(InputError, match=r"shape \(2, 68\) \(x, y rows: points\.T\)$"):
        read_landmarks(tmp_path / "t.npy", 640, 480)
    with pytest.raises(InputError, match=r"got rows of \[68\] values: a row of x and a row of y, the points "
                                         r"transposed\? Write one 'x, y' row per point"):
        read_landmarks(tmp_path / "t.csv", 640, 480)
    np.save(tmp_path / "xyz.npy", np.column_stack([points, np.zeros(68)]))
    with pytest.raises(InputError, match=r"shape \(68, 3\) \(x, y, z points, .*: points\[:, :2\]\)$"):
        read_landmarks(tmp_path / "xyz.npy", 640, 480)
    with pytest.raises(InputError, match=r"^lm: .*shape \(3, 68, 2\) \(a set per frame .*: points\[0\]\)$"):
        check_landmarks(np.stack([points] * 3), 640, 480, "lm")  # the Python API's array: the same rule
    np.savetxt(tmp_path / "three.csv", np.vstack([points.T, points.T[:1]]), delimiter=",")
    with pytest.raises(InputError, match=r"got rows of \[68\] values$"):  # three rows: no such guess
        read_landmarks(tmp_path / "three.csv", 640, 480)


def test_a_track_csv_given_as_landmarks_is_refused_naming_its_sidecar(tmp_path):
    """``--landmarks results/clip.csv`` (the run's per-frame CSV, not its sidecar) was told "got rows of [62]
    values", or, of a one-frame run, about one row's values: the message says it holds no landmarks and names the
    JSON sidecar whose ``initial_landmarks_px`` a run can start from."""
    from torchface.io import TrackCsvWriter, track_columns

    cols = track_columns(("AUV11 Jaw drop",), ("AU26",), ("gain", "bias"))
    for name, frames in (("clip.csv", 3), ("one.csv", 1)):
        with TrackCsvWriter(tmp_path / name, cols) as w:
            w.write(np.zeros((frames, len(cols))))
        with pytest.raises(InputError, match=rf"{name}: a torchface track CSV, which holds no landmarks: give its "
                                             rf"JSON sidecar \({name[:-4]}\.json\), whose initial_landmarks_px"):
            read_landmarks(tmp_path / name, 640, 480)
    w = TrackCsvWriter(tmp_path / "part.csv", cols)
    w.write(np.zeros((2, len(cols))))
    w.stop()
    with pytest.raises(InputError, match=r"part\.csv\.partial: a torchface track CSV.*\(part\.json\)"):
        read_landmarks(tmp_path / "part.csv.partial", 640, 480)



def test_a_track_csv_with_landmark_columns_added_is_read_as_openfaces(tmp_path):
    """A CSV of the track's columns with x_k, y_k columns added to its rows (a table joined with a detector's points)
    holds landmarks, which are read as OpenFace's are (the first row's x_k, y_k): the refusal of a track CSV given as
    landmarks refused it too, though it was read before."""
    from torchface.io import track_columns

    cols = list(track_columns(("AUV11 Jaw drop",), ("AU26",), ("gain", "bias")))
    points = np.random.default_rng(0).uniform(100, 400, (68, 2))
    names = cols + [f"x_{k}" for k in range(68)] + [f"y_{k}" for k in range(68)]
    rows = np.zeros((2, len(names)))
    rows[:, cols.index("success")] = 1
    rows[:, len(cols):] = np.concatenate([points[:, 0], points[:, 1]])
    rows[1, len(cols):] += 5.0  # (the second frame's points: not the start's)
    path = tmp_path / "joined.csv"
    path.write_text(",".join(names) + "\n" + "\n".join(",".join(repr(float(v)) for v in r) for r in rows) + "\n")
    assert np.array_equal(read_landmarks(path, 640, 480), points)


def test_a_frame_size_that_is_not_whole_pixels_is_a_type_error_naming_it(tmp_path):
    """``read_landmarks(path, "160", "120")`` (sizes from a command line's text) met a bare ``TypeError`` in the
    arithmetic ("unsupported operand type(s) for -: 'str' and 'float'"), and ``160.5`` was taken as the frame's
    edge; a numpy integer is a size as an int is."""
    points = np.stack([np.linspace(20, 140, 68), np.linspace(10, 110, 68)], 1)
    np.save(tmp_path / "lm.npy", points)
    for width, height in (("160", "120"), (160.5, 120), (160, 0), (True, 120)):
        with pytest.raises(TypeError, match=r"(width|height) must be a whole positive number of pixels"):
            read_landmarks(tmp_path / "lm.npy", width, height)
        with pytest.raises(TypeError, match=r"must be a whole positive number of pixels"):
            check_landmarks(points, width, height, "lm")
    assert np.array_equal(read_landmarks(tmp_path / "lm.npy", np.int64(160), 120), points)


def test_a_float16_landmarks_file_is_warned_of_and_read_as_it_is(tmp_path):
    """A float16 ``.npy`` of landmarks (``np.save`` of a half-precision detector's points) holds them rounded (0.5 px
    steps from 512 px, 1 px from 1024): ``torchface track`` read them as float64 without a word. It warns, naming the
    file and saying to save float32 or float64 points, and reads the values the file holds; float32 is not warned of."""
    points = _points().astype(np.float16)
    np.save(tmp_path / "half.npy", points)
    with pytest.warns(UserWarning, match=r"half\.npy: landmarks are float16, which rounds pixel coordinates to steps "
                                         r"of 0\.5 px from 512, 1 px from 1024 and 2 px from 2048: .*save the points "
                                         r"as float32 or float64$"):  # fmt: skip
        read = read_landmarks(tmp_path / "half.npy", 100, 100)
    assert read.dtype == np.float64 and np.array_equal(read, points.astype(np.float64))
    np.save(tmp_path / "single.npy", points.astype(np.float32))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_landmarks(tmp_path / "single.npy", 100, 100)
