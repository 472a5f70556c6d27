"""Tests for the torchface command-line interface."""

from __future__ import annotations

import pytest

from torchface.cli import build_parser, main
from torchface.synth.io import read_video
from torchface.synth.sequence import load_ground_truth


def test_render_demo_writes_a_sequence(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["render-demo", "--out", str(out), "--frames", "3", "--width", "64", "--height", "48"]) == 0
    text = capsys.readouterr().out
    assert "3/3 frames" in text and "pose_sweep.avi" in text
    assert read_video(out / "pose_sweep.avi").shape == (3, 3, 48, 64)
    assert load_ground_truth(out / "pose_sweep.gt.npz").num_frames == 3


def test_render_demo_rejects_unknown_scenario(tmp_path, capsys):
    assert main(["render-demo", "--out", str(tmp_path), "--scenario", "nope", "--frames", "2"]) == 2
    assert "unknown scenario" in capsys.readouterr().err


def test_parser_requires_a_command():
    with pytest.raises(SystemExit):
        build_parser().parse_args([])
    assert build_parser().parse_args(["demo"]).out.name == "torchface-demo"


def test_track_threads_sets_torchs_threads_and_rejects_non_positive(monkeypatch, tmp_path, capsys):
    import torch

    import torchface.cli as cli

    seen = []
    monkeypatch.setattr(cli, "_run_track", lambda *a, **k: seen.append(torch.get_num_threads()) or 0)
    before = torch.get_num_threads()
    try:
        assert main(["track", "clip.mp4", "--out", str(tmp_path), "--threads", "1"]) == 0
        assert seen == [1]
    finally:
        torch.set_num_threads(before)
    for bad in ("0", "-2", "two"):
        with pytest.raises(SystemExit):
            main(["track", "clip.mp4", "--out", str(tmp_path), "--threads", bad])
        assert "--threads: must be an integer >= 1" in capsys.readouterr().err
