"""The tracking job behind ``torchface track``: videos in, per-video CSV, JSON, overlay, plot and normalised face out.

:func:`track_videos` validates every input before any tracking starts, groups videos of the same frame size (and
pyramid, :func:`~torchface.tracker.step.pyramid_for_faces`) into batches of up to ``JobConfig.max_batch`` and
:data:`BATCH_PIXELS` (tracked together as B streams by
:func:`torchface.tracker.managed_step`; only one batch's inputs are open at a time; a video that has ended leaves
the batch, :meth:`~torchface.tracker.TrackerState.select`, and the others go on as a smaller one), and writes per video
(``<stem>`` is the input's file name without suffix):

- ``<stem>.csv``: one row per frame (:mod:`torchface.io.table` documents the columns and units; with
  ``JobConfig.smoothing``, ``torchface track --smooth``, the smoothed pose's ``smooth_*`` columns after them);
- ``<stem>.json``: versions, settings, camera, model, how the video started (``start``, :func:`_start_record`),
  timings, what a resumed run kept and tracked again (``resumed``, :func:`_resumed_record`), frame count and lost
  frames, ``redetections`` (re-detections of a low-confidence stream,
  ``redetect_after``, that found a face and re-fitted its pose) and ``detector_calls`` (how often this run asked the
  detector about the video's frames: the first frame (and each next one up to the first with a face), those
  re-detections, and the tracker's recovery attempts (and restarts, ``restart_after_unmatched``) of a lost stream,
  which ``redetections`` leaves out; both 0 without a detector; a resumed run does not ask about the rows it
  replays, nor about the frames up to the first with a face, which its record says (:func:`_recorded_first_face`;
  a record of an earlier version does not: it looks for it again), but for a re-detection due after the last one,
  which the tracking goes on from, and the rows it tracks again for the online start, :attr:`_Stream.retrack`, as the
  uninterrupted run did) and ``restart_failures`` (those restarts that failed, counted by
  :class:`~torchface.tracker.step.StartFailure` name, ``{}`` where none). The three counts are the whole video's in
  a resumed run too where it goes on from a checkpoint (which carries them, :func:`_restore_streams`) or tracks its
  rows again (the recorded first-face search counted as the interrupted run made it); from its CSV's rows alone,
  they count the recorded search and the rows this run tracks (the rows replayed say nothing of the detector);
- ``<stem>_overlay.mp4``: wireframe, head axes (the CSV row's pose) and confidence on each frame, in step with the
  input's time (each row at the slot of its ``timestamp`` at the input's nominal rate: :class:`_VideoOut`'s ``timed``;
  one frame per row for a constant-rate input; a gap longer than :data:`OVERLAY_MAX_GAP_S`, a broken time, not filled);
- ``<stem>_plot.png``: yaw/pitch/roll, the most active AUs and the confidence over time;
- ``<stem>_normalised.mp4``: the normalised face (:mod:`torchface.normalise`), one frame per CSV row (the sidecar's
  ``videos``, :func:`_video_timing`);
- ``<stem>_meshes/NNNNNN.ply`` with ``meshes=True``: the posed mesh per frame, camera frame, millimetres.

A video whose first frame shows no face to the detector (a title card, a black frame) is searched frame by frame
and tracked from the first frame where it finds one (:func:`_open_inputs`; ``start.first_frame`` in the JSON), its
rows before it without an estimate (:func:`_no_face_row`); one without any face is refused before anything is
written. A video whose start failed (:func:`_warn_failed_starts`) and that nothing started afresh is written complete,
every row unusable (``success`` 0): its :class:`VideoSummary`'s ``no_tracked_frame`` says it (``torchface track``
exits with status 3).

With ``JobConfig.keep_going`` (``torchface track --keep-going``) an input that is refused (by the checks before
tracking, as its batch opens, or, resumed, as its partial run is read) is skipped with a warning (:class:`InputSkipped`)
and the others are tracked as they would be without it (its batch goes on without it); a video stopped partway is
returned with the others; every input gets a :class:`VideoSummary` that says which (``refused``, ``stopped``).

Every output of a frame is drawn from its CSV row as written and the JSON's ``start`` (:func:`_drawn_pose`), so that
they agree with the CSV, lost and failed rows included, and a resumed run draws its replayed rows as the interrupted
run did.

Everything is written under a temporary name (``.partial``) and renamed when complete; the JSON is renamed last.
A video's outputs are finalised as soon as its last frame is tracked: one that ends before others of its batch is
complete then (after their checkpoint as the smaller batch they go on as), while they go on.
While a run goes on, ``<stem>.lock`` (holding its pid and host) keeps another run from writing the same video's
outputs: that run is refused with a one-line error; a lock left by a run that has ended (killed), or left empty
(killed as it made it), is taken over (:func:`_take_locks`). A run
without ``resume`` first removes what earlier runs wrote for all its videos (before its first batch; with a warning
where they were made from another input of the same name, :func:`_warn_replaced_inputs`). Outputs that would
replace an input or a landmarks file, or an output folder that is an image-folder input, are refused before anything is
written, as are two inputs whose ``<stem>`` is the same or differs only in case (one file on macOS and Windows). CSV
rows are flushed as they are tracked, so an interrupted run keeps ``<stem>.csv.partial``; with
``resume=True`` a video whose JSON exists is skipped (refused when made from another input or from its file as it was
before it changed, from other first-frame landmarks than its landmarks file holds now, with other settings or without
the meshes asked for:
:func:`_check_resumable`) and one with a partial CSV continues after its last complete
row: the first frame is
initialised again from the same landmarks (deterministic), or, for a video the online start had re-anchored (after
``LookaheadConfig.max_frames`` rows: sooner, it is tracked again, below), from the
refined fit recorded in ``<stem>.record.partial`` (which also names the input the partial results belong to, its size
and modification time, the first-frame landmarks (and the frame where the detector found them: a resumed run does
not look for them again, :func:`_recorded_first_face`) and every setting the rows depend on: a resume with other
settings, or after the input file changed, is refused (settings compared field by field, by value; a field added to
the settings since the interrupted run's version is compared at its default, what that version did where the
field's default kept the earlier behaviour (most do; not, e.g., ``min_face_width_px``, ``reference_focal_px`` or
``expression_range_from_start``),
one removed since is not compared), as is a damaged or missing record
or a damaged partial CSV: a row out of sequence, not finite, or whose rotation is not one, or whose ``timestamp`` is not
its frame's time, :func:`_check_replayed_time`); the parameters of the rows
already written are read back from the CSV, and the videos are re-drawn from them; so is the stream's loss
bookkeeping (lost or not, the frames of low confidence counted, the last confident parameters), so that a video
interrupted while its face was lost goes on lost, as the uninterrupted run would, and, with
``TrackerConfig.motion_prediction``, its velocity (:func:`_with_replayed_motion`), so that the next frames start from
the prediction the uninterrupted run made. A CSV under its final name without its JSON (interrupted while finalising) is
resumed as a partial one. A video interrupted within the frames the online start watches (fewer rows than
``LookaheadConfig.max_frames``), whether the start still waited for its head to turn or had re-anchored it, is not put
into the tracker's state from its rows: they are tracked again from its first frame, not written, each checked against
the CSV's (:func:`_check_retracked`: a row not met again is warned about, counted in the sidecar's ``resumed`` and
the summary's ``not_met_again``), so that it re-anchors where the
uninterrupted run did and goes on as it, its mosaic included (measured: the resumed CSV byte-identical to the
uninterrupted run's on rendered clips, also with a detector, ``smoothing`` or ``motion_prediction``, and on 160x120
pose sweeps of 20, 60 and 200 frames re-anchored before the interruption, resumed after 7 and 40 rows; 3-20 mm, 1-2
degrees and 0.25 of confidence off when one not re-anchored went on from its rows without the online start, up to
8.1 mm, 1.6 degrees and 0.45 when a re-anchored one went on from its record without its mosaic); at most
``max_frames - 1`` frames (149) tracked again.
Past those frames (from frame ``max_frames``; without the online start from frame :data:`CHECKPOINT_EVERY`), every
:data:`CHECKPOINT_EVERY` frames the loop writes each video's checkpoint, ``<stem>.state.partial``
(:func:`_write_checkpoints`: its part of the tracker's state, templates and mosaic included, of the pose filter, its
first pose and bookkeeping; tensors and plain data, :mod:`torchface._checkpoint`, read with ``weights_only=True``),
removed once the video is complete (a video that ends before others of its batch: as it ends). A resume goes on from
it where it matches the partial CSV (:func:`_load_checkpoint`: settings, row count, last row; else one warning line
and the rows as below): the rows written after it are cut off and tracked again, and the videos of the checkpoint's
batch are tracked as that batch again (:func:`_checkpoint_batches`), their states joined
(:func:`torchface._checkpoint.join`, the inverse of ``select``) after their last row (:func:`_joined`). Measured: a
200-frame 160x120 pose sweep interrupted after 170 rows (its checkpoint at 150) resumed byte for byte as the
uninterrupted run (CSV, overlay, normalised face) alone,
with ``smoothing``, with a detector re-detecting every 5 frames and as a batch of 3 sweeps of 193-200 frames, where
from its CSV's rows (the checkpoint removed) it went up to 1.10 mm, 1.36 degrees (the distance between the
translations, the angle between the rotations) and 0.12 of confidence off (the batch: 3.51 mm, 3.33 degrees, 0.65;
``scripts/doc_figures.py resume-sweep``); cost: :data:`CHECKPOINT_EVERY`. Ctrl-C and SIGTERM within the loop wait
for its step boundary (:class:`_AtStepBoundary`), where every live video's checkpoint of that state is written before
the signal's handler raises: a resume tracks no row again (a second signal interrupts at once, mid-step, without it).
For the others (``max_frames`` rows or more, without a checkpoint) the template mosaic built before the interruption
is not restored: on a
clip whose head turns, the resumed rows can part from the uninterrupted run's by tenths of a degree to a degree once
the mosaic is used (measured: up to 0.4 degrees of yaw and 0.9 mm, with the same error against the ground truth; the
200-frame 160x120 pose sweep above resumed after 170 rows without its checkpoint, up to 1.10 mm, 1.36 degrees and
0.12 of confidence). Their ``confidence`` can part by more, as it is measured against the mosaic entry nearest the
pose, which the resumed run may not have built again (measured when such videos resumed sooner went on from their
rows too: a 300-frame clip (160x120, its head turning back and forth) resumed at frame 104 went on at the same poses
(within 3e-5 degrees) and statuses, but frames that the uninterrupted run scored 0.22 against such an entry scored
0.93 against the first frame's, mean confidence 0.88 against 0.78). A loss can end at another frame for the same
reason: on a 160x120 clip interrupted in a loss (frames of noise) and resumed from its rows, the uninterrupted run's
tracking found the face again at the first frame after the noise against the re-anchoring frame's entry (confidence
0.77), the resumed run (which lacked it) a frame later, at its recovery attempt.
"""

from __future__ import annotations

import ast
import contextlib
import contextvars
import hashlib
import itertools
import json
import math
import os
import queue
import re
import signal
import socket
import sys
import threading
import time
import unicodedata
import warnings
import weakref
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import MISSING, dataclass, field, fields, is_dataclass, replace
from functools import lru_cache, partial
from importlib import resources
from pathlib import Path
from typing import Any, Literal, cast

import cv2
import numpy as np
import torch
from torch import Tensor

from torchface import _checkpoint
from torchface._device import check_device
from torchface._paths import check_no_tilde
from torchface._words import counted, plural, switch_hint
from torchface.appearance.illumination import NUM_ILLUMINATION_TERMS
from torchface.detect import _Batched, _uint8_planes, accepts_near, detector_image, search_first_face, usable_detection
from torchface.geometry._checks import check_bool, check_int, check_number, rotation_defects
from torchface.geometry.camera import Intrinsics
from torchface.geometry.so3 import axis_angle_to_matrix, matrix_to_axis_angle, matrix_to_euler
from torchface.io.errors import InputError, OutputError, dangling_link
from torchface.io.landmarks import NUM_LANDMARKS, check_landmarks, read_landmarks
from torchface.io.sidecar import package_versions, to_jsonable, write_json
from torchface.io.table import (
    POSE_COLUMNS, ROTATION_COLUMNS, SMOOTH_COLUMNS, TrackCsvWriter, partial_path, pose_values, read_back, read_track_csv,
    result_rows, track_columns,
)
from torchface.io.video import (
    ASSUMED_FPS, IMAGE_SUFFIXES, PLAUSIBLE_FPS, VIDEO_SUFFIXES, FrameReader, image_files, open_frames, opencv_path,
)  # fmt: skip
from torchface.model.candide import load_candide3
from torchface.model.face_model import FaceModel
from torchface.model.model_file import face_model_digest, load_face_model
from torchface.normalise.face import NormalisedFace
from torchface.solver.least_squares import SolveStatus
from torchface.tracker.fit import (
    LandmarkFit, check_model_landmarks, fit_landmarks, held_shape_indices, shape_prior_vector,
)  # fmt: skip
from torchface.tracker.lookahead import (
    LookaheadConfig, check_model_units, check_refine_first, levels_of, lookahead_fit,
)  # fmt: skip
from torchface.tracker.managed import initialise_managed, managed_step
from torchface.tracker.params import ParamLayout
from torchface.tracker.smoothing import SmoothingConfig, SmoothingState, one_euro_rotation_step, one_euro_step
from torchface.tracker.step import (
    StartFailure,
    TrackerConfig,
    TrackerState,
    TrackStatus,
    _unit_weights,
    min_frame_side,
    pyramid_for_faces,
)
from torchface.visualise.overlay import axes_geometry, draw_overlay, mesh_edges, overlay_geometry
from torchface.visualise.plot import plot_track

__all__ = [
    "DEMO_ATTRIBUTION",
    "InputSkipped",
    "JobConfig",
    "Progress",
    "VideoSummary",
    "VideosStopped",
    "demo_inputs",
    "output_paths",
    "track_videos",
]

#: The most pixels of one frame per stream a batch holds (``max_batch`` 640x480 videos' worth): a batch of 4K videos
#: takes about 0.6 GB per video (measured, one 3840x2160 video 1.1 GB at its peak, two 1.7 GB), so 128 of them at
#: once did not fit in memory; they are tracked 4 at a time (1920x1080: 18), which leaves their results as they were.
BATCH_PIXELS: int = 128 * 640 * 480

#: The frame rates :class:`JobConfig`'s ``fps`` (``torchface track --fps``) takes, frames per second: above 1000 the
#: CSV's millisecond ``timestamp`` of two rows could coincide; OpenCV's mp4v writer cannot write the overlay at 0.001
#: or less (a container's rate outside (0.001, 1000) is taken as none, with a warning: :class:`torchface.io.VideoInfo`'s
#: ``fps_assumed`` and ``declared_fps``, :data:`torchface.io.video.PLAUSIBLE_FPS`).
FPS_RANGE: str = "(0.001, 1000]"

#: Whether the job runs for the command line (``torchface track``, which sets it: :func:`_for_command_line`): its
#: messages then name the command's options (``--resume``, ``--out``), else, for a Python caller of
#: :func:`track_videos`, the :class:`JobConfig` fields they are (:func:`_worded`).
_COMMAND_LINE: contextvars.ContextVar[bool] = contextvars.ContextVar("torchface.job command line", default=False)

#: How a message to a Python caller says what the command line's says with an option (:func:`_worded`), in order:
#: what to do first (``run without --resume`` is ``run with resume=False``), then each option on its own as its
#: :class:`JobConfig` field (``--out``: ``out_dir``; ``--smooth``: ``smoothing``; in a settings difference, ``--focal
#: 300.0 then, 320.0 now``, its field's name). An option is a whole word (not one inside a path or a longer option,
#: nor one of a ``torchface track`` command line quoted as such).
_OPTION = r"(?<![\w/\\.-])(?<!torchface track )--{}(?![\w-])"
_FLAGS = {"resume": "resume", "keep-going": "keep_going", "convert": "convert", "meshes": "meshes"}
_FIELDS = {
    **_FLAGS, "out": "out_dir", "detector": "detector", "landmarks": "landmarks", "model": "model", "fps": "fps",
    "focal": "focal", "smooth": "smoothing", "lookahead": "lookahead", "keep-expression": "keep_expression",
    "max-batch": "max_batch", "no-online-refine": "refine_first=None",
    "motion-prediction": "TrackerConfig.motion_prediction",
    "restart-after-unmatched": "TemplateConfig.restart_after_unmatched",
}  # fmt: skip
_PYTHON_WORDS: tuple[tuple[re.Pattern[str], str], ...] = (
    (re.compile(r"\brun the same command with " + _OPTION.format("resume")),
     "call track_videos again with JobConfig(resume=True)"),
    (re.compile(r"\brun the same command again\b"), "call track_videos again"),
    (re.compile(r"\bpass " + _OPTION.format("convert")), "set JobConfig(convert=True)"),
    *((re.compile(r"\bwithout " + _OPTION.format(option)), f"with {name}=False") for option, name in _FLAGS.items()),
    (re.compile(r"\bwithout " + _OPTION.format("detector")), "with detector=None"),
    *((re.compile(r"\bwith " + _OPTION.format(option)), f"with {name}=True") for option, name in _FLAGS.items()),
    (re.compile(_OPTION.format("resume") + r"(?= skips)"), "resume=True"),
    (re.compile(_OPTION.format("landmarks") + " FILE"), "landmarks=(FILE, ...)"),
    (re.compile(_OPTION.format("detector") + " NAME"), "detector=NAME"),
    (re.compile(_OPTION.format("fps") + r" (\S+) not used"), r"fps=\1 not used"),
    *((re.compile(_OPTION.format(re.escape(option))), name) for option, name in _FIELDS.items()),
)  # fmt: skip


@contextlib.contextmanager
def _for_command_line() -> Iterator[None]:
    """Within it, :func:`track_videos` words its messages for the command line (:data:`_COMMAND_LINE`): what
    ``torchface track`` runs it in."""
    token = _COMMAND_LINE.set(True)
    try:
        yield
    finally:
        _COMMAND_LINE.reset(token)


def _worded(message: str) -> str:
    """``message`` (worded for the command line: ``run without --resume``) as the job's caller is told it: as it is
    for the command line (:data:`_COMMAND_LINE`), else naming the :class:`JobConfig` fields that the options are
    (``run with resume=False``; :data:`_PYTHON_WORDS`).

    Example:
        >>> _worded("cannot resume (--focal 300.0 then, 320.0 now): run with them, or without --resume")
        'cannot resume (focal 300.0 then, 320.0 now): run with them, or with resume=False'
    """
    if _COMMAND_LINE.get():
        return message
    for pattern, words in _PYTHON_WORDS:
        message = pattern.sub(words, message)
    return message


def _reword(exc: BaseException) -> None:
    """Word the error ``exc`` that :func:`track_videos` raises for its caller (:func:`_worded`): the message of an
    :class:`InputError`, :class:`OutputError` or ``DetectorUnavailable``, and an interruption's ``kept`` and
    ``error``."""
    if isinstance(exc, KeyboardInterrupt):
        kept = getattr(exc, "kept", None)
        if isinstance(kept, str):
            exc.kept = _worded(kept)  # type: ignore[attr-defined]
        error = getattr(exc, "error", None)
        if isinstance(error, BaseException) and error is not exc:
            _reword(error)
        return
    if not isinstance(exc, (InputError, OutputError, ImportError)) or len(exc.args) != 1:
        return
    if not isinstance(exc.args[0], str) or (said := _worded(exc.args[0])) == exc.args[0]:
        return
    exc.args = (said,)
    if isinstance(exc, ImportError):  # (its str is its msg)
        exc.msg = said


#: Credit line of the embedded demo clip.
DEMO_ATTRIBUTION: str = (
    "GRID audio-visual corpus clip bbaf2n (speaker 1), Cooke, Barker, Cunningham and Shao (2006), CC BY 4.0"
)


@dataclass(frozen=True)
class JobConfig:
    """Settings of a tracking job.

    Attributes:
        out_dir: output folder (created if missing); a ``str`` or any ``os.PathLike``, as the paths below.
        landmarks: one landmarks file per video (68 iBUG points of its first frame; with ``model``, that model's
            landmarks, in its order: :func:`torchface.io.read_landmarks`'s ``count``), or empty to use the detector;
            a sequence even for one video (a single path raises TypeError; ``""`` and a ``"~/lm.csv"`` nothing
            expands are refused, as ``out_dir``'s).
        detector: detector name (:mod:`torchface.detect`) used when no landmarks file is given (on the first
            frame, and each next one until it finds a face: the video is tracked from there), to re-initialise
            the pose of a stream whose confidence stays below ``redetect_below`` for ``redetect_after`` frames,
            and to recover a stream that template management declares lost
            (:func:`torchface.tracker.managed.managed_step`; without a detector it searches the mosaic). Both ask
            for the face nearest the stream's last confident position (:class:`torchface.detect.Detector`'s
            ``near``), not another one in view.
        focal: focal length in pixels (default ``max(W, H)``, :meth:`Intrinsics.default`).
        device: torch device for tracking (a name or a ``torch.device``); one this machine lacks is refused when the
            config is made (:func:`torchface.extending.check_device`'s ``ValueError``, naming the devices here), as
            ``FaceTracker.to`` refuses it.
        resume: continue interrupted videos (see the module docstring).
        convert: convert grayscale, RGBA, 16-bit and odd-sized frames (gray to RGB, alpha dropped, 16-bit
            scaled, last row / column cropped; :func:`torchface.io.open_frames`) instead of rejecting them.
        meshes: write one PLY mesh per frame.
        normalised_size: side ``G`` of the normalised-face video (even, >= 16).
        tracker: :class:`TrackerConfig` (its ``template`` field sets template management: the dissimilarity
            confidence written as ``confidence``, the mosaic, loss and recovery).
        redetect_after: consecutive low-confidence frames before asking the detector again (0 = never).
        redetect_below: the (dissimilarity) confidence threshold for that, any finite number: confidences lie in
            [0, 1], so one above 1 counts every frame low (a re-detection every ``redetect_after`` frames) and one
            at most 0 none that has a confidence.
        lookahead: start each video from the look-ahead fit (:mod:`torchface.tracker.lookahead`: the first
            frame's pose, expression and held shape units refined against the frames where the head turns 10
            degrees to each side, one side being enough),
            or None for the first frame's landmark fit alone. It reads up to ``lookahead.max_frames`` frames of
            every video of a batch ahead and keeps them in memory (150 frames of 640x480: about 550 MB each).
        max_batch: the most videos tracked together as one batch (videos of one frame size; more of them are
            tracked in several batches, one after another). Every video of a batch is open and in memory at once
            (about four open files each: its input, its CSV and the two videos being written): a run over 1000
            videos of one size held them all, and ran out of file descriptors at the usual ``ulimit -n`` of 1024
            ("Too many open files"). Batches of large frames hold fewer (:data:`BATCH_PIXELS`: 4 videos of
            3840x2160). The results do not depend on it (to float rounding:
            3e-5 mm between one video tracked alone and in a batch of six).
        refine_first: the online look-ahead start (:func:`torchface.tracker.managed.initialise_managed`, as
            :class:`~torchface.tracker.FaceTracker` starts by default), or None. Used when ``lookahead`` is None
            and template management is on. A resumed video that the interrupted run had re-anchored (recorded in
            ``<name>.record.partial`` beside its partial CSV) after ``max_frames`` rows starts from that run's
            refined fit and offset, so its rows go on as an uninterrupted run's (measured: the
            test clip's translations within 3e-5 mm until the template mosaic, which is not restored, is used:
            module docstring; 3-5 mm off when it was resumed from the landmark fit; also when interrupted right
            after the re-anchoring frame, whose row holds the estimate made before the re-anchoring: the record keeps
            the refined parameters the run went on from, 0.08 mm and 0.2 degrees off without them); with fewer rows
            than ``max_frames``, re-anchored or not, it has its rows tracked again from its first frame (module
            docstring), and so re-anchors where the uninterrupted run did, its mosaic built again (byte-identical
            CSVs measured; one not re-anchored went on without the online start: 3-20 mm, 1-2 degrees off on
            rendered clips; a re-anchored one from its record, without its mosaic: up to 8.1 mm, 1.6 degrees); one
            not re-anchored after ``max_frames`` rows goes on without it, as the uninterrupted run did (the batch's
            new videos keep it).
        model: a face model file (``""`` and a ``"~/m.npz"`` nothing expands are refused, as ``out_dir``'s;
            :func:`torchface.model.save_face_model` writes one; loaded in float32 with
            :func:`torchface.model.load_face_model`'s checks before any input is opened) to track with, or None for
            CANDIDE-3 (:func:`torchface.model.load_candide3`). The CSV's animation and FACS columns are the model's
            (:func:`torchface.io.track_columns`), the sidecar's ``model`` names it (``name``, ``file``, ``sha256``:
            :func:`torchface.model.face_model_digest`, and its sizes), and a resume with another model is refused. A
            detector gives the 68 iBUG points: with ``detector`` a model of another landmark count is refused (give
            landmarks files of its own points).
        smoothing: smooth the pose over time (``torchface track --smooth``: :class:`~torchface.tracker.SmoothingConfig`,
            its ``rotation`` and ``translation`` filters, one of them at least; an ``expression`` filter is refused: the
            job smooths the pose only), or None (the default: off, the outputs as without it). The CSV keeps its raw
            columns, which a resumed run replays into the tracker, and appends
            :data:`~torchface.io.table.SMOOTH_COLUMNS`; the overlay and the meshes show the smoothed pose, the
            normalised face is resampled at the raw one. The filter runs on each row as written (replayed rows too: a
            resumed video's filter goes on from the state the interrupted run had), at the frames' times, and starts
            afresh at a video's first tracked row, after an unsuccessful row, after the online start's re-anchoring
            frame and after a row where a re-detection was due (``redetect_after``). The sidecar's ``config.smoothing``
            and the resume record say it; a resume with another setting is refused.
        keep_expression: write the normalised face with the expression kept (``torchface track --keep-expression``):
            resampled at the person's neutral animation coefficients, those the row's ``AUxx_r`` are measured from (the
            first frame's fit, the online start's re-estimate after its re-anchoring frame, a restart's:
            :func:`_neutral_anim`) instead of the row's, pose and light undone as without it, as
            ``training_hooks``' ``FaceTrackingConfig(keep_expression=True)`` does. False (the default): the neutral
            face, the outputs as without it. Only the normalised video depends on it; the sidecar's
            ``config.keep_expression`` and the resume record say it, and a resume with another setting is refused.
        keep_going: go on past inputs that cannot be tracked (``torchface track --keep-going``): an input that the
            checks before tracking refuse (unreadable, empty, a bad first frame or landmarks file, no face found by
            the detector; with ``resume``, rows or complete outputs that cannot be resumed) is skipped with an
            :class:`InputSkipped` warning as it is, and the others are tracked; a video that stops partway is
            returned, not raised (:class:`VideosStopped`). Every input then gets a :class:`VideoSummary`, whose
            ``refused`` or ``stopped`` says why it was not completed. Nothing of a skipped input is written (a
            fresh run removes what earlier runs wrote for it, as for every input; a resumed run leaves its partial
            rows as they were). With ``resume``, a skipped input is checked again (tracked once mended), and a
            partial CSV whose input file has changed since its rows were written (mended; its size or modification
            time: a ``touch`` is enough) is tracked afresh, with a warning, its earlier rows and record kept aside
            (``<stem>.csv.partial.earlier``, ``.earlier-2``, ...: no run removes them), where without ``keep_going``
            the resume is refused. False (the default): the first refused
            input refuses the whole run (every refused input named), nothing tracked. The results of the videos
            tracked do not depend on it.
        fps: the frame rate (frames per second, in (0.001, 1000]) of the inputs that have none of their own (image
            folders, ``.npy`` arrays, a single image, a video whose container gives no plausible rate:
            :func:`torchface.io.open_frames`' ``fps``; ``torchface track --fps``), or None for the default 25: their
            CSV ``timestamp`` is ``frame / fps`` (a container's own frame times are still written where it gives
            them), their overlay and normalised videos run at it, and the sidecar's ``input.fps`` is it, with
            ``input.fps_given`` true and ``fps_assumed`` false. A video that gives its own rate keeps it, with a
            ``UserWarning`` that says ``fps`` was not used for it. Over 1000 frames/s the rows' millisecond
            timestamps would coincide; at 0.001 or less the mp4v overlay cannot be written (a container's rate
            there is taken as none too, with a ``UserWarning``, and ``fps`` is such a video's). The tracking does
            not depend on it (but for ``smoothing``, which runs at the frames' times). A resume with another rate
            for such an input is refused (a partial CSV would hold the rows of two clocks; None is
            :data:`~torchface.io.video.ASSUMED_FPS`, 25, so ``fps=25`` resumes a run without it).
    """

    out_dir: str | os.PathLike[str]
    landmarks: tuple[str | os.PathLike[str], ...] = ()
    detector: str | None = None
    focal: float | None = None
    device: str | torch.device = "cpu"
    resume: bool = False
    convert: bool = False
    meshes: bool = False
    normalised_size: int = 128
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    redetect_after: int = 10
    redetect_below: float = 0.15
    lookahead: LookaheadConfig | None = None
    refine_first: LookaheadConfig | None = field(default_factory=LookaheadConfig)
    max_batch: int = 128
    model: str | os.PathLike[str] | None = None
    smoothing: SmoothingConfig | None = None
    keep_going: bool = False
    keep_expression: bool = False
    fps: float | None = None

    def __post_init__(self) -> None:
        if self.smoothing is not None and not isinstance(self.smoothing, SmoothingConfig):
            raise TypeError(f"smoothing must be a SmoothingConfig or None, got {type(self.smoothing).__name__}"
                            f"{switch_hint(self.smoothing, 'SmoothingConfig')}")  # (smoothing=True, as --smooth)
        if self.smoothing is not None and self.smoothing.expression is not None:
            raise ValueError("smoothing.expression must be None: torchface track smooths the pose only (the rows' "
                             "expression stays raw; ResultSmoother smooths it in Python)")  # fmt: skip
        if self.smoothing is not None and self.smoothing.rotation is None and self.smoothing.translation is None:
            # (the smooth_* columns were written, equal to the raw ones, and the sidecar said the pose was smoothed)
            raise ValueError("smoothing smooths nothing with neither a rotation nor a translation filter: give one "
                             "(SmoothingConfig() has both), or smoothing=None for no smooth_* columns")  # fmt: skip
        if self.model is not None and not isinstance(self.model, (str, os.PathLike)):
            raise TypeError(f"model must be a path to a face model file or None, got {type(self.model).__name__}")
        if isinstance(self.landmarks, (str, bytes, os.PathLike)):  # one path: its characters were taken as files
            raise TypeError(f"landmarks must be a tuple of paths, one per video, e.g. (Path({str(self.landmarks)!r}),)")
        # (the paths: out_dir=None was a TypeError of Path's once the job ran, and out_dir="" the current folder,
        # which the command line refuses as an unset variable's; a list of landmarks files is kept as a tuple)
        _check_path(self.out_dir, "out_dir", "'.' for the current folder")
        check_no_tilde(self.out_dir, "out_dir")  # (nothing expands it: the outputs went to a folder '~' in the
        # working folder, as training_hooks' cache_dir once did)
        if self.model is not None:  # (as training_hooks' FaceTrackingConfig.model: "~/m.npz" was taken, and the job
            # said "~/m.npz: no such face model file"; "" was the current folder, "a folder, not a face model file")
            _check_path(self.model, "model", "a face model file, or None for CANDIDE-3")
            check_no_tilde(self.model, "model")
        try:
            object.__setattr__(self, "landmarks", tuple(self.landmarks))
        except TypeError:
            raise TypeError(f"landmarks must be a tuple of paths, one per video, got {type(self.landmarks).__name__}"
                            ) from None  # fmt: skip
        for k, lm in enumerate(self.landmarks):
            _check_path(lm, f"landmarks[{k}]", "a landmarks file")
            check_no_tilde(lm, f"landmarks[{k}]")  # (as model: "~/lm.csv" was taken, then "no such file" in the job)
        check_refine_first(self.refine_first)
        # (the types of the settings that hold settings or names: a lookahead="yes" was an AttributeError "'str'
        # object has no attribute 'max_frames'" once the videos were opened, a tracker dict a TypeError there)
        if not isinstance(self.tracker, TrackerConfig):
            raise TypeError(f"tracker must be a TrackerConfig, got {type(self.tracker).__name__}")
        if self.lookahead is not None and not isinstance(self.lookahead, LookaheadConfig):
            raise TypeError(f"lookahead must be a LookaheadConfig or None, got {type(self.lookahead).__name__}"
                            f"{switch_hint(self.lookahead, 'LookaheadConfig')}")  # (lookahead=True, as --lookahead)
        for name, start in (("refine_first", _online_start(self)), ("lookahead", self.lookahead)):
            if start is not None:  # (iterations for the tracker's levels: refused once a batch began, or at the turn)
                levels_of(start, self.tracker.num_levels, f"{name}.iterations")
        if self.detector is not None and not isinstance(self.detector, str):
            raise TypeError(f"detector must be a detector name (str) or None, got {type(self.detector).__name__}")
        if not isinstance(self.device, (str, torch.device)):
            raise TypeError(f"device must be a device name (str) or a torch.device, got {type(self.device).__name__}")
        check_device(self.device)  # (it was refused only when the job ran; kept as given: the sidecar writes it)
        object.__setattr__(self, "focal", check_number(self.focal, "focal", "(0, inf)", True, "pixels"))
        fps = check_number(self.fps, "fps", FPS_RANGE, True, "frames per second")
        object.__setattr__(self, "fps", None if fps is None else float(fps))
        # (NaN: every frame counted low, the detector asked without end)
        object.__setattr__(self, "redetect_below", check_number(self.redetect_below, "redetect_below", "(-inf, inf)"))
        for name in ("resume", "convert", "meshes", "keep_going", "keep_expression"):  # "no" was true
            object.__setattr__(self, name, check_bool(getattr(self, name), name))
        for name, low in (("normalised_size", None), ("redetect_after", 0), ("max_batch", 1)):
            object.__setattr__(self, name, check_int(getattr(self, name), name, low))
        if self.normalised_size < 16 or self.normalised_size % 2:  # mp4v keeps even sides: 17 was written 16x16
            raise ValueError(f"normalised_size must be an even number >= 16, got {self.normalised_size}")


def _check_path(path: object, name: str, give: str) -> None:
    """Refuse a :class:`JobConfig` path ``name`` that is not a ``str`` or ``os.PathLike`` (``TypeError``) or is
    empty (``ValueError``, saying to ``give`` what is meant: ``Path("")`` is the current folder)."""
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"{name} must be a path (a str or an os.PathLike), got {type(path).__name__}")
    if os.fspath(path) == "":
        raise ValueError(f"{name} is an empty path (an unset variable?): give {give}")


@dataclass(frozen=True)
class Progress:
    """One progress report: stream ``index`` (of ``count``) named ``name`` has ``done`` of ``total`` frames
    (``total``: the count the input declares, None where unknown; once the video has ended, the frames it had).
    ``searching``: the detector has found no face in the ``done`` frames looked at so far (before any tracking,
    :func:`track_videos` looks for the first frame with a face; ``fps``: the frames looked at per second).
    ``skipped``: (``JobConfig.keep_going``) the input is skipped, not tracked (its last report: a display drops its
    line; ``done`` 0). ``index`` is the input's place among those checked (all of them, but those ``resume`` found
    complete), ``count`` their number."""

    index: int
    count: int
    name: str
    done: int
    total: int | None
    fps: float
    confidence: float
    searching: bool = False
    skipped: bool = False


@dataclass(frozen=True)
class VideoSummary:
    """What :func:`track_videos` did for one video.

    Attributes:
        name: the output stem; input: the input path; outputs: the files written.
        frames: frames in the CSV; lost: frames whose estimate is not usable (``success`` 0: failed, or the
            stream lost); mean_confidence: over all frames.
        fps: this video's frames per second: its tracked frames over the wall time of the batch's per-frame
            loop (tracking plus writing every output) while the video was in the batch, from the loop's start until
            its last frame (the sidecar's ``timings_s.active``; the batch's whole loop, ``timings_s.track``, for the
            videos that ended last). The streams of one batch share that time: where its videos have one length
            and none was resumed the batch runs at the sum of their ``fps``; the batch's own rate is the sidecar's
            ``timings_s.batch_fps`` (its frames over its loop's time). Resumed, its rows tracked again for the
            online start count as tracked frames, the rows replayed from its CSV, only drawn, do not. skipped: True
            when ``resume`` found it complete (not tracked again; another sense than :class:`Progress`'s
            ``skipped``, an input that ``keep_going`` could not track, whose summary has ``refused`` or ``stopped``
            set).
        declared_frames: the frame count the input declares (a video container's), when known and the frames
            decoded fell short of it (a truncated or damaged file); None otherwise.
        refused: with ``JobConfig.keep_going``, why the input was skipped without being tracked: the error that
            refuses the run without it (:class:`InputError`'s message: ``"a.mp4: ..."``); nothing of it was written
            (``outputs`` empty, ``frames`` and ``lost`` 0, ``mean_confidence`` and ``fps`` 0.0). None otherwise.
        stopped: with ``JobConfig.keep_going``, why the video stopped partway (the error :class:`VideosStopped`
            says without it: a frame that could not be read, ...); ``outputs`` holds its partial CSV, whose complete
            rows ``frames``, ``lost`` and ``mean_confidence`` count (``fps`` 0.0), kept for ``resume``; its other
            outputs were not written. None otherwise.
        not_met_again: with ``resume``, how many of the rows kept from the interrupted run that this run tracked
            again for the online start it did not meet again (a ``RuntimeWarning`` said so; the sidecar's
            ``resumed`` says by how much); the video is complete all the same. 0 otherwise.
        start_failure: why the video's start failed, the :class:`~torchface.tracker.step.StartFailure` name that the
            sidecar's ``start.failure`` holds (``"TOO_FEW_POINTS"``, ...; a detector's restart may have started it
            since: :attr:`no_tracked_frame` says whether any row was tracked); None where it started, and for a
            video ``refused`` or ``stopped``.
    """

    name: str
    input: Path
    outputs: tuple[Path, ...]
    frames: int
    lost: int
    mean_confidence: float
    fps: float
    skipped: bool = False
    declared_frames: int | None = None
    refused: str | None = None
    stopped: str | None = None
    not_met_again: int = 0
    start_failure: str | None = None

    @property
    def complete(self) -> bool:
        """Whether the video's outputs are complete: tracked by this run, or found complete by ``resume``
        (``skipped``); False for a video ``refused`` or ``stopped``."""
        return self.refused is None and self.stopped is None

    @property
    def no_tracked_frame(self) -> bool:
        """Whether the video is complete but none of its rows is usable (``lost == frames``: every row ``success``
        0), as where its start failed (:attr:`start_failure`: a black first frame, landmarks no face fits) and no
        detector started it afresh: its outputs are written, with nothing tracked in them. ``torchface track``
        exits with status 3 where any video is such (a video with one usable row or more is not; one of no frames,
        which the job refuses before tracking, is not either)."""
        return self.complete and self.frames > 0 and self.lost >= self.frames


class InputSkipped(UserWarning):
    """Warned (one per input) by :func:`track_videos` with ``JobConfig.keep_going`` as it skips an input that cannot
    be tracked, or as a video stops partway (its :class:`VideoSummary`'s ``refused`` and ``stopped`` say it too);
    ``torchface track --keep-going`` prints it as one line ``torchface: warning: skipped ...``."""


#: :attr:`VideosStopped.reasons` of a video stopped at a frame that could not be read.
UNREADABLE_FRAME = "stopped at a frame that could not be read"


class VideosStopped(InputError):
    """Some videos stopped partway: at a frame that could not be read, or, resumed, at a replayed row whose
    ``timestamp`` is not its frame's time (:func:`_check_replayed_time`); raised by :func:`track_videos` once every
    other video is complete (their rows so far are kept in ``<stem>.csv.partial``).

    Attributes:
        summaries: the :class:`VideoSummary` of every other video (completed, or skipped by ``resume``), in input
            order: what the run would have returned for them.
        stopped: the output names of the videos that stopped, in input order.
        reasons: why each of them stopped (``"stopped at a frame that could not be read"``, ...), in that order.
        names: the output names of every input, in input order (the videos stopped among the others: ``torchface
            track``'s summary lists them in that order); empty where not given.
    """

    def __init__(
        self, message: str, summaries: Sequence[VideoSummary], stopped: Sequence[str], reasons: Sequence[str] = (),
        names: Sequence[str] = (),
    ) -> None:
        super().__init__(message)
        self.summaries = list(summaries)
        self.stopped = tuple(stopped)
        self.reasons = tuple(reasons) or (UNREADABLE_FRAME,) * len(self.stopped)
        self.names = tuple(names)


class _ReplayedTimeError(InputError):
    """A resumed video's replayed row whose ``timestamp`` is not its frame's time (:func:`_check_replayed_time`)."""

    reason = "stopped resuming at a row whose timestamp is not its frame's time"


def output_paths(out_dir: Path, name: str) -> dict[str, Path]:
    """The output files of video ``name`` in ``out_dir``, by kind."""
    return {
        "csv": out_dir / f"{name}.csv",
        "json": out_dir / f"{name}.json",
        "overlay": out_dir / f"{name}_overlay.mp4",
        "plot": out_dir / f"{name}_plot.png",
        "normalised": out_dir / f"{name}_normalised.mp4",
        "meshes": out_dir / f"{name}_meshes",
    }


def output_name(video: str | os.PathLike[str]) -> str:
    """The stem of video ``video``'s outputs: a file's stem, a folder's name (``.`` and ``..`` resolved first).

    Raises:
        InputError: the path names no folder or file (the file system's root).
    """
    path = Path(video)
    if path.is_dir():
        name = Path(os.path.abspath(path)).name  # '.' and '..' made absolute; symbolic links keep their name
    else:
        name = path.stem
    if not name:
        raise InputError(f"{video}: cannot name outputs after this input; give a folder or file with a name")
    return name


def demo_inputs() -> tuple[Path, Path]:
    """``(video, landmarks)`` of the embedded demo clip (GRID ``bbaf2n``, see :data:`DEMO_ATTRIBUTION`)."""
    root = Path(str(resources.files("torchface") / "data" / "grid"))
    return root / "bbaf2n.mpg", root / "bbaf2n_landmarks68.csv"


#: The longest gap (seconds of slots that no frame reached) that a timed video (:class:`_VideoOut`, the overlay) fills
#: with the frame before it. A longer one is not the input's frames further apart (a phone's variable rate: tens of
#: milliseconds; a camera that stalled: a few seconds) but a broken time: a container's time far ahead, MPEG-TS
#: streams concatenated (their clocks restart elsewhere), where filling it wrote ``fps`` copies of one frame per second
#: of the jump (an hour's: 90,000 frames at 25 frames/s, gigabytes of 1080p). Such a gap is left out: the next frame
#: goes to the next slot, and the later frames' slots count on from there.
OVERLAY_MAX_GAP_S: float = 10.0


#: Frames queued to a video's encoding thread (:class:`_Encoder`) at most (a 1080p frame is 6 MB; the frames of a gap
#: the overlay fills are one array): a step gives each video one frame, which its thread has encoded long before the
#: next step's (4.5 ms a 1080p frame); 0: no thread, each frame written as it is given.
ENCODE_QUEUE: int = 2


class _Encoder:
    """Writes the frames given to a ``cv2.VideoWriter`` in a thread of its own (the encoding, 4.5 ms a 1080p ``mp4v``
    frame, overlaps the tracking of the next one: OpenCV releases the GIL), at most :data:`ENCODE_QUEUE` frames
    waiting (the thread started at the first). The writer is the encoder's until :meth:`finish` or :meth:`stop`, which
    join the thread; an error in it (none is known: OpenCV's writer ignores write errors) is raised at the next
    :meth:`write` or at :meth:`finish`.
    """

    def __init__(self, writer: cv2.VideoWriter, name: str) -> None:
        self.writer = writer
        self._queue: queue.Queue[np.ndarray | None] = queue.Queue(ENCODE_QUEUE)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name=f"torchface encoder {name}", daemon=True)
        self._sync = ENCODE_QUEUE <= 0  # (the thread started at the first frame: a video given none has none)

    def _run(self) -> None:
        while (image := self._queue.get()) is not None:
            if self._error is None:  # (after an error the frames are taken and dropped: the caller never blocks)
                try:
                    self.writer.write(image)
                except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
                    self._error = exc

    def _raise(self) -> None:
        if self._error is not None:
            raise self._error

    def write(self, image: np.ndarray) -> None:
        """Queue one frame (the caller does not change it afterwards); waits while the queue is full."""
        self._raise()
        if self._sync:
            self.writer.write(image)
            return
        if self._thread.ident is None:
            self._thread.start()
        self._queue.put(image)

    def finish(self) -> None:
        """Write the frames queued, then end the thread (the error of one that failed raised)."""
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
        self._raise()

    def stop(self) -> None:
        """End the thread without writing the frames still queued (an interrupted run's: its file is removed)."""
        with contextlib.suppress(queue.Empty):
            while True:
                self._queue.get_nowait()
        if self._thread.is_alive():
            self._queue.put(None)  # (the queue is empty: only this thread puts)
            self._thread.join()


class _VideoOut:
    """An ``mp4v`` MP4 at ``fps`` frames/s written to ``<name>.partial.mp4`` and renamed on :meth:`close`.

    Written one frame per :meth:`write`, or, with ``timed``, in step with the input's time (what ffmpeg's
    ``-vsync cfr`` does): each frame goes to the slot of its time (``round((time - first time) * fps)``, the first
    frame's slot 0), the previous frame repeated into the slots before it that no frame reached (:attr:`duplicated`),
    and a frame whose slot is written already left out of it (:attr:`dropped`: those shown nowhere), but shown in a
    gap right after it, as the input's previous frame (the gap showed the frame written before it, older, and the
    left-out frame nowhere). A constant-rate input's frames (times ``k / fps``, within half a frame) are written one
    each, as without ``timed``; a variable-frame-rate one's (a phone's) play at their times, where one frame per slot
    at the nominal rate ran ahead of the input wherever its frames were further apart (a 30 -> 15 frames/s stretch
    played twice as fast). A gap longer than :data:`OVERLAY_MAX_GAP_S` (a broken time) is not filled
    (:attr:`skipped_gaps`, :attr:`skipped_s`; a ``RuntimeWarning`` at the first): the frame goes to the next slot
    (after one showing a frame left out of its slot), the later frames' slots counted on from it.
    """

    def __init__(self, path: Path, width: int, height: int, fps: float, timed: bool = False) -> None:
        self.path = path
        self.tmp = path.with_name(path.stem + ".partial" + path.suffix)
        self.size = (int(width), int(height))
        self.fps = float(fps)
        self.timed = timed
        self.frames = 0  # written to the file (duplicates included)
        self.duplicated = 0  # (timed) slots filled with the previous frame again
        self.dropped = 0  # (timed) frames not shown: their slot was written already, and no gap followed them
        self.skipped_gaps = 0  # (timed) gaps longer than OVERLAY_MAX_GAP_S, not filled
        self.skipped_s = 0.0  # (timed) the seconds of slots they would have filled
        self._origin: float | None = None  # (timed) the time of slot 0 (the first frame's; moved on by a skipped gap)
        self._last: np.ndarray | None = None  # (timed) the last frame given, repeated into a gap
        self._shown = True  # (timed) whether _last is in the file (False: left out of its slot)
        fourcc = cv2.VideoWriter.fourcc(*"mp4v")
        writer = cv2.VideoWriter(opencv_path(self.tmp, OutputError), fourcc, float(fps), self.size)
        if not writer.isOpened():
            writer.release()
            self.tmp.unlink(missing_ok=True)
            raise OutputError(f"{self.tmp}: cannot open an mp4v video writer")
        self.writer: cv2.VideoWriter | None = writer  # None once closed or aborted
        self._encoder = _Encoder(writer, self.path.name)  # (the writer's frames written by its thread)

    def write(self, image_bgr: np.ndarray, time: float | None = None) -> None:
        """Write one frame (``(H, W, 3)`` uint8 BGR); ``time``: its input's time in seconds, which places it in a
        ``timed`` video (ignored otherwise; required there)."""
        if self.writer is None:
            raise ValueError(f"{self.path}: the video is closed")
        if self.timed:
            if time is None or not math.isfinite(time):
                raise ValueError(f"{self.path}: a frame of a timed video needs its time, got {time}")
            if self._origin is None:
                self._origin = time
            slot = math.floor((time - self._origin) * self.fps + 0.5)
            if slot - self.frames > OVERLAY_MAX_GAP_S * self.fps:  # a broken time, not a gap to fill
                slot = self._skip_gap(slot, time)
            if slot < self.frames:  # (its slot holds an earlier frame)
                self.dropped += 1
                self._last, self._shown = image_bgr, False  # (the input shows it from its time on)
                return
            while self.frames < slot and self._last is not None:  # (a gap: the previous frame shown on)
                self._encoder.write(self._last)
                self.frames += 1
                if self._shown:
                    self.duplicated += 1
                else:  # (one left out of its slot, shown in the gap after it)
                    self.dropped -= 1
                    self._shown = True
            self._last, self._shown = image_bgr, True
        self._encoder.write(image_bgr)
        self.frames += 1

    def _skip_gap(self, slot: int, time: float) -> int:
        """The slot of a frame at ``time`` whose own ``slot`` is more than :data:`OVERLAY_MAX_GAP_S` ahead: the next
        one (after one showing the frame before it, where that was left out of its slot); slot 0's time moved so that
        the later frames' slots count on from it. Warned once per video."""
        new = self.frames + (0 if self._shown else 1)
        self.skipped_gaps += 1
        self.skipped_s += (slot - new) / self.fps
        if self.skipped_gaps == 1:
            warnings.warn(f"{self.path}: the input's time jumps {(slot - new) / self.fps:.1f} s ahead at {time:.3f} s "
                          f"(a broken time, or streams joined): gaps over {OVERLAY_MAX_GAP_S:g} s are not filled, the "
                          "overlay goes on at the next frame (the sidecar's videos.overlay.skipped_gaps)",
                          RuntimeWarning, stacklevel=4)  # fmt: skip
        self._origin = time - new / self.fps
        return new

    def close(self) -> None:
        """Rename the video to its final name once it reads back whole (OpenCV's writer ignores write errors:
        on a full disk it leaves a truncated file without its index).

        Raises:
            OutputError: the written file does not read back with every frame (the partial file is removed).
        """
        if self.writer is not None:
            try:
                self._encoder.finish()
            except BaseException:
                self.abort()
                raise
            self.writer.release()
            self.writer = None
            readback = cv2.VideoCapture(str(self.tmp))
            try:
                count = int(readback.get(cv2.CAP_PROP_FRAME_COUNT)) if readback.isOpened() else -1
            finally:
                readback.release()
            if count != self.frames:
                with contextlib.suppress(OSError):  # (a folder gone read-only: the error says why, not this)
                    self.tmp.unlink(missing_ok=True)
                raise OutputError(f"{self.path}: the video could not be written completely "
                                  f"({counted(self.frames, 'frame')} written, {max(count, 0)} read back; is the disk "
                                  "full?)")  # fmt: skip
            os.replace(self.tmp, self.path)

    def abort(self) -> None:
        """Stop unfinished, the partial file removed where it can be. Never raises ``OSError``: on a folder that has
        become read-only (a file system remounted so after an I/O error) the clean-up's error replaced the one that
        stopped the run, and left the other videos' writers open."""
        if self.writer is not None:
            self._encoder.stop()
            self.writer.release()
            self.writer = None
        with contextlib.suppress(OSError):
            self.tmp.unlink(missing_ok=True)


#: Frames each video's reading thread (:class:`_ReadAhead`) holds decoded and converted ahead of the tracking at most,
#: in batches of at most :data:`READ_AHEAD_STREAMS` videos; 0: no thread, each frame read when it is needed.
READ_AHEAD: int = 1
#: The most videos of a batch that are read by threads of their own (:data:`READ_AHEAD`): a thread and
#: :data:`READ_AHEAD` frames more in memory per video (a 640x480 frame and its 8-bit image take 4.6 MB, 1080p 31 MB),
#: where a large batch's memory is mostly its frames; its videos are read in the tracking's thread.
READ_AHEAD_STREAMS: int = 4


class _ReadAhead:
    """A :class:`~torchface.io.video.FrameReader` read by a thread of its own, up to :data:`READ_AHEAD` frames ahead
    of the tracking: the decoding and the conversion to a float frame (about 1.3 ms of CPU a 640x480 frame, 8 ms at
    1080p) overlap the tracking of the frame before (OpenCV and torch release the GIL). Gives what the
    reader gives: the frames (``next``), each one's :attr:`timestamp` and :attr:`image`, the reader's :attr:`info`,
    and the error that ended its reading (``StopIteration`` at its end, an :class:`InputError` at a bad frame) at the
    frame where the reader raised it, and again at every later ``next``. The reader is the thread's until
    :meth:`close`, which ends the thread (dropping the frames read ahead) and closes the reader.
    """

    def __init__(self, reader: FrameReader) -> None:
        self.reader = reader
        self.info = reader.info
        self.timestamp: float | None = None  # (FrameReader.timestamp of the last frame given)
        self.image: np.ndarray | None = None  # (FrameReader.image of the last frame given)
        self._queue: queue.Queue[tuple[Tensor, float | None, np.ndarray | None] | BaseException] = queue.Queue(
            max(READ_AHEAD, 1))
        # A frame is read only into a free place of the queue (taken before, given back by ``next``): a thread that
        # read its next frame while it waited on a full queue held READ_AHEAD + 1 frames ahead (a 1080p video's
        # reader 2 x 31 MB, not 31).
        self._free = threading.Semaphore(max(READ_AHEAD, 1))
        self._end: BaseException | None = None  # what ended the reading, once given
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"torchface reader {reader.info.path}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            self._free.acquire()  # (close() gives one back: the thread then sees _stop)
            if self._stop.is_set():
                return
            item: tuple[Tensor, float | None, np.ndarray | None] | BaseException
            try:
                item = (next(self.reader), self.reader.timestamp, self.reader.image)
            except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread at its frame
                item = exc
            self._queue.put(item)  # (never waits: the place was taken above)
            if isinstance(item, BaseException):
                return

    def __iter__(self) -> "_ReadAhead":
        return self

    def __next__(self) -> Tensor:
        if self._end is not None:
            raise self._end
        if self._stop.is_set():  # closed: no more frames, as a closed FrameReader
            raise StopIteration
        item = self._queue.get()
        self._free.release()
        if isinstance(item, BaseException):
            self._end = item
            raise item
        frame, self.timestamp, self.image = item
        return frame

    def close(self) -> None:
        """End the thread (the frames read ahead dropped) and close the reader; the reader gives no more frames."""
        self._stop.set()
        self._free.release()  # (a thread waiting for a free place wakes and ends; one reading ends after that frame)
        self._thread.join()
        with contextlib.suppress(queue.Empty):
            while True:
                self._queue.get_nowait()
        self.image = None
        self.reader.close()


def _frame_meshes(folder: Path) -> list[Path]:
    """The per-frame meshes a run wrote in ``folder`` (``NNNNNN.ply``, six or more digits), not other files."""
    return [f for f in folder.glob("*.ply") if re.fullmatch(r"\d{6,}\.ply", f.name) and f.is_file()]


#: Suffixes of files a run writes or reads (the inputs' videos, arrays and images, and its outputs' and landmarks'
#: files): an output folder not made yet that ends in one (``--out results.csv``) is likely meant as a file, and is
#: warned of (:func:`_check_out_dir`; made all the same: a folder may be so named).
_FILE_SUFFIXES: frozenset[str] = frozenset(
    VIDEO_SUFFIXES + IMAGE_SUFFIXES + (".csv", ".json", ".txt", ".pts", ".ply", ".obj")
)


def _check_out_dir(out_dir: Path) -> None:
    """Refuse an output folder that cannot be made or written (:class:`OutputError`), before anything is tracked;
    make it where it is missing, with a ``UserWarning`` where its name ends in a file's suffix (``results.csv``: a
    folder of that name was made without a word, each video's outputs inside it)."""
    a = dangling_link(out_dir)  # mkdir said only "File exists" (also for a link above the folder)
    if a is not None:
        where = "the output folder" if a == out_dir else f"a folder above {out_dir}"
        raise OutputError(f"{a}: {where} is a symbolic link to {os.readlink(a)}, which does not exist")
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputError(f"{out_dir}: the output folder is a file, not a folder")
    opencv_path(out_dir, OutputError)  # the videos are written by OpenCV
    if out_dir.suffix.lower() in _FILE_SUFFIXES and not out_dir.exists():
        warnings.warn(f"{out_dir}: the output folder's name ends in {out_dir.suffix}, as a file's: made as the "
                      f"folder {out_dir}/, which gets each video's outputs (<stem>.csv, <stem>.json, ...), not one "
                      "file", UserWarning, stacklevel=3)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{out_dir}: cannot create the output folder ({exc.strerror or exc})") from None
    probe = out_dir / f".torchface-write-test-{os.getpid()}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise OutputError(f"{out_dir}: output folder is not writable ({exc.strerror or exc})") from None


def _lock_owner(path: Path) -> tuple[int, str] | None:
    """``(pid, host)`` that the lock file ``path`` names (:func:`_take_locks`); None where it names none (not a
    lock of this job, or one whose run has created it and not yet written it, or a damaged one: a pid that no
    process can have, under 1 or 2**31 and over, which ``os.kill`` met with an ``OverflowError`` traceback)."""
    try:
        pid, host = path.read_text(encoding="utf-8").split(maxsplit=1)
        number = int(pid)
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    return (number, host.strip()) if 0 < number < 2**31 else None


def _alive(pid: int) -> bool:
    """Whether process ``pid`` of this host exists (one of another user's too; on Windows :func:`_alive_windows`).
    Unlike its near-twin :func:`torchface._atomic._running` (True where it cannot tell: on Windows, a lock of a run
    that ended would never be taken over, every later run refused), it tells on Windows too, and asks ``os.kill`` of
    the lock's pid as it is: 0 and -1 (a process group, every process) are True, another negative one False, and one
    too large for ``os.kill`` raises ``OverflowError`` (:func:`_lock_owner` gives it none of those: a lock naming
    one names no process)."""
    if sys.platform == "win32":  # (os.kill(pid, 0) there sends CTRL_C_EVENT, or terminates the process)
        return _alive_windows(pid)
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):  # another user's: it exists
        return True
    return True


def _alive_windows(pid: int) -> bool:
    """Whether process ``pid`` is running, on Windows: opened for a query (``OpenProcess``), its exit code is
    ``STILL_ACTIVE``; one that cannot be opened is not there (``ERROR_INVALID_PARAMETER``), or is another user's
    (access denied: running). A process that exited with code 259 (``STILL_ACTIVE``) is taken as running: its lock
    is left alone, as before, not taken over. (Every lock was left alone there: a run killed in the Task Manager, or
    a crash, left its lock, and every later run was refused until it was removed by hand.)"""
    import ctypes
    from ctypes import wintypes

    kernel32 = ctypes.WinDLL("kernel32", use_last_error=True)  # type: ignore[attr-defined,unused-ignore]
    kernel32.OpenProcess.argtypes = (wintypes.DWORD, wintypes.BOOL, wintypes.DWORD)
    kernel32.OpenProcess.restype = wintypes.HANDLE
    kernel32.GetExitCodeProcess.argtypes = (wintypes.HANDLE, ctypes.POINTER(wintypes.DWORD))
    kernel32.GetExitCodeProcess.restype = wintypes.BOOL
    kernel32.CloseHandle.argtypes = (wintypes.HANDLE,)
    kernel32.CloseHandle.restype = wintypes.BOOL
    query_limited_information, still_active, invalid_parameter = 0x1000, 259, 87
    handle = kernel32.OpenProcess(query_limited_information, False, pid)
    if not handle:
        return ctypes.get_last_error() != invalid_parameter  # type: ignore[attr-defined,unused-ignore]
    try:
        code = wintypes.DWORD()
        if not kernel32.GetExitCodeProcess(handle, ctypes.byref(code)):
            return True  # (not known: left alone)
        return code.value == still_active
    finally:
        kernel32.CloseHandle(handle)


#: Seconds after which an empty lock file is taken as left by a run that ended as it created it (its run writes
#: its pid and host into it at once: killed in between, or a machine that crashed before the file reached the
#: disk, leaves it empty, and every later run was refused, "another run is writing", until it was removed by hand).
EMPTY_LOCK_S: float = 10.0


def _ended_lock(owner: tuple[int, str] | None, seen: os.stat_result) -> str | None:
    """How a lock file (``owner``, :func:`_lock_owner`, and ``seen``, its ``stat``) was left by a run that has
    ended, for the warning that takes it over; None where its run may still be going on (a process of this host
    that exists, another host's, a file that names no process and is not empty)."""
    if owner is None:
        if seen.st_size == 0 and time.time() - seen.st_mtime > EMPTY_LOCK_S:
            return f"a run that ended as it created it (the lock is empty, {EMPTY_LOCK_S:g} s after it was made)"
        return None
    if owner[1] == socket.gethostname() and not _alive(owner[0]):
        return f"a run that has ended (pid {owner[0]})"
    return None


def _take_locks(out_dir: Path, names: Sequence[str]) -> list[Path]:
    """Lock the outputs of videos ``names`` in ``out_dir`` against another run (two runs writing one video's
    outputs at once corrupted each other's CSV, or one deleted what the other was writing): ``<name>.lock``,
    created exclusively (``O_EXCL``) holding this process's pid and host. A lock whose process has ended (a run
    killed with SIGKILL, a machine that crashed), or an empty one older than :data:`EMPTY_LOCK_S` (a run that ended
    before it wrote its lock), is taken over, with a :class:`RuntimeWarning` naming it; a lock of a process still
    running (or of another host, or that names no process) is an :class:`OutputError` naming it. Returns the locks
    taken (:func:`_release_locks` removes them; those taken before an error are removed).
    """
    me = f"{os.getpid()} {socket.gethostname()}\n"
    taken: list[Path] = []
    try:
        for name in names:
            path = out_dir / f"{name}.lock"
            for _ in range(10):  # (a lock that comes and goes meanwhile: look again)
                try:
                    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
                except FileExistsError:
                    try:
                        seen = path.stat()
                    except FileNotFoundError:  # (released meanwhile)
                        continue
                    owner = _lock_owner(path)
                    ended = _ended_lock(owner, seen)
                    if ended is None:
                        who = "another run" if owner is None else f"another run (pid {owner[0]} on {owner[1]})"
                        raise OutputError(f"{path}: {who} is writing the outputs of {name} in {out_dir}: wait for it "
                                          "to end, or give another --out (or remove this file if no torchface run "
                                          "is writing there)") from None  # fmt: skip
                    stale = path.with_name(f"{path.name}.{os.getpid()}.stale")
                    try:  # (moved aside first: of two runs taking it over at once, one moves it)
                        os.replace(path, stale)
                    except FileNotFoundError:
                        continue
                    except OSError as exc:  # (a folder with the sticky bit, and the lock another user's)
                        raise OutputError(f"{path}: cannot take over the lock of {ended} ({exc.strerror or exc}): "
                                          "remove it") from None  # fmt: skip
                    moved = stale.stat()
                    if _lock_owner(stale) != owner or (moved.st_ino, moved.st_mtime_ns) != (seen.st_ino,
                                                                                            seen.st_mtime_ns):
                        os.replace(stale, path)  # another run's new lock, moved by mistake: put back
                        continue
                    stale.unlink(missing_ok=True)
                    warnings.warn(f"{path}: taking over the lock of {ended}: its partial outputs are resumed or "
                                  "replaced as this run's", RuntimeWarning, stacklevel=3)  # fmt: skip
                    continue
                except OSError as exc:
                    raise OutputError(f"{path}: cannot create the lock file ({exc.strerror or exc})") from None
                taken.append(path)
                try:
                    os.write(fd, me.encode("utf-8"))
                except OSError as exc:  # (a full disk: no empty lock left behind, below)
                    raise OutputError(f"{path}: cannot write the lock file ({exc.strerror or exc})") from None
                finally:
                    os.close(fd)
                break
            else:
                raise OutputError(f"{path}: cannot take the lock, other runs keep taking and releasing it")
    except BaseException:
        _release_locks(taken)
        raise
    return taken


def _release_locks(locks: Sequence[Path]) -> None:
    """Remove the locks :func:`_take_locks` took, those that are still this run's (a lock removed by hand while
    the run went on, and taken by another run, is that run's); never raises ``OSError``: a folder gone read-only
    keeps them, and the next run takes them over, their process having ended."""
    mine = (os.getpid(), socket.gethostname())
    for path in locks:
        with contextlib.suppress(OSError):
            if _lock_owner(path) in (mine, None):  # (None: this run's, not written: a full disk, an interruption)
                path.unlink()


def _written_names(name: str) -> list[str]:
    """Every file name the job writes for video ``name``, final and temporary (``.partial``, ``.tmp``)."""
    return [f"{name}.csv.partial.tmp", f"{name}.record.partial.tmp", f"{name}.json.partial", f"{name}.lock",
            f"{name}_overlay.partial.mp4", f"{name}_normalised.partial.mp4", f"{name}_plot.partial.png",
            f"{name}_meshes.partial", f"{name}.state.partial.tmp"]  # fmt: skip


def _check_name_lengths(out_dir: Path, videos: Sequence[Path], names: Sequence[str]) -> None:
    """Refuse, before anything is written, an input whose outputs' names the output folder's file system cannot
    hold (a name near 255 bytes: the outputs add up to 23 bytes to it)."""
    try:
        limit = os.pathconf(out_dir, "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):  # not POSIX, or the file system does not say
        limit = 255
    for v, name in zip(videos, names):
        longest = max(_written_names(name), key=lambda n: len(os.fsencode(n)))
        if len(os.fsencode(longest)) > limit:
            spare = limit - (len(os.fsencode(longest)) - len(os.fsencode(name)))
            raise OutputError(f"{v}: its outputs' names would be too long for {out_dir} ({longest!r} is "
                              f"{len(os.fsencode(longest))} bytes, at most {limit}): rename the input to at most "
                              f"{spare} bytes before its extension")  # fmt: skip


def _frame_bgr(frame: Tensor, image: np.ndarray | None) -> np.ndarray:
    """What :func:`_to_uint8_bgr` makes of a frame read from ``image`` (its ``FrameReader.image``; None: not known),
    without converting it: ``image`` itself, whose values the frame's give back exactly in float32 and float64
    (the conversion took 9 ms a 1080p frame in a run)."""
    if image is not None and frame.dtype in (torch.float32, torch.float64) and image.shape[:2] == frame.shape[-2:]:
        return image
    return _to_uint8_bgr(frame)


def _to_uint8_bgr(frame: Tensor) -> np.ndarray:
    """``(3, H, W)`` float RGB in ``[0, 1]`` -> a contiguous ``(H, W, 3)`` uint8 BGR image, as
    ``cv2.cvtColor(detector_image(frame), cv2.COLOR_RGB2BGR)`` gives it, three times faster (the planes merged in
    their new order: the conversion of a strided RGB view took 16 ms a 1080p frame, this 4)."""
    planes = _uint8_planes(frame)
    return cv2.merge([planes[2], planes[1], planes[0]])


#: A stream's re-anchoring as its record keeps it (:func:`_record_anchors`): a JSON object of number lists
#: (``axis_angle``, ``translation``, ``head_rotation``, ...), the ``frame`` index (int) and ``first_shape_coeffs``,
#: ``params`` (lists or None).
_Anchor = dict[str, Any]


@dataclass(eq=False)
class _Stream:
    """Book-keeping of one video in a batch (mutable, private to the job loop)."""

    name: str
    reader: FrameReader | _ReadAhead  # (_ReadAhead: a batch's, while it is tracked)
    landmarks: np.ndarray
    landmarks_source: str
    total: int | None
    csv: TrackCsvWriter | None = None
    overlay: _VideoOut | None = None
    normalised: _VideoOut | None = None
    replay: np.ndarray | None = None  # rows already in the CSV when resuming
    # resumed within the online start's frames (fewer rows than its max_frames, re-anchored or not): its replayed
    # rows are tracked again from its first frame (not written, checked against the CSV's: _retracked_gap), not
    # put into the state from the CSV, so that it re-anchors where the uninterrupted run did (its anchor cleared
    # and recorded again) and builds its mosaic again
    retrack: bool = False
    # the largest gap of its rows tracked again from the CSV's: (mm, degrees, confidence, frame of the largest
    # translation gap (its first tracked frame where there is none), first frame whose status or success differs (or
    # None))
    retrack_gap: tuple[float, float, float, int, int | None] = (0.0, 0.0, 0.0, 0, None)
    tracked_again: int = 0  # its rows tracked again so far (counted as tracked frames: timings_s.fps)
    not_met_again: int = 0  # of them, those not met again (RETRACK_TOLERANCE; the sidecar's resumed)
    # seconds of the loop spent on its rows replayed from the CSV (redrawn; tracked again not): timings_s.replay,
    # left out of its fps (timings_s.fps: the frames tracked in this run over the time spent tracking them)
    t_replay: float = 0.0
    # seconds from the loop's start until it left the batch (its video ended: the batch's per-frame loop time it was
    # in, timings_s.active; None while it is in it): its fps is its frames over this time, not over the whole loop's
    t_active: float | None = None
    frames: int = 0
    tracked: int = 0
    done: bool = False
    last_frame: Tensor | None = None
    low_count: int = 0
    anchor: _Anchor | None = None  # the online start's re-anchoring, once recorded (_write_record)
    settings: dict[str, object] = field(default_factory=dict)  # what its rows depend on (_settings), in the record
    first_shape: list[float] | None = None  # the shape coefficients its first rows were tracked with
    first_neutral: list[float] | None = None  # the neutral animation coefficients of its first rows (their AUxx_r's)
    redetections: int = 0
    detector_calls: int = 0  # the detector asked about its frames (first frame, re-detections, recoveries)
    detection_warned: bool = False  # a re-detection's unusable landmarks were warned about (once per video)
    # the last replayed row (its t) after which a re-detection was due, its detector not asked again (the next rows
    # hold what it gave): the motion prediction's run of steady frames starts after it (_with_replayed_motion)
    replayed_redetection: int | None = None
    # a re-detection was due after its last row (asked or replayed): the pose smoothing starts afresh at its next row
    smooth_restart: bool = False
    near: np.ndarray | None = None  # (N, 2) the face's last confident pixel position: a re-detection's `near`
    confidence: float = 0.0  # its last frame's (for the progress line; nothing per frame is kept in memory)
    ahead: list[Tensor] = field(default_factory=list)  # frames read ahead (look-ahead start), next first
    # its first frame as _next_frame gives it (frame, time, 8-bit image), read by its check, its reader left open at
    # it (_open_inputs: an input of the first batch): _reopen goes on from it instead of decoding it again
    held: tuple[Tensor, float, np.ndarray | None] | None = None
    error: InputError | None = None  # a frame that could not be read: the video stops there, the batch goes on
    refused: str | None = None  # (keep_going) why it was skipped as its batch opened: nothing of it tracked
    index: int = 0  # its place among the inputs checked (Progress.index)
    # its shape coefficients and neutral animation coefficients in the state after its last frame (taken when its
    # stream leaves the batch's state: the sidecar's model.shape_coeffs and start.neutral_anim_coeffs)
    final_shape: list[float] | None = None
    final_neutral: list[float] | None = None
    # the first frame tracked: the first where the detector found a face (0: the first frame). The tracking loop
    # counts frames from it (its stream's t = frame - start); the rows before it have no estimate (_no_face_row)
    start: int = 0
    # why its start (at frame ``start``) failed, NONE where it started (TrackResult.start_failure): the warning's
    # reason and the sidecar's start.failure
    start_failure: StartFailure = StartFailure.NONE
    # the detector's restarts of its lost stream that failed, counted by StartFailure name (TrackResult.start_failure
    # of managed_step; the rows replayed from a CSV: none, but a checkpoint's counts, _restore_streams): the
    # sidecar's restart_failures
    restart_failures: dict[str, int] = field(default_factory=dict)
    # the times (seconds, FrameReader.timestamp) of the frames read and not yet written: last_frame's, then ahead's
    stamps: deque[float] = field(default_factory=deque)
    # and their 8-bit BGR images as read (FrameReader.image; None: drawn from the frame converted back), which the
    # overlay draws on
    images: deque[np.ndarray | None] = field(default_factory=deque)
    # with --lookahead: the frames its first fit was refined against (lookahead_fit's keyframes, counted as its rows
    # are); empty: its head did not turn (to min_keyframes sides) within the frames read ahead, and it starts from
    # the landmark fit
    keyframes: list[int] = field(default_factory=list)
    # its last row as written (read back: as the CSV holds it), which its checkpoint keeps (_write_checkpoints)
    last_row: np.ndarray | None = None
    # resumed: its checkpoint's data (_load_checkpoint; its states read again by _joined), which its batch's state is
    # put together from after its last row, and whether it was (the sidecar's resumed.checkpoint): "exact", with
    # its whole batch as it was (its rows the uninterrupted run's), "split", in a part of it (a smaller --max-batch,
    # some of its videos skipped or stopped: its rows the uninterrupted run's to float rounding), or False
    checkpoint: dict | None = None
    from_checkpoint: Literal["exact", "split", False] = False

    def frame(self) -> Tensor:
        """:attr:`last_frame`, which every stream of a batch being tracked holds (:func:`_reopen` reads the first)."""
        if self.last_frame is None:
            raise ValueError(f"{self.name}: no frame read (its batch is not open)")
        return self.last_frame

    def outputs(self) -> tuple[TrackCsvWriter, _VideoOut, _VideoOut]:
        """``(csv, overlay, normalised)``, which :func:`_track_group` opens before the first frame."""
        if self.csv is None or self.overlay is None or self.normalised is None:
            raise ValueError(f"{self.name}: its outputs are not open")
        return self.csv, self.overlay, self.normalised


def _next_frame(s: _Stream) -> Tensor:
    """The next frame of ``s``'s input (``StopIteration`` at its end), its time kept in ``s.stamps`` until its row is
    written."""
    frame = next(s.reader)
    s.stamps.append(0.0 if s.reader.timestamp is None else s.reader.timestamp)  # (None: never, once a frame is read)
    s.images.append(s.reader.image)
    return frame


def _row_values(
    rows: np.ndarray, columns: tuple[str, ...], pose: str = ""
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(B, C)`` CSV rows -> float64 ``(R (B, 3, 3), t (B, 3) mm, anim (B, A), light (B, L))``: the values a row
    holds of the pose, the expression (``anim_*``) and the light (``illum_*``); ``pose``: the pose columns' prefix
    (``"smooth_"``: the smoothed pose of :data:`~torchface.io.table.SMOOTH_COLUMNS`)."""
    idx = {c: i for i, c in enumerate(columns)}
    data = torch.as_tensor(rows, dtype=torch.float64)
    R = data[:, [idx[pose + c] for c in ROTATION_COLUMNS]].reshape(-1, 3, 3)
    t = data[:, [idx[pose + c] for c in POSE_COLUMNS[:3]]]
    anim = data[:, [i for i, c in enumerate(columns) if c.startswith("anim_")]]
    light = data[:, [i for i, c in enumerate(columns) if c.startswith("illum_")]]
    return R, t, anim, light


def _params_from_rows(rows: np.ndarray, columns: tuple[str, ...], layout: ParamLayout) -> Tensor:
    """``(B, C)`` CSV rows -> ``(B, P)`` packed parameters (axis-angle from the stored rotation matrix)."""
    R, t, anim, light = _row_values(rows, columns)
    if anim.shape[1] != layout.num_animation or light.shape[1] != layout.num_illumination:
        raise InputError("the partial CSV does not match the model's animation/illumination terms")
    return torch.cat([matrix_to_axis_angle(R), t, anim, light], dim=1)


def _not_rotations(R: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: which of ``R (N, 3, 3)`` are not rotations (orthonormal to 1e-4, the 9 significant digits a
    file holds being about 1e-8 and float32's rounding about 1e-7; determinant > 0)."""
    off, det = rotation_defects(R)
    return (off > 1e-4) | (det <= 0)


def _replay_problem(rows: np.ndarray, columns: tuple[str, ...], first: int = 0) -> str | None:
    """What is wrong with the complete rows of a partial CSV that a resumed run replays (None: nothing): the rows
    go on into the tracker's state, so each must be the row this version wrote for its frame: ``frame`` its index
    (from ``first``, the stream's first tracked frame), finite pose, rotation matrix (a rotation), animation and
    illumination values, and a :class:`TrackStatus`."""
    idx = {c: i for i, c in enumerate(columns)}
    frame = rows[:, idx["frame"]]
    wrong = np.flatnonzero(frame != np.arange(first, first + rows.shape[0]))
    if wrong.size:
        return f"the row of frame {first + wrong[0]} says frame {frame[wrong[0]]:g}"
    used = [i for i, c in enumerate(columns) if re.fullmatch(r"pose_[TR][xyz]|r[0-2][0-2]|(anim|illum)_.+", c)]
    bad = np.flatnonzero(~np.isfinite(rows[:, used]).all(1))
    if bad.size:
        return f"frame {first + bad[0]} has a pose, expression or light that is not a finite number"
    bad = np.flatnonzero(_not_rotations(rows[:, [idx[c] for c in ROTATION_COLUMNS]].reshape(-1, 3, 3)))
    if bad.size:
        return f"frame {first + bad[0]}'s r00-r22 are not a rotation"
    bad = np.flatnonzero(~np.isin(rows[:, idx["status"]], [int(s) for s in TrackStatus]))
    if bad.size:
        return f"frame {first + bad[0]} has status {rows[bad[0], idx['status']]:g}"
    return None


def _no_face_row(columns: tuple[str, ...], frame: int, timestamp: float, managed: bool) -> np.ndarray:
    """``(C,)`` the CSV row of frame ``frame`` (at ``timestamp`` seconds, :attr:`FrameReader.timestamp
    <torchface.io.video.FrameReader.timestamp>`) before the detector first found a face (``_Stream.start``): no estimate
    (``nan``), ``success`` 0 and ``confidence`` 0 as an unusable row, status LOST with template management (``managed``;
    as a stream whose start failed reads until a face is found) else FAILED, no iteration, point or mosaic entry
    (-1)."""
    row = np.full(len(columns), math.nan)
    status = TrackStatus.LOST if managed else TrackStatus.FAILED
    values = {"frame": frame, "timestamp": timestamp, "success": 0, "confidence": 0.0, "status": int(status),
              "iterations": 0, "num_points": 0, "mosaic_entry": -1}  # fmt: skip
    for name, value in values.items():
        row[columns.index(name)] = value
    return row


def _no_face_problem(rows: np.ndarray, columns: tuple[str, ...], start: int) -> str | None:
    """What is wrong with the rows of a partial CSV before its video's first face, frame ``start`` (its first
    ``start`` rows, or all of them where it holds fewer; None: nothing): each must be the row :func:`_no_face_row`
    writes for its frame (its ``frame``, ``success`` 0, no pose), else they were made with another start (the frame
    where the detector first finds a face is found again on resume where the record does not say it)."""
    idx = {c: i for i, c in enumerate(columns)}
    wrong = np.flatnonzero(rows[:, idx["frame"]] != np.arange(rows.shape[0]))
    if wrong.size:
        return f"the row of frame {wrong[0]} says frame {rows[wrong[0], idx['frame']]:g}"
    used = [idx[c] for c in ("success", *POSE_COLUMNS[:3])]
    bad = np.flatnonzero((rows[:, used[0]] != 0) | np.isfinite(rows[:, used[1:]]).any(1))
    if bad.size:
        return f"frame {bad[0]} has a pose, but the detector finds the first face at frame {start}"
    return None


def _write_no_face(s: _Stream, columns: tuple[str, ...], config: JobConfig, conf_label: str) -> None:
    """Write the frames of a video before the detector first found a face (``s.start``) and read its frames up to
    that one (``s.last_frame``, from which the batch is initialised): their rows (:func:`_no_face_row`; those a
    resumed run replays kept as they are), their overlay (the frame, no mesh, confidence 0 and "NO FACE") and a
    black normalised face; no mesh (``meshes``: from the first tracked frame on)."""
    csv, overlay, normalised = s.outputs()
    replayed = csv.rows_done
    managed = config.tracker.template.enabled
    G = config.normalised_size
    nowhere = np.full((4, 2), math.nan)  # (no mesh vertex, no axis drawn)
    for t in range(s.start):
        stamp, image = s.stamps.popleft(), s.images.popleft()
        if t >= replayed:
            csv.write(_no_face_row(columns, t, stamp, managed)[None])
        else:
            _check_replayed_time(s, csv.previous[t], columns, stamp, t)
        bgr = _frame_bgr(s.frame(), image)
        overlay.write(draw_overlay(bgr, nowhere, np.zeros((0, 2), np.int64), nowhere, 0.0, False, f"#{t}",
                                   conf_label, "NO FACE"), stamp)  # fmt: skip
        normalised.write(np.zeros((G, G, 3), np.uint8))
        s.frames += 1
        try:
            s.last_frame = _next_frame(s)
        except StopIteration:  # (read when the run started: the input has changed since)
            raise InputError(f"{s.reader.info.path}: it ends before frame {s.start}, where the run found its first "
                             "face when it started: was it replaced?") from None  # fmt: skip


#: How far (seconds) a replayed row's ``timestamp`` may be from its frame's time now (:func:`_check_replayed_time`):
#: the CSV's millisecond rounding of each, and a container that keeps its times in milliseconds against the
#: ``frame / fps`` of an earlier version (the same frames of a constant-rate video: within 1 ms).
REPLAY_TIME_TOLERANCE: float = 1.5e-3


def _check_replayed_time(s: _Stream, row: np.ndarray, columns: tuple[str, ...], stamp: float, frame: int) -> None:
    """Refuse to resume rows whose times are not their frames' (``row``: the replayed row of frame ``frame``;
    ``stamp``: its time as the reader gives it now): rows an earlier version wrote with ``frame / fps`` (before the
    ``timestamp`` column was the container's time) of a variable-frame-rate video, which the resumed rows would have
    gone on from with the other rule, one CSV holding both.

    Raises:
        InputError: (``_ReplayedTimeError``) the row's ``timestamp`` is more than :data:`REPLAY_TIME_TOLERANCE` from
            ``stamp``. Met before the first face (:func:`_write_no_face`), it stops the batch before its tracking,
            as the other refusals of a resume do; met at a tracked row, it stops that video only (its times are
            known only as its frames are read: reading them ahead decoded the replayed frames twice), as a frame
            that cannot be read does: the others go on, and :class:`VideosStopped` says it once they are complete.
    """
    then = float(row[columns.index("timestamp")])
    if not abs(then - stamp) <= REPLAY_TIME_TOLERANCE:
        where = s.csv.partial if s.csv is not None else s.name
        raise _ReplayedTimeError(f"{where}: cannot resume, its row of frame {frame} says timestamp {then:.3f} s, but "
                                 f"that frame of {s.reader.info.path} is at {stamp:.3f} s (rows written with other "
                                 "frame times: by an earlier version, which wrote frame / fps, of a variable-frame-rate "
                                 "video): run without --resume")  # fmt: skip


def _record_path(csv: Path) -> Path:
    """The partial CSV's companion record (:func:`_write_record`, JSON): ``<name>.record.partial``."""
    return csv.with_name(csv.stem + ".record.partial")


#: How often (every so many frames of a batch) ``torchface track`` writes each video's checkpoint
#: (``<stem>.state.partial``, :func:`_write_checkpoints`), from which ``--resume`` goes on exactly as the uninterrupted
#: run (:func:`_load_checkpoint`): the rows after the last checkpoint are tracked again. Written once the online
#: start's frames are past (with it, a video interrupted sooner is tracked again from its first frame instead:
#: :attr:`_Stream.retrack`). Measured on 200-frame 160x120 pose sweeps (the 2-core test machine, shared): 16-35 ms
#: per checkpoint at B = 1 and 23 ms for the 3 videos of a batch (8 ms each), 2.5-2.7 MB per video (its template
#: mosaic's 12 entries and its templates, most of it; their sizes are the model's and the pyramid's, not the
#: frame's), against 30-50 ms per tracked frame: 0.6-1.4 ms a frame past frame 150 (0.2-0.35 ms a frame over the
#: 200; the runs' track times alike within their noise), where every frame would have cost 30-100 %.
CHECKPOINT_EVERY: int = 25

#: The version of the checkpoint's layout (another one is not read: resumed from the rows, with a warning).
_CHECKPOINT_VERSION = 3  # (3: its stream entry holds the detector counts)


#: The signals whose Python handlers the tracking loop runs at its step boundary (:class:`_AtStepBoundary`).
_DEFERRED_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM)


class _AtStepBoundary:
    """Within the block (:func:`_track_group`'s per-frame loop), SIGINT and SIGTERM whose handler is a Python one
    (Ctrl-C's ``default_int_handler``, ``torchface track``'s SIGTERM handler, a caller's own) do not run it where the
    signal arrives, mid-step (the tracker's state half updated, which no checkpoint can be written of): the loop
    calls :meth:`check` once a step's rows are written, writes every live video's checkpoint of that consistent
    state first (:func:`_write_checkpoints`), and the handler runs there (raising ``KeyboardInterrupt``, or the
    command line's SIGTERM error). A second signal while one waits runs its handler at once (a step that hangs, a
    read that blocks: the user's second Ctrl-C). A handler that is not a Python one (``SIG_IGN``: a parent that
    ignores the signal, ``SIG_DFL``, one set outside Python) is left as it is, and nothing is deferred outside the
    main thread (whose handlers only it runs) or outside the block: its previous handlers are put back as it ends,
    however it ends (an error, the second signal's interruption), and a signal that waited still runs there (after
    the loop's last step: its rows complete; or over the error that ended the block, kept as its ``error``)."""

    def __init__(self) -> None:
        self._handlers: dict[int, Callable[[int, Any], Any]] = {}  # the handlers it runs, by signal
        self._previous: dict[int, Any] = {}  # the handlers it puts back, by signal (a nested block: the outer's)
        self._installed = False
        self.pending: int | None = None  # the signal that waits for the step boundary

    def __enter__(self) -> "_AtStepBoundary":
        if threading.current_thread() is not threading.main_thread():
            return self
        try:
            for signum in _DEFERRED_SIGNALS:
                previous = handler = signal.getsignal(signum)
                outer = getattr(previous, "__self__", None)
                if isinstance(outer, _AtStepBoundary):  # (a track_videos within another's loop: from its progress
                    # callback, or a handler it runs): the handler itself, not the outer loop's deferral, which would
                    # only mark the outer loop and let this one track on to its end (the outer's deferral put back
                    # as this one ends: the outer loop defers again)
                    handler = outer._handlers[signum]
                if callable(handler):  # (not SIG_IGN, SIG_DFL or None: a handler set outside Python)
                    self._handlers[signum], self._previous[signum] = handler, previous
                    self._installed = True
                    signal.signal(signum, self._defer)
        except BaseException:  # (a signal's handler that raised before the block began: none left installed)
            self.restore()
            raise
        return self

    def _defer(self, signum: int, frame: Any) -> None:
        if self.pending is None:
            self.pending = signum
            self._notice(signum)
            return
        self.pending = None  # a second one: its handler at once, mid-step (no checkpoint of that state)
        self._handlers[signum](signum, frame)

    @staticmethod
    def _notice(signum: int) -> None:
        """Say that the signal waits for the step's end (a large batch's step and checkpoints take a second or more,
        in which a user sees nothing happen), as a warning (``torchface track``: one ``torchface: warning:`` line).
        Never an error of the step it interrupts: a warning made an exception (``-W error``), or a write of stderr
        that the signal interrupted (a reentrant call), leaves it unsaid."""
        again = "; Ctrl-C again stops at once" if signum == signal.SIGINT else "; a second signal stops at once"
        try:
            warnings.warn(f"{signal.Signals(signum).name}: stopping once the frame under way is written, after its "
                          f"checkpoint{again}", RuntimeWarning, stacklevel=2)
        except Exception:
            pass

    def restore(self) -> None:
        """Put the previous handlers back (a signal that waits still waits for :meth:`check`)."""
        if self._installed:
            self._installed = False
            for signum, handler in self._previous.items():
                signal.signal(signum, handler)

    def check(self, error: BaseException | None = None) -> None:
        """Run the handler of the signal that waits, if any (the step's rows and checkpoints written), with the
        frame it runs from as its second argument (the loop's, where the interruption is raised; not the one the
        signal arrived in, whose locals, a step's tensors, would be held until then). ``error``: the exception the
        loop stopped with meanwhile (a CSV or the checkpoint that could not be written), which the handler's
        interruption replaces: kept as its ``error`` attribute, which the command line says (it was lost from its
        output: "interrupted", status 130)."""
        if self.pending is not None:
            signum, self.pending = self.pending, None
            try:
                self._handlers[signum](signum, sys._getframe(1))
            except BaseException as interruption:
                if isinstance(error, Exception) and interruption is not error:
                    interruption.error = error  # type: ignore[attr-defined]
                raise

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None, traceback: object) -> None:
        self.restore()
        self.check(error)  # (one that arrived after the last check: run now, the loop over or stopped by ``error``)


def _checkpoint_path(csv: Path) -> Path:
    """The partial CSV's checkpoint (:func:`_write_checkpoints`): ``<name>.state.partial``."""
    return csv.with_name(csv.stem + ".state.partial")


def _checkpoint_origin(device: torch.device | str, dtype: torch.dtype) -> dict[str, str]:
    """What a checkpoint's rows depend on besides the settings (:func:`_settings`, which a resume from the CSV's rows
    may change): the torchface version, the device and the dtype it was tracked with. A checkpoint of other ones is
    not used (:func:`_load_checkpoint`: its state, restored elsewhere, would not go on as the uninterrupted run)."""
    import torchface

    return {"torchface": str(torchface.__version__), "device": str(torch.device(device)),
            "dtype": str(dtype).removeprefix("torch.")}  # fmt: skip


def _settings_text(settings: dict[str, object]) -> str:
    """``settings`` (:func:`_settings`) as the checkpoint keeps them (JSON, keys sorted), to be compared as text."""
    return json.dumps(_as_json(settings), sort_keys=True)


def _write_checkpoints(
    state: TrackerState, smooth: SmoothingState | None, first_R: Tensor, first_t: Tensor, live: list[_Stream],
    paths: list[dict[str, Path]], t: int, written: list[bool],
) -> bool:
    """Write (atomically: a temporary file renamed) the checkpoint of each live stream whose row ``t`` this step
    wrote (``written``): what the tracking loop carries after that row (its re-detection made), for a resumed run to
    go on from (:func:`_load_checkpoint`): its part of ``state`` (``TrackerState.select``: parameters, shape,
    templates, the management's mosaic, counters and online-start watch, motion prediction), of ``smooth`` (the pose
    filter) and of the first poses ``first_R`` ``(B, 3, 3)``, ``first_t`` ``(B, 3)``; the loop's ``t``, the CSV's
    row count and last row (which a resume matches), the settings, the torchface version, device and dtype
    (:func:`_checkpoint_origin`), the batch's videos in order (a resume tracks
    those together again, :func:`_checkpoint_batches`) and the stream's own bookkeeping. Tensors and plain data
    only (:func:`torchface._checkpoint.to_plain`), read with ``torch.load(weights_only=True)``. Returns False, with
    a warning, where the state holds what plain data cannot (a value of a kind ``to_plain`` does not know): the run
    goes on without checkpoints, as an earlier version's (a checkpoint must not stop the tracking)."""
    names = [s.name for s in live]
    for k, s in enumerate(live):
        if not written[k] or s.done or s.csv is None:
            continue
        part = state if len(live) == 1 else state.select([k])
        try:
            plain = _checkpoint.to_plain(part)
            plain_smooth = None if smooth is None else _checkpoint.to_plain(smooth if len(live) == 1
                                                                            else smooth.select([k]))  # fmt: skip
        except TypeError as exc:
            warnings.warn(f"no checkpoints written ({exc}): an interrupted run resumes from its CSV's rows",
                          RuntimeWarning, stacklevel=2)  # fmt: skip
            return False
        data = {
            "version": _CHECKPOINT_VERSION, "t": t, "rows": s.csv.rows_done, "start": s.start,
            "row": None if s.last_row is None else torch.as_tensor(s.last_row, dtype=torch.float64),
            "settings": _settings_text(s.settings), "batch": names, "index": k,
            "origin": _checkpoint_origin(state.params.device, state.params.dtype),
            "threads": torch.get_num_threads(),  # (for information: _resumed_record)
            "state": plain, "smooth": plain_smooth,
            "first_R": first_R[k : k + 1].detach().clone(), "first_t": first_t[k : k + 1].detach().clone(),
            "stream": {"low_count": s.low_count, "smooth_restart": s.smooth_restart,
                       "detection_warned": s.detection_warned,
                       "near": None if s.near is None else torch.as_tensor(s.near),
                       # the sidecar's counts so far (a resume goes on counting from them: the whole video's)
                       "detector_calls": s.detector_calls, "redetections": s.redetections,
                       "restart_failures": dict(s.restart_failures)},
        }  # fmt: skip
        path = _checkpoint_path(paths[k]["csv"])
        tmp = path.with_name(path.name + ".tmp")
        try:
            with open(tmp, "wb") as f:
                torch.save(data, f)
            os.replace(tmp, path)
        except BaseException as exc:  # (a full disk, or interrupted: the last checkpoint as it was, no temporary)
            tmp.unlink(missing_ok=True)
            if isinstance(exc, OSError):
                raise OutputError(f"{path}: cannot write ({exc.strerror or exc})") from None
            raise
    return True


def _load_checkpoint(s: _Stream, csv: Path, config: JobConfig, model: FaceModel) -> dict | None:
    """The checkpoint of ``s``'s partial run (:func:`_write_checkpoints`; ``csv``: its CSV's final path) where it is
    there and matches its partial CSV: the same torchface version, device and dtype (:func:`_checkpoint_origin`),
    the same settings (other ones, which the record refuses: None without a word, the record's check says why the
    resume is refused; ones the record accepts, written otherwise: not used, with the warning line), a row count the
    CSV holds (rows after it, written after the checkpoint, are cut off once the resume is accepted: tracked again),
    the same last row, and past the online start's frames (sooner the rows are tracked again from the first frame:
    :attr:`_Stream.retrack`). None where there is none; None with one warning line where it cannot be read or does
    not match (the resume goes on from the CSV's rows)."""
    path = _checkpoint_path(csv)
    if not path.is_file():
        return None
    partial = partial_path(csv)
    rows_file = partial if partial.is_file() else csv
    if not rows_file.is_file():  # (no rows: the video starts afresh)
        return None
    try:
        data = torch.load(path, map_location=model.device, weights_only=True)
        if not isinstance(data, dict) or data.get("version") != _CHECKPOINT_VERSION:
            made = data.get("version") if isinstance(data, dict) else None
            raise ValueError(f"written by another torchface, its layout {made!r}, this one's {_CHECKPOINT_VERSION}"
                             if isinstance(made, int) else "not a checkpoint's layout")
        _check_checkpoint_layout(data)
        origin, here = data.get("origin"), _checkpoint_origin(model.device, model.dtype)
        if origin != here:  # (another version, device or dtype: a resume from the CSV's rows is allowed, not this)
            diff = [f"{k} {origin.get(k) if isinstance(origin, dict) else None}, now {v}" for k, v in here.items()
                    if not isinstance(origin, dict) or origin.get(k) != v]  # fmt: skip
            raise ValueError(f"made with another {', '.join(diff)}")
        settings = _settings(config, s, model)
        if data["settings"] != _settings_text(settings):
            made = json.loads(data["settings"])
            if not isinstance(made, dict):
                raise ValueError("its settings are not of its layout")
            # (settings the record refuses: the resume is refused, and the record's check says why)
            if _changed_settings(_ran_online_start(_with_defaults(made, _setting_values(config)), _RECORD_KEYS),
                                 settings):
                return None
            raise ValueError("its settings are written otherwise than this run's")  # (the record accepts them)
        n, t, start = int(data["rows"]), int(data["t"]), int(data["start"])
        online = _online_start(config)
        if online is not None and t + 1 < online.max_frames:
            return None
        _, rows = read_track_csv(rows_file)
        if len(rows) < n or n != start + t + 1 or start != s.start:
            raise ValueError(f"it is of row {n}, the CSV holds {len(rows)}")
        if data["row"] is None or not np.array_equal(rows[n - 1], data["row"].cpu().numpy(), equal_nan=True):
            raise ValueError(f"its row {n} is not the CSV's")
        if (data["smooth"] is None) != (config.smoothing is None):
            raise ValueError("its pose filter is not this run's")
        _checkpoint.from_plain(data["state"])  # (read again as its batch starts: _joined; not kept meanwhile)
        return {k: v for k, v in data.items() if k not in ("state", "smooth")} | {"path": path}
    except Exception as exc:  # (damaged, another version's, not this CSV's: the rows are resumed as before)
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        warnings.warn(f"{path}: not used ({why}): the video goes on from its CSV's rows, not exactly as the "
                      f"uninterrupted run", RuntimeWarning, stacklevel=2)  # fmt: skip
        return None


#: What a checkpoint holds (:func:`_write_checkpoints`), and its ``stream`` entry.
_CHECKPOINT_KEYS = frozenset({"version", "t", "rows", "start", "row", "settings", "origin", "batch", "index", "state",
                              "smooth", "first_R", "first_t", "stream"})  # fmt: skip
_CHECKPOINT_STREAM_KEYS = frozenset({"low_count", "smooth_restart", "detection_warned", "near", "detector_calls",
                                     "redetections", "restart_failures"})  # fmt: skip


def _check_checkpoint_layout(data: dict) -> None:
    """Raise ValueError where ``data`` lacks what :func:`_load_checkpoint` and the resume read of a checkpoint
    (its batch and place in it, its bookkeeping, its first poses): a file of this version's number without them
    (damaged, or not written by :func:`_write_checkpoints`) failed with a KeyError after the check, the run stopped."""
    missing = sorted(_CHECKPOINT_KEYS - set(data))
    stream = data.get("stream")
    if isinstance(stream, dict):
        missing += [f"stream.{k}" for k in sorted(_CHECKPOINT_STREAM_KEYS - set(stream))]
    if missing:
        raise ValueError(f"it lacks {', '.join(missing)}")
    batch, index = data["batch"], data["index"]
    if not isinstance(stream, dict) or not isinstance(batch, list) or not all(isinstance(n, str) for n in batch):
        raise ValueError("its batch or bookkeeping is not of its layout")
    failures = stream["restart_failures"]
    if not all(type(stream[k]) is int for k in ("detector_calls", "redetections")) or not isinstance(  # (not bool)
            failures, dict) or not all(isinstance(k, str) and type(v) is int for k, v in failures.items()):
        raise ValueError("its detector counts are not of their layout")
    if type(index) is not int or not 0 <= index < len(batch):
        raise ValueError(f"its place {index!r} is not in its batch of {len(batch)}")
    for name, shape in (("first_R", (1, 3, 3)), ("first_t", (1, 3))):
        if not isinstance(data[name], Tensor) or tuple(data[name].shape) != shape:
            raise ValueError(f"its {name} is not {shape}")


def _cut_rows(csv: Path, rows: int) -> None:
    """Cut the partial CSV of ``csv`` (or ``csv`` itself, not finalised) after its header and ``rows`` rows: the
    rows written after the checkpoint a resume goes on from (tracked again)."""
    partial = partial_path(csv)
    path = partial if partial.is_file() else csv
    with open(path, "r+b") as f:  # (line by line: not the whole file in memory; the writer's lines end in \n)
        for _ in range(rows + 1):
            if not f.readline().endswith(b"\n"):
                raise ValueError(f"{path}: it holds fewer than {rows} complete rows")
        f.truncate(f.tell())


def _checkpoint_batches(streams: list[_Stream]) -> list[list[int]]:
    """The batches of the streams resumed from their checkpoints (:attr:`_Stream.checkpoint`): each batch of the
    interrupted run (its videos, the loop's ``t``) whose videos are resumed, in its order, tracked as that batch
    again (the others: :func:`_track_opened`'s batches)."""
    groups: dict[tuple[tuple[str, ...], int], list[int]] = {}
    for i, s in enumerate(streams):
        if s.checkpoint is not None:
            groups.setdefault((tuple(s.checkpoint["batch"]), int(s.checkpoint["t"])), []).append(i)
    def place(i: int) -> int:
        return int(streams[i].checkpoint["index"])  # type: ignore[index]

    return [sorted(m, key=place) for m in groups.values()]


def _joined(streams: list[_Stream], smoothing: bool, device: torch.device
            ) -> tuple[TrackerState, SmoothingState | None, Tensor, Tensor] | None:  # fmt: skip
    """The batch's state put together from its streams' checkpoints (:attr:`_Stream.checkpoint`, every stream
    resumed from one, after the same row ``t``; read again here, so that no more than one batch's are held), in
    their order (:func:`torchface._checkpoint.join`): the state the interrupted run carried after that row, with its
    pose filter (``smoothing``) and first poses; None, with a warning, where they do not go together (the streams
    then go on from their CSV's rows; those after the checkpoint were cut off, and are tracked again)."""
    cks = [s.checkpoint for s in streams]
    if not any(c is not None for c in cks):
        return None
    try:
        if any(c is None for c in cks):
            raise ValueError("not every video of the batch has one")
        if len({int(c["t"]) for c in cks}) != 1 or any(  # type: ignore[index]
                s.replay is None or s.retrack or len(s.replay) != int(c["t"]) + 1  # type: ignore[index]
                for s, c in zip(streams, cks)):  # fmt: skip
            raise ValueError("the videos' rows do not end together")
        # (one video: its state as saved, the whole of it, a cache select would drop included)
        parts = [torch.load(c["path"], map_location=device, weights_only=True) for c in cks if c is not None]
        states = [_checkpoint.from_plain(c["state"], device) for c in parts]
        smooths = [_checkpoint.from_plain(c["smooth"], device) for c in parts] if smoothing else []
        # (one video: its state as saved, the whole of it, a cache select would drop included)
        state = states[0] if len(states) == 1 else _checkpoint.join(states)
        smooth = None if not smoothing else smooths[0] if len(smooths) == 1 else _checkpoint.join(smooths)
        first_R = torch.cat([c["first_R"] for c in parts]).to(device)
        first_t = torch.cat([c["first_t"] for c in parts]).to(device)
    except Exception as exc:  # (the file changed since, or the states do not join: the rows as before)
        names = ", ".join(s.name for s, c in zip(streams, cks) if c is not None)
        warnings.warn(f"the checkpoints of {names} not used ({exc}): they go on from their CSV's rows, not exactly "
                      f"as the uninterrupted run", RuntimeWarning, stacklevel=2)  # fmt: skip
        for s in streams:
            s.checkpoint = None
        return None
    return state, smooth, first_R, first_t


def _restore_streams(streams: list[_Stream]) -> None:
    """Put back each stream's own bookkeeping after its checkpoint's row (:func:`_write_checkpoints`), and say
    whether the streams are their checkpoints' whole batch, in its order (:attr:`_Stream.from_checkpoint`)."""
    whole = all(s.checkpoint is not None and list(s.checkpoint["batch"]) == [x.name for x in streams]
                for s in streams)  # fmt: skip
    for s in streams:
        assert s.checkpoint is not None
        b = s.checkpoint["stream"]
        s.low_count, s.smooth_restart = int(b["low_count"]), bool(b["smooth_restart"])
        s.detection_warned = bool(b["detection_warned"])
        s.near = None if b["near"] is None else b["near"].cpu().numpy()
        # (this run's counts so far are of the replayed rows, which asked nothing, and of its first-face search,
        # which the interrupted run's counts hold: replaced, not added to)
        s.detector_calls, s.redetections = int(b["detector_calls"]), int(b["redetections"])
        s.restart_failures = {str(k): int(v) for k, v in b["restart_failures"].items()}
        s.from_checkpoint = "exact" if whole else "split"


def _input_identity(path: Path) -> str:
    """The identity of input ``path`` as the resume compares it: a file's size and modification time, an image
    folder's image count and newest modification time (``"209508 bytes, modified 1764681857123456789 ns"``).

    Raises:
        OSError: it cannot be read (gone, or one of its images removed meanwhile).
    """
    if path.is_dir():
        stats = [f.stat() for f in image_files(path)]
        return f"{len(stats)} images, newest modified {max((st.st_mtime_ns for st in stats), default=0)} ns"
    st = path.stat()
    return f"{st.st_size} bytes, modified {st.st_mtime_ns} ns"


def _settings(config: JobConfig, stream: _Stream, model: FaceModel) -> dict[str, object]:
    """What a video's rows depend on besides its frames' content: the input file's identity (size and modification
    time; an image folder's count and newest file) and its first-frame landmarks, as text, every setting that
    changes the tracking, as JSON values (:func:`_as_json`), and ``model`` where it is not CANDIDE-3
    (:func:`_model_setting`). A resumed run must agree on all of them (:func:`_read_record`,
    :func:`_setting_differences`)."""
    ident = _input_identity(Path(stream.reader.info.path))
    points = np.ascontiguousarray(np.asarray(stream.landmarks, dtype=np.float64))
    # (the frame where the detector first found a face, when not the first: said only then, so that the records of
    # earlier versions, which tracked every video from its first frame, still compare equal)
    late = {"first face at frame": stream.start} if stream.start else {}
    # (the rate --fps gave an input without one: said only where it is not the rate assumed without it, so that the
    # records of runs without it, and of earlier versions, still compare equal, and --fps 25 resumes a run without it,
    # rows and times alike; a video's own rate is in its frames' times, which the replay checks)
    info = stream.reader.info
    given = {"--fps": float(info.fps)} if info.fps_given and info.fps != ASSUMED_FPS else {}
    return {
        "input file": ident, "first-frame landmarks": hashlib.sha256(points.tobytes()).hexdigest()[:16], **late,
        **given, **_as_json(_setting_values(config)), **_model_setting(model),
    }  # fmt: skip


#: :func:`~torchface.model.face_model_digest` of the models jobs track with, while they exist (one object all through
#: a job; an ``lru_cache`` kept the last job's model, on its device, alive after the job).
_DIGESTS: weakref.WeakKeyDictionary[FaceModel, str] = weakref.WeakKeyDictionary()


def _digest(model: FaceModel) -> str:
    """:func:`~torchface.model.face_model_digest` of ``model``, computed once per model object."""
    digest = _DIGESTS.get(model)
    if digest is None:
        digest = _DIGESTS[model] = face_model_digest(model)
    return digest


@lru_cache(maxsize=1)
def _candide3() -> FaceModel:
    """:func:`load_candide3`'s model (float32, on the CPU: what it depends on is fixed here), loaded once per process:
    the default model of every job (a load took 45 ms, and each job loaded it, and :func:`_candide_digest` once
    more). Shared by the jobs, never changed: a :class:`FaceModel` is frozen, nothing of the job writes into its
    tensors (another device or dtype is a copy, :meth:`FaceModel.to`), and no job returns it; its CPU tensors (43 KB)
    stay alive, never a job's device copy. On the CPU whatever torch's default device (``torch.set_default_device``,
    a ``with torch.device("cuda"):`` block) is when the first job loads it: loaded there, a GPU copy stayed alive for
    the process's life."""
    return load_candide3(device="cpu")


@lru_cache(maxsize=1)
def _candide_digest() -> str:
    """The digest of :func:`load_candide3`'s model, what every job tracked with before ``JobConfig.model``."""
    return _digest(_candide3())


def _model_label(model: FaceModel) -> str:
    """How a record and a message name ``model``: its name and the start of its digest."""
    return f"{model.name} (sha256 {_digest(model)[:16]})"


def _model_setting(model: FaceModel) -> dict[str, str]:
    """The ``--model`` entry of :func:`_settings`: the model's name and digest (:func:`_model_label`); none for
    CANDIDE-3, given or not (records of earlier versions, made with it, have none; :func:`_read_record` refuses a
    record with the entry resumed without it)."""
    return {} if _digest(model) == _candide_digest() else {"--model": _model_label(model)}


def _setting_values(config: JobConfig) -> dict[str, object]:
    """The settings of :func:`_settings` that change the tracking, under its names, as Python values (the settings
    dataclasses themselves: :func:`_with_defaults` takes the defaults of the fields a record lacks from them)."""
    return {
        "--focal": None if config.focal is None else float(config.focal), "--convert": config.convert,
        "--lookahead": config.lookahead, "online start": _online_start(config), "tracker settings": config.tracker,
        "--detector": config.detector, "re-detection": (config.redetect_after, config.redetect_below),
        "normalised size": config.normalised_size,
        # (only when on: the records of runs without it, and of earlier versions, hold none)
        **({"--smooth": config.smoothing} if config.smoothing is not None else {}),
        **({"--keep-expression": True} if config.keep_expression else {}),
    }  # fmt: skip


def _as_json(value: object) -> Any:
    """``value`` as a JSON file holds it (:func:`~torchface.io.sidecar.to_jsonable`: a dataclass as the dict of its
    fields, a tuple as a list), the form in which the record and the sidecar's ``config`` keep the settings."""
    return json.loads(json.dumps(to_jsonable(value)))


_ENUM_REPR = re.compile(r"<\w+(?:\.\w+)+: ('[^']*'|[-+.\w]+)>")


def _from_repr(text: str) -> object:
    """A setting that a record of an earlier version holds as its ``repr`` (``TrackerConfig(num_levels=3, ...)``,
    ``(10, 0.15)``, ``'dlib'``) as :func:`_as_json` gives it; ``text`` itself where it is not such a repr."""

    def value(node: ast.expr) -> object:
        if isinstance(node, ast.Call) and not node.args:  # a dataclass: its fields
            return {k.arg: value(k.value) for k in node.keywords}
        if isinstance(node, (ast.Tuple, ast.List)):
            return [value(e) for e in node.elts]
        if isinstance(node, ast.Name) and node.id in ("inf", "nan"):  # (to_jsonable writes them as null)
            return None
        return ast.literal_eval(node)

    try:  # (an enum's repr, <RobustKind.TUKEY: 'tukey'>, as its value)
        return value(ast.parse(_ENUM_REPR.sub(r"\1", text), mode="eval").body)
    except (SyntaxError, ValueError, TypeError, MemoryError, RecursionError):
        return text


def _changed_settings(made_with: dict, now: dict[str, object]) -> list[str]:
    """The names of the settings ``now`` that a record's ``made_with`` does not hold, or holds with another value
    (:func:`_setting_differences`): what a resume is refused over (:func:`_read_record`), and what leaves the
    record's first face unused (:func:`_recorded_first_face`)."""
    return [k for k in now if k not in made_with or _setting_differences(made_with[k], now[k])]


def _with_defaults(then: Any, value: object, default: object = None) -> Any:
    """The setting ``then`` (as a record or a sidecar holds it, :func:`_as_json`) with each field that it lacks and
    the settings dataclass of ``value`` (the setting now, a Python value: :func:`_setting_values`,
    :func:`_result_settings`) has, at that field's default, as JSON, nested dataclasses alike: a field added to a
    settings dataclass since ``then`` was written is compared as what the earlier version did, where a version
    that added it kept that by default, as most did (not all: ``min_face_width_px``, ``max_rotation_std_deg``,
    ``max_facing_deg``, ``reference_focal_px`` and ``expression_range_from_start`` changed what the tracker does at
    their defaults); a partial
    run's record from before ``motion_prediction`` existed, resumed with ``--motion-prediction 0.5``, mixed two
    settings in one video. A field without a default stays absent (not
    compared, :func:`_setting_differences`), as does one that ``then`` has and ``value``'s dataclass no longer
    does (removed since). ``default``: ``value``'s default where it is a field of another dataclass (that field's
    default), whose fields' values are the defaults of a nested one's fields: TrackerConfig's ``fit`` is
    ``FitConfig(fit_expression=True, ...)``, and a record without ``fit.fit_expression`` compared at
    ``FitConfig()``'s (False) was refused with the default settings."""
    if isinstance(then, dict) and is_dataclass(value) and not isinstance(value, type):
        own = default if type(default) is type(value) else None
        out = dict(then)
        for f in fields(value):
            if own is not None:
                d = getattr(own, f.name)
            elif f.default is not MISSING:
                d = f.default
            elif f.default_factory is not MISSING:
                d = f.default_factory()
            else:  # (no default: absent, not compared)
                d = MISSING
            if f.name in then:
                out[f.name] = _with_defaults(then[f.name], getattr(value, f.name), None if d is MISSING else d)
            elif d is not MISSING:
                out[f.name] = _as_json(d)
        return out
    if isinstance(then, dict) and isinstance(value, dict):  # (the settings by name: their own keys compared)
        return {k: _with_defaults(v, value[k]) if k in value else v for k, v in then.items()}
    if isinstance(then, list) and isinstance(value, (list, tuple)) and len(then) == len(value):
        return [_with_defaults(a, b) for a, b in zip(then, value)]
    return then


def _setting_differences(then: object, now: object, at: str = "") -> list[str]:
    """Where the setting ``then`` (as a record or a sidecar holds it, :func:`_as_json`; the fields it lacks filled
    with their defaults first, :func:`_with_defaults`) differs from ``now``: the dotted names of the fields that
    differ (``""``: the whole value). Numbers compare by value (``5`` and ``5.0`` are one setting); a field that
    only one of them has (one removed from a settings dataclass between versions, or one without a default) is not
    compared."""
    if isinstance(then, dict) and isinstance(now, dict):
        return [d for k in then.keys() & now.keys() for d in _setting_differences(then[k], now[k], f"{at}{k}.")]
    if isinstance(then, list) and isinstance(now, list) and len(then) == len(now):
        return [d for k, (a, b) in enumerate(zip(then, now)) for d in _setting_differences(a, b, f"{at}{k}.")]
    same = then == now and isinstance(then, bool) == isinstance(now, bool)
    return [] if same else [at.rstrip(".")]


#: The tracker settings (:class:`~torchface.tracker.TrackerConfig` fields, dotted) that ``torchface track`` sets with
#: an option of its own: a settings difference names the option (:func:`_said_difference`), as ``--smooth``'s does.
_TRACKER_OPTIONS = {"motion_prediction": "--motion-prediction",
                    "template.restart_after_unmatched": "--restart-after-unmatched"}  # fmt: skip


def _field_at(setting: object, dotted: str) -> object:
    """The value of field ``dotted`` (:func:`_setting_differences`' names: ``template.lost_after``, ``iterations.1``)
    in ``setting`` as a record holds it (:func:`_as_json`)."""
    for key in dotted.split(".") if dotted else ():
        setting = setting[int(key)] if isinstance(setting, list) else setting[key]  # type: ignore[index]
    return setting


def _said_value(value: object) -> str:
    """A settings field's value in a message: as Python writes it, a nested setting as ``{...}``, long ones cut."""
    said = "{...}" if isinstance(value, dict) else repr(value)
    return said if len(said) <= 60 else said[:57] + "..."


def _said_difference(name: str, then: object, now: object) -> str:
    """How a message says that setting ``name`` was ``then`` and is ``now``: the two values (None: ``default`` for
    ``--focal``, ``max(W, H)``; else ``none``), or for settings dataclasses (dicts; None where off) whether it was on,
    or which of their fields differ and their two values (the first four; a tracker field that ``torchface track``
    sets with an option, :data:`_TRACKER_OPTIONS`, as that option)."""
    if isinstance(then, dict) and isinstance(now, dict):
        fields = sorted(_setting_differences(then, now))
        options = _TRACKER_OPTIONS if name in ("tracker settings", "tracker") else {}
        parts = [_said_difference(options[f], _field_at(then, f), _field_at(now, f)) for f in fields if f in options]
        rest = [f for f in fields if f not in options]
        if rest or not parts:
            values = [f"{f} {_said_value(_field_at(then, f))} then, {_said_value(_field_at(now, f))} now"
                      for f in rest[:4]]  # fmt: skip
            parts.append(f"{name}: {'; '.join(values)}{' and more' if len(rest) > 4 else ''}")
        return "; ".join(parts)
    if isinstance(then, dict) or isinstance(now, dict):
        return f"{name} {'on' if then is not None else 'off'} then, {'on' if now is not None else 'off'} now"
    # (a setting left unset: "--focal None then" said Python's None where the user gave no --focal; a flag says on /
    # off, as --smooth does, not Python's True / False)
    unset = {"--focal": "default", "--model": "CANDIDE-3 (no --model)", "--keep-expression": "off",
             "--fps": "none (25 assumed)"}.get(name, "none")  # fmt: skip

    def said(value: object) -> object:
        return unset if value is None else ("on" if value else "off") if isinstance(value, bool) else value

    return f"{name} {said(then)} then, {said(now)} now"


def _write_record(
    path: Path, video: Path, anchor: _Anchor | None, settings: dict[str, object], first_face: dict | None = None
) -> None:
    """Write (atomically) what a resumed run needs besides the partial CSV's rows: the input it belongs to, the
    settings the rows were made with (:func:`_settings`) and, once the online start has re-anchored the stream
    (``anchor``), the first frame's refined fit and the offset between the re-anchored frame and the first
    result's (the rows' frame), so that the rest is tracked from the same templates and the rows go on in the same
    frame, the shape the rows up to the re-anchoring were tracked with (their mesh is re-drawn with it), and the
    re-anchoring frame's refined parameters, which its row does not hold (the tracking went on from them); and, for a
    video started from the detector, ``first_face`` (:func:`_first_face`: where it found the first face, which a
    resumed run does not look for again, :func:`_recorded_first_face`; absent in records of earlier versions)."""
    tmp = path.with_name(path.name + ".tmp")
    record = {"input": str(video.resolve()), "anchor": anchor, "settings": settings, "settings_as": "json"}
    if first_face is not None:
        record["first_face"] = first_face
    try:
        tmp.write_text(json.dumps(record), encoding="utf-8")
    except OSError as exc:  # a full disk: say where, and leave no temporary file behind
        tmp.unlink(missing_ok=True)
        raise OutputError(f"{path}: cannot write the resume record ({exc.strerror or exc})") from None
    os.replace(tmp, path)


def _first_face(s: _Stream) -> dict | None:
    """Where the detector found the first face of ``s``'s video, as its record keeps it (:func:`_write_record`):
    ``{"frame": s.start, "landmarks": (68, 2) pixels}``; None for a video started from a landmarks file."""
    if not s.landmarks_source.startswith("detector:"):
        return None
    return {"frame": s.start, "landmarks": np.asarray(s.landmarks, dtype=np.float64).tolist()}


def _recorded_first_face(
    config: JobConfig, reader: FrameReader, name: str, model: FaceModel
) -> tuple[int, np.ndarray] | None:
    """``(frame, (68, 2) landmarks)``: where the interrupted run whose record (:func:`_write_record`) is beside video
    ``name``'s partial CSV found the first face, for a resumed run to start there without asking the detector about
    the frames before it again (a minute of title frames at 30 frames/s: 1800 calls); None where the record does not
    say (none, one of an earlier version or unreadable) or would not be resumed (made from another input, with
    other settings: :func:`_read_record` refuses it, or the search finds the face elsewhere, as before)."""
    path = _record_path(output_paths(Path(config.out_dir), name)["csv"])
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
        made_from, made_with, first = record["input"], record["settings"], record["first_face"]
        frame, points = first["frame"], np.asarray(first["landmarks"], dtype=np.float64)
        if not isinstance(made_from, str) or not isinstance(made_with, dict) or record.get("settings_as") != "json":
            return None
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None
    if not isinstance(frame, int) or isinstance(frame, bool) or frame < 0 or points.shape != (68, 2):
        return None
    if not np.isfinite(points).all() or Path(made_from).resolve() != Path(reader.info.path).resolve():
        return None
    found = _Stream(name, reader, points, f"detector:{config.detector}", reader.info.num_frames, start=frame)
    now = _settings(config, found, model)  # (the landmarks and the frame among them)
    made_with = _ran_online_start(_with_defaults(made_with, _setting_values(config)), _RECORD_KEYS)
    if _changed_settings(made_with, now) or set(made_with) - set(now):
        return None
    return frame, points


def _numbers(value: object, shape: tuple[int, ...]) -> bool:
    """Whether ``value`` (from JSON) is nested lists of finite numbers (not booleans) of ``shape``."""
    if not shape:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    return isinstance(value, list) and len(value) == shape[0] and all(_numbers(v, shape[1:]) for v in value)


def _anchor_problem(anchor: object, num_shape: int, num_animation: int) -> str | None:
    """What is wrong with a record's re-anchoring (:func:`_record_anchors` writes it; None: nothing, or no
    re-anchoring): its fields must be finite numbers of the model's sizes, ``head_rotation`` a rotation and
    ``frame`` (absent in records of earlier versions) a frame index, ``params`` (absent or None: not kept) the
    packed parameters of the model (:func:`_anchor_params`)."""
    if anchor is None:
        return None
    if not isinstance(anchor, dict):
        return f"its anchor is a {type(anchor).__name__}, not an object"
    shapes = {"axis_angle": (3,), "translation": (3,), "shape_coeffs": (num_shape,),
              "anim_coeffs": (num_animation,), "head_rotation": (3, 3), "head_translation": (3,)}  # fmt: skip
    for name, shape in shapes.items():
        if not _numbers(anchor.get(name), shape):
            return f"anchor.{name} is not {' x '.join(map(str, shape))} finite numbers"
    first = anchor.get("first_shape_coeffs")
    if first is not None and not _numbers(first, (num_shape,)):
        return f"anchor.first_shape_coeffs is not {num_shape} finite numbers"
    first = anchor.get("first_anim_coeffs")  # (absent in records of earlier versions)
    if first is not None and not _numbers(first, (num_animation,)):
        return f"anchor.first_anim_coeffs is not {num_animation} finite numbers"
    params, size = anchor.get("params"), 6 + num_animation + NUM_ILLUMINATION_TERMS
    if params is not None and not _numbers(params, (size,)):  # (the replay put them into the state: a traceback)
        return f"anchor.params is not {size} finite numbers"
    frame = anchor.get("frame")
    if frame is not None and (not isinstance(frame, int) or isinstance(frame, bool) or frame < 0):
        return "anchor.frame is not a frame index"
    if _not_rotations(np.asarray(anchor["head_rotation"], dtype=np.float64)[None])[0]:
        return "anchor.head_rotation is not a rotation"
    return None


@dataclass(frozen=True)
class _Record:
    """A partial run's record (:func:`_write_record`) as read once on ``--resume``, for every check of it
    (:func:`_changed_input`, :func:`_check_record_model`, :func:`_check_record_smoothing`, :func:`_read_record`;
    each read and parsed the file itself, four times a video). ``found``: the file is there; ``readable``: it was
    read and parsed as JSON, into ``value`` (None otherwise)."""

    path: Path
    found: bool
    readable: bool
    value: Any = None  # (JSON: any of its values; each check catches what a wrong one raises)


def _load_record(path: Path) -> _Record:
    """Read and parse the record at ``path`` (:class:`_Record`)."""
    if not path.is_file():
        return _Record(path, found=False, readable=False)
    try:
        return _Record(path, found=True, readable=True, value=json.loads(path.read_text(encoding="utf-8")))
    except (OSError, ValueError):
        return _Record(path, found=True, readable=False)


def _read_record(
    loaded: _Record, video: Path, settings: dict[str, object], values: dict[str, object], num_shape: int,
    num_animation: int,
) -> _Anchor | None:
    """The re-anchoring in a partial run's record ``loaded`` (:func:`_load_record`; None: none); ``settings``: this
    run's (:func:`_settings`), ``values``: its :func:`_setting_values` (the defaults of the fields a record of an
    earlier version lacks, :func:`_with_defaults`); ``num_shape``, ``num_animation``: the model's units, the sizes of
    the re-anchoring's fields.

    Raises:
        InputError: the record belongs to another input, was made with other settings or from an input file
            that has changed since (:func:`_settings`), cannot be read, is damaged (:func:`_anchor_problem`), or
            is missing (every partial CSV with rows has one, written before its first row: without it, nothing
            says what the rows were made with, and a resume with another --focal went on silently).
    """
    path = loaded.path
    if not loaded.found:
        raise InputError(f"{path}: cannot resume, the partial CSV's record (what its rows were made with) is missing: "
                         "run without --resume")  # fmt: skip
    try:
        if not loaded.readable:
            raise ValueError
        record = loaded.value
        made_from, anchor = record["input"], record["anchor"]
        made_with = record.get("settings", settings)  # records before settings: nothing to compare
        if not isinstance(made_with, dict) or not isinstance(made_from, str):
            raise TypeError
        if record.get("settings_as") != "json" and made_with is not settings:  # an earlier version's: reprs
            made_with = {k: v if k in ("input file", "first-frame landmarks") else _from_repr(v)
                         for k, v in made_with.items()}  # fmt: skip
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        raise InputError(f"{path}: cannot resume, this record is unreadable: run without --resume") from None
    made_with = _with_defaults(made_with, values)  # (a field added since: its default, what that version did)
    made_with = _ran_online_start(made_with, _RECORD_KEYS)  # (an earlier version's online start where none ran)
    problem = _anchor_problem(anchor, num_shape, num_animation)
    if problem is not None:  # (it raised a bare TypeError or RuntimeError later, or resumed from NaN silently)
        raise InputError(f"{path}: cannot resume, this record is damaged ({problem}): run without --resume")
    _check_made_from(made_from, video, f"{path}: the partial results were")
    # (compared as text, an upgrade that added a field to TrackerConfig, or 5 for 5.0, refused an equal setting)
    differ = _changed_settings(made_with, settings)
    # (made with a model, or with the expression kept: settings a record holds only when given)
    differ += [k for k in ("--model", "--keep-expression", "--fps") if k in made_with and k not in settings]
    if differ:
        what = "; ".join(_said_difference(k, made_with.get(k), settings.get(k)) for k in differ)
        raise InputError(
            f"{path}: cannot resume, the partial results were made with other settings or input ({what}): run "
            "with the interrupted run's settings, or without --resume"
        )
    return anchor


def _check_record_model(loaded: _Record, settings: dict[str, object]) -> None:
    """Refuse to resume the partial run of record ``loaded`` (:func:`_load_record`) where another face model made it
    than ``settings``' (:func:`_settings`' ``--model``, :func:`_model_setting`): checked before the partial CSV's
    columns are compared with this run's (:class:`~torchface.io.table.TrackCsvWriter`'s "its columns differ" said
    nothing of the model). No record, or one that cannot be read: left to :func:`_read_record`."""
    try:
        made = loaded.value["settings"].get("--model")
    except (KeyError, TypeError, AttributeError):  # (None where it is missing or unreadable: a TypeError)
        return
    if made != settings.get("--model"):
        raise InputError(f"{loaded.path}: cannot resume, the partial results were made with another face model "
                         f"({_said_difference('--model', made, settings.get('--model'))}): run with the interrupted "
                         "run's --model, or without --resume")  # fmt: skip


def _check_record_smoothing(loaded: _Record, settings: dict[str, object]) -> None:
    """Refuse to resume the partial run of record ``loaded`` (:func:`_load_record`) made with another ``--smooth``
    setting than ``settings``' (:func:`_settings`), before the partial CSV's columns are compared (with ``--smooth``
    on one side only they differ, and "its columns differ" said nothing of why). No record, or one that cannot be
    read: left to :func:`_read_record`."""
    try:
        made = loaded.value["settings"].get("--smooth")
    except (KeyError, TypeError, AttributeError):  # (None where it is missing or unreadable: a TypeError)
        return
    now = settings.get("--smooth")
    if (made is None) != (now is None) or (made is not None and _setting_differences(made, now)):
        raise InputError(f"{loaded.path}: cannot resume, the partial results were made with another smoothing "
                         f"({_said_difference('--smooth', made, now)}): run with the interrupted run's --smooth "
                         "setting, or without --resume")  # fmt: skip


def _check_made_from(made_from: str, video: Path, subject: str) -> None:
    """Refuse to resume results made from ``made_from``, not from ``video`` (``subject``: what the message says
    they are, with its verb: "<csv> was", "<record>: the partial results were")."""
    if Path(made_from).resolve() != video.resolve():
        raise InputError(f"{subject} made from {made_from}, not {video}: use another --out, or run without --resume")


def _rows_to_internal(params: Tensor, head_R: Tensor, head_t: Tensor, layout: ParamLayout) -> Tensor:
    """Packed parameters of CSV rows (the first result's head frame) in a re-anchored stream's own frame: the
    inverse of :func:`torchface.tracker.managed._in_head_frame` (``R D``, ``R d + t``) for offsets ``(D, d)``."""
    R = axis_angle_to_matrix(params[:, layout.rotation])
    R_own = torch.matmul(R, head_R.transpose(1, 2))
    t_own = params[:, layout.translation] - torch.matmul(R_own, head_t.unsqueeze(-1)).squeeze(-1)
    out = params.clone()
    out[:, layout.rotation], out[:, layout.translation] = matrix_to_axis_angle(R_own), t_own
    return out


def _first_landmarks(
    reader: FrameReader, first: Tensor, landmarks: str | os.PathLike[str] | None, detector, detector_name: str | None,
    count: int = NUM_LANDMARKS,
) -> tuple[np.ndarray, str] | None:
    """The landmarks of frame ``first`` (a landmarks file's, of ``count`` points: the model's, or the detector's)
    and where they come from; None where the detector finds no face in it."""
    W, H = reader.info.width, reader.info.height
    if landmarks is not None:  # (str() of an os.PathLike that is not a Path, an os.DirEntry, is its repr)
        return read_landmarks(landmarks, W, H, count=count), os.fspath(landmarks)
    points = detector(detector_image(first))
    if points is None:
        return None
    # (half of them inside: dlib's predictor places the chin of a face at the frame's edge just outside it)
    where = f"{reader.info.path}: detector landmarks"
    return check_landmarks(points, W, H, where, min_inside=0.5), f"detector:{detector_name}"


def _name_key(name: str) -> str:
    """``name`` as a file system that ignores case and Unicode normalisation compares it (macOS, Windows): two names
    of one key are one file there."""
    return unicodedata.normalize("NFC", name).lower()


def _path_key(path: Path) -> tuple[Path, str]:
    """``path`` resolved, its file name as :func:`_name_key` (its folder as given: compared exactly)."""
    path = path.resolve()
    return path.parent, _name_key(path.name)


def _same_file(a: Path, b: Path) -> bool:
    """Whether paths ``a`` and ``b`` are one input (one path resolved, or one file: ``A.mp4`` and ``a.mp4`` on a
    case-insensitive file system, a hard link)."""
    if a.resolve() == b.resolve():
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:
        return False


def _check_unique(videos: Sequence[Path], names: Sequence[str]) -> None:
    """Refuse two inputs with one output name, naming both (among many inputs "two inputs" named neither): the same
    input given twice, or two of one name (``a/clip.mp4`` and ``b/clip.mp4``, ``clip.mp4`` and ``clip.avi``), or of
    names that differ only in case or Unicode normalisation (``A.mp4`` and ``a.mp4``): on a case-insensitive file
    system (macOS, Windows) their outputs are the same files, the second video's replacing the first's; refused on
    every system, so that a run does not depend on the file system it writes to."""
    first: dict[str, tuple[Path, str]] = {}
    for v, name in zip(videos, names):
        key = _name_key(name)
        if key not in first:
            first[key] = (v, name)
            continue
        other, other_name = first[key]
        if _same_file(other, v):
            raise InputError(f"{v}: this input is given twice ({other} and {v}): give each input once")
        if other_name == name:
            raise InputError(f"{other} and {v} would write the same outputs {name!r}: rename one of them, or track "
                             "them with different --out folders")  # fmt: skip
        nfc = unicodedata.normalize("NFC", other_name) == unicodedata.normalize("NFC", name)
        how = ("in how their accents are encoded", "macOS") if nfc else ("in case", "macOS and Windows")
        raise InputError(f"{other} and {v} would write outputs whose names differ only {how[0]} ({other_name!r} and "
                         f"{name!r}): the same files on {how[1]}'s usual file systems: rename one of them, or track "
                         "them with different --out folders")  # fmt: skip


def _check_inputs_kept(
    videos: Sequence[Path], names: Sequence[str], landmarks: Sequence[str | os.PathLike[str]], out_dir: Path,
    meshes: bool,
) -> None:
    """Refuse a run whose outputs would replace what it reads: an output with the path of an input or of a
    landmarks file (``clip.csv`` beside ``clip.mp4`` with ``--out`` their folder; a fresh run deletes it before
    tracking), also where the names differ only in case (``IMG_1.csv`` of ``IMG_1.MOV`` and the landmarks
    ``img_1.csv``: one file on macOS and Windows; refused on every system, :func:`_name_key`), or an output folder
    that is an image-folder input (the next run would read the plot PNG as a frame).

    Raises:
        OutputError: naming the output and what it would replace.
    """
    read = {_path_key(Path(v)): f"the input {v}" for v in videos}
    read.update({_path_key(Path(f)): f"the landmarks file {Path(f)}" for f in landmarks})
    for v in videos:
        if v.is_dir() and v.resolve() == out_dir.resolve():
            raise OutputError(f"{out_dir}: the output folder is the image folder {v}, whose frames are every image "
                              "in it (the plot PNG would be one): give another --out")  # fmt: skip
    for v, name in zip(videos, names):
        for kind, path in output_paths(out_dir, name).items():
            what = read.get(_path_key(path)) if kind != "meshes" or meshes else None
            if what is not None:
                raise OutputError(f"{path}: the {kind} output of {v} would replace {what}: give another --out, or "
                                  "rename that file")  # fmt: skip


def _check_resumable(
    video: Path, paths: dict[str, Path], config: JobConfig, model: FaceModel,
    landmarks: str | os.PathLike[str] | None = None,
) -> str | None:
    """Refuse to skip a video whose complete outputs (their sidecar) were made from another input, from its file as
    it was before it changed (the sidecar's ``input.identity``, :func:`_input_identity`; a sidecar without it, or an
    input gone: not compared), from other first-frame landmarks than the file ``landmarks`` now holds (the
    sidecar's ``initial_landmarks_px``, compared exactly, as the sidecar stores them, a missing point's
    ``[null, null]`` equal to a NaN row; a file fixed in place kept the results of its old points; a sidecar without
    them: not compared), or with other settings than
    ``config``'s (those :func:`_result_settings` names, compared by :func:`_setting_differences`; a sidecar without
    one of them: not compared; a field of a settings dataclass it lacks: compared at its default,
    :func:`_with_defaults`), with another face model than ``model`` (the sidecar's ``model.sha256``; a sidecar without
    it was made with CANDIDE-3), at another rate than ``config.fps`` gives an input without one of its own (the
    sidecar's ``input.fps`` where ``input.fps_given`` or ``input.fps_assumed``, against ``config.fps`` or
    :data:`~torchface.io.video.ASSUMED_FPS`; an input with its own rate: not compared), or without the meshes
    ``config.meshes`` asks for.

    Returns:
        The name of the failure of the start that the sidecar records (its ``start.failure``, :func:`_start_record`;
        :attr:`VideoSummary.start_failure` of the video skipped as complete); None where it started, or the sidecar
        says nothing of it (made before it did).
    """
    try:
        sidecar = json.loads(paths["json"].read_text(encoding="utf-8"))
        made, made_with = sidecar["input"], sidecar.get("config", {})
        made_from = made.get("resolved_path", made["path"])  # sidecars before resolved_path: the path as given
        if not isinstance(made_from, str) or not isinstance(made_with, dict):  # (null or a number: a TypeError's
            raise TypeError  # traceback from Path)
        points = sidecar.get("initial_landmarks_px") if landmarks is not None else None
        made_lm = None if points is None else np.array(
            [[np.nan if c is None else float(c) for c in p] for p in points], dtype=np.float64
        )  # fmt: skip
        size = (int(made["width"]), int(made["height"])) if made_lm is not None else (0, 0)  # (the points' frame)
        made_model = sidecar.get("model", {})
        made_digest, made_name = made_model.get("sha256", _candide_digest()), made_model.get("name", "CANDIDE-3")
        # (the rate of an input without one of its own, --fps's or the one assumed; a sidecar of an input with its own
        # rate, or of an earlier version without fps_assumed: not compared)
        rated = made.get("fps_given") is True or made.get("fps_assumed") is True
        made_fps = float(made["fps"]) if rated else None
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        raise InputError(f"{paths['json']}: cannot resume, this sidecar is unreadable: run without --resume") from None
    _check_made_from(made_from, video, f"{paths['csv']} was")
    then = made.get("identity")  # (sidecars before it: not compared)
    try:
        now = _input_identity(video) if isinstance(then, str) else then
    except OSError:  # (gone: the complete outputs stand, as they did before the identity was recorded)
        now = then
    if now != then:  # (it was skipped as complete: a truncated download tracked, then downloaded again whole,
        # kept the truncated one's rows, status 0)
        raise InputError(f"{paths['json']}: cannot resume, these complete outputs were made from {video} as it was "
                         f"before it changed ({then} then, {now} now): track it again without --resume (given "
                         "alone, the other videos' outputs are kept)")  # fmt: skip
    if made_digest != _digest(model):  # (skipped as complete: the CSV's columns and values were another model's)
        raise InputError(f"{paths['json']}: cannot resume, these complete outputs were made with another face model "
                         f"({made_name}, sha256 {str(made_digest)[:16]}, then; {_model_label(model)} now): run with "
                         "their --model, or without --resume")  # fmt: skip
    if made_lm is not None and landmarks is not None:
        now_lm = read_landmarks(landmarks, *size, count=model.num_landmarks)
        if made_lm.shape != now_lm.shape or not np.array_equal(made_lm, now_lm, equal_nan=True):
            what = _landmarks_difference(made_lm, now_lm)
            raise InputError(f"{paths['json']}: cannot resume, these complete outputs were made from other first-frame "
                             f"landmarks than {os.fspath(landmarks)} holds now ({what}): run without --resume")
    now = _as_json(_result_settings(config))  # as the sidecar holds them
    made_with = {"smoothing": None, "keep_expression": False, **made_with}  # (sidecars before them: without)
    made_with = _ran_online_start(_with_defaults(made_with, _result_settings(config)))  # (a field added since: at
    # its default; an earlier version's online_start where none ran: none)
    differ = [k for k in now if k in made_with and _setting_differences(made_with[k], now[k])]
    now_fps = ASSUMED_FPS if config.fps is None else config.fps
    if rated and made_fps != now_fps:  # (its timestamps and videos at another rate than --fps asks for now)
        differ.append("fps")
        made_with = {**made_with, "fps": None if made.get("fps_given") is not True else made_fps}
        now = {**now, "fps": config.fps}
    if differ:  # (it was skipped as complete: a --resume over many videos with another --focal kept the old ones)
        names = {"focal": "--focal", "convert": "--convert", "lookahead": "--lookahead", "online_start": "online start",
                 "detector": "--detector", "smoothing": "--smooth", "keep_expression": "--keep-expression",
                 "fps": "--fps"}  # fmt: skip
        what = "; ".join(_said_difference(names.get(k, k.replace("_", " ")), made_with[k], now[k]) for k in differ)
        raise InputError(f"{paths['json']}: cannot resume, these complete outputs were made with other settings "
                         f"({what}): run with their settings, or without --resume")  # fmt: skip
    # (skipped as complete, without the meshes asked for; a folder of that name may hold only the user's files)
    if config.meshes and not (paths["meshes"].is_dir() and _frame_meshes(paths["meshes"])):
        raise InputError(f"{paths['json']}: cannot resume, these complete outputs were made without --meshes (no "
                         f"{paths['meshes'].name}/): run without --meshes, or without --resume")  # fmt: skip
    start = sidecar.get("start")
    failure = start.get("failure") if isinstance(start, dict) else None
    return str(failure["name"]) if isinstance(failure, dict) and "name" in failure else None


def _landmarks_difference(then: np.ndarray, now: np.ndarray) -> str:
    """How first-frame landmarks ``then`` and ``now`` (``(68, 2)``, NaN rows: missing points) differ, in words: the
    count of points that differ and the first of them: ``2 points differ, e.g. point 5: (10.0, 20.0) then, missing
    now``."""
    if then.shape != now.shape:
        return f"{counted(len(then), 'point')} then, {len(now)} now"
    same = (then == now) | (np.isnan(then) & np.isnan(now))
    differ = np.flatnonzero(~same.all(axis=1))
    k = int(differ[0])

    def said(p: np.ndarray) -> str:
        return "missing" if np.isnan(p).all() else f"({float(p[0])!r}, {float(p[1])!r})"

    many = f"{len(differ)} points differ, e.g." if len(differ) > 1 else "1 point differs:"
    return f"{many} point {k}: {said(then[k])} then, {said(now[k])} now"


def _result_settings(config: JobConfig) -> dict[str, object]:
    """The settings a video's results depend on, under the names of the sidecar's ``config`` (which also says the
    device, the landmarks' source, ``resume`` and the batch size): :func:`_check_resumable` compares them.
    ``online_start``: the online start that ran (:func:`_online_start`), None with ``--lookahead`` or without
    template management, where ``JobConfig.refine_first`` is not used (it was recorded there all the same, and the
    sidecar of a ``--lookahead`` run said an online start it never made: :func:`_ran_online_start`)."""
    return {"tracker": config.tracker, "focal": config.focal, "detector": config.detector,
            "lookahead": config.lookahead, "online_start": _online_start(config), "convert": config.convert,
            "normalised_size": config.normalised_size, "redetect_after": config.redetect_after,
            "redetect_below": config.redetect_below, "smoothing": config.smoothing,
            "keep_expression": config.keep_expression}  # fmt: skip


#: The names of the look-ahead, the online start and the tracker settings in a partial run's record
#: (:func:`_setting_values`), for :func:`_ran_online_start`; its defaults are the sidecar's (:func:`_result_settings`).
_RECORD_KEYS: tuple[str, str, str] = ("--lookahead", "online start", "tracker settings")


def _ran_online_start(
    made_with: dict, keys: tuple[str, str, str] = ("lookahead", "online_start", "tracker")
) -> dict:
    """A sidecar's ``config`` (as JSON, its fields filled in, :func:`_with_defaults`) with ``online_start`` None
    where no online start ran (:func:`_online_start`: ``lookahead`` set, or ``tracker.template.enabled`` false), as
    :func:`_result_settings` records it now: the sidecars of earlier versions held ``JobConfig.refine_first`` there
    all the same, and a ``--lookahead`` run resumed over its own complete outputs was refused over a setting it
    does not use ("online start on then, off now"). ``keys``: the names of the look-ahead, the online start and the
    tracker settings; a partial run's record (:func:`_setting_values`) under its own (:data:`_RECORD_KEYS`), whose
    ``--resume`` of a ``--lookahead`` run with or without ``--no-online-refine`` was refused alike."""
    lookahead, online_start, tracker_key = keys
    tracker = made_with.get(tracker_key)
    template = tracker.get("template") if isinstance(tracker, dict) else None
    templates_off = isinstance(template, dict) and template.get("enabled") is False
    if online_start in made_with and (made_with.get(lookahead) is not None or templates_off):
        return {**made_with, online_start: None}
    return made_with


def _open_inputs(
    videos: Sequence[Path], config: JobConfig, detector, model: FaceModel,
    progress: Callable[[Progress], None] | None = None, skipped: dict[int, str] | None = None,
) -> list[_Stream]:
    """Check every input before any tracking starts: open it, read its first frame, find its first-frame landmarks;
    then close it again (its batch reopens it, :func:`_reopen`): with all of them held open until the end, a run
    over many videos ran out of file descriptors (1024 inputs at the usual ``ulimit -n``: "Too many open files",
    blamed on one of them) and held every video's first frame and decoder while the other sizes were tracked. Those
    of the first batch (the first :func:`_batch_size` of the first input's :func:`_batch_key`) are held open at
    their first frame (:attr:`_Stream.held`), that batch going on from them: reopened, each was decoded again (a
    4K video's first frame took 0.5 s, 1080p 0.1 s); never more than ``max_batch`` inputs open at once, as when
    tracking, and none on a resume (its checkpoints' batches come first).

    Where the detector finds no face in the first frame (a title card, a black frame, an empty room), it is asked
    about each next frame until it finds one (``progress`` reports the search, :attr:`Progress.searching`): the
    video is tracked from that frame (``_Stream.start``), as the video cut to start there would be, and its rows
    before it have no estimate (:func:`_no_face_row`; it was refused). A video in none of whose frames it finds a
    face is an :class:`InputError` (nothing of the run is written). A resumed video starts where the interrupted
    run's record says it found the face (:func:`_recorded_first_face`), the detector not asked again.

    With ``skipped`` (``JobConfig.keep_going``) a refused input is skipped (:func:`_warn_skipped`) and its message
    kept in ``skipped`` under its index in ``videos``; the streams of the others are returned.

    Raises:
        InputError: inputs that cannot be tracked: one's error as :func:`_open_input` says it, several named in one
            message (``2 of the 40 inputs refused, nothing tracked: (1) ... (2) ...``, the first
            :data:`MAX_REFUSED_SHOWN`): every input is checked (the error named the first alone, and a run over many
            videos was refused again for each of the others in turn).
    """
    names = [output_name(v) for v in videos]  # distinct: track_videos checked all the inputs' names
    streams: list[_Stream] = []
    refused: list[str] = []  # (every input is checked: one error names them all, not the first alone)
    first: tuple[int, int, int] | None = None  # the first batch's _batch_key
    first_count = held = 0  # the inputs of that key checked, those held
    try:
        for k, (path, name) in enumerate(zip(videos, names)):
            try:
                stream = _open_input(path, name, k, videos, config, detector, model, progress)
            except InputError as exc:
                if skipped is not None:  # (keep_going: said as it is skipped, the others tracked)
                    _report_skipped(progress, k, len(videos), name)
                    skipped[k] = _warn_skipped(path, exc)
                    continue
                refused.append(str(exc))
                continue
            streams.append(stream)
            key = _batch_key(stream, config)
            first = key if first is None else first
            in_first = key == first and first_count < _batch_size(key[0], key[1], config)  # (in the first batch)
            first_count += key == first
            # (the next input's check opens one more: at most max_batch open at once, as when tracking)
            room = held < config.max_batch - 1 or k == len(videos) - 1
            if stream.held is not None and (refused or config.resume or not in_first or not room):
                _let_go(stream)
            held += stream.held is not None
    except BaseException:
        for s in streams:
            _let_go(s)
        raise
    if refused:
        for s in streams:
            _let_go(s)
    if len(refused) == 1:
        raise InputError(refused[0])
    if refused:
        shown = " ".join(f"({i}) {m}" for i, m in enumerate(refused[:MAX_REFUSED_SHOWN], start=1))
        more = f" and {len(refused) - MAX_REFUSED_SHOWN} more" if len(refused) > MAX_REFUSED_SHOWN else ""
        raise InputError(f"{len(refused)} of the {len(videos)} inputs refused, nothing tracked: {shown}{more}")
    return streams


def _let_go(s: _Stream) -> None:
    """Close the reader of ``s`` held open since its check (:attr:`_Stream.held`; nothing where it is not): its batch
    reopens it."""
    if s.held is not None:
        s.held = None
        s.reader.close()


def _batch_key(s: _Stream, config: JobConfig) -> tuple[int, int, int]:
    """What the videos of one batch share: frame height, width and pyramid levels (:func:`~torchface.tracker.step.
    pyramid_for_faces` of the video's own face, so that a video's results do not depend on the others')."""
    H, W = s.reader.info.height, s.reader.info.width
    return H, W, pyramid_for_faces(config.tracker, torch.as_tensor(s.landmarks)[None], (H, W)).num_levels


def _batch_size(height: int, width: int, config: JobConfig) -> int:
    """The most videos of ``height x width`` frames in one batch: ``max_batch``, and :data:`BATCH_PIXELS` allow."""
    return max(1, min(config.max_batch, BATCH_PIXELS // (height * width)))


#: The refused inputs that :func:`_open_inputs`' error names (the others are counted).
MAX_REFUSED_SHOWN = 10


def _warn_skipped(path: Path, exc: BaseException, what: str = "skipped") -> str:
    """Warn (:class:`InputSkipped`, one line) that input ``path`` is ``what`` (skipped, or stopped partway) because of
    ``exc`` (an :class:`InputError`), as it is (``JobConfig.keep_going``); returns ``exc``'s message on one line (the
    :class:`VideoSummary`'s ``refused`` or ``stopped``)."""
    message = _worded(" ".join(str(exc).split()))  # (a Python caller's in JobConfig's words)
    said = message.removeprefix(f"{path}: ")  # (most name the input first: not twice)
    warnings.warn(f"{what} {path}: {said}", InputSkipped, stacklevel=2)
    return message


def _report_skipped(progress: Callable[[Progress], None] | None, index: int, count: int, name: str) -> None:
    """Report (:attr:`Progress.skipped`) that input ``index`` of ``count`` (output stem ``name``) is skipped."""
    if progress is not None:
        progress(Progress(index, count, name, 0, None, 0.0, 0.0, skipped=True))


def _refused_summary(path: Path, name: str, message: str) -> VideoSummary:
    """The :class:`VideoSummary` of input ``path`` (output stem ``name``) skipped for ``message``
    (``JobConfig.keep_going``): nothing of it written."""
    return VideoSummary(name, path, (), 0, 0, 0.0, 0.0, refused=message)


def _stopped_summary(s: _Stream, csv: Path, message: str) -> VideoSummary:
    """The :class:`VideoSummary` of ``s``'s video, stopped partway for ``message`` (``JobConfig.keep_going``): its
    partial CSV (``csv``'s ``.partial``) and its complete rows, as that file holds them."""
    partial = partial_path(csv)
    frames, lost, mean = _complete_rows(partial), 0, 0.0
    with contextlib.suppress(InputError, OSError, ValueError, IndexError):  # (the counts of its lines alone)
        cols, rows = read_track_csv(partial)
        frames, lost = len(rows), int((rows[:, cols.index("success")] < 0.5).sum()) if len(rows) else 0
        mean = float(rows[:, cols.index("confidence")].mean()) if len(rows) else 0.0
    outs = (partial,) if partial.is_file() else ()
    return VideoSummary(s.name, Path(s.reader.info.path), outs, frames, lost, mean, 0.0, stopped=message)


def _open_input(
    path: Path, name: str, k: int, videos: Sequence[Path], config: JobConfig, detector, model: FaceModel,
    progress: Callable[[Progress], None] | None,
) -> _Stream:
    """:func:`_open_inputs`' check of input ``k`` (``path``, output stem ``name``): its stream, its reader closed
    again, or left open where the check read its first frame alone and the face is on it (its :attr:`_Stream.held`
    set: :func:`_open_inputs` holds it or closes it).

    Raises:
        InputError: the input cannot be tracked (unreadable, a bad first frame or landmarks file, no face found).
    """
    reader = open_frames(path, convert=config.convert, fps=config.fps)
    try:
        if config.fps is not None and not reader.info.fps_given:  # (its frames' times are the container's)
            warnings.warn(_worded(f"{path}: --fps {config.fps:g} not used for it: the video gives its own frame "
                                  f"rate, {reader.info.fps:g} frames/s, which its timestamps and overlay follow"),
                          UserWarning, stacklevel=2)  # fmt: skip
        if reader.info.declared_fps is not None:  # (0.0005: its overlay could not be written at it)
            low, high = PLAUSIBLE_FPS
            other = "" if reader.info.fps_given else " (--fps gives another)"
            warnings.warn(_worded(f"{path}: its container declares {reader.info.declared_fps:g} frames/s, not a "
                                  f"plausible frame rate (one in ({low:g}, {high:g})): taken as none, its overlay and "
                                  f"normalised videos at {reader.info.fps:g} frames/s{other}; the container's own "
                                  "frame times are still the rows' timestamps"), UserWarning, stacklevel=2)  # fmt: skip
        frame = next(reader)
        lm = config.landmarks[k] if config.landmarks else None
        t0 = time.perf_counter()
        recorded = _recorded_first_face(config, reader, name, model) if config.resume and lm is None else None
        if recorded is not None:  # (the interrupted run's search: not made again, its calls counted as it did)
            start, calls = recorded[0], recorded[0] + 1
            points, source = recorded[1], f"detector:{config.detector}"
        else:  # (only a detector finds no face: a landmarks file's are the first frame's)
            find = partial(_first_landmarks, reader, landmarks=lm, detector=detector, detector_name=config.detector,
                           count=model.num_landmarks)  # fmt: skip
            searching: Callable[[int], None] | None = None
            if progress is not None:
                searching = partial(_report_search, progress, k, len(videos), name, reader, t0)
            start, _, (points, source) = search_first_face(
                itertools.chain([frame], reader), find, f"{path}: the {config.detector} detector",
                " (give the 68 landmarks of its first frame with --landmarks FILE if it shows one)", searching,
            )  # fmt: skip
            calls = start + 1 if lm is None else 0
    except BaseException:
        reader.close()
        raise
    stream = _Stream(name, reader, points, source, reader.info.num_frames, detector_calls=calls, start=start, index=k)
    if start == 0 and reader.frames_read == 1:  # (what _next_frame keeps of it, as a batch reopening it would)
        stream.held = frame, 0.0 if reader.timestamp is None else reader.timestamp, reader.image
    else:
        reader.close()
    return stream


def _report_search(
    progress: Callable[[Progress], None], index: int, count: int, name: str, reader: FrameReader, t0: float, done: int
) -> None:
    """Report that the detector has found no face in the first ``done`` frames of stream ``index``'s video ``name``
    (:attr:`Progress.searching`; ``t0``: when the search started)."""
    rate = done / max(time.perf_counter() - t0, 1e-9)
    progress(Progress(index, count, name, done, reader.info.num_frames, rate, 0.0, True))


def _reopen(streams: Sequence[_Stream], convert: bool, keep_going: bool = False) -> None:
    """Open the inputs of a batch again (:func:`_open_inputs` closed them) at their first frame, or go on from it
    where it held them open (:attr:`_Stream.held`: the first batch's). With ``keep_going``, one that cannot be is
    closed and skipped (:func:`_warn_skipped`; ``_Stream.refused``), the others opened.

    Raises:
        InputError: an input that cannot be opened now, or whose frames have changed size since it was checked.
    """
    try:
        for s in streams:
            info = s.reader.info
            try:
                first, s.held = s.held, None
                if first is None:  # (else open since its check, at its first frame: not opened and decoded again)
                    s.reader = open_frames(info.path, convert=convert, fps=info.fps if info.fps_given else None)
                    if (s.reader.info.height, s.reader.info.width) != (info.height, info.width):
                        raise InputError(f"{info.path}: its frames are {s.reader.info.width}x{s.reader.info.height} "
                                         f"now, {info.width}x{info.height} when the run started: was it replaced?")
                if READ_AHEAD > 0 and len(streams) <= READ_AHEAD_STREAMS:  # (a held reader is a FrameReader too)
                    s.reader = _ReadAhead(cast(FrameReader, s.reader))
                s.stamps.clear()
                s.images.clear()
                if first is None:
                    s.last_frame = _next_frame(s)
                else:
                    s.last_frame = first[0]
                    s.stamps.append(first[1])
                    s.images.append(first[2])
            except InputError as exc:
                if not keep_going:
                    raise
                s.reader.close()
                s.refused = _warn_skipped(Path(info.path), exc)
    except BaseException:
        for s in streams:
            s.reader.close()
        raise


def _release(streams: Sequence[_Stream]) -> None:
    """Close the inputs of a tracked batch and drop the frames they hold."""
    for s in streams:
        s.reader.close()
        s.last_frame, s.ahead = None, []
        s.stamps.clear()
        s.images.clear()


def track_videos(
    videos: Sequence[str | os.PathLike[str]],
    config: JobConfig,
    progress: Callable[[Progress], None] | None = None,
) -> list[VideoSummary]:
    """Track every video and write its outputs (see the module docstring).

    Its messages (errors, warnings, the summaries' ``refused`` and ``stopped``, an interruption's ``kept``) name the
    :class:`JobConfig` fields to set, ``call track_videos again with JobConfig(resume=True)``, ``run with
    resume=False``, where ``torchface track``'s name its options, ``--resume`` (:func:`_worded`).

    Args:
        videos: input paths (video files, image folders or ``.npy`` arrays, :func:`torchface.io.open_frames`).
        config: :class:`JobConfig`.
        progress: called after every batch step with one :class:`Progress` per stream.

    Returns:
        One :class:`VideoSummary` per video, in input order; with ``config.keep_going`` the inputs skipped and the
        videos stopped partway among them (their ``refused``, ``stopped``; ``complete`` False), where without it the
        run raises (``InputError``, :class:`VideosStopped`).

    Raises:
        TypeError: ``videos`` is one path, not a sequence of them, or holds something else than paths; ``config``
            is not a :class:`JobConfig` (the landmarks files given in its place: told where they go).
        InputError: an empty path among ``videos`` (``Path("")`` is the current folder); a bad input (each video's
            first frame and landmarks are checked before tracking starts; the message names every input refused,
            :func:`_open_inputs`; with ``keep_going`` it is skipped instead); two inputs of one output name, or the
            number of landmarks files (with ``keep_going`` too).
        VideosStopped: (an InputError; not with ``keep_going``) a later frame that cannot be read stopped a video, or
            a resumed video's replayed row whose ``timestamp`` is not its frame's time (:func:`_check_replayed_time`);
            raised once every other video is complete, with their summaries.
        OutputError: the output folder cannot be written, or an output would replace an input or a landmarks
            file, or the output folder is an image-folder input, or an output's name (with its temporary suffix,
            up to 23 bytes) would be too long for the output folder's file system, or another run is writing the
            outputs of one of the videos there (its ``<stem>.lock``, :func:`_take_locks`).
        torchface.detect.DetectorUnavailable: the detector is needed but not installed.
        KeyboardInterrupt: (Ctrl-C) passed on, its writers stopped, with a ``kept`` attribute saying what the run
            leaves for ``resume`` (:func:`_kept_outputs`: the partial CSVs and their complete rows, the videos
            complete; or that nothing was written, interrupted before tracking). In the per-frame loop, SIGINT's and
            SIGTERM's Python handlers (the caller's own too) run at the end of the step under way, after every
            live video's checkpoint (:class:`_AtStepBoundary`; the main thread only, the handlers given back after);
            where the step or its checkpoint failed meanwhile (a full disk), the interruption has that exception as
            its ``error`` attribute (the command line says it, then that it was interrupted).
    """
    try:
        if isinstance(videos, (str, bytes, os.PathLike)):  # one path: its characters were taken as inputs
            raise TypeError(f"videos must be a sequence of paths, e.g. [{str(videos)!r}] for one video")
        videos = list(videos)
        for k, v in enumerate(videos):  # (Path("") is ".": the current folder's images were tracked as a video)
            if not isinstance(v, (str, os.PathLike)):
                raise TypeError(f"videos[{k}] must be a path (a str or an os.PathLike), got {type(v).__name__}")
            if os.fspath(v) == "":
                raise InputError(f"videos[{k}] is an empty path (an unset variable?): give a video file, an image "
                                 "folder ('.' for the current one) or a .npy array")  # fmt: skip
        if not isinstance(config, JobConfig):  # (an AttributeError, "'list' object has no attribute 'landmarks'")
            hint = ""
            if isinstance(config, (list, tuple)) or (isinstance(config, (str, os.PathLike)) and config):
                hint = ": the landmarks files go in it, JobConfig(landmarks=(...))"  # (given where the config goes)
            raise TypeError(f"config must be a JobConfig, got {type(config).__name__}{hint}")
        inputs = [Path(v) for v in videos]
        if not inputs:
            raise InputError("no input video given")
        if config.landmarks and len(config.landmarks) != len(inputs):
            raise InputError(f"give one landmarks file per video: {counted(len(inputs), 'video')}, "
                             f"{counted(len(config.landmarks), 'file')}")
        model = _job_model(config)  # (checked before the detector is loaded and any input opened)
        _check_settings_for_model(config, model)  # (before any output is touched)
        detector = None
        if config.detector is not None:
            from torchface.detect import load_detector

            detector = load_detector(config.detector)
        elif not config.landmarks and model.num_landmarks != NUM_LANDMARKS:  # (a detector is refused for it)
            raise InputError(f"no initialisation: give --landmarks FILE (the {model.num_landmarks} landmarks of the "
                             f"face model {model.name!r}, of the first frame, in its order)")  # fmt: skip
        elif not config.landmarks:
            raise InputError(
                "no initialisation: give --landmarks FILE (68 iBUG points of the first frame) or --detector NAME"
            )
        out_dir = Path(config.out_dir)
        _check_out_dir(out_dir)
        names = [output_name(v) for v in inputs]
        _check_unique(inputs, names)
        _check_name_lengths(out_dir, inputs, names)
        _check_inputs_kept(inputs, names, config.landmarks, out_dir, config.meshes)
        for v, name in zip(inputs, names):
            for kind, path in output_paths(out_dir, name).items():
                if kind != "meshes" and path.is_dir():
                    raise OutputError(f"{path}: an output of {v} would go there, but it is a folder")
                if kind == "meshes" and config.meshes and path.exists() and not path.is_dir():
                    raise OutputError(f"{path}: the meshes of {v} would go in this folder, but it is a file")
        locks = _take_locks(out_dir, names)  # (held until the run ends, also on an error or an interruption)
        try:
            try:
                # (a copy: the same object on its device, digested once)
                if model.device != torch.device(config.device):
                    model = model.to(device=torch.device(config.device))
                return _track_locked(inputs, names, config, detector, model, out_dir, progress)
            finally:
                _release_locks(locks)
        except KeyboardInterrupt as exc:  # (its writers stopped: what they leave is on disk)
            _say_kept(exc, _kept_outputs(out_dir, names))
            raise
    except BaseException as exc:  # (a Python caller's in JobConfig's words, the command line's as they are)
        _reword(exc)
        raise


def _say_kept(exc: BaseException, kept: str) -> None:
    """Say on the interruption ``exc`` (a ``KeyboardInterrupt``) what the run leaves for ``--resume``: its ``kept``
    attribute, which the command line prints; unless a step nearer the interruption has said it."""
    if getattr(exc, "kept", None) is None:
        exc.kept = kept  # type: ignore[attr-defined]


def _complete_rows(csv: Path) -> int:
    """The complete rows (lines ended) after the header of a (partial) CSV; 0 where it cannot be read."""
    try:
        with open(csv, "rb") as f:
            lines = sum(chunk.count(b"\n") for chunk in iter(lambda: f.read(1 << 20), b""))
    except OSError:
        return 0
    return max(lines - 1, 0)


def _listed(items: Sequence[str]) -> str:
    """``items`` comma separated for a message, the first ten named and the rest counted."""
    return ", ".join(items[:10]) + (f" and {len(items) - 10} more" if len(items) > 10 else "")


def _kept_outputs(out_dir: Path, names: Sequence[str]) -> str:
    """What an interrupted run leaves of the outputs of videos ``names`` in ``out_dir`` (looked at once its writers
    are stopped), and what to do: the videos complete (their JSON written), the rows a resumed run goes on from (a
    partial CSV's complete rows, or a CSV under its final name without its JSON: interrupted while finalising,
    every row written), the videos of which nothing is kept (a CSV without rows: a resumed run starts it afresh)."""
    complete, rows, none = [], [], []
    for name in names:
        p = output_paths(out_dir, name)
        partial = partial_path(p["csv"])
        recorded = _record_path(p["csv"]).is_file()  # (rows without it are not resumed: _read_record)
        n = _complete_rows(partial) if partial.is_file() and recorded else 0
        if p["json"].is_file() and p["csv"].is_file() and not partial.exists():
            complete.append(name)
        elif n:  # (the file a resumed run goes on from, where both are there)
            rows.append(f"{partial} ({counted(n, 'row')})")
        elif p["csv"].is_file() and recorded:
            n = _complete_rows(p["csv"])
            rows.append(f"{p['csv']} (all {counted(n, 'row')}, not finalised)")
        else:
            none.append(name)

    said = [f"rows kept in {_listed(rows)}"] if rows else []
    said += [f"complete: {_listed(complete)}"] if complete else []
    if not rows and not none:
        return f"every video is complete ({_listed(complete)})"
    if not said:
        return "no row was kept: run the same command again"
    said += [f"nothing kept of {_listed(none)}"] if none else []
    return "; ".join(said) + ": run the same command with --resume to continue"


def _job_model(config: JobConfig) -> FaceModel:
    """The face model of ``config`` (on the CPU): CANDIDE-3, or the file ``config.model``, refused where its
    landmarks cannot start a track (:func:`~torchface.tracker.fit.check_model_landmarks`: fewer than four, or all on
    the midline; the first frame's fit refused it, after the outputs of earlier runs were removed) or, with a
    detector, are not the detector's 68 iBUG points."""
    if config.model is None:
        return _candide3()  # (loaded once per process; a model file is read again for each job: it may change)
    model = load_face_model(config.model)
    try:
        check_model_landmarks(model)
    except ValueError as exc:
        raise InputError(f"{os.fspath(config.model)}: {exc}") from None
    if config.detector is not None and model.num_landmarks != NUM_LANDMARKS:
        raise InputError(
            f"{os.fspath(config.model)}: the face model {model.name!r} has {model.num_landmarks} landmarks, and the "
            f"{config.detector} detector gives the {NUM_LANDMARKS} iBUG points (the first frame's, and those of "
            f"re-detection and recovery): give --landmarks files of the model's {model.num_landmarks} points, without "
            "--detector"
        )
    return model


def _check_settings_for_model(config: JobConfig, model: FaceModel) -> None:
    """Refuse the settings of ``config`` that name or count the face model's units where ``model`` (the job's) has no
    such units: the tracker's ``expression_prior_weights`` (one per animation unit), its landmark fit's
    ``held_shape_units`` and ``shape_prior_precision``, and the look-ahead's or online start's ``shape_units``,
    ``kept_shape_units`` and ``shape_prior_precision``
    (:func:`~torchface.tracker.lookahead.check_model_units`; the online start's only where it runs,
    :func:`_online_start`). The tracker refuses them too, but only once a batch started (the online start's, the
    look-ahead's, once it had read its frames ahead), after a fresh run had cleared the earlier run's outputs of
    those videos: the error left ``.partial`` files where their complete outputs had been.

    Raises:
        ValueError: the first such setting, with the tracker's message.
    """
    tracker = config.tracker
    _unit_weights(tracker, model.num_animation, torch.zeros(0))
    held_shape_indices(tracker.fit, model.shape_names)
    shape_prior_vector(tracker.fit.shape_prior_precision, model.num_shape, torch.float64, "cpu")
    if config.lookahead is not None:
        check_model_units(config.lookahead, model, "lookahead")
    online = _online_start(config)
    if online is not None:
        check_model_units(online, model, "refine_first")


def _track_locked(
    inputs: list[Path], names: list[str], config: JobConfig, detector, model: FaceModel, out_dir: Path,
    progress: Callable[[Progress], None] | None,
) -> list[VideoSummary]:
    """:func:`track_videos` once its inputs are checked and its outputs locked (:func:`_take_locks`)."""
    summaries: dict[str, VideoSummary] = {}
    pending: list[Path] = []
    pending_lm: list[str | os.PathLike[str]] = []
    for k, (v, name) in enumerate(zip(inputs, names)):
        paths = output_paths(out_dir, name)
        if config.resume and paths["json"].is_file() and paths["csv"].is_file():
            try:
                failed = _check_resumable(v, paths, config, model, config.landmarks[k] if config.landmarks else None)
                cols, rows = read_track_csv(paths["csv"])
            except InputError as exc:
                if not config.keep_going:
                    raise
                summaries[str(v)] = _refused_summary(v, name, _warn_skipped(v, exc))  # (its outputs as they were)
                continue
            conf = rows[:, cols.index("confidence")] if len(rows) else np.zeros(0)
            lost = int((rows[:, cols.index("success")] < 0.5).sum()) if len(rows) else 0
            outs = tuple(p for p in paths.values() if p.exists())
            mean = float(conf.mean()) if len(conf) else 0.0
            summaries[str(v)] = VideoSummary(name, v, outs, len(rows), lost, mean, 0.0, True,
                                             start_failure=failed)
            continue
        pending.append(v)
        if config.landmarks:
            pending_lm.append(config.landmarks[k])
    sub = replace(config, landmarks=tuple(pending_lm))
    skipped: dict[int, str] | None = {} if config.keep_going else None
    try:
        streams = _open_inputs(pending, sub, detector, model, progress, skipped) if pending else []
    except KeyboardInterrupt as exc:  # (nothing of this run is there; an earlier run's outputs are as they were)
        _say_kept(exc, "nothing was written (interrupted before tracking, while checking the inputs or looking for "
                       "a first face): run the same command again")  # fmt: skip
        raise
    for i, message in (skipped or {}).items():
        summaries[str(pending[i])] = _refused_summary(pending[i], output_name(pending[i]), message)
    return _track_opened(streams, inputs, config, detector, model, out_dir, progress, summaries, len(pending))


def _check_frame_sizes(streams: list[_Stream], config: JobConfig) -> None:
    """Refuse the run where a video's frames are too small for the tracker's pyramid (``config.tracker.num_levels``
    levels need :func:`~torchface.tracker.step.min_frame_side` pixels a side, the check of
    :func:`~torchface.tracker.step.check_initialise_inputs`; the levels :func:`~torchface.tracker.step.
    pyramid_for_faces` adds, and the look-ahead's and online start's, which are cut to the tracker's, fit any frame
    that passes), from the sizes the opened inputs declare. The tracker refused them only at its batch's start, after
    a fresh run had cleared the earlier run's outputs of the videos: the error left ``.partial`` files in their place.

    Raises:
        ValueError: the first such video, named, with its size and the least one.
    """
    levels = config.tracker.num_levels
    side = min_frame_side(levels)  # (the tracker's rule)
    for s in streams:
        H, W = s.reader.info.height, s.reader.info.width
        if min(H, W) < side:
            raise ValueError(f"{s.reader.info.path}: frames must be at least {side}x{side} pixels for "
                             f"tracker.num_levels = {levels}, got {W}x{H} (W x H): track it with fewer pyramid levels "
                             "(TrackerConfig.num_levels and its iterations)")  # fmt: skip


def _track_opened(
    streams: list[_Stream], inputs: list[Path], config: JobConfig, detector, model: FaceModel, out_dir: Path,
    progress: Callable[[Progress], None] | None, summaries: dict[str, VideoSummary], count: int,
) -> list[VideoSummary]:
    """:func:`_track_locked` once its inputs are checked (``streams``, :func:`_open_inputs`, of the ``count`` inputs
    checked; ``summaries``: of the videos ``resume`` skipped, and those ``keep_going`` skipped): track and write them,
    batch by batch."""
    try:
        _check_frame_sizes(streams, config)  # (before a fresh run clears the earlier outputs: it raised at the start)
        if not config.resume:  # a fresh run (the inputs keep_going skipped too: every complete output is this run's)
            earlier = [(s.name, Path(s.reader.info.path)) for s in streams]
            earlier += [(x.name, x.input) for x in summaries.values() if x.refused]
            _warn_replaced_inputs(out_dir, earlier)
            _clear_earlier_outputs(out_dir, [name for name, _ in earlier])
        # One batch: videos of one frame size and one pyramid (pyramid_for_faces of each video's own face, so that a
        # video's results do not depend on the others'), as many as max_batch and BATCH_PIXELS allow.
        if config.resume:  # (a video resumed from its checkpoint is tracked with its batch's others again)
            for s in streams:
                s.checkpoint = _load_checkpoint(s, output_paths(out_dir, s.name)["csv"], config, model)
        again = _checkpoint_batches(streams)
        grouped = {i for m in again for i in m}
        groups: dict[tuple[int, int, int], list[int]] = {}
        for i, s in enumerate(streams):
            if i in grouped:
                continue
            groups.setdefault(_batch_key(s, config), []).append(i)
        batches = [m[i : i + n] for key, m in groups.items() for n in [_batch_size(key[0], key[1], config)]
                   for i in range(0, len(m), n)]  # fmt: skip
        for m in reversed(again):  # (first; as many as max_batch and BATCH_PIXELS allow now: a part joined alone)
            H, W = streams[m[0]].reader.info.height, streams[m[0]].reader.info.width
            n = _batch_size(H, W, config)
            batches[:0] = [m[i : i + n] for i in range(0, len(m), n)]
        for i, s in enumerate(streams):  # (held open since its check for the first batch: _open_inputs)
            if not batches or i not in batches[0]:
                _let_go(s)
        for members in batches:
            _reopen([streams[i] for i in members], config.convert, config.keep_going)
            for i in members:
                if streams[i].refused is not None:  # (keep_going: the others are tracked)
                    _report_skipped(progress, streams[i].index, count, streams[i].name)
            batch = [streams[i] for i in members if streams[i].refused is None]
            places = [s.index for s in batch]  # (Progress.index)
            try:
                tracked = _track_group(model, batch, config, detector, progress, count, places) if batch else []
            finally:
                _release(batch)
            for s, summary in zip(batch, tracked):
                if summary is not None:
                    summaries[str(s.reader.info.path)] = summary
                elif s.error is not None and config.keep_going:  # (said as its batch ends)
                    message = _warn_skipped(Path(s.reader.info.path), s.error, "stopped")
                    summaries[str(s.reader.info.path)] = _stopped_summary(s, output_paths(out_dir, s.name)["csv"],
                                                                          message)  # fmt: skip
        for s in streams:  # (keep_going: refused as its batch opened)
            if s.refused is not None:
                summaries[str(s.reader.info.path)] = _refused_summary(Path(s.reader.info.path), s.name, s.refused)
    finally:
        for s in streams:
            s.reader.close()
    failed = [s for s in streams if s.error is not None]
    if failed and not config.keep_going:  # after every other video is complete
        done = [s.name for s in streams if s.error is None]
        rest = f"; the other videos were completed ({_listed(done)}): --resume skips them" if done else ""
        unread = "; ".join(str(s.error) for s in failed if not isinstance(s.error, _ReplayedTimeError))
        unread += " (mend or remove the frame and track that video again without --resume)" if unread else ""
        refused = [str(s.error) for s in failed if isinstance(s.error, _ReplayedTimeError)]
        what = "; ".join(refused + ([unread] if unread else []))
        reasons = [getattr(s.error, "reason", UNREADABLE_FRAME) for s in failed]
        raise VideosStopped(f"{what}{rest}", [summaries[str(v)] for v in inputs if str(v) in summaries],
                            [s.name for s in failed], reasons, [output_name(v) for v in inputs])  # fmt: skip
    return [summaries[str(v)] for v in inputs]


def _with_recorded_fits(fit: LandmarkFit, recorded: list[tuple[int, _Anchor]]) -> LandmarkFit:
    """``fit`` with the first-frame fits of the recorded streams (``(row, anchor)`` pairs) in their rows."""
    fields = {n: getattr(fit, n).clone() for n in LandmarkFit.__dataclass_fields__}
    for k, anchor in recorded:
        for n in ("axis_angle", "translation", "shape_coeffs", "anim_coeffs"):
            fields[n][k] = torch.as_tensor(anchor[n], dtype=fields[n].dtype, device=fields[n].device)
    fields["rotation"] = axis_angle_to_matrix(fields["axis_angle"])
    return LandmarkFit(**fields)


def _neutral_anim(state: TrackerState, streams: list[_Stream], alpha: Tensor, t: int) -> Tensor:
    """``(B, A)`` the neutral animation coefficients that the rows ``t`` of ``streams`` measure their ``AUxx_r`` from
    (``alpha (B, A)``: their ``anim_*``, for the dtype and device), which :attr:`JobConfig.keep_expression` resamples
    the normalised face at: the state's (:meth:`~torchface.tracker.TrackerState.neutral_anim_coeffs`: the first
    frame's fit, a restart's, the online start's re-estimate after its re-anchoring frame), but the first fit's
    (:attr:`_Stream.first_neutral`) for the rows up to and including the re-anchoring frame (estimated before it; a
    run resumed from the record holds the re-estimate in its state)."""
    neutral = state.neutral_anim_coeffs(alpha).clone()
    for k, s in enumerate(streams):
        a = s.anchor
        if a is not None and s.first_neutral is not None and a.get("frame") is not None and t <= a["frame"]:
            neutral[k] = torch.as_tensor(s.first_neutral, dtype=alpha.dtype, device=alpha.device)
    return neutral


def _head_offset(s: _Stream, t: int) -> tuple[list, list] | None:
    """The offset ``(D, d)`` (the sidecar's ``start.head_rotation``, ``start.head_translation``) that turns row
    ``t``'s pose into the pose placing its mesh, or None where the row places it with its own pose and the first
    shape: a stream not re-anchored, and the rows up to and including the re-anchoring frame (whose row holds the
    estimate made before the re-anchoring; a record of an earlier version, which does not say the frame: every row
    is offset)."""
    a = s.anchor
    if a is None or (a.get("frame") is not None and t <= a["frame"]):
        return None
    return a["head_rotation"], a["head_translation"]


def _anchor_params(s: _Stream, t: int) -> list[float] | None:
    """The packed parameters (the stream's own frame) that the online start gave the re-anchoring frame, when
    ``t`` is that frame and the record keeps them: the tracking went on from them, not from the row's estimate."""
    a = s.anchor
    return a.get("params") if a is not None and a.get("frame") == t else None


def _with_recorded_offsets(state: TrackerState, recorded: list[tuple[int, _Anchor]]) -> TrackerState:
    """``state`` whose recorded streams carry their re-anchoring offsets (the others the identity)."""
    ms = state.management
    if ms is None:  # (never: the recorded streams were tracked with template management)
        return state
    B, dt, dev = state.params.shape[0], state.params.dtype, state.params.device
    head_R = torch.eye(3, dtype=dt, device=dev).expand(B, 3, 3).clone()
    head_t = torch.zeros(B, 3, dtype=dt, device=dev)
    for k, anchor in recorded:
        head_R[k] = torch.as_tensor(anchor["head_rotation"], dtype=dt, device=dev)
        head_t[k] = torch.as_tensor(anchor["head_translation"], dtype=dt, device=dev)
    return replace(state, management=replace(ms, head_rotation=head_R, head_translation=head_t))


#: The largest gap, in millimetres, degrees and confidence, between a row tracked again on a resume
#: (:attr:`_Stream.retrack`) and the CSV's row of that frame (as the CSV holds it, 9 significant digits) that
#: :func:`_check_retracked` takes as the same row; a larger one, or another status, is warned about. Tracked alone
#: again, a video gives its CSV's rows to the digit (measured: 0 on two rendered clips); beside other videos in its
#: batch, by float rounding (1.5e-6 mm, 6e-6 degrees and 2e-7 of confidence, resumed after 3 rows beside two others;
#: 3e-5 mm between a video tracked alone and in a batch of six, JobConfig.max_batch).
RETRACK_TOLERANCE: tuple[float, float, float] = (1e-3, 1e-3, 1e-4)


def _online_start(config: JobConfig) -> LookaheadConfig | None:
    """The online look-ahead start the job's videos are tracked with (``JobConfig.refine_first``), or None where
    there is none: ``--lookahead`` instead, no template management (no re-anchoring without it), or none asked for."""
    if config.lookahead is None and config.tracker.template.enabled:
        return config.refine_first
    return None


def _online_start_pending(s: _Stream, lookahead: LookaheadConfig | None) -> bool:
    """Whether ``s``'s run was interrupted within the frames the online start (``lookahead``, :func:`_online_start`'s;
    None: none) watches: resumed (rows to replay) with fewer tracked rows than ``max_frames``, so
    that the start may still have been waiting for its head to turn (the uninterrupted run could re-anchor at the
    next frame), or re-anchored it so recently that tracking its rows again costs little. Such a stream's rows are
    tracked again (:attr:`_Stream.retrack`; at most ``max_frames - 1`` frames, 149 by default), re-anchored or not:
    the tracking again re-anchors it where the uninterrupted run did and builds its template mosaic again, which a
    stream put into the state from its rows lacks (measured on a 20-frame 160x120 ``pose_sweep`` re-anchored at frame
    4 and resumed after 7 rows: up to 8.1 mm, 0.64 degrees and 0.30 of confidence off the uninterrupted run from the
    record; byte-identical tracked again)."""
    return lookahead is not None and s.replay is not None and len(s.replay) < lookahead.max_frames


def _retracked_gap(new: np.ndarray, old: np.ndarray, columns: tuple[str, ...]) -> tuple[float, float, float, bool]:
    """The gap between a row tracked again (``new``, ``(C,)``, as :func:`~torchface.io.table.result_rows` gives it)
    and the CSV's row of that frame (``old``, ``(C,)``, as read back): translation (mm, Euclidean), rotation (degrees,
    from the rotation matrices: ``|R1 - R2|_F / sqrt(2)``, the angle to first order, well conditioned at 0),
    confidence, and whether the status or the success differs."""
    new = read_back(columns, new[None])[0]  # (as the CSV would hold it)
    pose = [columns.index(c) for c in POSE_COLUMNS[:3]]
    rot = [columns.index(c) for c in ROTATION_COLUMNS]
    mm = float(np.linalg.norm(new[pose] - old[pose]))
    deg = math.degrees(float(np.linalg.norm(new[rot] - old[rot])) / math.sqrt(2.0))
    ci, st, su = columns.index("confidence"), columns.index("status"), columns.index("success")
    conf = abs(float(new[ci]) - float(old[ci]))
    return mm, deg, conf, bool(new[st] != old[st] or new[su] != old[su])


def _check_retracked(s: _Stream, new: np.ndarray, old: np.ndarray, columns: tuple[str, ...], t: int, n: int) -> None:
    """Count ``s``'s row ``t`` tracked again (``new``; :attr:`_Stream.tracked_again`), keep its largest gap from its
    CSV row (``old``) in :attr:`_Stream.retrack_gap`, and count it in :attr:`_Stream.not_met_again` where a gap passed
    :data:`RETRACK_TOLERANCE` or its status differed; after the last of its ``n`` rows, warn (``RuntimeWarning``)
    where one was not met again (another version, another machine): the rows from the next frame on go on from the
    frames tracked again, not from the CSV's. The sidecar's ``resumed`` records them (:func:`_resumed_record`)."""
    mm, deg, conf, other = _retracked_gap(new, old, columns)
    big_mm, big_deg, big_conf, at, first_other = s.retrack_gap
    if mm > big_mm or t == 0:
        at = t + s.start
    if other and first_other is None:
        first_other = t + s.start
    s.retrack_gap = (max(mm, big_mm), max(deg, big_deg), max(conf, big_conf), at, first_other)
    s.tracked_again += 1
    tol_mm, tol_deg, tol_conf = RETRACK_TOLERANCE
    if mm > tol_mm or deg > tol_deg or conf > tol_conf or other:
        s.not_met_again += 1
    if t != n - 1 or s.not_met_again == 0:
        return
    big_mm, big_deg, big_conf, at, first_other = s.retrack_gap
    status = "" if first_other is None else f"; another status or success from frame {first_other} on"
    were = plural(s.not_met_again, "was", "were")
    warnings.warn(
        _worded(f"{s.reader.info.path}: {s.not_met_again} of its {counted(n, 'row')} written before the interruption, "
                f"tracked again from its first frame for the online start, {were} not met again: up to {big_mm:.3g} mm "
                f"(frame {at}), {big_deg:.3g} degrees and {big_conf:.3g} of confidence off the CSV's{status}; the CSV "
                "keeps its rows and the next ones go on from the frames tracked again (track the video without "
                "--resume for rows of one run)"),
        RuntimeWarning, stacklevel=2,
    )  # fmt: skip


def _without_online_start(state: TrackerState, resumed: list[bool]) -> TrackerState:
    """``state`` whose resumed streams (``resumed``) no longer wait for the online start: their rows so far were
    tracked with or without it, and the record (:func:`_write_record`) has put a re-anchored one back in its frame;
    the batch's new videos keep it."""
    ms = state.management
    if ms is None or ms.first is None:
        return state
    pending = ms.first.pending & ~torch.tensor(resumed, dtype=torch.bool, device=ms.first.pending.device)
    first = replace(ms.first, pending=pending) if bool(pending.any()) else None
    return replace(state, management=replace(ms, first=first))


def _with_replayed_loss(
    state: TrackerState, ended: list[tuple[int, np.ndarray]], columns: tuple[str, ...], layout: ParamLayout,
    config: TrackerConfig, streams: list[_Stream],
) -> TrackerState:
    """``state`` whose streams ``k`` of ``ended`` (``(k, rows)``: every row replayed from its CSV, the last one this
    frame's) carry the loss bookkeeping those rows say: lost when the last row is LOST (the next step then goes on
    with the loss, attempting a recovery at once, as the interrupted run would have, instead of starting afresh and
    reporting frames on the background successful), the counts of trailing frames not confident (lost ones too:
    ``TrackerState.management.low_count``) and below the very-low threshold,
    and the last confident row's parameters (status converged or iteration limit, confidence at least
    ``confidence_threshold``; and the online start's re-anchoring frame, whose refined parameters the record keeps:
    :func:`_anchor_params`) as the parameters a loss falls back to; a last row lost with a failed solve (residual
    confidence 0: its row holds the previous row's parameters) goes on from those, as the tracker reverted to them."""
    ms = state.management
    if ms is None or not ended:
        return state
    tc = config.template
    status_col, conf_col = columns.index("status"), columns.index("confidence")
    residual_col, reverted = columns.index("residual_confidence"), []
    lost, low, very_low = ms.lost.clone(), ms.low_count.clone(), ms.very_low_count.clone()
    since, confident = ms.since_attempt.clone(), ms.confident_params.clone()
    attempts = None if ms.attempts is None else ms.attempts.clone()
    scale = None if ms.adopted_scale is None else ms.adopted_scale.clone()
    for k, rows in ended:
        status, conf = rows[:, status_col], rows[:, conf_col]
        failed = status == int(TrackStatus.FAILED)
        ok = (conf >= tc.confidence_threshold) & ~failed & (status != int(TrackStatus.LOST))
        n_low = n_very_low = 0
        for c, f, o in zip(conf.tolist(), failed.tolist(), ok.tolist()):  # managed_step's counts, from the first
            n_low = 0 if o else n_low + 1  # row on (a lost row counts, whatever its confidence)
            n_very_low = n_very_low + 1 if (c < tc.very_low_confidence or f) else 0
        low[k], very_low[k] = n_low, n_very_low
        lost[k] = bool(status[-1] == int(TrackStatus.LOST))
        since[k] = tc.recovery_every if bool(lost[k]) else 0  # a lost stream attempts a recovery at once
        if attempts is not None:  # (the interrupted run's attempts are not known: the search starts again)
            attempts[k] = 0
        if scale is not None:
            scale[k] = 1.0
        a = streams[k].anchor
        kept = None if a is None else a.get("params")  # the re-anchoring frame's refined parameters
        at = None if a is None or kept is None else a.get("frame")
        if at is not None and at < len(rows):  # the re-anchoring made that frame's refined parameters confident
            ok[at] = True
        if ok.any():
            last = int(np.flatnonzero(ok)[-1])
            params = _params_from_rows(rows[last : last + 1], columns, layout)
            params = params.to(dtype=confident.dtype, device=confident.device)
            if ms.head_rotation is not None and ms.head_translation is not None:  # re-anchored: its own frame
                # (the offsets are set together)
                params = _rows_to_internal(params, ms.head_rotation[k : k + 1].to(params.dtype),
                                           ms.head_translation[k : k + 1].to(params.dtype), layout)  # fmt: skip
            if last == at:
                params[0] = torch.as_tensor(kept, dtype=params.dtype, device=params.device)
            confident[k] = params[0]
        if bool(lost[k]) and rows[-1, residual_col] == 0:  # a failed solve (no residual confidence) while lost: the
            reverted.append(k)  # tracker went on from the confident parameters, not from the held ones of its row
    ms = replace(ms, lost=lost, low_count=low, very_low_count=very_low, since_attempt=since,
                 confident_params=confident, attempts=attempts, adopted_scale=scale,
                 unmatched=None, unmatched_face=None)  # fmt: skip
    params = state.params
    if reverted:
        params = params.clone()
        params[reverted] = confident[reverted].to(params.dtype)
    return replace(state, params=params, management=ms)


def _with_replayed_motion(
    state: TrackerState, ended: list[tuple[int, np.ndarray]], columns: tuple[str, ...], layout: ParamLayout,
    config: TrackerConfig, streams: list[_Stream],
) -> TrackerState:
    """``state`` whose streams ``k`` of ``ended`` (``(k, rows)``: every row replayed, the last one this frame's) carry
    the motion prediction's velocity (:attr:`TrackerConfig.motion_prediction`, ``ManagementState.previous_pose`` and
    ``steady``) those rows say, so that the next frame starts from the prediction the uninterrupted run made: the
    confident rows (status converged or iteration limit, ``confidence`` at least ``confidence_threshold``) that end
    the rows, the first row (the initialisation), the online start's re-anchoring frame and a row after which a
    re-detection was due (:attr:`_Stream.replayed_redetection`: taken as made, its detector not asked again)
    counting none, and the pose of the row before the last, in the stream's own frame. (Without it a resumed stream
    went two frames without the prediction: 0.18 mm and 0.17 degrees off the uninterrupted run's rows, on the test
    clip.) A restart (``TemplateConfig.restart_after_unmatched``), which its row does not show, counts as a
    confident frame."""
    ms = state.management
    if ms is None or not ended or config.motion_prediction <= 0.0:
        return state
    tc, P = config.template, state.params
    status_col, conf_col = columns.index("status"), columns.index("confidence")
    B, bad = P.shape[0], (int(TrackStatus.FAILED), int(TrackStatus.LOST))
    # (None: no step yet, every stream of the batch replayed so far; those still replaying get theirs as they end)
    previous = torch.zeros(B, 6, dtype=P.dtype, device=P.device) if ms.previous_pose is None else ms.previous_pose
    steady = torch.zeros(B, dtype=torch.int64, device=P.device) if ms.steady is None else ms.steady
    previous, steady = previous.clone(), steady.clone()
    for k, rows in ended:
        status, conf = rows[:, status_col], rows[:, conf_col]
        ok = (conf >= tc.confidence_threshold) & ~np.isin(status, bad)
        a = streams[k].anchor
        # (after these rows no velocity: the re-anchoring frame's, and a replayed re-detection's, taken as made)
        restarts = {None if a is None else a.get("frame"), streams[k].replayed_redetection}
        run = 0
        for t in range(1, len(rows)):  # (row 0 is the initialisation: it counts none)
            run = run + 1 if bool(ok[t]) and t not in restarts else 0
        steady[k] = run
        if len(rows) >= 2:
            pose = _params_from_rows(rows[-2:-1], columns, layout).to(dtype=P.dtype, device=P.device)
            if ms.head_rotation is not None and ms.head_translation is not None:  # re-anchored: its own frame
                pose = _rows_to_internal(pose, ms.head_rotation[k : k + 1].to(P.dtype),
                                         ms.head_translation[k : k + 1].to(P.dtype), layout)  # fmt: skip
            kept = _anchor_params(streams[k], len(rows) - 2)
            if kept is not None:  # the re-anchoring frame: the refined pose the run went on from
                pose[0] = torch.as_tensor(kept, dtype=P.dtype, device=P.device)
            previous[k] = pose[0, :6]
    return replace(state, management=replace(ms, previous_pose=previous, steady=steady))


def _record_anchors(state: TrackerState, streams: list[_Stream], paths: list[dict[str, Path]], first_R: Tensor,
                    first_t: Tensor, layout: ParamLayout, frame: int) -> None:  # fmt: skip
    """Write the record (:func:`_write_record`) of each stream the online start has just re-anchored: its first
    frame's refined fit, recovered from the offsets ``D = R0c^T R0``, ``d = R0c^T (t0 - t0c)`` between the refined
    first pose ``(R0c, t0c)`` and the first result's ``(R0, t0)``, with the state's shape and starting expression."""
    ms = state.management
    todo = [k for k, s in enumerate(streams) if s.anchor is None]
    if ms is None or ms.head_rotation is None or ms.head_translation is None or not todo:  # (set together)
        return
    eye = torch.eye(3, dtype=ms.head_rotation.dtype, device=ms.head_rotation.device)
    rows = torch.tensor(todo, device=ms.head_rotation.device)
    moved = ((ms.head_rotation[rows] - eye).abs().flatten(1).amax(1) > 0) | (ms.head_translation[rows].abs().amax(1) > 0)
    neutral = state.neutral_anim_coeffs(state.params[:, layout.animation])
    for k in [todo[i] for i in moved.nonzero().flatten().tolist()]:  # one host sync per frame
        s, D, d = streams[k], ms.head_rotation[k], ms.head_translation[k]
        R0c = torch.matmul(first_R[k].to(D.dtype), D.transpose(0, 1))
        t0c = first_t[k].to(d.dtype) - torch.matmul(R0c, d)
        s.anchor = {
            "axis_angle": matrix_to_axis_angle(R0c[None])[0].tolist(), "translation": t0c.tolist(),
            "shape_coeffs": state.shape_coeffs[k].tolist(), "anim_coeffs": neutral[k].tolist(),
            "head_rotation": D.tolist(), "head_translation": d.tolist(), "frame": frame,
            "first_shape_coeffs": s.first_shape,  # the rows up to ``frame`` place the mesh with it
            "first_anim_coeffs": s.first_neutral,  # their AUxx_r are measured from it (JobConfig.keep_expression)
            "params": state.params[k].tolist(),  # the frame's refined parameters, which its row does not hold
        }  # fmt: skip
        _write_record(_record_path(paths[k]["csv"]), s.reader.info.path, s.anchor, s.settings, _first_face(s))


def _track_group(
    model: FaceModel, streams: list[_Stream], config: JobConfig, detector, progress, count: int, members: list[int]
) -> list[VideoSummary | None]:
    """Track one batch of same-size videos to the end and finalise their outputs, each video's as it ends (one that
    ends before others of its batch as it leaves it, after their checkpoint as the smaller batch they go on as; a
    warning it has to say, once the whole batch is finalised); per video its summary, or None
    for one stopped by a frame that could not be read (``_Stream.error``; its partial CSV kept) or, with
    ``keep_going``, one whose outputs could not be opened (:func:`_open_outputs`: ``_Stream.refused``; not tracked,
    the others tracked as a batch without it). ``members``: the streams' places among the ``count`` inputs checked
    (:attr:`Progress.index`)."""
    out_dir = Path(config.out_dir)
    info = streams[0].reader.info
    H, W = info.height, info.width
    intr = Intrinsics.default(W, H, config.focal)
    device, dtype = model.device, model.dtype
    layout = ParamLayout(model.num_animation, NUM_ILLUMINATION_TERMS)
    columns = track_columns(model.animation_names, model.facs_names, tuple(_illumination_names()))
    columns += SMOOTH_COLUMNS if config.smoothing is not None else ()
    edges = mesh_edges(model.faces)
    normaliser = NormalisedFace(model, size=config.normalised_size)
    paths = [output_paths(out_dir, s.name) for s in streams]
    mesh_tmp = [p["meshes"].with_name(p["meshes"].name + ".partial") for p in paths]
    t_start = time.perf_counter()
    batch = list(streams)  # (keep_going: those whose outputs cannot be opened leave it, and are abandoned)
    # SIGINT and SIGTERM in the per-frame loop: at its step boundary, a checkpoint written first (_AtStepBoundary;
    # not before it: the first fit, the look-ahead and the online start's initialisation are interrupted at once)
    boundary = _AtStepBoundary()
    try:
        for k, (s, p) in enumerate(zip(batch, paths)):
            try:
                _open_outputs(s, p, config, model, columns, (W, H))
            except InputError as exc:  # (a partial run that cannot be resumed: damaged, other settings, ...)
                if not config.keep_going:
                    raise
                _abandon(s)  # (its partial CSV as it was, or as far as its complete rows)
                s.csv = s.overlay = s.normalised = None
                _report_skipped(progress, members[k], count, s.name)
                s.refused = _warn_skipped(Path(s.reader.info.path), exc)
        if any(s.refused is not None for s in batch):
            opened = [k for k, s in enumerate(batch) if s.refused is None]
            streams, paths = [streams[k] for k in opened], [paths[k] for k in opened]
            mesh_tmp, members = [mesh_tmp[k] for k in opened], [members[k] for k in opened]
            if not streams:
                return [None] * len(batch)
        if config.meshes:
            for d in mesh_tmp:
                d.mkdir(parents=True, exist_ok=True)
        frames = torch.stack([s.frame() for s in streams]).to(device=device, dtype=dtype)
        lm = torch.as_tensor(np.stack([s.landmarks for s in streams]), dtype=dtype, device=device)
        # The batch is tracked with coarser pyramid levels added for faces larger than the default pyramid is made
        # for (HD and 4K video: pyramid_for_faces); the settings recorded and compared on --resume stay the user's.
        run = replace(config, tracker=pyramid_for_faces(config.tracker, lm, (H, W)))
        fit = None if config.lookahead is None else _lookahead_fit(model, run, streams, lm, intr)
        # (refine_first only without --lookahead: a batch too short to look ahead, a 1-frame video in it, starts
        # from the landmark fit, not the online start its sidecar would not mention)
        online = _online_start(config)
        # (without template management there is no re-anchoring offset to apply: those rows resume as before)
        anchored = {k: s.anchor for k, s in enumerate(streams)
                    if s.anchor is not None and config.tracker.template.enabled}  # fmt: skip
        if anchored:  # resumed streams the interrupted run had re-anchored: start from their refined fits
            fit = fit_landmarks(model, lm, intr, config=config.tracker.fit) if fit is None else fit
            fit = _with_recorded_fits(fit, list(anchored.items()))
        state, result = initialise_managed(model, run.tracker, frames, lm, intr, fit=fit,
                                           refine_first=online)  # fmt: skip
        for s, code in zip(streams, cast(Tensor, result.start_failure).tolist()):  # (initialise's: always set)
            s.start_failure = StartFailure(code)
        # (a detector starts a failed stream afresh only with template management: managed_step's restart)
        hints = [_swapped_fit_hint(model, config, intr, s, W, H) if s.replay is None else "" for s in streams]
        _warn_failed_starts(streams, detector is not None and config.tracker.template.enabled, hints)
        if anchored:
            state = _with_recorded_offsets(state, list(anchored.items()))
        if online is not None and any(s.replay is not None and not s.retrack for s in streams):
            state = _without_online_start(state, [s.replay is not None and not s.retrack for s in streams])
        first_R, first_t = result.rotation.detach().clone(), result.translation.detach().clone()
        first_neutral = state.neutral_anim_coeffs(state.params[:, layout.animation]).tolist()
        for k, s in enumerate(streams):  # (the online start's re-anchoring replaces them; the sidecar keeps both)
            s.first_shape, s.first_neutral = state.shape_coeffs[k].tolist(), first_neutral[k]
            if k in anchored and anchored[k].get("first_shape_coeffs") is not None:  # resumed from the record
                s.first_shape = list(anchored[k]["first_shape_coeffs"])  # (the state's: the refined shape)
            if k in anchored and anchored[k].get("first_anim_coeffs") is not None:  # (the state's: the refined one)
                s.first_neutral = list(anchored[k]["first_anim_coeffs"])
        current = _Current(frames)  # the frames being tracked: which stream a recovery's frame is (_recovery_near)
        smooth: SmoothingState | None = None  # the pose filter's state (JobConfig.smoothing), stream by stream
        for s in streams:  # (a landmarks file's given points: a detector's `near` is told no missing one, NaN)
            s.near = s.landmarks[np.isfinite(s.landmarks).all(axis=1)]
        # The streams in the tracker's state, in its order (with their output paths and first poses): a video that
        # has ended leaves it before the next step (TrackerState.select), so that the batch shrinks as its videos end.
        live, live_paths, live_mesh = list(streams), list(paths), list(mesh_tmp)
        recover = None if detector is None else _Batched(detector, config.detector, _recovery_near(live, current))
        joined = _joined(streams, config.smoothing is not None, device)  # (resumed from their checkpoints)
        restore_at = None if joined is None else len(streams[0].replay) - 1  # type: ignore[arg-type]
        checkpoint_from = 0 if online is None else online.max_frames  # (sooner: tracked again, _Stream.retrack)
        t_init = time.perf_counter() - t_start
        t_track0 = t_iter = time.perf_counter()
        t_idle = 0.0  # the loop's time in which every live stream replayed rows from its CSV (timings_s.batch_fps)
        early: dict[int, VideoSummary] = {}  # the videos finalised as they ended, before the batch (by id)
        t = 0
        with boundary:  # (its handlers given back however the loop ends; a signal that waited run as it ends)
            while True:
                # this frame's:
                replays = [s.replay if s.replay is not None and t < len(s.replay) else None for s in live]
                replaying = [r is not None for r in replays]  # (its row written already: drawn, not written again)
                redrawn = [s for s, r in zip(live, replaying) if r and not s.retrack]  # (_Stream.t_replay)
                held = [None if s.retrack else r for s, r in zip(live, replays)]  # (put into the state from the CSV)
                if any(r is not None for r in held):
                    idx = [k for k, r in enumerate(held) if r is not None]
                    rows = np.stack([r[t] for r in held if r is not None])
                    params = state.params.clone()
                    own = _params_from_rows(rows, columns, layout).to(device=device, dtype=dtype)
                    replayed = own
                    ms = state.management
                    # re-anchored streams: their own frame (the offsets are set together)
                    if ms is not None and ms.head_rotation is not None and ms.head_translation is not None:
                        replayed = _rows_to_internal(own, ms.head_rotation[idx].to(dtype),
                                                     ms.head_translation[idx].to(dtype), layout)  # fmt: skip
                    for i, k in enumerate(idx):  # the re-anchoring frame: the refined pose the run went on from
                        kept = _anchor_params(live[k], t)
                        if kept is not None:
                            replayed[i] = torch.as_tensor(kept, dtype=replayed.dtype, device=replayed.device)
                    params[idx] = replayed
                    state = replace(state, params=params)
                    ended = [(k, r) for k, r in enumerate(held) if r is not None and t == len(r) - 1]
                    state = _with_replayed_loss(state, ended, columns, layout, run.tracker, live)
                    state = _with_replayed_motion(state, ended, columns, layout, run.tracker, live)
                new_rows = result_rows(result, np.full(len(live), t), 1.0)
                if config.smoothing is not None:  # (filled by _write_step)
                    new_rows = np.concatenate([new_rows, np.full((len(live), len(SMOOTH_COLUMNS)), math.nan)], axis=1)
                for k, s in enumerate(live):  # a row tracked again: checked against the CSV's
                    r = replays[k]
                    if s.retrack and r is not None and not s.done:
                        _check_retracked(s, new_rows[k], r[t], columns, t, len(r))
                smooth = _write_step(model, state, result, frames, live, replaying, columns, new_rows, t, intr, edges,
                                     normaliser, layout, live_mesh if config.meshes else None, config.redetect_below,
                                     "dissim. conf" if config.tracker.template.enabled else "conf", config.smoothing,
                                     smooth, config.keep_expression)  # fmt: skip
                if joined is not None and t == restore_at:  # the state after this row, as the interrupted run had it
                    state, smooth, first_R, first_t = joined
                    idx = [k for k, s in enumerate(streams) if any(s is x for x in live)]
                    if len(idx) < len(streams):  # (a video that stopped while its rows were replayed: InputError)
                        state, first_R, first_t = state.select(idx), first_R[idx], first_t[idx]
                        smooth = None if smooth is None else smooth.select(idx)
                    _restore_streams(live)
                    joined = None
                elif detector is not None and config.redetect_after > 0:
                    state = _maybe_redetect(model, config, state, frames, live, detector, intr, layout,
                                            [r is not None and t < len(r) - 1 for r in held])
                stop = boundary.pending is not None  # (Ctrl-C, SIGTERM: this state's checkpoint, then the handler)
                if (stop or (t + 1) % CHECKPOINT_EVERY == 0) and t + 1 >= checkpoint_from:
                    if not _write_checkpoints(state, smooth, first_R, first_t, live, live_paths, t,
                                              [not r for r in replaying]):  # fmt: skip
                        checkpoint_from = sys.maxsize  # (warned: none for this batch)
                if stop:  # (one that arrives after `stop` was read waits for the next step's checkpoint)
                    boundary.check()
                nxt = []
                for s in live:
                    if not s.done:
                        try:
                            if s.ahead:  # (the last one copied: a view would keep every frame read ahead, of every
                                s.last_frame = s.ahead.pop(0)  # stream, for as long as a stream that ends holds it)
                                if not s.ahead:
                                    s.last_frame = s.last_frame.clone()
                            elif s.error is not None:  # the look-ahead's reading stopped at a bad frame
                                s.done = True
                            else:
                                s.last_frame = _next_frame(s)
                        except StopIteration:
                            s.done = True
                        except InputError as exc:  # this video stops; the others of the batch go on
                            s.done, s.error = True, exc
                        if s.done:  # its decoder (file, threads, buffers) not kept; its stream leaves the batch below
                            s.reader.close()
                    nxt.append(s.frame())
                now = t_read = time.perf_counter()  # (this frame's rows written, the next frames read)
                for s in redrawn:
                    s.t_replay += now - t_iter
                t_idle += (now - t_iter) if len(redrawn) == len(live) else 0.0
                if progress is not None:  # (after reading: a video that has ended reports its frames as its total, so
                    # that it shows finished where its container's count was short, long or unknown)
                    elapsed = time.perf_counter() - t_track0
                    for k, s in enumerate(streams):
                        total = s.frames if s.done and s.error is None else s.total
                        active = elapsed if s.t_active is None else s.t_active  # (an ended video's: not growing)
                        fps = (s.tracked + s.tracked_again) / max(active - s.t_replay, 1e-9)  # (timings_s.fps)
                        progress(Progress(members[k], count, s.name, s.frames, total, fps, s.confidence))
                if all(s.done for s in live):
                    break
                t += 1
                keep = [k for k, s in enumerate(live) if not s.done]
                if len(keep) < len(live):  # videos ended: their streams leave the state, the others go on as a smaller
                    # batch (tracked as in the whole one; kept in it, an ended video's last frame was tracked again at
                    # every step until the longest video ended)
                    _keep_final(state, live, layout, [k for k in range(len(live)) if live[k].done])
                    for k in range(len(live)):
                        if k not in keep:
                            live[k].t_active = t_read - t_track0
                    if any(live[k].error is not None for k in range(len(live)) if k not in keep):  # (a video stopped:
                        for s in live:  # the batch goes on smaller than the uninterrupted run's)
                            s.from_checkpoint = "split" if s.from_checkpoint else False
                    state, result = state.select(keep), result.select(keep)
                    smooth = None if smooth is None else smooth.select(keep)
                    first_R, first_t = first_R[keep], first_t[keep]
                    complete = [(live[k], live_paths[k], live_mesh[k]) for k in range(len(live))
                             if k not in keep and live[k].error is None]  # fmt: skip
                    written = [not replaying[k] for k in keep]  # (row t - 1's, as a checkpoint after it says)
                    live[:] = [live[k] for k in keep]  # (in place: the recovery's callback reads this list)
                    live_paths, live_mesh = [live_paths[k] for k in keep], [live_mesh[k] for k in keep]
                    nxt = [nxt[k] for k in keep]
                    if complete:  # finalised now, not as the batch ends (an interruption meanwhile kept them
                        # partial, and --resume replayed them); first the checkpoint of the others as the smaller
                        # batch they go on as (a resume from theirs of the whole batch went on split: _restore_streams)
                        t_aside = time.perf_counter()
                        if t >= checkpoint_from and not _write_checkpoints(state, smooth, first_R, first_t, live,
                                                                           live_paths, t - 1, written):  # fmt: skip
                            checkpoint_from = sys.maxsize  # (warned: none for this batch)
                        for s, p, mt in complete:  # (the loop's time so far, its time in the batch: s.t_active)
                            early[id(s)] = _finalise(model, s, p, mt, config, streams, intr, t_init,
                                                     cast(float, s.t_active), t_idle, run.tracker.num_levels)
                        t_track0 += time.perf_counter() - t_aside  # (not the loop's time: the others' fps as before)
                # (one video: its frame itself, not a copy stacked: 2 ms of CPU a 1080p frame; nothing changes a frame)
                frames = (nxt[0].unsqueeze(0) if len(nxt) == 1 else torch.stack(nxt)).to(device=device, dtype=dtype)
                t_iter = time.perf_counter()
                if all(s.replay is not None and t < len(s.replay) and not s.retrack for s in live):
                    continue  # every live stream replays this frame from its CSV: nothing to track
                current.frames, current.asked = frames, {}
                state, result = managed_step(model, run.tracker, state, frames, recover, donate=True)
                if result.start_failure is not None:  # (a detector's restart tried: why those it did not start failed)
                    for s, code in zip(live, result.start_failure.tolist()):
                        held_here = s.replay is not None and t < len(s.replay) and not s.retrack  # (its row: the CSV's)
                        if code != int(StartFailure.NONE) and not held_here:
                            name = StartFailure(code).name
                            s.restart_failures[name] = s.restart_failures.get(name, 0) + 1
                _record_anchors(state, live, live_paths, first_R, first_t, layout, t)
                now = time.perf_counter()  # (a step for the streams whose row t is tracked: for the others, not theirs)
                for s in live:
                    if s.replay is not None and t < len(s.replay) and not s.retrack:
                        s.t_replay += now - t_iter
                t_iter = now
        t_track = time.perf_counter() - t_track0
        for s in live:  # (the videos that ended last: in the batch for the whole loop)
            s.t_active = t_track
        _keep_final(state, live, layout, list(range(len(live))))
    except BaseException:  # (a signal that waited: its interruption, run as the loop's block ended, keeps the error)
        for s in batch:
            _abandon(s)
        raise
    summaries: list[VideoSummary | None] = []
    finished = 0
    try:
        for s, p, mt in zip(streams, paths, mesh_tmp):
            if id(s) in early:  # (finalised as it ended, the others going on)
                summaries.append(early[id(s)])
            elif s.error is None:
                summaries.append(_finalise(model, s, p, mt, config, streams, intr, t_init, t_track, t_idle,
                                           run.tracker.num_levels))
            else:  # its rows so far stay in the partial CSV; nothing else of it is kept
                _abandon(s)
                summaries.append(None)
            finished += 1
    except BaseException:  # interrupted while finalising: the videos not finalised leave no partial video files
        for s in streams[finished:]:
            _abandon(s)
        raise
    for summary in summaries:  # (once every video of the batch is finalised: a warning made an error, -W error,
        # leaves none of them unfinished)
        if summary is not None and summary.declared_frames is not None:  # (said in the summary alone, on stdout: a
            # script logging stderr, or --quiet with stdout thrown away, heard nothing of a video cut short, its
            # outputs complete and its status 0)
            warnings.warn(f"{summary.input} declares {counted(summary.declared_frames, 'frame')}, {summary.frames} "
                          f"could be decoded (truncated or damaged?): its outputs are complete with those "
                          f"{counted(summary.frames, 'frame')}", RuntimeWarning, stacklevel=2)  # fmt: skip
    by_stream = {id(s): summary for s, summary in zip(streams, summaries)}
    return [by_stream.get(id(s)) for s in batch]


def _open_outputs(
    s: _Stream, p: dict[str, Path], config: JobConfig, model: FaceModel, columns: tuple[str, ...], size: tuple[int, int]
) -> None:
    """Open the outputs of ``s``'s video (``p``: its paths, :func:`output_paths`; ``size``: ``(W, H)``) before its
    batch's first frame: its CSV (with ``resume``, its partial one's rows checked and kept to replay, and its record
    read: the re-anchoring), its record written, its videos started and its rows before the first face written.

    With ``keep_going`` and ``resume``, a partial run made from the input file as it was before it changed (mended:
    :func:`_changed_input`) is removed first, and the video tracked afresh, with a warning.

    Raises:
        InputError: the partial run cannot be resumed (damaged rows or record, other settings, another model, ...).
    """
    W, H = size
    G = config.normalised_size
    s.settings = _settings(config, s, model)
    record = _record_path(p["csv"])
    loaded = _load_record(record) if config.resume else _Record(record, found=False, readable=False)
    if config.keep_going and config.resume:
        changed = _changed_input(loaded, Path(s.reader.info.path), s.settings)
        if changed is not None:  # (its size or time: a ``touch`` is enough; its rows are kept, not removed)
            aside = _set_aside(p["csv"])
            _clear_earlier_outputs(Path(config.out_dir), [s.name])
            kept = f", its earlier rows kept in {aside}" if aside is not None else ""
            warnings.warn(f"{s.reader.info.path}: the input has changed since the rows in {partial_path(p['csv'])} "
                          f"were tracked ({changed}): tracked afresh{kept}", RuntimeWarning, stacklevel=3)  # fmt: skip
            loaded = _load_record(record)  # (set aside with the rows where there were rows: then none)
    partial = partial_path(p["csv"])
    if config.resume:  # (before the CSV's columns, the model's, are compared with the partial one's)
        _check_record_model(loaded, s.settings)
        _check_record_smoothing(loaded, s.settings)
    if config.resume and p["csv"].is_file() and not p["json"].is_file() and not partial.exists():
        os.replace(p["csv"], partial)  # interrupted while finalising (the JSON comes last): resume its rows
    s.csv = TrackCsvWriter(p["csv"], columns, resume=config.resume)
    # Its rows after the checkpoint (tracked again) are left out of the checks below, and cut from the file only
    # once the resume is accepted: a resume refused (damaged rows, another record) keeps them all.
    ck = s.checkpoint if config.resume else None
    cut = None if ck is None else int(ck["rows"])
    if ck is not None and cut is not None:
        if s.csv.rows_done < cut:  # (not the rows it was checked against: the file changed since)
            warnings.warn(f"{ck['path']}: not used (it is of row {cut}, the CSV holds {s.csv.rows_done}): "
                          "the video goes on from its CSV's rows, not exactly as the uninterrupted run",
                          RuntimeWarning, stacklevel=3)  # fmt: skip
            s.checkpoint, cut = None, None
        else:
            s.csv.previous, s.csv.rows_done = s.csv.previous[:cut], cut
    exact = s.reader.info.kind in ("array", "images")  # a container's count may be an estimate
    if exact and s.total is not None and s.csv.rows_done > s.total:
        raise InputError(f"{s.csv.partial}: cannot resume, it holds {counted(s.csv.rows_done, 'row')} and "
                         f"{s.reader.info.path} has {counted(s.total, 'frame')}: run without --resume")  # fmt: skip
    # (the rows before the first face replay nothing into the state: the tracked rows after them do)
    s.replay = s.csv.previous[s.start :] if s.csv.rows_done > s.start else None
    problem = _no_face_problem(s.csv.previous[: s.start], columns, s.start)
    if problem is None and s.replay is not None:
        problem = _replay_problem(s.replay, columns, s.start)
    if problem is not None:  # (its values went into the state: NaN, a missing frame, a scaled rotation...)
        raise InputError(f"{s.csv.partial}: cannot resume, its rows are damaged ({problem}): run without "
                         "--resume")  # fmt: skip
    s.anchor = None
    if s.csv.rows_done:  # (made with other settings, a detector among them, its rows are not this run's)
        s.anchor = _read_record(loaded, s.reader.info.path, s.settings, _setting_values(config),
                                model.num_shape, model.num_animation)  # fmt: skip
    if s.replay is None:  # (no tracked row: nothing re-anchored)
        s.anchor = None
    # Resumed within the online start's frames: its rows are tracked again (_Stream.retrack), and its record says
    # no re-anchoring until the tracking again re-anchors it (_record_anchors): one that does not (another machine's
    # rounding at the turn's threshold) kept the first run's, and a resume after a second interruption took its
    # rows as re-anchored. (A re-anchoring is recorded only by the online start, at a frame below its max_frames,
    # which a resume compares with its own; so a record whose re-anchoring frame has no row yet, interrupted between
    # the re-anchoring step and its row, is always one tracked again.)
    s.retrack = _online_start_pending(s, _online_start(config))
    if s.retrack:
        s.anchor = None
    if cut is not None:  # (accepted: the rows after the checkpoint go; the writer appends after its row)
        _cut_rows(p["csv"], cut)
    _write_record(record, s.reader.info.path, s.anchor, s.settings, _first_face(s))
    s.overlay = _VideoOut(p["overlay"], W, H, s.reader.info.fps, timed=True)  # (in step with the frames' times)
    s.normalised = _VideoOut(p["normalised"], G, G, s.reader.info.fps)
    _write_no_face(s, columns, config, "dissim. conf" if config.tracker.template.enabled else "conf")


def _set_aside(csv: Path) -> Path | None:
    """Keep the partial CSV of ``csv`` and its record (:func:`_record_path`), which a resumed run tracks afresh
    (``JobConfig.keep_going``: its input file has changed since), under names of their own, which no run writes nor
    removes: ``<name>.csv.partial.earlier`` and ``<name>.record.partial.earlier`` (``.earlier-2``, ... where those are
    taken). Returns where the rows are kept; None where there were none (nothing moved)."""
    partial, record = partial_path(csv), _record_path(csv)
    if not partial.is_file():
        return None
    n = 1
    while True:
        tag = ".earlier" if n == 1 else f".earlier-{n}"
        rows, rec = partial.with_name(partial.name + tag), record.with_name(record.name + tag)
        if not rows.exists() and not rec.exists():
            break
        n += 1
    if record.is_file():
        os.replace(record, rec)
    os.replace(partial, rows)
    return rows


def _changed_input(loaded: _Record, video: Path, settings: dict[str, object]) -> str | None:
    """How the input file of a partial run whose record is ``loaded`` (:func:`_load_record`) has changed since
    (``"<size and time> then, <size and time> now"``, :func:`_settings`' ``input file``), where the record was made
    from ``video`` (the same path); None where it has not, or the record says nothing of it (none, unreadable, of
    another input: :func:`_read_record` refuses it)."""
    try:
        made = loaded.value
        made_from, then = made["input"], made["settings"]["input file"]
        if not isinstance(made_from, str) or not isinstance(then, str):
            return None
    except (KeyError, TypeError, AttributeError):  # (None where it is missing or unreadable: a TypeError)
        return None
    now = settings["input file"]
    if Path(made_from).resolve() != video.resolve() or then == now:
        return None
    return f"{then} then, {now} now"


def _keep_final(state: TrackerState, streams: list[_Stream], layout: ParamLayout, ks: list[int]) -> None:
    """Keep on streams ``ks`` (rows of ``state``, whose streams are ``streams``) what their sidecar takes from the
    state after their last frame (``final_shape``, ``final_neutral``), before they leave it."""
    neutral = state.neutral_anim_coeffs(state.params[:, layout.animation])
    for k in ks:
        streams[k].final_shape = state.shape_coeffs[k].tolist()
        streams[k].final_neutral = neutral[k].tolist()


def _warn_replaced_inputs(out_dir: Path, videos: Sequence[tuple[str, Path]]) -> None:
    """Warn, for each ``(name, input)`` of a fresh run, where ``out_dir`` holds complete outputs of that name made
    from another input (their sidecar's ``input.resolved_path``), which the run is about to remove: two videos of
    one stem in different folders, tracked one by one into one ``--out`` (a shell loop over ``*/clip.mp4``), kept
    the last one's outputs alone, without a word. A sidecar that cannot be read, or that names no input, is not
    warned about."""
    for name, video in videos:
        path = output_paths(out_dir, name)["json"]
        try:
            made_from = json.loads(path.read_text(encoding="utf-8"))["input"]["resolved_path"]
        except (OSError, ValueError, KeyError, TypeError):
            continue
        if isinstance(made_from, str) and Path(made_from) != video.resolve():
            warnings.warn(_worded(f"{path}: replacing the outputs made from {made_from} with those of {video}, of "
                                  "the same name: give each its own --out (or rename one) to keep both"),
                          RuntimeWarning, stacklevel=3)  # fmt: skip


def _clear_earlier_outputs(out_dir: Path, names: Sequence[str]) -> None:
    """Remove what earlier runs wrote for videos ``names`` (a fresh run's, before its first batch: they must not
    outlive it; removed batch by batch, the later batches' complete outputs outlived a run interrupted before
    them, and ``--resume`` then skipped them as this run's): complete outputs, partial CSV and its record, and the
    PLY files of the meshes folders (complete or interrupted; other files there are the user's)."""
    for name in names:
        p = output_paths(out_dir, name)
        for kind in ("json", "csv", "overlay", "plot", "normalised"):
            p[kind].unlink(missing_ok=True)
        partial_path(p["csv"]).unlink(missing_ok=True)
        _record_path(p["csv"]).unlink(missing_ok=True)
        for ck in (_checkpoint_path(p["csv"]), _checkpoint_path(p["csv"]).with_suffix(".partial.tmp")):
            ck.unlink(missing_ok=True)
        for folder in (p["meshes"], p["meshes"].with_name(p["meshes"].name + ".partial")):
            if folder.is_dir():
                for f in _frame_meshes(folder):
                    f.unlink()
                if not any(folder.iterdir()):
                    folder.rmdir()


def _abandon(s: _Stream) -> None:
    """Stop a video's outputs unfinished: its partial CSV kept (for --resume), its partial videos deleted."""
    if s.csv is not None:
        s.csv.stop()
    for v in (s.overlay, s.normalised):
        if v is not None:
            v.abort()


def _finalise(
    model: FaceModel, s: _Stream, p: dict[str, Path], mt: Path, config: JobConfig, streams: list[_Stream],
    intr: Intrinsics, t_init: float, t_track: float, t_idle: float, levels: int,
) -> VideoSummary:
    """Close one video's outputs under their final names, the JSON last (a CSV without its JSON is resumed as
    partial), then remove its resume record. ``levels``: the pyramid levels the batch was tracked with
    (:func:`~torchface.tracker.step.pyramid_for_faces`)."""
    W, H, B = intr.width, intr.height, len(streams)
    for out in s.outputs():
        out.close()
    cols, rows = read_track_csv(p["csv"])
    plot_track(cols, rows, p["plot"], title=f"{s.name} ({len(rows)} frames)")
    outs = [p["csv"], p["overlay"], p["plot"], p["normalised"]]
    if config.meshes:
        if p["meshes"].is_dir():  # keep what else the folder holds: replace an earlier run's frame meshes only
            for f in _frame_meshes(p["meshes"]):
                f.unlink()
            for f in sorted(mt.iterdir()):
                os.replace(f, p["meshes"] / f.name)
            mt.rmdir()
        else:
            os.replace(mt, p["meshes"])
        outs.append(p["meshes"])
    elif mt.is_dir():  # an interrupted --meshes run's, resumed without: its frame meshes were left there for good
        for f in _frame_meshes(mt):
            f.unlink()
        if not any(mt.iterdir()):
            mt.rmdir()
    conf = rows[:, cols.index("confidence")]
    lost = [int(f) for f, ok in zip(rows[:, 0], rows[:, cols.index("success")]) if ok < 0.5]
    # (a resumed video's rows tracked again for the online start are tracked frames: their time is in t_track; counted
    # only its new rows, a 40-frame 160x120 pose sweep resumed after 20 rows gave 16-17 frames/s where the
    # uninterrupted run gave 28-32, and 32-34 now. Its rows replayed from the CSV are not, nor is the time spent
    # redrawing them, s.t_replay: counted, a 200-frame sweep resumed after 170 rows from its checkpoint at 150 gave
    # 10 frames/s (median of 6 runs on a shared 2-core machine, 3.5-15) where the uninterrupted run gave 20 (14-30);
    # not counted, 23 (17-46): scripts/doc_figures.py resume-sweep)
    # (over the time it was in the batch, s.t_active: over the whole loop's, t_track, a 3-frame video tracked in one
    # batch with a longer one reported 0.0083 frames/s where the batch ran at 2.6)
    active = t_track if s.t_active is None else s.t_active
    fps = (s.tracked + s.tracked_again) / max(active - s.t_replay, 1e-9) if t_track > 0 else 0.0
    # (the batch's frames over its time: B * fps overstated it by the other videos' shortfall, and differed from
    # video to video of one batch where their lengths differ; without the time in which every video replayed)
    batch_fps = (sum(x.tracked + x.tracked_again for x in streams) / max(t_track - t_idle, 1e-9) if t_track > 0
                 else 0.0)  # fmt: skip
    sidecar = {
        "torchface_output": 1,
        "input": {
            "path": str(s.reader.info.path), "resolved_path": str(Path(s.reader.info.path).resolve()),
            "identity": s.settings.get("input file"),  # (what --resume compares)
            "kind": s.reader.info.kind, "format": s.reader.info.source_format,
            "conversion": s.reader.info.conversion, "width": W, "height": H, "fps": s.reader.info.fps,
            "fps_assumed": s.reader.info.fps_assumed, "fps_given": s.reader.info.fps_given,
        },  # fmt: skip
        "versions": package_versions(),
        "config": {**_result_settings(config), "device": config.device, "landmarks": s.landmarks_source,
                   "resume": config.resume, "batch_streams": B, "fps": config.fps},  # fmt: skip
        "camera": {
            "width": intr.width, "height": intr.height, "fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy,
            "frame": "OpenCV: x right, y down, z forward; millimetres",
            "pixels": "(u, v) = (column, row), pixel centres at integers: the top-left pixel's centre is (0, 0)",
        },  # fmt: skip
        "model": {"name": model.name, "file": None if config.model is None else os.fspath(config.model),
                  "sha256": _digest(model), "vertices": model.num_vertices, "triangles": model.num_faces,
                  "landmarks": model.num_landmarks, "animation_units": list(model.animation_names),
                  "facs": list(model.facs_names), "shape_units": model.num_shape,
                  "shape_coeffs": s.final_shape},  # fmt: skip
        "start": _start_record(config, s),
        "pyramid_levels": levels,
        "initial_landmarks_px": s.landmarks.tolist(),  # (a file's missing point, NaN: [null, null])
        "timings_s": {"initialise": t_init, "track": t_track, "active": active, "replay": s.t_replay, "fps": fps,
                      "batch_fps": batch_fps},
        "resumed": _resumed_record(s),
        "frames": int(len(rows)),
        "declared_frames": s.total,
        "lost_frames": lost,
        "mean_confidence": float(conf.mean()) if len(conf) else 0.0,
        "redetections": s.redetections,
        "detector_calls": s.detector_calls,
        "restart_failures": dict(sorted(s.restart_failures.items())),
        # (relative to the sidecar's own folder, where they lie: the run's --out as given, relative to its working
        # folder, broke them when read from elsewhere or once the folder was moved; an earlier version's sidecar
        # holds those, whose names are these: Path(json).parent / Path(path).name reads both)
        "outputs": {k: v.name for k, v in p.items() if k != "json" and (k != "meshes" or config.meshes)},
        "videos": _video_timing(s),
    }
    # (its checkpoint, and a temporary one a SIGKILL cut off while it was written, before the JSON: a video killed
    # between them is resumed from its complete CSV's rows, none tracked again; one left behind stayed beside the
    # complete outputs, where no run removed it)
    for ck in (_checkpoint_path(p["csv"]), _checkpoint_path(p["csv"]).with_suffix(".partial.tmp")):
        ck.unlink(missing_ok=True)
    write_json(p["json"], sidecar)
    _record_path(p["csv"]).unlink(missing_ok=True)
    outs.insert(1, p["json"])
    short = s.total if s.total is not None and len(rows) < s.total else None  # the container's (estimated) count
    failed = None if s.start_failure == StartFailure.NONE else s.start_failure.name  # (the sidecar's start.failure)
    return VideoSummary(s.name, s.reader.info.path, tuple(outs), len(rows), len(lost),
                        float(conf.mean()) if len(conf) else 0.0, fps, declared_frames=short,
                        not_met_again=s.not_met_again, start_failure=failed)  # fmt: skip


def _resumed_record(s: _Stream) -> dict | None:
    """The sidecar's ``resumed``: None where every row of the CSV is this run's (not resumed, or resumed without
    rows); else ``rows``, the CSV's first rows, written by the interrupted run(s) and kept as they were (the rows
    before the first face included), ``tracked_again``, how many of them (from the first face on) this run tracked
    again for the online start (:attr:`_Stream.retrack`; 0: put into the tracker's state from the CSV), and
    ``not_met_again``, how many of those passed :data:`RETRACK_TOLERANCE` or had another status or success
    (:func:`_check_retracked`, which warns; the CSV keeps them, and the rows after them go on from the frames tracked
    again, so its rows are of two runs that disagree), with ``largest_gap`` over the rows tracked again (None where
    none was): ``mm``, ``degrees``, ``confidence``, ``frame`` (of the largest translation gap) and
    ``other_status_from_frame`` (the first frame whose status or success differs, or None); ``checkpoint``: whether
    the tracking went on from the interrupted run's checkpoint (:func:`_load_checkpoint`) rather than from the CSV's
    last row: ``"exact"``, with its whole batch as it was (the rows after it the uninterrupted run's, byte for
    byte), ``"split"``, in a part of its batch (a smaller ``max_batch``, some of its videos skipped, or one
    stopped since: to float rounding), or False (:attr:`_Stream.from_checkpoint`); ``threads``, where it went on from
    a checkpoint: ``checkpoint``, the CPU threads (``torch.get_num_threads()``) of the run that wrote it (None: one
    written before they were recorded), and ``now``, this run's. For information only: another count changes no
    result (the native kernels split the batch's streams among the threads, each stream's numbers its own; the
    tracker's 40 frames of 3 scenarios at 640x480, B = 1 and 3, on 1, 2 and 5 threads, 20 frames at B = 6 on 1 and
    2, and a resume from a checkpoint on another count than the interrupted run's: bit for bit the same), so a
    checkpoint of another count is used as any other, without a word."""
    rows = 0 if s.csv is None else len(s.csv.previous)
    if rows == 0:
        return None
    mm, deg, conf, at, first_other = s.retrack_gap
    gap = None if s.tracked_again == 0 else {
        "mm": mm, "degrees": deg, "confidence": conf, "frame": at, "other_status_from_frame": first_other,
    }  # fmt: skip
    threads = None
    if s.from_checkpoint and s.checkpoint is not None:
        threads = {"checkpoint": s.checkpoint.get("threads"), "now": torch.get_num_threads()}
    return {"rows": rows, "tracked_again": s.tracked_again, "not_met_again": s.not_met_again, "largest_gap": gap,
            "checkpoint": s.from_checkpoint, "threads": threads}


def _video_timing(s: _Stream) -> dict:
    """The sidecar's ``videos``: how the frames of the overlay and of the normalised face relate to the CSV's rows.
    The overlay is ``time_synced`` (:class:`_VideoOut`'s ``timed``): a constant-rate video at ``input.fps`` whose
    frames show each row at its ``timestamp`` (``duplicated_frames``: slots that showed the previous row again, where
    the input's frames are further apart than ``1 / fps``; ``dropped_frames``: rows not shown, their slot taken by an
    earlier one; both 0 for a constant-rate input, one frame per row; ``skipped_gaps``: gaps between two rows' times
    longer than :data:`OVERLAY_MAX_GAP_S`, a broken time, not filled, ``skipped_seconds`` their length: the overlay
    went on at the next slot, and is behind the rows' times by that much from there). The normalised face is one
    frame per row (``frames`` the rows; frame ``i`` is row ``i``, a dataset's order), not in step with the rows' times
    where they are not ``i / fps``."""
    overlay, normalised = s.outputs()[1:]
    return {
        "overlay": {"fps": overlay.fps, "frames": overlay.frames, "time_synced": True,
                    "duplicated_frames": overlay.duplicated, "dropped_frames": overlay.dropped,
                    "skipped_gaps": overlay.skipped_gaps, "skipped_seconds": round(overlay.skipped_s, 3)},
        "normalised": {"fps": normalised.fps, "frames": normalised.frames, "time_synced": False},
    }  # fmt: skip


#: The largest roll (degrees, about the optical axis) of a fit of a failed start's landmarks with x and y swapped that
#: :func:`_swapped_fit_hint` takes for the file's being written ``(y, x)``: an upright face's points written so fit
#: upright once swapped, where a mirrored face's (a flipped frame's) fit a face rolled 90 degrees.
SWAPPED_FIT_MAX_ROLL_DEG: float = 45.0


def _swapped_fit_hint(model: FaceModel, config: JobConfig, intr: Intrinsics, s: _Stream, W: int, H: int) -> str:
    """What the warning of a failed start adds where ``s``'s landmarks came from a file (not a detector), the start
    failed as :attr:`~torchface.tracker.step.StartFailure.NO_POSE` (a mirrored face's points: a headerless CSV of
    ``(y, x)`` pairs, ``(row, column)``, as they are written), and its points with x and y swapped lie in the
    ``W x H`` frame and fit a pose (:func:`~torchface.tracker.fit.fit_landmarks`, the tracker's fit settings) of
    a roll under :data:`SWAPPED_FIT_MAX_ROLL_DEG`: ``"; with x and y swapped ..."``; else ``""``. The landmarks are
    not swapped: the file is the user's to mend. (A diagnosis only: the start, the rows, are as without it.)"""
    if s.start_failure != StartFailure.NO_POSE or s.landmarks_source.startswith("detector:"):
        return ""
    swapped = np.ascontiguousarray(s.landmarks[:, ::-1])
    given = swapped[np.isfinite(swapped).all(axis=1)]
    if not len(given) or not ((given >= -0.5) & (given <= np.array([W - 0.5, H - 0.5]))).all():
        return ""
    lm = torch.as_tensor(swapped, dtype=model.dtype, device=model.device)[None]
    fit = fit_landmarks(model, lm, intr, config=config.tracker.fit)
    if int(fit.status[0]) == int(SolveStatus.FAILED):
        return ""
    roll = float(matrix_to_euler(fit.rotation.double())[0, 2])
    if not abs(roll) < SWAPPED_FIT_MAX_ROLL_DEG:
        return ""
    return (f"; with x and y swapped its landmarks fit a pose: does {s.landmarks_source} hold (y, x) pairs, (row, "
            "column)? Swap its columns, or give it a first line y,x, then track it again without --resume")


def _warn_failed_starts(streams: list[_Stream], restarts: bool, hints: Sequence[str]) -> None:
    """Warn (one line per video) where the start from the first frame's landmarks failed, with its reason
    (:attr:`_Stream.start_failure`, :class:`~torchface.tracker.step.StartFailure`: its name and
    :attr:`~torchface.tracker.step.StartFailure.reason`, such as landmarks that no face fits, a black first frame, a
    face mostly outside the frame): every row of that video was written unusable (``success`` 0) with nothing said
    but the summary's lost count, and the warning guessed the cause among them all. ``restarts``: a detector starts
    such a stream afresh (with template management only: without it, its rows stay unusable, and the warning said it
    would be lost until the detector found a face). ``hints``: per stream, what its line adds
    (:func:`_swapped_fit_hint`; ``""``: nothing)."""
    for s, hint in zip(streams, hints, strict=True):
        if s.start_failure == StartFailure.NONE or s.replay is not None:  # (a resumed video's: said in its first run)
            continue
        then = ("it is lost until the detector finds a face it can start from" if restarts else
                "every row is unusable (success 0): give the landmarks of a frame that shows the face")  # fmt: skip
        warnings.warn(_worded(f"{s.name}: the start from the landmarks of frame {s.start} failed "
                              f"({s.start_failure.name}): {s.start_failure.reason}; {then}{hint}"), RuntimeWarning,
                      stacklevel=3)  # fmt: skip


def _start_record(config: JobConfig, s: _Stream) -> dict:
    """The sidecar's ``start``: how the video's first pose was found and, once the online start re-anchored it,
    what turns the CSV's pose into the pose that places the mesh.

    ``method``: ``"lookahead"`` (``--lookahead``), ``"online"`` (the online look-ahead start), or ``"landmark fit"``
    (``--no-online-refine``, no template management, or a resumed video the interrupted run had not re-anchored
    within the online start's ``max_frames``, resumed from its CSV's rows: one resumed sooner is tracked again from
    its first frame, :attr:`_Stream.retrack`, and one resumed from its checkpoint goes on from the online start's
    state, :attr:`_Stream.from_checkpoint`).
    ``lookahead_keyframes`` (``"lookahead"`` only, else None): the frames the first fit was refined against; empty for
    a video whose head did not turn ``yaw_deg`` within the frames read ahead (to ``min_keyframes`` sides), which
    starts from the landmark fit.
    ``first_frame``: the frame tracking started at (its landmarks are ``initial_landmarks_px``): 0, or the first
    frame where the detector found a face (the rows before it have no estimate). ``reanchored_at_frame``: the frame
    whose step re-anchored the stream (None: not, or not known: a record of an earlier version). The rows after it
    report the pose (rotation ``R``, translation ``t``) in the head frame of the first row, and the mesh is placed
    (overlay wireframe, normalised face, meshes; the overlay's head axes stay the rows' pose) by
    ``R_mesh = R @ head_rotation^T``, ``t_mesh = t - R_mesh @ head_translation``, with ``model.shape_coeffs``; their
    ``AUxx_r`` columns are measured from ``neutral_anim_coeffs`` (the re-estimated starting expression), ``anim_*``
    are the coefficients that place the mesh. The rows up to and including that frame (its row holds the estimate made
    before the re-anchoring) were tracked with ``first_shape_coeffs`` and place the mesh with their own pose
    (:func:`_drawn_pose`).
    ``failure``: why the start at ``first_frame`` failed (:attr:`_Stream.start_failure`), ``{"name": ..., "reason":
    ...}`` (:class:`~torchface.tracker.step.StartFailure`'s name, such as ``"TOO_FEW_POINTS"``, and its
    :attr:`~torchface.tracker.step.StartFailure.reason`), or None where it started: its rows are unusable (``success``
    0) from there, until a detector starts it afresh (with template management; a restart does not change it). A
    resumed video's is that of its start made again from the same frame and landmarks.
    """
    if config.lookahead is not None:
        method = "lookahead"
    elif _online_start(config) is not None and (s.replay is None or s.anchor is not None or s.retrack
                                                or s.from_checkpoint):  # fmt: skip
        method = "online"
    else:
        method = "landmark fit"
    anchor = s.anchor
    at = None if anchor is None else anchor.get("frame")  # (the record counts from the first tracked frame)
    return {
        "method": method,
        "lookahead_keyframes": list(s.keyframes) if method == "lookahead" else None,
        "first_frame": s.start,
        "reanchored_at_frame": None if at is None else at + s.start,
        "head_rotation": None if anchor is None else anchor["head_rotation"],
        "head_translation": None if anchor is None else anchor["head_translation"],
        "neutral_anim_coeffs": s.final_neutral,
        "first_shape_coeffs": s.first_shape,
        "failure": None if s.start_failure == StartFailure.NONE else {"name": s.start_failure.name,
                                                                      "reason": s.start_failure.reason},
    }  # fmt: skip


def _lookahead_fit(
    model: FaceModel, config: JobConfig, streams: list[_Stream], lm: Tensor, intr: Intrinsics
) -> LandmarkFit | None:
    """Read up to ``config.lookahead.max_frames`` frames of every stream ahead (kept in ``_Stream.ahead`` for the
    tracking pass) and return :func:`~torchface.tracker.lookahead.lookahead_fit`'s first-frame fit (None when no
    video has a second frame, or without ``config.lookahead``); a video shorter than the batch's longest is looked
    at with its last frame repeated."""
    la = config.lookahead
    if la is None:  # (never: the job calls it with a look-ahead)
        return None
    for s in streams:
        while len(s.ahead) < la.max_frames - 1 and s.error is None:
            try:
                s.ahead.append(_next_frame(s))
            except StopIteration:
                break
            except InputError as exc:  # this video stops after the frames read; the others go on
                s.error = exc
    longest = max(len(s.ahead) for s in streams)
    if longest < 1:  # nothing to look ahead at
        return None
    # (a shorter video repeats its last frame, as the tracking loop does once it has ended: the batch's shortest
    # length capped the look-ahead of every video, and a 1-frame video turned it off)
    first = streams[0].frame()
    frames = torch.empty((len(streams), longest + 1, *first.shape), dtype=first.dtype, device=first.device)
    for k, s in enumerate(streams):  # each frame read ahead moved into the batch, its list keeping a view: one copy
        frames[k, 0] = s.frame()  # of the frames in memory (stacked, they were held three times over at once)
        for j, frame in enumerate(s.ahead):
            frames[k, j + 1] = frame
            s.ahead[j] = frames[k, j + 1]
        frames[k, len(s.ahead) + 1 :] = frames[k, len(s.ahead)]
    fit, keys = lookahead_fit(model, config.tracker, frames.to(device=model.device, dtype=model.dtype), lm, intr,
                              config=la)  # fmt: skip
    for stream, found in zip(streams, keys):  # the sidecar's start.lookahead_keyframes ("lookahead" alone did not
        # say whether the first fit was refined at all); a shorter video's repeated last frame is that frame; fewer
        # than min_keyframes: not refined (lookahead_fit keeps the landmark fit), none listed
        refined = len(found) >= la.min_keyframes
        stream.keyframes = sorted({stream.start + min(int(i), len(stream.ahead)) for i in found}) if refined else []
    return fit


def _illumination_names() -> tuple[str, ...]:
    from torchface.appearance.illumination import ILLUMINATION_TERM_NAMES

    return tuple(ILLUMINATION_TERM_NAMES)


def _write_step(
    model: FaceModel, state: TrackerState, result, frames: Tensor, streams: list[_Stream], replaying: list[bool],
    columns: tuple[str, ...], rows: np.ndarray, t: int, intr: Intrinsics, edges: np.ndarray,
    normaliser: NormalisedFace, layout: ParamLayout, mesh_dirs: list[Path] | None, redetect_below: float,
    conf_label: str, smoothing: SmoothingConfig | None = None, smooth: SmoothingState | None = None,
    keep_expression: bool = False,
) -> SmoothingState | None:
    """Write frame ``t`` of every live stream (its frame ``t + start``, ``_Stream.start``): its CSV row (unless
    replayed), then its overlay, normalised face and mesh, drawn from that row as the CSV holds it
    (:func:`_drawn_pose`). With ``smoothing`` (``rows`` then end with :data:`~torchface.io.table.SMOOTH_COLUMNS`,
    to be filled), the rows' pose as written (a replayed row's as the CSV holds it) goes through the filter, whose
    state ``smooth`` (None: every stream starts) this returns for the next frame; the overlay and the meshes are
    drawn at the smoothed pose, the normalised face resampled at the raw one. With ``keep_expression``
    (:attr:`JobConfig.keep_expression`) the normalised face is resampled at the rows' neutral animation
    coefficients (:func:`_neutral_anim`) instead of their ``anim_*``."""
    live = [not s.done for s in streams]
    if not any(live):
        return smooth
    written = rows.copy()
    stamps: dict[int, float] = {}
    images: dict[int, np.ndarray | None] = {}
    new: dict[int, np.ndarray] = {}  # the rows to write (not replayed)
    for k, s in enumerate(streams):
        if not live[k]:
            continue
        stamp = stamps[k] = s.stamps.popleft()  # (its frame's time, replayed or not: it places its overlay frame)
        images[k] = s.images.popleft()
        if replaying[k] and s.replay is not None:  # (replaying: its replay holds row t)
            written[k] = s.replay[t]
            try:
                _check_replayed_time(s, s.replay[t], columns, stamp, t + s.start)
            except _ReplayedTimeError as exc:  # this video stops (its partial CSV as it was), the batch goes on
                s.done, s.error, live[k] = True, exc, False
                s.reader.close()
        else:
            row = rows[k].copy()
            row[0] = t + s.start
            row[1] = stamp
            new[k] = row
            written[k] = read_back(columns, row[None])[0]
    if smoothing is not None:
        values, smooth = _smooth_rows(smoothing, smooth, written, columns, streams, live, stamps, t)
        for k, row in new.items():  # (a replayed row holds what the interrupted run's filter gave it)
            row[-len(SMOOTH_COLUMNS) :] = values[k]
            written[k] = read_back(columns, row[None])[0]
    for k, row in new.items():
        streams[k].outputs()[0].write(row[None])
        streams[k].tracked += 1
    for k, s in enumerate(streams):
        if live[k]:
            s.last_row = written[k]
    R, trans, R_mesh, t_mesh, shape, alpha, light = _drawn_pose(model, state, streams, written, columns, t)
    if smoothing is not None:  # (what is drawn: the smoothed pose; what is resampled from the frame: the raw one)
        R_s, trans_s, R_mesh_s, t_mesh_s, _, _, _ = _drawn_pose(model, state, streams, written, columns, t, "smooth_")
    else:
        R_s, trans_s, R_mesh_s, t_mesh_s = R, trans, R_mesh, t_mesh
    verts_uv, _ = overlay_geometry(model, shape, alpha, R_mesh_s, t_mesh_s, intr)
    axes_uv = axes_geometry(R_s, trans_s, intr)  # the axes of the CSV's pose, not of the mesh's placement
    aa = matrix_to_axis_angle(R_mesh.to(torch.float64)).to(R_mesh.dtype)
    norm_alpha = _neutral_anim(state, streams, alpha, t) if keep_expression else alpha
    norm = normaliser.from_params(frames, shape, norm_alpha, aa, t_mesh, light, intr)
    norm_img = (norm.image * norm.mask).clamp(0, 1)
    verts_px, axes_px = verts_uv.detach().cpu().numpy(), axes_uv.detach().cpu().numpy()
    ci = columns.index("confidence")
    si = columns.index("success")
    st = columns.index("status")
    for k, s in enumerate(streams):
        if not live[k]:
            continue
        row = written[k]
        conf, ok = float(row[ci]), bool(row[si] > 0.5)
        s.confidence = conf
        s.low_count = 0 if conf >= redetect_below else s.low_count + 1
        if ok and conf >= redetect_below:
            s.near = verts_px[k]
        bgr = _frame_bgr(frames[k], images[k])
        unusable = "FAILED" if int(row[st]) == int(TrackStatus.FAILED) else "LOST"  # (both were drawn "LOST")
        _, overlay, normalised = s.outputs()
        overlay.write(draw_overlay(bgr, verts_px[k], edges, axes_px[k], conf, ok, f"#{t + s.start}", conf_label,
                                   unusable), stamps[k])  # fmt: skip
        normalised.write(_to_uint8_bgr(norm_img[k]))
        if mesh_dirs is not None:
            import trimesh

            verts = torch.matmul(model.deform(shape[k : k + 1], alpha[k : k + 1]), R_mesh_s[k].T) + t_mesh_s[k]
            mesh = trimesh.Trimesh(verts[0].detach().cpu().numpy(), model.faces.cpu().numpy(), process=False)
            ply = mesh_dirs[k] / f"{t + s.start:06d}.ply"
            try:
                mesh.export(str(ply))
            except OSError as exc:  # a full disk: say which file (the error named none), and keep no cut-off mesh
                ply.unlink(missing_ok=True)
                raise OutputError(f"{ply}: cannot write ({exc.strerror or exc})") from None
        s.frames += 1
    return smooth


def _smooth_rows(
    config: SmoothingConfig, state: SmoothingState | None, written: np.ndarray, columns: tuple[str, ...],
    streams: list[_Stream], live: list[bool], stamps: dict[int, float], t: int,
) -> tuple[np.ndarray, SmoothingState]:
    """The :data:`~torchface.io.table.SMOOTH_COLUMNS` ``(B, 18)`` of frame ``t``'s rows ``written`` ``(B, C)`` (as
    written: raw columns read back, or replayed): their pose filtered over time (:mod:`torchface.tracker.smoothing`,
    float64 on the CPU, at the frames' times ``stamps``) from the filter's ``state`` (None: every stream starts),
    and the filter's next state. A row starts its stream
    afresh where it is unsuccessful (passed through; the next successful one starts), after the online start's
    re-anchoring frame (``_Stream.anchor``'s ``frame``: the rows after it are the re-anchored estimate) and after a
    row where a re-detection was due (``_Stream.smooth_restart``); each depends on the rows alone, so a resumed run's
    filter, given the replayed rows, goes on as the interrupted run's did. Streams no longer live are passed
    through."""
    B = written.shape[0]
    R, trans, _, _ = _row_values(written, columns)
    ok = torch.as_tensor(written[:, columns.index("success")] > 0.5) & torch.as_tensor(live)
    time = torch.tensor([stamps.get(k, 0.0) for k in range(B)], dtype=torch.float64)
    restart = torch.zeros(B, dtype=torch.bool)
    for k, s in enumerate(streams):
        at = None if s.anchor is None else s.anchor.get("frame")
        restart[k] = s.smooth_restart or (at is not None and t == at + 1)
        s.smooth_restart = False
    dt = time - state.time if state is not None else torch.ones_like(time)  # (the first row starts anyway)
    rot = trans_state = None
    R_raw = R
    if config.rotation is not None:
        R, rot = one_euro_rotation_step(R, None if state is None else state.rotation, dt, config.rotation, valid=ok,
                                        restart=restart)  # fmt: skip
    if config.translation is not None:
        trans, trans_state = one_euro_step(trans, None if state is None else state.translation, dt,
                                           config.translation, valid=ok, restart=restart)  # fmt: skip
    values = pose_values(R, trans)
    # a rotation passed through (a start, an unsuccessful row): the row's own angle cells, not those recomputed from
    # its rounded matrix (up to 4e-6 degrees apart), so that a start's smooth_* cells are its raw ones exactly
    kept = (R == R_raw).flatten(1).all(1).numpy()
    angles = np.array([columns.index(c) for c in POSE_COLUMNS[3:]])
    values[kept, 3 : len(POSE_COLUMNS)] = written[np.ix_(kept, angles)]
    return values, SmoothingState(rot, trans_state, None, time)


def _drawn_pose(
    model: FaceModel, state: TrackerState, streams: list[_Stream], rows: np.ndarray, columns: tuple[str, ...], t: int,
    pose: str = "",
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """What the outputs of frame ``t`` show, from its ``(B, C)`` CSV rows as written (:func:`read_back`) and the
    sidecar's ``start`` (:func:`_start_record`), so that every output agrees with the CSV and a replayed row is drawn
    as the run that tracked it drew it: ``(R, t)`` the rows' pose (the head axes), ``(R_mesh, t_mesh)`` and
    ``shape`` the pose and shape coefficients placing the mesh (after the re-anchoring frame the pose offset by
    :func:`_head_offset` and the state's shape, the sidecar's ``model.shape_coeffs``; else the row's own pose and
    the first shape, ``start.first_shape_coeffs``), ``alpha`` the rows' ``anim_*``, ``light`` their ``illum_*``.
    The model's dtype and device; a lost or failed row is drawn as the CSV holds it (not at the parameters the
    tracker falls back to). ``pose``: the prefix of the pose columns drawn (``"smooth_"``: the smoothed pose,
    ``JobConfig.smoothing``)."""
    R, trans, alpha, light = _row_values(rows, columns, pose)
    R_mesh, t_mesh = R.clone(), trans.clone()
    shape = state.shape_coeffs.detach().to("cpu", torch.float64).clone()
    for k, s in enumerate(streams):
        offset = _head_offset(s, t)
        if offset is None:
            if s.first_shape is not None:
                shape[k] = torch.as_tensor(s.first_shape, dtype=torch.float64)
            continue
        D, d = (torch.as_tensor(x, dtype=torch.float64) for x in offset)
        R_mesh[k] = torch.matmul(R[k], D.T)
        t_mesh[k] = trans[k] - torch.matmul(R_mesh[k], d)
    R, trans, R_mesh, t_mesh, shape, alpha, light = (
        x.to(device=model.device, dtype=model.dtype) for x in (R, trans, R_mesh, t_mesh, shape, alpha, light)
    )
    return R, trans, R_mesh, t_mesh, shape, alpha, light


@dataclass(eq=False)
class _Current:
    """The frames of the step being tracked, and how often the recovery callback has matched each stream in it."""

    frames: Tensor
    asked: dict[int, int] = field(default_factory=dict)


def _recovery_near(streams: list[_Stream], current: _Current):
    """The ``near`` points (:class:`torchface.detect.Detector`) of a frame the tracker's recovery asks the detector
    about: the last confident position of the stream whose frame of ``current.frames`` it is (the callback is given
    the lost streams' frames only, in stream order: of streams with equal frames, the one asked about least often
    in this step, the first of those). A stream is asked about twice in a step when a restart follows its recovery
    attempt (``TemplateConfig.restart_after_unmatched``): the second call counts too and asks for its face again
    (it was taken as no stream's: no ``near``, not counted)."""

    def near_of(frame: Tensor) -> np.ndarray | None:
        best = None
        for k, s in enumerate(streams):
            if s.done or (best is not None and current.asked.get(k, 0) >= current.asked.get(best, 0)):
                continue
            if torch.equal(current.frames[k].to(device=frame.device, dtype=frame.dtype), frame):
                best = k
        if best is None:
            return None
        current.asked[best] = current.asked.get(best, 0) + 1
        streams[best].detector_calls += 1
        return streams[best].near

    return near_of


def _maybe_redetect(
    model: FaceModel, config: JobConfig, state: TrackerState, frames: Tensor, streams: list[_Stream], detector,
    intr: Intrinsics, layout: ParamLayout, replayed: list[bool],
) -> TrackerState:
    """Ask the detector again for streams whose confidence stayed low, for the face nearest each one's last
    confident position (when it takes ``near``); re-fit their pose (shape and template kept). Streams whose next
    row is replayed too (``replayed``) only count their low frames again: what a re-detection there gave is in the
    next rows already (the detector was asked on every replayed row due one, for nothing but the time and the
    sidecar's counts); the last replayed row's is made again, as the tracking goes on from it. A re-fitted stream's
    motion prediction (``ManagementState.steady``) starts again: no velocity across the re-fit (with ``redetect_below``
    above the confidence threshold, the next frame started from the jump to the detector's pose, repeated)."""
    params, refitted = state.params, []
    for k, s in enumerate(streams):
        if s.done or s.low_count < config.redetect_after:
            continue
        s.low_count = 0
        s.smooth_restart = True  # (due, whether or not it finds a face: the rows alone say it, replayed or not)
        if replayed[k]:
            s.replayed_redetection = s.frames - s.start - 1  # (this row's t: its row is written)
            continue
        s.detector_calls += 1
        image = detector_image(frames[k])
        points = detector(image, near=s.near) if accepts_near(detector) else detector(image)
        if points is None:
            continue
        where = f"{s.reader.info.path}: the {config.detector} detector's landmarks at a re-detection"
        points = usable_detection(points, intr.width, intr.height, where, warn=not s.detection_warned)
        if points is None:  # NaN / mostly outside: no face (warned about once per video)
            s.detection_warned = True
            continue
        lm = torch.as_tensor(points, dtype=model.dtype, device=model.device).unsqueeze(0)
        fit = fit_landmarks(model, lm, intr, config=config.tracker.fit)
        p = params[k].clone()
        p[layout.rotation] = fit.axis_angle[0]
        p[layout.translation] = fit.translation[0]
        params = torch.cat([params[:k], p[None], params[k + 1 :]])
        s.redetections += 1
        refitted.append(k)
    if not refitted:
        return state
    ms = state.management
    if ms is not None and ms.steady is not None:
        steady = ms.steady.clone()
        steady[refitted] = 0
        state = replace(state, management=replace(ms, steady=steady))
    return replace(state, params=params)
