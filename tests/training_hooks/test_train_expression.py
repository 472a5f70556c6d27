"""Smoke test of scripts/train_expression.py --quick: every stage runs, the figures are written and consistent."""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/_helpers.py
from _helpers import load_script  # noqa: E402


def _load():
    return load_script("train_expression")  # (registered by name: the render processes look the module up)


def test_quick_run(tmp_path, capsys):
    script = _load()
    out = tmp_path / "run"
    figures_path = tmp_path / "figures.json"
    assert script.main(["--quick", "--crop-single", "--out", str(out), "--json", str(figures_path)]) == 0
    text = capsys.readouterr().out
    for needle in ("epoch 1 (tracking", "epoch 2 (cached)", "pooled", "stage times"):
        assert needle in text
    figures = json.loads(figures_path.read_text())
    q = script.QUICK
    clips = len(figures["identities"]) * len(figures["classes"]) * q.clips
    assert figures["clips"] == clips
    # Epoch 1 tracked everything (fresh cache), epoch 2 read everything from the cache; every frame counted.
    assert figures["throughput_epoch1"]["cached_fraction"] == 0.0
    assert figures["throughput_epoch2"]["cached_fraction"] == 1.0
    assert figures["throughput_epoch2"]["faces"] == clips * q.clip_frames
    acc = figures["accuracy"]
    assert set(acc) == {"normalised", "crop", "crop_single"} and all(0.0 <= v <= 1.0 for v in acc.values())
    best_crop = max(acc["crop"], acc["crop_single"])
    assert abs(figures["gain_points"] - 100 * (acc["normalised"] - best_crop)) < 1e-9
    # a --quick run's 10 test clips judged the target ("NOT met (0.0)"); the figures said False
    assert "10 points: not judged on a --quick run" in text and figures["target_met"] is None
    assert len(list((out / "videos").glob("*.avi"))) == clips


def test_a_users_folder_is_never_emptied(tmp_path):
    """``<out>/videos`` and ``<out>/cache`` are emptied on a new run only when the script made them (a mark file):
    a user's folder of that name is refused before anything runs (it was deleted without a word)."""
    import pytest

    script = _load()
    (tmp_path / "videos").mkdir()
    (tmp_path / "videos" / "keep.txt").write_text("my data")
    with pytest.raises(SystemExit, match="was not made by this script"):
        script._clear_own_folder(tmp_path / "videos")
    assert (tmp_path / "videos" / "keep.txt").read_text() == "my data"
    own = tmp_path / "cache"
    script._clear_own_folder(own)  # made and marked
    (own / "entry.npz").write_bytes(b"x")
    script._clear_own_folder(own)  # the script's own: emptied for the new run
    assert [f.name for f in own.iterdir()] == [script._OWN_MARK]


def test_bad_out_and_json_paths_are_refused_before_the_run(tmp_path, capsys):
    """A ``--json`` folder (or a path under a file), an ``--out`` under a file and a negative seed are one-line
    errors before anything runs: the ``--json`` folder failed only after the whole run, leaving ``<json>.partial``."""
    import pytest

    script = _load()
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    (tmp_path / "a_folder").mkdir()
    dangling = tmp_path / "dangling"
    dangling.symlink_to(tmp_path / "gone")
    out = tmp_path / "run"
    for argv, needle in (
        (["--out", str(out), "--json", str(tmp_path / "a_folder")], "--json"),
        (["--out", str(out), "--json", str(a_file / "figures.json")], "--json"),
        (["--out", str(a_file)], "--out"),
        (["--out", str(a_file / "run")], "--out"),
        (["--out", str(dangling)], "symbolic link to"),  # (a FileExistsError's traceback from mkdir, after the checks)
        (["--out", str(dangling / "run")], "symbolic link to"),
        (["--out", str(out), "--json", str(dangling / "figures.json")], "symbolic link to"),  # (after the whole run)
        (["--out", str(out), "--seed", "-1"], "--seed"),
        (["--out", str(out), "--seed", str(2**64)], "--seed must be an integer in [0, 2**32 - 1]"),
    ):
        with pytest.raises(SystemExit) as exc:
            script.main(["--quick", *argv])
        assert exc.value.code == 2, argv
        assert needle in capsys.readouterr().err, argv
    assert not out.exists()  # nothing ran
    assert sorted(f.name for f in tmp_path.iterdir()) == ["a_file", "a_folder", "dangling"]


def test_threads_option(tmp_path, capsys, monkeypatch):
    """``--threads`` as in the other scripts (the script set two threads itself, with no option); 0 is refused."""
    import pytest
    import torch

    script = _load()
    with pytest.raises(SystemExit) as exc:
        script.main(["--quick", "--out", str(tmp_path / "run"), "--threads", "0"])
    assert exc.value.code == 2 and "--threads must be >= 1, got 0" in capsys.readouterr().err

    class Stop(Exception):
        pass

    def stop(*args, **kwargs):
        raise Stop

    monkeypatch.setattr(script, "identities", stop)  # the first stage, just after the threads are set
    before = torch.get_num_threads()
    try:
        with pytest.raises(Stop):
            script.main(["--quick", "--out", str(tmp_path / "run"), "--threads", "3"])
        assert torch.get_num_threads() == 3
    finally:
        torch.set_num_threads(before)


def test_a_users_cache_folder_is_refused_before_rendering(tmp_path, monkeypatch):
    """``<out>/cache`` of the user's (or a file there) was refused only after every clip had been rendered (minutes
    in a full run), with ``<out>/videos`` already emptied and refilled."""
    import pytest

    script = _load()
    monkeypatch.setattr(script, "render_all", lambda *a: (_ for _ in ()).throw(AssertionError("rendering started")))
    out = tmp_path / "run"
    (out / "cache").mkdir(parents=True)
    (out / "cache" / "keep.txt").write_text("my data")
    with pytest.raises(SystemExit, match="cache exists and was not made by this script"):
        script.main(["--quick", "--out", str(out)])
    (out / "cache" / "keep.txt").unlink()
    (out / "cache").rmdir()
    (out / "cache").write_text("a file")
    with pytest.raises(SystemExit, match="cache is a file"):
        script.main(["--quick", "--out", str(out)])
    assert sorted(f.name for f in out.iterdir()) == ["cache"]  # no videos folder made
