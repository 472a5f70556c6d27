"""Landmark files: CSV and NPY layouts, and every way they can be wrong."""

from __future__ import annotations

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


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda p: p[:67], "expected 68 iBUG landmarks, got 67"),
        (lambda p: np.vstack([p, p[:1]]), "got 69"),
        (lambda p: np.where(np.arange(68)[:, None] == 5, np.nan, p), r"landmark\(s\) \[5\] are NaN"),
        (lambda p: np.where(np.arange(68)[:, None] == 3, 150.0, p), "outside the 100x100 frame, e.g. point 3"),
        (lambda p: np.where(np.arange(68)[:, None] == 0, [-3.0, 50.0], p), "point 0 at \\(-3.0, 50.0\\)"),
    ],
)
def test_bad_landmarks(tmp_path, edit, message):
    np.save(tmp_path / "lm.npy", edit(_points()))
    with pytest.raises(InputError, match=message) as info:
        read_landmarks(tmp_path / "lm.npy", 100, 100)
    assert "\n" not in str(info.value)


def test_check_landmarks_min_inside_lets_a_detectors_points_cross_the_edge():
    """A detector's landmarks (``min_inside=0.5``) may lie partly outside the frame (a chin at the edge); a file's
    (the default) may not, and more than half outside is refused either way."""
    points = _points()
    points[:3] = [[50.0, 100.5], [60.0, 101.0], [-1.0, 50.0]]
    with pytest.raises(InputError, match="3 landmark.s. outside the 100x100 frame"):
        check_landmarks(points, 100, 100, "file")
    assert np.array_equal(check_landmarks(points, 100, 100, "detector", min_inside=0.5), points)
    with pytest.raises(InputError, match="68 landmark.s. outside"):
        check_landmarks(points + 500.0, 100, 100, "detector", min_inside=0.5)


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
