"""Framework-agnostic helpers for training loops fed by the tracked datasets.

Batches are dicts of batch-first tensors as the datasets and collates make them: frame batches (PyTorch's
``default_collate`` of frame items: ``confidence`` ``(B,)``) or clip batches
(:func:`~training_hooks.collate.collate_clips`: ``confidence`` ``(B, T)`` plus ``frame_mask`` ``(B, T)``).

- :func:`confidence_weighted_loss`: ``sum_i c_i m_i l_i / sum_i c_i m_i``, the tracker's confidence as a weight;
- :func:`drop_low_confidence`: keep the samples whose (clip-mean) confidence reaches a threshold;
- :func:`tracking_quality` and :class:`TrackingQualityLogger`: confidence, success and pose statistics of a
  batch and of an epoch, as plain floats for any logger (:mod:`training_hooks.lightning` for Lightning).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import torch
from torch import Tensor

__all__ = [
    "FilteredBatch",
    "TrackingQualityLogger",
    "confidence_weighted_loss",
    "drop_low_confidence",
    "sample_confidence",
    "tracking_quality",
]


def _check_batch(batch: object) -> Mapping[str, Any]:
    if not isinstance(batch, Mapping):
        raise TypeError(f"batch must be a dict of tensors (a dataset batch), got {type(batch).__name__}")
    if "confidence" not in batch:
        raise ValueError(f"batch must hold a 'confidence' tensor, got keys {sorted(batch)}")
    if not isinstance(batch["confidence"], Tensor):  # (was "must hold a 'confidence' tensor, got keys ['confidence']")
        raise TypeError(f"batch['confidence'] must be a (B,) or (B, T) tensor, got {type(batch['confidence']).__name__}")
    conf = batch["confidence"]
    if conf.dim() not in (1, 2):
        raise ValueError(f"batch['confidence'] must be (B,) or (B, T), got {tuple(conf.shape)}")
    for key in ("frame_mask", "success"):  # a (1,) success was broadcast over every sample, a list an AttributeError
        if key not in batch:
            continue
        if not isinstance(batch[key], Tensor):
            raise TypeError(f"batch['{key}'] must be a tensor like confidence {tuple(conf.shape)}, "
                            f"got {type(batch[key]).__name__}")  # fmt: skip
        if tuple(batch[key].shape) != tuple(conf.shape):
            raise ValueError(f"{key} {tuple(batch[key].shape)} must match confidence {tuple(conf.shape)}")
    real = conf.detach() if "frame_mask" not in batch else conf.detach()[batch["frame_mask"].to(torch.bool)]
    if real.is_floating_point() and not bool(torch.isfinite(real).all()):  # the minimum was inf, the mean NaN
        raise ValueError("batch['confidence'] must be finite on the real frames")
    return batch


def _check_per_frame(batch: Mapping[str, Any], key: str, trailing: tuple[int | None, ...] | None) -> None:
    """Check that ``batch[key]`` is a tensor whose leading dimensions are the confidence's shape (``(B,)`` or
    ``(B, T)``), followed by the sizes ``trailing`` (None: any size; ``trailing`` None: any dimensions)."""
    value, lead = batch[key], tuple(batch["confidence"].shape)
    names = ["B", "T"][: len(lead)] + (["..."] if trailing is None else [str(n or "*") for n in trailing])
    want = "(" + ", ".join(names) + ")"
    if not isinstance(value, Tensor):
        raise TypeError(f"batch['{key}'] must be a {want} tensor, got {type(value).__name__}")
    rest = tuple(value.shape[len(lead) :])
    if tuple(value.shape[: len(lead)]) != lead or (
        trailing is not None
        and (len(rest) != len(trailing) or any(n is not None and n != r for n, r in zip(trailing, rest)))
    ):
        raise ValueError(f"batch['{key}'] must be {want} like confidence {lead}, got {tuple(value.shape)}")


def _valid(batch: Mapping[str, Any]) -> Tensor:
    """``(B,)`` or ``(B, T)`` bool: the real (not padded) frames."""
    conf = batch["confidence"]
    mask = batch.get("frame_mask")
    return torch.ones_like(conf, dtype=torch.bool) if mask is None else mask.to(torch.bool)


def _loss_shape_hint(loss: tuple[int, ...], confidence: tuple[int, ...]) -> str:
    """How to make a ``loss`` of another shape than the ``confidence`` one :func:`confidence_weighted_loss` takes
    ("" when nothing fits): a loss already reduced (a loss function's default ``reduction="mean"``), one per clip of
    a clip batch, or a ``(B, 1)`` head's (they were told the shapes alone)."""
    if loss == ():
        return " (a scalar: compute the loss with reduction=\"none\", one per sample or frame)"
    if len(confidence) == 2 and loss == confidence[:1]:
        return (" (one loss per clip, the confidence per frame: weigh it by each clip's, sample_confidence(batch), "
                "or compute a loss per frame)")
    if loss == (*confidence, 1):
        return " (a trailing 1: loss.squeeze(-1))"
    return ""


def confidence_weighted_loss(loss: Tensor, confidence: Tensor, mask: Tensor | None = None) -> Tensor:
    """Mean of a per-sample loss weighted by the tracker's confidence: ``sum c m l / sum c m``.

    The weights are detached (the confidence is data, not a parameter). An entry of weight zero (confidence 0,
    or ``mask`` False, e.g. a padded frame) contributes exactly 0 to the value and to the gradient w.r.t. ``loss``,
    even where its loss is NaN or inf; when every weight is zero the result is zero, still connected to the graph,
    never NaN. What no loss function can undo is a NaN made before it: the backward of whatever computed a NaN loss
    multiplies that 0 by NaN, and the network's gradients come out NaN (a padded or failed frame's face is black:
    divided by its own standard deviation it is 0 / 0). A ``RuntimeWarning`` says so where ``loss`` has a graph and
    is NaN or inf at an entry of weight zero: compute the loss of the real frames alone, or keep those inputs
    finite.
    Under DDP each rank weighs its own batch, and DDP averages the ranks' gradients: the step follows the mean of
    the ranks' weighted means, not one weighted mean over every rank's samples.

    Args:
        loss: ``(B,)`` or ``(B, T)`` per-sample (per-frame) losses.
        confidence: the same shape, in ``[0, 1]``.
        mask: the same shape, bool (e.g. ``frame_mask`` of a clip batch); None counts every entry.

    Returns:
        A scalar tensor.

    Raises:
        TypeError: ``loss`` is not a floating-point tensor, or an argument is not a tensor.
        ValueError: shapes differ, or the confidence is non-finite or outside ``[0, 1]``.

    Example:
        >>> confidence_weighted_loss(torch.tensor([1.0, 3.0]), torch.tensor([0.75, 0.25]))
        tensor(1.5000)
    """
    if not isinstance(loss, Tensor) or not isinstance(confidence, Tensor):
        raise TypeError("loss and confidence must be tensors")
    if not loss.is_floating_point():  # the confidence was cast to it: an int64 loss weighed 0 everywhere, gave 0
        raise TypeError(f"loss must be a floating-point tensor, got {loss.dtype}")
    if mask is not None and not isinstance(mask, Tensor):
        raise TypeError(f"mask must be a bool tensor or None, got {type(mask).__name__}")
    if loss.shape != confidence.shape or (mask is not None and mask.shape != loss.shape):
        got = tuple(mask.shape) if mask is not None else None
        raise ValueError(
            f"loss, confidence and mask must have one shape, got {tuple(loss.shape)}, {tuple(confidence.shape)}, {got}"
            f"{_loss_shape_hint(tuple(loss.shape), tuple(confidence.shape))}"
        )
    # (on the loss's device: a batch's confidence stays on the CPU where a training loop moves its images alone)
    c = confidence.detach().to(device=loss.device, dtype=loss.dtype)
    if not bool(torch.isfinite(c).all()) or bool((c < 0).any()) or bool((c > 1).any()):
        raise ValueError("confidence must be finite and in [0, 1]")
    if mask is not None:
        c = c * mask.to(device=c.device, dtype=c.dtype)
    # torch.where, not the product alone: 0 * NaN (a padded frame's 0 / 0 loss) would be NaN.
    weighted = torch.where(c > 0, loss * c, 0.0).sum()
    total = c.sum()
    if loss.grad_fn is None:
        positive = not float(total) <= 0.0  # (a NaN total, of a float mask with NaN, divides, as before)
    else:  # (the parameters' gradients came out NaN without a word; one read of the device for both, as without)
        read = torch.stack([(~(total <= 0)).to(torch.int64), ((c <= 0) & ~torch.isfinite(loss.detach())).sum()])
        flag, bad = read.tolist()
        positive = flag > 0
        if bad:
            warnings.warn(
                f"confidence_weighted_loss: the loss is NaN or inf at {bad} of its {loss.numel()} entries of weight 0 "
                "(padded, failed or zero-confidence frames): they add 0 to the value, but the backward of what made "
                "them NaN gives NaN gradients upstream (0 * NaN). Compute the loss of the real frames alone (e.g. of "
                "batch['face'][batch['frame_mask']]), or keep those inputs finite (a black padded face over its own "
                "standard deviation is 0 / 0). NaN put there on purpose (torch.where, masked_fill) has finite "
                "gradients: filter this warning then",
                RuntimeWarning,
                stacklevel=2,
            )
    if not positive:
        return weighted  # 0, in the graph
    return weighted / total


def sample_confidence(batch: Mapping[str, Any], require_success: bool = True) -> Tensor:
    """``(B,)`` one confidence per sample: the frame's, or a clip's mean over its real frames.

    With ``require_success`` a frame whose tracking FAILED (``success`` False) counts as confidence 0.

    Example:
        >>> sample_confidence({"confidence": torch.tensor([[0.8, 0.4], [0.9, 0.0]]),
        ...                    "frame_mask": torch.tensor([[True, True], [True, False]])})
        tensor([0.6000, 0.9000])
    """
    batch = _check_batch(batch)
    conf = batch["confidence"].detach().to(torch.float32)
    if require_success and "success" in batch:
        conf = conf * batch["success"].to(conf.dtype)
    if conf.dim() == 1:
        return conf
    valid = _valid(batch).to(conf.dtype)
    return (conf * valid).sum(1) / valid.sum(1).clamp_min(1.0)


class FilteredBatch(NamedTuple):
    """What :func:`drop_low_confidence` returns (unpacks as ``batch, indices``).

    Attributes:
        batch: the kept samples (every batch-first value indexed).
        indices: ``(B',)`` int64 positions of the kept samples in the input batch.
    """

    batch: dict[str, Any]
    indices: Tensor


def drop_low_confidence(
    batch: Mapping[str, Any], threshold: float, require_success: bool = True
) -> FilteredBatch:
    """Keep the samples whose confidence (:func:`sample_confidence`) is at least ``threshold``.

    Every tensor value whose first dimension is the batch size ``B`` is indexed, and the values PyTorch's
    ``default_collate`` batches per sample are filtered as it built them: a nested dict key by key, a list or
    tuple of tensors that all have ``B`` rows (a tuple of tensors in each item) tensor by tensor, any other list
    or tuple of ``B`` entries (strings, say) entry by entry; other values are kept as they are. The result may
    be empty (``B' = 0``): check ``len(indices)`` before using it.

    Args:
        batch: a frame or clip batch (module docstring).
        threshold: in ``[0, 1]``.
        require_success: failed frames count as confidence 0, and a failed frame (a clip without a successful
            frame) is dropped even at threshold 0.

    Example:
        >>> batch = {"confidence": torch.tensor([0.9, 0.2, 0.6]), "face": torch.zeros(3, 3, 4, 4)}
        >>> out = drop_low_confidence(batch, 0.5)
        >>> out.indices.tolist(), out.batch["face"].shape[0]
        ([0, 2], 2)
    """
    batch = _check_batch(batch)
    if not 0.0 <= float(threshold) <= 1.0:
        raise ValueError(f"threshold must be in [0, 1], got {threshold}")
    score = sample_confidence(batch, require_success)
    keep = score >= float(threshold)
    if require_success and "success" in batch:
        success = batch["success"].to(torch.bool)  # a clip needs at least one successful real frame
        keep &= success if success.dim() == 1 else (success & _valid(batch)).any(1)
    indices = keep.nonzero().squeeze(-1)
    B = score.shape[0]
    out = {key: _select(value, indices, B) for key, value in batch.items()}
    return FilteredBatch(out, indices)


def _batched(value: object, B: int) -> bool:
    return isinstance(value, Tensor) and value.dim() >= 1 and value.shape[0] == B


def _rebuild(value: list | tuple, entries: list[Any]) -> list | tuple:
    """A list or tuple of ``value``'s type (a named tuple too) holding ``entries``."""
    return type(value)(*entries) if hasattr(value, "_fields") else type(value)(entries)


def _select(value: Any, indices: Tensor, B: int) -> Any:
    """The rows ``indices`` of a batch value (:func:`drop_low_confidence`)."""
    if _batched(value, B):
        return value[indices.to(value.device)]
    if isinstance(value, Mapping):  # a dict in each item: default_collate batched it key by key
        return {k: _select(v, indices, B) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        if value and all(_batched(v, B) for v in value):  # a tuple of tensors in each item, batched element-wise
            return _rebuild(value, [v[indices.to(v.device)] for v in value])
        if len(value) == B:  # one entry per sample (strings, file names)
            return _rebuild(value, [value[int(i)] for i in indices])
    return value


#: The pose and animation statistics of :class:`_Accumulator` (``moments`` keys), in a fixed order.
_MOMENTS = ("yaw_deg", "pitch_deg", "roll_deg", "depth_mm", "anim_abs")


@dataclass
class _Accumulator:
    """Running sums over the real frames of batches (:func:`tracking_quality`, :class:`TrackingQualityLogger`)."""

    frames: int = 0
    samples: int = 0
    conf_sum: float = 0.0
    conf_min: float = math.inf
    success: float = 0.0
    cached: float = 0.0
    cached_count: int = 0
    coverage: float = 0.0
    coverage_count: int = 0
    moments: dict[str, list[float]] = field(default_factory=dict)  # name -> [n, sum, sum of squares]

    def _moment(self, name: str, values: Tensor) -> None:
        m = self.moments.setdefault(name, [0.0, 0.0, 0.0])
        v = values.to(torch.float64)
        m[0] += v.numel()
        m[1] += float(v.sum())
        m[2] += float((v * v).sum())

    def add(self, batch: Mapping[str, Any]) -> "_Accumulator":
        batch = _check_batch(batch)
        for key, trailing in (("ypr_deg", (3,)), ("translation", (3,)), ("anim_coeffs", (None,)), ("mask", None)):
            if key in batch:  # (a wrong shape was an IndexError from the indexing below)
                _check_per_frame(batch, key, trailing)
        if "cached" in batch and (
            not isinstance(batch["cached"], Tensor) or batch["cached"].numel() != batch["confidence"].shape[0]
        ):  # one flag per sample (a single flag was counted for every frame)
            got = tuple(batch["cached"].shape) if isinstance(batch["cached"], Tensor) else type(batch["cached"]).__name__
            raise ValueError(f"batch['cached'] must be one flag per sample ({batch['confidence'].shape[0]},), got {got}")
        valid = _valid(batch)
        conf = batch["confidence"].detach()[valid].to(torch.float64)
        self.samples += int(batch["confidence"].shape[0])
        self.frames += int(conf.numel())
        if conf.numel() == 0:
            return self
        self.conf_sum += float(conf.sum())
        self.conf_min = min(self.conf_min, float(conf.min()))
        if "success" in batch:
            self.success += float(batch["success"][valid].to(torch.float64).sum())
        else:
            self.success += float(conf.numel())
        if "cached" in batch:  # per sample; a clip's frames share its flag
            flag = batch["cached"].to(torch.float64).reshape(-1)
            per = valid.reshape(valid.shape[0], -1).sum(1).to(torch.float64)
            self.cached += float((flag * per).sum())
            self.cached_count += int(per.sum())
        if "mask" in batch:
            # Each frame's mean first, then the real frames' (the mask indexed by the frames and cast to float64 was
            # two copies of it: 160 ms for a batch of 32 clips of 16 frames of 128-pixel faces, now 3 ms)
            mask = batch["mask"].detach()
            per = mask.reshape(*valid.shape, -1)  # (B, S * S) or (B, T, S * S)
            wide = torch.float64 if per.dtype == torch.float64 else torch.float32  # (a bfloat16 mean: 3 digits)
            cover = per.mean(-1, dtype=wide)[valid]
            self.coverage += float(cover.to(torch.float64).sum())
            self.coverage_count += int(cover.numel())
        if "ypr_deg" in batch:
            ypr = batch["ypr_deg"].detach()[valid]
            for k, name in enumerate(("yaw_deg", "pitch_deg", "roll_deg")):
                self._moment(name, ypr[:, k])
        if "translation" in batch:
            self._moment("depth_mm", batch["translation"].detach()[valid][:, 2])
        if "anim_coeffs" in batch:
            self._moment("anim_abs", batch["anim_coeffs"].detach()[valid].abs().mean(-1))
        return self

    def merge(self, other: "_Accumulator") -> "_Accumulator":
        """Add ``other``'s sums to these (in place; returns self): the same sums as adding its batches here."""
        self.frames += other.frames
        self.samples += other.samples
        self.conf_sum += other.conf_sum
        self.conf_min = min(self.conf_min, other.conf_min)
        self.success += other.success
        self.cached += other.cached
        self.cached_count += other.cached_count
        self.coverage += other.coverage
        self.coverage_count += other.coverage_count
        for name, (n, total, squares) in other.moments.items():
            m = self.moments.setdefault(name, [0.0, 0.0, 0.0])
            m[0] += n
            m[1] += total
            m[2] += squares
        return self

    def all_reduce(self) -> "_Accumulator":
        """The sums over every rank of the default ``torch.distributed`` process group (a collective: every rank
        calls it); this accumulator itself without a group."""
        dist = torch.distributed
        if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
            return self
        device = torch.device("cuda", torch.cuda.current_device()) if dist.get_backend() == "nccl" else None
        counts = [self.frames, self.samples, self.conf_sum, self.success, self.cached, self.cached_count,
                  self.coverage, self.coverage_count]  # fmt: skip
        for name in _MOMENTS:  # (a rank without frames has no moments: every rank packs every name)
            counts.extend(self.moments.get(name, [0.0, 0.0, 0.0]))
        sums = torch.tensor(counts, dtype=torch.float64, device=device)
        low = torch.tensor([self.conf_min], dtype=torch.float64, device=device)
        dist.all_reduce(sums)
        dist.all_reduce(low, op=dist.ReduceOp.MIN)
        v = sums.cpu().tolist()
        out = _Accumulator(frames=int(v[0]), samples=int(v[1]), conf_sum=v[2], conf_min=float(low), success=v[3],
                           cached=v[4], cached_count=int(v[5]), coverage=v[6], coverage_count=int(v[7]))
        for k, name in enumerate(_MOMENTS):
            m = v[8 + 3 * k : 11 + 3 * k]
            if m[0] > 0:
                out.moments[name] = m
        return out

    def summary(self) -> dict[str, float]:
        if self.frames == 0:
            return {"frames": 0.0, "samples": float(self.samples)}
        out = {
            "frames": float(self.frames),
            "samples": float(self.samples),
            "confidence_mean": self.conf_sum / self.frames,
            "confidence_min": self.conf_min,
            "success_fraction": self.success / self.frames,
        }
        if self.cached_count:
            out["cached_fraction"] = self.cached / self.cached_count
        if self.coverage_count:
            out["face_coverage"] = self.coverage / self.coverage_count
        for name, (n, s, ss) in self.moments.items():
            mean = s / n
            out[f"{name}_mean"] = mean
            out[f"{name}_std"] = math.sqrt(max(ss / n - mean * mean, 0.0))
        return out


def tracking_quality(batch: Mapping[str, Any]) -> dict[str, float]:
    """Tracking-quality statistics of one batch over its real frames, as floats.

    Keys: ``frames``, ``samples``, ``confidence_mean``, ``confidence_min``, ``success_fraction``; when the batch
    has them, ``cached_fraction`` (frames read from the cache), ``face_coverage`` (mean fraction of the
    normalised face that is visible), ``yaw_deg`` / ``pitch_deg`` / ``roll_deg`` / ``depth_mm`` (translation z) /
    ``anim_abs`` (mean absolute animation unit) ``_mean`` and ``_std`` (population). A batch without real
    frames gives only ``frames`` (0) and ``samples``.

    Example:
        >>> q = tracking_quality({"confidence": torch.tensor([0.5, 1.0]), "success": torch.tensor([True, False])})
        >>> q["confidence_mean"], q["confidence_min"], q["success_fraction"]
        (0.75, 0.5, 0.5)
    """
    return _Accumulator().add(batch).summary()


class TrackingQualityLogger:
    """Accumulates :func:`tracking_quality` over an epoch.

    :meth:`update` adds a batch and returns that batch's statistics; :meth:`compute` gives the statistics of every
    frame since the last :meth:`reset` (means over frames, not means of batch means; the minimum over all).
    Under DDP each rank sees its own share of the items (:mod:`training_hooks.datasets`, "Sharding"):
    ``compute(sync_dist=True)`` gives the statistics of every rank's frames together (items a rank repeats to
    balance the ranks' counts, :class:`~training_hooks.datasets.RankBalance` ``PAD``, count again, as with a
    ``DistributedSampler``).

    Example:
        >>> log = TrackingQualityLogger()
        >>> _ = log.update({"confidence": torch.tensor([0.2, 0.4])})
        >>> _ = log.update({"confidence": torch.tensor([1.0])})
        >>> round(log.compute()["confidence_mean"], 4), round(log.compute()["confidence_min"], 4)
        (0.5333, 0.2)
    """

    def __init__(self) -> None:
        self._epoch = _Accumulator()

    def update(self, batch: Mapping[str, Any]) -> dict[str, float]:
        """Add a batch; returns its own statistics (:func:`tracking_quality`)."""
        own = _Accumulator().add(batch)  # (once: each batch was checked and summed twice, for itself and the epoch)
        self._epoch.merge(own)
        return own.summary()

    def compute(self, sync_dist: bool = False) -> dict[str, float]:
        """Statistics of all frames added since the last :meth:`reset`.

        Args:
            sync_dist: in a ``torch.distributed`` process group, the statistics of the frames added on every rank
                (a collective: every rank must call it; NCCL groups reduce on the current CUDA device); without a
                group the same as False.
        """
        return (self._epoch.all_reduce() if sync_dist else self._epoch).summary()

    def reset(self) -> None:
        """Start a new epoch."""
        self._epoch = _Accumulator()
