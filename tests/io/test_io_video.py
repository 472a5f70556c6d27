"""Frame reading: gray, RGBA, 16-bit and odd-sized frames rejected by default and converted exactly on request;
bad inputs rejected with one-line errors."""

from __future__ import annotations

import os
import shlex
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from torchface.io import InputError, frame_to_tensor, open_frames

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from _helpers import opencv_411_capture, write_rotated_mp4  # noqa: E402

#: The per-channel (R, G, B) mean and standard deviation with which ImageNet networks' inputs are normalised.
IMAGENET_MEAN, IMAGENET_STD = np.array([0.485, 0.456, 0.406]), np.array([0.229, 0.224, 0.225])


def _ramp(lo: float, hi: float) -> np.ndarray:
    """A 2-frame ``(2, 40, 40, 3)`` float64 clip whose every frame holds values from ``lo`` to ``hi``."""
    return np.linspace(lo, hi, 40 * 40 * 3).reshape(40, 40, 3)[None].repeat(2, 0)


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


def test_an_integer_array_is_told_the_unsigned_type_of_its_values(tmp_path):
    """An ``.npy`` clip of int64 (``np.array`` of Python ints) or int32 pixels was told "unsupported pixel type int64
    (expected uint8, uint16 or float in [0, 1])" alone; where its values fit uint8 (or uint16) it is told the
    conversion, and the array converted so reads as the same frames."""
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (2, 40, 50, 3))  # int64
    for array, said in ((frames, r"its values are 0-255: a\.astype\(np\.uint8\)\)$"),
                        (frames.astype(np.int32) * 257, r"its values are 0-65535: a\.astype\(np\.uint16\)\)$"),
                        (frames - 1, r"\(expected uint8, uint16 or float in \[0, 1\]\)$")):  # fmt: skip
        np.save(tmp_path / "clip.npy", array)
        with pytest.raises(InputError, match=rf"frame 0: unsupported pixel type {array.dtype} .*{said}"):
            open_frames(tmp_path / "clip.npy")
    np.save(tmp_path / "clip.npy", frames.astype(np.uint8))
    with open_frames(tmp_path / "clip.npy") as reader:
        first = next(reader)
    torch.testing.assert_close(first, torch.from_numpy(frames[0]).permute(2, 0, 1).float() / 255)


def test_float16_array_is_read_as_float_in_0_1(tmp_path):
    """docs/cli.md takes ``.npy`` float arrays in [0, 1]; a float16 one (half the size of float32) was refused as
    "unsupported pixel type float16 (expected uint8, uint16 or float in [0, 1])", which it is."""
    arr = np.random.default_rng(0).random((2, 40, 50, 3)).astype(np.float16)
    np.save(tmp_path / "half.npy", arr)
    out = _frames(open_frames(tmp_path / "half.npy"))
    assert out.shape == (2, 3, 40, 50) and out.dtype == torch.float32
    torch.testing.assert_close(out, torch.from_numpy(arr.astype(np.float32)).permute(0, 3, 1, 2))
    np.save(tmp_path / "over.npy", arr * np.float16(2))
    with pytest.raises(InputError, match=r"float frames must be finite and in \[0, 1\]"):
        open_frames(tmp_path / "over.npy")


def _assert_format_error(info, *problems):
    msg = str(info.value)
    assert "\n" not in msg, msg
    for problem in problems:
        assert problem in msg, msg
    assert "--convert" in msg and "ffmpeg -i" in msg and "-pix_fmt rgb24" in msg, msg


@pytest.mark.parametrize(
    "array, problems",
    [
        (np.zeros((40, 40), np.uint8), ["grayscale"]),
        (np.zeros((40, 40, 1), np.uint8), ["grayscale"]),
        (np.zeros((40, 40, 4), np.uint8), ["RGBA (4 channels)"]),
        (np.zeros((40, 40, 3), np.uint16), ["16-bit"]),
        (np.zeros((40, 41, 3), np.uint8), ["odd size 41x40"]),
        (np.zeros((39, 40, 3), np.float32), ["odd size 40x39"]),
        (np.zeros((41, 57), np.uint16), ["grayscale", "16-bit", "odd size 57x41"]),
    ],
)
def test_gray_rgba_16_bit_and_odd_sizes_are_rejected_by_default(array, problems):
    with pytest.raises(InputError) as info:
        frame_to_tensor(array, bgr=True, where="x")
    _assert_format_error(info, *problems)
    t, _ = frame_to_tensor(array, bgr=True, where="x", convert=True)
    assert t.shape == (3, array.shape[0] // 2 * 2, array.shape[1] // 2 * 2)


def test_colour_8_bit_even_frames_are_accepted_as_stored():
    rng = np.random.default_rng(1)
    bgr = rng.integers(0, 256, size=(40, 42, 3), dtype=np.uint8)
    t, fmt = frame_to_tensor(bgr, bgr=True, where="x")
    assert fmt == "uint8 BGR"
    torch.testing.assert_close(t, torch.from_numpy(bgr[:, :, ::-1].copy()).permute(2, 0, 1).float() / 255)


def test_a_read_only_array_converts_without_a_warning():
    """Frames of ``np.frombuffer`` (an ffmpeg pipe's bytes) are read-only: torch's "The given NumPy array is not
    writable" UserWarning came with the first one, though the tensor is a float copy. torch says it once per
    process, so a child process runs it with warnings as errors."""
    import subprocess
    import sys

    code = (
        "import numpy as np; from torchface.io import frame_to_tensor\n"
        "a = np.frombuffer(bytes(range(120)) * 2, np.uint8).reshape(8, 10, 3)\n"
        "t, _ = frame_to_tensor(a, bgr=False, where='x')\n"
        "assert np.array_equal((t.permute(1, 2, 0).numpy() * 255).round(), a), 'values'\n"
        "print('ok')"
    )  # fmt: skip
    run = subprocess.run([sys.executable, "-W", "error", "-c", code], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr[-1500:]


def test_gray_rgba_and_16_bit_are_converted_with_convert():
    gray16 = np.full((40, 40), 65535 // 5, dtype=np.uint16)
    t, fmt = frame_to_tensor(gray16, bgr=False, where="x", convert=True)
    assert fmt == "uint16 gray" and t.shape == (3, 40, 40)
    torch.testing.assert_close(t, torch.full((3, 40, 40), (65535 // 5) / 65535))
    bgra = np.zeros((40, 40, 4), dtype=np.uint8)
    bgra[..., 0], bgra[..., 3] = 255, 7  # blue, some alpha
    t, fmt = frame_to_tensor(bgra, bgr=True, where="x", convert=True)
    assert fmt == "uint8 BGRA"
    torch.testing.assert_close(t[:, 0, 0], torch.tensor([0.0, 0.0, 1.0]))  # RGB order, alpha dropped
    odd = np.arange(41 * 43 * 3, dtype=np.float64).reshape(41, 43, 3) / (41 * 43 * 3)
    t, _ = frame_to_tensor(odd, bgr=False, where="x", convert=True)
    torch.testing.assert_close(t, torch.from_numpy(odd[:40, :42]).permute(2, 0, 1).float())  # last row/column cut


def test_image_folder_16_bit_gray_and_odd_size(tmp_path):
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i:02d}.png"), np.full((41, 57), 1000 * (i + 1), dtype=np.uint16))
    with pytest.raises(InputError) as info:
        open_frames(tmp_path)
    _assert_format_error(info, "f00.png", "grayscale, 16-bit, odd size 57x41")
    reader = open_frames(tmp_path, convert=True)
    assert reader.info.kind == "images" and reader.info.source_format == "uint16 gray"
    assert (reader.info.width, reader.info.height) == (56, 40)
    assert reader.info.conversion == "uint16 gray -> RGB; cropped 57x41 to 56x40"
    out = _frames(reader)
    assert out.shape == (3, 3, 40, 56)
    torch.testing.assert_close(out[:, 0, 0, 0], torch.tensor([1000.0, 2000.0, 3000.0]) / 65535)


def test_convert_must_be_a_bool(tmp_path):
    """``open_frames(path, convert=...)`` took any truthy value: ``convert="no"`` (or ``"False"``, from a config
    file's text) converted the frames it was meant to refuse. It is a bool, as the settings' flags are, checked
    before the input is opened; ``np.bool_`` (an array's element) too."""
    for i in range(2):
        cv2.imwrite(str(tmp_path / f"f{i:02d}.png"), np.full((40, 56), 100, dtype=np.uint8))  # gray: refused
    for bad in ("no", "False", 0, None):
        with pytest.raises(TypeError, match=rf"^convert must be a bool, got {type(bad).__name__} {bad!r}$"):
            open_frames(tmp_path, convert=bad)  # type: ignore[arg-type]
        with pytest.raises(TypeError, match="convert must be a bool"):
            open_frames(tmp_path / "missing", convert=bad)  # type: ignore[arg-type]
    with pytest.raises(InputError, match="grayscale"):
        open_frames(tmp_path, convert=np.bool_(False))  # type: ignore[arg-type]
    assert open_frames(tmp_path, convert=True).info.conversion == "uint8 gray -> RGB"
    gray = np.full((40, 56), 100, dtype=np.uint8)  # frame_to_tensor's own convert alike (it converted on "no")
    with pytest.raises(TypeError, match=r"^convert must be a bool, got str 'no'$"):
        frame_to_tensor(gray, bgr=True, where="x", convert="no")  # type: ignore[arg-type]
    assert frame_to_tensor(gray, bgr=True, where="x", convert=True)[0].shape == (3, 40, 56)


def test_gray_frame_mid_folder_is_rejected(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((40, 40, 3), np.uint8))
    cv2.imwrite(str(tmp_path / "b.png"), np.zeros((40, 40), np.uint8))
    reader = open_frames(tmp_path)
    next(reader)
    with pytest.raises(InputError) as info:
        next(reader)
    _assert_format_error(info, "frame 1", "grayscale")
    reader = open_frames(tmp_path, convert=True)
    assert _frames(reader).shape == (2, 3, 40, 40)


def test_an_array_to_convert_is_told_how_to_save_it_not_an_ffmpeg_command(tmp_path):
    """``torchface track gray.npy`` was told ``ffmpeg -i in.mp4 ...``, a video file's remedy: an array is told how to
    save it as the reader takes it (its own problems' fixes only), and the fix reads; a video file keeps ffmpeg's."""
    from torchface.io.video import CONVERT_HINT, CONVERT_OPTION

    gray = np.full((3, 41, 40), 90, np.uint8)
    np.save(tmp_path / "gray.npy", gray)
    with pytest.raises(InputError) as info:
        open_frames(tmp_path / "gray.npy")
    text = str(info.value)
    assert "frames are grayscale, odd size 40x41" in text and "ffmpeg" not in text, text
    assert "np.save(path, a) after a = np.repeat(a[..., None], 3, -1) for gray (T, H, W) frames" in text, text
    assert "then a = a[:, : a.shape[1] // 2 * 2, : a.shape[2] // 2 * 2]" in text and "16-bit" not in text, text
    assert text.endswith(CONVERT_OPTION) and CONVERT_HINT.endswith(CONVERT_OPTION)
    a = np.repeat(gray[..., None], 3, -1)  # the fixes as told
    np.save(tmp_path / "rgb.npy", a[:, : a.shape[1] // 2 * 2, : a.shape[2] // 2 * 2])
    assert _frames(open_frames(tmp_path / "rgb.npy")).shape == (3, 3, 40, 40)
    assert _frames(open_frames(tmp_path / "gray.npy", convert=True)).shape == (3, 3, 40, 40)


def test_a_single_image_file_is_one_frame_of_an_assumed_rate(tmp_path):
    """A ``.png`` given as an input is read as a video of one frame, whose 25 frames/s FFmpeg's image demuxer gave as
    the input's own (``fps_assumed`` False, so the JSON claimed a frame rate an image has not) with no frame count."""
    for k in range(1, 3):  # (a numbered name: still the one image, not a sequence from it)
        cv2.imwrite(str(tmp_path / f"img_{k:03d}.png"), np.full((48, 64, 3), 40 * k, np.uint8))
    reader = open_frames(tmp_path / "img_001.png")
    assert reader.info.fps_assumed and reader.info.fps == 25.0 and reader.info.num_frames == 1, reader.info
    assert _frames(reader).shape == (1, 3, 48, 64)


def _write_ffv1(path, frames, params):
    writer = cv2.VideoWriter(str(path), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"FFV1"), 25, (64, 48), params)
    if not writer.isOpened():
        pytest.skip(f"this OpenCV build cannot write {path.name}")
    for f in frames:
        writer.write(f)
    writer.release()
    return path


def test_video_files_gray_16_bit_and_rgba_are_rejected(tmp_path):
    gray = _write_ffv1(tmp_path / "gray.mkv", [np.full((48, 64), 50 * i, np.uint8) for i in range(3)],
                       [cv2.VIDEOWRITER_PROP_IS_COLOR, 0])  # fmt: skip
    gray16 = _write_ffv1(tmp_path / "gray16.mkv", [np.full((48, 64), 9000 * i, np.uint16) for i in range(3)],
                         [cv2.VIDEOWRITER_PROP_DEPTH, cv2.CV_16U, cv2.VIDEOWRITER_PROP_IS_COLOR, 0])  # fmt: skip
    rgba = np.full((48, 64, 4), 100, np.uint8)
    rgba[..., 3] = 128
    alpha = _write_ffv1(tmp_path / "rgba.mkv", [rgba] * 3, [cv2.VIDEOWRITER_PROP_ENABLE_ALPHA, 1])
    opaque = rgba.copy()
    opaque[..., 3] = 255
    colour = _write_ffv1(tmp_path / "opaque.mkv", [opaque] * 3, [cv2.VIDEOWRITER_PROP_ENABLE_ALPHA, 1])
    for path, problems, fmt in [
        (gray, ["grayscale"], "uint8 gray"),
        (gray16, ["grayscale, 16-bit"], "uint16 gray"),
        (alpha, ["RGBA (4 channels)"], "uint8 BGRA"),
    ]:
        with pytest.raises(InputError) as info:
            open_frames(path)
        _assert_format_error(info, path.name, *problems)
        reader = open_frames(path, convert=True)
        assert reader.info.source_format == fmt and reader.info.conversion == f"{fmt} -> RGB"
        assert _frames(reader).shape == (3, 3, 48, 64)
    reader = open_frames(colour)  # an opaque alpha channel is colour padding
    assert reader.info.source_format == "uint8 BGR" and reader.info.conversion == ""
    torch.testing.assert_close(_frames(reader)[0, :, 0, 0], torch.full((3,), 100 / 255))


def test_a_stream_without_a_frame_count_declares_none(tmp_path):
    """A raw MJPEG stream has no frame count: OpenCV reports -192153584101141, which was kept as the declared count
    (the progress bar read "1/-192153584101141" and the JSON's declared_frames that number)."""
    path = tmp_path / "raw.mjpeg"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (64, 48))
    assert writer.isOpened()
    for k in range(3):
        writer.write(np.full((48, 64, 3), 40 * k, np.uint8))
    writer.release()
    reader = open_frames(path)
    assert reader.info.num_frames is None or reader.info.num_frames == 3, reader.info.num_frames
    assert _frames(reader).shape[0] == 3


def test_an_assumed_frame_rate_is_said_so(tmp_path):
    """fps is the container's where it is plausible, else 25 with ``fps_assumed`` (it was replaced silently: a
    5000 frames/s file's timestamps were frame / 25 with nothing saying the rate was not the file's)."""
    got = {}
    for rate in (30.0, 5000.0):
        path = tmp_path / f"clip{int(rate)}.mp4"
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), rate, (64, 48))
        assert writer.isOpened()
        for k in range(2):
            writer.write(np.full((48, 64, 3), 40 * k, np.uint8))
        writer.release()
        info = open_frames(path).info
        got[rate] = (info.fps, info.fps_assumed)
    assert got == {30.0: (30.0, False), 5000.0: (25.0, True)}, got
    cv2.imwrite(str(tmp_path / "0.png"), np.zeros((40, 40, 3), np.uint8))
    folder = open_frames(tmp_path).info
    assert (folder.fps, folder.fps_assumed) == (25.0, True)


def test_frame_size_change_mid_video(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((40, 40, 3), np.uint8))
    cv2.imwrite(str(tmp_path / "b.png"), np.zeros((48, 40, 3), np.uint8))
    reader = open_frames(tmp_path)
    next(reader)
    with pytest.raises(InputError, match=r"frame 1 \(b\.png\) is 40x48 but the video started at 40x40"):
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
        (lambda p: np.save(p / "f.npy", np.full((2, 40, 40), 2.0, np.float32)) or p / "f.npy",
         r"in \[0, 1\], got values from 2 to 2$"),
        # 0-255 floats (a uint8 clip's .astype(np.float32)): the range and what to do (it said "must be finite and in
        # [0, 1]" alone); NaN pixels named
        (lambda p: np.save(p / "g.npy", np.arange(2 * 40 * 40 * 3, dtype=np.float32).reshape(2, 40, 40, 3) % 256)
         or p / "g.npy", r"frame 0: float frames must be finite and in \[0, 1\], got values from 0 to 255 \(0-255 "
         r"values\? divide by 255, or save them as uint8\)$"),
        # mean/std-normalised frames (ImageNet's, about -2.1 to 2.6), and frames brightened past 1: told the likely
        # cause and how to undo it (their range alone was said)
        (lambda p: np.save(p / "in.npy", (_ramp(0.0, 1.0) - IMAGENET_MEAN) / IMAGENET_STD) or p / "in.npy",
         r"got values from -2\.118 to 2\.64 \(values below 0: normalised with a mean and standard deviation, as for "
         r"an ImageNet network\? undo it, x \* std \+ mean per channel, to get values in \[0, 1\]\)$"),
        # a 0-255 frame less its mean: undone, 0-255 values (it was told that undoing it gave [0, 1])
        (lambda p: np.save(p / "m.npy", _ramp(-128.0, 127.0)) or p / "m.npy",
         r"got values from -128 to 127 \(values below 0: .* to get 0-255 values, then divide by 255\)$"),
        (lambda p: np.save(p / "b.npy", _ramp(0.0, 1.2)) or p / "b.npy",
         r"got values from 0 to 1\.2 \(brightened past 1\? np\.clip\(frames, 0, 1\)\)$"),
        # a bicubic resize's overshoot, a few values just below 0 (it was told of mean/std normalisation)
        (lambda p: np.save(p / "r.npy", _ramp(-0.03, 1.04)) or p / "r.npy",
         r"got values from -0\.03 to 1\.04 \(a little outside \[0, 1\]: resampled, sharpened or brightened\? "
         r"np\.clip\(frames, 0, 1\)\)$"),
        (lambda p: np.save(p / "n.npy", np.where(np.eye(40)[None, :, :, None] > 0, np.nan, np.full((2, 40, 40, 3), .5)))
         or p / "n.npy", r"got NaN and values from 0\.5 to 0\.5 \(a frame file's pixels must be values; NaN marks a "
         r"missing pixel only in the Python API's frame tensors .*np\.nan_to_num\(frames, nan=0\.0\), or track the "
         r"frames as a tensor\)$"),
        (lambda p: np.save(p / "c.npy", np.zeros((2, 40, 40, 2), np.uint8)) or p / "c.npy", "image, got shape"),
        (lambda p: np.save(p / "one.npy", np.zeros((48, 64, 3), np.uint8)) or p / "one.npy", r"one colour image"),
        # a PyTorch clip's .numpy(), (T, 3, H, W): told to transpose it (it was "expected an (H, W) or (H, W, 1|3|4)
        # image, got shape (3, 48, 64)", about a frame)
        (lambda p: np.save(p / "chw.npy", np.zeros((2, 3, 48, 64), np.uint8)) or p / "chw.npy",
         r"chw\.npy: shape \(2, 3, 48, 64\) looks like channels-first frames \(T, C, H, W\).*"
         r"array\.transpose\(0, 2, 3, 1\)"),
        (lambda p: (p / "d").mkdir() or p / "d", "no images"),
        (lambda p: (p / "e.npy").write_bytes(b"") == 0 and p / "e.npy", "not a readable .npy"),  # was EOFError
        # an .npz under an .npy name (np.savez): it was a traceback, AttributeError 'NpzFile' object has no 'ndim'
        (lambda p: np.savez(p / "a.npz", frames=np.zeros((2, 40, 40, 3))) or (p / "a.npz").rename(p / "a.npy"),
         r"a\.npy: an \.npz archive of arrays \(frames\), not one \.npy array: save the frames with np\.save"),
    ],
)
def test_bad_inputs(tmp_path, make, message):
    with pytest.raises(InputError, match=message) as info:
        open_frames(make(tmp_path))
    assert "\n" not in str(info.value)


def test_a_folder_of_videos_is_told_to_give_the_files(tmp_path):
    """A folder of video files (``torchface track clips/``) was told only "folder holds no images ...: zero frames":
    it names the videos and the glob that gives them as inputs (hidden files left out, the names in natural order)."""
    for name in ("s10.mpg", "s2.mpg", "s1.mpg", "s3.mpg", "._s0.mpg", "notes.txt"):
        (tmp_path / name).write_bytes(b"")
    with pytest.raises(InputError) as info:
        open_frames(tmp_path)
    assert str(info.value) == (
        f"{tmp_path}: folder holds no images (.png, .jpg, .jpeg, .bmp, .tif, .tiff) but 4 videos (s1.mpg, s2.mpg, "
        f"s3.mpg, ...): a folder is one video of image frames; give each file as an input ({tmp_path}/*.mpg)"
    )
    (tmp_path / "frames.npy").write_bytes(b"")  # two kinds: a glob each (a '*' named the notes too)
    with pytest.raises(InputError) as info:
        open_frames(tmp_path)
    assert str(info.value).endswith(f"but 5 videos (frames.npy, s1.mpg, s2.mpg, ...): a folder is one video of image "
                                    f"frames; give each file as an input ({tmp_path}/*.mpg {tmp_path}/*.npy)")
    spaced = tmp_path / "my clips"  # quoted as a shell needs it (my clips/*.mp4 was two words)
    spaced.mkdir()
    (spaced / "a.mp4").write_bytes(b"")
    with pytest.raises(InputError) as info:
        open_frames(spaced)
    glob = str(info.value).rsplit(" (", 1)[1].rstrip(")")
    assert shlex.split(glob) == [f"{spaced}/*.mp4"], glob
    spaced.joinpath("a.mp4").unlink()
    spaced.rmdir()
    for f in tmp_path.iterdir():  # an empty folder (but for its notes): as before
        if f.name != "notes.txt":
            f.unlink()
    with pytest.raises(InputError, match=r"holds no images \(.*\): zero frames$"):
        open_frames(tmp_path)


def test_image_folder_order_is_numeric_and_hidden_files_are_skipped(tmp_path):
    """``ffmpeg ... %d.png`` names frames 1.png ... 12.png: read 1, 2, ..., 12 (a plain string sort read 1, 10,
    11, 12, 2, ...); macOS's ``._1.png`` companions are not frames; a bad frame's error names its file."""
    from torchface.io.video import image_files

    for k in range(1, 13):
        cv2.imwrite(str(tmp_path / f"{k}.png"), np.full((40, 40, 3), 10 * k, np.uint8))
    (tmp_path / "._1.png").write_bytes(b"\x00\x05\x16\x07AppleDouble")
    (tmp_path / "notes.txt").write_text("not a frame")
    assert [f.name for f in image_files(tmp_path)] == [f"{k}.png" for k in range(1, 13)]
    frames = _frames(open_frames(tmp_path))
    assert frames.shape == (12, 3, 40, 40)
    torch.testing.assert_close(frames[:, 0, 0, 0] * 255, torch.arange(1, 13, dtype=torch.float32) * 10)
    cv2.imwrite(str(tmp_path / "13.png"), np.zeros((30, 40, 3), np.uint8))
    with pytest.raises(InputError, match=r"frame 12 \(13\.png\) is 40x30"):
        _frames(open_frames(tmp_path))
    names = ["img10.png", "img9.png", "img010b.png", "a.png", "frame_0002.png", "frame_0010.png"]
    for n in names:
        (tmp_path / n).write_bytes(b"")
    order = [f.name for f in image_files(tmp_path) if not f.name[0].isdigit()]
    assert order == ["a.png", "frame_0002.png", "frame_0010.png", "img9.png", "img10.png", "img010b.png"]
    (tmp_path / "1\u00b22.png").write_bytes(b"")  # '1²2': a superscript is a digit to str.isdigit, not a number
    assert "1\u00b22.png" in [f.name for f in image_files(tmp_path)]


def test_npy_clip_is_read_a_frame_at_a_time(tmp_path):
    """A ``.npy`` clip is mapped, not loaded: opening it and reading its frames holds about one frame in memory
    (it used to load the whole array first, so a clip larger than the memory could not be tracked)."""
    import tracemalloc

    T, H, W = 120, 120, 160  # 6.9 MB of frames, 58 KB each
    clip = np.random.default_rng(0).integers(0, 256, (T, H, W, 3), dtype=np.uint8)
    path = tmp_path / "clip.npy"
    np.save(path, clip)
    tracemalloc.start()
    try:
        with open_frames(path) as frames:
            got = [next(frames) for _ in range(T)]
            assert frames.info.num_frames == T
            _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < clip.nbytes / 4, peak  # (the tensors kept here are torch's, which tracemalloc does not see)
    for k in (0, 1, T - 1):
        np.testing.assert_array_equal((got[k].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8), clip[k])


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc (Linux)")
def test_closing_a_npy_reader_releases_its_file(tmp_path):
    """``close`` left a ``.npy`` clip mapped (the frames not read held the mapping, and the mapping the file open):
    a job over many clips ran out of file descriptors although it closed the readers it had done with."""
    path = tmp_path / "clip.npy"
    np.save(path, np.zeros((4, 32, 32, 3), np.uint8))

    def held() -> int:
        return sum(os.path.realpath(f"/proc/self/fd/{fd}") == str(path.resolve()) for fd in os.listdir("/proc/self/fd"))

    reader = open_frames(path)
    next(reader)
    assert held() == 1
    reader.close()
    assert held() == 0
    with pytest.raises(StopIteration):  # nothing more to read once closed
        next(reader)


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="needs /proc/self/fd")
def test_a_video_that_fails_to_open_leaves_no_file_open(tmp_path, monkeypatch):
    """A failure while checking the first frame other than an InputError (an interruption, a memory error) left
    the decoder, and its file, open for as long as the exception was held (a data pipeline that keeps the errors
    of the videos it skips)."""
    import torchface.io.video as video

    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (64, 48))
    assert writer.isOpened()
    for k in range(3):
        writer.write(np.full((48, 64, 3), 40 * k, np.uint8))
    writer.release()

    def open_files() -> int:
        links = (os.path.join("/proc/self/fd", f) for f in os.listdir("/proc/self/fd"))
        return sum(os.path.realpath(link) == str(path.resolve()) for link in links if os.path.islink(link))

    with open_frames(path):
        assert open_files() == 1  # (the decoder holds the file open: what is measured)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(video, "format_problems", interrupted)
    with pytest.raises(KeyboardInterrupt) as held:
        open_frames(path)
    assert held.value is not None and open_files() == 0


@pytest.mark.skipif(not os.path.isfile("/proc/self/maps"), reason="needs /proc/self/maps")
def test_closing_an_npy_reader_unmaps_its_file(tmp_path):
    """A closed ``.npy`` reader kept its file mapped (and went on giving frames) for as long as the reader lived:
    a job keeps its readers to the end of the run."""
    path = tmp_path / "clip.npy"
    np.save(path, np.zeros((3, 32, 32, 3), np.uint8))

    def mapped() -> bool:
        with open("/proc/self/maps") as maps:
            return any(line.rstrip().endswith(str(path)) for line in maps)

    reader = open_frames(path)
    next(reader)
    assert mapped()  # (what is measured)
    reader.close()
    assert not mapped()
    with pytest.raises(StopIteration):  # as a closed video's reader
        next(reader)


def test_frame_times_are_the_containers_where_they_go_forward(tmp_path):
    """Every frame's time was ``frame / fps``: a variable-frame-rate video's rows were placed on a grid its frames
    are not on. The reader gives the container's time (``CAP_PROP_POS_MSEC``, a fake clock here) where it is a number
    that goes forward, else the last such time plus ``1 / fps`` per frame; without a clock, ``frame / fps``."""
    from torchface.io.video import FrameReader, VideoInfo

    ms = iter([0.0, 40.0, 100.0, 120.0, float("nan"), 200.0, 200.0, -5.0, 300.0])
    frame = torch.zeros(3, 32, 32)
    info = VideoInfo(tmp_path / "v.mp4", "video", 32, 32, 25.0, 9, "uint8 BGR")
    rest = iter([(np.zeros((32, 32, 3), np.uint8), True)] * 8)
    reader = FrameReader(info, frame, rest, clock=lambda: next(ms))
    times = []
    for _ in reader:
        times.append(reader.timestamp)
    np.testing.assert_allclose(times, [0.0, 0.04, 0.1, 0.12, 0.16, 0.2, 0.24, 0.28, 0.3], atol=1e-12)
    np.save(tmp_path / "clip.npy", np.zeros((4, 32, 32, 3), np.uint8))
    with open_frames(tmp_path / "clip.npy") as reader:
        assert [reader.timestamp for _ in reader] == [k / 25.0 for k in range(4)]
    path = str(tmp_path / "cfr.avi")
    writer = cv2.VideoWriter(path, cv2.VideoWriter.fourcc(*"MJPG"), 30.0, (32, 32))
    for k in range(5):
        writer.write(np.full((32, 32, 3), 40 * k, np.uint8))
    writer.release()
    with open_frames(path) as reader:  # a constant-rate video's container times are frame / fps
        np.testing.assert_allclose([reader.timestamp for _ in reader], np.arange(5) / 30.0, atol=1e-6)


@pytest.mark.parametrize("opencv_default", ["installed", "4.11"])
@pytest.mark.parametrize("rotate", [90, 180, 270])
def test_a_phone_videos_frames_come_out_as_displayed(tmp_path, monkeypatch, rotate, opencv_default):
    """A video stored landscape with a display rotation (a phone's portrait video) reads as a viewer shows it: frames
    turned ``rotate`` degrees clockwise, and the info's width and height theirs. Under OpenCV 4.11's default
    (auto-rotation off) the frames came out as stored, 64x48 for a 48x64 portrait video, so that landmarks given in
    the displayed frame (as any viewer shows it) fell elsewhere, and what was tracked depended on the OpenCV."""
    stored = np.kron(np.random.default_rng(rotate).integers(0, 256, (3, 6, 8, 3)), np.ones((1, 8, 8, 1)))
    write_rotated_mp4(tmp_path / "plain.mp4", stored.astype(np.uint8), 0)
    write_rotated_mp4(tmp_path / "phone.mp4", stored.astype(np.uint8), rotate)
    plain = _frames(open_frames(tmp_path / "plain.mp4"))  # (3, 3, 48, 64)
    if opencv_default == "4.11":
        monkeypatch.setattr(cv2, "VideoCapture", opencv_411_capture)
    reader = open_frames(tmp_path / "phone.mp4")
    w, h = (48, 64) if rotate in (90, 270) else (64, 48)
    assert (reader.info.width, reader.info.height) == (w, h)
    torch.testing.assert_close(_frames(reader), torch.rot90(plain, -rotate // 90, dims=(2, 3)), rtol=0, atol=0)


@pytest.mark.parametrize("bgr", [True, False])
@pytest.mark.parametrize("size", [(48, 64), (49, 65)])
def test_uint8_colour_frames_by_planes_are_the_whole_image_conversion(bgr, size):
    """An 8-bit colour frame (a video's) is converted by planes: the values of converting the (H, W, 3) image and
    flipping and permuting it, a read-only or odd-sized (converted) one's too, contiguous."""
    h, w = size
    array = np.random.default_rng(3).integers(0, 256, (h, w, 3), dtype=np.uint8)
    array.flags.writeable = False
    want = torch.from_numpy(array[: h - h % 2, : w - w % 2].astype(np.float32)) / 255.0
    want = (want.flip(2) if bgr else want).permute(2, 0, 1)
    got, fmt = frame_to_tensor(array, bgr, "x", convert=h % 2 == 1)
    assert torch.equal(got, want) and got.is_contiguous() and got.dtype == torch.float32
    assert fmt == ("uint8 BGR" if bgr else "uint8 RGB")


def test_a_missing_path_starting_with_a_tilde_is_told_that_nothing_expanded_it(tmp_path, monkeypatch):
    """From Python no shell expands ``~``: ``open_frames("~/clip.mp4")`` and ``read_landmarks("~/lm.csv", W, H)``
    were told "no such file or folder" / "no such landmarks file" alone, where ``torchface track`` and training_hooks'
    datasets name the ``~``. They are told so too, also where ``os.path.expanduser`` cannot expand it; a ``~name``
    that no home is, is a name as any other."""
    from _helpers import without_home

    from torchface.io import read_landmarks

    monkeypatch.setenv("HOME", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    tilde = r" \('~' is not expanded here: os\.path\.expanduser\(path\) names the home folder\)$"
    with pytest.raises(InputError, match=r"^~/no_such\.mp4: no such file or folder" + tilde):
        open_frames("~/no_such.mp4")
    with pytest.raises(InputError, match=r"^~/no_such\.csv: no such landmarks file" + tilde):
        read_landmarks("~/no_such.csv", 64, 48)
    with pytest.raises(InputError, match=r"^~torchface-no-such-user\.mp4: no such file or folder$"):
        open_frames("~torchface-no-such-user.mp4")
    without_home(monkeypatch)
    with pytest.raises(InputError, match=r"^~/no_such\.npy: no such file or folder \('~' is not expanded here, and "
                                         r"os\.path\.expanduser cannot expand it here \(HOME is not set"):
        open_frames("~/no_such.npy")
