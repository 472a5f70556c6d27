"""Smoke tests of scripts/make_sequence.py and scripts/overlay_landmarks.py on a tiny sequence."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import cv2

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_make_sequence_then_overlay(tmp_path, capsys):
    make = _load("make_sequence")
    out = tmp_path / "seq"
    assert make.main(["--scenario", "expressions", "--width", "64", "--height", "48", "--frames", "3", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "3/3 frames" in text and "expressions.avi" in text
    overlay = _load("overlay_landmarks")
    assert overlay.main([str(out / "expressions.avi"), "--frames", "0", "2", "--out", str(tmp_path / "ov")]) == 0
    text = capsys.readouterr().out
    assert "max |reprojected - landmarks_px| = 0.00e+00" in text
    img = cv2.imread(str(tmp_path / "ov" / "expressions_0002.png"))
    assert img is not None and img.shape[1] == 640  # upscaled to about 640 px wide


def test_make_sequence_writes_a_long_scenario(tmp_path, capsys):
    """The long runs are reachable by name (their timeline needs at least 100 frames)."""
    make = _load("make_sequence")
    out = tmp_path / "long"
    args = ["--scenario", "long_run", "--width", "64", "--height", "48", "--frames", "100", "--out", str(out)]
    assert make.main(args) == 0
    assert "100/100 frames" in capsys.readouterr().out
    assert (out / "long_run.avi").stat().st_size > 0 and (out / "long_run.gt.npz").exists()
