"""``torchface track --keep-expression`` (``JobConfig.keep_expression``): the normalised video resampled at the
person's neutral (the neutral the CSV's ``AUxx_r`` are measured from) instead of each row's expression, every other
output as without it, the sidecar's ``config.keep_expression``, and ``--resume`` refusing another setting."""

from __future__ import annotations

import contextlib
import json
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from torchface.cli import main
from torchface.io import read_track_csv
from torchface.job import JobConfig, track_videos
from torchface.model.candide import load_candide3
from torchface.normalise.face import NormalisedFace
from torchface.tracker.lookahead import LookaheadConfig

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/_helpers.py
from _helpers import lossless_scenario_clip  # noqa: E402

T, W, H = 8, 160, 120
OUTPUTS = ("clip.csv", "clip_overlay.mp4", "clip_plot.png")  # (the normalised video is the one that differs)


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """The ``expressions`` scenario's first frames, lossless as an ``.npy`` array, and its first landmarks."""
    return lossless_scenario_clip(tmp_path_factory.mktemp("clip"), "expressions", T, W, H)


@contextlib.contextmanager
def _resampled():
    """The animation coefficients ``(B, A)`` the normalised faces are resampled at in the block, frame by frame."""
    log: list[torch.Tensor] = []
    original = NormalisedFace.from_params

    def record(self, frames, shape, alpha, *args, **kwargs):
        log.append(alpha.detach().double().cpu().clone())
        return original(self, frames, shape, alpha, *args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(NormalisedFace, "from_params", record)
        yield log


def _assert_measured_from(csv, resampled: torch.Tensor) -> torch.Tensor:
    """The rows' ``AUxx_r`` of ``csv`` are measured from the coefficients ``resampled`` ``(T, A)`` (the FACS values
    of the expression, the coefficients minus the neutral); returns the rows' ``anim_*``."""
    cols, rows = read_track_csv(csv)
    anim = torch.from_numpy(rows[:, [i for i, c in enumerate(cols) if c.startswith("anim_")]])
    facs = torch.from_numpy(rows[:, [i for i, c in enumerate(cols) if c.startswith("AU") and c.endswith("_r")]])
    assert resampled.shape == anim.shape == (T, anim.shape[1])
    model = load_candide3(dtype=torch.float64)
    torch.testing.assert_close(model.facs_values(anim - resampled), facs, rtol=0, atol=1e-5)
    assert float(facs.abs().max()) > 0.1  # (the clip has expressions: the two differ)
    return anim


@pytest.fixture(scope="module")
def runs(clip, tmp_path_factory):
    """The clip tracked without and with ``--keep-expression``, each with the animation coefficients its normalised
    faces were resampled at, frame by frame."""
    video, lm = clip
    out, resampled = {}, {}
    for name, extra in (("plain", []), ("keep", ["--keep-expression"])):
        out[name] = tmp_path_factory.mktemp(name)
        with _resampled() as log:
            assert main(["track", str(video), "--out", str(out[name]), "--landmarks", str(lm), "--quiet", *extra]) == 0
        resampled[name] = torch.cat(log)
    return out, resampled


def test_keep_expression_resamples_at_the_neutral_and_changes_nothing_else(runs) -> None:
    out, resampled = runs
    # without it: each row's own coefficients (the neutral face); with it: the neutral the rows' AUxx_r are measured
    # from
    anim = _assert_measured_from(out["keep"] / "clip.csv", resampled["keep"])
    torch.testing.assert_close(resampled["plain"], anim, rtol=0, atol=1e-6)
    assert float((resampled["keep"] - anim).abs().max()) > 0.1
    for name in OUTPUTS:  # every other output byte for byte as without it
        assert (out["keep"] / name).read_bytes() == (out["plain"] / name).read_bytes(), name
    assert (out["keep"] / "clip_normalised.mp4").read_bytes() != (out["plain"] / "clip_normalised.mp4").read_bytes()
    for name, want in (("plain", False), ("keep", True)):
        assert json.loads((out[name] / "clip.json").read_text())["config"]["keep_expression"] is want


def test_keep_expression_resume_goes_on_and_another_setting_is_refused(clip, runs, tmp_path, capsys) -> None:
    """Interrupted after 4 rows with ``--keep-expression``: resumed without it, refused; with it, the uninterrupted
    run's outputs. A partial run without it, and complete outputs without it, resumed with it: refused. Resumed from
    the record after the re-anchoring frame: the replayed rows resampled at the neutral of their AUxx_r."""
    video, lm = clip
    out, _ = runs
    args = ["track", str(video), "--landmarks", str(lm), "--quiet", "--resume"]

    def interrupt(p, after=4):
        if p.done == after:
            raise KeyboardInterrupt

    for name, keep in (("keep", True), ("plain", False)):
        with pytest.raises(KeyboardInterrupt):
            track_videos([video], JobConfig(out_dir=tmp_path / name, landmarks=(lm,), keep_expression=keep),
                         progress=interrupt)  # fmt: skip
    assert main([*args, "--out", str(tmp_path / "keep")]) == 2
    assert "--keep-expression on then, off now" in capsys.readouterr().err
    assert main([*args, "--out", str(tmp_path / "plain"), "--keep-expression"]) == 2
    assert "--keep-expression off then, on now" in capsys.readouterr().err
    assert main([*args, "--out", str(tmp_path / "keep"), "--keep-expression"]) == 0
    for name in (*OUTPUTS, "clip_normalised.mp4"):
        assert (tmp_path / "keep" / name).read_bytes() == (out["keep"] / name).read_bytes(), name
    # complete outputs made without it (skipped as complete, they would have kept the neutral faces)
    done = tmp_path / "done"
    done.mkdir()
    for f in out["plain"].iterdir():
        if f.is_file():
            (done / f.name).write_bytes(f.read_bytes())
    assert main([*args, "--out", str(done), "--keep-expression"]) == 2
    assert "--keep-expression off then, on now" in capsys.readouterr().err
    # interrupted after the online start's last frame (4) and its re-anchoring, resumed from the record without a
    # checkpoint (none before 25 rows): the rows up to the re-anchoring frame, replayed, are resampled at the neutral
    # their AUxx_r are measured from, the first fit's (the record's anchor.first_anim_coeffs; the state holds the
    # re-estimate), as the rows after it at the re-estimate
    config = JobConfig(out_dir=tmp_path / "record", landmarks=(lm,), keep_expression=True,
                       refine_first=LookaheadConfig(max_frames=4))  # fmt: skip
    with pytest.raises(KeyboardInterrupt):
        track_videos([video], config, progress=lambda p: interrupt(p, 6))
    with _resampled() as resampled:
        track_videos([video], replace(config, resume=True))
    side = json.loads((tmp_path / "record" / "clip.json").read_text())
    assert side["resumed"]["tracked_again"] == 0 and side["resumed"]["checkpoint"] is False
    assert side["start"]["reanchored_at_frame"] < 6
    _assert_measured_from(tmp_path / "record" / "clip.csv", torch.cat(resampled))


def test_job_keep_expression_setting_is_checked(tmp_path) -> None:
    with pytest.raises(TypeError, match="keep_expression"):
        JobConfig(out_dir=tmp_path, keep_expression="no")  # type: ignore[arg-type]
