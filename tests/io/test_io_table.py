"""The track CSV: OpenFace Euler angles, column layout, flushed partial file, truncated-row recovery."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
import torch

from torchface.geometry.so3 import axis_angle_to_matrix
from torchface.io import InputError, TrackCsvWriter, openface_euler, read_track_csv, track_columns
from torchface.io.table import column_name


def _rx(a):
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=torch.float64)


def _ry(a):
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=torch.float64)


def _rz(a):
    c, s = math.cos(a), math.sin(a)
    return torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=torch.float64)


def test_openface_euler_known_answers():
    rng = np.random.default_rng(3)
    angles = rng.uniform([-3, -1.5, -3], [3, 1.5, 3], size=(50, 3))
    R = torch.stack([_rx(a) @ _ry(b) @ _rz(c) for a, b, c in angles])
    torch.testing.assert_close(openface_euler(R), torch.from_numpy(angles), atol=1e-9, rtol=0)
    # Single-axis signs: Rx only, Ry only, Rz only.
    for k, f in enumerate((_rx, _ry, _rz)):
        out = openface_euler(f(0.3)[None])[0]
        torch.testing.assert_close(out, torch.eye(3, dtype=torch.float64)[k] * 0.3)


def test_openface_euler_gimbal_lock_reconstructs_the_rotation():
    R = (_rx(0.4) @ _ry(math.pi / 2) @ _rz(0.1))[None]
    a, b, c = openface_euler(R)[0].tolist()
    torch.testing.assert_close(_rx(a) @ _ry(b) @ _rz(c), R[0], atol=1e-7, rtol=0)


def test_columns_and_names():
    cols = track_columns(("AUV11 Jaw drop", "AUV2 Lip stretcher"), ("AU26", "AU2", "AU45"), ("gain", "light_x"))
    assert cols[:4] == ("frame", "timestamp", "success", "confidence")
    assert "pose_Rx" in cols and "r22" in cols
    assert [c for c in cols if c.endswith("_r")] == ["AU26_r", "AU02_r", "AU45_r"]  # OpenFace's two digits
    assert "anim_AUV11_jaw_drop" in cols and "illum_light_x" in cols
    assert column_name("anim", "AUV0 Upper lip raiser") == "anim_AUV0_upper_lip_raiser"
    with pytest.raises(ValueError, match="collide"):
        track_columns(("a b", "a-b"), (), ())


def test_writer_partial_then_final(tmp_path):
    cols = ("frame", "timestamp", "success", "confidence", "x")
    w = TrackCsvWriter(tmp_path / "v.csv", cols)
    w.write(np.array([[0, 0.0, 1, 0.5, 1.25], [1, 0.04, 1, 0.6, math.nan]]))
    assert (tmp_path / "v.csv.partial").is_file() and not (tmp_path / "v.csv").exists()
    c, rows = read_track_csv(tmp_path / "v.csv.partial")  # flushed: readable while open
    assert c == cols and rows.shape == (2, 5) and rows[0, 4] == 1.25 and math.isnan(rows[1, 4])
    w.close()
    assert (tmp_path / "v.csv").is_file() and not (tmp_path / "v.csv.partial").exists()


def test_resume_drops_a_cut_row_and_appends(tmp_path):
    cols = ("frame", "timestamp", "success", "confidence")
    part = tmp_path / "v.csv.partial"
    part.write_text("frame,timestamp,success,confidence\n0,0.000,1,0.9\n1,0.040,1,0.8\n2,0.08")
    w = TrackCsvWriter(tmp_path / "v.csv", cols, resume=True)
    assert w.rows_done == 2 and w.previous.shape == (2, 4)
    w.write(np.array([[2, 0.08, 1, 0.7]]))
    w.close()
    _, rows = read_track_csv(tmp_path / "v.csv")
    np.testing.assert_allclose(rows[:, 0], [0, 1, 2])
    (tmp_path / "w.csv.partial").write_text("a,b\n1,2\n")
    with pytest.raises(InputError, match="columns differ"):
        TrackCsvWriter(tmp_path / "w.csv", cols, resume=True)
    with pytest.raises(TypeError, match="one string"):  # its characters were taken as the columns
        TrackCsvWriter(tmp_path / "s.csv", "frame,a")


def test_rotation_columns_match_axis_angle():
    aa = torch.tensor([[0.1, -0.2, 0.3]], dtype=torch.float64)
    R = axis_angle_to_matrix(aa)
    a, b, c = openface_euler(R)[0].tolist()
    torch.testing.assert_close(_rx(a) @ _ry(b) @ _rz(c), R[0])


def test_write_json_is_strict_json_with_undefined_figures_as_null(tmp_path):
    """The one JSON writer of the job and the scripts (evaluate, benchmark, track_grid): NaN or infinite figures
    (an AUROC without negatives, a jitter of a 2-frame clip) become null, in numpy and torch values too; the file
    is written whole or not at all."""
    import json

    import numpy as np
    import torch

    from torchface.io.sidecar import write_json

    payload = {
        "a": float("nan"), "b": np.float32("inf"), "c": torch.tensor([1.0, float("nan")]), "d": {"e": (2.5, -1e999)},
    }  # fmt: skip
    path = write_json(tmp_path / "f.json", payload)
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"a": None, "b": None, "c": [1.0, None], "d": {"e": [2.5, None]}}
    assert not (tmp_path / "f.json.partial").exists()
    # a torch device or dtype (JobConfig(device=torch.device("cpu"))) is its name; it raised TypeError
    write_json(tmp_path / "g.json", {"device": torch.device("cpu"), "dtype": torch.float64})
    assert json.loads((tmp_path / "g.json").read_text()) == {"device": "cpu", "dtype": "torch.float64"}


def test_columns_of_a_model_with_any_names_make_a_csv_that_reads_back(tmp_path):
    """A FACS name with a comma or a quote went into the header as it was (the file read back with one column more
    than its rows, so with no rows); a name in another script was refused ('cannot make a column name') and one
    with an umlaut mangled ('anim_l_cheln'); colliding names were reported as the whole header."""
    cols = track_columns(("smile, left", "微笑", "lächeln", "jawOpen"), ("AU12,AU6", 'AU"6', "AU12L", "AU 1"),
                         ("gain",))  # fmt: skip
    assert [c for c in cols if c.endswith("_r")] == ["AU12_AU6_r", "AU_6_r", "AU12L_r", "AU_1_r"]
    assert [c for c in cols if c.startswith("anim_")] == ["anim_smile_left", "anim_微笑", "anim_lächeln", "anim_jawopen"]
    with TrackCsvWriter(tmp_path / "v.csv", cols) as w:
        w.write(np.arange(len(cols), dtype=np.float64)[None])
    read_cols, rows = read_track_csv(tmp_path / "v.csv")
    assert read_cols == cols and rows.shape == (1, len(cols))
    with pytest.raises(ValueError, match=r"'anim_smile_l' from \['smile L', 'smile_L'\]"):
        track_columns(("smile L", "smile_L", "frown"), (), ())
    with pytest.raises(ValueError, match=r"'AU02_r' from \['AU2', 'AU02'\]"):
        track_columns((), ("AU2", "AU02"), ())
    with pytest.raises(ValueError, match="no letter or digit"):
        track_columns(("--",), (), ())


def test_to_jsonable_writes_any_path_as_its_text(tmp_path):
    """``to_jsonable`` promises paths as text but took only ``Path``: a ``PurePosixPath`` or an ``os.DirEntry`` went
    through unchanged and ``write_json`` raised "Object of type PurePosixPath is not JSON serializable"."""
    import json
    import os
    from pathlib import PurePosixPath

    from torchface.io.sidecar import to_jsonable, write_json

    (tmp_path / "clip.mp4").touch()
    (entry,) = os.scandir(tmp_path)
    assert to_jsonable({"a": PurePosixPath("/data/a.mp4"), "b": [entry]}) == {"a": "/data/a.mp4", "b": [entry.path]}
    write_json(tmp_path / "h.json", {"input": PurePosixPath("/data/a.mp4"), "path": tmp_path})
    assert json.loads((tmp_path / "h.json").read_text()) == {"input": "/data/a.mp4", "path": str(tmp_path)}


def test_openface_differences_the_readme_lists_match_candide3s_au_columns():
    """docs/cli.md ("Differences from OpenFace's per-frame CSV"): the AUs without a column and the AU columns that
    repeat one animation unit's value are CANDIDE-3's."""
    from torchface.io.table import facs_column_stem
    from torchface.model.candide import read_auv_facs_table

    table = read_auv_facs_table()
    columns = {f"{facs_column_stem(au)}_r" for row in table for au in row.facs}
    for absent in ("AU01_r", "AU06_r", "AU12_r", "AU14_r", "AU17_r", "AU25_r"):
        assert absent not in columns
    shared = sorted(tuple(f"{facs_column_stem(au)}_r" for au in row.facs) for row in table if len(row.facs) > 1)
    assert shared == [("AU13_r", "AU15_r"), ("AU23_r", "AU24_r"), ("AU26_r", "AU27_r"),
                      ("AU42_r", "AU43_r", "AU44_r", "AU45_r")]
    header = ",".join(track_columns(("a",), ("AU2",), ("g",)))
    assert " " not in header and header.startswith("frame,timestamp,success,confidence,")


class _FullDisk:
    """A file on a full disk: writes are buffered, every flush fails (as ENOSPC does), close flushes first."""

    def __init__(self, file):
        self.file, self.closed = file, False

    def write(self, text):
        return len(text)

    def flush(self):
        raise OSError(28, "No space left on device")

    def fileno(self):
        return self.file.fileno()

    def close(self):
        self.file.close()
        self.closed = True
        self.flush()


def test_csv_writer_on_a_full_disk_names_its_file_and_stops_cleanly(tmp_path):
    """The row write said only "No space left on device" (no file named), and stop(), the job's clean-up, raised
    the same error again before the job deleted its partial videos, leaving them and the file open."""
    from torchface.io import OutputError

    cols = ("frame", "confidence")
    writer = TrackCsvWriter(tmp_path / "clip.csv", cols)
    writer.write(np.array([[0.0, 1.0]]))
    disk = _FullDisk(writer._file)
    writer._file = disk
    with pytest.raises(OutputError, match=r"clip\.csv\.partial: cannot write \(No space left on device\)"):
        writer.write(np.array([[1.0, 1.0]]))
    writer.stop()
    assert disk.closed and writer._file is None
    assert read_track_csv(tmp_path / "clip.csv.partial")[1].shape == (1, 2)  # the rows that fitted stay


def test_a_full_disk_while_resuming_leaves_the_partial_csv_and_no_temporary_file(tmp_path, monkeypatch):
    """Resuming a partial CSV of other line ends rewrites its complete rows through ``<name>.csv.partial.tmp``
    (one as the writer writes it is appended to in place); on a full disk that file was left behind, cut off."""
    from pathlib import Path

    from torchface.io import OutputError

    cols = ("frame", "confidence")
    part = tmp_path / "clip.csv.partial"
    text = b"frame,confidence\r\n0,0.9\r\n1,0.8\r\n"
    part.write_bytes(text)
    real = Path.write_text

    def full_disk(self, data, *args, **kwargs):
        real(self, data[:5], *args, **kwargs)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Path, "write_text", full_disk)
    with pytest.raises(OutputError, match=r"clip\.csv\.partial: cannot write \(No space left on device\)"):
        TrackCsvWriter(tmp_path / "clip.csv", cols, resume=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.csv.partial"] and part.read_bytes() == text


def test_a_damaged_complete_line_is_refused_not_read_as_the_end(tmp_path):
    """A line ending in a newline is complete: one that is not a row is damage, not a cut. It ended the rows read
    silently (the rows after it dropped, and a resumed run tracked them again from the rows before it)."""
    cols = ("frame", "timestamp", "success", "confidence")
    part = tmp_path / "v.csv.partial"
    for bad, why in (("1,0.040,x,0.8", "could not convert"), ("1,0.040,1", "3 cells, the header has 4"),
                     ("", "1 cells")):  # fmt: skip
        part.write_text(f"frame,timestamp,success,confidence\n0,0.000,1,0.9\n{bad}\n2,0.080,1,0.7\n3,0.1")
        with pytest.raises(InputError, match=f"v.csv.partial: line 3 is not a row of the track CSV .*{why}"):
            read_track_csv(part)
        with pytest.raises(InputError, match="line 3 is not a row"):
            TrackCsvWriter(tmp_path / "v.csv", cols, resume=True)
    part.write_text("frame,timestamp,success,confidence\n0,0.000,1,0.9\n\n\n")  # blank lines at the end: no rows
    assert read_track_csv(part)[1].shape == (1, 4)


def test_a_track_csv_that_cannot_be_read_says_why_not_the_exception_class(tmp_path):
    """A missing file, a folder or a file that is not text said the exception's class alone ("cannot read the
    track CSV (FileNotFoundError)")."""
    (tmp_path / "results.csv").mkdir()
    (tmp_path / "clip.csv").write_bytes(b"\xff\xfeframe,timestamp\n0,0\n")
    # (bytes that are not UTF-8 under a track CSV's header: a damaged row, as other damage is; it was "not a track CSV")
    (tmp_path / "damaged.csv").write_bytes(b"frame,timestamp\n0,0\n\xff\xfe1,0\n2,0\n")
    for name, said in (("nope.csv", r"cannot read the track CSV \(No such file or directory\)"),
                       ("results.csv", r"cannot read the track CSV \(Is a directory\)"),
                       ("clip.csv", r"not a track CSV \(not UTF-8 text\)"),
                       ("damaged.csv", r"line 3 is not a row of the track CSV \(not UTF-8 text\): the file is "
                                       "damaged")):  # fmt: skip
        with pytest.raises(InputError, match=rf"^{re.escape(str(tmp_path / name))}: {said}$"):
            read_track_csv(tmp_path / name)


def test_an_openface_csv_is_read_by_column_name(tmp_path):
    """OpenFace writes a space after each comma (header and rows); the names kept it (' face_id', ' AU12_r'), so
    ``columns.index('AU12_r')`` failed. Windows line ends and a byte-order mark (a spreadsheet's save) likewise."""
    text = ("frame, face_id, timestamp, confidence, success, AU12_r\n"
            "1, 0, 0.000, 0.98, 1, 0.50\n2, 0, 0.033, 0.97, 1, 1.25\n")  # fmt: skip
    (tmp_path / "of.csv").write_text(text, encoding="utf-8")
    (tmp_path / "win.csv").write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    for name in ("of.csv", "win.csv"):
        cols, rows = read_track_csv(tmp_path / name)
        assert cols == ("frame", "face_id", "timestamp", "confidence", "success", "AU12_r"), cols
        assert rows[:, cols.index("AU12_r")].tolist() == [0.5, 1.25]


def test_one_name_given_alone_is_refused_not_spelt_out():
    """``track_columns("jawOpen", ...)`` made one column per letter ('anim_j', 'anim_a', ...); like the writer's and
    plot_track's ``columns`` (one shared check), a string alone is refused."""
    for args in (("jawOpen", (), ()), ((), "AU12", ()), ((), (), "gain")):
        with pytest.raises(TypeError, match=r"must be a sequence of names, e.g. \('\w+',\), not one string"):
            track_columns(*args)
    assert "anim_jawopen" in track_columns(["jawOpen"], [], [])  # lists are sequences too


def test_a_partial_csv_without_a_whole_header_is_resumed_from_its_start(tmp_path, monkeypatch):
    """A run killed, or its disk full, as it started the partial CSV left it empty or cut off in its header; a
    resume then refused it ("not a track CSV (no complete header line)"), so that --resume stopped at that video
    and only a fresh run, which removes every video's outputs, went on. It holds no rows: it is started afresh.
    A fresh file whose header does not fit is not left behind."""
    import builtins

    from torchface.io import OutputError

    cols = ("frame", "timestamp", "success", "confidence")
    part = tmp_path / "v.csv.partial"
    for text in ("", "frame,times", "frame,timestamp,success,confidence"):
        part.write_text(text)
        with TrackCsvWriter(tmp_path / "v.csv", cols, resume=True) as w:
            assert w.rows_done == 0
            w.write(np.array([[0, 0.0, 1, 0.9]]))
        c, rows = read_track_csv(tmp_path / "v.csv")
        assert c == cols and rows.tolist() == [[0.0, 0.0, 1.0, 0.9]]
        (tmp_path / "v.csv").unlink()
    part.write_text("frame,timestamp,suXcess")  # not this header's beginning: refused as before
    with pytest.raises(InputError, match="no complete header line"):
        TrackCsvWriter(tmp_path / "v.csv", cols, resume=True)
    part.unlink()
    real_open = builtins.open

    def full_disk(*args, **kwargs):
        return _FullDisk(real_open(*args, **kwargs))

    monkeypatch.setattr(builtins, "open", full_disk)
    with pytest.raises(OutputError, match=r"v\.csv\.partial: cannot write \(No space left on device\)"):
        TrackCsvWriter(tmp_path / "v.csv", cols)
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []


def test_reading_a_long_track_csv_holds_little_more_than_its_rows(tmp_path):
    """The job reads a video's CSV back when it finalises it (its plot, its sidecar's figures) and when it resumes
    it. The file was read whole and its rows held as lists of Python floats before they became the array: about 9
    times the array's size at its peak (430 MB for the 62 columns of an hour's video at 30 frames/s)."""
    import tracemalloc

    cols = tuple(f"c{k}" for k in range(8))
    rows = np.random.default_rng(0).normal(size=(20000, len(cols)))
    with TrackCsvWriter(tmp_path / "long.csv", cols) as w:
        w.write(rows)
    tracemalloc.start()
    try:
        got_cols, got = read_track_csv(tmp_path / "long.csv")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert got_cols == cols and got.shape == rows.shape
    np.testing.assert_allclose(got, rows, rtol=1e-8)
    assert peak < 2 * got.nbytes, (peak, got.nbytes)


def test_a_full_disk_or_a_read_only_folder_when_closing_names_the_file(tmp_path, monkeypatch):
    """close() syncs the rows and renames the file: a failed sync said only "No space left on device" (no file
    named; among many videos, which one?), a failed rename was a bare PermissionError. Both are an OutputError
    naming the file now, the partial CSV kept (open until stop() where the sync failed)."""
    import os

    from torchface.io import OutputError

    cols = ("frame", "confidence")
    writer = TrackCsvWriter(tmp_path / "clip.csv", cols)
    writer.write(np.array([[0.0, 1.0]]))

    def no_space(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", no_space)
    with pytest.raises(OutputError, match=r"clip\.csv\.partial: cannot write \(No space left on device\)"):
        writer.close()
    monkeypatch.undo()
    writer.stop()
    assert writer._file is None and read_track_csv(tmp_path / "clip.csv.partial")[1].shape == (1, 2)
    writer = TrackCsvWriter(tmp_path / "other.csv", cols)

    def read_only(src, dst):
        raise PermissionError(13, "Permission denied", str(src), None, str(dst))

    monkeypatch.setattr(os, "replace", read_only)
    with pytest.raises(OutputError, match=r"other\.csv\.partial: cannot rename it to other\.csv \(Permission denied"):
        writer.close()
    assert (tmp_path / "other.csv.partial").is_file() and not (tmp_path / "other.csv").exists()


def _rows(n):
    rng = np.random.default_rng(5)
    return np.column_stack([np.arange(n), np.arange(n) / 25, np.ones(n), rng.uniform(size=n), rng.normal(size=n)])


def test_resume_appends_after_the_last_complete_row_without_rewriting_the_rows(tmp_path, monkeypatch):
    """A resumed partial CSV was written again whole, every row formatted anew (18.8 s per hour of video at 30
    frames/s): it is now cut after its last complete row and appended to, in place, and the file comes out as an
    uninterrupted writer's, byte for byte (a cut row, blank lines at the end, NaN cells)."""
    import torchface.io.table as table

    cols = ("frame", "timestamp", "success", "confidence", "x")
    rows = _rows(40)
    rows[7, 4] = math.nan
    with TrackCsvWriter(tmp_path / "ref.csv", cols) as w:
        w.write(rows)
    for keep, tail in ((25, "25,1.0"), (25, ""), (3, "\n\n"), (0, "")):
        with TrackCsvWriter(tmp_path / "v.csv", cols) as w:
            w.write(rows[:keep])
            w.stop()
        part = tmp_path / "v.csv.partial"
        with open(part, "a", encoding="utf-8") as f:
            f.write(tail)
        inode = part.stat().st_ino
        formatted = []
        real = table._format_row
        monkeypatch.setattr(table, "_format_row", lambda c, r: formatted.append(1) or real(c, r))
        w = TrackCsvWriter(tmp_path / "v.csv", cols, resume=True)
        assert w.rows_done == keep and not formatted and part.stat().st_ino == inode  # nothing written again
        np.testing.assert_array_equal(w.previous, read_track_csv(tmp_path / "ref.csv")[1][:keep])
        w.write(rows[keep:])
        w.close()
        monkeypatch.setattr(table, "_format_row", real)
        assert (tmp_path / "v.csv").read_bytes() == (tmp_path / "ref.csv").read_bytes(), (keep, tail)
        (tmp_path / "v.csv").unlink()


def test_a_partial_csv_with_other_line_ends_is_written_again_when_resumed(tmp_path):
    """A partial CSV this writer would not have written (Windows line ends, a byte-order mark: saved by another
    program) is written again with its rows, so that the new rows are not appended to lines of another form."""
    cols = ("frame", "timestamp", "success", "confidence", "x")
    rows = _rows(10)
    with TrackCsvWriter(tmp_path / "ref.csv", cols) as w:
        w.write(rows)
    text = (tmp_path / "ref.csv").read_text().splitlines(keepends=True)
    for head, eol in ((b"", "\r\n"), (b"\xef\xbb\xbf", "\n")):
        (tmp_path / "v.csv.partial").write_bytes(head + "".join(text[:5]).replace("\n", eol).encode())
        with TrackCsvWriter(tmp_path / "v.csv", cols, resume=True) as w:
            assert w.rows_done == 4
            w.write(rows[4:])
        assert (tmp_path / "v.csv").read_bytes() == (tmp_path / "ref.csv").read_bytes()


def test_reading_the_csv_of_a_run_not_complete_says_its_partial_file_holds_the_rows(tmp_path):
    """A script reading ``clip.csv`` while its run is under way, or after it was interrupted, was told "No such file
    or directory" alone, though ``clip.csv.partial`` beside it held the rows: the message says so."""
    cols = ("frame", "timestamp", "success", "confidence")
    with TrackCsvWriter(tmp_path / "done.csv", cols) as w:
        w.write(np.array([[0, 0.0, 1, 0.9]]))
    w = TrackCsvWriter(tmp_path / "clip.csv", cols)
    w.write(np.array([[0, 0.0, 1, 0.9], [1, 0.04, 1, 0.8]]))
    w.stop()
    with pytest.raises(InputError, match=r"clip\.csv: cannot read the track CSV \(No such file or directory; "
                                         r"clip\.csv\.partial holds the rows of a run not complete.*--resume"):
        read_track_csv(tmp_path / "clip.csv")
    assert read_track_csv(tmp_path / "clip.csv.partial")[1].shape == (2, 4)
    with pytest.raises(InputError, match=r"nope\.csv: cannot read the track CSV \(No such file or directory\)$"):
        read_track_csv(tmp_path / "nope.csv")  # no partial file: as before
    assert read_track_csv(tmp_path / "done.csv")[1].shape == (1, 4)


def test_a_sidecar_read_as_a_track_csv_is_told_json_not_damage(tmp_path):
    """A script given the run's ``clip.json`` rather than its ``clip.csv`` was told "line 2 is not a row of the track
    CSV (2 cells, the header has 1): the file is damaged"."""
    from torchface.io import write_json

    write_json(tmp_path / "clip.json", {"frames": 3, "outputs": {"csv": "clip.csv"}})
    (tmp_path / "list.json").write_text("[1, 2]\n")
    for name in ("clip.json", "list.json"):
        with pytest.raises(InputError, match=rf"{name}: not a track CSV but JSON text \(a run's sidecar\? its rows "
                                             rf"are {name[:-5]}\.csv\)$"):
            read_track_csv(tmp_path / name)
