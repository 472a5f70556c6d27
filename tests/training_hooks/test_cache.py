"""The tracking cache: a second epoch reads it (bit-identical items), a changed config / video / landmark set never
reads a stale entry, damaged files are detected and tracked again, writes are atomic."""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from torchface.synth.io import read_video_uint8, write_video
from training_hooks import CacheWarning, FaceStorage, TrackCache, VideoDataset, cache_key, content_hash
from training_hooks.cache import _HASH_MEMO
from training_hooks.transforms import TrackedSequence

from th_data import FRAMES, TRACKING


def epoch(dataset, num_workers: int = 0) -> dict[tuple[int, int], dict[str, torch.Tensor]]:
    return {
        (int(i["video"]), int(i["frame"])): i for i in DataLoader(dataset, batch_size=None, num_workers=num_workers)
    }


def same_items(a, b) -> bool:
    return a.keys() == b.keys() and all(
        torch.equal(a[k][n], b[k][n]) for k in a for n in a[k] if n != "cached"
    )


def cached_videos(items) -> dict[int, bool]:
    flags: dict[int, set[bool]] = {}
    for (v, _), item in items.items():
        flags.setdefault(v, set()).add(bool(item["cached"]))
    assert all(len(f) == 1 for f in flags.values()), "a video's frames disagree on where they came from"
    return {v: f.pop() for v, f in sorted(flags.items())}


@pytest.fixture
def two(clips, tmp_path):
    """Copies of two clips' videos (tests modify them) and their landmarks."""
    videos = []
    for c in clips[:2]:
        dst = tmp_path / c.video.name
        shutil.copy(c.video, dst)
        videos.append(dst)
    return videos, [c.landmarks for c in clips[:2]]


# --------------------------------------------------------------------------------------------- feature


def test_second_epoch_hits_the_cache_with_identical_items(two, config):
    videos, lms = two
    data = VideoDataset(videos, lms, config)
    first = epoch(data, 2)
    assert cached_videos(first) == {0: False, 1: False}
    assert len(list(config.cache_dir.glob("*.npz"))) == 2
    assert not list(config.cache_dir.glob(".*partial"))
    second = epoch(data, 2)
    assert cached_videos(second) == {0: True, 1: True}
    assert same_items(first, second)
    # in-process counters (num_workers = 0)
    third = epoch(data, 0)
    assert same_items(first, third)
    assert data.stats.cache.hits == 2 and data.stats.cache.misses == 0 and data.stats.frames_tracked == 0


def test_changed_config_never_reads_a_stale_cache(two, config):
    videos, lms = two
    base = epoch(VideoDataset(videos, lms, config))
    fit = replace(TRACKING.tracker.fit, shape_prior_precision=0.5)  # a field of a nested dataclass
    changes = [
        replace(TRACKING, tracker=replace(TRACKING.tracker, max_points=400)),  # a tracker field
        replace(TRACKING, tracker=replace(TRACKING.tracker, fit=fit)),
        replace(TRACKING, face_size=24),
        replace(TRACKING, face_storage=FaceStorage.FLOAT16),
        replace(TRACKING, focal=140.0),
    ]
    for tracking in changes:
        items = epoch(VideoDataset(videos, lms, replace(config, tracking=tracking)))
        assert cached_videos(items) == {0: False, 1: False}, tracking
    # what the changes produce really differs from the base, so a stale read would have been visible
    items = epoch(VideoDataset(videos, lms, replace(config, tracking=changes[0])))
    assert cached_videos(items) == {0: True, 1: True}
    assert not torch.equal(items[(0, FRAMES - 1)]["axis_angle"], base[(0, FRAMES - 1)]["axis_angle"])
    assert epoch(VideoDataset(videos, lms, replace(config, tracking=changes[2])))[(0, 0)]["face"].shape[-1] == 24
    # the original config still hits its own entries
    assert cached_videos(epoch(VideoDataset(videos, lms, config))) == {0: True, 1: True}


def test_changed_video_bytes_or_landmarks_invalidate(two, config, clips):
    videos, lms = two
    data = VideoDataset(videos, lms, config)
    before = epoch(data)
    # rewrite video 1 with its last frame brightened: same name, size and frame count, different content
    frames = read_video_uint8(videos[1]).float() / 255
    frames[-1] = (frames[-1] * 1.1).clamp(0, 1)
    write_video(videos[1], frames)
    after = epoch(data)
    assert cached_videos(after) == {0: True, 1: False}
    assert not torch.equal(after[(1, FRAMES - 1)]["face"], before[(1, FRAMES - 1)]["face"])
    assert torch.equal(after[(1, 0)]["face"], before[(1, 0)]["face"])  # the unchanged frames track alike
    # moved landmarks are another key
    moved = [lms[0] + 0.5, lms[1]]
    assert cached_videos(epoch(VideoDataset(videos, moved, config))) == {0: False, 1: True}
    # a renamed copy with the same bytes hits (the key is the content, not the path)
    copy = videos[0].with_name("renamed.avi")
    shutil.copy(videos[0], copy)
    assert cached_videos(epoch(VideoDataset([copy], lms[:1], config))) == {0: True}


@pytest.mark.parametrize("damage", ["truncate", "flip", "garbage", "empty", "swap"])
def test_damaged_cache_file_is_detected_and_recomputed(two, config, damage):
    videos, lms = two
    data = VideoDataset(videos[:1], lms[:1], config)
    ref = epoch(data)
    (path,) = config.cache_dir.glob("*.npz")
    raw = bytearray(path.read_bytes())
    if damage == "truncate":
        path.write_bytes(bytes(raw[: len(raw) // 2]))
    elif damage == "flip":  # one bit inside the stored faces
        raw[len(raw) // 3] ^= 0x10
        path.write_bytes(bytes(raw))
    elif damage == "garbage":
        path.write_bytes(b"not a cache file" * 10)
    elif damage == "empty":
        path.write_bytes(b"")
    else:  # a valid file of ANOTHER key under this key's name
        other = epoch(VideoDataset(videos[1:], lms[1:], config))
        assert other
        (other_path,) = [p for p in config.cache_dir.glob("*.npz") if p != path]
        shutil.copy(other_path, path)
    with pytest.warns(CacheWarning, match="damaged cache file"):
        again = epoch(data)
    assert cached_videos(again) == {0: False}
    assert same_items(ref, again)
    assert data.stats.cache.corrupt == 1
    # the rewritten file is good again
    assert cached_videos(epoch(data)) == {0: True}


def test_a_damaged_file_replaced_while_it_was_read_is_kept(two, config, monkeypatch):
    """Two processes (DataLoader workers, ranks) that find a cache file damaged both track the video again, and the
    first to finish stores a good file under its name. The other then deleted that good file (it deleted the name,
    not the file it had read): the next epoch tracked the video once more. Now a file replaced since it was read
    is kept."""
    import training_hooks.cache as cache_module

    videos, lms = two
    data = VideoDataset(videos[:1], lms[:1], config)
    epoch(data)
    (path,) = config.cache_dir.glob("*.npz")
    good = path.read_bytes()
    path.write_bytes(good[: len(good) // 2])
    real = cache_module._read

    def read_while_another_process_stores(p, key):
        try:
            return real(p, key)
        finally:  # the other process's store (TrackCache.store: a temporary file renamed into place)
            fresh = p.with_name("fresh.tmp")
            fresh.write_bytes(good)
            os.replace(fresh, p)

    monkeypatch.setattr(cache_module, "_read", read_while_another_process_stores)
    with pytest.warns(CacheWarning, match="damaged cache file .*; a new file replaced it meanwhile, kept"):
        assert cache_module.TrackCache(config.cache_dir).load(path.stem) is None
    monkeypatch.undo()
    assert path.read_bytes() == good
    assert cached_videos(epoch(data)) == {0: True}


def test_failed_write_leaves_no_file(two, config, monkeypatch):
    videos, lms = two

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", boom)
    with pytest.raises(OSError, match="disk full"):
        epoch(VideoDataset(videos[:1], lms[:1], config))
    assert list(config.cache_dir.iterdir()) == []


def test_float_storage_round_trips(two, config):
    videos, lms = two
    cfg = replace(config, tracking=replace(TRACKING, face_storage=FaceStorage.FLOAT32))
    data = VideoDataset(videos[:1], lms[:1], cfg)
    first, second = epoch(data), epoch(data)
    assert cached_videos(second) == {0: True} and same_items(first, second)
    face = first[(0, 0)]["face"]
    assert not torch.equal((face * 255).round() / 255, face)  # not quantised


# --------------------------------------------------------------------------------------------- keys


def test_content_hash_and_key(tmp_path, clips):
    a = tmp_path / "a.bin"
    a.write_bytes(b"abc")
    h = content_hash(a)
    assert len(h) == 64 and content_hash(a) == h
    a.write_bytes(b"abd")
    assert content_hash(a) != h
    folder = tmp_path / "frames"
    folder.mkdir()
    (folder / "0.png").write_bytes(b"one")
    (folder / "1.png").write_bytes(b"two")
    (folder / "notes.txt").write_bytes(b"ignored")
    hf = content_hash(folder)
    (folder / "notes.txt").write_bytes(b"changed")
    assert content_hash(folder) == hf
    (folder / "0.png").write_bytes(b"two")
    (folder / "1.png").write_bytes(b"one")  # same bytes, other order
    assert content_hash(folder) != hf
    lm = clips[0].landmarks
    k = cache_key(h, TRACKING, lm)
    assert k == cache_key(h, TRACKING, lm.copy())
    assert k != cache_key(h, TRACKING, lm, extra="convert=True")
    assert k != cache_key(h, replace(TRACKING, num_threads=2), lm)
    lm2 = lm.copy()
    lm2[5, 0] = np.nextafter(lm2[5, 0], np.inf)
    assert k != cache_key(h, TRACKING, lm2)
    with pytest.raises(ValueError, match=r"\(68, 2\)"):
        cache_key(h, TRACKING, lm[:5])
    with pytest.raises(ValueError, match="64 lowercase hex"):
        TrackCache(tmp_path).path("../../etc")
    assert _HASH_MEMO  # the per-process memo is used


def test_a_missing_point_has_one_key_whatever_its_nan(clips):
    """A missing landmark is a NaN row, whatever the NaN's bits: NumPy's ``0 / 0`` (a computed NaN, the sign bit set
    on x86), a NaN with a payload and a file's ``nan`` were different cache keys for the same landmarks (tracked again,
    stored twice); a missing point and a given one still differ. (The NaNs are made bit by bit: ``0 / 0`` is the
    file's NaN on ARM, where the test could not tell them apart.)"""
    lm = clips[0].landmarks
    read = lm.copy()
    read[[3, 4]] = np.nan
    key = cache_key("0" * 64, TRACKING, read)
    for bits in (0xFFF8000000000000, 0x7FF8000000000001):  # x86's 0 / 0; a quiet NaN with a payload
        other = lm.copy()
        other[[3, 4]] = np.array([bits], dtype=np.uint64).view(np.float64)[0]
        assert np.isnan(other[3]).all() and read.tobytes() != other.tobytes()
        assert cache_key("0" * 64, TRACKING, other) == key != cache_key("0" * 64, TRACKING, lm)


def test_the_hash_memo_keeps_one_small_entry_per_path(tmp_path):
    """The per-process memo of content hashes (a dataset's main process or persistent workers hash every video
    each epoch) keeps one entry per path, of a fixed size: it was keyed by the files' stats, so each version of a
    changed file added an entry, and a folder's entry held three numbers per image (46 kB for 500 images)."""
    import pickle

    a = tmp_path / "a.bin"
    before = set(_HASH_MEMO)
    hashes = set()
    for i in range(5):
        a.write_bytes(b"v%d" % i)
        os.utime(a, ns=(i * 10**9, i * 10**9))  # each version with its own modification time
        hashes.add(content_hash(a))
    assert len(hashes) == 5 and content_hash(a) in hashes
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(200):
        (folder / f"{i}.png").write_bytes(b"%d" % i)
    h = content_hash(folder)
    assert content_hash(folder) == h
    new = {k: v for k, v in _HASH_MEMO.items() if k not in before}
    assert len(new) == 2
    assert max(len(pickle.dumps(item)) for item in new.items()) < 1000


def test_torchface_version_is_part_of_the_key(monkeypatch, clips):
    import torchface

    k = cache_key("0" * 64, TRACKING, clips[0].landmarks)
    monkeypatch.setattr(torchface, "__version__", "99.0")
    assert cache_key("0" * 64, TRACKING, clips[0].landmarks) != k


def test_a_cache_filled_by_other_code_of_the_same_version_is_not_read(two, config, monkeypatch):
    """An editable install keeps ``torchface.__version__`` across the commits it is pulled to, and their tracking may
    differ: a cache filled before a ``git pull`` was read after it (``cached`` True, the old code's items)."""
    from training_hooks import cache as cache_module

    videos, lms = two
    first = epoch(VideoDataset(videos, lms, config))
    assert cached_videos(epoch(VideoDataset(videos, lms, config))) == {0: True, 1: True}
    real = cache_module.code_version()
    monkeypatch.setattr(cache_module, "_CODE_VERSION", ["0" * 64])  # the same installed files, edited
    again = epoch(VideoDataset(videos, lms, config))
    assert cached_videos(again) == {0: False, 1: False}
    assert same_items(first, again)  # (the code did not change here: the same items)
    # each file's meta names the code that tracked it, so that a user can tell the files no code of theirs reads
    codes = sorted(json.loads(bytes(np.load(f)["meta"]))["code"] for f in Path(config.cache_dir).glob("*.npz"))
    assert codes == sorted([real] * 2 + ["0" * 64] * 2), codes


def test_the_code_version_is_a_digest_of_the_packages_files(tmp_path):
    """:func:`code_version` digests every file of the two packages (source, C kernels, model data), not their
    ``__pycache__``, whatever the folder they are installed in."""
    import torchface
    import training_hooks
    from training_hooks.cache import _package_digest, code_version

    installed = tuple(Path(m.__file__).parent for m in (torchface, training_hooks))
    assert code_version() == _package_digest(installed) and len(code_version()) == 64
    copies = tuple(tmp_path / root.name for root in installed)
    for root, copy in zip(installed, copies):
        shutil.copytree(root, copy, ignore=shutil.ignore_patterns("__pycache__"))
    assert _package_digest(copies) == code_version()  # (moved: the same digest)
    (copies[0] / "__pycache__").mkdir(exist_ok=True)
    (copies[0] / "__pycache__" / "step.cpython-311.pyc").write_bytes(b"compiled")
    assert _package_digest(copies) == code_version()
    for edited in ("tracker/step.py", "_native/kernels.c", "data/candide3.wfm"):
        path = copies[0] / edited
        before = path.read_bytes()
        path.write_bytes(before + b"\n")
        assert _package_digest(copies) != code_version(), edited
        path.write_bytes(before)
    path = copies[1] / "transforms.py"
    path.write_bytes(path.read_bytes() + b"\n")
    assert _package_digest(copies) != code_version()



def test_the_code_version_leaves_out_editor_files_and_reads_a_zip_import(tmp_path, monkeypatch):
    """What editors and tools leave beside the code (swap, backup and auto-save files, hidden files and folders,
    stray byte-code), which come and go or change as one types while a run goes on, does not change the digest (a
    ``DataLoader`` worker started later keyed its videos apart from its rank's and tracked them again); a file
    removed between the listing and its reading is left out, not an error; packages imported from a zip archive
    are digested from it (their ``Path(__file__).parent`` is no folder: no file was read, one digest for any code)."""
    import zipfile
    from importlib import resources

    import torchface
    import training_hooks
    from training_hooks.cache import _package_digest, code_version

    assert code_version() == _package_digest(tuple(resources.files(n) for n in ("torchface", "training_hooks")))
    copies = tuple(tmp_path / "site" / Path(m.__file__).parent.name for m in (torchface, training_hooks))
    for module, copy in zip((torchface, training_hooks), copies):
        shutil.copytree(Path(module.__file__).parent, copy, ignore=shutil.ignore_patterns("__pycache__"))
    base = _package_digest(copies)
    assert base == code_version()
    tracker = copies[0] / "tracker"
    for junk in (".step.py.swp", "step.py~", "#step.py#", ".#step.py", ".DS_Store", "step.cpython-311.pyc",
                 "step.py.orig", ".mypy_cache/3.11/x.json", ".idea/workspace.xml"):  # fmt: skip
        (tracker / junk).parent.mkdir(parents=True, exist_ok=True)
        (tracker / junk).write_bytes(b"not code")
    assert _package_digest(copies) == base
    (tracker / ".step.py.swp").write_bytes(b"typed on")
    assert _package_digest(copies) == base
    read = Path.read_bytes

    def vanishing(path: Path) -> bytes:
        if path.name == "new.py":
            raise FileNotFoundError(2, "No such file or directory", str(path))
        return read(path)

    (tracker / "new.py").write_bytes(b"x = 1\n")
    assert _package_digest(copies) != base  # (a new module counts)
    with monkeypatch.context() as m:
        m.setattr(Path, "read_bytes", vanishing)
        assert _package_digest(copies) == base  # (gone as it was read: left out, no error)
    (tracker / "new.py").unlink()
    archive = tmp_path / "packages.zip"
    with zipfile.ZipFile(archive, "w") as z:
        for copy in copies:
            for f in sorted(copy.rglob("*")):
                if f.is_file():
                    z.write(f, f.relative_to(copy.parent).as_posix())
    assert _package_digest(tuple(zipfile.Path(archive, f"{c.name}/") for c in copies)) == base

def test_torch_version_and_native_kernels_are_part_of_the_key(monkeypatch, clips):
    """The native kernels and the torch code agree to float tolerance only: a run with ``TORCHFACE_NATIVE=0`` (or
    another torch) must not read the other's entry."""
    from torchface import _native
    from torchface.backend import Backend

    lm = clips[0].landmarks
    k = cache_key("0" * 64, TRACKING, lm)
    torch_only = replace(TRACKING, tracker=replace(TRACKING.tracker, backend=Backend.TORCH))
    k_torch = cache_key("0" * 64, torch_only, lm)
    monkeypatch.setattr(torch, "__version__", "0.0.1")
    assert cache_key("0" * 64, TRACKING, lm) != k
    monkeypatch.undo()
    if _native.library() is not None:  # the kernels run here: turned off, the key changes
        monkeypatch.setattr(_native, "library", lambda: None)
        k_off = cache_key("0" * 64, TRACKING, lm)
        assert k_off != k
        assert cache_key("0" * 64, torch_only, lm) == k_torch  # Backend.TORCH never used them


def test_a_killed_writers_temporary_files_are_swept(tmp_path):
    """A writer killed mid-write leaves ``.<key>.<pid>.<id>.partial``; the next cache's first write deletes those
    older than a day and keeps younger ones (a writer still at work)."""
    import os
    import time

    old, young = tmp_path / f".{'a' * 64}.1.x.partial", tmp_path / f".{'b' * 64}.2.y.partial"
    for f in (old, young):
        f.write_bytes(b"half a file")
    day = time.time() - 25 * 3600
    os.utime(old, (day, day))
    seq = TrackedSequence(
        faces=torch.zeros(1, 3, 4, 4, dtype=torch.uint8), masks=torch.zeros(1, 1, 4, 4, dtype=torch.bool),
        rotation=torch.eye(3)[None], axis_angle=torch.zeros(1, 3), translation=torch.zeros(1, 3),
        ypr_deg=torch.zeros(1, 3), anim_coeffs=torch.zeros(1, 11), expression=torch.zeros(1, 11),
        facs=torch.zeros(1, 11), illumination=torch.zeros(1, 5), confidence=torch.zeros(1),
        status=torch.zeros(1, dtype=torch.int64), shape_coeffs=torch.zeros(14),
        landmarks=torch.zeros(68, 2, dtype=torch.float64), frame_size=(4, 4),
    )  # fmt: skip
    TrackCache(tmp_path).store("c" * 64, seq)
    assert not old.exists() and young.exists() and (tmp_path / f"{'c' * 64}.npz").is_file()


def test_cache_hit_with_array_landmarks_does_not_decode_the_video(two, config, monkeypatch, tmp_path):
    import training_hooks.datasets as datasets

    videos, lms = two
    data = VideoDataset(videos, lms, config)
    first = epoch(data)

    def no_decoding(*args, **kwargs):
        raise AssertionError("the video was decoded on a cache hit")

    monkeypatch.setattr(datasets, "open_frames", no_decoding)
    assert same_items(first, epoch(data))
    # landmarks from a file need the frame size, so the video is opened for them
    csv = tmp_path / "lm.csv"
    np.savetxt(csv, lms[0], delimiter=",", fmt="%.17g")
    with pytest.raises(AssertionError, match="decoded"):
        epoch(VideoDataset(videos[:1], [csv], config))


def test_a_file_that_cannot_be_read_now_is_kept(two, config, monkeypatch):
    """An OS error while reading (too many open files, an I/O error) is no proof of damage: the entry is tracked
    again but the file is kept (it used to be deleted as corrupt)."""
    import training_hooks.cache as cache_module

    videos, lms = two
    data = VideoDataset(videos[:1], lms[:1], config)
    epoch(data)
    (stored,) = list(config.cache_dir.glob("*.npz"))

    def emfile(path, key):
        raise OSError(24, "Too many open files")

    monkeypatch.setattr(cache_module, "_read", emfile)
    with pytest.warns(CacheWarning, match="unreadable now"):
        assert cache_module.TrackCache(config.cache_dir).load(stored.stem) is None
    assert stored.is_file()


def test_a_relative_cache_root_is_the_folder_it_named_when_made(tmp_path, monkeypatch):
    """TrackCache("cache") kept its root relative: after an os.chdir its entries were looked for (and written) in the
    new working folder. The root is made absolute when the cache is made."""
    monkeypatch.chdir(tmp_path)
    cache = TrackCache("cache")
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    assert cache.root == tmp_path / "cache" and cache.path("d" * 64) == tmp_path / "cache" / f"{'d' * 64}.npz"
    with pytest.raises(ValueError, match=r"^root is empty"):  # (was the working folder, unasked)
        TrackCache("")
    with pytest.raises(TypeError, match=r"^root must be a folder \(a str or path-like\), got NoneType$"):
        TrackCache(None)  # type: ignore[arg-type]
    assert TrackCache(".").root == tmp_path / "elsewhere"
    monkeypatch.setenv("HOME", str(tmp_path / "home"))  # ('~' expands wherever HOME is set)
    with pytest.raises(ValueError, match=r"^root '~/c' starts with '~', which is not expanded "):
        TrackCache(Path("~/c"))
    if os.path.expanduser("~root") != "~root":  # (a user's home: ~root expands wherever root is a user)
        with pytest.raises(ValueError, match=r"^root '~root/c' starts with '~', which is not expanded .*'~root'"):
            TrackCache(Path("~root/c"))
    # a name that no user's home expands is a folder's name as any other (it was refused, as any leading '~' was;
    # JobConfig's out_dir and the command line take it)
    assert TrackCache("~torchface-no-such-user").root == tmp_path / "elsewhere" / "~torchface-no-such-user"


def test_a_failed_write_names_the_cache_folder_and_what_to_do(two, config, monkeypatch):
    """A full disk was ``OSError: [Errno 28] No space left on device``, naming neither the cache nor a way out (the
    epoch stops: DatasetConfig.keep_going does not skip a video for the cache's error). The error keeps its errno and
    class, and names the folder and what to do."""
    import errno

    videos, lms = two

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(np, "savez", full)
    with pytest.raises(OSError, match=r"^\[Errno 28\] cannot store a tracked sequence in the cache folder "
                                      + r".*/cache \(No space left on device\): free space there") as caught:
        epoch(VideoDataset(videos[:1], lms[:1], replace(config, keep_going=True)))
    assert caught.value.errno == errno.ENOSPC and "DatasetConfig.cache_dir" in str(caught.value)
    assert list(config.cache_dir.iterdir()) == []
    monkeypatch.undo()
    real_open = open

    def read_only(file, mode="r", *args, **kwargs):
        if "w" in mode and Path(file).parent == config.cache_dir:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(file))
        return real_open(file, mode, *args, **kwargs)

    monkeypatch.setattr("builtins.open", read_only)
    with pytest.raises(PermissionError, match=r"\(Permission denied\): .*make it writable") as caught:
        epoch(VideoDataset(videos[:1], lms[:1], config))
    assert caught.value.errno == errno.EACCES
    monkeypatch.undo()
    sequence, _ = VideoDataset(videos[:1], lms[:1], replace(config, cache_dir=None)).sequence(0)
    (config.cache_dir / "file").write_text("not a folder")
    for root in (config.cache_dir / "file", config.cache_dir / "file" / "cache"):  # (FileExistsError, NotADirectory)
        with pytest.raises(OSError, match=r"^\[Errno \d+\] cannot store a tracked sequence in the cache folder "
                                          + r".*/file(/cache)? \(it is a file, or inside one\): "):
            TrackCache(root).store("d" * 64, sequence)


def test_a_damaged_file_that_cannot_be_deleted_is_tracked_again(two, config, monkeypatch):
    """A damaged file that could not be deleted (a folder that does not let this user delete) raised the deletion's
    PermissionError out of the lookup: the epoch stopped, or with DatasetConfig.keep_going the video was skipped for
    good, as if it were the video's fault. It is a miss: the warning says the file was kept, the video is tracked
    again and its file replaced."""
    import errno

    videos, lms = two
    data = VideoDataset(videos[:1], lms[:1], replace(config, keep_going=True))
    ref = epoch(data)
    (path,) = config.cache_dir.glob("*.npz")
    path.write_bytes(path.read_bytes()[:100])
    real_unlink = Path.unlink

    def no_delete(self, missing_ok=False):
        if self == path:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(self))
        return real_unlink(self, missing_ok)

    monkeypatch.setattr(Path, "unlink", no_delete)
    with pytest.warns(CacheWarning, match=r"damaged cache file .*; it could not be deleted \(Permission denied\), "
                                          r"tracking again"):
        again = epoch(data)
    assert cached_videos(again) == {0: False} and same_items(ref, again) and not data.skipped
    assert cached_videos(epoch(data)) == {0: True}  # (the tracked sequence replaced the damaged file)


def test_a_file_too_big_for_the_memory_left_is_kept(two, config, monkeypatch):
    """A MemoryError while reading (a long video's file, in a worker short of memory) is no proof of damage either:
    it was taken as one, and the good file, hours of tracking for a long video, was deleted."""
    import training_hooks.cache as cache_module

    videos, lms = two
    epoch(VideoDataset(videos[:1], lms[:1], config))
    (stored,) = list(config.cache_dir.glob("*.npz"))

    def short_of_memory(path, key):
        raise MemoryError("Unable to allocate 7.2 GiB for an array with shape (110000, 3, 128, 128)")

    monkeypatch.setattr(cache_module, "_read", short_of_memory)
    cache = cache_module.TrackCache(config.cache_dir)
    with pytest.warns(CacheWarning, match=r"unreadable now \(MemoryError: Unable to allocate 7\.2 GiB"):
        assert cache.load(stored.stem) is None
    assert stored.is_file() and cache.stats.corrupt == 0 and cache.stats.misses == 1


def test_reading_a_file_holds_one_copy_of_its_arrays(tmp_path):
    """A cache file was read whole into memory and its arrays copied out of those bytes: twice the sequence at the
    peak (14 GB for an hour's 7 GB file, in each DataLoader worker). The arrays are read from the file."""
    import tracemalloc

    n = 120
    sequence = TrackedSequence(
        faces=torch.randint(0, 256, (n, 3, 96, 96), dtype=torch.uint8),
        masks=torch.ones(n, 1, 96, 96, dtype=torch.bool),
        rotation=torch.eye(3).expand(n, 3, 3).clone(), axis_angle=torch.zeros(n, 3), translation=torch.zeros(n, 3),
        ypr_deg=torch.zeros(n, 3), anim_coeffs=torch.zeros(n, 11), expression=torch.zeros(n, 11),
        facs=torch.zeros(n, 11), illumination=torch.zeros(n, 5), confidence=torch.zeros(n),
        status=torch.zeros(n, dtype=torch.int64), shape_coeffs=torch.zeros(14),
        landmarks=torch.zeros(68, 2, dtype=torch.float64), frame_size=(4, 4),
    )  # fmt: skip
    cache = TrackCache(tmp_path)
    size = cache.store("a" * 64, sequence).stat().st_size
    tracemalloc.start()
    try:
        read = cache.load("a" * 64)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert read is not None and torch.equal(read.faces, sequence.faces) and torch.equal(read.masks, sequence.masks)
    assert peak < 1.3 * size, (peak, size)  # (was 2.0 times)
