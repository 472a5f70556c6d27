"""``torch.utils.data`` datasets of normalised faces, tracked inside the ``DataLoader`` worker processes.

:class:`VideoDataset` (video files or ``.npy`` frame arrays) and :class:`FrameFolderDataset` (folders of
images, read in name order) are iterable datasets. Each video is tracked from its first frame's 68 iBUG
landmarks (:data:`LandmarkSource`; the model's ``K`` with :attr:`FaceTrackingConfig.model
<training_hooks.transforms.FaceTrackingConfig.model>`: NaN rows for missing points, as ``torchface track`` takes
them; or a :data:`Detector`'s, from the first frame where it finds a face, below;
:func:`~training_hooks.transforms.track_sequence`, one stream at a time) and every frame becomes a
normalised face with its parameters; the dataset yields one item per frame, or one per clip of
:attr:`DatasetConfig.clip_length` frames every :attr:`DatasetConfig.clip_stride` frames. A video is tracked to
its end before its items are yielded (a :class:`~training_hooks.transforms.TrackedSequence`, whose items may be
shuffled), so a worker holds every frame's face and parameters of the video it tracks: about 66 KB a frame with
the default 128-pixel uint8 faces (7 GB for an hour of video at 30 frames/s): cut long videos into parts.

With a :data:`Detector` in place of landmarks, a video whose first frame shows no face (a title card, a black
frame, an empty room) is searched frame by frame as ``torchface track --detector`` searches it
(:func:`torchface.detect.search_first_face`) and tracked from the first frame where the detector finds one, as the
video cut to start there would be: its items are those of the cut video, but for ``frame``, which stays the frame's
number in the video (the sequence's :attr:`~training_hooks.transforms.TrackedSequence.first_frame` is where the
face was found); the frames before it give no item. A video in none of whose frames it finds a face is an
:class:`~torchface.io.InputError` naming it and the frames searched (no cap: it is searched to its end). Each
video is searched once per dataset: the detection is shared with the dataset's ``DataLoader`` workers and kept for
later epochs (a new dataset searches again, then finds its sequence in the cache).

Sharding: each video is tracked by exactly one process, from its start to its end, so that process owns its
tracker state and no state crosses processes. In a ``torch.distributed`` process group (DDP: default group,
``world_size`` ranks) video ``i`` belongs to rank ``i % world_size`` (:attr:`DatasetConfig.shard_ranks`), and
within a rank the ``j``-th of its videos to ``DataLoader`` worker ``j % num_workers``
(``torch.utils.data.get_worker_info()``; the rank's own process does everything when ``num_workers = 0``):
video ``i`` goes to rank ``i % world_size``, worker ``(i // world_size) % num_workers``
(:meth:`VideoDataset.worker_videos`). Without a group this is video ``i`` -> worker ``i % num_workers``. Each
item is tracked by one rank, except those that a worker without a video of its own repeats to balance the counts
(below): it tracks other ranks' videos again (unless cached).
Tracking runs with a fixed torch thread count
(:attr:`~training_hooks.transforms.FaceTrackingConfig.num_threads`), so every item is bit-identical for any
number of ranks and workers (only the order in which a ``DataLoader`` interleaves the workers' items differs).
The rank and world size are read when the dataset is iterated, or, in a ``DataLoader`` worker started with
the ``spawn`` or ``forkserver`` method (where ``torch.distributed`` is not initialised), the ones of the rank
that sent the dataset to it. Use the datasets without a ``DistributedSampler`` (they are iterable datasets).

Equal counts under DDP (:attr:`DatasetConfig.rank_balance`): a DDP training loop hangs when one rank takes more
optimiser steps than another, so by default every rank yields the same number of items and batches, as a
``DistributedSampler`` gives them. A ``DataLoader`` batches each worker's items separately, so the counts are made
equal per worker: worker ``w`` of every rank yields as many items as the worker ``w`` with the most
(:attr:`RankBalance.PAD`, the default: a worker short of items repeats its own from its first video on, one without
a video repeats those of its worker on the other ranks, as ``DistributedSampler(drop_last=False)`` does) or with
the fewest (:attr:`RankBalance.DROP`: the rest are left out, as ``drop_last=True``). This needs the same
``num_workers`` on every rank, and each video's item count before it is tracked: the workers count the frames of
their worker's videos on every rank (:meth:`VideoDataset.num_items`: image folders and ``.npy`` arrays at no cost,
a video file whose tracked sequence is in the cache by the count stored with it (the file is hashed, not decoded),
other video files decoded through without tracking; with a detector, the frames from the first with a face on,
the video searched first, as above), each video once per dataset (the counts are shared with the
workers' copies, and kept for later epochs). Repeated items equal the originals (same ``video`` and ``frame``),
so the union of the ranks' epochs is every item at least once (PAD). :attr:`RankBalance.UNEVEN` turns this off:
each rank yields its own videos' items once and the counts differ unless the videos split evenly (wrap the
training loop in ``DistributedDataParallel.join()``). With fewer videos than ranks :class:`DistributedWarning`
says so, once per dataset in each rank. ``DatasetConfig(shard_ranks=False)`` makes every rank yield every item
(for a dataset built with each rank's own list of videos; no balancing).

Skipping (:attr:`DatasetConfig.keep_going`, off by default): a video that cannot be read or tracked (an
:class:`~torchface.io.InputError` or ``OSError``) stops the epoch by default, as it stops ``torchface track``. With
``keep_going`` it is skipped as ``torchface track --keep-going`` skips it: the process that finds it warns
(:class:`SkippedVideoWarning`, naming the file and the error, once: another process of the dataset failing on it
finds it recorded and says nothing; DDP ranks share nothing, so each warns of a video it cannot count) and records
it in :attr:`VideoDataset.skipped` (shared memory: the dataset the caller holds sees its workers' records), the video
yields no item, and it is not tried again in later epochs (make the dataset again to retry it). A video is tracked
whole before its items are yielded, so none of a skipped video's items is yielded (an error at its last frame too).
The datasets are iterable (no ``len()``, no item by index: there is no index a sampler could ask for and get another
video's item), so skipping changes no sampler's indices; what it changes is the epoch's item count:

- :meth:`VideoDataset.num_items` counts a video without tracking it: a video that cannot even be counted (it does
  not decode, or the detector finds no face in it) is skipped then and counts 0, on every rank alike; one that fails
  only when tracked (landmarks outside its frame, a frame that fails to decode partway) keeps its count, so
  :meth:`~VideoDataset.count_items` and :meth:`~VideoDataset.worker_items` are then an upper bound of the epoch's
  items in one process (a schedule planned from them ends a few steps early; it never overruns).
- Under DDP with :attr:`RankBalance.PAD` or ``DROP`` every rank still yields the balanced count per worker: a worker
  whose video was skipped when tracked repeats its other videos' items in its place (as ``PAD`` repeats a short
  worker's), so the ranks take the same number of steps and DDP does not hang. It repeats the sequences it still
  holds (those tracked after the skip, or the last one before it), so no video is tracked twice in a worker's epoch,
  cache or not. Each rank records its own skips. A worker left nothing to repeat raises a ``RuntimeError`` rather
  than end short, saying what happened with the counts: its videos and its worker's videos on the other ranks
  skipped, or giving fewer items when tracked than counted (a file replaced since the dataset counted it). A rank
  cannot tell whether another read those videos and takes more steps.

Short videos: a clip dataset (:attr:`DatasetConfig.clip_length`) without :attr:`~DatasetConfig.keep_short_clips`
leaves out a video shorter than ``clip_length`` (it gives no clip). Each video's frame count is kept in shared
memory as it is counted (:meth:`VideoDataset.num_items`) or tracked, and the process that first knows every count
(:meth:`VideoDataset.count_items`, or the ``DataLoader`` worker that ends an epoch's pass last; under DDP, every
count of its rank's videos) warns once per dataset (:class:`ShortVideoWarning`) of how many were too short, which,
and their frames. Where none of the dataset's videos gives a clip (too short, or skipped, at least one too
short: a dataset all of whose videos were skipped has its :class:`SkippedVideoWarning` alone), the dataset yields
nothing and a loop over it would take no step without a word: the end of the epoch's pass raises a ``ValueError``
naming the videos and the way out, each epoch (:meth:`~VideoDataset.count_items` only warns). Under DDP a rank
none of whose own videos gives a clip counts the other ranks' videos (until one gives a clip), so that the error
comes on every rank there too. With a detector a video's frames are those from its first face (the message says
which frame). A pass cut short says nothing (a later whole pass, or :meth:`~VideoDataset.count_items`, does).

Progress (:attr:`DatasetConfig.progress_after`): counting the videos' items decodes each video file through, and
with a detector searches each for its first face; :meth:`VideoDataset.count_items` does it for every video, and under
DDP each ``DataLoader`` worker does it for its videos on every rank before its first batch. Over hundreds of videos
that takes minutes, so a count that has taken more than ``progress_after`` seconds (5 by default) says how far it
has got, in whole lines on stderr (``VideoDataset: counting the items of 200 videos: 37 counted in 6 s (...)``),
another every :data:`PROGRESS_EVERY_S` seconds and one when it ends; a line is due as a video is counted and as
each of its frames is read (decoded, searched by the detector), so one long video says how far it has got too
(``, a.avi: 840 frames searched for its first face``). The wait for a ``DataLoader`` worker's first item (it
searches and tracks its first video whole, and with ``shuffle_buffer`` those that fill the buffer, before it yields
anything) says its progress alike (``VideoDataset: the first item: 0 videos tracked in 6 s, a.avi: 150 frames
tracked (...)``, and ``the first item came in 41 s``). One process speaks: rank 0's, and where there are
``DataLoader`` workers, its worker 0 (the others do as much meanwhile, at about its pace). A shorter wait (a test,
a few videos, counts known already) says nothing; ``progress_after=None`` never does. Tracking after the first
item says nothing (:attr:`VideoDataset.stats`, :func:`loader_throughput` measure it).

Epochs: with :attr:`DatasetConfig.shuffle_buffer` the order is seeded by the epoch (:meth:`VideoDataset.set_epoch`),
so a training loop that does not call ``set_epoch`` before each epoch repeats one order every epoch. The dataset
counts its ``set_epoch`` calls (each call, of the same epoch too) and records what the last iteration begun had: that
count, the ``DataLoader`` workers, the rank and the world size, which with the epoch decide the order; all in shared
memory. An iteration that begins (its first item asked for) with the same, shuffled, repeats the last one's order,
and :class:`RepeatedEpochWarning` says so, once per dataset. Iterations begin in the process that iterates the
dataset (``num_workers=0``) or in its ``DataLoader`` workers (worker 0 records them): forked or spawned, persistent
or started anew each epoch, the workers share the record with the dataset, so a forgotten ``set_epoch`` is told at
the second epoch. Not told: a dataset without ``shuffle_buffer`` (the same order by design); an iteration after a
``set_epoch`` of the same epoch (``data.set_epoch(data.epoch)``: the way to say the order is wanted again); one with
other worker counts, rank or world size than the last (another order); the first iteration of a ``copy.deepcopy`` or
plain-pickled copy (an independent dataset, not iterated yet; ``copy.copy`` shares the record, as the epoch);
:mod:`training_hooks.lightning`'s loaders (they call ``set_epoch`` before each iteration); :func:`loader_throughput`'s
pass (a measurement), nor the iteration after it. Told, as the order does
repeat: a shuffled validation set iterated each epoch (give it ``shuffle_buffer=0``, or call
``data.set_epoch(data.epoch)`` before it), and a first batch looked at (``next(iter(loader))``) followed by the first
epoch with no ``set_epoch`` between (a loop that calls it after each epoch). Under DDP each rank's
dataset keeps its own record where each rank builds its own (``torchrun``'s processes); ranks handed one dataset's
shared memory (Lightning's ``ddp_spawn``) overwrite each other's record, and are not told. The warning can be
filtered as any (a forked worker keeps the filter of the process that started it; a spawned one takes ``-W`` and
``PYTHONWARNINGS``).

Copies: ``copy.copy(data)`` shares the dataset's state (the same shared memory: epoch, counts, detections, skips,
the warnings given); ``copy.deepcopy(data)`` is an independent dataset, its state copied as it is then into shared
memory of its own, which its own ``DataLoader`` workers share with it (not with ``data``). A ``DataLoader`` sends
the dataset to its workers by reference to its shared memory (forked, or pickled by ``multiprocessing``); a plain
``pickle`` of it reads back an independent dataset. The once-per-dataset warnings (:class:`SkippedVideoWarning`
of a video, :class:`ShortVideoWarning`, :class:`DistributedWarning`) are given exactly once among a dataset's
processes: the first to create a marker file in the dataset's private temporary folder (``torchface-dataset-*``,
made with the dataset, removed when it is collected or its process exits; one a killed process left is removed by
a later process's first dataset, once its maker is certainly gone) gives it.

Cache: with :attr:`DatasetConfig.cache_dir`, a video's :class:`~training_hooks.transforms.TrackedSequence`
(parameters, confidence, status and the normalised faces, uint8 by default) is stored after tracking and read
back in later epochs (:mod:`training_hooks.cache`: keys of the content, the config, the landmarks and the frame
they are of, atomic writes, damaged files tracked again; not the videos' labels, ``targets``). Each item says
where it came from (``cached``), and :attr:`VideoDataset.stats` counts hits and misses in the current process.

Items are dicts of tensors (:meth:`TrackedSequence.item <training_hooks.transforms.TrackedSequence.item>`: ``frame``,
the frame's number in the video) plus ``video`` ``()`` int64 (index in the dataset's list), ``cached`` ``()`` bool
and, with ``targets=``, ``target``: its video's label (``()`` or the label's shape; one per clip, not per frame,
as ``video``). Frame items stack with PyTorch's default collate; clip items of different lengths with
:func:`~training_hooks.collate.collate_clips`.

Example:
    >>> from torch.utils.data import DataLoader
    >>> # data = VideoDataset(["a.avi", "b.avi"], ["a.csv", "b.csv"], DatasetConfig(cache_dir="cache"))
    >>> # for batch in DataLoader(data, batch_size=64, num_workers=2): batch["face"]  # (64, 3, 128, 128)
"""

from __future__ import annotations

import copy
import enum
import functools
import glob
import itertools
import multiprocessing.util
import os
import pickle
import random
import re
import shutil
import stat
import sys
import tempfile
import time
import types
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from multiprocessing.reduction import ForkingPickler
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from torchface.conventions import MEDIAPIPE_MESH_HINT, MEDIAPIPE_MESH_POINT_COUNTS, other_landmark_set_hint
from torchface.detect import detector_image, search_first_face
from torchface.extending import (
    check_bool,
    check_choice,
    check_int,
    check_no_tilde,
    check_number,
    check_optional_int,
    missing_path_hint,
)
from torchface.io.errors import InputError
from torchface.io.landmarks import NUM_LANDMARKS, check_landmarks, read_landmarks
from torchface.io.video import (
    CONVERT_HINT,
    CONVERT_OPTION,
    NAN_PIXELS_HINT,
    NAN_PIXELS_WHY,
    folder_of_videos_hint,
    image_files,
    open_capture,
    open_frames,
)
from torchface.model.face_model import FaceModel
from torchface.tracker.step import TrackerConfig
from training_hooks.cache import CacheStats, TrackCache, cache_key, content_hash
from training_hooks.transforms import FaceTrackingConfig, NormaliseFaces, TrackedSequence, _landmarks_shape_hint

__all__ = [
    "DatasetConfig",
    "DistributedWarning",
    "DatasetStats",
    "Detector",
    "FrameFolderDataset",
    "LandmarkSource",
    "RankBalance",
    "RepeatedEpochWarning",
    "ShortVideoWarning",
    "SkippedVideoWarning",
    "Targets",
    "VideoDataset",
    "clip_bounds",
    "loader_throughput",
]

#: First-frame landmarks of one video: a ``(68, 2)`` array or tensor in pixels, or a ``.csv`` / ``.pts`` / ``.npy`` file
#: (:func:`torchface.io.read_landmarks`). A missing point (occluded) is a NaN row, given weight 0 by the landmark fit,
#: as ``torchface track`` takes a file's and :meth:`FaceTracker.initialise <torchface.tracker.FaceTracker.initialise>`
#: an array's: at least :data:`~torchface.tracker.fit.MIN_FIT_LANDMARKS` (4) given; a row with one coordinate NaN, an
#: infinite value or more than half of the given points outside the frame is refused
#: (:func:`torchface.io.check_landmarks`; a face at the frame's edge may have points just outside it).
LandmarkSource = np.ndarray | Tensor | str | os.PathLike
#: A detector: ``(image_rgb (H, W, 3) uint8) -> (68, 2) landmarks or None`` (:mod:`torchface.detect`). A
#: ``DataLoader`` worker started by ``spawn`` or ``forkserver`` (the default on macOS and Windows, and on Linux from
#: Python 3.14) receives it pickled: a module-level function or an instance of a module-level class (a lambda, or a
#: function or class defined inside a function, is a ``pickle.PicklingError`` naming it then).
Detector = Callable[[np.ndarray], "np.ndarray | None"]
#: Labels of a dataset's videos (:class:`VideoDataset`'s ``targets``), one per video in the order of the videos: a
#: sequence of ints (class indices), floats, or arrays / tensors of one shape; or one array or tensor whose first
#: dimension is the videos' (``(N,)``, ``(N, ...)``).
Targets = Sequence[int | float | np.ndarray | Tensor] | np.ndarray | Tensor


class DistributedWarning(UserWarning):
    """A ``torch.distributed`` process group has more ranks than a dataset has videos: a rank without a video
    repeats other ranks' items (:attr:`RankBalance.PAD`) or yields none (module docstring, "Sharding"). Warned
    once per dataset in each rank (by its first ``DataLoader`` worker, not again in later epochs)."""


class SkippedVideoWarning(UserWarning):
    """With :attr:`DatasetConfig.keep_going`, a video that cannot be read or tracked is skipped (its items left out)
    instead of stopping the epoch: warned once per dataset, in the process that found it (a ``DataLoader`` worker
    prints it to its stderr), and recorded in :attr:`VideoDataset.skipped`, which every process of the dataset sees.
    ``torchface track --keep-going``'s :class:`~torchface.job.InputSkipped` for a dataset."""


class ShortVideoWarning(UserWarning):
    """Videos of a clip dataset (:attr:`DatasetConfig.clip_length`, without :attr:`~DatasetConfig.keep_short_clips`)
    are shorter than ``clip_length`` and give no clip: the warning says how many, which, and their frame counts
    against ``clip_length``. Warned once per dataset (not by each ``DataLoader`` worker, nor again in later epochs),
    by the process that first knows every video's count: :meth:`VideoDataset.count_items`, or the ``DataLoader``
    worker that finishes an epoch's pass last (each video counted when it was counted or tracked). Where no video
    gives a clip the dataset yields nothing: that is a ``ValueError`` instead (module docstring, "Short videos")."""


class RepeatedEpochWarning(UserWarning):
    """A shuffled dataset (:attr:`DatasetConfig.shuffle_buffer`) began an iteration in the same order as an earlier
    one: no :meth:`VideoDataset.set_epoch` came between them, so a training loop that forgets it repeats its first
    epoch's order every epoch. Warned once per dataset, by the process that began the iteration (a ``DataLoader``
    worker prints it to its stderr), when the dataset can tell (module docstring, "Epochs"). Call
    ``data.set_epoch(epoch)`` before each epoch (:class:`~training_hooks.lightning.TrackedFaceDataModule`'s loaders
    do under a trainer), or, to repeat an order deliberately, ``data.set_epoch(data.epoch)`` before the iteration."""


class RankBalance(enum.Enum):
    """How the ranks of a ``torch.distributed`` group get equal item counts (module docstring, "Sharding"), as a
    ``DistributedSampler`` gives them: per ``DataLoader`` worker, so that their batch counts are equal too."""

    #: Each worker yields as many items as the same worker of the rank with the most: a worker short of items
    #: repeats its own videos' items from its first video on (one without a video of its own, those of its
    #: worker on the other ranks), as ``DistributedSampler(drop_last=False)`` does. The default.
    PAD = "pad"
    #: Each worker yields as many items as the same worker of the rank with the fewest, and leaves out the rest of
    #: its items, as ``DistributedSampler(drop_last=True)`` does.
    DROP = "drop"
    #: Each rank yields its own videos' items and no others: counts differ unless the videos split evenly, and the
    #: training loop must cope (``DistributedDataParallel.join()``).
    UNEVEN = "uneven"


#: A dataset's attributes in shared memory (:func:`_shared_state`, :func:`_shared_detections`, :func:`_shared_skips`,
#: :func:`_shared_frames`, :func:`_shared_iterations`).
_SHARED_STATE: tuple[str, ...] = ("_shared", "_found_at", "_found", "_skips", "_frames", "_iterations")

#: Entries of a dataset's shared state (:func:`_shared_state`).
_EPOCH, _WARNED, _COUNTS = 0, 1, 2


def _shared_state(num_videos: int, epoch: int = 0) -> Tensor:
    """``(2 + num_videos,)`` int64: the epoch, whether the :class:`DistributedWarning` was given, and each video's
    item count (-1: not counted yet). A dataset keeps it in shared memory, so that its copies in ``DataLoader``
    workers (forked, or pickled to spawned ones) share it: persistent workers see each ``set_epoch``, and later
    workers and epochs neither warn again nor count a video again."""
    state = torch.full((_COUNTS + num_videos,), -1, dtype=torch.int64)
    state[_EPOCH], state[_WARNED] = epoch, 0
    return state


def _shared_detections(num_videos: int) -> tuple[Tensor, Tensor]:
    """Where a dataset's detector found each video's first face, in shared memory as :func:`_shared_state` (so that
    neither a ``DataLoader`` worker nor a later epoch searches a video again): ``(num_videos, 5)`` int64, the
    frame (-1: not searched yet) and the video's :func:`~training_hooks.cache.content_hash` as four words, and
    ``(num_videos, 68, 2)`` float64, the landmarks found in that frame: 1128 bytes a video, so a dataset without a
    detector passes ``num_videos=0`` (with landmarks for each of a million clips it held 1.1 GB of ``/dev/shm``,
    whose default size in a Docker container is 64 MB)."""
    where = torch.full((num_videos, 5), -1, dtype=torch.int64).share_memory_()
    return where, torch.zeros(num_videos, NUM_LANDMARKS, 2, dtype=torch.float64).share_memory_()


#: Bytes of a skipped video's record (:func:`_shared_skips`): a flag, then its reason, UTF-8, cut to fit.
_SKIP_BYTES: int = 256


def _shared_skips(num_videos: int) -> Tensor:
    """Which videos a dataset with :attr:`DatasetConfig.keep_going` skipped and why, in shared memory as
    :func:`_shared_state` (its ``DataLoader`` workers' skips reach the dataset the caller holds, and a later epoch does
    not try a skipped video again): ``(num_videos, 256)`` uint8, per video a flag (1: skipped; written after the
    reason) and the reason, UTF-8, zero-padded: 256 bytes a video, so a dataset without ``keep_going`` passes
    ``num_videos=0``."""
    return torch.zeros(num_videos, _SKIP_BYTES, dtype=torch.uint8).share_memory_()


def _shared_frames(num_videos: int) -> Tensor:
    """Each video's frame count as a clip dataset without ``keep_short_clips`` finds it (counted or tracked), to say
    which videos are too short for a clip (:class:`ShortVideoWarning`): ``(1 + num_videos,)`` int64 in shared memory
    as :func:`_shared_state`, entry 0 whether the warning was given, then per video its frames (those from the first
    with a face, with a detector), -1 not known yet, -2 skipped (:attr:`DatasetConfig.keep_going`). 8 bytes a video;
    a dataset whose videos cannot be too short (frame items, ``keep_short_clips``) passes ``num_videos=0`` (an empty
    tensor)."""
    state = torch.full((1 + num_videos,) if num_videos else (0,), -1, dtype=torch.int64)
    if num_videos:
        state[0] = 0
    return state.share_memory_()


#: Entries of a dataset's record of its iterations (:func:`_shared_iterations`).
_SETS, _TOLD, _BEGUN = 0, 1, 2


def _shared_iterations() -> Tensor:
    """``(3,)`` int64 in shared memory as :func:`_shared_state`, to tell an iteration that repeats an earlier one's
    shuffled order (:class:`RepeatedEpochWarning`): how many times the epoch was set (each
    :meth:`VideoDataset.set_epoch`, the same epoch too), whether the warning was given, and the
    :func:`_iteration_mark` of the last iteration begun (-1: none). A separate tensor, not entries of
    :func:`_shared_state`, whose layout a dataset pickled before it keeps."""
    state = torch.zeros(3, dtype=torch.int64)
    state[_BEGUN] = -1
    return state.share_memory_()


def _iteration_mark(sets: int, workers: int, rank: int, world: int) -> int:
    """What decides an iteration's shuffled order besides the epoch, as one int64 (written and read whole, where
    two processes of the dataset could meet): the count of :meth:`VideoDataset.set_epoch` calls (so a call, even
    of the same epoch, makes the next iteration a new one), the ``DataLoader`` workers (1: none, the same order as
    one worker), the rank and the world size. Two equal marks are the same order (hashed into 62 bits: two
    different ones meet with a chance of 2**-62)."""
    return hash((sets, workers, rank, world)) & ((1 << 62) - 1)


#: :func:`_shared_frames`' entry of a skipped video.
_SKIPPED_FRAMES: int = -2


def _content_words(content: str) -> Tensor:
    """``(4,)`` int64: a :func:`~training_hooks.cache.content_hash` (64 hex digits) as :func:`_shared_detections`
    keeps it."""
    return torch.from_numpy(np.frombuffer(bytes.fromhex(content), dtype=np.int64).copy())


#: The start of a dataset's private folder's name (:class:`_Claims`), in :func:`tempfile.gettempdir`.
_CLAIMS_PREFIX: str = "torchface-dataset-"

#: A folder name :func:`_claims_owner` wrote: ``torchface-dataset-<boot id>-<pid namespace>-<pid>-<start>-`` then
#: ``mkdtemp``'s random part.
_CLAIMS_NAME: re.Pattern[str] = re.compile(
    re.escape(_CLAIMS_PREFIX) + r"([0-9a-f]{32})-([0-9]+)-([0-9]+)-([0-9]+)-[A-Za-z0-9_]+"
)


def _process_start(pid: int) -> int | None:
    """When process ``pid`` (of this ``/proc``) started, in clock ticks after boot (``/proc/<pid>/stat``'s 22nd
    field: a pid reused by a later process has a later one), or None where there is no such process.

    Raises:
        OSError: where ``/proc`` cannot tell (no ``/proc``, not readable); ValueError, IndexError: a ``stat`` not
            read as Linux writes it."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            text = f.read()
    except (FileNotFoundError, ProcessLookupError):
        if not os.path.isdir("/proc/self"):  # (no /proc at all: not known)
            raise
        return None
    return int(text[text.rindex(b")") + 2 :].split()[19])  # (after the command's parentheses: fields 3 on)


def _claims_owner() -> tuple[str, int, int, int] | None:
    """This process as a folder's name records its maker (:data:`_CLAIMS_NAME`): the kernel's boot id, the inode of
    its pid namespace, its pid and start (:func:`_process_start`); None where they cannot be read (not Linux, a
    ``/proc`` of another pid namespace than this process's), and no folder records its maker."""
    try:
        pid = os.getpid()
        if os.readlink("/proc/self") != str(pid):  # (a /proc mounted from another pid namespace: its pids are not ours)
            return None
        with open("/proc/sys/kernel/random/boot_id") as f:
            boot = f.read().strip().replace("-", "").lower()
        start = _process_start(pid)
        if start is None or not re.fullmatch(r"[0-9a-f]{32}", boot):
            return None
        return boot, os.stat("/proc/self/ns/pid").st_ino, pid, start
    except (OSError, ValueError, IndexError):
        return None


def _remove_stale_claims(folder: str, owner: tuple[str, int, int, int]) -> list[str]:
    """Remove the private folders of datasets (:class:`_Claims`) in ``folder`` whose makers are certainly gone
    (killed by SIGKILL: a dataset's folder is otherwise removed with it or at its process's exit); returns their
    names. ``owner``: this process (:func:`_claims_owner`).

    A folder is removed only where it is this user's (a directory, not a link), its name records its maker
    (:data:`_CLAIMS_NAME`: an older torchface's does not), made under this boot and in this pid namespace (another
    machine's, a container's of its own pid namespace sharing the temporary folder, or one of a boot before: whether
    its maker lives is not known here) and ``/proc`` shows no process of that pid, or one that started at another
    time (the pid reused). One whose maker lives, or whose maker ``/proc`` cannot tell, is left. The maker's
    ``DataLoader`` workers end with it; a process it passed the dataset to by ``multiprocessing`` (a spawned rank,
    given it as an argument) that outlives it finds the folder gone and gives its once-per-dataset warnings itself,
    as where no folder could be made."""
    boot, namespace, _, _ = owner
    removed: list[str] = []
    uid = os.geteuid()
    starts: dict[int, int | None] = {}  # (a pid's start, read once: a process's datasets' folders share it)
    unknown = -1  # (a start /proc cannot tell: left)
    with os.scandir(folder) as entries:
        for entry in entries:
            match = _CLAIMS_NAME.fullmatch(entry.name) if entry.name.startswith(_CLAIMS_PREFIX) else None
            if match is None or match[1] != boot or int(match[2]) != namespace:
                continue
            pid = int(match[3])
            if pid not in starts:
                try:
                    starts[pid] = _process_start(pid)
                except (OSError, ValueError, IndexError):
                    starts[pid] = unknown
            if starts[pid] in (unknown, int(match[4])):  # (its maker alive, or not known)
                continue
            try:  # (read again: the start kept was read before this folder was listed, and a process given the pid
                # since then, which read its own start before making the folder, lives)
                starts[pid] = _process_start(pid)
            except (OSError, ValueError, IndexError):
                starts[pid] = unknown
            if starts[pid] in (unknown, int(match[4])):
                continue
            try:
                info = entry.stat(follow_symlinks=False)
            except OSError:
                continue
            if stat.S_ISDIR(info.st_mode) and info.st_uid == uid:
                shutil.rmtree(entry.path, ignore_errors=True)
                removed.append(entry.name)
    return removed


#: The temporary folders whose stale dataset folders a process has removed (:func:`_remove_stale_claims`), as
#: ``(pid, folder)``: once a process and folder, at its first dataset there (the makers gone then; one that dies
#: later leaves its folder to a later process's first dataset). A forked process (a ``DataLoader`` worker that
#: makes a dataset: a plain pickle, a ``deepcopy``) has another pid, and scans once itself.
_SCANNED: set[tuple[int, str]] = set()


class _Claims:
    """What makes a once-per-dataset warning exactly once across the dataset's processes (its ``DataLoader``
    workers, forked or spawned, and the process that holds it): a private folder (``tempfile.mkdtemp``, made with
    the dataset) in which the first process to act on ``what`` creates the marker ``what`` with
    ``os.open(O_CREAT | O_EXCL)``, which the file system grants to exactly one. The shared-memory flags
    (:func:`_shared_state`, ...) were checked, then set: two processes finishing within the microseconds between
    the two both warned. The flags stay (a cheap first check, and what copies and old pickles read); the marker
    decides.

    The folder is removed when the dataset that made it is collected, or at the exit of its process (not by its
    workers, nor a forked child's exit); a process killed (SIGKILL) leaves it, empty but for a few markers, and the
    first dataset that a later process makes in that temporary folder, on the machine and in the same pid namespace,
    removes it (:func:`_remove_stale_claims`, once a process and folder: :data:`_SCANNED`; its name records its
    maker, once certainly gone; where that cannot be known, it stays). It
    travels as the tensors of shared memory do: by reference to the ``DataLoader`` workers
    (``multiprocessing``'s pickler, :meth:`_shared_reduce`), while a plain ``pickle`` of the dataset (whose tensors
    are then copied by value, an independent dataset) and ``copy.deepcopy`` make a new folder. Where no folder can
    be made (an unwritable temporary folder) or it is gone, a claim is granted, as the flags alone did."""

    def __init__(self, folder: str | None = None) -> None:
        self.folder = folder
        if folder is None:
            owner = _claims_owner()
            name = _CLAIMS_PREFIX if owner is None else _CLAIMS_PREFIX + "-".join(map(str, owner)) + "-"
            try:
                self.folder = tempfile.mkdtemp(prefix=name)
            except OSError:
                return
            # (multiprocessing's finalizer, not weakref.finalize: it also runs at the exit of a process multiprocessing
            # started, which leaves by os._exit, without atexit: the folders of datasets made in a torch.multiprocessing
            # rank were left; and only in the process that made it)
            multiprocessing.util.Finalize(self, shutil.rmtree, (self.folder, True), exitpriority=0)
            temp = os.path.dirname(self.folder)
            if owner is not None and (owner[2], temp) not in _SCANNED:  # (once a process and folder: a scan cost
                _SCANNED.add((owner[2], temp))  # 0.65 ms a dataset, a copy or a worker's pickle, 400 entries in /tmp)
                try:
                    _remove_stale_claims(temp, owner)
                except Exception:  # (a cleanup of others' leftovers: never the dataset's failure)
                    pass

    def claim(self, what: str) -> bool:
        """True in exactly one of the dataset's processes for ``what`` (a file name): the first to ask."""
        if self.folder is None:
            return True
        try:
            os.close(os.open(os.path.join(self.folder, what), os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
        except FileExistsError:
            return False
        except OSError:  # (the folder gone: removed by a cleaner of old temporary files, say)
            return True
        return True

    def __reduce__(self) -> tuple[type[_Claims], tuple[()]]:
        return _Claims, ()  # (a plain pickle: an independent dataset, its own claims)

    def _shared_reduce(self) -> tuple[type[_Claims], tuple[str | None]]:
        return _Claims, (self.folder,)  # (multiprocessing's pickler: the same folder, not removed by the reader)

    def __copy__(self) -> _Claims:
        return self

    def __deepcopy__(self, memo: dict[int, Any]) -> _Claims:
        return _Claims()


ForkingPickler.register(_Claims, _Claims._shared_reduce)


#: The end of :mod:`torchface.io`'s message for a frame to convert, as a dataset says it (the command line's
#: ``--convert`` is ``DatasetConfig(convert=True)`` here).
_DATASET_CONVERT_HINT: str = CONVERT_HINT.replace("pass --convert", "set DatasetConfig(convert=True)")

#: What a dataset's frame file with NaN pixels is told after :data:`~torchface.io.video.NAN_PIXELS_WHY`: a dataset
#: reads its videos from files, so :mod:`torchface.io`'s "track the frames as a tensor" is not its user's remedy.
_DATASET_NAN_PIXELS_HINT: str = (
    NAN_PIXELS_WHY + ": fill them in the file (np.save(path, np.nan_to_num(frames, nan=0.0))), or read the frames "
    "yourself and give them as tensors to training_hooks.NormaliseFaces, which takes NaN pixels as missing"
)


@contextmanager
def _dataset_hint() -> Iterator[None]:
    """Re-raise :mod:`torchface.io`'s refusal of a grayscale, RGBA, 16-bit or odd-sized frame with the dataset's
    setting in place of the command line's ``--convert`` (a ``.npy`` array is told how to save it:
    :func:`torchface.io.video.array_convert_hint`), and its refusal of a frame file's NaN pixels with what a
    dataset's user can do (:data:`_DATASET_NAN_PIXELS_HINT`)."""
    try:
        yield
    except InputError as exc:
        text = str(exc)
        if text.endswith(f"({NAN_PIXELS_HINT})"):
            raise InputError(text[: -len(NAN_PIXELS_HINT) - 1] + _DATASET_NAN_PIXELS_HINT + ")") from None
        if text.endswith(CONVERT_HINT):
            raise InputError(text[: -len(CONVERT_HINT)] + _DATASET_CONVERT_HINT) from None
        if text.endswith(CONVERT_OPTION):  # (a .npy array's: torchface.io.array_convert_hint, how to save it)
            raise InputError(text[: -len(CONVERT_OPTION)] + "set DatasetConfig(convert=True)") from None
        raise


def _by_reference(detector: object) -> object:
    """The part of ``detector`` that pickle saves by reference (its module and qualified name, looked up again in
    the process that reads it): a function itself, a ``functools.partial``'s function, a bound method's object's
    class (or the class of a classmethod), a class itself, else the object's class. Pickling it alone is cheap (a
    name, nothing of the detector's contents) and fails where the detector is a lambda or is defined inside a
    function."""
    if isinstance(detector, functools.partial):
        return _by_reference(detector.func)
    if isinstance(detector, types.MethodType):
        owner = detector.__self__
        return owner if isinstance(owner, type) else type(owner)
    if isinstance(detector, (types.FunctionType, type)):
        return detector
    return type(detector)


def _received_detector(detector: Detector) -> Detector:
    """The detector a pickled :class:`_SentDetector` is read back as."""
    return detector


class _SentDetector:
    """A dataset's detector as its ``__getstate__`` gives it: pickled, it checks first that the detector's
    by-reference part (:func:`_by_reference`) pickles, and raises a ``pickle.PicklingError`` that names the
    detector and what to do where it does not (pickle's own was "Can't pickle <function <lambda> at 0x...>:
    attribute lookup <lambda> on __main__ failed", or "Can't pickle local object 'make.<locals>.find'", from a
    ``DataLoader`` worker started by spawn or forkserver); it is read back as the detector itself. ``copy.copy`` and
    ``copy.deepcopy`` of the dataset do not pickle (a lambda is copied as itself, as before): the dataset's
    ``__setstate__`` unwraps it."""

    def __init__(self, detector: Detector, dataset: str) -> None:
        self.detector, self.dataset = detector, dataset

    def __copy__(self) -> _SentDetector:
        return self

    def __deepcopy__(self, memo: dict[int, Any]) -> _SentDetector:
        return _SentDetector(copy.deepcopy(self.detector, memo), self.dataset)

    def __reduce__(self) -> tuple[Callable[[Detector], Detector], tuple[Detector]]:
        errors = (pickle.PicklingError, AttributeError, TypeError)  # (pickle's errors for a local object)
        try:
            pickle.dumps(_by_reference(self.detector))
        except errors:
            try:  # (a local class whose instances pickle by a __reduce__ of their own still pickle: nothing refused)
                pickle.dumps(self.detector)
            except errors as exc:
                raise pickle.PicklingError(
                    f"{self.dataset}'s detector {_detector_name(self.detector)} cannot be pickled ({exc}), and a "
                    "DataLoader worker started by spawn or forkserver (the default start method on macOS and "
                    "Windows, and on Linux from Python 3.14) receives the dataset pickled: make the detector a "
                    "module-level function or an instance of a module-level class (not a lambda, nor a function or "
                    "class defined inside a function), or start the workers by fork "
                    '(DataLoader(multiprocessing_context="fork"), where the platform has it)'
                ) from exc
        return _received_detector, (self.detector,)


def _detector_name(detector: object) -> str:
    """``detector`` named for a message by its by-reference part (:func:`_by_reference`): ``module.qualname`` of a
    function, else what it is of that (``an instance of module.Class``, ``a functools.partial of module.f``)."""
    ref = _by_reference(detector)
    name = f"{getattr(ref, '__module__', '?')}.{getattr(ref, '__qualname__', type(ref).__qualname__)}"
    if ref is detector:
        return name
    if isinstance(detector, functools.partial):
        return f"(a functools.partial of {_detector_name(detector.func)})"
    if isinstance(detector, types.MethodType):
        return f"(a method of {name})"
    return f"(an instance of {name})"


#: Seconds between the lines of a long count's progress after its first (:attr:`DatasetConfig.progress_after`).
PROGRESS_EVERY_S = 30.0


class _CountProgress:
    """The progress of a count of ``total`` videos' items (:attr:`DatasetConfig.progress_after`), as whole lines on
    stderr (a log file and a terminal alike; a warning given meanwhile stays readable): none until the count has
    taken ``after`` seconds (None: never), then one every :data:`PROGRESS_EVERY_S` seconds and one at its end.
    ``name``: the dataset's class, which begins each line; ``why``: what the count is for, said in the first.

    A line is due as a video's count ends (:meth:`step`) or as a frame of the video being read is (:meth:`frame`:
    decoded through to be counted, searched by the detector, tracked), so that one long video (a detector
    searching it frame by frame, the only video of a count) says how far it has got too: ``, a.avi: 840 frames
    searched for its first face``. A tick costs a clock reading."""

    def __init__(self, name: str, total: int, why: str, after: float | None) -> None:
        self.name, self.total, self.why = name, total, why
        self.videos = f"{total} video{'' if total == 1 else 's'}"
        self.t0 = time.monotonic()
        self.due = after  # seconds into the count of the next line (None: no line)
        self.said = False
        self.done = 0  # videos counted
        self.current: tuple[str, str] | None = None  # (the video being read, what is done with its frames)
        self.read = 0  # its frames read so far

    def _say(self, line: str) -> None:
        if sys.stderr is None:  # (pythonw, a detached process: print(file=None) wrote the line to stdout)
            self.due = None
            return
        try:
            print(f"{self.name}: {line}", file=sys.stderr, flush=True)
        except (OSError, ValueError):  # (a closed or broken stderr: the count goes on without a word)
            self.due = None

    def _now(self) -> str:
        """The video being read and how far, for a line (empty between videos)."""
        if self.current is None:
            return ""
        name, doing = self.current
        return f", {name}: {self.read} frame{'' if self.read == 1 else 's'} {doing}"

    def _line(self, elapsed: float) -> str:
        first = "" if self.said else (
            f" ({self.why}; each video file is decoded through, and with a detector searched for its first face, "
            "once per dataset: DatasetConfig(progress_after=None) says nothing)"
        )  # fmt: skip
        return f"counting the items of {self.videos}: {self.done} counted in {elapsed:.0f} s{self._now()}{first}"

    def _due(self) -> None:
        if self.due is None:
            return
        elapsed = time.monotonic() - self.t0
        if elapsed < self.due:
            return
        self._say(self._line(elapsed))
        self.said = True
        if self.due is not None:
            self.due = elapsed + PROGRESS_EVERY_S

    def video(self, path: Path, doing: str) -> None:
        """Video ``path``'s frames are read next, ``doing`` with them (``"decoded"``, ``"tracked"``, ...)."""
        self.current, self.read = (path.name, doing), 0

    def frame(self, read: int | None = None) -> None:
        """One more frame of the current video read (``read``: the frames read so far): a line if one is due."""
        self.read = self.read + 1 if read is None else read
        self._due()

    def step(self, done: int) -> None:
        """``done`` of the ``total`` videos counted: a line if one is due (none for the last: :meth:`end`'s)."""
        self.done, self.current = done, None
        if done < self.total:
            self._due()

    def end(self) -> None:
        """The count is over: its last line, where it said anything before."""
        if self.said and self.due is not None:
            self._say(f"counted the items of {self.videos} in {time.monotonic() - self.t0:.0f} s")


class _FirstItemProgress(_CountProgress):
    """The wait for a ``DataLoader`` worker's first item (:attr:`DatasetConfig.progress_after`): it searches and
    tracks its first video whole (and with ``shuffle_buffer``, as many as fill the buffer) before it yields
    anything, minutes for a long video. Lines as :class:`_CountProgress`'s (``VideoDataset: the first item: 2
    videos tracked in 35 s, b.avi: 300 frames tracked (...)``), and ``VideoDataset: the first item came in 41 s``
    at the end, where it said anything. A count made first (under DDP) says its own progress."""

    def __init__(self, name: str, after: float | None) -> None:
        super().__init__(name, 0, "", after)

    def _line(self, elapsed: float) -> str:
        first = "" if self.said else (
            " (each video is tracked whole before its items are yielded, with a detector from its first face on: "
            "DatasetConfig(progress_after=None) says nothing)"
        )  # fmt: skip
        tracked = f"{self.done} video{'' if self.done == 1 else 's'} tracked"
        return f"the first item: {tracked} in {elapsed:.0f} s{self._now()}{first}"

    def step(self, done: int) -> None:
        self.done, self.current = done, None

    def end(self) -> None:
        if self.said and self.due is not None:
            self._say(f"the first item came in {time.monotonic() - self.t0:.0f} s")
        self.due = None


def _process_group() -> tuple[int, int] | None:
    """``(rank, world_size)`` in the default ``torch.distributed`` process group; None without one."""
    dist = torch.distributed
    if not (dist.is_available() and dist.is_initialized()):
        return None
    return dist.get_rank(), dist.get_world_size()


@dataclass(frozen=True)
class DatasetConfig:
    """Settings of :class:`VideoDataset` and :class:`FrameFolderDataset`.

    Attributes:
        tracking: tracker and normalised-face settings (:class:`~training_hooks.transforms.FaceTrackingConfig`).
        clip_length: ``None`` yields one item per frame; an int yields clips of that many frames.
        clip_stride: frames between clip starts (default ``clip_length``: back-to-back clips).
        keep_short_clips: also yield the last, shorter clip of a video whose end no full clip reaches (and a
            video shorter than ``clip_length`` as one short clip); otherwise such frames are left out. Needs
            ``clip_length`` (frame items have no short clip: refused without it, as ``clip_stride`` is).
        cache_dir: folder of the tracking cache (:mod:`training_hooks.cache`), a ``str`` or path-like kept as an
            absolute ``Path``: a relative one is taken against the working folder when the config is made
            (``Path.absolute()``: symbolic links are kept as named), so a later ``os.chdir``, or a ``DataLoader``
            worker in another folder, uses the same cache. None tracks every epoch. An empty string is refused
            (``Path("")`` is the working folder: say ``"."`` for it), and so is one starting with a ``~`` or
            ``~user`` that ``os.path.expanduser`` expands (not expanded here: it named a folder ``~`` in the working
            folder; give ``os.path.expanduser(...)``). A dataset refuses one that is a file or inside one when it is
            made.
        convert: convert grayscale, RGBA, 16-bit and odd-sized frames as ``torchface track --convert`` does
            (:func:`torchface.io.open_frames`) instead of raising.
        shuffle_buffer: 0 keeps the order (videos in list order, frames in time order). A positive size
            shuffles: each epoch (:meth:`VideoDataset.set_epoch`) permutes the videos, and each worker draws its
            items at random from a buffer of this many (seeded by ``seed``, the epoch, the worker and the rank,
            so an epoch's order is reproducible for given worker and rank counts; the items never change).
        seed: seed of the shuffling.
        shard_ranks: in a ``torch.distributed`` process group, split the videos between the ranks (video ``i`` ->
            rank ``i % world_size``, module docstring); False makes every rank yield every item.
        rank_balance: :class:`RankBalance`: how the ranks get equal item (and batch) counts when they split the
            videos; :attr:`RankBalance.PAD` (repeat items, the default), ``DROP`` or ``UNEVEN`` (no balancing).
        keep_going: skip a video that cannot be read or tracked (an :class:`~torchface.io.InputError`: a file that
            does not decode, landmarks outside its frame, a detector that finds no face; or an ``OSError``: the file
            gone since the dataset was made) instead of raising, as ``torchface track --keep-going`` does: its items
            are left out, a :class:`SkippedVideoWarning` says so and :attr:`VideoDataset.skipped` records it (module
            docstring, "Skipping"). False (the default): the error stops the epoch. An error writing
            :attr:`cache_dir` (a full disk, a read-only folder) is not the video's: it stops the epoch either way
            (an ``OSError`` naming the folder and what to do).
        progress_after: seconds a count of the videos' items may take before it says how far it has got, on
            stderr (module docstring, "Progress"): :meth:`VideoDataset.count_items`, :meth:`~VideoDataset.
            worker_items`, and under DDP the counts that balance the ranks, which come before the first batch. Each
            video file is decoded through to be counted, and with a detector searched for its first face: over
            hundreds of videos, minutes without a word. A line once the count has taken this long, another every
            :data:`PROGRESS_EVERY_S` seconds (at a video's end or a frame read), and one when it ends; from one
            process only (rank 0's, its ``DataLoader`` worker 0 where the workers count). The wait for a worker's
            first item (its first video searched and tracked whole) says its progress alike. A count or wait that
            takes less says nothing. None: never.
    """

    tracking: FaceTrackingConfig = field(default_factory=FaceTrackingConfig)
    clip_length: int | None = None
    clip_stride: int | None = None
    keep_short_clips: bool = False
    cache_dir: str | os.PathLike[str] | None = None  # stored as a Path (__post_init__)
    convert: bool = False
    shuffle_buffer: int = 0
    seed: int = 0
    shard_ranks: bool = True
    rank_balance: RankBalance = RankBalance.PAD
    keep_going: bool = False
    progress_after: float | None = 5.0

    def __post_init__(self) -> None:
        if not isinstance(self.tracking, FaceTrackingConfig):
            # (the tracker's own settings, one level down, were told the type alone)
            hint = (", which goes inside it: FaceTrackingConfig(tracker=TrackerConfig(...))"
                    if isinstance(self.tracking, TrackerConfig) else "")  # fmt: skip
            raise TypeError(f"tracking must be a FaceTrackingConfig, got {type(self.tracking).__name__}{hint}")
        for name in ("clip_length", "clip_stride"):
            object.__setattr__(self, name, check_optional_int(getattr(self, name), name, 1))
        if self.clip_stride is not None and self.clip_length is None:
            raise ValueError("clip_stride needs clip_length")
        object.__setattr__(self, "shuffle_buffer", check_int(self.shuffle_buffer, "shuffle_buffer", 0))
        object.__setattr__(self, "seed", check_int(self.seed, "seed"))  # (was not checked: 2.5 or None seeded a draw)
        for name in ("keep_short_clips", "convert", "shard_ranks", "keep_going"):  # "no" was true
            object.__setattr__(self, name, check_bool(getattr(self, name), name))
        if self.keep_short_clips and self.clip_length is None:  # (was taken, and did nothing: every frame an item)
            raise ValueError("keep_short_clips needs clip_length")
        # (None: no progress. NaN or inf: never a count's time)
        after = check_number(self.progress_after, "progress_after", "[0, inf)", True, "seconds")
        object.__setattr__(self, "progress_after", after)
        check_choice(self.rank_balance, "rank_balance", RankBalance)
        if self.cache_dir is not None:
            if not isinstance(self.cache_dir, (str, os.PathLike)):  # (was pathlib's "expected str, bytes or ...")
                raise TypeError(f"cache_dir must be a folder (a str or path-like) or None, got "
                                f"{type(self.cache_dir).__name__}")  # fmt: skip
            if isinstance(self.cache_dir, str) and not self.cache_dir:  # (Path("") is ".": the cache went there)
                raise ValueError('cache_dir is empty (the working folder): give a folder, or None for no cache ("." '
                                 "for the working folder)")  # fmt: skip
            check_no_tilde(self.cache_dir, "cache_dir")  # ("~/cache" was a folder "~" in the working folder)
            # (absolute now: a relative one was taken against the working folder when the cache was first used, so a
            # dataset iterated after an os.chdir, or in a worker that had changed folder, filled a cache elsewhere)
            object.__setattr__(self, "cache_dir", Path(self.cache_dir).absolute())


@dataclass
class DatasetStats:
    """What the dataset did in THIS process (each ``DataLoader`` worker counts in its own copy; the items'
    ``cached`` flag is the cross-process record).

    Attributes:
        videos: videos processed.
        frames_tracked: frames tracked (not read from the cache).
        tracking_s: seconds spent reading and tracking frames.
        cache: the cache's counters (hits, misses, corrupt, writes).
    """

    videos: int = 0
    frames_tracked: int = 0
    tracking_s: float = 0.0
    cache: CacheStats = field(default_factory=CacheStats)


def _check_exists(path: Path, given: str | os.PathLike[str]) -> None:
    """Refuse a video or folder that is not there by saying so (a mistyped path was told "VideoDataset takes video
    files or .npy arrays (use FrameFolderDataset for folders)", or the other way round); ``path`` is the absolute
    path of the one ``given``."""
    if not path.exists():
        # (a "~" nothing expanded: torchface's words, torchface.extending.missing_path_hint)
        link = " (a symbolic link to a missing target)" if path.is_symlink() else (missing_path_hint(given)
                                                                                   or _pattern(path))  # fmt: skip
        raise InputError(f"{path}: no such file or folder{link}")


def _pattern(path: Path) -> str:
    """A hint for a missing ``path`` that is a glob pattern (``"clips/*.mp4"``, as a shell or a Hydra config holds
    it: it was told "no such file or folder" alone); "" otherwise."""
    if not any(c in os.fspath(path) for c in "*?["):
        return ""
    n = len(glob.glob(os.fspath(path)))
    return (f" (a pattern? Nothing expands it here: sorted(glob.glob(pattern)) gives the {n} "
            f"path{'' if n == 1 else 's'} it matches)")  # fmt: skip


def _holds_images(folder: Path) -> bool:
    """Whether ``folder`` holds a frame :func:`torchface.io.open_frames` would read (False where it cannot be
    listed)."""
    try:
        return bool(image_files(folder))
    except OSError:
        return False


def _as_numpy(points: Tensor) -> np.ndarray:
    """Landmarks ``points`` as a NumPy array of their values: ``.detach().cpu().numpy()``, bfloat16 as float32
    (which NumPy lacks)."""
    points = points.detach().cpu()
    return (points.to(torch.float32) if points.dtype == torch.bfloat16 else points).numpy()


def _kept_landmarks(
    source: LandmarkSource, video: Path, count: int, index: int = 0
) -> np.ndarray | str | os.PathLike:
    """One video's landmarks as a dataset keeps them, checked as far as they can be without its frames.

    A tensor is kept as a NumPy array (``.detach().cpu().numpy()``, bfloat16 as float32: the values the landmark fit
    takes, and the cache key): a ``DataLoader`` worker started by ``spawn`` or ``forkserver`` received each tensor
    through shared memory, one file descriptor apiece, and a dataset of 3000 videos with a tensor each stopped at
    the first batch with "Too many open files" under the usual limit of 1024 (an array travels by value, as the
    datasets' arrays did); a CUDA tensor is moved to the CPU once, here, not in each worker. An array's or tensor's
    shape, and a file's existence, are checked here (:class:`~torchface.io.InputError` naming the video), not in
    the worker once its video comes up, after the videos before it were tracked: the values (NaN rows, infinite
    values, points outside the frame) are checked there, against the frame, as before.
    """
    where = f"{video}: landmarks"
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        if not path.is_file():  # (read_landmarks' words)
            problem = ("a folder, not a landmarks file" if path.is_dir()
                       else f"no such landmarks file{missing_path_hint(source) or _pattern(path)}")  # fmt: skip
            raise InputError(f"{where}: {path}: {problem}")
        return path.absolute()  # (as the videos: read in the worker, perhaps after an os.chdir)
    if isinstance(source, Tensor):
        source = _as_numpy(source)
    shape = tuple(np.shape(source))
    if len(shape) == 3 and shape[0] == 1:  # (the layouts torchface.io.check_landmarks reads: (1, K, 2), (2K,))
        shape = shape[1:]
    if len(shape) == 1 and shape[0] % 2 == 0:
        shape = (shape[0] // 2, 2)
    if len(shape) != 2 or shape[1] != 2:
        hint = _landmarks_shape_hint(tuple(np.shape(source)), count, f"landmarks[{index}]")
        raise InputError(f"{where}: expected {count} (x, y) points, got an array of shape {np.shape(source)}{hint}")
    if shape[0] != count:
        what = "iBUG landmarks" if count == NUM_LANDMARKS else "landmarks (the face model's)"
        hint = "a missing point stays, as a NaN row"
        if count == NUM_LANDMARKS and shape[0] in MEDIAPIPE_MESH_POINT_COUNTS:  # (was told the NaN row's rule)
            hint = MEDIAPIPE_MESH_HINT
        other = other_landmark_set_hint(shape[0], f"landmarks[{index}][:68]") if count == NUM_LANDMARKS else None
        hint = other or hint  # (WFLW's 98 points were told the NaN row's rule too)
        raise InputError(f"{where}: expected {count} {what}, got {shape[0]} ({hint})")
    return source


#: What a label given as a class name is told (a ``str`` target).
_CLASS_NAMES_HINT: str = (
    "map class names to ints first, e.g. classes = {name: i for i, name in enumerate(sorted(set(names)))} and "
    "targets=[classes[name] for name in names]"
)
#: What a ``bool`` label is told: 0 / 1 as ints or floats, as the loss it feeds takes them.
_BOOL_HINT: str = "give 0 / 1 as ints (a class index, for CrossEntropyLoss) or as floats (for BCEWithLogitsLoss)"


def _target_array(array: np.ndarray, where: str) -> np.ndarray:
    """``array`` (a label, or all of them: ``where`` names it for a message) as int64 (ints) or float64 (floats),
    refusing what is not a real number: bools (:data:`_BOOL_HINT`), strings (:data:`_CLASS_NAMES_HINT`), complex,
    objects, dates; an unsigned value past int64."""
    kind = array.dtype.kind
    if kind == "b":
        raise TypeError(f"{where} holds bools: {_BOOL_HINT}")
    if kind in "US" or kind == "O" and any(isinstance(v, (str, bytes)) for v in array.flat):
        raise TypeError(f"{where} holds strings: {_CLASS_NAMES_HINT}")
    if kind in "iu":
        if kind == "u" and array.size and int(array.max()) > np.iinfo(np.int64).max:
            raise ValueError(f"{where} holds {int(array.max())}, past int64's range (the labels' dtype)")
        return array.astype(np.int64)
    if kind == "f":
        return array.astype(np.float64)
    if kind == "c":
        raise TypeError(f"{where} holds complex numbers (dtype {array.dtype}): give real ones")
    raise TypeError(f"{where} must be ints or floats, got dtype {array.dtype}")


def _one_target(value: object, where: str) -> np.ndarray:
    """One video's label (an entry of a sequence of ``targets``, named by ``where``) as :func:`_target_array`
    gives it."""
    if value is None:
        raise TypeError(f"{where} is None: every video needs a label (leave a video without one out of the dataset)")
    if isinstance(value, (bool, np.bool_)):  # (before int: True is an int)
        raise TypeError(f"{where} is a bool ({value}): {_BOOL_HINT}")
    if isinstance(value, (str, bytes)):
        raise TypeError(f"{where} is a {type(value).__name__} ({value!r}): {_CLASS_NAMES_HINT}")
    if isinstance(value, Tensor):
        return _target_array(_as_numpy(value), where)
    if not isinstance(value, (int, float, np.ndarray, np.generic, list, tuple)):
        raise TypeError(f"{where} must be an int, a float, or an array or tensor of them, got {type(value).__name__}")
    try:
        array = np.asarray(value)
    except ValueError as exc:  # (nested lists of several lengths)
        raise ValueError(f"{where} is not an array of one shape ({exc})") from None
    if array.dtype.kind == "O" and isinstance(value, int):  # (a Python int past 64 bits)
        raise ValueError(f"{where} is {value}, past int64's range (the labels' dtype)")
    return _target_array(array, where)


def _kept_targets(targets: object, videos: tuple[Path, ...]) -> Tensor | None:
    """``targets`` (:class:`VideoDataset`) as the dataset keeps them: one ``(N, ...)`` tensor of its own (a copy: the
    caller's array or tensor, changed later, changes no item), int64 for integer labels and the default float dtype
    (``torch.get_default_dtype()`` when the dataset is made) for floating ones, any float among a sequence's labels
    making them all floats (as ``torch.tensor([1, 0.5])``); None for None. Refused, naming ``targets`` and the
    entry and video at fault: another count than the videos', a single label (0-d), a mapping or a string, entries
    of different shapes, None, bools, strings (class names: map them to ints), complex numbers and other objects
    (``TypeError``), NaN and infinite values (``ValueError``: a label must be finite)."""
    if targets is None:
        return None
    n = len(videos)
    if not isinstance(targets, (Tensor, np.ndarray, str, bytes, Mapping)) and hasattr(targets, "__array__"):
        targets = np.asarray(targets)  # (a pandas column, df["label"], as NumPy reads it)
    if isinstance(targets, (Tensor, np.ndarray)):
        array = _as_numpy(targets) if isinstance(targets, Tensor) else np.asarray(targets)
        if array.ndim == 0:
            raise TypeError(f"targets must hold one label per video ({n}), got a 0-d {type(targets).__name__}: one "
                            f"label for every video is [label] * {n}")  # fmt: skip
        if array.shape[0] != n:
            raise ValueError(f"targets must have one label per video ({n}), got {array.shape[0]} (an array of shape "
                             f"{tuple(array.shape)})")  # fmt: skip
        # (an object array, a pandas column's .values: its entries of any kind, one by one)
        if array.dtype.kind == "O":
            stacked = _stacked_targets(list(array), videos)
        else:
            stacked = _target_array(array, "targets")
    else:
        if isinstance(targets, (str, bytes, Mapping)) or not isinstance(targets, Sequence):
            hint = (": one label per video in the order of the videos, [labels[v] for v in videos]"
                    if isinstance(targets, Mapping) else "")  # fmt: skip
            raise TypeError(f"targets must be a sequence with one label per video, or an array or tensor whose "
                            f"first dimension is the videos', got {type(targets).__name__}{hint}")  # fmt: skip
        if len(targets) != n:
            raise ValueError(f"targets must have one label per video ({n}), got {len(targets)}")
        stacked = _stacked_targets(targets, videos)
    # (torch's own memory, not NumPy's: a DataLoader moves it to shared memory to send it to a spawned worker)
    kept = torch.tensor(stacked, dtype=torch.int64 if stacked.dtype == np.int64 else torch.get_default_dtype())
    if kept.is_floating_point():
        finite = torch.isfinite(kept.flatten(1)).all(1) if kept.dim() > 1 else torch.isfinite(kept)
        if not bool(finite.all()):
            i = int((~finite).nonzero()[0])
            value = stacked[i]
            if np.isfinite(value).all():  # (a float64 past float32's range)
                said = (f"{'is' if value.ndim == 0 else 'holds'} {np.abs(value).max():g}, past the range of "
                        f"{kept.dtype} (the default dtype)")  # fmt: skip
            else:
                said = ("is " if value.ndim == 0 else "holds ") + ("NaN" if np.isnan(value).any() else "inf")
            raise ValueError(
                f"targets[{i}] ({videos[i]}) {said}: a label must be finite (leave a video without a label out of "
                "the dataset, or give it a value your loss ignores: CrossEntropyLoss's ignore_index, -100, for a class)"
            )
    return kept


#: The labels' types :func:`_stacked_targets` stacks at once (no bool: its own type; no unsigned 64-bit, which NumPy
#: turns into floats with signed ints): a list of a million of them in 0.1 s, where one by one took 2.4 s.
_PLAIN_NUMBERS: tuple[type, ...] = (int, float, np.int64, np.int32, np.float64, np.float32)


def _stacked_targets(targets: Sequence[object], videos: tuple[Path, ...]) -> np.ndarray:
    """A sequence of one label per video (:func:`_kept_targets`), each checked (:func:`_one_target`), stacked:
    ``(N, ...)`` int64, or float64 where any is a float."""
    if all(type(t) in _PLAIN_NUMBERS for t in targets):  # (the common case: at once)
        stacked = np.asarray(targets)
        if stacked.dtype.kind in "if":  # (else ints past int64: told entry by entry, below)
            return stacked.astype(np.int64 if stacked.dtype.kind == "i" else np.float64)
    entries = [_one_target(t, f"targets[{i}] ({videos[i]})") for i, t in enumerate(targets)]
    for i, entry in enumerate(entries):
        if entry.shape != entries[0].shape:
            raise ValueError(
                f"targets[{i}] ({videos[i]}) has shape {entry.shape}, targets[0] {entries[0].shape}: every video's "
                "label has one shape (a batch's targets stack to (B, *shape))"
            )
    return np.stack(entries)  # (ints with floats: float64)


def clip_bounds(
    num_frames: int, clip_length: int | None, stride: int | None, keep_short: bool
) -> list[tuple[int, int]]:
    """``(start, stop)`` frame ranges of the items of a ``num_frames``-frame video (:class:`DatasetConfig`).

    Example:
        >>> clip_bounds(10, 4, 3, False)
        [(0, 4), (3, 7), (6, 10)]
        >>> clip_bounds(9, 4, None, True)
        [(0, 4), (4, 8), (8, 9)]
        >>> clip_bounds(3, 4, None, False), clip_bounds(3, None, None, False)
        ([], [(0, 1), (1, 2), (2, 3)])

    Raises:
        TypeError: ``num_frames`` is not an int, or ``clip_length`` / ``stride`` neither an int nor None (numpy
            integers are ints).
        ValueError: ``num_frames`` is negative, or ``clip_length`` / ``stride`` not positive (a length of 0 gave
            empty clips ``(0, 0), (2, 2), ...``, a stride of 0 range()'s message).
    """
    num_frames = check_int(num_frames, "num_frames", 0)
    clip_length = check_optional_int(clip_length, "clip_length", 1)
    stride = check_optional_int(stride, "stride", 1)
    if clip_length is None:
        return [(t, t + 1) for t in range(num_frames)]
    stride = clip_length if stride is None else stride
    bounds = [(s, s + clip_length) for s in range(0, num_frames - clip_length + 1, stride)]
    end = bounds[-1][1] if bounds else 0
    start = bounds[-1][0] + stride if bounds else 0
    if keep_short and end < num_frames and start < num_frames:
        bounds.append((start, num_frames))
    return bounds


class VideoDataset(IterableDataset):
    """Normalised faces and tracked parameters of a list of videos (module docstring).

    Args:
        videos: video files OpenCV decodes (``.avi``, ``.mp4``, ...) or ``.npy`` frame arrays ``(T, H, W, 3)``;
            kept in :attr:`videos` as absolute paths (``Path.absolute()``: a relative one is taken against the working
            folder when the dataset is made, as a landmarks file is, so that a ``DataLoader`` worker, or an epoch
            after an ``os.chdir`` (Lightning, Hydra), reads the same file; the cache keys hash the content, not the
            path, and are unchanged).
        landmarks: the first frame's 68 iBUG landmarks per video (:data:`LandmarkSource`: a ``(68, 2)`` array or
            tensor in pixels, or a ``.csv`` / ``.pts`` / ``.npy`` file; NaN rows for missing points, at least 4
            given), or all of them stacked, one ``(N, 68, 2)`` array or tensor (as
            :meth:`FaceTracker.initialise <torchface.tracker.FaceTracker.initialise>` takes a batch's), or one
            :data:`Detector` asked about each video's frames from the first on until it finds a face, the video
            tracked from that frame (:meth:`sequence`, as ``torchface track --detector`` does; its answer is
            remembered by the dataset, for its ``DataLoader`` workers and later epochs too; all 68 points, as
            ``--detector`` takes them).
        config: :class:`DatasetConfig`.
        targets: one label per video, in the order of ``videos`` (:data:`Targets`): a sequence of ints (class
            indices), floats, or arrays / tensors of one shape, or one ``(N,)`` / ``(N, ...)`` array or tensor (or
            what NumPy reads as one, ``np.asarray``: a pandas column). Each item of video ``i`` then holds
            ``target``, ``targets[i]`` as a tensor: int64 for ints, the default float dtype
            (``torch.get_default_dtype()`` when the dataset is made) for floats (a sequence with any float is all
            floats); one per item, a clip's too (not per frame), as ``video``, so a batch's ``target`` is ``(B,)`` or
            ``(B, ...)`` with the default collate and with :func:`~training_hooks.collate.collate_clips` alike. Kept
            in :attr:`targets` (a copy). It follows its video wherever the video's items go (any ``DataLoader``
            worker or rank, shuffled, repeated by :attr:`RankBalance.PAD`) and is not part of the cache key (the
            cache holds tracking results: one cache serves datasets with and without labels). None (the default):
            items without ``target``.

    Raises:
        TypeError, ValueError: bad arguments (checked here; also a missing or damaged face model file of
            :attr:`FaceTrackingConfig.model <training_hooks.transforms.FaceTrackingConfig.model>`, a landmarks
            array or tensor of another count of points, or a missing landmarks file, an
            :class:`~torchface.io.InputError`); problems with a video's content or its landmarks' values
            (:class:`~torchface.io.InputError`) surface when it is read, in the worker, and reach the caller through
            the ``DataLoader`` (with :attr:`DatasetConfig.keep_going`, the video is skipped instead:
            :attr:`skipped`). ``targets`` of another count than the videos, or of labels of different shapes, or
            holding None, bools, strings (class names: map them to ints first) or NaN / infinite values, are refused
            here, naming ``targets`` and the video.

    Example:
        >>> # data = VideoDataset(["a.avi"], [np.load("a_lm.npy")], DatasetConfig(clip_length=8))
        >>> # item = next(iter(data)); item["face"].shape -> (8, 3, 128, 128)
        >>> # labelled = VideoDataset(["a.avi", "b.avi"], landmarks, config, targets=[3, 0])  # item["target"]: 3 or 0
    """

    def __init__(
        self,
        videos: Sequence[str | os.PathLike[str]],
        landmarks: Sequence[LandmarkSource] | np.ndarray | Tensor | Detector,
        config: DatasetConfig | None = None,
        *,
        targets: Targets | None = None,
    ) -> None:
        super().__init__()
        self.config = DatasetConfig() if config is None else config
        if not isinstance(self.config, DatasetConfig):  # (a FaceTrackingConfig, the inner one, was told no more)
            hint = (", which goes inside it: DatasetConfig(tracking=FaceTrackingConfig(...))"
                    if isinstance(self.config, FaceTrackingConfig) else "")  # fmt: skip
            raise TypeError(f"config must be a DatasetConfig, got {type(self.config).__name__}{hint}")
        if isinstance(videos, (str, os.PathLike)) or not isinstance(videos, Sequence):
            # (one video's path was told no more)
            hint = f": one video's, [{videos!r}]" if isinstance(videos, (str, os.PathLike)) else ""
            raise TypeError(f"videos must be a sequence of paths, got {type(videos).__name__}{hint}")
        # (absolute, as cache_dir is: a relative path was taken against the working folder when the video was read,
        # so a dataset iterated after an os.chdir (Lightning, Hydra), or in a worker that had changed folder, read
        # another file or none; Path.absolute(): symbolic links kept as named)
        self.videos = tuple(Path(v).absolute() for v in videos)
        if not self.videos:
            raise ValueError("videos is empty")
        for given, v in zip(videos, self.videos):
            _check_exists(v, given)
            self._check_source(v)
        cache_dir = None if self.config.cache_dir is None else Path(self.config.cache_dir)
        # (found here, not after the first video has been tracked; a folder inside a file was a NotADirectoryError then)
        for there in () if cache_dir is None else (cache_dir, *cache_dir.parents):
            if there.exists():
                if not there.is_dir():
                    where = "exists" if there == cache_dir else f"is inside {there}, which"
                    raise ValueError(f"{cache_dir}: cache_dir {where} is not a folder")
                break
        self._normalise: NormaliseFaces | None = None
        self._model_content: str | None = None  # (content_hash of the model file as the model was read from it)
        if self.config.tracking.model is not None:
            # (the model file read and checked here, not in each worker at its first video: a missing or damaged
            # file was found only when the first video was tracked; read before the landmarks' checks, which name
            # its K)
            path = self.config.tracking.model
            before = content_hash(path) if Path(path).is_file() else None
            # (InputError for a missing or damaged file; the workers get the model read here)
            num_landmarks = self.model.num_landmarks
            self._model_content = content_hash(path)
            if before != self._model_content:
                raise InputError(f"{os.fspath(path)}: the face model file changed while it was read: make the "
                                 "dataset again")  # fmt: skip
        else:
            num_landmarks = NUM_LANDMARKS
        one = f"({num_landmarks}, 2)"  # (the 68 iBUG points, or the model's K landmarks)
        if isinstance(landmarks, (np.ndarray, Tensor)) and landmarks.ndim == 3:
            # (N, K, 2), the batch FaceTracker.initialise takes: one entry per video (it was "must be a sequence")
            landmarks = list(_as_numpy(landmarks) if isinstance(landmarks, Tensor) else landmarks)  # (moved once)
        if callable(landmarks) and not isinstance(landmarks, (np.ndarray, Tensor)):
            self.detector: Detector | None = landmarks
            self.landmarks: tuple[LandmarkSource, ...] | None = None
        else:
            if isinstance(landmarks, (str, os.PathLike, np.ndarray, Tensor)) or not isinstance(landmarks, Sequence):
                shape = f" of shape {tuple(landmarks.shape)}" if isinstance(landmarks, (np.ndarray, Tensor)) else ""
                # (one video's points or file, not in a list, was told the type and shape alone)
                single = isinstance(landmarks, (str, os.PathLike)) or isinstance(landmarks, (np.ndarray, Tensor)) and (
                    tuple(landmarks.shape) in ((num_landmarks, 2), (2 * num_landmarks,)))  # fmt: skip
                if single:
                    shape += (": one video's, in a list: [landmarks]" if len(self.videos) == 1 else
                              f": one video's? give one entry per video, a list of {len(self.videos)}")  # fmt: skip
                raise TypeError(
                    f"landmarks must be a sequence with one {one} array/tensor or landmarks file per video, an "
                    f"(N, {one[1:]} stack of them, or a detector callable, got {type(landmarks).__name__}{shape}"
                )
            if len(landmarks) != len(self.videos):
                raise ValueError(f"landmarks must have one entry per video ({len(self.videos)}), got {len(landmarks)}")
            for i, source in enumerate(landmarks):  # (a list of points, lm.tolist(), failed in the worker)
                if not isinstance(source, (np.ndarray, Tensor, str, os.PathLike)):
                    # (a detector per video, [detector] * N, read as "got _DlibDetector", with no way out)
                    once = (": a detector is given once for every video, as landmarks itself "
                            "(VideoDataset(videos, detector, config))") if callable(source) else ""  # fmt: skip
                    raise TypeError(
                        f"landmarks[{i}] ({self.videos[i]}) must be a {one} array or tensor, or a landmarks file, "
                        f"got {type(source).__name__}{once}"
                    )
            kept = tuple(_kept_landmarks(s, self.videos[i], num_landmarks, i) for i, s in enumerate(landmarks))
            self.detector, self.landmarks = None, kept
        if self.detector is not None and num_landmarks != NUM_LANDMARKS:
            raise ValueError(
                f"{os.fspath(path)}: the face model {self.model.name!r} has "
                f"{num_landmarks} landmarks, and a detector gives the {NUM_LANDMARKS} iBUG points: give "
                "each video's first-frame landmarks of the model instead of a detector"
            )
        self.targets: Tensor | None = _kept_targets(targets, self.videos)
        self._shared = _shared_state(len(self.videos)).share_memory_()
        self._sender_group: tuple[int, int] | None = None  # (rank, world_size) of the process that pickled it
        self.stats = DatasetStats()
        self._cache: TrackCache | None = None
        self._found_at, self._found = _shared_detections(len(self.videos) if self.detector is not None else 0)
        self._skips = _shared_skips(len(self.videos) if self.config.keep_going else 0)
        short = self.config.clip_length is not None and not self.config.keep_short_clips
        self._frames = _shared_frames(len(self.videos) if short else 0)
        self._iterations = _shared_iterations()  # (the epochs set and the iterations begun: RepeatedEpochWarning)
        self._claims: _Claims | None = _Claims()  # (the once-per-dataset warnings' markers)
        self._progress: _CountProgress | None = None  # (what this process says the progress of now, if anything)

    def _check_source(self, path: Path) -> None:
        if not path.is_file():
            # (a folder of videos was told to use FrameFolderDataset, which then found no images in it; a folder of
            # frames is told to use it, a stray video among them or not)
            videos = "" if _holds_images(path) else folder_of_videos_hint(path, "give the files, one entry per video")
            if videos:
                raise ValueError(f"{path}: VideoDataset takes video files or .npy arrays, not a folder{videos}")
            raise ValueError(
                f"{path}: VideoDataset takes video files or .npy arrays (use FrameFolderDataset for folders of frames)"
            )

    def __repr__(self) -> str:
        """The class, the number of videos (the first two named), where their first faces come from, and the settings
        that shape an epoch: e.g. ``VideoDataset(3 videos (a.avi, b.avi, ...), landmarks, clip_length=8,
        shuffle_buffer=64, epoch=2, face_size=128, keep_expression=False, cache_dir=None)`` (it was the object's
        address)."""
        c, n = self.config, len(self.videos)
        names = ", ".join(v.name for v in self.videos[:2]) + (", ..." if n > 2 else "")
        start = "landmarks" if self.detector is None else (
            f"detector={getattr(self.detector, '__name__', type(self.detector).__name__)}")  # fmt: skip
        cache = None if c.cache_dir is None else os.fspath(c.cache_dir)
        return (f"{type(self).__name__}({n} video{'s' if n != 1 else ''} ({names}), {start}, "
                f"clip_length={c.clip_length}, shuffle_buffer={c.shuffle_buffer}, epoch={self.epoch}, "
                f"face_size={c.tracking.face_size}, keep_expression={c.tracking.keep_expression}, "
                f"cache_dir={cache!r})")  # fmt: skip

    def __getitem__(self, index: int) -> dict[str, Tensor]:
        """Refused with a ``TypeError`` saying what to use (``data[0]`` was torch's "Subclasses of Dataset should
        implement __getitem__", a ``NotImplementedError`` that read as a bug of the dataset): each video is tracked
        from its first frame to its last in the one process that owns it, so there is no item by index.

        There is deliberately no ``__len__`` (``len(data)`` is Python's "has no len()" ``TypeError``): any
        ``__len__`` makes the dataset a ``collections.abc.Sized``, and what checks that before calling ``len()``
        (Lightning's ``str(datamodule)``: "Train dataloader: None") took one that raises for no loader at all.
        Count with :meth:`count_items` and :meth:`worker_items`."""
        raise TypeError(
            f"{type(self).__name__} is an iterable dataset (each video tracked start to end in the worker that owns "
            "it) and has no items by index: iterate it (next(iter(data)) is the first item), or take video i's "
            "tracked sequence, data.sequence(i)[0], and its frame t's item, .item(t)"
        )

    def __setstate__(self, state: dict[str, Any]) -> None:
        if "_shared" not in state:  # pickled before the shared state existed
            state["_shared"] = _shared_state(len(state["videos"]), int(state.pop("epoch", 0)))
        if "_found_at" not in state:  # pickled before the detections were shared (its own were per process)
            state.pop("_detected", None)
            searched = len(state["videos"]) if state.get("detector") is not None else 0
            state["_found_at"], state["_found"] = _shared_detections(searched)
        if "_skips" not in state:  # pickled before keep_going existed
            state["_skips"] = _shared_skips(0)
        if "_frames" not in state:  # pickled before short videos were reported
            state["_frames"] = _shared_frames(0)
        if "_iterations" not in state:  # pickled before repeated orders were told
            state["_iterations"] = _shared_iterations()
        elif not state["_iterations"].is_shared():  # (by value: an independent dataset, deepcopy or plain pickle, not
            state["_iterations"][_BEGUN] = -1  # iterated yet: its first iteration repeats no order of its own)
        state.setdefault("_claims", None)  # (pickled before the claims: the flags alone, as then)
        state.setdefault("targets", None)  # (pickled before the labels: items without a target, as then)
        state["_progress"] = None  # (this process's own)
        for name in _SHARED_STATE:  # (read back from a plain pickle, by value: an independent dataset, whose own
            if not state[name].is_shared():  # DataLoader workers must share its state)
                state[name] = state[name].share_memory_()
        if isinstance(state.get("detector"), _SentDetector):  # (copied, not pickled: copy.copy of the dataset)
            state["detector"] = state["detector"].detector
        self.__dict__.update(state)

    def __deepcopy__(self, memo: dict[int, Any]) -> VideoDataset:
        """An independent dataset (module docstring, "Copies"): its shared state (epoch, counts, detections, skips,
        the warnings given) copied as it is now into new shared memory, which its own ``DataLoader`` workers share
        with it and not with this dataset; new claims (:class:`_Claims`). The default deepcopy gave the copy tensors
        out of shared memory: forked workers then each changed a private copy (a persistent worker missed each
        ``set_epoch``, every worker counted and warned again, ``skipped`` stayed empty)."""
        new = type(self).__new__(type(self))
        memo[id(self)] = new
        new.__setstate__(copy.deepcopy(self.__getstate__(), memo))  # (the copied tensors moved to shared memory)
        return new

    def _claim(self, what: str) -> bool:
        """Whether this process is the one of the dataset's processes to act on ``what`` (a once-per-dataset
        warning: :class:`_Claims`); True where the dataset has no claims (one pickled before them)."""
        claims = getattr(self, "_claims", None)
        return True if claims is None else claims.claim(what)

    @property
    def epoch(self) -> int:
        """The epoch that seeds the shuffling (:meth:`set_epoch`)."""
        return int(self._shared[_EPOCH])

    @epoch.setter
    def epoch(self, epoch: int) -> None:
        self._shared[_EPOCH] = check_int(epoch, "epoch", 0)
        self._iterations[_SETS] += 1  # (the next iteration is a new one, the same epoch too: RepeatedEpochWarning)

    def set_epoch(self, epoch: int) -> None:
        """Set the epoch that seeds the shuffling (call before each epoch's ``DataLoader`` iteration). The
        ``DataLoader`` workers' copies of the dataset share it, so ``persistent_workers=True`` workers shuffle
        each epoch anew too.

        With :attr:`DatasetConfig.shuffle_buffer`, an iteration begun with no ``set_epoch`` since an earlier one
        repeats its order: where the dataset can tell (module docstring, "Epochs"), a
        :class:`RepeatedEpochWarning` says so, once. Calling ``set_epoch`` with the epoch it has
        (``data.set_epoch(data.epoch)``) says the same order is wanted: the next iteration is not told.

        Raises:
            TypeError, ValueError: ``epoch`` is not an int >= 0 (``1.5`` and ``"2"`` were taken as 1 and 2)."""
        self.epoch = epoch

    @property
    def transform(self) -> NormaliseFaces:
        """The :class:`~training_hooks.transforms.NormaliseFaces` this dataset tracks with (built on first use)."""
        if self._normalise is None:
            self._normalise = NormaliseFaces(self.config.tracking)
        return self._normalise

    @property
    def model(self) -> FaceModel:
        """The face model tracked with (CANDIDE-3, or :attr:`FaceTrackingConfig.model
        <training_hooks.transforms.FaceTrackingConfig.model>`'s)."""
        return self.transform.model

    @property
    def num_landmarks(self) -> int:
        """The first-frame landmarks' count: the model's ``K`` (68 for CANDIDE-3, known without loading it)."""
        return NUM_LANDMARKS if self.config.tracking.model is None else self.model.num_landmarks

    @property
    def cache(self) -> TrackCache | None:
        """The tracking cache (None without :attr:`DatasetConfig.cache_dir`)."""
        if self._cache is None and self.config.cache_dir is not None:
            self._cache = TrackCache(self.config.cache_dir)
            self.stats.cache = self._cache.stats
        return self._cache

    def __getstate__(self) -> dict[str, object]:
        # A DataLoader worker started by spawn / forkserver receives the dataset pickled by its rank, and has no
        # torch.distributed group of its own: the rank's (rank, world size) travel with the dataset.
        state = self.__dict__.copy()
        state.pop("_progress", None)  # (this process's own)
        group = _process_group()
        if group is not None:
            state["_sender_group"] = group
        if state.get("detector") is not None:  # (a lambda or local function: an error that says what to do)
            state["detector"] = _SentDetector(state["detector"], type(self).__name__)
        return state

    def rank_and_world_size(self) -> tuple[int, int]:
        """``(rank, world_size)`` the videos are split by in this process: the default ``torch.distributed``
        group's, else the group of the rank that pickled this dataset (a spawned ``DataLoader`` worker), else
        ``(0, 1)``; always ``(0, 1)`` with ``DatasetConfig(shard_ranks=False)``."""
        if not self.config.shard_ranks:
            return 0, 1
        group = _process_group()
        if group is None:
            group = getattr(self, "_sender_group", None)  # (absent from a dataset pickled before it existed)
        return (0, 1) if group is None else group

    def _epoch_order(self) -> list[int]:
        """The video indices in this epoch's order (permuted each epoch with ``shuffle_buffer > 0``)."""
        order = list(range(len(self.videos)))
        if self.config.shuffle_buffer > 0:
            random.Random(f"videos:{self.config.seed}:{self.epoch}").shuffle(order)
        return order

    def worker_videos(self, worker_id: int, num_workers: int, rank: int = 0, world_size: int = 1) -> list[int]:
        """Indices of the videos worker ``worker_id`` of ``num_workers`` on rank ``rank`` of ``world_size``
        handles, in this epoch's order: ``i % world_size == rank`` and ``(i // world_size) % num_workers ==
        worker_id`` (the rank's ``j``-th video goes to worker ``j % num_workers``; module docstring).

        Example:
            >>> # VideoDataset(five_videos, ...).worker_videos(1, 2) -> [1, 3]
            >>> # VideoDataset(five_videos, ...).worker_videos(0, 2, rank=1, world_size=2) -> [1]  (worker 1: [3])
        """
        num_workers, world_size = check_int(num_workers, "num_workers", 1), check_int(world_size, "world_size", 1)
        for name, value, count in (("worker_id", worker_id, num_workers), ("rank", rank, world_size)):
            value = check_int(value, name)  # (True was worker 1)
            if not 0 <= value < count:
                raise ValueError(f"{name} must be in [0, {count}), got {value}")
        return [
            i for i in self._epoch_order() if i % world_size == rank and (i // world_size) % num_workers == worker_id
        ]

    def num_items(self, index: int) -> int:
        """Items of video ``index`` (:func:`clip_bounds` of its tracked frames' count), counted without tracking: an
        image folder's images, a ``.npy`` array's length, a video file's frames as its tracked sequence in the cache
        holds them (:meth:`_cached_frames`: the file is hashed, not decoded) or else decoded through (a container's
        stated count can be approximate); with a detector, the frames from the first one with a face on (found by
        the search :meth:`sequence` makes, once: decoded up to it, the detector asked about each frame, and
        remembered for the tracking). Remembered by the dataset, for its copies in ``DataLoader`` workers too
        (shared memory): each video is counted once, by the first process that needs it.

        With :attr:`DatasetConfig.keep_going`, a video that cannot be counted is skipped (:attr:`skipped`) and counts
        0; a video skipped when tracked keeps its count (module docstring, "Skipping").

        Raises:
            torchface.io.InputError: the video cannot be read, or the detector finds no face in any of its frames
                (the message names the file); not with :attr:`DatasetConfig.keep_going`.
        """
        index = check_int(index, "index")  # (1.0 was torch's message about tensor indices)
        if not 0 <= index < len(self.videos):
            raise IndexError(f"video {index} out of range for {len(self.videos)} videos")
        counts = self._shared[_COUNTS:]
        if int(counts[index]) < 0:
            c = self.config
            try:
                start = self._face_frame(index)  # (before the cache is asked: the key holds the detection)
                frames = self._cached_frames(index)
                if frames is None:
                    with _dataset_hint():
                        frames = _count_frames(self.videos[index], c.convert, self._frame_ticks(index, "decoded"))
                    frames -= start
            except (InputError, OSError) as exc:
                if not c.keep_going:
                    raise
                self._skip(index, exc)
                frames = 0  # (skipped: no item, on every rank alike, the file being the same)
            else:
                self._record_frames(index, frames)
            counts[index] = len(clip_bounds(frames, c.clip_length, c.clip_stride, c.keep_short_clips))
        return int(counts[index])

    def _cached_frames(self, index: int) -> int | None:
        """Frames of video file ``index`` from the cache, without decoding it: the frame count recorded with its
        tracked sequence (:meth:`TrackCache.num_frames <training_hooks.cache.TrackCache.num_frames>`), under the key
        :meth:`sequence` looks it up by. None without a cache or an entry, for an image folder or ``.npy`` array
        (counted at no cost), with landmarks not known before decoding (a detector's, until this dataset has
        searched the video: :meth:`_face_frame`), or when the video or its landmarks cannot be read (decoding then
        reports what is wrong)."""
        path, cache = self.videos[index], self.cache
        if cache is None or not cache.root.is_dir() or path.is_dir() or path.suffix.lower() == ".npy":
            return None  # (no cache yet: nothing to hash the video for; folders and arrays: open_frames' kinds)
        try:
            content = content_hash(path)
            known = self._known_start(index, content)
            source = None if self.landmarks is None else self.landmarks[index]
            if known is None and isinstance(source, (str, os.PathLike)):
                # the frame size only checks the points (sequence() checks them against it): the same float64 array
                known = 0, read_landmarks(source, 1 << 30, 1 << 30, count=self.num_landmarks)
        except (InputError, OSError):
            return None
        if known is None:
            return None
        return cache.num_frames(self._key(content, *known))

    def _key_extra(self) -> str:
        """The dataset's part of its cache keys (:func:`~training_hooks.cache.cache_key`'s ``extra``)."""
        return f"convert={self.config.convert}"

    def _key(self, content: str, start: int, landmarks: np.ndarray) -> str:
        """The cache key of a video of content ``content`` tracked from frame ``start``'s ``landmarks``."""
        # (the model file's content as the model tracked with was read from it: a file saved again since, while
        # this dataset's workers still track with the model read before, keyed that model's sequences as the new one's)
        return cache_key(content, self.config.tracking, landmarks, self._key_extra(), first_frame=start,
                         model_content=self._model_content)  # fmt: skip

    def _count(self, indices: Sequence[int], why: str) -> None:
        """:meth:`num_items` of videos ``indices`` not counted yet (by any process of the dataset), saying on stderr
        how far it has got where that takes long (:attr:`DatasetConfig.progress_after`; ``why``: what the count is
        for), in one process only: rank 0's (the default group's, or the rank's that sent the dataset to a spawned
        worker), its ``DataLoader`` worker 0 where the workers count (each counts its own videos, at about the same
        pace: one speaks for them, as :meth:`_warn_distributed` does)."""
        todo = [i for i in dict.fromkeys(indices) if int(self._shared[_COUNTS + i]) < 0]
        after = self.config.progress_after if self._speaks() else None
        progress = _CountProgress(type(self).__name__, len(todo), why, after)
        outer, self._progress = getattr(self, "_progress", None), (None if after is None else progress)
        try:
            for done, index in enumerate(todo, start=1):
                self.num_items(index)
                progress.step(done)
        finally:
            self._progress = outer
        progress.end()

    def _speaks(self) -> bool:
        """Whether this process says the dataset's progress (:attr:`DatasetConfig.progress_after`): rank 0's (the
        default group's, or the rank's that sent the dataset to a spawned worker), its ``DataLoader`` worker 0 where
        there are workers (each does as much at about the same pace: one speaks for them)."""
        group = _process_group() or getattr(self, "_sender_group", None)
        info = get_worker_info()
        return (group is None or group[0] == 0) and (info is None or info.id == 0)

    def _frame_ticks(self, index: int, doing: str) -> Callable[..., None] | None:
        """The tick to call at each frame of video ``index`` read (``doing`` with it) where this process says
        progress now (a count's, or the first item's: :class:`_CountProgress`); None otherwise (no cost)."""
        progress = getattr(self, "_progress", None)
        if progress is None:
            return None
        progress.video(self.videos[index], doing)
        return progress.frame

    def count_items(self) -> list[int]:
        """:meth:`num_items` of every video, in list order (e.g. to plan the steps of an epoch). Videos shorter than
        :attr:`DatasetConfig.clip_length` count 0 and are named by a :class:`ShortVideoWarning` (once per dataset),
        also where none gives a clip (iterating the dataset then raises a ``ValueError``). A count that takes long
        says how far it has got (:attr:`DatasetConfig.progress_after`)."""
        self._count(range(len(self.videos)), "count_items()")
        counts = [self.num_items(i) for i in range(len(self.videos))]
        self._report_short(*self.rank_and_world_size(), final=False)
        return counts

    def _record_frames(self, index: int, frames: int) -> None:
        """Keep video ``index``'s frame count (or :data:`_SKIPPED_FRAMES`) for :meth:`_report_short`
        (:func:`_shared_frames`; nothing where no video can be too short)."""
        if self._frames.numel():
            self._frames[1 + index] = frames

    def _no_clip_error(self) -> ValueError | None:
        """The error of a clip dataset none of whose videos gives a clip (every video's count known: all too short
        for :attr:`DatasetConfig.clip_length`, or skipped): it yields nothing, every epoch. None otherwise."""
        frames = self._frames[1:] if self._frames.numel() else None
        length = self.config.clip_length
        if frames is None or bool((frames == -1).any()) or bool((frames >= length).any()):  # type: ignore[operator]
            return None
        short = [i for i, n in enumerate(frames.tolist()) if n >= 0]
        if not short:  # (all skipped: SkippedVideoWarning said why, one by one)
            return None
        skipped = len(self.videos) - len(short)
        also = f"; {skipped} more skipped (.skipped says why)" if skipped else ""
        return ValueError(
            f"{type(self).__name__} yields no item: {self._named_short(short)} (DatasetConfig.clip_length={length}, "
            f"keep_short_clips=False){also}. Set DatasetConfig(keep_short_clips=True) to yield each as one shorter "
            "clip (collate_clips pads them), or a clip_length of at most the shortest video's frames"
        )

    def _named_short(self, short: list[int]) -> str:
        """``short`` videos (all shorter than ``clip_length``) with their frame counts, for a message."""
        frames = self._frames[1:]

        def counted(i: int) -> str:
            # (with a detector the frames are those from its first face: "3 frames" of a 10-frame video read wrong)
            start = int(self._found_at[i, 0]) if self._found_at.shape[0] else 0
            late = f" from frame {start}, the detector's first with a face" if start > 0 else ""
            return f"{self.videos[i]} ({int(frames[i])} frames{late})"

        said = ", ".join(counted(i) for i in short[:3])
        more = f" and {len(short) - 3} more" if len(short) > 3 else ""
        n, total = len(short), len(self.videos)
        if n == total == 1:
            whole = "its only video"
        else:
            whole = f"all {n} videos" if n == total else f"{n} of the {total} videos"
        verb = "is shorter than clip_length and gives" if n == 1 else "are shorter than clip_length and give"
        return f"{whole} {verb} no clip: {said}{more}"

    def _report_short(self, rank: int, world: int, final: bool) -> None:
        """Warn once per dataset (:class:`ShortVideoWarning`) of the videos too short for a clip, when every video of
        this rank (``i % world == rank``) has its frame count (:meth:`_record_frames`: counted or tracked by any
        process of the dataset); ``final`` (the end of a ``DataLoader`` worker's pass, or of the only process's):
        where no video of the dataset gives a clip, raise the ``ValueError`` of :meth:`_no_clip_error` instead, each
        epoch (a loop over the dataset takes no step)."""
        if not self._frames.numel():
            return
        frames = self._frames[1:]
        if final:
            if world > 1:
                self._count_others(rank, world)
            error = self._no_clip_error()
            if error is not None:
                raise error
        own = frames[rank::world] if world > 1 else frames
        if int(self._frames[0]) or bool((own == -1).any()):  # (warned already, or not every count known yet)
            return
        length = self.config.clip_length
        short = [i for i, n in enumerate(frames.tolist()) if 0 <= n < length]  # type: ignore[operator]
        if not short or not self._claim("short-videos"):  # (another process finishing meanwhile warns instead)
            return
        self._frames[0] = 1
        warnings.warn(
            f"{type(self).__name__}: {self._named_short(short)} (DatasetConfig.clip_length={length}): left out. "
            "DatasetConfig(keep_short_clips=True) yields each as one shorter clip (collate_clips pads them)",
            ShortVideoWarning,
            stacklevel=3,
        )

    def _count_others(self, rank: int, world: int) -> None:
        """Under DDP a rank knows its own videos' frame counts (``i % world == rank``), and the others' only where it
        counted them (:attr:`DatasetConfig.rank_balance` ``PAD`` / ``DROP``; ``UNEVEN`` counts none): where none of
        its own gives a clip, count the others (:meth:`num_items`, each once: the counts are kept) until one does,
        so that a dataset with no clip at all is :meth:`_no_clip_error` on every rank, as in one process. A video
        that cannot be counted stops the search (its own rank says why)."""
        frames, length = self._frames[1:], self.config.clip_length
        own = frames[rank::world]
        if bool((own == -1).any()) or bool((frames >= length).any()):  # type: ignore[operator]
            return  # (not every own count known yet, or a clip known)
        for i in range(len(self.videos)):
            if int(frames[i]) != -1:
                continue
            try:
                self.num_items(i)
            except (InputError, OSError):
                return
            if int(frames[i]) >= length:  # type: ignore[operator]
                return

    def _balanced_count(self, worker_id: int, num_workers: int, world_size: int) -> int | None:
        """Items every rank's worker ``worker_id`` yields under :attr:`DatasetConfig.rank_balance`; None when the
        ranks are not balanced (one rank, or ``UNEVEN``)."""
        if world_size == 1 or self.config.rank_balance is RankBalance.UNEVEN:
            return None
        slot = [i for r in range(world_size) for i in self.worker_videos(worker_id, num_workers, r, world_size)]
        self._count(slot, f"to give every rank's worker {worker_id} as many items, DatasetConfig.rank_balance")
        per_rank = [
            sum(self.num_items(i) for i in self.worker_videos(worker_id, num_workers, r, world_size))
            for r in range(world_size)
        ]
        return max(per_rank) if self.config.rank_balance is RankBalance.PAD else min(per_rank)

    def worker_items(self, worker_id: int, num_workers: int, rank: int = 0, world_size: int = 1) -> int:
        """Items worker ``worker_id`` of ``num_workers`` on rank ``rank`` of ``world_size`` yields in an epoch: its
        videos' items (:meth:`worker_videos`), or with ``world_size > 1`` the count :attr:`DatasetConfig.rank_balance`
        gives every rank's worker ``worker_id`` (module docstring, "Sharding"). Counted without tracking
        (:meth:`num_items`). A rank's batches per epoch are ``sum(ceil(worker_items(w, ...) / batch_size))`` over its
        workers (a ``DataLoader`` batches each worker's items separately).

        Example:
            >>> # three 6-frame videos, 2 ranks, 2 workers: rank 1's worker 1 has no video, and repeats 6 items (PAD)
            >>> # [data.worker_items(w, 2, r, 2) for r in range(2) for w in range(2)] -> [6, 6, 6, 6]
        """
        own = self.worker_videos(worker_id, num_workers, rank, world_size)
        target = self._balanced_count(worker_id, num_workers, world_size)
        if target is None:
            self._count(own, f"worker_items({worker_id}, ...)")
        return sum(self.num_items(i) for i in own) if target is None else target

    def _detection(self, index: int, content: str) -> tuple[int, np.ndarray] | None:
        """``(frame, (68, 2) landmarks)``: where the detector found the first face of video ``index`` of content
        ``content``, as remembered by this dataset (shared with its workers' copies, kept for later epochs); None
        where it has not searched that content."""
        where = self._found_at[index]
        if int(where[0]) < 0 or not torch.equal(where[1:], _content_words(content)):
            return None
        return int(where[0]), self._found[index].numpy().copy()

    def _search(self, index: int, frames: Iterator[Tensor], content: str) -> tuple[int, Tensor, np.ndarray]:
        """The detector's first face in video ``index``'s ``frames`` (:func:`torchface.detect.search_first_face`, as
        ``torchface track --detector`` looks for it): ``(its frame, the frame, (68, 2) landmarks)``, remembered
        (:meth:`_detection`); the frames after it are left in ``frames``. A detection made earlier is not made
        again: its frame is read, the detector not asked."""
        path = self.videos[index]
        known = self._detection(index, content)
        if known is not None:
            start, points = known
            return start, next(itertools.islice(frames, start, None)), points
        first = next(frames)
        H, W = first.shape[-2:]
        where = f"{path}: landmarks (detector)"

        def find(frame: Tensor) -> np.ndarray | None:
            points = self.detector(detector_image(frame))  # type: ignore[misc]
            if points is None:
                return None
            points = np.asarray(points)
            if points.size == 0:  # (read "expected 68 iBUG landmarks, got 0": a detector's "no face" of its own)
                raise InputError(
                    f"{where}: the detector returned an empty array {points.shape}: a detector returns None where it "
                    "finds no face (torchface.detect.Detector), and the search goes on to the next frame"
                )
            # (half of them inside: dlib's predictor places the chin of a face at the frame's edge outside it)
            return check_landmarks(points, W, H, where, min_inside=0.5)

        tick = self._frame_ticks(index, "searched for its first face")
        start, frame, points = search_first_face(
            itertools.chain([first], frames), find, f"{path}: the detector",
            " (leave it out of the videos, or give every video's first-frame landmarks instead of a detector)",
            searching=tick,  # (called with the frames searched so far: _CountProgress.frame's read)
        )  # fmt: skip
        self._found_at[index, 0] = -1  # (an entry of the video's earlier content, if any: void while rewritten)
        self._found[index] = torch.from_numpy(points)
        self._found_at[index, 1:] = _content_words(content)
        self._found_at[index, 0] = start  # (last: the entry is whole once its frame is set)
        return start, frame, points

    def _face_frame(self, index: int) -> int:
        """The frame video ``index`` is tracked from: 0, or with a detector the first where it finds a face
        (:meth:`_search`, made here where it has not been made)."""
        if self.detector is None:
            return 0
        path = self.videos[index]
        content = content_hash(path)
        known = self._detection(index, content)
        if known is not None:
            return known[0]
        with _dataset_hint():
            with open_frames(path, convert=self.config.convert) as reader:
                return self._search(index, reader, content)[0]

    def _first_landmarks(self, index: int, reader: Iterator[Tensor], content: str) -> tuple[int, Tensor, np.ndarray]:
        """``(start, frame, (68, 2) float64 landmarks)`` of video ``index``: the frame its tracking starts from (0,
        or with a detector the first where it finds a face, :meth:`_search`), read from ``reader`` (the frames after
        it left there), and its landmarks, validated against it."""
        if self.detector is not None:
            return self._search(index, reader, content)
        first = next(reader)
        H, W = first.shape[-2:]
        where = f"{self.videos[index]}: landmarks"
        source = self.landmarks[index]  # type: ignore[index]
        if isinstance(source, (str, os.PathLike)):
            # (missing points, NaN rows, as torchface track takes them)
            return 0, first, read_landmarks(source, W, H, count=self.num_landmarks)
        if isinstance(source, Tensor):
            source = source.detach().cpu().numpy()
        if not isinstance(source, np.ndarray):
            raise InputError(f"{where} must be a ({self.num_landmarks}, 2) array, tensor or file, got "
                             f"{type(source).__name__}")  # fmt: skip
        return 0, first, check_landmarks(source, W, H, where, missing=True, count=self.num_landmarks)

    def _known_start(self, index: int, content: str) -> tuple[int, np.ndarray] | None:
        """``(start, landmarks)`` known without decoding the video: an array or tensor (start 0), or a detection
        made earlier (:meth:`_detection`), checked for shape and values (NaN rows: missing points) but not yet
        against the frame size; None otherwise."""
        if self.detector is not None:
            return self._detection(index, content)
        source = self.landmarks[index]  # type: ignore[index]
        if isinstance(source, (str, os.PathLike)):
            return None
        if isinstance(source, Tensor):
            source = source.detach().cpu().numpy()
        if not isinstance(source, np.ndarray):
            raise InputError(
                f"{self.videos[index]}: landmarks must be a ({self.num_landmarks}, 2) array, tensor or file, got "
                f"{type(source).__name__}"
            )
        where = f"{self.videos[index]}: landmarks"
        return 0, check_landmarks(source, 1 << 30, 1 << 30, where, missing=True, count=self.num_landmarks)

    @property
    def skipped(self) -> dict[int, str]:
        """``{video index: why}`` of the videos skipped so far (:attr:`DatasetConfig.keep_going`), by any process of
        this dataset (its ``DataLoader`` workers too: shared memory), in index order; ``why`` is the error's message
        on one line, naming the file (cut to about 250 bytes). Empty without ``keep_going``. Under DDP, each rank's
        own (the videos it read)."""
        flags = self._skips[:, 0].nonzero().flatten().tolist() if self._skips.numel() else []
        out = {}
        for index in flags:
            text = bytes(self._skips[index, 1:].numpy()).rstrip(b"\0").decode("utf-8", errors="ignore")
            out[index] = f"{self.videos[index]}: {text}"
        return out

    def _is_skipped(self, index: int) -> bool:
        """Whether video ``index`` was skipped (:attr:`skipped`): it is not tried again."""
        return bool(self._skips.numel()) and bool(self._skips[index, 0])

    def _skip(self, index: int, exc: BaseException) -> None:
        """Record (:attr:`skipped`) and warn (:class:`SkippedVideoWarning`) that video ``index`` is skipped for
        ``exc`` (:attr:`DatasetConfig.keep_going`), unless a process of the dataset (a ``DataLoader`` worker, the
        caller counting) has recorded it already: it records before it warns, since a warning can take a while to
        show (a busy stderr), and two processes that failed on one video at the same time both warned. Two that
        failed within the microseconds between finding it unrecorded and recording it both warned too: the first
        to claim it (:class:`_Claims`, a marker file created exclusively) records and warns, the other says
        nothing. (The ranks of a DDP group share nothing: each warns of a video it cannot count, as each counts its
        workers' videos on every rank.)"""
        if self._is_skipped(index):
            return
        if not self._claim(f"skipped-{index}"):  # (another process records and warns: it failed on it meanwhile)
            self._record_frames(index, _SKIPPED_FRAMES)
            return
        path = self.videos[index]
        said = " ".join(str(exc).split()).removeprefix(f"{path}: ")  # (most name the video first: not twice)
        if isinstance(exc, OSError) and not isinstance(exc, InputError):
            said = f"{type(exc).__name__}: {said}"
        data = said.encode("utf-8")[: _SKIP_BYTES - 1]  # (a character cut in two is dropped when read)
        self._skips[index, 1:] = 0
        self._skips[index, 1 : 1 + len(data)] = torch.tensor(list(data), dtype=torch.uint8)
        self._skips[index, 0] = 1  # (last: the record is whole once flagged)
        self._record_frames(index, _SKIPPED_FRAMES)
        warnings.warn(
            f"skipped {path} (video {index}): {said} (DatasetConfig(keep_going=True): its items are left out; "
            f"the dataset's .skipped records it)",
            SkippedVideoWarning,
            stacklevel=2,
        )

    def _tracked(self, index: int) -> tuple[TrackedSequence, bool] | None:
        """:meth:`sequence`, or with :attr:`DatasetConfig.keep_going` None for a video that cannot be read or
        tracked (:meth:`_skip`; not tried again)."""
        if not self.config.keep_going:
            return self.sequence(index)
        if self._is_skipped(index):
            return None
        try:
            sequence, cached, key = self._read_or_track(index)
        except (InputError, OSError) as exc:
            self._skip(index, exc)
            return None
        # (outside the try: the cache's write errors, a full disk or a read-only folder, are not the video's; they
        # skipped every video, tracked or not, for good)
        self._store(index, sequence, key)
        self._record_frames(index, sequence.num_frames)
        return sequence, cached

    def sequence(self, index: int) -> tuple[TrackedSequence, bool]:
        """Video ``index`` tracked (or read from the cache): its sequence and whether it came from the cache.

        With a detector, the video is tracked from the first frame where it finds a face (:meth:`_search`), as
        the video cut to start there would be: the sequence's :attr:`~training_hooks.transforms.TrackedSequence.
        first_frame` is that frame, so that items' ``frame`` numbers the video's frames.

        With landmarks given as arrays or tensors (or a detection this dataset made earlier, in any of its
        processes) a cache hit does not decode the video at all: it hashes the file, reads the cache file and
        checks the landmarks against the stored frame size.

        Raises:
            torchface.io.InputError: the video or its landmarks cannot be used (the message names the file).
        """
        sequence, cached, key = self._read_or_track(index)
        self._store(index, sequence, key)
        self._record_frames(index, sequence.num_frames)
        return sequence, cached

    def _read_or_track(self, index: int) -> tuple[TrackedSequence, bool, str | None]:
        """:meth:`sequence` without storing it: the sequence, whether it came from the cache, and the cache key to
        store a tracked one under (None: nothing to store)."""
        path = self.videos[index]
        content = content_hash(path)
        cache = self.cache
        known = self._known_start(index, content)
        if cache is not None and known is not None:
            stored = cache.load(self._key(content, *known))
            if stored is not None:
                if self.detector is None:  # (a detection was checked against this video's frame when made)
                    H, W = stored.frame_size
                    check_landmarks(known[1], W, H, f"{path}: landmarks", missing=True, count=self.num_landmarks)
                self.stats.videos += 1
                return stored, True, None
        with _dataset_hint():
            reader = open_frames(path, convert=self.config.convert)
        try:
            with _dataset_hint():  # (a later frame's format is found as the search reads it)
                start, first, landmarks = self._first_landmarks(index, reader, content)
            key = None
            if cache is not None:
                key = self._key(content, start, landmarks)
                if known is None:  # not looked up yet
                    stored = cache.load(key)
                    if stored is not None:
                        self.stats.videos += 1
                        return stored, True, None
            t0 = time.perf_counter()
            frames: Iterator[Tensor] = itertools.chain([first], reader)
            tick = self._frame_ticks(index, "tracked")
            if tick is not None:  # (the wait for the first item: :class:`_FirstItemProgress`)
                frames = _ticking(frames, tick)
            with _dataset_hint():  # (a later frame's format is found as it is read)
                sequence, _ = self.transform.track(frames, landmarks)
            self.stats.tracking_s += time.perf_counter() - t0
        finally:
            reader.close()
        if start:  # (the frames' numbers in the video, as the stored sequence keeps them)
            sequence = replace(sequence, first_frame=start)
        progress = getattr(self, "_progress", None)
        if isinstance(progress, _FirstItemProgress):
            progress.step(progress.done + 1)
        self.stats.videos += 1
        self.stats.frames_tracked += sequence.num_frames
        return sequence, False, key

    def _store(self, index: int, sequence: TrackedSequence, key: str | None) -> None:
        """Store video ``index``'s tracked ``sequence`` in the cache under ``key`` (None: nothing to store)."""
        cache = self.cache
        if cache is not None and key is not None:
            cache.store(key, sequence, source=str(self.videos[index]), config=self.config.tracking)

    def _items(
        self, index: int, rng: random.Random | None, tracked: tuple[TrackedSequence, bool] | None = None
    ) -> Iterator[dict[str, Tensor]]:
        if tracked is None:
            tracked = self._tracked(index)
            if tracked is None:  # (skipped: DatasetConfig.keep_going)
                return
        sequence, cached = tracked
        c = self.config
        bounds = clip_bounds(sequence.num_frames, c.clip_length, c.clip_stride, c.keep_short_clips)
        if rng is not None:
            rng.shuffle(bounds)
        video = torch.tensor(index, dtype=torch.int64)
        flag = torch.tensor(cached)
        target = None if self.targets is None else self.targets[index]  # (the video's: a repeated item's too)
        for start, stop in bounds:
            item = sequence.item(start if c.clip_length is None else slice(start, stop))
            item["video"] = video.clone()
            if target is not None:  # (one per item, a clip's too, as video; cloned: not a view of every label)
                item["target"] = target.clone()
            item["cached"] = flag.clone()
            yield item

    def _item_count(self, sequence: TrackedSequence) -> int:
        """Items of a tracked ``sequence`` (:func:`clip_bounds` of its frames)."""
        c = self.config
        return len(clip_bounds(sequence.num_frames, c.clip_length, c.clip_stride, c.keep_short_clips))

    def _balanced_items(
        self, videos: list[int], target: int, slot: list[int], rng: random.Random | None
    ) -> Iterator[dict[str, Tensor]]:
        """Exactly ``target`` items: those of ``videos`` (cut at ``target``), then repeated from the first of them
        with items (or, if none has, of the worker's videos on every rank, ``slot``) up to ``target``.

        No video is read or tracked twice: the sequences to repeat are held from when they were tracked, as many as
        the items to repeat need, counted as the videos are tracked. Where a video skipped later (or one that gave
        fewer items than counted) leaves more to repeat than those hold, the items repeated are those of the last
        video tracked (held until the next is tracked, as it was anyway), then those held again, in turn.

        Raises:
            RuntimeError: fewer than ``target`` items to give, after yielding the rest: other ranks would take more
                steps, and DDP hang at the end of the epoch (:meth:`_short_error`: every video to repeat skipped,
                :attr:`DatasetConfig.keep_going`, or tracking gave fewer items than counted)."""
        count = 0
        short = target - sum(self.num_items(i) for i in videos)  # items to repeat, as known so far
        pool: list[tuple[int, tuple[TrackedSequence, bool] | None]] = []  # (video, sequence) to repeat, in order
        held = 0  # items of the sequences in pool
        last: tuple[int, tuple[TrackedSequence, bool]] | None = None  # the last video tracked with items
        gave: dict[int, int] = {}  # items each tracked video gave (the error's account)
        for index in videos:
            if count == target:
                return
            tracked = self._tracked(index)
            if tracked is None:  # (skipped, DatasetConfig.keep_going: its counted items are repeated ones instead)
                short += self.num_items(index)
                continue
            n = gave[index] = self._item_count(tracked[0])
            short += self.num_items(index) - n  # (a video that gave fewer items than counted: more to repeat)
            if n > 0:
                if held < short:
                    pool.append((index, tracked))
                    held += n
                last = (index, tracked)
            for item in self._items(index, rng, tracked):
                if count == target:
                    return
                yield item
                count += 1
        if count == target:
            return
        if last is not None and held < target - count and all(i != last[0] for i, _ in pool):
            pool.append(last)  # (more to repeat than the sequences held from before hold: skipped videos)
        if not pool:  # no video of its own gave an item: those of its worker on the other ranks, tracked here
            pool = [(i, None) for i in slot if i not in gave and self.num_items(i) > 0 and not self._is_skipped(i)]
        del last
        held = 0
        while count < target:
            before = count
            for j, (index, tracked) in enumerate(pool):
                if tracked is None:  # (another rank's video, not tracked here yet: tracked once, held if needed)
                    tracked = self._tracked(index)
                    if tracked is None:
                        continue
                    gave[index] = self._item_count(tracked[0])
                    if held < target - count:
                        pool[j] = index, tracked
                        held += gave[index]
                for item in self._items(index, rng, tracked):
                    if count == target:
                        return
                    yield item
                    count += 1
            pool = [(i, t) for i, t in pool if t is not None]  # (skipped, or not held: never tracked twice)
            if count == before:  # nothing to repeat
                raise self._short_error(count, target, videos, slot, gave)

    def _short_error(
        self, count: int, target: int, videos: list[int], slot: list[int], gave: dict[int, int]
    ) -> RuntimeError:
        """The error of a worker that yielded ``count`` of its balanced ``target`` items and has nothing left to
        repeat (its ``videos``; ``slot``: its worker's videos on every rank; ``gave``: the items each video it tracked
        gave). A rank cannot tell whether the others fared alike (a file read on one node and not on another, a
        flaky disk): it stops rather than leave DDP waiting. The message says what happened, with counts: which
        videos were skipped (:attr:`DatasetConfig.keep_going`), which gave fewer items when tracked than when
        counted (a file changed since it was counted), which have no item."""
        rank, _ = self.rank_and_world_size()
        info = get_worker_info()

        def named(indices: list[int]) -> str:
            names = [str(self.videos[i]) for i in indices]
            return ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")

        def what(indices: list[int]) -> str:
            """What became of ``indices``' counted items, with counts."""
            skipped = [i for i in indices if self._is_skipped(i)]
            fewer = [i for i in indices if i in gave and gave[i] < self.num_items(i)]
            empty = [i for i in indices if not self._is_skipped(i) and i not in fewer and self.num_items(i) == 0]
            parts = [f"{len(skipped)} skipped ({named(skipped)})"] if skipped else []
            if fewer:
                said = ", ".join(f"{self.videos[i]}: {gave[i]} of {self.num_items(i)}" for i in fewer[:3])
                more = f" and {len(fewer) - 3} more" if len(fewer) > 3 else ""
                parts.append(f"{len(fewer)} gave fewer items when tracked than counted ({said}{more}: a file changed "
                             "or replaced since the dataset counted it?)")  # fmt: skip
            if empty:
                parts.append(f"{len(empty)} with no item ({named(empty)})")
            return ", ".join(parts) or "none gave an item"

        own = set(videos)
        others = [i for i in slot if i not in own]
        counted = sum(self.num_items(i) for i in videos)
        if videos:
            s = "s" if len(videos) != 1 else ""
            facts = [f"its own {len(videos)} video{s} ({counted} items counted): {what(videos)}"]
        else:
            facts = ["it has no video of its own"]
        s = "s" if len(others) != 1 else ""
        facts.append(f"the {len(others)} video{s} of its worker on the other ranks, repeated in their place: "
                     + (what(others) if others else "none"))  # fmt: skip
        why = " (.skipped says why)" if any(self._is_skipped(i) for i in slot) else ""
        return RuntimeError(
            f"{type(self).__name__}: DataLoader worker {0 if info is None else info.id} of rank {rank} yielded {count} "
            f"of the {target} items every rank's worker yields (DatasetConfig.rank_balance "
            f"RankBalance.{self.config.rank_balance.name}) and has nothing left to repeat: " + "; ".join(facts) + why
            + ". Other ranks would take more steps, and DDP would hang. Leave those videos out of the dataset (or fix "
            "what failed), or use RankBalance.UNEVEN with DistributedDataParallel.join()"
        )

    def _warn_distributed(self, rank: int, world: int) -> None:
        """Warn once per dataset (and rank) when the group has more ranks than the dataset has videos."""
        n, mode = len(self.videos), self.config.rank_balance
        if n >= world or (rank < n and mode is not RankBalance.DROP) or int(self._shared[_WARNED]):
            return
        if not self._claim("distributed"):
            return
        self._shared[_WARNED] = 1
        if mode is RankBalance.DROP:
            what = f"with RankBalance.DROP every rank yields no item (rank {rank} has no video)"
        elif mode is RankBalance.PAD:
            what = f"rank {rank} gets none and repeats items of other ranks' videos (tracking them again)"
        else:
            what = (f"rank {rank} gets none and yields no item (DDP training needs every rank to take the same "
                    "number of steps: RankBalance.PAD)")  # fmt: skip
        warnings.warn(
            f"{type(self).__name__} has {n} videos for {world} torch.distributed ranks: {what}",
            DistributedWarning,
            stacklevel=3,
        )

    def _warn_repeated(self, workers: int, rank: int, world: int) -> None:
        """Record the iteration this process's worker 0 (or the process, without workers) begins, and warn once per
        dataset (:class:`RepeatedEpochWarning`) where it is shuffled in the order of the last one begun: the same
        :func:`_iteration_mark` (no ``set_epoch`` since; the same workers, rank and world size)."""
        record = self._iterations
        mark = _iteration_mark(int(record[_SETS]), workers, rank, world)
        repeated = int(record[_BEGUN]) == mark
        record[_BEGUN] = mark
        if not repeated or self.config.shuffle_buffer == 0 or int(record[_TOLD]) or not self._claim("repeated"):
            return
        record[_TOLD] = 1
        warnings.warn(
            f"{type(self).__name__}: an iteration began in the same shuffled order as the last one (epoch "
            f"{self.epoch}, DatasetConfig.shuffle_buffer={self.config.shuffle_buffer}): no set_epoch came between "
            "them, so every epoch of this loop repeats one order. Call data.set_epoch(epoch) before each epoch (or "
            "train with a Lightning trainer and training_hooks.lightning.TrackedFaceDataModule, whose loaders do); to "
            "repeat the order deliberately (a validation set: shuffle_buffer=0 shuffles nothing), call "
            "data.set_epoch(data.epoch) before it. Warned once per dataset",
            RepeatedEpochWarning,
            stacklevel=4,
        )

    def __iter__(self) -> Iterator[dict[str, Tensor]]:
        items = self._epoch_items()
        if self.config.progress_after is not None and self._speaks():
            items = self._then_first(items)
        return items

    def _epoch_items(self) -> Iterator[dict[str, Tensor]]:
        """This process's items of the epoch (:meth:`__iter__`)."""
        rank, world = self.rank_and_world_size()
        info = get_worker_info()
        worker, workers = (0, 1) if info is None else (info.id, info.num_workers)
        if worker == 0:  # (one worker per rank speaks for it; each of a loader's iterations begins in worker 0)
            self._warn_distributed(rank, world)
            self._warn_repeated(workers, rank, world)
        videos = self.worker_videos(worker, workers, rank, world)
        size = self.config.shuffle_buffer
        rng = None
        if size > 0:
            ranks = f":{rank}:{world}" if world > 1 else ""  # (one process: the seeds of before ranks were split)
            rng = random.Random(f"items:{self.config.seed}:{self.epoch}:{worker}:{workers}{ranks}")
        target = self._balanced_count(worker, workers, world)
        if target is None:
            items: Iterator[dict[str, Tensor]] = (item for index in videos for item in self._items(index, rng))
        else:
            slot = [i for i in self._epoch_order() if (i // world) % workers == worker]
            items = self._balanced_items(videos, target, slot, rng)
        items = self._then_report(items, rank, world)
        if rng is None:
            yield from items
            return
        buffer: list[dict[str, Tensor]] = []
        for item in items:
            if len(buffer) < size:
                buffer.append(item)
                continue
            k = rng.randrange(size)
            buffer[k], item = item, buffer[k]
            yield item
        rng.shuffle(buffer)
        yield from buffer

    def _then_first(self, items: Iterator[dict[str, Tensor]]) -> Iterator[dict[str, Tensor]]:
        """``items``, saying the progress of the wait for the first (:class:`_FirstItemProgress`: the videos it
        tracks meanwhile, frame by frame) where it takes more than :attr:`DatasetConfig.progress_after`."""
        progress = _FirstItemProgress(type(self).__name__, self.config.progress_after)
        outer, self._progress = getattr(self, "_progress", None), progress
        try:
            first = next(items, None)
        finally:
            self._progress = outer
        progress.end()
        if first is None:
            return
        yield first
        yield from items

    def _then_report(
        self, items: Iterator[dict[str, Tensor]], rank: int, world: int
    ) -> Iterator[dict[str, Tensor]]:
        """``items``, then (once they are all given: a pass cut short says nothing) :meth:`_report_short`."""
        yield from items
        self._report_short(rank, world, final=True)


def _ticking(frames: Iterator[Tensor], tick: Callable[[], None]) -> Iterator[Tensor]:
    """``frames``, calling ``tick`` after each is taken (the progress of the first item: it is tracked then)."""
    for frame in frames:
        yield frame
        tick()


def _count_frames(path: Path, convert: bool, tick: Callable[[], None] | None = None) -> int:
    """Frames of a video file, image folder or ``.npy`` array, read as :func:`torchface.io.open_frames` reads them
    (and refused as it refuses them) but not converted: a video file is decoded through, by ``read()`` as the
    reader does (``grab()`` alone could count a frame whose ``retrieve()`` fails, where the reader stops), so the
    count equals that of the sequence tracked from it (:meth:`VideoDataset._cached_frames` takes that one)."""
    with open_frames(path, convert=convert) as reader:
        if reader.info.kind != "video":
            return int(reader.info.num_frames or 0)  # (exact for images and arrays)
    cap = open_capture(path)  # (the reader's own opening: turned as displayed, odd names refused alike)
    try:
        count = 0
        while cap.read()[0]:
            count += 1
            if tick is not None:  # (a long count's progress, :class:`_CountProgress`)
                tick()
        return count
    finally:
        cap.release()


class FrameFolderDataset(VideoDataset):
    """:class:`VideoDataset` over folders of frames (``.png``, ``.jpg``, ... read in name order,
    :func:`torchface.io.open_frames`); the cache key hashes the images' bytes in that order.

    Example:
        >>> # data = FrameFolderDataset(["clip_a/", "clip_b/"], [lm_a, lm_b], DatasetConfig(cache_dir="cache"))
    """

    def _check_source(self, path: Path) -> None:
        if not path.is_dir():
            raise ValueError(f"{path}: FrameFolderDataset takes folders of frames (use VideoDataset for video files)")


def loader_throughput(
    dataset: VideoDataset,
    num_workers: int,
    batch_size: int = 32,
    collate_fn: Callable[[list[dict[str, Tensor]]], dict[str, Tensor]] | None = None,
) -> dict[str, float]:
    """One full pass of a ``DataLoader`` over ``dataset``: normalised faces per second and where they came from.

    Args:
        dataset: the dataset (its epoch and cache as they are; the pass is a measurement, not an epoch: neither it
            nor the next iteration is told :class:`RepeatedEpochWarning`).
        num_workers: ``DataLoader`` workers (0 = the calling process).
        batch_size: items per batch.
        collate_fn: e.g. :func:`~training_hooks.collate.collate_clips` for clips; None is PyTorch's default.

    Returns:
        ``{"faces": count, "seconds": wall time, "faces_per_s": ..., "cached_fraction": share of faces read from
        the cache}``; a clip counts its frames (padding excluded).
    """
    loader = DataLoader(dataset, batch_size=batch_size, num_workers=num_workers, collate_fn=collate_fn)
    faces = cached = 0
    ours = isinstance(dataset, VideoDataset)  # (another dataset of such dicts, a ChainDataset: measured as it is)
    if ours:
        dataset.set_epoch(dataset.epoch)  # (the order as it is, on purpose: RepeatedEpochWarning, before and after)
    t0 = time.perf_counter()
    try:
        for batch in loader:
            if "frame_mask" in batch:
                per_item = batch["frame_mask"].sum(-1)
            elif batch["face"].dim() == 5:
                per_item = torch.full((batch["face"].shape[0],), batch["face"].shape[1])
            else:
                per_item = torch.ones(batch["face"].shape[0], dtype=torch.int64)
            faces += int(per_item.sum())
            cached += int((per_item * batch["cached"].reshape(-1)).sum())
    finally:
        if ours:
            dataset.set_epoch(dataset.epoch)
    seconds = time.perf_counter() - t0
    return {
        "faces": float(faces),
        "seconds": seconds,
        "faces_per_s": faces / seconds if seconds > 0 else 0.0,
        "cached_fraction": cached / faces if faces else 0.0,
    }
