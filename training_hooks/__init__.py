"""Dataloader and training-loop integration for torchface (normalised faces inside PyTorch pipelines).

- :mod:`~training_hooks.datasets`: :class:`VideoDataset` / :class:`FrameFolderDataset`, tracked inside the
  ``DataLoader`` workers, per frame or per clip, with a disk cache (:mod:`~training_hooks.cache`);
- :mod:`~training_hooks.transforms`: :class:`NormaliseFaces` (frames + landmarks or a tracker state ->
  normalised faces) and the tracking core :func:`track_sequence`;
- :mod:`~training_hooks.collate`: :func:`collate_clips` (clips of different lengths: padding plus mask);
- :mod:`~training_hooks.layer`: :class:`NormalisedFaceLayer`, the normalised face as a differentiable layer
  (detached tracking, or unrolled solver iterations so gradients reach the frames through the tracking);
- :mod:`~training_hooks.hooks`: confidence-weighted loss, dropping low-confidence samples, tracking-quality
  logging;
- :mod:`training_hooks.lightning`: a PyTorch Lightning callback and data module (imported only on request; it
  needs the optional ``lightning`` package).
"""

from training_hooks.cache import CacheWarning, TrackCache, cache_key, content_hash
from training_hooks.collate import collate_clips
from training_hooks.datasets import (
    DatasetConfig,
    DistributedWarning,
    FrameFolderDataset,
    RankBalance,
    RepeatedEpochWarning,
    ShortVideoWarning,
    SkippedVideoWarning,
    VideoDataset,
    clip_bounds,
    loader_throughput,
)
from training_hooks.hooks import (
    FilteredBatch,
    TrackingQualityLogger,
    confidence_weighted_loss,
    drop_low_confidence,
    sample_confidence,
    tracking_quality,
)
from training_hooks.layer import LayerConfig, LayerMode, LayerResult, NormalisedFaceLayer, UnrollStart, unrolled_params
from training_hooks.transforms import FaceStorage, FaceTrackingConfig, NormaliseFaces, TrackedSequence, track_sequence

__all__ = [
    "CacheWarning",
    "DatasetConfig",
    "DistributedWarning",
    "FaceStorage",
    "FaceTrackingConfig",
    "FilteredBatch",
    "FrameFolderDataset",
    "LayerConfig",
    "LayerMode",
    "LayerResult",
    "NormaliseFaces",
    "NormalisedFaceLayer",
    "RankBalance",
    "RepeatedEpochWarning",
    "ShortVideoWarning",
    "SkippedVideoWarning",
    "TrackCache",
    "TrackedSequence",
    "TrackingQualityLogger",
    "UnrollStart",
    "VideoDataset",
    "cache_key",
    "clip_bounds",
    "collate_clips",
    "confidence_weighted_loss",
    "content_hash",
    "drop_low_confidence",
    "loader_throughput",
    "sample_confidence",
    "track_sequence",
    "tracking_quality",
    "unrolled_params",
]
