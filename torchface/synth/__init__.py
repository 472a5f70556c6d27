"""Synthetic test sequences with exact ground truth (pose, expression, light, occlusion, landmarks).

Subjects (:mod:`~torchface.synth.subjects`): CANDIDE-3 textured from a frontal photograph, and the
James face scan. Scenarios (:mod:`~torchface.synth.scenarios`) are deterministic functions of
``(num_frames, width, height)``; :func:`render_sequence` renders one in memory and
:func:`write_sequence` writes a lossless video plus ``<name>.gt.npz`` / ``<name>.gt.json``.

A sequence of one's own is a :class:`SequenceSpec` (pose, animation units, light per frame; the helpers
:func:`~torchface.synth.scenarios.keyframe_path`, :func:`~torchface.synth.scenarios.default_light` and
:data:`~torchface.synth.scenarios.FACE_DISTANCE_MM` are in :mod:`~torchface.synth.scenarios`). A tracked sequence is
scored against its :class:`GroundTruth` by :mod:`torchface.synth.metrics`
(:func:`~torchface.synth.metrics.sequence_metrics`); docs/python-api.md, "Synthetic sequences with ground truth",
renders, tracks and scores one.
"""

from __future__ import annotations

from torchface.synth.background import BackgroundSpec, OccluderSpec
from torchface.synth.io import read_video, write_video
from torchface.synth.scenarios import SCENARIOS, SIZES, make_scenario, scenario_size
from torchface.synth.sequence import (
    GroundTruth,
    SequenceFiles,
    SequenceSpec,
    load_ground_truth,
    render_sequence,
    save_ground_truth,
    write_sequence,
)
from torchface.synth.subjects import Subject, candide_subject, get_subject, james_subject

__all__ = [
    "BackgroundSpec",
    "GroundTruth",
    "OccluderSpec",
    "SCENARIOS",
    "SIZES",
    "SequenceFiles",
    "SequenceSpec",
    "Subject",
    "candide_subject",
    "get_subject",
    "james_subject",
    "load_ground_truth",
    "make_scenario",
    "read_video",
    "render_sequence",
    "save_ground_truth",
    "scenario_size",
    "write_sequence",
    "write_video",
]
