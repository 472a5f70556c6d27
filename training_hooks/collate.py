"""Batching clips of different lengths: pad to the longest, keep a mask, keep every parameter a tensor.

Frame items (:class:`~training_hooks.datasets.VideoDataset` with ``clip_length=None``) all have the same shapes
and batch with PyTorch's ``default_collate``. Clip items have a leading ``T_i`` that can differ (the short last
clip of a video with :attr:`~training_hooks.datasets.DatasetConfig.keep_short_clips`, or clips from
:class:`~training_hooks.transforms.NormaliseFaces` on sequences of different lengths); :func:`collate_clips`
pads them to ``T = max_i T_i``.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import default_collate

from torchface.tracker.step import TrackStatus
from training_hooks.transforms import PER_FRAME_KEYS

__all__ = ["collate_clips", "pad_value"]


def pad_value(key: str, example: Tensor) -> Tensor:
    """What a padded frame holds under ``key`` (shape of one frame, ``example``'s dtype and device).

    ``frame`` -1, ``status`` FAILED (2), ``success`` False, ``rotation`` the identity (a valid rotation, so code that
    applies it stays finite); everything else 0 (``confidence`` 0, ``mask`` 0, ``face`` black).

    Example:
        >>> pad_value("rotation", torch.zeros(3, 3))
        tensor([[1., 0., 0.],
                [0., 1., 0.],
                [0., 0., 1.]])
    """
    if key == "frame":
        return torch.full_like(example, -1)
    if key == "status":
        return torch.full_like(example, int(TrackStatus.FAILED))
    if key == "rotation" and example.shape[-2:] == (3, 3):
        return torch.eye(3, dtype=example.dtype, device=example.device).expand_as(example).clone()
    return torch.zeros_like(example)


def _check_same_shape(key: str, values: list[object], lengths: list[int]) -> None:
    """Refuse a key batched with ``default_collate`` (not in ``per_frame_keys``) whose arrays differ in shape
    between items, naming it; where their leading sizes are the clips' lengths, say how to pad it as a per-frame key
    (a per-frame label of clips of 3 and 5 frames was torch's "stack expects each tensor to be equal size, but got
    [3] at entry 0 and [5] at entry 1", naming no key)."""
    arrays = [v for v in values if isinstance(v, (Tensor, np.ndarray))]
    if len(arrays) != len(values):
        return
    shapes = [tuple(v.shape) for v in arrays]
    if len(set(shapes)) < 2:
        return
    hint = ""
    if all(len(s) >= 1 and s[0] == n for s, n in zip(shapes, lengths)):
        hint = (f": one value per frame? name it a per-frame key, padded as the others, collate_clips(batch, "
                f"per_frame_keys=(*training_hooks.transforms.PER_FRAME_KEYS, {key!r}))")
    k = next(k for k, s in enumerate(shapes) if s != shapes[0])
    raise ValueError(
        f"{key!r} is batched per clip (not a per-frame key) but item {k} has shape {shapes[k]}, item 0 "
        f"{shapes[0]}{hint}"
    )


def collate_clips(
    batch: Sequence[dict[str, Tensor]], per_frame_keys: Sequence[str] = PER_FRAME_KEYS
) -> dict[str, Tensor]:
    """Collate clip items of lengths ``T_i`` into one batch padded to ``T = max T_i``.

    Args:
        batch: ``B`` clip items (dicts of tensors). Under ``per_frame_keys`` each holds ``(T_i, ...)`` with the
            same ``T_i`` across those keys of an item and the same trailing shape across items; every other key
            (``video``, ``target``, ``cached``, ``shape_coeffs``, a label of your own, ...) is batched with
            ``default_collate``.
        per_frame_keys: the keys with a leading time axis (default
            :data:`~training_hooks.transforms.PER_FRAME_KEYS`; keys an item lacks are skipped, so add your own
            per-frame keys to them: ``(*PER_FRAME_KEYS, "frame_label")``; given alone they replace them).

    Returns:
        The per-frame keys as ``(B, T, ...)`` tensors, padded after each clip's end with :func:`pad_value`
        (``face`` ``(B, T, C, S, S)``, ``mask`` ``(B, T, 1, S, S)``, ``confidence`` ``(B, T)``, ...); the other keys
        batched; ``frame_mask`` ``(B, T)`` bool, True on real frames; ``lengths`` ``(B,)`` int64, the ``T_i``.

    Raises:
        TypeError: ``batch`` is one item (a dict) rather than a list of them, or holds something other than dicts.
        ValueError: an empty batch, items with different keys, a per-frame tensor without a time axis, lengths
            that differ within an item, or trailing shapes that differ between items, an array under another key
            whose shape differs between items (a per-frame key left out of ``per_frame_keys`` is named so), or an
            integer and a float
            dtype under one key (a ``uint8`` face in ``[0, 255]`` and a float one in ``[0, 1]`` do not batch; float32
            and float64 batch as float64).

    Example:
        >>> a = {"face": torch.ones(3, 3, 8, 8), "confidence": torch.ones(3), "video": torch.tensor(0)}
        >>> b = {"face": torch.ones(5, 3, 8, 8), "confidence": torch.ones(5), "video": torch.tensor(1)}
        >>> out = collate_clips([a, b])
        >>> out["face"].shape, out["frame_mask"].sum(1).tolist(), out["video"].tolist()
        (torch.Size([2, 5, 3, 8, 8]), [3, 5], [0, 1])
    """
    if isinstance(per_frame_keys, (str, bytes)) or not isinstance(per_frame_keys, Collection):
        # (a string matched its substrings: "face" took 'face' alone as per-frame, then failed stacking confidences)
        raise TypeError(f"per_frame_keys must be a sequence of key names (a list), got {type(per_frame_keys).__name__}")
    if isinstance(batch, dict):
        # DataLoader(batch_size=None) calls collate_fn on each item: iterating the dict gave its keys, and the
        # error read "collate_clips takes dict items, got ['str']"
        raise TypeError(
            "collate_clips takes a batch, a list of clip items (dicts), got one item (a dict): give the DataLoader a "
            "batch_size (DataLoader(batch_size=None) calls collate_fn on each item), or collate_clips([item])"
        )
    if len(batch) == 0:
        raise ValueError("collate_clips got an empty batch")
    if not all(isinstance(item, dict) for item in batch):
        raise TypeError(f"collate_clips takes dict items, got {sorted({type(i).__name__ for i in batch})}")
    keys = list(batch[0].keys())
    for k, item in enumerate(batch):
        if set(item.keys()) != set(keys):
            raise ValueError(f"item {k} has keys {sorted(item.keys())}, item 0 has {sorted(keys)}")
    frame_keys = [key for key in keys if key in per_frame_keys]
    if not frame_keys:
        raise ValueError(f"no per-frame key among {sorted(keys)} (expected some of {list(per_frame_keys)})")
    lengths = []
    for k, item in enumerate(batch):
        lens = set()
        for key in frame_keys:
            x = item[key]
            if not isinstance(x, Tensor) or x.dim() < 1:
                got = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
                raise ValueError(
                    f"item {k}: {key!r} must be a (T, ...) tensor (a clip item), got {got}; frame items batch with "
                    "torch.utils.data.default_collate"
                )
            lens.add(int(x.shape[0]))
        if len(lens) != 1:
            raise ValueError(f"item {k}: per-frame tensors disagree on the clip length: {sorted(lens)}")
        lengths.append(lens.pop())
    if min(lengths) < 1:
        raise ValueError("collate_clips got an empty clip (T = 0)")
    B, T = len(batch), max(lengths)
    out: dict[str, Tensor] = {}
    for key in frame_keys:
        tail = tuple(batch[0][key].shape[1:])
        dtype = batch[0][key].dtype
        for k, item in enumerate(batch):
            if tuple(item[key].shape[1:]) != tail:
                raise ValueError(
                    f"{key!r}: item {k} has frames of shape {tuple(item[key].shape[1:])}, item 0 has {tail}"
                )
            if item[key].dtype.is_floating_point != dtype.is_floating_point:  # uint8 0-255 against float 0-1
                raise ValueError(f"{key!r}: item {k} is {item[key].dtype}, item 0 is {dtype}: convert the items alike")
            dtype = torch.promote_types(dtype, item[key].dtype)  # float32 with float64: float64
        ref = batch[0][key].to(dtype)
        padded = pad_value(key, ref[:1]).expand(B, T, *tail).clone()
        for k, item in enumerate(batch):
            padded[k, : lengths[k]] = item[key]
        out[key] = padded
    rest = [key for key in keys if key not in frame_keys]
    for key in rest:  # (default_collate's "stack expects each tensor to be equal size" named no key)
        _check_same_shape(key, [item[key] for item in batch], lengths)
    if rest:
        out.update(default_collate([{key: item[key] for key in rest} for item in batch]))
    device = batch[0][frame_keys[0]].device  # the clips' device, as the padded keys
    length = torch.tensor(lengths, dtype=torch.int64, device=device)
    out["lengths"] = length
    out["frame_mask"] = torch.arange(T, device=device).unsqueeze(0) < length.unsqueeze(1)
    return out
