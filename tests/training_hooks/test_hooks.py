"""Training-loop hooks: the weighted loss's maths and gradients, dropping low-confidence samples from frame and
clip batches, tracking-quality statistics against a NumPy reference, epoch accumulation."""

from __future__ import annotations

import ast
import math
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from training_hooks import (
    TrackingQualityLogger,
    collate_clips,
    confidence_weighted_loss,
    drop_low_confidence,
    tracking_quality,
)
from training_hooks.hooks import sample_confidence


def frame_batch(B: int = 6, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "face": torch.rand(B, 3, 4, 4, generator=g),
        "mask": (torch.rand(B, 1, 4, 4, generator=g) > 0.3).float(),
        "confidence": torch.rand(B, generator=g),
        "success": torch.rand(B, generator=g) > 0.2,
        "ypr_deg": torch.randn(B, 3, generator=g) * 10,
        "translation": torch.randn(B, 3, generator=g) * 5 + torch.tensor([0.0, 0.0, 500.0]),
        "anim_coeffs": torch.randn(B, 11, generator=g) * 0.2,
        "cached": torch.rand(B, generator=g) > 0.5,
        "video": torch.arange(B),
        "names": [f"v{i}" for i in range(B)],
    }


# --------------------------------------------------------------------------------------------- loss


def test_every_hook_is_exported_by_the_package():
    """The hooks are used together (``drop_low_confidence`` keeps clips by ``sample_confidence``, which the layer's
    result names beside it), but ``from training_hooks import sample_confidence`` was an ImportError: every name of
    the hooks module is the package's too."""
    import training_hooks
    import training_hooks.hooks

    hooks = training_hooks.hooks
    missing = [n for n in hooks.__all__ if n not in training_hooks.__all__ or getattr(training_hooks, n, None) is not
               getattr(hooks, n)]  # fmt: skip
    assert not missing, missing


def test_weighted_loss_known_answer_and_gradient():
    loss = torch.tensor([1.0, 2.0, 4.0], dtype=torch.float64, requires_grad=True)
    conf = torch.tensor([0.5, 0.25, 0.0], dtype=torch.float64)
    out = confidence_weighted_loss(loss, conf)
    assert math.isclose(float(out.detach()), (0.5 * 1 + 0.25 * 2) / 0.75)
    out.backward()
    assert torch.allclose(loss.grad, conf / conf.sum())  # d/dl_i = c_i / sum c
    assert torch.autograd.gradcheck(lambda l: confidence_weighted_loss(l, conf), (loss.detach().requires_grad_(),))


def test_weighted_loss_with_mask_equals_dropping_entries():
    g = torch.Generator().manual_seed(1)
    loss, conf = torch.rand(3, 5, generator=g), torch.rand(3, 5, generator=g)
    mask = torch.rand(3, 5, generator=g) > 0.4
    got = confidence_weighted_loss(loss, conf, mask)
    ref = confidence_weighted_loss(loss[mask], conf[mask])
    assert torch.allclose(got, ref)
    # uniform confidence is the plain mean
    assert torch.allclose(confidence_weighted_loss(loss, torch.full_like(loss, 0.3)), loss.mean())


def test_weighted_loss_all_zero_weights_is_zero_not_nan():
    loss = torch.tensor([1.0, 2.0], requires_grad=True)
    out = confidence_weighted_loss(loss, torch.zeros(2))
    assert float(out.detach()) == 0.0
    out.backward()
    assert torch.equal(loss.grad, torch.zeros(2))


def test_weighted_loss_zero_weight_entries_with_nan_loss_contribute_nothing():
    """Padded frames (mask False), confidence 0: their NaN / inf losses add exactly 0 to value and gradient."""
    nan, inf = float("nan"), float("inf")
    loss = torch.tensor([[1.0, nan, inf], [3.0, nan, 2.0]], requires_grad=True)
    conf = torch.tensor([[0.5, 0.0, 0.9], [0.5, 0.7, 0.0]])
    mask = torch.tensor([[True, True, False], [True, False, True]])
    out = confidence_weighted_loss(loss, conf, mask)
    assert float(out.detach()) == 2.0
    out.backward()
    assert torch.equal(loss.grad, torch.tensor([[0.5, 0.0, 0.0], [0.5, 0.0, 0.0]]))
    loss = torch.tensor([nan, inf], requires_grad=True)
    out = confidence_weighted_loss(loss, torch.zeros(2))  # every weight zero
    assert float(out.detach()) == 0.0
    out.backward()
    assert torch.equal(loss.grad, torch.zeros(2))


def test_weighted_loss_warns_of_a_nan_loss_made_upstream_at_a_zero_weight_entry():
    """A NaN loss at a padded frame made by the network (a black padded face standardised by its own std, 0 / 0)
    adds 0 to the value, but its backward poisons the parameters' gradients with NaN: that went without a word."""
    face = torch.rand(2, 3, 1, 4, 4)  # (B, T, C, S, S)
    face[1, 2] = 0.0  # a padded frame: black
    mask = torch.tensor([[True, True, True], [True, True, False]])
    conf = torch.tensor([[0.9, 0.8, 0.7], [0.9, 0.9, 0.0]])
    w = torch.ones(16, requires_grad=True)
    x = face.flatten(2)
    x = (x - x.mean(-1, keepdim=True)) / x.std(-1, keepdim=True)  # NaN on the black face
    loss = (x * w).sum(-1) ** 2  # (2, 3), NaN at [1, 2]
    with pytest.warns(RuntimeWarning, match=r"NaN or inf at 1 of its 6 entries of weight 0 .* real frames alone"):
        out = confidence_weighted_loss(loss, conf, mask)
    assert bool(torch.isfinite(out))
    out.backward()
    assert not bool(torch.isfinite(w.grad).all())  # what the warning is about
    # the loss of the real frames alone: no warning, finite gradients
    w.grad = None
    x = face[mask].flatten(1)
    x = (x - x.mean(-1, keepdim=True)) / x.std(-1, keepdim=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        confidence_weighted_loss((x * w).sum(-1) ** 2, conf[mask]).backward()
        # a leaf loss (no upstream) and finite losses at zero weights say nothing
        confidence_weighted_loss(torch.tensor([1.0, float("nan")], requires_grad=True), torch.tensor([1.0, 0.0]))
        confidence_weighted_loss(loss.detach().nan_to_num() * w.sum(), conf, mask)
    assert bool(torch.isfinite(w.grad).all())


class _HostReads(torch.overrides.TorchFunctionMode):
    """Counts the reads of a tensor's values into Python (each a device sync on a GPU)."""

    READS = ("item", "tolist", "__bool__", "__int__", "__float__", "__index__", "cpu", "numpy")

    def __init__(self) -> None:
        super().__init__()
        self.reads: list[str] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if getattr(func, "__name__", "") in self.READS:
            self.reads.append(func.__name__)
        return func(*args, **(kwargs or {}))


def test_weighted_loss_with_a_graph_reads_the_device_no_more_than_without():
    """The check for NaN losses at zero weights (only where the loss has a graph: a training step) added a sync of
    its own, an ``int(...)`` per call, to a function called every training step; it now shares the one read the
    weighted mean already made. The value and the warning are as before."""
    w = torch.ones(2, 3, requires_grad=True)
    conf = torch.tensor([[0.9, 0.8, 0.7], [0.9, 0.9, 0.0]])
    mask = torch.tensor([[True, True, True], [True, True, False]])
    counts = []
    for loss in ((w * 2).detach(), w * 2):
        with _HostReads() as reads:
            out = confidence_weighted_loss(loss, conf, mask)
        counts.append(len(reads.reads))
        assert torch.allclose(out, torch.tensor(2.0))
    assert counts[1] == counts[0], counts
    bad = w * torch.tensor([[1.0, 1.0, 1.0], [1.0, 1.0, float("nan")]])
    with _HostReads() as reads, pytest.warns(RuntimeWarning, match="NaN or inf at 1 of its 6 entries"):
        out = confidence_weighted_loss(bad, conf, mask)
    assert len(reads.reads) == counts[0] and torch.allclose(out, torch.tensor(1.0))
    assert confidence_weighted_loss(w * 2, torch.zeros(2, 3)).item() == 0.0  # every weight 0: 0, in the graph


def test_weighted_loss_of_another_shape_is_told_how_to_make_it():
    """A loss already reduced (cross_entropy's default reduction="mean"), one per clip of a clip batch and a (B, 1)
    head's were told the shapes alone."""
    conf, mask = torch.rand(4, 3), torch.ones(4, 3, dtype=torch.bool)
    logits, y = torch.randn(4, 2), torch.tensor([0, 1, 0, 1])
    with pytest.raises(ValueError, match=r"got \(\), \(4, 3\), \(4, 3\) \(a scalar: compute the loss with "
                                         r'reduction="none", one per sample or frame\)$'):
        confidence_weighted_loss(torch.nn.functional.cross_entropy(logits, y), conf, mask)
    per_clip = torch.nn.functional.cross_entropy(logits, y, reduction="none")
    with pytest.raises(ValueError, match=r"got \(4,\), \(4, 3\), \(4, 3\) \(one loss per clip, the confidence per "
                                         r"frame: weigh it by each clip's, sample_confidence\(batch\), or compute"):
        confidence_weighted_loss(per_clip, conf, mask)
    batch = {"confidence": conf, "frame_mask": mask}
    assert bool(torch.isfinite(confidence_weighted_loss(per_clip, sample_confidence(batch))))  # (the way named)
    with pytest.raises(ValueError, match=r"got \(4, 1\), \(4,\), None \(a trailing 1: loss.squeeze\(-1\)\)$"):
        confidence_weighted_loss(torch.rand(4, 1), conf[:, 0])
    with pytest.raises(ValueError, match=r"got \(4, 2\), \(4, 3\), None$"):  # (nothing to say)
        confidence_weighted_loss(torch.rand(4, 2), conf)


def test_weighted_loss_bad_input():
    with pytest.raises(ValueError, match="one shape"):
        confidence_weighted_loss(torch.ones(3), torch.ones(2))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        confidence_weighted_loss(torch.ones(2), torch.tensor([0.5, 1.5]))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        confidence_weighted_loss(torch.ones(2), torch.tensor([0.5, float("nan")]))


def test_weighted_loss_refuses_an_integer_loss_and_a_mask_that_is_not_a_tensor():
    """An int64 loss (per-sample error counts) cast the confidence to int64: every weight 0, the result 0 instead
    of 1.5. A numpy or list mask was an AttributeError ('numpy.ndarray' object has no attribute 'to')."""
    with pytest.raises(TypeError, match="loss must be a floating-point tensor, got torch.int64"):
        confidence_weighted_loss(torch.tensor([1, 3]), torch.tensor([0.75, 0.25]))
    for mask in (np.array([True, False]), [True, False]):
        with pytest.raises(TypeError, match="mask must be a bool tensor or None"):
            confidence_weighted_loss(torch.ones(2), torch.ones(2), mask)  # type: ignore[arg-type]
    assert float(confidence_weighted_loss(torch.tensor([1, 3]).double(), torch.tensor([0.75, 0.25]))) == 1.5


# --------------------------------------------------------------------------------------------- dropping


def test_drop_low_confidence_frames():
    batch = frame_batch()
    out = drop_low_confidence(batch, 0.4)
    keep = (batch["confidence"] >= 0.4) & batch["success"]
    assert out.indices.tolist() == keep.nonzero().squeeze(-1).tolist()
    for key in ("face", "mask", "confidence", "ypr_deg", "video"):
        assert torch.equal(out.batch[key], batch[key][keep]), key
    assert out.batch["names"] == [n for n, k in zip(batch["names"], keep.tolist()) if k]
    # without the success requirement only the threshold counts
    loose = drop_low_confidence(batch, 0.4, require_success=False)
    assert loose.indices.tolist() == (batch["confidence"] >= 0.4).nonzero().squeeze(-1).tolist()
    # threshold 0 still drops failed frames; threshold 1 keeps (almost) nothing
    assert drop_low_confidence(batch, 0.0).indices.tolist() == batch["success"].nonzero().squeeze(-1).tolist()
    assert len(drop_low_confidence(batch, 1.0).indices) == 0


def test_drop_low_confidence_clips_uses_the_mean_over_real_frames():
    conf = torch.tensor([[0.9, 0.1, 0.0], [0.6, 0.6, 0.6], [0.2, 0.0, 0.0]])
    mask = torch.tensor([[True, True, False], [True, True, True], [True, False, False]])
    success = torch.tensor([[True, True, False], [True, False, True], [False, False, False]])
    batch = {"confidence": conf, "frame_mask": mask, "success": success, "face": torch.zeros(3, 3, 2, 4, 4)}
    # clip means: (0.9 + 0.1) / 2 = 0.5; success-weighted (0.6 + 0 + 0.6) / 3 = 0.4; 0.2 but its frame failed
    assert torch.allclose(sample_confidence(batch), torch.tensor([0.5, 0.4, 0.0]))
    assert torch.allclose(sample_confidence(batch, require_success=False), torch.tensor([0.5, 0.6, 0.2]))
    assert drop_low_confidence(batch, 0.45).indices.tolist() == [0]
    assert drop_low_confidence(batch, 0.45, require_success=False).indices.tolist() == [0, 1]
    assert drop_low_confidence(batch, 0.0).indices.tolist() == [0, 1]  # clip 2 has no successful frame
    assert drop_low_confidence(batch, 0.45).batch["face"].shape == (1, 3, 2, 4, 4)


def test_drop_low_confidence_keeps_collated_labels_with_their_samples():
    """Labels that ``default_collate`` batched from a nested dict or a tuple in each item stay with their samples
    (the dict was kept whole, and a tuple of as many tensors as samples was cut as if it were one per sample:
    the kept face was paired with another sample's label)."""
    from collections import namedtuple

    from torch.utils.data import default_collate

    Pair = namedtuple("Pair", "cls intensity")
    conf = [0.9, 0.1, 0.8]
    items = [
        {"confidence": torch.tensor(c), "face": torch.full((2,), float(i)), "target": {"label": torch.tensor(i)},
         "pair": (torch.tensor(i), torch.tensor(10.0 * i), torch.tensor(-i)), "named": Pair(i, 0.5 * i),
         "path": f"v{i}.avi"}
        for i, c in enumerate(conf)
    ]  # fmt: skip
    out = drop_low_confidence(default_collate(items), 0.5)
    kept = [0, 2]
    assert out.indices.tolist() == kept and out.batch["face"][:, 0].tolist() == kept
    assert out.batch["target"]["label"].tolist() == kept
    assert [p.tolist() for p in out.batch["pair"]] == [kept, [0.0, 20.0], [0, -2]]
    assert isinstance(out.batch["named"], Pair) and out.batch["named"].cls.tolist() == kept
    assert out.batch["named"].intensity.tolist() == [0.0, 1.0]
    assert out.batch["path"] == ["v0.avi", "v2.avi"]


def test_drop_bad_input():
    with pytest.raises(TypeError, match="dict"):
        drop_low_confidence([torch.ones(2)], 0.5)
    with pytest.raises(ValueError, match="confidence"):
        drop_low_confidence({"face": torch.ones(2)}, 0.5)
    with pytest.raises(ValueError, match="threshold"):
        drop_low_confidence({"confidence": torch.ones(2)}, 1.5)


# --------------------------------------------------------------------------------------------- quality logging


def reference_quality(batch: dict) -> dict[str, float]:
    """The statistics computed plainly with NumPy over the real frames."""
    valid = batch["frame_mask"].numpy() if "frame_mask" in batch else np.ones(batch["confidence"].shape, bool)
    conf = batch["confidence"].numpy()[valid].astype(np.float64)
    out = {
        "frames": float(valid.sum()),
        "confidence_mean": conf.mean(),
        "confidence_min": conf.min(),
        "success_fraction": batch["success"].numpy()[valid].mean(),
        "face_coverage": batch["mask"].numpy()[valid].reshape(int(valid.sum()), -1).mean(1).mean(),
        "depth_mm_mean": batch["translation"].numpy()[valid][:, 2].astype(np.float64).mean(),
        "depth_mm_std": batch["translation"].numpy()[valid][:, 2].astype(np.float64).std(),
        "anim_abs_mean": np.abs(batch["anim_coeffs"].numpy()[valid]).mean(-1).mean(),
    }
    for k, name in enumerate(("yaw_deg", "pitch_deg", "roll_deg")):
        v = batch["ypr_deg"].numpy()[valid][:, k].astype(np.float64)
        out[f"{name}_mean"], out[f"{name}_std"] = v.mean(), v.std()
    cached = np.broadcast_to(batch["cached"].numpy().reshape(-1, *([1] * (valid.ndim - 1))), valid.shape)[valid]
    out["cached_fraction"] = cached.mean()
    return out


def check_against_reference(got: dict, batch: dict) -> None:
    ref = reference_quality(batch)
    for key, value in ref.items():
        assert math.isclose(got[key], float(value), rel_tol=1e-6, abs_tol=1e-6), (key, got[key], value)


def test_tracking_quality_frame_batch_against_numpy():
    batch = frame_batch()
    got = tracking_quality(batch)
    check_against_reference(got, batch)
    assert got["samples"] == 6.0


def test_tracking_quality_clip_batch_ignores_padding():
    b1, b2 = frame_batch(3, seed=1), frame_batch(5, seed=2)
    per_frame = ("face", "mask", "confidence", "success", "ypr_deg", "translation", "anim_coeffs")
    items = [
        {**{k: b[k] for k in per_frame}, "cached": b["cached"][0], "video": torch.tensor(i)}
        for i, b in enumerate((b1, b2))
    ]
    batch = collate_clips(items)
    assert batch["frame_mask"].sum() == 8
    got = tracking_quality(batch)
    check_against_reference(got, batch)
    assert got["frames"] == 8.0 and got["samples"] == 2.0


def test_logger_accumulates_over_the_epoch():
    b1, b2 = frame_batch(4, seed=3), frame_batch(7, seed=4)
    log = TrackingQualityLogger()
    assert log.update(b1) == tracking_quality(b1)
    log.update(b2)
    both = {k: torch.cat([b1[k], b2[k]]) for k in b1 if isinstance(b1[k], torch.Tensor)}
    check_against_reference(log.compute(), both)
    assert log.compute()["confidence_min"] == min(float(b1["confidence"].min()), float(b2["confidence"].min()))
    log.reset()
    assert log.compute() == {"frames": 0.0, "samples": 0.0}


class _Copies(torch.overrides.TorchFunctionMode):
    """Counts the torch calls made under it and the largest tensor they allocated (bytes of a storage that none of
    the call's tensor arguments holds: a copy, not a view)."""

    def __init__(self) -> None:
        super().__init__()
        self.calls, self.largest = 0, 0

    def __torch_function__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        self.calls += 1
        inputs = [a for a in (*args, *(kwargs or {}).values()) if isinstance(a, torch.Tensor)]
        if isinstance(out, torch.Tensor) and out.numel() > 0:
            held = {a.untyped_storage().data_ptr() for a in inputs if a.numel() > 0}
            if out.untyped_storage().data_ptr() not in held:
                self.largest = max(self.largest, out.untyped_storage().nbytes())
        return out


def test_quality_statistics_neither_copy_the_masks_nor_sum_a_batch_twice():
    """The face coverage indexed the masks by the real frames and cast them to float64 (two copies of every mask: 160 ms
    for a batch of 32 clips of 16 frames of 128-pixel faces, now 3 ms), and TrackingQualityLogger.update summed each
    batch twice (for the epoch and for its own statistics). The values stay those of the NumPy reference."""
    items = [{**{k: frame_batch(5, seed=s)[k] for k in ("mask", "confidence", "success", "ypr_deg")}} for s in (5, 6)]
    items[1] = {k: v[:3] for k, v in items[1].items()}
    for k in range(2):
        items[k]["mask"] = items[k]["mask"].repeat(1, 1, 8, 8)  # (32 x 32: larger than anything else)
    batch = collate_clips(items)
    mask_bytes = batch["mask"].untyped_storage().nbytes()
    with _Copies() as seen:
        got = tracking_quality(batch)
    assert seen.largest < mask_bytes / 8, (seen.largest, mask_bytes)
    valid = batch["frame_mask"]
    reference = batch["mask"][valid].reshape(int(valid.sum()), -1).to(torch.float64).mean(1).mean()
    assert math.isclose(got["face_coverage"], float(reference), rel_tol=1e-12)
    with _Copies() as once:
        tracking_quality(batch)
    log = TrackingQualityLogger()
    with _Copies() as update:
        assert log.update(batch) == got
    assert update.calls <= once.calls and log.compute() == got


def test_quality_of_a_batch_without_real_frames():
    batch = {"confidence": torch.zeros(2, 3), "frame_mask": torch.zeros(2, 3, dtype=torch.bool)}
    assert tracking_quality(batch) == {"frames": 0.0, "samples": 2.0}
    with pytest.raises(ValueError, match="frame_mask"):
        tracking_quality({"confidence": torch.zeros(2, 3), "frame_mask": torch.zeros(2, 2, dtype=torch.bool)})


def test_batch_values_of_the_wrong_shape_or_type_are_named():
    """A (1,) ``success`` was broadcast over every sample by drop_low_confidence (all kept) and was an IndexError in
    tracking_quality, as were ``ypr_deg``, ``translation`` or ``mask`` of another shape; a single ``cached`` flag was
    counted for every frame; numpy ``frame_mask`` / ``success`` were AttributeErrors, a numpy confidence "must hold a
    'confidence' tensor, got keys ['confidence']"; a NaN confidence gave confidence_min inf and mean NaN (and was
    dropped silently), where confidence_weighted_loss refuses it."""
    batch = frame_batch(3)
    for key, bad in (("success", torch.tensor([True])), ("frame_mask", torch.ones(3, 2, dtype=torch.bool))):
        with pytest.raises(ValueError, match=f"{key} .* must match confidence"):
            drop_low_confidence({**batch, key: bad}, 0.5)
        with pytest.raises(ValueError, match=f"{key} .* must match confidence"):
            tracking_quality({**batch, key: bad})
    for key, bad in (("ypr_deg", torch.zeros(3)), ("ypr_deg", torch.zeros(4, 3)), ("translation", torch.zeros(3, 2)),
                     ("mask", torch.zeros(2, 1, 4, 4)), ("anim_coeffs", torch.zeros(3))):  # fmt: skip
        with pytest.raises(ValueError, match=rf"batch\['{key}'\] must be \(B, .*like confidence \(3,\)"):
            tracking_quality({**batch, key: bad})
    with pytest.raises(ValueError, match="one flag per sample"):
        tracking_quality({**batch, "cached": torch.tensor([True])})
    for key in ("success", "confidence"):
        with pytest.raises(TypeError, match=rf"batch\['{key}'\] must be a"):
            drop_low_confidence({**batch, key: batch[key].numpy()}, 0.5)
    with pytest.raises(TypeError, match=r"batch\['frame_mask'\] must be a tensor"):
        tracking_quality({"confidence": torch.ones(2, 3), "frame_mask": np.ones((2, 3), bool)})
    nan = batch["confidence"].clone()
    nan[1] = float("nan")
    for fn in (tracking_quality, lambda b: drop_low_confidence(b, 0.5)):
        with pytest.raises(ValueError, match="confidence'] must be finite"):
            fn({**batch, "confidence": nan})
    # A NaN on a padded frame is not looked at; the clip layout's per-frame values are (B, T, ...).
    clip = {"confidence": torch.tensor([[0.5, float("nan")]]), "frame_mask": torch.tensor([[True, False]]),
            "ypr_deg": torch.zeros(1, 2, 3), "mask": torch.ones(1, 2, 1, 4, 4)}  # fmt: skip
    assert tracking_quality(clip)["confidence_min"] == 0.5
    with pytest.raises(ValueError, match=r"must be \(B, T, 3\)"):
        tracking_quality({**clip, "ypr_deg": torch.zeros(1, 3)})


def _private_torchface_uses(folder: Path) -> list[str]:
    """``file:line: name`` of each private ``torchface`` name the ``.py`` files under ``folder`` use: a module path or
    an imported name with a part that starts with ``_`` (``torchface._native``, ``torchface.geometry._checks``,
    ``torchface.tracker.step._bounds``), an attribute of that kind read from a name bound to ``torchface`` or to
    anything imported from it (``torchface.backend._native``, ``step._bounds``; dunders such as ``__version__`` are
    public), or such a dotted path in a string (``importlib.import_module("torchface._native")``)."""

    def private(dotted: str) -> bool:
        parts = dotted.split(".")
        return parts[0] == "torchface" and any(p.startswith("_") and not p.startswith("__") for p in parts)

    found = []
    for path in sorted(folder.rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        bound: dict[str, str] = {}  # local name -> the torchface path it stands for
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.split(".")[0] == "torchface":
                        bound[a.asname or a.name.split(".")[0]] = a.name if a.asname else "torchface"
            elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "torchface":
                for a in node.names:
                    bound[a.asname or a.name] = f"{node.module}.{a.name}"
        for node in ast.walk(tree):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
                chain, value = [node.attr], node.value
                while isinstance(value, ast.Attribute):
                    chain.append(value.attr)
                    value = value.value
                if isinstance(value, ast.Name) and value.id in bound:
                    names = [".".join([bound[value.id], *reversed(chain)])]
            elif isinstance(node, ast.Constant) and isinstance(node.value, str):
                names = [node.value] if re.fullmatch(r"torchface(\.\w+)+", node.value) else []
            found += [f"{path.name}:{node.lineno}: {name}" for name in names if private(name)]
    return sorted(found)


def test_training_hooks_use_only_torchface_public_names():
    """``training_hooks`` is a package outside ``torchface`` and uses its public names only: it imported
    ``torchface._native`` (whether the native kernels load, for the cache key), ``torchface.tracker.step._bounds``
    (the reference path's bounds), the settings' checks from ``torchface.geometry._checks``, and
    ``torchface._autocast`` / ``torchface._compiling``; now ``torchface.backend.native_available``,
    ``torchface.tracker.step.parameter_bounds`` and :mod:`torchface.extending`."""
    import training_hooks

    assert _private_torchface_uses(Path(training_hooks.__file__).parent) == []


def test_the_private_name_scan_finds_each_kind_of_use(tmp_path):
    """The scan above finds private names however they are reached (a scan that finds nothing passes anything)."""
    (tmp_path / "a.py").write_text(
        "import importlib\nimport torchface\nimport torchface._native as n\nfrom torchface import _native\n"
        "from torchface.geometry._checks import check_int\nfrom torchface.tracker import step\n"
        "from torchface.backend import native_available, Backend\n"
        "x = torchface.__version__, torchface.backend._native.library(), step._bounds, Backend._member_map_\n"
        "importlib.import_module('torchface._compiling')\n",
        encoding="utf-8",
    )
    assert _private_torchface_uses(tmp_path) == [
        "a.py:3: torchface._native", "a.py:4: torchface._native", "a.py:5: torchface.geometry._checks.check_int",
        "a.py:8: torchface.backend.Backend._member_map_", "a.py:8: torchface.backend._native",
        "a.py:8: torchface.tracker.step._bounds", "a.py:9: torchface._compiling",
    ]  # fmt: skip


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16, torch.bool, torch.uint8])
def test_face_coverage_of_low_precision_masks_is_exact(dtype):
    """A bfloat16 mask's frame means were taken in bfloat16 (the float64 cast left out to avoid the copy): 5000 of
    128 x 128 pixels read 0.3047 instead of 0.30518 (the float64 mean before); each frame's mean is now accumulated
    and returned in float32 at least."""
    mask = torch.zeros(4, 1, 128, 128)
    mask.view(4, -1)[:, :5000] = 1
    got = tracking_quality({"confidence": torch.ones(4), "mask": mask.to(dtype)})["face_coverage"]
    assert got == 5000 / 128**2
