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
