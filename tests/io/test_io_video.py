"""Frame reading: formats converted exactly, and bad inputs rejected with one-line errors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from torchface.io import InputError, frame_to_tensor, open_frames


def _frames(reader) -> torch.Tensor:
    with reader:
        return torch.stack(list(reader))


def test_rgb_uint8_array_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    arr = rng.integers(0, 256, size=(3, 40, 50, 3), dtype=np.uint8)
    np.save(tmp_path / "clip.npy", arr)
    reader = open_frames(tmp_path / "clip.npy")
    assert (reader.info.width, reader.info.height, reader.info.num_frames) == (50, 40, 3)
    out = _frames(reader)
    assert out.shape == (3, 3, 40, 50) and out.dtype == torch.float32
    torch.testing.assert_close(out, torch.from_numpy(arr).permute(0, 3, 1, 2).float() / 255)


def test_gray_rgba_and_16_bit_are_converted():
    gray16 = np.full((40, 40), 65535 // 5, dtype=np.uint16)
    t, fmt = frame_to_tensor(gray16, bgr=False, where="x")
    assert fmt == "uint16 gray" and t.shape == (3, 40, 40)
    torch.testing.assert_close(t, torch.full((3, 40, 40), (65535 // 5) / 65535))
    bgra = np.zeros((40, 40, 4), dtype=np.uint8)
    bgra[..., 0], bgra[..., 3] = 255, 7  # blue, some alpha
    t, fmt = frame_to_tensor(bgra, bgr=True, where="x")
    assert fmt == "uint8 BGRA"
    torch.testing.assert_close(t[:, 0, 0], torch.tensor([0.0, 0.0, 1.0]))  # RGB order, alpha dropped


def test_image_folder_16_bit_gray_and_odd_size(tmp_path):
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i:02d}.png"), np.full((41, 57), 1000 * (i + 1), dtype=np.uint16))
    reader = open_frames(tmp_path)
    assert reader.info.kind == "images" and reader.info.source_format == "uint16 gray"
    out = _frames(reader)
    assert out.shape == (3, 3, 41, 57)
    torch.testing.assert_close(out[:, 0, 0, 0], torch.tensor([1000.0, 2000.0, 3000.0]) / 65535)


def test_frame_size_change_mid_video(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((40, 40, 3), np.uint8))
    cv2.imwrite(str(tmp_path / "b.png"), np.zeros((48, 40, 3), np.uint8))
    reader = open_frames(tmp_path)
    next(reader)
    with pytest.raises(InputError, match="frame 1 is 40x48 but the video started at 40x40"):
        next(reader)


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda p: p / "missing.mp4", "no such file"),
        (lambda p: (p / "bad.mp4").write_bytes(b"\x00garbage" * 100) and p / "bad.mp4", "OpenCV can open|decoded"),
        (lambda p: (p / "empty.mp4").write_bytes(b"") == 0 and p / "empty.mp4", "OpenCV can open|decoded"),
        (lambda p: np.save(p / "z.npy", np.zeros((0, 40, 40, 3), np.uint8)) or p / "z.npy", "zero frames"),
        (lambda p: np.save(p / "t.npy", np.zeros((2, 20, 40, 3), np.uint8)) or p / "t.npy", "at least 32x32"),
        (lambda p: np.save(p / "i.npy", np.zeros((2, 40, 40, 3), np.int32)) or p / "i.npy", "unsupported pixel type"),
        (lambda p: np.save(p / "f.npy", np.full((2, 40, 40), 2.0, np.float32)) or p / "f.npy", r"in \[0, 1\]"),
        (lambda p: np.save(p / "c.npy", np.zeros((2, 40, 40, 2), np.uint8)) or p / "c.npy", "image, got shape"),
        (lambda p: (p / "d").mkdir() or p / "d", "no images"),
    ],
)
def test_bad_inputs(tmp_path, make, message):
    with pytest.raises(InputError, match=message) as info:
        open_frames(make(tmp_path))
    assert "\n" not in str(info.value)
