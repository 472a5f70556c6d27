"""``torchface track --keep-expression`` (``JobConfig.keep_expression``): the normalised video resampled at the
person's neutral (the neutral the CSV's ``AUxx_r`` are measured from) instead of each row's expression, every other
output as without it, the sidecar's ``config.keep_expression``, and ``--resume`` refusing another setting."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

from torchface.cli import main
from torchface.io import read_track_csv
from torchface.job import JobConfig, track_videos
from torchface.model.candide import load_candide3
from torchface.normalise.face import NormalisedFace

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/_helpers.py
from _helpers import lossless_scenario_clip  # noqa: E402

T, W, H = 8, 160, 120
OUTPUTS = ("clip.csv", "clip_overlay.mp4", "clip_plot.png")  # (the normalised video is the one that differs)


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    """The ``expressions`` scenario's first frames, lossless as an ``.npy`` array, and its first landmarks."""
    return lossless_scenario_clip(tmp_path_factory.mktemp("clip"), "expressions", T, W, H)


@pytest.fixture(scope="module")
def runs(clip, tmp_path_factory):
    """The clip tracked without and with ``--keep-expression``, each with the animation coefficients its normalised
    faces were resampled at, frame by frame."""
    video, lm = clip
    out, resampled = {}, {}
    original = NormalisedFace.from_params
    for name, extra in (("plain", []), ("keep", ["--keep-expression"])):
        out[name], resampled[name] = tmp_path_factory.mktemp(name), []

        def record(self, frames, shape, alpha, *args, _log=resampled[name], **kwargs):
            _log.append(alpha.detach().double().cpu().clone())
            return original(self, frames, shape, alpha, *args, **kwargs)

        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(NormalisedFace, "from_params", record)
            assert main(["track", str(video), "--out", str(out[name]), "--landmarks", str(lm), "--quiet", *extra]) == 0
    return out, {k: torch.cat(v) for k, v in resampled.items()}


def test_keep_expression_resamples_at_the_neutral_and_changes_nothing_else(runs) -> None:
    out, resampled = runs
    cols, rows = read_track_csv(out["keep"] / "clip.csv")
    anim = torch.from_numpy(rows[:, [i for i, c in enumerate(cols) if c.startswith("anim_")]])
    facs = torch.from_numpy(rows[:, [i for i, c in enumerate(cols) if c.startswith("AU") and c.endswith("_r")]])
    assert resampled["plain"].shape == resampled["keep"].shape == anim.shape == (T, anim.shape[1])
    # without it: each row's own coefficients (the neutral face); with it: the neutral, which the rows' AUxx_r
    # (the FACS values of the expression, the coefficients minus the neutral) are measured from
    torch.testing.assert_close(resampled["plain"], anim, rtol=0, atol=1e-6)
    model = load_candide3(dtype=torch.float64)
    torch.testing.assert_close(model.facs_values(anim - resampled["keep"]), facs, rtol=0, atol=1e-5)
    assert float(facs.abs().max()) > 0.1  # (the clip has expressions: the two differ)
    assert float((resampled["keep"] - anim).abs().max()) > 0.1
    for name in OUTPUTS:  # every other output byte for byte as without it
        assert (out["keep"] / name).read_bytes() == (out["plain"] / name).read_bytes(), name
    assert (out["keep"] / "clip_normalised.mp4").read_bytes() != (out["plain"] / "clip_normalised.mp4").read_bytes()
    for name, want in (("plain", False), ("keep", True)):
        assert json.loads((out[name] / "clip.json").read_text())["config"]["keep_expression"] is want


def test_keep_expression_resume_goes_on_and_another_setting_is_refused(clip, runs, tmp_path, capsys) -> None:
    """Interrupted after 4 rows with ``--keep-expression``: resumed without it, refused; with it, the uninterrupted
    run's outputs. A partial run without it, and complete outputs without it, resumed with it: refused."""
    video, lm = clip
    out, _ = runs
    args = ["track", str(video), "--landmarks", str(lm), "--quiet", "--resume"]

    def interrupt(p):
        if p.done == 4:
            raise KeyboardInterrupt

    for name, keep in (("keep", True), ("plain", False)):
        with pytest.raises(KeyboardInterrupt):
            track_videos([video], JobConfig(out_dir=tmp_path / name, landmarks=(lm,), keep_expression=keep),
                         progress=interrupt)  # fmt: skip
    assert main([*args, "--out", str(tmp_path / "keep")]) == 2
    assert "--keep-expression True then, False now" in capsys.readouterr().err
    assert main([*args, "--out", str(tmp_path / "plain"), "--keep-expression"]) == 2
    assert "--keep-expression False then, True now" in capsys.readouterr().err
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
    assert "--keep-expression False then, True now" in capsys.readouterr().err


def test_job_keep_expression_setting_is_checked(tmp_path) -> None:
    with pytest.raises(TypeError, match="keep_expression"):
        JobConfig(out_dir=tmp_path, keep_expression="no")  # type: ignore[arg-type]
