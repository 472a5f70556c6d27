"""collate_clips: shapes, masks, padding values, the non-frame keys, bad input."""

from __future__ import annotations

import pytest
import torch

from training_hooks import collate_clips
from training_hooks.collate import pad_value


def clip(T: int, video: int, S: int = 8, A: int = 11, label: int = 0) -> dict[str, torch.Tensor]:
    """A clip item shaped like the dataset's, with recognisable values (frame t of video v holds v * 100 + t)."""
    g = torch.Generator().manual_seed(video)
    upper = torch.randn(T, 3, 3, generator=g).triu(1)
    base = (video * 100 + torch.arange(T, dtype=torch.float32)).reshape(T, 1)
    return {
        "face": torch.rand(T, 3, S, S, generator=g),
        "mask": (torch.rand(T, 1, S, S, generator=g) > 0.5).float(),
        "rotation": torch.linalg.matrix_exp(upper - upper.mT),
        "axis_angle": base.expand(T, 3).clone(),
        "translation": base.expand(T, 3) + 400,
        "ypr_deg": base.expand(T, 3) * 0.1,
        "anim_coeffs": base.expand(T, A) * 0.01,
        "facs": base.expand(T, 6) * 0.01,
        "illumination": base.expand(T, 5) * 0.001,
        "confidence": torch.linspace(0.5, 1.0, T),
        "success": torch.ones(T, dtype=torch.bool),
        "status": torch.zeros(T, dtype=torch.int64),
        "frame": torch.arange(T) + 10,
        "shape_coeffs": torch.full((14,), float(video)),
        "video": torch.tensor(video),
        "cached": torch.tensor(video % 2 == 0),
        "label": torch.tensor(label),
    }


def test_shapes_masks_and_padding():
    items = [clip(3, 0), clip(5, 1, label=2), clip(1, 2, label=1)]
    out = collate_clips(items)
    B, T = 3, 5
    assert out["face"].shape == (B, T, 3, 8, 8) and out["mask"].shape == (B, T, 1, 8, 8)
    assert out["rotation"].shape == (B, T, 3, 3) and out["anim_coeffs"].shape == (B, T, 11)
    assert out["confidence"].shape == (B, T) and out["frame"].shape == (B, T)
    assert out["lengths"].tolist() == [3, 5, 1]
    assert out["frame_mask"].dtype == torch.bool
    assert out["frame_mask"].tolist() == [[1, 1, 1, 0, 0], [1, 1, 1, 1, 1], [1, 0, 0, 0, 0]]
    # the real frames are the items' own, in order
    for b, item in enumerate(items):
        n = item["face"].shape[0]
        for key in ("face", "mask", "rotation", "axis_angle", "confidence", "frame", "status", "success"):
            assert torch.equal(out[key][b, :n], item[key]), key
    # padding: black face, no mask, identity rotation, zero confidence, failed, frame -1
    pad = ~out["frame_mask"]
    assert float(out["face"][pad].abs().sum()) == 0 and float(out["mask"][pad].sum()) == 0
    assert torch.equal(out["rotation"][pad], torch.eye(3).expand(int(pad.sum()), 3, 3))
    assert float(out["confidence"][pad].sum()) == 0 and not bool(out["success"][pad].any())
    assert (out["status"][pad] == 2).all() and (out["frame"][pad] == -1).all()
    # per-clip keys are batched, not padded
    assert out["video"].tolist() == [0, 1, 2] and out["label"].tolist() == [0, 2, 1]
    assert out["cached"].tolist() == [True, False, True] and out["shape_coeffs"].shape == (B, 14)


def test_equal_lengths_match_default_collate():
    items = [clip(4, 0), clip(4, 1)]
    out = collate_clips(items)
    ref = torch.utils.data.default_collate(items)
    assert out["frame_mask"].all()
    for key, value in ref.items():
        assert torch.equal(out[key], value), key


def test_extra_per_frame_keys():
    items = [dict(clip(2, 0), au_label=torch.tensor([1, 2])), dict(clip(3, 1), au_label=torch.tensor([3, 4, 5]))]
    from training_hooks.transforms import PER_FRAME_KEYS

    out = collate_clips(items, per_frame_keys=(*PER_FRAME_KEYS, "au_label"))
    assert out["au_label"].tolist() == [[1, 2, 0], [3, 4, 5]]


def test_a_per_frame_key_left_out_is_named():
    """A per-frame label of clips of different lengths, not in per_frame_keys, was default_collate's "stack expects
    each tensor to be equal size, but got [2] at entry 0 and [3] at entry 1", naming no key."""
    items = [dict(clip(2, 0), au_label=torch.tensor([1, 2])), dict(clip(3, 1), au_label=torch.tensor([3, 4, 5]))]
    with pytest.raises(ValueError, match=r"'au_label' is batched per clip \(not a per-frame key\) but item 1 has "
                       r"shape \(3,\), item 0 \(2,\): one value per frame\? .*PER_FRAME_KEYS, 'au_label'\)\)"):
        collate_clips(items)
    # the defaults replaced by the user's key alone: the face is then the key named
    with pytest.raises(ValueError, match=r"'face' is batched per clip .* one value per frame\?"):
        collate_clips(items, per_frame_keys=["au_label"])
    # an array of another shape that is not per frame: named, without the hint
    a, b = dict(clip(2, 0), emb=torch.zeros(4)), dict(clip(3, 1), emb=torch.zeros(5))
    with pytest.raises(ValueError, match=r"'emb' is batched per clip \(not a per-frame key\) but item 1 has shape "
                       r"\(5,\), item 0 \(4,\)$"):
        collate_clips([a, b])
    # equal lengths still batch without padding, as default_collate does
    same = [dict(clip(3, 0), au_label=torch.tensor([1, 2, 3])), dict(clip(3, 1), au_label=torch.tensor([4, 5, 6]))]
    assert collate_clips(same)["au_label"].tolist() == [[1, 2, 3], [4, 5, 6]]


def test_pad_value():
    assert pad_value("frame", torch.zeros(2, dtype=torch.int64)).tolist() == [-1, -1]
    assert pad_value("status", torch.zeros(1, dtype=torch.int64)).tolist() == [2]
    assert pad_value("confidence", torch.ones(3)).tolist() == [0, 0, 0]


def test_bad_input():
    with pytest.raises(ValueError, match="empty batch"):
        collate_clips([])
    with pytest.raises(ValueError, match="keys"):
        a = clip(2, 0)
        b = clip(2, 1)
        del b["label"]
        collate_clips([a, b])
    with pytest.raises(ValueError, match="default_collate"):
        collate_clips([{"face": torch.zeros(3, 8, 8), "confidence": torch.tensor(1.0)}])  # a frame item
    with pytest.raises(ValueError, match="disagree on the clip length"):
        a = clip(3, 0)
        a["confidence"] = a["confidence"][:2]
        collate_clips([a])
    with pytest.raises(ValueError, match="frames of shape"):
        collate_clips([clip(2, 0, S=8), clip(2, 1, S=16)])
    with pytest.raises(TypeError, match="dict items"):
        collate_clips([(torch.zeros(2),)])
    with pytest.raises(TypeError, match=r"got one item \(a dict\): give the DataLoader a batch_size"):
        collate_clips(clip(2, 0))  # type: ignore[arg-type]  # DataLoader(batch_size=None, collate_fn=collate_clips)
    # One key as a string matched its substrings ("face" made 'face' alone per-frame: then a RuntimeError stacking
    # the clips' confidences of lengths 2 and 3); None was "argument of type 'NoneType' is not iterable".
    for keys in ("face", None):
        with pytest.raises(TypeError, match="per_frame_keys must be a sequence of key names"):
            collate_clips([clip(2, 0), clip(3, 1)], per_frame_keys=keys)  # type: ignore[arg-type]
    per_frame = {k for k in clip(2, 0) if k not in ("shape_coeffs", "video", "cached", "label")}  # a set will do
    assert collate_clips([clip(2, 0), clip(3, 1)], per_frame_keys=per_frame)["face"].shape[1] == 3


def test_items_of_different_dtypes_raise():
    a, b = clip(2, 0), clip(3, 1)
    a["face"] = (a["face"] * 255).to(torch.uint8)  # 0-255 uint8, then a [0, 1] float face
    with pytest.raises(ValueError, match=r"'face': item 1 is torch.float32, item 0 is torch.uint8"):
        collate_clips([a, b])
    c, d = clip(2, 0), clip(3, 1)
    d["face"] = d["face"].double()  # float32 then float64: promoted, nothing lost
    out = collate_clips([c, d])
    assert out["face"].dtype == torch.float64 and torch.equal(out["face"][1, :3], d["face"])


def test_rotation_padding_follows_the_items_dtype_and_device():
    items = [{k: v.double() if k == "rotation" else v for k, v in clip(T, T).items()} for T in (2, 4)]
    out = collate_clips(items)
    assert out["rotation"].dtype == torch.float64
    assert torch.equal(out["rotation"][0, 2:], torch.eye(3, dtype=torch.float64).expand(2, 3, 3))
    example = torch.zeros(2, 3, 3, dtype=torch.float64, device="meta")  # a device other than the CPU
    pad = pad_value("rotation", example)
    assert pad.device == example.device and pad.dtype == torch.float64 and pad.shape == (2, 3, 3)


def test_lengths_and_frame_mask_are_on_the_clips_device():
    """``lengths`` and ``frame_mask`` follow the clips' device (they were made on the CPU, so a mask product with
    clips already on a GPU failed); "meta" stands in for another device."""
    items = [{k: v.to("meta") for k, v in clip(T, T).items()} for T in (2, 4)]
    out = collate_clips(items)
    assert {k: v.device.type for k, v in out.items()} == {k: "meta" for k in out}
    ref = collate_clips([clip(T, T) for T in (2, 4)])
    assert ref["frame_mask"].tolist() == [[True, True, False, False], [True] * 4] and ref["lengths"].tolist() == [2, 4]
