"""``torchface track --keep-going`` (``JobConfig.keep_going``): a folder of videos with bad ones among them is tracked
but for the bad ones, each skipped with a line on stderr and listed with its reason in the summary (exit status 3);
the good ones' outputs are those of a run without the bad ones; ``--resume`` retries what was skipped."""

from __future__ import annotations

import io
import json
import os
import re
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from torchface.cli import EXIT_INCOMPLETE, ProgressDisplay, main
from torchface.io import InputError
from torchface.job import InputSkipped, JobConfig, VideosStopped, VideoSummary, output_paths, track_videos
from torchface.synth.io import read_video
from torchface.synth.scenarios import make_scenario
from torchface.synth.sequence import load_ground_truth, write_sequence

T, W, H = 3, 160, 120
#: Every output file of a video but its JSON (whose timings differ from run to run).
KINDS = ("csv", "overlay", "plot", "normalised")


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """``(frames, landmarks file)``: the first ``T`` frames of a rendered clip, ``(T, H, W, 3)`` uint8 RGB, and its
    first frame's landmarks."""
    root = tmp_path_factory.mktemp("clip")
    files = write_sequence(make_scenario("expressions", T, W, H), root)
    lm = root / "first_frame.csv"
    np.savetxt(lm, load_ground_truth(files.ground_truth).landmarks_px[0].numpy(), delimiter=",", header="x,y",
               comments="")  # fmt: skip
    frames = (read_video(files.video).permute(0, 2, 3, 1).numpy() * 255).round().astype(np.uint8)
    return frames, lm


class _Tty(io.StringIO):
    """A terminal's stream, as the progress display sees it (``isatty``), holding what is written to it."""

    def isatty(self) -> bool:
        return True


def _folder(frames: np.ndarray, path: Path, bad: int | None = None) -> Path:
    """``frames`` as a folder of PNG images, frame ``bad`` (if any) one that cannot be decoded."""
    path.mkdir(exist_ok=True)
    for i, f in enumerate(frames):
        cv2.imwrite(str(path / f"{i}.png"), f[..., ::-1])
    if bad is not None:
        (path / f"{bad}.png").write_bytes(b"not an image")
    return path


def _track(inputs, landmarks, out, *options):
    """``torchface track`` of ``inputs`` (each with its landmarks file), quiet, without the online start (3 frames)."""
    args = ["track", *map(str, inputs), "--out", str(out), "--quiet", "--no-online-refine", *options]
    return main(args + [a for lm in landmarks for a in ("--landmarks", str(lm))])


def _written(out: Path, name: str) -> list[str]:
    """The files in ``out`` of the video ``name``."""
    return sorted(p.name for p in out.iterdir() if p.name.split(".")[0].removesuffix("_overlay").removesuffix(
        "_normalised").removesuffix("_plot").removesuffix("_meshes") == name)  # fmt: skip


def _same_outputs(out: Path, ref: Path, name: str) -> None:
    """The outputs of ``name`` in ``out`` are those in ``ref``: byte for byte, the JSON but for its timings, its
    output paths and whether the run was a resumed one."""
    a, b = output_paths(out, name), output_paths(ref, name)
    for kind in KINDS:
        assert a[kind].read_bytes() == b[kind].read_bytes(), (name, kind)
    ja, jb = (json.loads(p["json"].read_text()) for p in (a, b))
    for j in (ja, jb):
        del j["timings_s"], j["outputs"], j["config"]["resume"]
    assert ja == jb, name


def test_bad_inputs_of_each_kind_are_skipped_and_the_others_tracked_as_without_them(clip, tmp_path, capsys):
    """One bad input refused the run (status 2, nothing tracked): with ``--keep-going`` each is skipped, named on
    stderr as it is, the others' outputs are byte for byte those of a run without the bad ones, the summary lists
    every input in order (the skipped ones with their reason) and the status is 3."""
    frames, lm = clip
    np.save(tmp_path / "good_a.npy", frames)
    _folder(frames, tmp_path / "good_b")
    np.save(tmp_path / "gray.npy", frames[..., 0])  # (refused without --convert)
    (tmp_path / "corrupt.mp4").write_bytes(b"not a video" * 50)
    np.save(tmp_path / "empty.npy", frames[:0])
    np.save(tmp_path / "lm_target.npy", frames)  # a good video whose landmarks file is wrong
    bad_lm = tmp_path / "lm67.csv"
    np.savetxt(bad_lm, np.loadtxt(lm, delimiter=",", skiprows=1)[:67], delimiter=",")
    kinds = {  # input: (its landmarks, what its refusal says)
        tmp_path / "gray.npy": (lm, "frames are grayscale"),
        tmp_path / "missing.mp4": (lm, "no such file"),
        tmp_path / "corrupt.mp4": (lm, "corrupt"),
        tmp_path / "empty.npy": (lm, "zero frames"),
        tmp_path / "lm_target.npy": (bad_lm, "expected 68 iBUG landmarks, got 67"),
    }
    good = [tmp_path / "good_a.npy", tmp_path / "good_b"]
    inputs = [good[0], *list(kinds)[:3], good[1], *list(kinds)[3:]]
    landmarks = [kinds[v][0] if v in kinds else lm for v in inputs]
    assert _track(good, [lm, lm], tmp_path / "ref") == 0
    capsys.readouterr()
    out = tmp_path / "out"
    assert _track(inputs, landmarks, out) == 2  # without --keep-going: refused, nothing written
    assert not out.exists() or not list(out.iterdir())
    assert "5 of the 7 inputs refused, nothing tracked" in capsys.readouterr().err

    rc = _track(inputs, landmarks, out, "--keep-going")
    captured = capsys.readouterr()
    assert rc == EXIT_INCOMPLETE == 3, captured.err
    skipped = [line for line in captured.err.splitlines() if line.startswith("torchface: warning: skipped ")]
    assert len(skipped) == len(kinds), captured.err  # one line each, in input order, with the reason
    for line, (v, (_, said)) in zip(skipped, kinds.items()):
        assert line.startswith(f"torchface: warning: skipped {v}: ") and said in line, line
    assert captured.err.splitlines()[-1] == (
        "torchface: 5 skipped (gray, missing, corrupt, empty, lm_target) of the 7 inputs, 2 complete (exit status 3; "
        "the summary says why)"
    )
    lines = captured.out.splitlines()
    assert lines[1] == "summary" and [line.split(":")[0].strip() for line in lines[2:9]] == [
        "good_a", "gray", "missing", "corrupt", "good_b", "empty", "lm_target"
    ]  # fmt: skip
    for v, (_, said) in kinds.items():
        (line,) = [x for x in lines if x.startswith(f"  {v.stem}: ")]
        assert line.startswith(f"  {v.stem}: skipped, not tracked: ") and said in line, line
        assert _written(out, v.stem) == []  # nothing of it written
    assert re.match(r"  good_a: 3 frames, [\d.]+ fps, mean confidence", lines[2]), lines[2]
    for v in good:
        _same_outputs(out, tmp_path / "ref", v.stem)
    assert lines[-1].startswith(f"outputs in {out}/")


def test_a_faceless_video_under_the_detector_is_skipped(clip, tmp_path, monkeypatch, capsys):
    """With ``--detector`` a video in none of whose frames it finds a face refused the whole run, after its frames
    were searched: with ``--keep-going`` it is skipped and the others tracked from the detector's face."""
    import torchface.detect

    frames, lm = clip
    points = np.loadtxt(lm, delimiter=",", skiprows=1)
    monkeypatch.setitem(torchface.detect.DETECTORS, "bright",
                        lambda: lambda image: points.copy() if image.max() > 0 else None)  # fmt: skip
    np.save(tmp_path / "face.npy", frames)
    np.save(tmp_path / "black.npy", np.zeros_like(frames))
    args = ["--detector", "bright", "--quiet", "--no-online-refine"]
    assert main(["track", str(tmp_path / "face.npy"), "--out", str(tmp_path / "ref"), *args]) == 0
    both = [str(tmp_path / "black.npy"), str(tmp_path / "face.npy")]
    assert main(["track", *both, "--out", str(tmp_path / "no"), *args]) == 2
    capsys.readouterr()
    assert main(["track", *both, "--out", str(tmp_path / "out"), *args, "--keep-going"]) == 3
    captured = capsys.readouterr()
    assert f"torchface: warning: skipped {tmp_path / 'black.npy'}: the bright detector found no face in any of its " \
           f"{T} frames" in captured.err, captured.err  # fmt: skip
    assert "  black: skipped, not tracked: " in captured.out and "  face: 3 frames" in captured.out
    _same_outputs(tmp_path / "out", tmp_path / "ref", "face")
    assert _written(tmp_path / "out", "black") == []
    # Its progress: searched, then reported skipped (a terminal's display drops its "searching" bar, which stayed
    # among the bars of the videos being tracked); the others keep their place among the inputs.
    reports, tty = [], _Tty()
    display = ProgressDisplay(tty)
    config = JobConfig(out_dir=tmp_path / "api", detector="bright", refine_first=None, keep_going=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputSkipped)
        track_videos(list(map(Path, both)), config, progress=lambda p: (reports.append(p), display(p)))
    assert [(p.index, p.done, p.searching, p.skipped) for p in reports if p.name == "black"] == [
        (0, k, True, False) for k in range(1, T + 1)
    ] + [(0, 0, False, True)]  # fmt: skip
    assert {(p.index, p.count) for p in reports if p.name == "face"} == {(1, 2)}
    assert "searching" in tty.getvalue() and display.lines == {}  # (no bar left: the tracked one finished)


def test_track_videos_returns_a_summary_per_input_that_says_why(clip, tmp_path):
    """The Python API: with ``keep_going`` every input gets a ``VideoSummary``, whose ``refused`` (nothing written)
    or ``stopped`` (its partial CSV kept) is the error the run without it raises, warned as an ``InputSkipped``, and
    a video stopped partway is returned with the others rather than raised (``VideosStopped``)."""
    frames, lm = clip
    np.save(tmp_path / "good.npy", frames)
    (tmp_path / "empty.npy").write_bytes(b"")
    broken = _folder(frames, tmp_path / "broken", bad=2)
    inputs = [tmp_path / "empty.npy", broken, tmp_path / "good.npy"]
    config = JobConfig(out_dir=tmp_path / "out", landmarks=(lm,) * 3, refine_first=None, keep_going=True)
    with pytest.raises(InputError) as refused:  # (the error of that input alone, without keep_going)
        track_videos(inputs[:1], JobConfig(out_dir=tmp_path / "no", landmarks=(lm,), refine_first=None))
    with pytest.raises(VideosStopped) as stopped:
        track_videos(inputs[1:], JobConfig(out_dir=tmp_path / "no", landmarks=(lm, lm), refine_first=None))
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        empty, partway, good = track_videos(inputs, config)
    assert [(w.category, str(w.message).split(":")[0]) for w in said if w.category is InputSkipped] == [
        (InputSkipped, f"skipped {tmp_path / 'empty.npy'}"), (InputSkipped, f"stopped {broken}")
    ]  # fmt: skip
    assert empty == VideoSummary("empty", inputs[0], (), 0, 0, 0.0, 0.0, refused=str(refused.value))
    assert not empty.complete and not empty.skipped and _written(tmp_path / "out", "empty") == []
    assert partway.stopped is not None and partway.stopped in str(stopped.value) and "2.png" in partway.stopped
    assert partway.refused is None and not partway.complete and partway.input == broken
    assert partway.outputs == (tmp_path / "out" / "broken.csv.partial",) and partway.frames == 2 and partway.lost == 0
    assert partway.mean_confidence == pytest.approx(stopped.value.summaries[0].mean_confidence, abs=0.05)
    assert _written(tmp_path / "out", "broken") == ["broken.csv.partial", "broken.record.partial"]
    assert good.complete and good.refused is None and good.stopped is None and good.frames == T
    assert (good.name, good.input, good.frames, good.lost) == (stopped.value.summaries[0].name, inputs[2], T, 0)
    with pytest.raises(TypeError, match="keep_going"):
        JobConfig(out_dir=tmp_path, keep_going="yes")


def test_without_keep_going_the_summary_lists_a_stopped_video_in_input_order(clip, tmp_path, capsys):
    """A video stopped partway without ``--keep-going`` (``VideosStopped``, status 2) is listed in the summary in its
    input's place, as with ``--keep-going`` (it was listed last, after the videos completed); ``VideosStopped.names``
    holds every input's name in input order."""
    frames, lm = clip
    np.save(tmp_path / "good.npy", frames)
    np.save(tmp_path / "last.npy", frames)
    broken = _folder(frames, tmp_path / "broken", bad=2)
    inputs = [tmp_path / "good.npy", broken, tmp_path / "last.npy"]
    assert _track(inputs, [lm] * 3, tmp_path / "out") == 2
    out = capsys.readouterr().out
    lines = out.splitlines()
    said = [line.split(":")[0].strip() for line in lines[lines.index("summary") + 1 :] if line.startswith("  ")
            and not line.startswith("    ")]  # fmt: skip
    assert said == ["good", "broken", "last"], out
    assert "  broken: stopped at a frame that could not be read, not completed" in out
    with pytest.raises(VideosStopped) as stopped:
        track_videos(inputs, JobConfig(out_dir=tmp_path / "py", landmarks=(lm,) * 3, refine_first=None))
    assert stopped.value.names == ("good", "broken", "last") and stopped.value.stopped == ("broken",)
    assert [x.name for x in stopped.value.summaries] == ["good", "last"]


def test_resume_retries_what_was_skipped_and_never_leaves_a_partial_output_looking_complete(clip, tmp_path, capsys):
    """``--resume --keep-going`` checks a skipped input again and tracks it once mended; a video stopped partway is
    resumed (and stops again) until its file is mended, then tracked afresh (its rows were made from the file as it
    was: the resume without ``--keep-going`` is refused). A skipped or stopped video is never left with outputs
    that look complete, and a fresh run removes what earlier runs wrote for a video it skips."""
    frames, lm = clip
    np.save(tmp_path / "good.npy", frames)
    np.save(tmp_path / "gray.npy", frames[..., 0])
    broken = _folder(frames, tmp_path / "broken", bad=2)
    inputs = [tmp_path / "good.npy", tmp_path / "gray.npy", broken]
    out = tmp_path / "out"

    def status(*options):
        rc = _track(inputs, [lm] * 3, out, "--keep-going", *options)
        return rc, capsys.readouterr()

    def looks_complete(name):
        return any((out / f"{name}{suffix}").exists() for suffix in (".csv", ".json", "_overlay.mp4", "_plot.png"))

    np.save(tmp_path / "gray.npy", frames)  # first tracked whole, then replaced by a file that cannot be tracked
    assert status()[0] == 3 and looks_complete("gray")  # (the broken one stopped)
    np.save(tmp_path / "gray.npy", frames[..., 0])
    rc, said = status()
    assert rc == 3 and "gray: skipped" in said.out and "broken: stopped partway" in said.out
    assert not looks_complete("gray") and _written(out, "gray") == []  # (the fresh run's: the earlier ones removed)
    assert not looks_complete("broken") and (out / "broken.csv.partial").is_file()
    rc, said = status("--resume")  # nothing mended: skipped and stopped again, the complete one left as it is
    assert rc == 3 and "good: already complete" in said.out and "gray: skipped" in said.out
    assert "broken: stopped partway, not completed (its 2 rows so far are kept" in said.out and not looks_complete("broken")
    np.save(tmp_path / "gray.npy", frames)  # mended
    _folder(frames, broken)
    assert _track(inputs, [lm] * 3, out, "--resume") == 2  # (without --keep-going: the changed input is refused)
    assert "cannot resume" in capsys.readouterr().err
    rc, said = status("--resume")
    assert rc == 0, said.err
    assert f"torchface: warning: {broken}: the input has changed since the rows in" in said.err, said.err
    assert "tracked afresh" in said.err and "good: already complete" in said.out
    # (no partial output left but the stopped run's rows, kept aside: they were made from the file as it was)
    aside = sorted(p.name for p in out.iterdir() if "partial" in p.name)
    assert aside == ["broken.csv.partial.earlier", "broken.record.partial.earlier"], aside
    assert _track(inputs[1:], [lm] * 2, tmp_path / "ref") == 0  # the two tracked as one batch, fresh
    for name in ("gray", "broken"):
        _same_outputs(out, tmp_path / "ref", name)


def test_resume_skips_complete_outputs_it_must_not_take_as_complete(clip, tmp_path, capsys):
    """``--resume`` refuses the run where an input's complete outputs were made from other first-frame landmarks
    than its file now holds: with ``--keep-going`` that input is skipped, its outputs as they were, the others
    skipped as complete."""
    frames, lm = clip
    np.save(tmp_path / "a.npy", frames)
    np.save(tmp_path / "b.npy", frames)
    moved = tmp_path / "moved.csv"
    moved.write_text(lm.read_text())
    out = tmp_path / "out"
    inputs = [tmp_path / "a.npy", tmp_path / "b.npy"]
    assert _track(inputs, [lm, moved], out) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    points = np.loadtxt(lm, delimiter=",", skiprows=1)
    np.savetxt(moved, points + 1.0, delimiter=",", header="x,y", comments="")
    capsys.readouterr()
    assert _track(inputs, [lm, moved], out, "--resume") == 2
    rc = _track(inputs, [lm, moved], out, "--resume", "--keep-going")
    captured = capsys.readouterr()
    assert rc == 3 and "  a: already complete (3 frames), skipped" in captured.out
    assert "  b: skipped, not tracked: " in captured.out and "other first-frame landmarks" in captured.out
    assert f"torchface: warning: skipped {tmp_path / 'b.npy'}: " in captured.err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_inputs_refused_as_their_batch_opens_are_skipped_and_their_batch_goes_on(clip, tmp_path):
    """Inputs refused after the checks, as their batch opens: one deleted meanwhile (its batch's first frame cannot
    be read) and, resumed, one whose partial rows are damaged. With ``keep_going`` each is skipped (its partial rows
    as they were), and the others of its batch are tracked."""
    frames, lm = clip
    for name in ("a", "b", "c"):
        np.save(tmp_path / f"{name}.npy", frames)
    inputs = [tmp_path / f"{name}.npy" for name in ("a", "b", "c")]

    def delete_c(p):  # (one video a batch: c's batch opens after a's and b's are complete)
        if p.name == "a" and p.done == T:
            inputs[2].unlink()

    config = JobConfig(out_dir=tmp_path / "out", landmarks=(lm,) * 3, refine_first=None, max_batch=1, keep_going=True)
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        a, b, c = track_videos(inputs, config, progress=delete_c)
    assert a.complete and b.complete and c.refused is not None and "no such file" in c.refused
    assert c.refused == f"{inputs[2]}: no such file or folder"
    assert [str(w.message) for w in said if w.category is InputSkipped] == [f"skipped {c.refused}"]
    assert _written(tmp_path / "out", "c") == []

    def interrupt(p):
        if p.done == 2 and not p.skipped:
            raise KeyboardInterrupt

    out = tmp_path / "resumed"
    with pytest.raises(KeyboardInterrupt):  # (a and b tracked together, interrupted after 2 rows)
        track_videos(inputs[:2], JobConfig(out_dir=out, landmarks=(lm, lm), refine_first=None), progress=interrupt)
    damaged = out / "b.csv.partial"
    damaged.write_text(damaged.read_text() + "not,a,row\n")
    kept = damaged.read_bytes()
    with pytest.raises(InputError, match="b.csv.partial"):
        track_videos(inputs[:2], JobConfig(out_dir=out, landmarks=(lm, lm), refine_first=None, resume=True))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputSkipped)
        a, b = track_videos(inputs[:2], JobConfig(out_dir=out, landmarks=(lm, lm), refine_first=None, resume=True,
                                                  keep_going=True))  # fmt: skip
    assert a.complete and a.frames == T and (out / "a.json").is_file()
    assert b.refused is not None and b.refused.startswith(f"{damaged}: line 4 is not a row") and "damaged" in b.refused
    assert damaged.read_bytes() == kept and not (out / "b.csv").exists()


def test_a_changed_input_tracked_afresh_keeps_its_earlier_rows_aside(clip, tmp_path, capsys):
    """``--resume --keep-going`` tracks afresh a partial run whose input file has changed since (its size or time:
    a ``touch`` is enough), but loses none of its rows: they (and their record) are kept aside under a name of their
    own, which the warning gives, and a second such resume keeps the first one's aside too, under another."""
    frames, lm = clip
    broken = _folder(frames, tmp_path / "broken", bad=2)
    out = tmp_path / "out"
    assert _track([broken], [lm], out, "--keep-going") == 3
    rows, record = (out / "broken.csv.partial").read_bytes(), (out / "broken.record.partial").read_bytes()
    capsys.readouterr()
    for n, aside in enumerate(("broken.csv.partial.earlier", "broken.csv.partial.earlier-2")):
        image = broken / "0.png"
        os.utime(image, ns=(image.stat().st_atime_ns, image.stat().st_mtime_ns + 10**9 * (n + 1)))  # touched only
        assert _track([broken], [lm], out, "--keep-going", "--resume") == 3
        said = capsys.readouterr()
        assert "tracked afresh" in said.err and f"earlier rows kept in {out / aside}" in said.err, said.err
        assert (out / aside).read_bytes() == rows  # (the same frames: the same rows, tracked afresh)
        assert (out / aside.replace(".csv.", ".record.")).read_bytes() != b""
        assert (out / "broken.csv.partial").read_bytes() == rows  # the fresh run's, stopped at the same frame
    assert (out / "broken.record.partial.earlier").read_bytes() == record
    assert not (out / "broken.csv").exists()


def test_interrupted_once_the_job_has_returned_names_what_it_skipped_and_what_stopped(clip, tmp_path, monkeypatch,
                                                                                      capsys):  # fmt: skip
    """Ctrl-C (or SIGTERM) while a ``--keep-going`` run's summary was printed said "every video is complete", where
    one input was skipped and a video had stopped partway (its rows in its partial CSV)."""
    import torchface.cli

    frames, lm = clip
    np.save(tmp_path / "good.npy", frames)
    np.save(tmp_path / "gray.npy", frames[..., 0])
    broken = _folder(frames, tmp_path / "broken", bad=2)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(torchface.cli, "_print_summary", interrupted)
    out = tmp_path / "out"
    assert _track([tmp_path / "good.npy", tmp_path / "gray.npy", broken], [lm] * 3, out, "--keep-going") == 130
    said = capsys.readouterr().err.splitlines()[-1]
    assert said == (f"torchface: interrupted; every video is complete but gray, skipped (nothing written), and "
                    f"broken, stopped partway: its rows are kept in {out / 'broken.csv.partial'}"), said
    assert (out / "good.json").is_file() and (out / "broken.csv.partial").is_file()


def test_a_video_with_no_tracked_frame_exits_with_3_and_is_named(clip, tmp_path, capsys):
    """A video whose start failed (a black first frame: TOO_FEW_POINTS) and that nothing started again was written
    complete, every row unusable (success 0), with a warning line, and the run exited with 0: a script over many
    videos took it for a tracked one. The run now exits with 3, with or without ``--keep-going`` (its outputs still
    written), the summary says it under the video's line and the last line names it, with ``--keep-going``'s skipped
    inputs where there are some; a ``--resume`` that finds it complete says it again (3). (The Python API's
    ``VideoSummary.no_tracked_frame``: test_cli_track's failed-start tests.)"""
    frames, lm = clip
    black_frames = frames.copy()
    black_frames[0] = 0
    np.save(tmp_path / "black.npy", black_frames)
    np.save(tmp_path / "good.npy", frames)
    np.save(tmp_path / "gray.npy", frames[..., 0])
    out = tmp_path / "out"
    rc = _track([tmp_path / "black.npy", tmp_path / "good.npy"], [lm, lm], out)
    captured = capsys.readouterr()
    assert rc == EXIT_INCOMPLETE, captured.err
    warning = ("    warning: no tracked frame, every row unusable (success 0): its start failed (TOO_FEW_POINTS) and "
               "nothing started it again; its outputs are written")  # fmt: skip
    lines = captured.out.splitlines()
    assert lines[2].startswith("  black: 3 frames, ") and lines[2].endswith(", 3 lost frames"), lines
    assert lines[3] == warning and lines[4].startswith("  good: 3 frames, ") and "warning" not in lines[5], lines
    assert captured.err.splitlines()[-1] == ("torchface: 1 with no tracked frame (black) of the 2 inputs, 1 complete "
                                             "(exit status 3; the summary says why)")  # fmt: skip
    assert "black: the start from the landmarks of frame 0 failed (TOO_FEW_POINTS)" in captured.err
    assert sorted(_written(out, "black")) == ["black.csv", "black.json", "black_normalised.mp4", "black_overlay.mp4",
                                              "black_plot.png"]  # fmt: skip

    rc = _track([tmp_path / "black.npy", tmp_path / "good.npy"], [lm, lm], out, "--resume")  # (found complete)
    captured = capsys.readouterr()
    assert rc == EXIT_INCOMPLETE and "  black: already complete (3 frames), skipped\n" + warning in captured.out
    assert captured.err.splitlines()[-1].startswith("torchface: 1 with no tracked frame (black) of the 2 inputs")
    rc = _track([tmp_path / "gray.npy", tmp_path / "black.npy", tmp_path / "good.npy"], [lm] * 3, out, "--resume",
                "--keep-going")  # fmt: skip
    captured = capsys.readouterr()
    assert rc == EXIT_INCOMPLETE and captured.err.splitlines()[-1] == (
        "torchface: 1 skipped (gray) and 1 with no tracked frame (black) of the 3 inputs, 1 complete (exit status 3; "
        "the summary says why)")  # fmt: skip
