"""What :func:`torchface.job.track_videos` tells a Python caller names the :class:`~torchface.job.JobConfig` fields
(``JobConfig(resume=True)``, ``with resume=False``, ``set JobConfig(convert=True)``, ``out_dir``), where the same
message of ``torchface track`` names its options (``--resume``, ``--convert``, ``--out``) as it did: a Python caller
was told to "run the same command with --resume" and to "pass --convert"."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

import torchface.job
from torchface.cli import main
from torchface.io import InputError
from torchface.job import InputSkipped, JobConfig, track_videos
from torchface.synth.io import read_video
from torchface.synth.scenarios import make_scenario
from torchface.synth.sequence import load_ground_truth, write_sequence

T, W, H = 3, 160, 120


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """``(clip.npy, landmarks file)``: the first ``T`` frames of a rendered clip as an 8-bit RGB array, and its first
    frame's landmarks."""
    root = tmp_path_factory.mktemp("clip")
    files = write_sequence(make_scenario("expressions", T, W, H), root)
    lm = root / "first_frame.csv"
    np.savetxt(lm, load_ground_truth(files.ground_truth).landmarks_px[0].numpy(), delimiter=",", header="x,y",
               comments="")  # fmt: skip
    array = root / "clip.npy"
    np.save(array, (read_video(files.video).permute(0, 2, 3, 1).numpy() * 255).round().astype(np.uint8))
    return array, lm


def _cli(*args: object) -> int:
    return main(["track", *map(str, args), "--quiet"])


def _options(text: str) -> list[str]:
    """The command-line options that ``text`` names (``--resume``, ``--out``, ...)."""
    return [w for w in text.replace("(", " ").split() if w.startswith("--")]


def test_an_interrupted_run_says_to_resume_with_the_field_or_the_option(clip, tmp_path, monkeypatch, capsys):
    array, lm = clip
    real_step = torchface.job.managed_step
    steps = []

    def interrupted_step(*args, **kwargs):
        steps.append(1)
        if len(steps) == 2:  # (after the first row past the first frame)
            raise KeyboardInterrupt
        return real_step(*args, **kwargs)

    monkeypatch.setattr(torchface.job, "managed_step", interrupted_step)
    with pytest.raises(KeyboardInterrupt) as caught:
        track_videos([array], JobConfig(out_dir=tmp_path / "py", landmarks=(lm,), refine_first=None))
    kept = caught.value.kept  # type: ignore[attr-defined]
    assert kept.startswith(f"rows kept in {tmp_path / 'py' / 'clip.csv.partial'}"), kept
    assert kept.endswith(": call track_videos again with JobConfig(resume=True) to continue") and not _options(kept)

    steps.clear()
    assert _cli(array, "--out", tmp_path / "cli", "--landmarks", lm, "--no-online-refine") == 130
    err = capsys.readouterr().err
    assert err.rstrip().endswith(": run the same command with --resume to continue"), err
    assert "JobConfig" not in err


def test_a_refused_resume_names_the_setting_and_resume_false(clip, tmp_path, capsys):
    """A resume with another focal over complete outputs: "(focal default then, 150.0 now): run with their settings,
    or with resume=False" from Python, "(--focal default then, 150.0 now): ..., or without --resume" on the command
    line."""
    array, lm = clip
    out = tmp_path / "out"
    track_videos([array], JobConfig(out_dir=out, landmarks=(lm,), refine_first=None))
    with pytest.raises(InputError) as caught:
        track_videos([array], JobConfig(out_dir=out, landmarks=(lm,), refine_first=None, focal=150.0, resume=True))
    said = str(caught.value)
    assert "cannot resume" in said and "(focal default then, 150.0 now)" in said, said
    assert said.endswith("run with their settings, or with resume=False") and not _options(said), said

    assert _cli(array, "--out", out, "--landmarks", lm, "--no-online-refine", "--focal", "150", "--resume") == 2
    err = capsys.readouterr().err
    assert "(--focal default then, 150.0 now)" in err and err.rstrip().endswith("or without --resume"), err


def test_frames_to_convert_say_convert_true_also_when_skipped(clip, tmp_path, capsys):
    """A grayscale array: refused with "set JobConfig(convert=True)" (raised, and with ``keep_going`` in its warning
    and summary), "pass --convert" on the command line."""
    array, lm = clip
    gray = tmp_path / "gray.npy"
    np.save(gray, np.load(array)[..., 0])
    with pytest.raises(InputError, match=r"; or set JobConfig\(convert=True\) to let torchface convert") as caught:
        track_videos([gray], JobConfig(out_dir=tmp_path / "a", landmarks=(lm,)))
    assert not _options(str(caught.value))
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        (summary,) = track_videos([gray], JobConfig(out_dir=tmp_path / "b", landmarks=(lm,), keep_going=True))
    skipped = [str(w.message) for w in said if issubclass(w.category, InputSkipped)]
    assert len(skipped) == 1 and "set JobConfig(convert=True)" in skipped[0] and not _options(skipped[0]), skipped
    assert summary.refused is not None and "set JobConfig(convert=True)" in summary.refused, summary

    assert _cli(gray, "--out", tmp_path / "c", "--landmarks", lm) == 2
    err = capsys.readouterr().err
    assert "; or pass --convert to let torchface convert" in err and "JobConfig" not in err, err
    assert _cli(gray, "--out", tmp_path / "d", "--landmarks", lm, "--keep-going") == 3
    err = capsys.readouterr().err
    assert "warning: skipped" in err and "pass --convert" in err and "JobConfig" not in err, err


def test_no_initialisation_names_the_landmarks_and_detector_fields(clip, tmp_path, capsys):
    array, _ = clip
    with pytest.raises(InputError) as caught:
        track_videos([array], JobConfig(out_dir=tmp_path / "a"))
    assert str(caught.value) == ("no initialisation: give landmarks=(FILE, ...) (68 iBUG points of the first frame) "
                                 "or detector=NAME")  # fmt: skip
    assert _cli(array, "--out", tmp_path / "b") == 2
    assert "give --landmarks FILE (68 iBUG points of the first frame) or --detector NAME" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("command_line", "python"),
    [
        ("run the same command again", "call track_videos again"),
        ("x: give another --out, or remove it", "x: give another out_dir, or remove it"),
        ("made without --meshes (no a_meshes/): run without --meshes, or without --resume",
         "made with meshes=False (no a_meshes/): run with meshes=False, or with resume=False"),
        ("(--smooth on then, off now; --keep-expression off then, on now; CANDIDE-3 (no --model) then, m now)",
         "(smoothing on then, off now; keep_expression off then, on now; CANDIDE-3 (no model) then, m now)"),
        ("a: --fps 30 not used for it", "a: fps=30 not used for it"),
        ("give --landmarks files of its 5 points, without --detector",
         "give landmarks files of its 5 points, with detector=None"),
        ("the others were completed (a): --resume skips them", "the others were completed (a): resume=True skips them"),
        # (not an option: in a path, a longer word, another program's, a command line quoted as such)
        ("/data/--resume/a.npy, a--out, --outer, pip install --no-deps x, torchface track --resume completes it",
         "/data/--resume/a.npy, a--out, --outer, pip install --no-deps x, torchface track --resume completes it"),
    ],
)  # fmt: skip
def test_messages_worded_for_each_caller(command_line: str, python: str) -> None:
    from torchface.job import _for_command_line, _worded  # (the command line runs the job within the first)

    assert _worded(command_line) == python
    with _for_command_line():
        assert _worded(command_line) == command_line
    assert _worded(command_line) == python  # (the command line's wording ends with it)
