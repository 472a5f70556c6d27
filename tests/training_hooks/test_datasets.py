"""VideoDataset / FrameFolderDataset: worker-count invariance, known answers against the rendered ground truth,
clips, landmark sources, the transform's equality with the dataset, shuffling, bad input."""

from __future__ import annotations

import copy
import functools
import itertools
import os
import pickle
import re
import sys
import typing
import warnings
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from torchface.geometry.so3 import geodesic_angle_deg
from torchface.io import InputError
from torchface.io.video import NAN_PIXELS_WHY
from torchface.synth.io import read_video, read_video_uint8, write_video
from training_hooks import (
    DatasetConfig,
    FrameFolderDataset,
    NormaliseFaces,
    RepeatedEpochWarning,
    ShortVideoWarning,
    VideoDataset,
    cache_key,
    clip_bounds,
    collate_clips,
    content_hash,
    loader_throughput,
)
from training_hooks.transforms import PER_FRAME_KEYS

from th_data import FRAMES, TRACKING, sideways_clip
from _helpers import lossless_scenario_clip, without_home  # noqa: E402  (the tests folder is on sys.path: th_data puts it there)


def collect(dataset, num_workers: int, key=("video", "frame")) -> dict[tuple[int, ...], dict[str, torch.Tensor]]:
    """Every item of one epoch keyed by (video, first frame)."""
    out = {}
    for item in DataLoader(dataset, batch_size=None, num_workers=num_workers):
        k = (int(item["video"]), int(item["frame"].reshape(-1)[0]))
        assert k not in out, f"item {k} delivered twice"
        out[k] = item
    return out  # insertion order = delivery order


def assert_items_equal(a: dict, b: dict, skip: tuple[str, ...] = ()) -> None:
    assert a.keys() == b.keys()
    for k in a:
        for name in a[k]:
            if name in skip:
                continue
            assert torch.equal(a[k][name], b[k][name]), f"item {k}: {name} differs"


# --------------------------------------------------------------------------------------------- smoke, cardinality


def test_frame_items_shapes_and_types(clips, config):
    data = VideoDataset([c.video for c in clips[:1]], [clips[0].landmarks], replace(config, cache_dir=None))
    items = list(data)
    assert len(items) == FRAMES
    S = TRACKING.face_size
    it = items[0]
    assert set(it) == set(PER_FRAME_KEYS) | {"shape_coeffs", "video", "cached"}
    assert it["face"].shape == (3, S, S) and it["face"].dtype == torch.float32
    assert it["mask"].shape == (1, S, S) and set(it["mask"].unique().tolist()) <= {0.0, 1.0}
    assert it["rotation"].shape == (3, 3) and it["axis_angle"].shape == (3,) and it["ypr_deg"].shape == (3,)
    assert it["anim_coeffs"].shape == (11,) and it["expression"].shape == (11,) and it["illumination"].shape == (5,)
    assert it["confidence"].shape == () and it["success"].dtype == torch.bool and it["status"].dtype == torch.int64
    assert [int(i["frame"]) for i in items] == list(range(FRAMES))
    assert all(int(i["video"]) == 0 and not bool(i["cached"]) for i in items)
    # uint8 storage: faces are multiples of 1/255 in [0, 1], and there is a face (not an empty mask)
    face = items[0]["face"]
    assert torch.equal((face * 255).round() / 255, face) and 0 <= float(face.min()) and float(face.max()) <= 1
    assert float(items[0]["mask"].mean()) > 0.3
    assert data.stats.videos == 1 and data.stats.frames_tracked == FRAMES


# --------------------------------------------------------------------------------------------- feature


def test_known_answer_parameters_follow_the_rendered_frames(clips, config):
    """Each item's pose belongs to ITS frame: the rotation relative to frame 0 matches the ground truth of the same
    frame, far better than that of the neighbouring frame (catches an off-by-one between frames and results)."""
    data = VideoDataset([c.video for c in clips], [c.landmarks for c in clips], replace(config, cache_dir=None))
    items = collect(data, 0)
    for v, clip in enumerate(clips):
        R = torch.stack([items[(v, t)]["rotation"] for t in range(FRAMES)]).double()
        rel, rel_gt = R @ R[:1].mT, clip.gt.rotation @ clip.gt.rotation[:1].mT
        own = geodesic_angle_deg(rel, rel_gt)
        shifted = geodesic_angle_deg(rel[1:], rel_gt[:-1])
        assert float(geodesic_angle_deg(R, clip.gt.rotation).max()) < 2.5
        assert float(own.max()) < 2.0, own
        assert float(own[1:].mean()) < 0.5 * float(shifted.mean()), (own, shifted)
        assert all(bool(items[(v, t)]["success"]) for t in range(FRAMES))
        # Every frame confident by the tracker's own definition (the dissimilarity confidence of template
        # management, whose threshold is TemplateConfig.confidence_threshold; 0.5 was the residual confidence's).
        threshold = config.tracking.tracker.template.confidence_threshold
        assert min(float(items[(v, t)]["confidence"]) for t in range(FRAMES)) > threshold


def test_worker_count_invariance(clips, config):
    """0, 1 and 2 workers give bit-identical items for every (video, frame), and each worker tracks its own
    videos (i % num_workers)."""
    data = VideoDataset([c.video for c in clips], [c.landmarks for c in clips], replace(config, cache_dir=None))
    runs = [collect(data, n) for n in (0, 1, 2)]
    assert len(runs[0]) == len(clips) * FRAMES
    assert_items_equal(runs[0], runs[1])
    assert_items_equal(runs[0], runs[2])
    assert data.worker_videos(0, 2) == [0, 2] and data.worker_videos(1, 2) == [1]
    # with 2 workers the DataLoader alternates: the first item comes from worker 0 (video 0), the next from
    # worker 1 (video 1); worker 0 delivers video 0 then video 2, in time order
    order = list(runs[2])
    assert order[:2] == [(0, 0), (1, 0)]
    assert [k for k in order if k[0] != 1] == [(v, t) for v in (0, 2) for t in range(FRAMES)]


def test_main_process_thread_count_is_restored(clips, config):
    data = VideoDataset([clips[0].video], [clips[0].landmarks], replace(config, cache_dir=None))
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        list(data)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_clips_cover_the_same_frames_as_frame_items(clips, config):
    frames = collect(VideoDataset([clips[0].video], [clips[0].landmarks], config), 0)
    clip_cfg = replace(config, clip_length=4, clip_stride=3, keep_short_clips=True)
    clip_items = list(VideoDataset([clips[0].video], [clips[0].landmarks], clip_cfg))
    assert [i["frame"].tolist() for i in clip_items] == [[0, 1, 2, 3], [3, 4, 5]]
    for item in clip_items:
        for k, t in enumerate(item["frame"].tolist()):
            for name in PER_FRAME_KEYS:
                assert torch.equal(item[name][k], frames[(0, t)][name]), (t, name)
        assert torch.equal(item["shape_coeffs"], frames[(0, 0)]["shape_coeffs"])
    batch = collate_clips(clip_items)
    assert batch["face"].shape[:2] == (2, 4) and batch["frame_mask"].tolist() == [[True] * 4, [True] * 3 + [False]]


def test_clip_bounds():
    assert clip_bounds(6, 4, 3, True) == [(0, 4), (3, 6)]
    assert clip_bounds(6, 4, 3, False) == [(0, 4)]
    assert clip_bounds(8, 4, 2, True) == [(0, 4), (2, 6), (4, 8)]  # the tail is already covered
    assert clip_bounds(3, 5, None, True) == [(0, 3)]
    assert clip_bounds(3, 5, None, False) == []
    assert clip_bounds(0, None, None, True) == []
    assert clip_bounds(10, 3, 5, True) == [(0, 3), (5, 8)]  # a stride past the end starts no clip
    assert clip_bounds(12, 3, 5, True) == [(0, 3), (5, 8), (10, 12)]
    # A length of 0 gave empty clips [(0, 0), (2, 2), ...], -1 frames no clip, a stride of 0 or 1.5 range()'s error.
    for args, name in (((10, 0, 2), "clip_length"), ((10, 4, 0), "stride"), ((-1, 4, 2), "num_frames")):
        with pytest.raises(ValueError, match=name):
            clip_bounds(*args, False)
    # A wrong type is a TypeError (it was a ValueError); numpy integers are taken as ints.
    for args, name in (((10, 4, 1.5), "stride"), ((10, 2.0, None), "clip_length"), ((10.0, 4, 2), "num_frames")):
        with pytest.raises(TypeError, match=name):
            clip_bounds(*args, False)  # type: ignore[arg-type]
    assert clip_bounds(np.int64(6), np.int64(4), np.int32(3), True) == [(0, 4), (3, 6)]  # type: ignore[arg-type]


def test_frame_folder_dataset_equals_video_dataset(clips, config, tmp_path):
    """PNG frames of the same (lossless) video give the same items."""
    folder = tmp_path / "frames_a"
    folder.mkdir()
    for t, img in enumerate(read_video_uint8(clips[0].video)):
        cv2.imwrite(str(folder / f"{t:04d}.png"), img.permute(1, 2, 0).flip(-1).numpy())
    cfg = replace(config, cache_dir=None)
    from_video = collect(VideoDataset([clips[0].video], [clips[0].landmarks], cfg), 0)
    from_folder = collect(FrameFolderDataset([folder], [clips[0].landmarks], cfg), 0)
    assert_items_equal(from_video, from_folder)


def test_landmark_sources_agree(clips, config, tmp_path):
    """A (68, 2) array, a tensor, a CSV file, an NPY file and a detector callable give the same items."""
    clip = clips[1]
    csv, npy = tmp_path / "lm.csv", tmp_path / "lm.npy"
    np.savetxt(csv, clip.landmarks, delimiter=",", header="x,y", comments="", fmt="%.17g")
    np.save(npy, clip.landmarks)
    seen = []

    def detector(image: np.ndarray) -> np.ndarray:
        seen.append(image.shape)
        assert image.dtype == np.uint8 and image.shape == (128, 128, 3)
        return clip.landmarks

    cfg = replace(config, cache_dir=None)
    ref = collect(VideoDataset([clip.video], [clip.landmarks], cfg), 0)
    for source in ([torch.from_numpy(clip.landmarks)], [csv], [str(npy)], detector):
        assert_items_equal(ref, collect(VideoDataset([clip.video], source, cfg), 0))
    assert len(seen) == 1


#: Points left out (NaN rows) in the missing-point tests: the right jaw and the right eye's corners.
MISSING = [0, 1, 2, 3, 4, 5, 6, 7, 36, 39]


def _with_missing(landmarks: np.ndarray, rows=MISSING) -> np.ndarray:
    partial = np.array(landmarks, dtype=np.float64)
    partial[rows] = np.nan
    return partial


def test_missing_landmark_points_track_as_the_trackers_python_api(clips, config, tmp_path):
    """``torchface track`` and ``FaceTracker.initialise`` take first-frame landmarks with missing points (NaN rows,
    weight 0 in the fit), the dataset and its transform refused them ("landmarks must be finite"; a file "are NaN or
    infinite"). Now an array, a tensor, an NPY file and a CSV with empty cells, given to VideoDataset, and the
    array given to NormaliseFaces, track as FaceTracker does from the same NaN rows: first-frame pose equal to float
    tolerance, every later frame's too; and a second epoch reads the cache."""
    from torchface.tracker import FaceTracker
    from training_hooks.transforms import torch_threads

    clip = clips[0]
    partial = _with_missing(clip.landmarks)
    frames = read_video(clip.video)
    tracker = FaceTracker(TRACKING.tracker, refine_first=TRACKING.refine_first)
    with torch_threads(TRACKING.num_threads):
        results = [tracker.initialise(frames[:1], torch.from_numpy(partial).float()[None])]
        results += [tracker(frames[t : t + 1]) for t in range(1, FRAMES)]
    rotation = torch.cat([r.rotation for r in results]).float()
    translation = torch.cat([r.translation for r in results]).float()
    npy, csv = tmp_path / "partial.npy", tmp_path / "partial.csv"
    np.save(npy, partial)
    lines = ["x,y"] + [",".join("" if np.isnan(v) else repr(float(v)) for v in row) for row in partial]
    csv.write_text("\n".join(lines) + "\n")
    cfg = replace(config, cache_dir=None)
    full = collect(VideoDataset([clip.video], [clip.landmarks], cfg), 0)
    ref = collect(VideoDataset([clip.video], [partial], cfg), 0)
    for k in range(FRAMES):
        item = ref[(0, k)]
        assert torch.allclose(item["rotation"], rotation[k], atol=1e-5), k
        assert torch.allclose(item["translation"], translation[k], atol=1e-3), k
    # (the points were left out of the fit: the first pose is not that of all 68)
    assert not torch.allclose(full[(0, 0)]["translation"], ref[(0, 0)]["translation"], atol=1e-3)
    for source in ([torch.from_numpy(partial)], [npy], [str(csv)]):
        assert_items_equal(ref, collect(VideoDataset([clip.video], source, cfg), 0))
    out = NormaliseFaces(TRACKING)(frames, partial)
    whole = next(iter(VideoDataset([clip.video], [partial], replace(cfg, clip_length=FRAMES))))
    for name in out:
        assert torch.equal(out[name], whole[name]), name
    cached = VideoDataset([clip.video], [npy], config)
    assert_items_equal(ref, collect(cached, 0), skip=("cached",))
    again = collect(VideoDataset([clip.video], [partial], config), 0)  # (the file's and the array's key: one entry)
    assert all(bool(item["cached"]) for item in again.values())
    assert_items_equal(ref, again, skip=("cached",))
    assert VideoDataset([clip.video], [csv], config)._cached_frames(0) == FRAMES  # counted from the cache


def test_landmarks_with_too_few_points_half_nan_rows_or_infinite_values_are_refused(clips, config, tmp_path):
    """The command line's rules for missing points (torchface.io.check_landmarks): at least MIN_FIT_LANDMARKS (4)
    given, no row with one coordinate NaN, no infinite value; one-line errors naming the video (an array) or the file,
    and the transform's ValueError saying the same."""
    clip = clips[0]
    cfg = replace(config, cache_dir=None)
    few = np.full((68, 2), np.nan)
    few[[30, 36, 45]] = clip.landmarks[[30, 36, 45]]
    half = np.array(clip.landmarks)
    half[[12, 40], 0] = np.nan
    inf = np.array(clip.landmarks)
    inf[50, 1] = np.inf
    cases = [
        (few, r"3 of the 68 iBUG points given, the others missing \(NaN\): the landmark fit needs at least 4"),
        (half, r"landmark\(s\) \[12, 40\] have one coordinate NaN \(a missing point has neither\): mark a missing "
               r"point with both coordinates NaN \(a NaN row\); one coordinate alone is most likely a bug upstream "
               r"\(a column lost or shifted\)"),
        (inf, r"landmark\(s\) \[50\] are infinite \(a missing point is a NaN row\): most likely a bug upstream \(a "
              r"division by zero, an overflow\)"),
    ]
    frames = read_video(clip.video)[:2]
    for i, (points, message) in enumerate(cases):
        npy = tmp_path / f"bad{i}.npy"
        np.save(npy, points)
        with pytest.raises(InputError, match=rf"^{re.escape(str(clip.video))}: landmarks: {message}$"):
            list(VideoDataset([clip.video], [points], cfg))
        with pytest.raises(InputError, match=rf"^{re.escape(str(npy))}: {message}$"):
            list(VideoDataset([clip.video], [npy], cfg))
        # (known without decoding: checked for the cache key)
        with pytest.raises(InputError, match=rf"^{re.escape(str(clip.video))}: landmarks: {message}$"):
            VideoDataset([clip.video], [torch.from_numpy(points)], config).sequence(0)
        with pytest.raises(ValueError, match=rf"^landmarks: {message}$"):
            NormaliseFaces(TRACKING)(frames, points)
    # A wrong count: an array is told a missing point stays a NaN row, not about a file's empty cells or 'nan nan'
    short = re.escape("expected 68 iBUG landmarks, got 67 (a missing point stays, as a NaN row)")
    with pytest.raises(InputError, match=rf"^{re.escape(str(clip.video))}: landmarks: {short}$"):
        list(VideoDataset([clip.video], [np.array(clip.landmarks)[:67]], cfg))
    # MediaPipe's 478 face mesh points: told which points are wanted (it said a missing point stays a NaN row)
    mesh = re.escape("expected 68 iBUG landmarks, got 478 (MediaPipe's face mesh points? The 68 iBUG")
    with pytest.raises(InputError, match=rf"^{re.escape(str(clip.video))}: landmarks: {mesh}"):
        VideoDataset([clip.video], [np.full((478, 2), 50.0)], cfg)
    wflw = re.escape("expected 68 iBUG landmarks, got 98 (WFLW's 98 points? The 68 iBUG")  # (was the NaN row's rule)
    with pytest.raises(InputError, match=rf"^{re.escape(str(clip.video))}: landmarks: {wflw}"):
        VideoDataset([clip.video], [np.full((98, 2), 50.0)], cfg)
    four = np.full((68, 2), np.nan)
    four[[30, 36, 45, 48]] = clip.landmarks[[30, 36, 45, 48]]
    assert len(list(VideoDataset([clip.video], [four], cfg))) == FRAMES  # (the fit's minimum: tracked)


def test_detector_landmarks_at_the_frame_edge_are_taken_from_the_cache_too(clips, config):
    """A detector's landmarks may lie partly outside the frame (dlib's chin), and were taken when tracked, but a
    later epoch in the same process, reading the cache, checked them as a file's (all inside): "1 landmark(s)
    outside the 128x128 frame"."""
    clip = clips[0]
    edge = np.array(clip.landmarks, dtype=np.float64)
    edge[7:10, 1] = 129.0
    data = VideoDataset([clip.video], lambda image: edge, config)
    first = collect(data, 0)
    second = collect(data, 0)
    assert all(bool(item["cached"]) for item in second.values())
    assert_items_equal(first, second, skip=("cached",))


def test_transform_equals_dataset_output(clips, config):
    """NormaliseFaces on the decoded frames and landmarks equals the dataset's whole-video clip; continuing from
    a TrackerState equals tracking the whole sequence in one go."""
    clip = clips[2]
    frames = read_video(clip.video)
    normalise = NormaliseFaces(TRACKING)
    out = normalise(frames, clip.landmarks)
    item = next(iter(VideoDataset([clip.video], [clip.landmarks], replace(config, clip_length=FRAMES))))
    for name in out:
        assert torch.equal(out[name], item[name]), name
    # uint8 frames are accepted too
    out8 = normalise(read_video_uint8(clip.video), torch.from_numpy(clip.landmarks))
    assert torch.equal(out8["face"], out["face"])
    # continue from the state after 3 frames
    head, state = normalise.track(frames[:3], clip.landmarks)
    tail = normalise(frames[3:], state)
    assert tail["face"].shape[0] == FRAMES - 3
    assert torch.equal(tail["face"], out["face"][3:]) and torch.equal(tail["axis_angle"], out["axis_angle"][3:])
    assert torch.equal(head.faces.float() / 255, out["face"][:3])


def test_landmarks_and_frames_in_any_memory_layout_give_the_same_items(clips, config):
    """Landmarks as a NumPy view with a negative stride (``yx[:, ::-1]``, points read as (y, x) and turned round),
    given to NormaliseFaces or VideoDataset, and frames as strided or channels-last views: the items of the plain
    arrays (the landmarks were "At least one stride in the given numpy array is negative" from torch.tensor)."""
    clip = clips[2]
    frames = read_video(clip.video)[:3]
    yx = np.ascontiguousarray(clip.landmarks[:, ::-1])
    turned = yx[:, ::-1]  # the (x, y) points, as a view with a negative stride
    assert turned.strides[1] < 0 and np.array_equal(turned, clip.landmarks)
    normalise = NormaliseFaces(TRACKING)
    want = normalise(frames, clip.landmarks)
    views = {
        "landmarks": (frames, turned),
        "channels_last frames": (frames.contiguous(memory_format=torch.channels_last), clip.landmarks),
        "strided frames": (torch.stack([frames, frames], -1)[..., 1], clip.landmarks),
    }
    for name, (f, lm) in views.items():
        got = normalise(f, lm)
        for key in want:
            assert torch.equal(got[key], want[key]), (name, key)
    item = next(iter(VideoDataset([clip.video], [turned], replace(config, cache_dir=None))))
    plain = next(iter(VideoDataset([clip.video], [clip.landmarks], replace(config, cache_dir=None))))
    for key in plain:
        assert torch.equal(item[key], plain[key]), key


def test_a_continued_sequence_numbers_its_frames_on(clips, tmp_path):
    """Frames that continue a TrackerState are frames ``frame_index ..`` of the sequence: a video tracked in two
    parts gives the items of one tracking, ``frame`` included (the second part said 0, 1, 2: per-frame labels
    looked up by ``frame`` were the first part's), and the cache keeps the numbering."""
    from training_hooks import TrackCache

    clip = clips[2]
    frames = read_video(clip.video)
    normalise = NormaliseFaces(TRACKING)
    whole = normalise(frames, clip.landmarks)
    head, state = normalise.track(frames[:3], clip.landmarks)
    parts = [head.item(slice(0, 3)), normalise(frames[3:], state)]
    assert parts[1]["frame"].tolist() == [3, 4, 5]
    for name in whole:
        if name != "shape_coeffs":
            assert torch.equal(torch.cat([p[name] for p in parts]), whole[name]), name
    tail, _ = normalise.track(frames[3:], state)
    assert head.first_frame == 0 and tail.first_frame == 3 == state.frame_index
    assert [int(tail.item(t)["frame"]) for t in range(FRAMES - 3)] == [3, 4, 5]
    cache = TrackCache(tmp_path / "cache")
    cache.store("a" * 64, tail)
    assert cache.load("a" * 64).first_frame == 3


def test_continuing_a_state_leaves_it_as_it_was():
    """NormaliseFaces (track_sequence) continuing a caller's TrackerState leaves it as it was: the same frames from
    the same state give the same items twice, and those of a copy of it. Its first steps handed the state to
    managed_step as donated, which writes a new mosaic entry's templates into the state's own tensors: on a head
    turning to 55 degrees, a second call from the state was 0.027 rad (1.5 degrees) off the first."""
    import copy

    from torchface.synth.sequence import render_sequence

    from th_data import gentle

    frames, gt = render_sequence(gentle("turn", "james", (55.0, 0.0, 0.0), (0.0, 0.0, 0.0), {}, seed=3, num_frames=12))
    frames = frames.float()
    normalise = NormaliseFaces(TRACKING)
    _, state = normalise.track(frames[:4], gt.landmarks_px[0].numpy())
    fork = copy.deepcopy(state)
    first = normalise(frames[4:], state)
    assert int(first["status"].max()) < 2  # (tracked throughout)
    again, of_fork = normalise(frames[4:], state), normalise(frames[4:], fork)
    for name in first:
        assert torch.equal(again[name], first[name]), name
        assert torch.equal(of_fork[name], first[name]), name


def test_a_state_of_another_dtype_is_refused_naming_the_transforms_model(clips):
    """NormaliseFaces continuing a float64 FaceTracker's state said "track a state with the model in the dtype and
    device it was initialised with (or initialise again)": the model is the transform's own, float32 CANDIDE-3,
    which its user does not hold. The message says so, and what to continue instead."""
    from torchface.tracker import FaceTracker

    clip = clips[2]
    frames = read_video(clip.video)[:2]
    tracker = FaceTracker(TRACKING.tracker, refine_first=None).double()
    tracker.initialise(frames[:1], torch.from_numpy(clip.landmarks)[None])
    with pytest.raises(TypeError, match=r"TrackerState to continue is torch.float64 .* torch.float32 model .*"
                                        r"NormaliseFaces.*FaceTracker left in torch.float32"):
        NormaliseFaces(TRACKING)(frames[1:], tracker.state)


def test_a_state_is_continued_with_the_levels_pyramid_auto_added_and_no_more(clips):
    """NormaliseFaces (track_sequence) continuing a state with ``pyramid="auto"`` made any config up to the state's
    levels: a FaceTracker's 2-level state (small faces: "auto" added none), or its own, continued with a config of
    1 level was tracked with 2, the coarsest's iterations repeated, without a word. As the tracker does
    (``torchface.tracker.module.continuing_config``), only the levels its start added are added back: refused."""
    from torchface.tracker import FaceTracker

    clip = clips[2]
    frames = read_video(clip.video)[:3]
    tracker = FaceTracker(TRACKING.tracker, refine_first=None)
    tracker.initialise(frames[:1], torch.from_numpy(clip.landmarks)[None])
    _, own = NormaliseFaces(TRACKING).track(frames[:1], clip.landmarks)
    fewer = replace(TRACKING, tracker=replace(TRACKING.tracker, num_levels=1, iterations=(6,)))
    for state in (tracker.state, own):
        assert state.num_levels == 2
        with pytest.raises(ValueError, match="the state holds templates for 2 pyramid levels, the config has "
                                             "num_levels = 1"):  # fmt: skip
            NormaliseFaces(fewer)(frames[1:], state)
    assert NormaliseFaces(TRACKING)(frames[1:], own)["face"].shape[0] == 2


def test_shuffle_buffer_permutes_but_keeps_items(clips, config):
    videos, lms = [c.video for c in clips], [c.landmarks for c in clips]
    plain = collect(VideoDataset(videos, lms, config), 0)  # fills the cache
    shuffled = VideoDataset(videos, lms, replace(config, shuffle_buffer=8, seed=5))
    order = lambda: [(int(i["video"]), int(i["frame"])) for i in shuffled]  # noqa: E731
    first = order()
    with pytest.warns(RepeatedEpochWarning):  # (no set_epoch between: the same order, told)
        again = order()
    assert first == again and sorted(first) == sorted(plain)
    assert first != sorted(first)
    shuffled.set_epoch(1)
    assert order() != first
    assert_items_equal(plain, collect(shuffled, 2), skip=("cached",))


def test_set_epoch_reaches_persistent_workers(clips, config):
    """persistent_workers=True: the workers kept the epoch of the dataset they were started with, so every epoch
    was shuffled as the first. Now they share the dataset's epoch: each epoch's order is the one the dataset gives
    in the main process for that epoch (1 worker: the same seeds)."""
    videos, lms = [c.video for c in clips], [c.landmarks for c in clips]
    collect(VideoDataset(videos, lms, config), 0)  # fills the cache
    shuffled = VideoDataset(videos, lms, replace(config, shuffle_buffer=8, seed=5))
    expected = []
    for epoch in range(2):
        shuffled.set_epoch(epoch)
        expected.append([(int(i["video"]), int(i["frame"])) for i in shuffled])
    assert expected[0] != expected[1]
    loader = DataLoader(shuffled, batch_size=None, num_workers=1, persistent_workers=True)
    for epoch in range(2):
        shuffled.set_epoch(epoch)
        assert [(int(i["video"]), int(i["frame"])) for i in loader] == expected[epoch]


def _orders(data: VideoDataset, loader, epochs, capfd) -> tuple[list[list[tuple[int, int]]], list[str]]:
    """Each epoch's order of ``loader`` (a ``DataLoader`` over ``data``, batch_size=None), ``epochs`` giving the
    ``set_epoch`` before each (None: none), and the RepeatedEpochWarning lines its processes wrote to stderr (the
    workers' warnings go there, and this process's, written there as the workers write them)."""
    capfd.readouterr()
    orders = []
    with warnings.catch_warnings():
        warnings.simplefilter("always")  # (forked workers keep the filter and the writer to stderr)
        warnings.showwarning = lambda message, category, *args, **kwargs: print(f"{category.__name__}: {message}",
                                                                                file=sys.stderr, flush=True)
        for epoch in epochs:
            if epoch is not None:
                data.set_epoch(epoch)
            orders.append([(int(i["video"]), int(i["frame"])) for i in loader])
    told = [line for line in capfd.readouterr().err.splitlines() if "RepeatedEpochWarning" in line]
    return orders, told


def test_a_forgotten_set_epoch_is_told_once(clips, config, capfd):
    """A plain loop that forgot ``data.set_epoch(epoch)`` iterated a shuffled dataset in the same order every epoch
    without a word (documented only). The second iteration begun with no ``set_epoch`` since the last, shuffled, is
    a RepeatedEpochWarning naming the fix, once per dataset: in this process (num_workers=0), and from DataLoader
    worker 0 (two forked workers, started anew each epoch or persistent: the record is in the dataset's shared
    memory). Not told: a ``set_epoch`` before each epoch (the same epoch too: the order wanted again), a dataset
    without shuffling, and the first iteration of a deep or pickled copy (independent datasets)."""
    videos, lms = [c.video for c in clips], [c.landmarks for c in clips]
    collect(VideoDataset(videos, lms, config), 0)  # fills the cache
    shuffled = replace(config, shuffle_buffer=8, seed=5)
    for workers, persistent in ((0, False), (2, False), (2, True)):
        data = VideoDataset(videos, lms, shuffled)
        loader = DataLoader(data, batch_size=None, num_workers=workers, persistent_workers=persistent,
                            multiprocessing_context="fork" if workers else None)  # fmt: skip
        orders, told = _orders(data, loader, [None, None, None], capfd)
        assert orders[0] == orders[1] == orders[2]
        assert len(told) == 1, (workers, persistent, told)  # (the second epoch; not again at the third)
        assert "set_epoch(epoch) before each epoch" in told[0] and "TrackedFaceDataModule" in told[0]
        again = VideoDataset(videos, lms, shuffled)  # set_epoch before each epoch: never told
        loader = DataLoader(again, batch_size=None, num_workers=workers, persistent_workers=persistent,
                            multiprocessing_context="fork" if workers else None)  # fmt: skip
        orders, told = _orders(again, loader, [0, 1, 1, 1], capfd)  # (1 again: the same order, deliberately)
        assert orders[0] != orders[1] == orders[2] == orders[3] and told == [], (workers, persistent, told)
    plain = VideoDataset(videos, lms, config)  # no shuffling: the same order is the design, never told
    assert _orders(plain, plain, [None, None], capfd)[1] == []
    data = VideoDataset(videos, lms, shuffled)
    assert _orders(data, data, [None], capfd)[1] == []
    for copied in (copy.deepcopy(data), pickle.loads(pickle.dumps(data))):  # independent: not iterated yet
        assert _orders(copied, copied, [None], capfd)[1] == []
        assert len(_orders(copied, copied, [None], capfd)[1]) == 1  # (their own second iteration)
    shallow = copy.copy(data)  # (shares the dataset's state: its iteration repeats the dataset's)
    assert len(_orders(shallow, shallow, [None], capfd)[1]) == 1
    assert _orders(data, data, [None], capfd)[1] == []  # (told once per dataset: the copy.copy was the dataset)
    quiet = VideoDataset(videos, lms, shuffled)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for _ in range(2):  # (a measurement, not an epoch: neither told nor telling the next iteration)
            loader_throughput(quiet, 0)
        list(quiet)
        warnings.filterwarnings("ignore", category=RepeatedEpochWarning)  # the standard filter silences it
        list(quiet)


def test_a_forgotten_set_epoch_is_told_by_a_spawned_worker(clips, config, capfd):
    """A spawned DataLoader worker, started anew each epoch, receives the dataset pickled by multiprocessing (its
    shared memory by reference, not by value as a plain pickle's copy): the record it finds is the dataset's, and
    the second epoch with no set_epoch is told (on the worker's stderr, by the default filter)."""
    videos, lms = [c.video for c in clips[:2]], [c.landmarks for c in clips[:2]]
    collect(VideoDataset(videos, lms, config), 0)  # fills the cache
    data = VideoDataset(videos, lms, replace(config, shuffle_buffer=8, seed=5))
    loader = DataLoader(data, batch_size=None, num_workers=1, multiprocessing_context="spawn")
    orders, told = _orders(data, loader, [None, None], capfd)
    assert orders[0] == orders[1] and len(told) == 1 and "data.set_epoch(epoch)" in told[0]


def test_a_deep_copy_is_an_independent_dataset_whose_workers_share_its_state(clips, config, tmp_path):
    """copy.deepcopy(data) (a validation copy, a framework copying its datasets) gave the copy its state out of
    shared memory: its forked DataLoader workers each changed a private copy (a persistent worker missed every
    set_epoch, each worker counted and warned again). The copy is now an independent dataset in shared memory of
    its own: it starts from the original's state (epoch, counts), its processes share it with it, and neither it
    nor the original sees the other's later changes. copy.copy shares the original's state, as before."""
    import multiprocessing

    from training_hooks.datasets import _COUNTS

    videos = [tmp_path / f"v{i}.npy" for i in range(3)]  # (.npy: no decoder whose threads a fork would hang)
    for path in videos:
        np.save(path, np.zeros((FRAMES, 32, 32, 3), np.uint8))
    data = VideoDataset(videos, [c.landmarks for c in clips], replace(config, cache_dir=None, clip_length=FRAMES + 1))
    data.set_epoch(2)
    data.num_items(0)  # (counted before the copy: the copy keeps it)
    copied = copy.deepcopy(data)
    assert copied._shared.is_shared() and copied._frames.is_shared() and copied._claims is not data._claims
    assert copied.epoch == 2 and copied._shared[_COUNTS:].tolist() == [0, -1, -1]
    copied.set_epoch(5)
    assert data.epoch == 2
    log = tmp_path / "warnings.txt"

    def count() -> None:  # (a forked DataLoader worker of the copy, counting its videos)
        warnings.simplefilter("ignore")
        warnings.simplefilter("always", UserWarning)
        warnings.showwarning = lambda message, category, *args, **kwargs: log.write_text(category.__name__)
        assert copied.count_items() == [0, 0, 0] and copied.epoch == 5

    process = multiprocessing.get_context("fork").Process(target=count)
    process.start()
    process.join(30)
    assert process.exitcode == 0 and log.read_text() == "ShortVideoWarning"
    assert copied._shared[_COUNTS:].tolist() == [0, 0, 0] and int(copied._frames[0]) == 1  # (seen by the copy)
    assert data._shared[_COUNTS:].tolist() == [0, -1, -1] and int(data._frames[0]) == 0  # (not by the original)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert copied.count_items() == [0, 0, 0]  # (the copy's warning given: by its worker)
    with pytest.warns(ShortVideoWarning):
        assert data.count_items() == [0, 0, 0]  # (the original's own)
    shallow = copy.copy(data)
    shallow.set_epoch(7)
    assert data.epoch == 7 and shallow._shared is data._shared and shallow._claims is data._claims
    received = pickle.loads(pickle.dumps(data))  # a plain pickle: independent too, in shared memory of its own
    assert received._shared.is_shared() and received._claims.folder != data._claims.folder
    received.set_epoch(8)
    assert data.epoch == 7


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="a process's start is read from Linux's /proc")
def test_a_killed_processs_dataset_folder_is_removed_by_the_next_dataset(tmp_path, monkeypatch):
    """A dataset's private folder of once-only warning markers (``torchface-dataset-*``, in the temporary folder) is
    removed with it or at its process's exit; a process killed by SIGKILL left it, one more in /tmp per killed
    training run. Its name now records its maker (boot, pid namespace, pid, start), and a new dataset removes those
    whose maker is certainly gone: a subprocess killed and reaped, or a pid now another process's (a later start).
    It leaves those of live processes (a running subprocess, this one), of another boot or pid namespace (another
    machine's or container's sharing the folder: not known here), without a recorded maker (an older torchface's),
    another user's, and what is not a folder; and a failing cleanup does not fail the dataset."""
    import subprocess
    import sys
    import tempfile

    from training_hooks import datasets

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # (where mkdtemp makes the dataset's folder)
    boot, namespace, me, my_start = datasets._claims_owner()
    sleep = [sys.executable, "-c", "import time; time.sleep(60)"]
    dead, live = subprocess.Popen(sleep), subprocess.Popen(sleep)
    try:
        dead_start, live_start = datasets._process_start(dead.pid), datasets._process_start(live.pid)
        dead.kill()
        dead.wait(30)  # (reaped: a zombie's pid still shows its start, and its folder waits for the next dataset)

        def name(pid: int, start: int, of_boot: str = boot, of_namespace: int = namespace) -> str:
            return f"torchface-dataset-{of_boot}-{of_namespace}-{pid}-{start}-ab_c12Z9"

        stale = [name(dead.pid, dead_start), name(live.pid, live_start - 1)]  # (the second: its pid reused since)
        kept = [name(live.pid, live_start), name(me, my_start), name(dead.pid, dead_start, "0" * 32),
                name(dead.pid, dead_start, of_namespace=namespace + 1), "torchface-dataset-k2j4x_9q"]
        for folder in stale + kept:
            (tmp_path / folder).mkdir()
            (tmp_path / folder / "short-videos").touch()  # (a marker: not empty)
        (tmp_path / name(dead.pid, dead_start).replace("ab_c", "ab_d")).touch()  # (a file: not a dataset's folder)
        (tmp_path / name(dead.pid, dead_start).replace("ab_c", "ab_e")).symlink_to(tmp_path / kept[0])
        monkeypatch.setattr(os, "geteuid", lambda: os.getuid() + 1)  # (another user: none of its folders)
        assert datasets._remove_stale_claims(str(tmp_path), datasets._claims_owner()) == []
        monkeypatch.undo()
        monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
        video = tmp_path / "v.npy"
        np.save(video, np.zeros((FRAMES, 32, 32, 3), np.uint8))
        before = {p.name for p in tmp_path.iterdir()}
        points = np.random.default_rng(0).uniform(4.0, 28.0, (68, 2))
        data = VideoDataset([video], [points], DatasetConfig(tracking=TRACKING))
        after = {p.name for p in tmp_path.iterdir()}
        mine = Path(data._claims.folder).name
        assert after == before - set(stale) | {mine} and mine.startswith(name(me, my_start)[:-9])
    finally:
        live.kill()
        live.wait(30)
    monkeypatch.setattr(datasets, "_remove_stale_claims", lambda *args: 1 / 0)
    monkeypatch.setattr(datasets, "_SCANNED", set())  # (this process scanned tmp_path above: scan it again)
    assert os.path.isdir(datasets._Claims().folder)  # (its cleanup failed: the dataset's folder made all the same)
    assert datasets._SCANNED == {(os.getpid(), str(tmp_path))}  # (failed: not tried again at every dataset)


@pytest.mark.skipif(not hasattr(os, "fork") or not os.path.isdir("/proc/self"),
                    reason="a process's start is read from Linux's /proc; a forked process")
def test_the_stale_folder_cleanup_scans_a_temporary_folder_once_a_process(tmp_path, monkeypatch):
    """The cleanup of killed processes' dataset folders scanned the temporary folder at every dataset made (its
    copies, a worker's pickle: 0.4-0.65 ms each with a few hundred entries in /tmp); now at a process's first
    dataset in that folder, and again at the first in another folder or in a forked process (another pid)."""
    import tempfile

    from training_hooks import datasets

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setattr(datasets, "_SCANNED", set())
    scans: list[tuple[int, str]] = []
    scan = datasets._remove_stale_claims
    monkeypatch.setattr(datasets, "_remove_stale_claims",
                        lambda folder, owner: scans.append((os.getpid(), folder)) or scan(folder, owner))  # fmt: skip
    kept = [datasets._Claims(), datasets._Claims(), copy.deepcopy(datasets._Claims())]
    assert scans == [(os.getpid(), str(tmp_path))] and all(os.path.isdir(c.folder) for c in kept)
    (tmp_path / "other").mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "other"))
    kept += [datasets._Claims(), datasets._Claims()]
    assert scans[1:] == [(os.getpid(), str(tmp_path / "other"))]
    read, write = os.pipe()
    child = os.fork()
    if child == 0:  # (a DataLoader worker making a dataset: its own first scan, once)
        try:
            datasets._Claims(), datasets._Claims()
            os.write(write, repr(scans).encode())
        finally:
            os._exit(0)
    os.close(write)
    with os.fdopen(read) as f:
        seen = f.read()
    os.waitpid(child, 0)
    assert seen == repr([*scans, (child, str(tmp_path / "other"))])


@pytest.mark.skipif(not hasattr(os, "geteuid"), reason="folders are told apart by their owner (POSIX)")
def test_a_folder_of_a_process_given_a_dead_makers_pid_during_a_cleanup_is_kept(tmp_path, monkeypatch):
    """The cleanup reads a pid's start once per scan of the folder; a folder listed after that read may be that of
    a process given the pid since (which read its own start before it made the folder): it was removed with the dead
    maker's, a live dataset's markers gone. Now a start that says "gone" is read again before a folder is removed."""
    from training_hooks import datasets

    boot, namespace, pid = "ab" * 16, 4026531836, 4321
    old, new = (f"torchface-dataset-{boot}-{namespace}-{pid}-{start}-x1" for start in (100, 900))
    for folder in (old, new):
        (tmp_path / folder).mkdir()
    reads = itertools.chain([None], itertools.repeat(900))  # (no such pid at the first read, then one started at 900)
    monkeypatch.setattr(datasets, "_process_start", lambda _: next(reads))
    assert datasets._remove_stale_claims(str(tmp_path), (boot, namespace, 1, 1)) == [old]
    assert [p.name for p in tmp_path.iterdir()] == [new]


# --------------------------------------------------------------------------------------------- exceptions


def test_bad_arguments(clips, tmp_path):
    video, lm = clips[0].video, clips[0].landmarks
    with pytest.raises(ValueError, match="one entry per video"):
        VideoDataset([video, video], [lm])
    with pytest.raises(TypeError, match="sequence with one"):
        VideoDataset([video], lm)
    with pytest.raises(ValueError, match="FrameFolderDataset"):
        VideoDataset([tmp_path], [lm])
    # a folder of videos: told to give the files (it was told to use FrameFolderDataset, which found no images there)
    (tmp_path / "videos").mkdir()
    for name in ("b.mpg", "a.mpg"):
        (tmp_path / "videos" / name).write_bytes(b"")
    with pytest.raises(ValueError, match=r"videos: VideoDataset takes video files or \.npy arrays, not a folder but 2 "
                       r"videos \(a\.mpg, b\.mpg\): .*give the files, one entry per video \(.*videos/\*\.mpg\)$"):
        VideoDataset([tmp_path / "videos"], [lm])
    (tmp_path / "videos" / "0001.png").write_bytes(b"")  # frames beside them: FrameFolderDataset (not "give the files")
    with pytest.raises(ValueError, match=r"videos: VideoDataset .*\(use FrameFolderDataset for folders of frames\)$"):
        VideoDataset([tmp_path / "videos"], [lm])
    with pytest.raises(ValueError, match="VideoDataset"):
        FrameFolderDataset([video], [lm])
    # a mistyped path: said so (it was told to use the other dataset, "takes folders of frames", or the other way round)
    for dataset, missing in ((VideoDataset, tmp_path / "typo.avi"), (FrameFolderDataset, tmp_path / "typo")):
        with pytest.raises(InputError, match=r"typo(\.avi)?: no such file or folder$"):
            dataset([missing], [lm])
    (tmp_path / "gone.avi").symlink_to(tmp_path / "moved.avi")
    with pytest.raises(InputError, match=r"gone\.avi: no such file or folder \(a symbolic link to a missing target\)"):
        VideoDataset([tmp_path / "gone.avi"], [lm])
    # "~" is not expanded (made absolute against the working folder): the message says so, for a landmarks file too
    tilde = r" \('~' is not expanded here: os\.path\.expanduser\(path\) names the home folder\)$"
    with pytest.raises(InputError, match=r"/~/no_such_r3\.avi: no such file or folder" + tilde):
        VideoDataset(["~/no_such_r3.avi"], [lm])
    with pytest.raises(InputError, match=r"landmarks: ~/no_such_r3\.csv: no such landmarks file" + tilde):
        VideoDataset([video], ["~/no_such_r3.csv"])
    with pytest.raises(InputError, match=r"/~torchface-no-such-user\.avi: no such file or folder$"):  # (not a home)
        VideoDataset(["~torchface-no-such-user.avi"], [lm])
    with pytest.raises(InputError, match=r"/~/no_such_r3\.avi: no such file or folder$"):  # (a '~' further on: as
        VideoDataset([tmp_path / "~" / "no_such_r3.avi"], [lm])  # a shell, expanduser leaves it; it gave the hint)
    with pytest.raises(ValueError, match="empty"):
        VideoDataset([], [])
    with pytest.raises(ValueError, match="clip_stride needs clip_length"):
        DatasetConfig(clip_stride=2)
    with pytest.raises(ValueError, match="clip_length"):
        DatasetConfig(clip_length=0)
    with pytest.raises(TypeError, match="FaceTrackingConfig"):
        DatasetConfig(tracking="fast")
    for after, error in (("5", TypeError), (True, TypeError), (-1.0, ValueError), (float("nan"), ValueError)):
        with pytest.raises(error, match=r"progress_after must be a .* or None"):
            DatasetConfig(progress_after=after)
    (tmp_path / "cache").write_text("a file")  # refused at once (it failed after the first video was tracked)
    with pytest.raises(ValueError, match="not a folder"):
        VideoDataset([video], [lm], DatasetConfig(cache_dir=tmp_path / "cache"))
    # a cache_dir inside a file: refused at once too (a NotADirectoryError after the first video was tracked)
    with pytest.raises(ValueError, match=r"/cache/runs: cache_dir is inside .*/cache, which is not a folder$"):
        VideoDataset([video], [lm], DatasetConfig(cache_dir=tmp_path / "cache" / "runs"))


def test_a_missing_path_starting_with_an_unexpandable_tilde_is_told_so(tmp_path, monkeypatch):
    """With ``HOME`` unset and no password entry (a container run as an uid without one), ``os.path.expanduser``
    leaves ``~/x`` as it is, and a missing ``~/x`` was told nothing of the ``~`` (its own look at each part asked
    ``expanduser``); it is told what the path settings' check says (:func:`torchface._paths.unexpanded_home`)."""
    without_home(monkeypatch)
    monkeypatch.chdir(tmp_path)
    lm = np.zeros((68, 2), np.float32)
    hint = (r" \('~' is not expanded here, and os\.path\.expanduser cannot expand it here \(HOME is not set and the "
            r"password database has no entry for this user\): give the home folder's path\)$")
    with pytest.raises(InputError, match=r"/~/no_such\.avi: no such file or folder" + hint):
        VideoDataset(["~/no_such.avi"], [lm])
    (tmp_path / "clip").mkdir()
    with pytest.raises(InputError, match=r"landmarks: ~/no_such\.csv: no such landmarks file" + hint):
        FrameFolderDataset([tmp_path / "clip"], ["~/no_such.csv"])


def test_a_gray_array_is_told_how_to_save_it_as_rgb_not_an_ffmpeg_command(clips, config, tmp_path):
    """A grayscale ``.npy`` clip was told to convert it with ffmpeg (``-i in.mp4``), a video file's remedy: an array
    is told how to save it as the reader takes it, and that fix reads (and ``DatasetConfig(convert=True)`` still)."""
    gray = read_video_uint8(clips[0].video).float().mean(1).round().to(torch.uint8).numpy()  # (T, H, W)
    np.save(tmp_path / "gray.npy", gray)
    np.save(tmp_path / "gray1.npy", gray[:, :-1, :, None])  # (T, H - 1, W, 1): gray and an odd height
    lm = [clips[0].landmarks]
    cfg = replace(config, cache_dir=None)
    odd = "then a = a[:, : a.shape[1] // 2 * 2"
    for name, fixes in (("gray.npy", ["np.repeat(a[..., None], 3, -1)"]),
                        ("gray1.npy", ["np.repeat(a, 3, -1) of (T, H, W, 1)", odd])):  # fmt: skip
        for run in (lambda: VideoDataset([tmp_path / name], lm, cfg).num_items(0),
                    lambda: list(VideoDataset([tmp_path / name], lm, cfg))):  # fmt: skip
            with pytest.raises(InputError, match="grayscale") as info:
                run()
            text = str(info.value)
            assert "ffmpeg" not in text and "in.mp4" not in text and "DatasetConfig(convert=True)" in text, text
            assert all(fix in text for fix in fixes), text
            assert "16-bit" not in text.split("frames are", 1)[1] and "RGBA" not in text, text  # (its own fixes only)
    np.save(tmp_path / "rgb.npy", np.repeat(gray[..., None], 3, -1))  # the fix as told
    assert VideoDataset([tmp_path / "rgb.npy"], lm, cfg).num_items(0) == gray.shape[0]


def test_repr_names_the_videos_and_the_epochs_settings(clips, config, tmp_path):
    """``print(data)`` showed ``<training_hooks.datasets.VideoDataset object at 0x...>``."""
    lm = [c.landmarks for c in clips]
    cfg = replace(config, clip_length=4, shuffle_buffer=16)
    data = VideoDataset([c.video for c in clips], lm, cfg)
    data.set_epoch(2)
    names = ", ".join(c.video.name for c in clips[:2])
    assert repr(data) == (
        f"VideoDataset(3 videos ({names}, ...), landmarks, clip_length=4, shuffle_buffer=16, epoch=2, "
        f"face_size={cfg.tracking.face_size}, keep_expression=False, cache_dir={os.fspath(cfg.cache_dir)!r})"
    )
    one = VideoDataset([clips[0].video], lm[:1], replace(cfg, cache_dir=None, clip_length=None))
    assert repr(one).startswith(f"VideoDataset(1 video ({clips[0].video.name}), landmarks, clip_length=None, ")
    assert str(one) == repr(one) and repr(one).endswith("cache_dir=None)")
    frames = read_video_uint8(clips[0].video)
    folder = tmp_path / "frames"
    folder.mkdir()
    cv2.imwrite(str(folder / "000.png"), frames[0].permute(1, 2, 0).numpy()[..., ::-1])
    assert repr(FrameFolderDataset([folder], lm[:1], cfg)).startswith("FrameFolderDataset(1 video (frames), landmarks")


def test_a_frame_to_convert_names_the_datasets_setting(clips, config, tmp_path):
    """Grayscale frames (a first one, a later one, or counted under DDP) are refused with the dataset's way out,
    DatasetConfig(convert=True): the message told a Python user to "pass --convert", the command line's flag."""
    frames = read_video_uint8(clips[0].video)  # (T, 3, H, W) uint8
    gray = frames.float().mean(1).round().to(torch.uint8).numpy()  # (T, H, W)
    np.save(tmp_path / "gray.npy", gray)
    folder = tmp_path / "later_gray"
    folder.mkdir()
    for t in range(frames.shape[0]):
        image = frames[t].permute(1, 2, 0).numpy()[..., ::-1]
        cv2.imwrite(str(folder / f"{t:03d}.png"), image if t < 2 else gray[t])
    lm = [clips[0].landmarks]
    cfg = replace(config, cache_dir=None)
    for run in (lambda: list(VideoDataset([tmp_path / "gray.npy"], lm, cfg)),
                lambda: VideoDataset([tmp_path / "gray.npy"], lm, cfg).num_items(0),
                lambda: list(FrameFolderDataset([folder], lm, cfg))):  # fmt: skip
        with pytest.raises(InputError, match="grayscale") as info:
            run()
        assert "DatasetConfig(convert=True)" in str(info.value) and "--convert" not in str(info.value)
    assert len(list(FrameFolderDataset([folder], lm, replace(cfg, convert=True)))) == frames.shape[0]
    # a float clip's NaN pixels (the first frame's, a later one's): why, then what a dataset's user can do (the
    # command line's "track the frames as a tensor" is the tracker's API, not a dataset's)
    for f in (0, 2):
        clip = frames.permute(0, 2, 3, 1).numpy().astype(np.float32) / 255
        clip[f, 3, 4] = np.nan
        np.save(tmp_path / f"nan{f}.npy", clip)
        runs = [lambda: list(VideoDataset([tmp_path / f"nan{f}.npy"], lm, cfg))]
        if f == 0:  # (counting a .npy clip reads its first frame alone)
            runs.append(lambda: VideoDataset([tmp_path / f"nan{f}.npy"], lm, cfg).num_items(0))
        for run in runs:
            with pytest.raises(InputError, match="NaN") as info:
                run()
            text = str(info.value)
            assert text.endswith(f"({NAN_PIXELS_WHY}: fill them in the file (np.save(path, np.nan_to_num(frames, "
                                 "nan=0.0))), or read the frames yourself and give them as tensors to "
                                 "training_hooks.NormaliseFaces, which takes NaN pixels as missing)"), text
            assert "as a tensor" not in text and text.count(NAN_PIXELS_WHY) == 1, text


def test_cache_dir_annotation_takes_the_documented_str(tmp_path):
    # The README's DatasetConfig(cache_dir="cache") worked, but the field was annotated `Path | None`: a type checker
    # (the package ships py.typed) refused the documented call. The value is still kept as a Path.
    hint = typing.get_type_hints(DatasetConfig)["cache_dir"]
    assert str in typing.get_args(hint) and os.PathLike[str] in typing.get_args(hint)
    assert DatasetConfig(cache_dir="cache").cache_dir == Path.cwd() / "cache"  # (made absolute: test below)
    (tmp_path / "c").mkdir()
    (entry,) = os.scandir(tmp_path)
    assert DatasetConfig(cache_dir=entry).cache_dir == tmp_path / "c"


def test_bad_landmarks_and_detector_fail_with_the_file_name(clips, config):
    clip = clips[0]
    cfg = replace(config, cache_dir=None)
    with pytest.raises(InputError, match="expected 68"):
        list(VideoDataset([clip.video], [clip.landmarks[:60]], cfg))
    outside = clip.landmarks + 500.0
    with pytest.raises(InputError, match="outside the 128x128 frame"):
        list(VideoDataset([clip.video], [outside], cfg))
    with pytest.raises(InputError, match="no face"):
        list(VideoDataset([clip.video], lambda image: None, cfg))
    # a detector's own "no face", an empty array, read "expected 68 iBUG landmarks, got 0"
    with pytest.raises(InputError, match=r"returned an empty array \(0, 2\): a detector returns None where it finds"):
        list(VideoDataset([clip.video], lambda image: np.zeros((0, 2)), cfg))
    with pytest.raises(InputError, match=str(clip.video.name)):
        list(DataLoader(VideoDataset([clip.video], [clip.landmarks[:60]], cfg), batch_size=None, num_workers=1))


def test_landmarks_of_another_kind_are_refused_when_the_dataset_is_made(tmp_path):
    """A video's landmarks as a list of points (``lm.tolist()``) were taken by VideoDataset and refused in the
    DataLoader worker, once its video was opened; they are a TypeError naming the entry and its video at once."""
    video = tmp_path / "a.avi"
    video.write_bytes(b"")  # (never opened)
    points = np.zeros((68, 2))
    with pytest.raises(TypeError, match=r"landmarks\[1\] \(.*a.avi\) must be a \(68, 2\) array .*got list"):
        VideoDataset([video, video], [points, points.tolist()])
    with pytest.raises(TypeError, match=r"landmarks\[0\] .*got function: a detector is given once for every video, "
                                        r"as landmarks itself \(VideoDataset\(videos, detector, config\)\)"):
        VideoDataset([video, video], [_no_face, _no_face])  # (a detector per video, as "per video" read)
    VideoDataset([video, video], _no_face)  # (the way named)
    for name in ("a.csv", "a.npy"):
        (tmp_path / name).write_bytes(b"")  # (never read)
    VideoDataset([video] * 4, [points, torch.zeros(68, 2), str(tmp_path / "a.csv"), tmp_path / "a.npy"])  # its kinds


def test_a_dataset_given_its_inner_config_or_one_video_is_told_what_to_pass(tmp_path):
    """Session 58's audit of the README's example: ``VideoDataset(videos, landmarks, FaceTrackingConfig(...))`` (the
    inner config) and ``VideoDataset("a.avi", ...)`` (one video's path) were told the type alone."""
    from training_hooks import FaceTrackingConfig

    video = tmp_path / "a.avi"
    video.write_bytes(b"")  # (never opened)
    points = np.zeros((68, 2))
    with pytest.raises(TypeError, match=r"^config must be a DatasetConfig, got FaceTrackingConfig, which goes inside "
                                        r"it: DatasetConfig\(tracking=FaceTrackingConfig\(...\)\)$"):
        VideoDataset([video], [points], FaceTrackingConfig())  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"^videos must be a sequence of paths, got str: one video's, \['.*a.avi'\]$"):
        VideoDataset(str(video), [points])
    VideoDataset([str(video)], [points], DatasetConfig(tracking=FaceTrackingConfig()))  # (the ways named)


def test_landmarks_of_another_count_or_a_missing_file_are_refused_when_the_dataset_is_made(tmp_path):
    """A video's landmarks of another count of points (dlib's 5, a (67, 2) slice) or a landmarks file that is not
    there were taken by VideoDataset and refused in the DataLoader worker once their video came up, after every
    video before it had been tracked; they are an InputError naming the video when the dataset is made (the values
    are checked against the frame in the worker, as before)."""
    video = tmp_path / "a.avi"
    video.write_bytes(b"")  # (never opened)
    points = np.zeros((68, 2))
    for bad, what in ((points[:67], "expected 68 iBUG landmarks, got 67"), (torch.zeros(5, 2), "got 5"),
                      (np.zeros((68, 3)), r"expected 68 \(x, y\) points, got an array of shape \(68, 3\) \(x, y, z "
                                          r"points, as 3D landmark detectors give them: landmarks\[1\]\[:, :2\]\)"),
                      (points.T, r"shape \(2, 68\) \(x, y rows: landmarks\[1\]\.T\)"),
                      (np.stack([points] * 3), r"shape \(3, 68, 2\) \(a set per frame or per stream\? one set, of "
                                               r"the first frame: landmarks\[1\]\[0\]\)"),
                      (tmp_path / "b.csv", "b.csv: no such landmarks file"),
                      (str(tmp_path), "a folder, not a landmarks file")):  # fmt: skip
        with pytest.raises(InputError, match=rf"a\.avi: landmarks: .*{what}"):
            VideoDataset([video, video], [points, bad])
    # a glob pattern, as a shell or a Hydra config holds it, was "no such file or folder" / "no such landmarks file"
    (tmp_path / "b.avi").write_bytes(b"")
    with pytest.raises(InputError, match=r"\*\.avi: no such file or folder \(a pattern\? Nothing expands it here: "
                                         r"sorted\(glob\.glob\(pattern\)\) gives the 2 paths it matches\)$"):
        VideoDataset([tmp_path / "*.avi"], [points])
    with pytest.raises(InputError, match=r"no such landmarks file \(a pattern\? .* gives the 0 paths it matches\)$"):
        VideoDataset([video], [str(tmp_path / "*.csv")])
    # the layouts the worker reads (torchface.io.check_landmarks) are still taken: (1, 68, 2), (136,)
    data = VideoDataset([video] * 3, [points[None], points.reshape(-1), torch.zeros(68, 2, dtype=torch.bfloat16)])
    assert all(isinstance(lm, np.ndarray) for lm in data.landmarks)


def test_many_videos_with_tensor_landmarks_reach_a_spawned_worker(clips, tmp_path):
    """Each video's landmarks tensor went to a DataLoader worker started by spawn through shared memory, a file
    descriptor apiece: 3000 videos stopped the first batch with "Too many open files" under a limit of 1024 (here
    400 under 256, in a child process). The dataset keeps them as NumPy arrays, sent by value."""
    import subprocess
    import sys

    code = (
        "import resource, sys, numpy as np, torch\n"
        "from torch.utils.data import DataLoader\n"
        "from training_hooks import DatasetConfig, FaceTrackingConfig, VideoDataset\n"
        "resource.setrlimit(resource.RLIMIT_NOFILE, (256, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))\n"
        "lm = torch.from_numpy(np.load(sys.argv[2]))\n"
        "data = VideoDataset([sys.argv[1]] * 400, [lm.clone() for _ in range(400)],\n"
        "                    DatasetConfig(tracking=FaceTrackingConfig(face_size=16)))\n"
        "loader = DataLoader(data, batch_size=None, num_workers=1, multiprocessing_context='spawn')\n"
        "item = next(iter(loader))\n"
        "print('ok', int(item['video']), int(item['frame']))"
    )  # fmt: skip
    np.save(tmp_path / "lm.npy", clips[0].landmarks)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(Path(__file__).resolve().parents[2]),
                                                                      os.environ.get("PYTHONPATH")]))}  # fmt: skip
    run = subprocess.run([sys.executable, "-c", code, str(clips[0].video), str(tmp_path / "lm.npy")],
                         capture_output=True, text=True, timeout=300, env=env)  # fmt: skip
    assert run.returncode == 0 and run.stdout.split() == ["ok", "0", "0"], run.stderr[-1500:]


def test_landmarks_stacked_as_facetracker_takes_them_give_one_entry_per_video(clips, config):
    """FaceTracker.initialise takes a batch's landmarks as one (B, 68, 2) tensor; the dataset refused that stack
    ("must be a sequence ... got Tensor"). An (N, 68, 2) array or tensor is N entries, the items those of the list;
    one video's (68, 2) array alone is still refused, its shape named."""
    videos = [c.video for c in clips[:2]]
    stack = np.stack([c.landmarks for c in clips[:2]])
    cfg = replace(config, cache_dir=None)
    want = collect(VideoDataset(videos, [c.landmarks for c in clips[:2]], cfg), 0)
    for given in (stack, torch.from_numpy(stack)):
        data = VideoDataset(videos, given, cfg)
        assert len(data.landmarks) == 2 and np.array_equal(np.asarray(data.landmarks[1]), clips[1].landmarks)
        assert_items_equal(collect(data, 0), want)
    with pytest.raises(TypeError, match=r"\(N, 68, 2\) stack .*got ndarray of shape \(68, 2\)"):
        VideoDataset(videos[:1], clips[0].landmarks, cfg)
    with pytest.raises(ValueError, match="one entry per video"):
        VideoDataset(videos, stack[:1], cfg)


def test_one_videos_landmarks_not_in_a_list_are_told_the_list(clips, config, tmp_path):
    """One video's (68, 2) points, its (136,) row or its landmarks file, given without the list, were told the type
    (and shape) alone; the message now says to put it in a list."""
    videos = [c.video for c in clips[:2]]
    cfg = replace(config, cache_dir=None)
    lm_file = tmp_path / "a.npy"
    np.save(lm_file, clips[0].landmarks)
    for given in (clips[0].landmarks, torch.from_numpy(clips[0].landmarks).reshape(-1), str(lm_file), lm_file):
        with pytest.raises(TypeError, match=r"got \w+( of shape \(\d+,( 2)?\))?: one video's, in a list: "
                                            r"\[landmarks\]$"):
            VideoDataset(videos[:1], given, cfg)
        with pytest.raises(TypeError, match=r": one video's\? give one entry per video, a list of 2$"):
            VideoDataset(videos, given, cfg)
    with pytest.raises(TypeError, match=r"got int$"):  # (no hint where it is not one video's)
        VideoDataset(videos[:1], 3, cfg)  # type: ignore[arg-type]


def test_detector_landmarks_of_a_face_at_the_frame_edge_are_taken(clips, config):
    """dlib's predictor places the chin of a face at the frame's edge just outside it: a detector's landmarks may
    lie partly outside the frame (they were refused as a landmarks file's), not mostly."""
    clip = clips[0]
    cfg = replace(config, cache_dir=None)
    edge = np.array(clip.landmarks, dtype=np.float64)
    edge[7:10, 1] = 129.0  # below the 128x128 frame
    assert len(list(VideoDataset([clip.video], lambda image: edge, cfg))) > 0
    with pytest.raises(InputError, match="outside the 128x128 frame"):
        list(VideoDataset([clip.video], lambda image: edge + [0.0, 200.0], cfg))


def test_transform_rejects_bad_input(clips):
    normalise = NormaliseFaces(TRACKING)
    frames = read_video(clips[0].video)
    with pytest.raises(ValueError, match=r"\(T, 3, H, W\)"):
        normalise(frames[0], clips[0].landmarks)
    with pytest.raises(ValueError, match=r"\(68, 2\)"):
        normalise(frames, clips[0].landmarks[:10])
    # other layouts of the points were told the wanted shape alone; now what to do, as the dataset and the layer say
    lm = clips[0].landmarks
    for bad, hint in ((lm.T, r"\(2, 68\) \(x, y rows: landmarks\.T\)"),
                      (np.c_[lm, np.zeros(68)], r"\(68, 3\) \(x, y, z points, .*: landmarks\[:, :2\]\)"),
                      (np.stack([lm] * 6), r"\(6, 68, 2\) \(a set per frame or per stream\? one set, of the first "
                                           r"frame: landmarks\[0\]\)")):  # fmt: skip
        with pytest.raises(ValueError, match=rf"landmarks must be \(68, 2\) iBUG points in pixels, got {hint}$"):
            normalise(frames, bad)
    with pytest.raises(ValueError, match="empty"):
        normalise(frames[:0], clips[0].landmarks)
    with pytest.raises(ValueError, match=r"frame 0: .*divide by 255"):  # 0-255 floats: refused, not tracked
        normalise(frames[:2] * 255.0, clips[0].landmarks)
    first, state = normalise.track(frames[:1], clips[0].landmarks)
    # a batch of one (1, 68, 2) and a flat (136,): taken as a dataset's entry and an NPY landmarks file are (refused)
    for layout in (lm[None], torch.from_numpy(lm.reshape(-1))):
        assert torch.equal(normalise.track(frames[:1], layout)[0].faces, first.faces)
    with pytest.raises(ValueError, match=r"landmarks: the 136 values .* all x then all y they do"):  # (planar)
        normalise.track(frames[:1], torch.from_numpy(np.ascontiguousarray(lm.T).reshape(-1)))
    with pytest.raises(ValueError, match=r"frame 1: .*divide by 255"):  # also when a clip continues a state
        normalise.track(torch.cat([frames[1:2], frames[2:3] * 255.0]), state)


def test_the_transform_says_how_to_lay_out_refused_frames(clips):
    """Frames as OpenCV or NumPy hold them (channels last), gray or RGBA: the message said only "frames must be a
    (T, 3, H, W) tensor, got (6, 128, 128, 3)"; it now says how to make the clip."""
    frames = read_video_uint8(clips[0].video)  # (T, 3, H, W) uint8
    normalise = NormaliseFaces(TRACKING)
    for bad, hint in ((frames.permute(0, 2, 3, 1), r"frames\.permute\(0, 3, 1, 2\)"),
                      (torch.cat([frames, frames[:, :1]], 1), r"frames\[:, :3\]"),
                      (frames[:, 0], r"frames\[:, None\]"),
                      # a batch of clips (told its shape alone): one clip per call, or the layer
                      (frames[None], r"one clip: frames\[i\].*NormalisedFaceLayer\.forward_clip")):  # fmt: skip
        with pytest.raises(ValueError, match=r"\(T, 3, H, W\).*" + hint):
            normalise(bad, clips[0].landmarks)
    fixed = normalise(frames[:, 0][:, None], clips[0].landmarks)  # the hint's gray clip is taken (gray faces)
    assert fixed["face"].shape[:2] == (frames.shape[0], 1)
    # frames streamed one by one (track: any iterable), as OpenCV gives them: (H, W, 3) BGR arrays, or tensors of
    # them; the messages said "got a numpy array" or "got (128, 128, 3)" alone
    bgr = [f.permute(1, 2, 0).numpy()[..., ::-1] for f in frames[:2]]
    recipe = r"torch\.from_numpy\(image\[\.\.\., ::-1\]\.copy\(\)\)\.permute\(2, 0, 1\)"
    with pytest.raises(TypeError, match=r"frame 0: frames must be torch tensors \(3, H, W\), got a numpy array \(.*"
                       + recipe):  # fmt: skip
        normalise.track(iter(bgr), clips[0].landmarks)
    with pytest.raises(ValueError, match=r"frame 0: .*got \(\d+, \d+, 3\) \(channels last \(H, W, 3\): frame\.permute"):
        normalise.track((torch.from_numpy(image.copy()) for image in bgr), clips[0].landmarks)
    # ... and for such a tensor of an OpenCV image, BGR: the permute alone (all the hint said) tracked it in BGR order
    with pytest.raises(ValueError, match=r"BGR as OpenCV reads it: frame\.flip\(-1\)\.permute\(2, 0, 1\)"):
        normalise.track((torch.from_numpy(image.copy()) for image in bgr), clips[0].landmarks)
    flipped, _ = normalise.track((torch.from_numpy(image.copy()).flip(-1).permute(2, 0, 1) for image in bgr),
                                 clips[0].landmarks)  # fmt: skip
    streamed, _ = normalise.track((torch.from_numpy(image[..., ::-1].copy()).permute(2, 0, 1) for image in bgr),
                                  clips[0].landmarks)  # the recipe, as written: the frames of the clip
    direct, _ = normalise.track(frames[:2], clips[0].landmarks)
    assert torch.equal(streamed.faces, direct.faces) and torch.equal(flipped.faces, direct.faces)
    # a NumPy gray image: run as written, the recipe makes a (1, 1, H, W) gray clip, which the transform takes
    gray = frames[0, 1].numpy().copy()
    with pytest.raises(TypeError, match=r"got ndarray \(a NumPy gray image") as info:
        normalise(gray, clips[0].landmarks)
    made = eval(str(info.value).split(": ", 1)[-1][:-1], {"torch": torch, "image": gray})
    assert normalise(made, clips[0].landmarks)["face"].shape[:2] == (1, 1)


def test_the_transform_takes_gray_frames_as_the_tracker_does(clips):
    """``FaceTracker`` tracks ``(B, 1, H, W)`` gray frames; ``NormaliseFaces`` refused ``(T, 1, H, W)`` ("gray
    frames: frames.expand(-1, 3, -1, -1)"). It takes them now, float or uint8, and normalises them into gray faces
    ``(T, 1, S, S)``: the items of the same frames made RGB (``expand``), to float rounding (the luminance of three
    equal channels is the gray level to 1 ulp: parameters measured within 3e-5 (translation, mm), faces within one
    uint8 level of each channel)."""
    frames = read_video_uint8(clips[0].video)  # (T, 3, H, W) uint8
    gray = frames.float().mean(1, keepdim=True).round().to(torch.uint8)  # (T, 1, H, W)
    normalise = NormaliseFaces(TRACKING)
    for clip in (gray, gray.float() / 255.0):
        item = normalise(clip, clips[0].landmarks)
        rgb = normalise(clip.expand(-1, 3, -1, -1), clips[0].landmarks)
        assert item["face"].shape == (FRAMES, 1, 32, 32) and item["mask"].shape == (FRAMES, 1, 32, 32)
        for key, value in rgb.items():
            if key == "face":
                assert all(float((item["face"][:, 0] - value[:, c]).abs().max()) <= 1.01 / 255 for c in range(3))
            elif value.is_floating_point():
                assert torch.allclose(item[key], value, rtol=0.0, atol=1e-3), key
            else:
                assert torch.equal(item[key], value), key
        assert bool(item["success"].all()) and float(item["confidence"].min()) > 0.5
    # one kind per sequence (the faces stack): a gray frame after RGB ones is refused, saying so
    with pytest.raises(ValueError, match=r"frame 2 is gray \(1, H, W\) but the sequence started RGB"):
        normalise.track(iter([frames[0], frames[1], gray[2]]), clips[0].landmarks)
    with pytest.raises(ValueError, match=r"\(T, 3, H, W\) RGB or \(T, 1, H, W\) gray tensor, got \(6, 2, "):
        normalise(frames[:, :2], clips[0].landmarks)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float64])
def test_a_streamed_numpy_frame_is_told_the_trackers_recipe_for_one_frame(dtype):
    """A frame streamed to ``track`` as a NumPy array is told how to make it by the tracker's own rule
    (:func:`torchface.tracker.step.not_tensor_hint`, for one frame ``(3, H, W)`` that may be uint8), not by a copy of
    its image case: a gray image ``(H, W)`` was told nothing, and the copy said "an (H, W, 3) image". Each recipe,
    run as written, makes a frame the transform takes."""
    from torchface.tracker.step import not_tensor_hint
    from training_hooks.transforms import _frame_tensor

    scale = {np.uint8: 255, np.uint16: 65535, np.float64: 1.0}[dtype]
    rgb = (np.random.default_rng(0).random((24, 32, 3)) * scale).astype(dtype)
    normalise = NormaliseFaces(TRACKING)
    for image, says in ((rgb[..., ::-1], r"a NumPy image \(H, W, 3\), BGR as OpenCV reads it: "),
                        (rgb[..., 1], r"a NumPy gray image \(H, W\): "),
                        (rgb.transpose(2, 0, 1), r"a NumPy array: ")):  # fmt: skip
        with pytest.raises(TypeError, match=r"frame 0: frames must be torch tensors \(3, H, W\), got a numpy array \("
                           + says) as info:  # fmt: skip
            normalise.track(iter([image]), np.zeros((68, 2)))
        hint = str(info.value).split("got a numpy array", 1)[1]
        assert hint == not_tensor_hint(image, to_float=False, layout="(3, H, W)", one_frame=True)
        recipe = hint[2:-1].split(": ", 1)[1].split(";")[0].split(", laid out")[0]  # (the text in " (...)")
        made = eval(recipe, {"torch": torch, "image": image.copy(), "array": image.copy()})
        frame = _frame_tensor(made, 0, None)  # taken: (1, C, H, W) float32 in [0, 1], RGB or gray (C = 1)
        assert frame.shape == (1, 1 if image.ndim == 2 else 3, 24, 32)
        if image.ndim == 3 and image.shape[-1] == 3:  # the BGR image's recipe gives back the RGB frame
            assert torch.allclose(frame[0], torch.from_numpy(rgb.astype(np.float64) / scale).permute(2, 0, 1).float())


def test_a_sequence_keeps_its_own_copy_of_the_landmarks(clips, tmp_path):
    """track_sequence kept the caller's float64 landmark tensor itself: refilling that buffer for the next video
    changed the tracked sequence's landmarks (and what the cache would store), and landmarks that required grad
    made TrackCache.store fail (numpy() of a tensor that requires grad)."""
    from training_hooks import TrackCache

    frames = read_video_uint8(clips[0].video)[:2]
    buffer = torch.tensor(clips[0].landmarks, dtype=torch.float64)
    normalise = NormaliseFaces(TRACKING)
    sequence, _ = normalise.track(frames, buffer)
    buffer += 5.0
    assert torch.equal(sequence.landmarks, torch.tensor(clips[0].landmarks))
    graded, _ = normalise.track(frames, torch.tensor(clips[0].landmarks, requires_grad=True))
    assert not graded.landmarks.requires_grad
    TrackCache(tmp_path / "cache").store("b" * 64, graded)


def test_read_only_landmarks_are_taken_without_a_warning():
    """Landmarks in a read-only array (``np.load(..., mmap_mode="r")``, ``np.frombuffer``) made torch print "The
    given NumPy array is not writable" (a UserWarning, once per process: checked in a child process)."""
    import subprocess
    import sys

    code = (
        "import numpy as np\n"
        "from torchface.io import open_frames, read_landmarks\n"
        "from torchface.job import demo_inputs\n"
        "from training_hooks import FaceTrackingConfig, NormaliseFaces\n"
        "video, lm = demo_inputs()\n"
        "with open_frames(video) as reader:\n"
        "    frames = [next(reader) for _ in range(2)]\n"
        "points = read_landmarks(lm, frames[0].shape[-1], frames[0].shape[-2])\n"
        "points.setflags(write=False)\n"
        "import torch\n"
        "item = NormaliseFaces(FaceTrackingConfig(face_size=32))(torch.stack(frames), points)\n"
        "assert item['face'].shape == (2, 3, 32, 32)\n"
        "print('ok')"
    )  # fmt: skip
    run = subprocess.run([sys.executable, "-W", "error", "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.strip() == "ok", run.stderr[-1500:]


def test_sequence_success_and_validation(clips):
    from dataclasses import replace as dc_replace

    sequence, state = NormaliseFaces(TRACKING).track(read_video(clips[0].video)[:3], clips[0].landmarks)
    assert state.management is not None  # tracked as FaceTracker tracks: with template management
    marked = dc_replace(sequence, status=torch.tensor([0, 2, 3]))  # converged, FAILED, LOST
    assert marked.success.tolist() == [True, False, False]
    assert marked.item(2)["success"].item() is False and marked.item(slice(0, 3))["success"].tolist() == [1, 0, 0]
    # Each item's tensors hold its own frames only (a worker sends them whole): success was a view of all T flags.
    long = dc_replace(sequence, **{f: torch.cat([getattr(sequence, f)] * 100) for f in (
        "faces", "masks", "rotation", "axis_angle", "translation", "ypr_deg", "anim_coeffs", "expression", "facs",
        "illumination", "confidence", "status")})  # fmt: skip
    as_float = dc_replace(long, faces=long.faces.to(torch.float32) / 255.0)  # FaceStorage.FLOAT32
    for seq, index in itertools.product((long, as_float), (5, slice(5, 9))):
        item = seq.item(index)
        for key, value in item.items():
            assert value.untyped_storage().nbytes() == value.numel() * value.element_size(), key
    with pytest.raises(ValueError, match="confidence must be"):
        dc_replace(sequence, confidence=torch.ones(2))
    with pytest.raises(ValueError, match="finite"):
        dc_replace(sequence, axis_angle=torch.full((3, 3), float("nan")))
    with pytest.raises(IndexError):
        sequence.item(3)
    with pytest.raises(ValueError, match="step 1"):
        sequence.item(slice(0, 3, 2))
    for bad in (1.7, True, "1"):  # int(1.7) took frame 1 without a word
        with pytest.raises(TypeError, match="frames must be an int"):
            sequence.item(bad)  # type: ignore[arg-type]
    assert int(sequence.item(np.int64(1))["frame"]) == int(sequence.item(torch.tensor(1))["frame"]) == 1


def test_items_carry_the_expression_measured_from_the_first_frame(clips):
    """``expression`` is ``TrackResult.expression``: the coefficients less the first frame's fitted ones (0 on the
    first frame), and ``facs`` is linked to it, not to the coefficients."""
    from torchface.model.candide import load_candide3

    sequence, state = NormaliseFaces(TRACKING).track(read_video(clips[0].video)[:3], clips[0].landmarks)
    neutral = state.anim_prior_mean[0].to(torch.float32)
    assert float(sequence.anim_coeffs[0].abs().max()) > 1e-3  # the fitted start is not zero: the test can fail
    torch.testing.assert_close(sequence.expression, sequence.anim_coeffs - neutral, atol=1e-6, rtol=0)
    assert float(sequence.expression[0].abs().max()) == 0.0
    facs = load_candide3().facs_values(sequence.expression)
    torch.testing.assert_close(sequence.facs, facs, atol=1e-6, rtol=0)
    item = sequence.item(slice(0, 3))
    torch.testing.assert_close(item["expression"], sequence.expression)
    with pytest.raises(ValueError, match="expression must be"):
        replace(sequence, expression=torch.zeros(3, 10))


def test_keep_expression_resamples_at_the_persons_neutral(clips):
    """``FaceTrackingConfig(keep_expression=True)`` resamples each frame at the state's neutral (the first
    frame's fitted coefficients, which ``TrackResult.expression`` is measured from), not at zero."""
    from torchface.model.candide import load_candide3
    from torchface.normalise import NormalisedFace
    from torchface.tracker.step import _layout
    from training_hooks.transforms import FaceStorage, track_sequence

    model = load_candide3()
    config = replace(TRACKING, keep_expression=True, face_storage=FaceStorage.FLOAT32)
    normaliser = NormalisedFace(model, config.face_size, config.face_margin)
    frames = read_video(clips[0].video)[:3]
    _, state = track_sequence(frames[:2], torch.as_tensor(clips[0].landmarks), config, model, normaliser)
    neutral = torch.zeros_like(state.anim_prior_mean)
    neutral[0, model.animation_names.index("AUV11 Jaw drop")] = 0.3
    seq, after = track_sequence(frames[2:], replace(state, anim_prior_mean=neutral), config, model, normaliser)
    aa, t, _, light = _layout(model).split(after.params)
    frame = frames[2:].to(model.dtype)

    def face(alpha):
        return normaliser.from_params(frame, after.shape_coeffs, alpha, aa, t, light, after.intrinsics).image[0]

    torch.testing.assert_close(seq.faces[0], face(neutral))
    assert not torch.allclose(seq.faces[0], face(torch.zeros_like(neutral)))


def test_keep_expression_resamples_each_frame_at_the_neutral_its_expression_is_measured_from(tmp_path):
    """Where the online start re-anchors (the ``expressions`` clip at 160x120 turns past its yaw at frame 1), the
    neutral is re-estimated at the end of that frame's step, after its result (``expression``, ``facs``) was
    measured from the first fit's: that frame's face was resampled at the new neutral, 1.05 off its labels. Now
    every frame's ``expression`` is its ``anim_coeffs`` minus the coefficients its face was resampled at, as
    ``torchface track --keep-expression``'s rows are."""
    from torchface.model.candide import load_candide3
    from torchface.normalise import NormalisedFace
    from training_hooks.transforms import FaceStorage, FaceTrackingConfig, track_sequence

    video, lm = lossless_scenario_clip(tmp_path, "expressions", 6, 160, 120)
    frames = torch.from_numpy(np.load(video)).permute(0, 3, 1, 2).float() / 255
    model = load_candide3()
    config = FaceTrackingConfig(keep_expression=True, face_storage=FaceStorage.FLOAT32)
    normaliser = NormalisedFace(model, config.face_size, config.face_margin)
    resampled: list[torch.Tensor] = []
    original = NormalisedFace.from_params

    def record(self, fr, shape, alpha, *args, **kwargs):
        resampled.append(alpha.detach().double().clone())
        return original(self, fr, shape, alpha, *args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(NormalisedFace, "from_params", record)
        seq, _ = track_sequence(frames, torch.from_numpy(np.loadtxt(lm, delimiter=",", skiprows=1)), config, model,
                                normaliser)  # fmt: skip
    at = torch.cat(resampled)
    moved = (at - at[0]).abs().amax(-1)
    assert bool((moved[:2] == 0).all()) and bool((moved[2:] > 0.5).all()), moved  # re-anchored in frame 1's step
    torch.testing.assert_close(seq.expression.double(), seq.anim_coeffs.double() - at, atol=1e-6, rtol=0)


def test_transform_inside_autocast_equals_full_precision(clips):
    """A transform called inside a training step's ``torch.autocast`` region tracks in full precision: the items
    equal those made outside it bit for bit (bfloat16 products changed faces, poses and statuses, and the cache
    would keep them)."""
    clip = clips[1]
    frames = read_video(clip.video)
    normalise = NormaliseFaces(TRACKING)
    ref = normalise(frames, clip.landmarks)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = normalise(frames, clip.landmarks)
        assert torch.is_autocast_enabled("cpu")  # the caller's region is back on afterwards
    for name in ref:
        assert torch.equal(out[name], ref[name]), name


def test_track_sequence_takes_its_models_landmark_count(clips):
    """track_sequence takes a model, but refused any first-frame landmarks but 68 ('(68, 2) iBUG points'): a model
    with another landmark table (here CANDIDE-3 with the 51 inner iBUG points) could not be tracked."""
    from dataclasses import replace as dc_replace

    from torchface.model.candide import load_candide3
    from torchface.normalise import NormalisedFace
    from training_hooks.transforms import track_sequence

    candide = load_candide3()
    inner = dc_replace(candide, landmark_vertices=candide.landmark_vertices[17:],
                       landmark_weights=candide.landmark_weights[17:], landmark_names=candide.landmark_names[17:])
    normaliser = NormalisedFace(inner, size=TRACKING.face_size, margin=TRACKING.face_margin)
    frames = read_video(clips[0].video)[:2]
    sequence, _ = track_sequence(frames, clips[0].landmarks[17:], TRACKING, inner, normaliser)
    assert sequence.num_frames == 2 and sequence.landmarks.shape == (51, 2)
    assert bool(sequence.success.all())
    with pytest.raises(ValueError, match=r"\(51, 2\) points, the model's landmarks"):
        track_sequence(frames, clips[0].landmarks, TRACKING, inner, normaliser)


def test_a_dataset_pickled_without_the_shared_state_still_loads(clips, config):
    """A dataset pickled before the epoch, warning flag and item counts were shared (its epoch a plain attribute)
    unpickles with its epoch and counts its items."""
    data = VideoDataset([clips[0].video], [clips[0].landmarks], config)
    state = data.__getstate__()
    del state["_shared"], state["_claims"]  # (nor the claims of the once-per-dataset warnings)
    state["epoch"] = 3
    old = VideoDataset.__new__(VideoDataset)
    old.__setstate__(state)
    assert old.epoch == 3 and old.count_items() == [FRAMES]
    old.set_epoch(4)
    assert old.epoch == 4 and data.epoch == 0


def test_hd_video_is_tracked_with_the_coarser_levels_its_face_needs():
    """Tracking for the dataloaders took the config as given, so an HD video lost a fast motion that ``torchface
    track`` followed: the 1280x720 clip of tests/cli/test_cli_track.py's HD test (13 mm a frame sideways at 450 mm,
    37 pixels), frames 1 and 2 23 and 28 degrees off with the default three levels. ``FaceTrackingConfig.pyramid``
    "auto" (the default) adds the job's levels (pyramid_for_faces: four) and follows it, and a state it returns is
    continued with them; "config" keeps the three levels (and cannot continue that state)."""
    from torchface.model.candide import load_candide3
    from torchface.normalise import NormalisedFace
    from training_hooks import FaceTrackingConfig
    from training_hooks.transforms import track_sequence

    frames, lm, truth = sideways_clip(1280, 720)
    model = load_candide3()
    auto = FaceTrackingConfig(face_size=16, refine_first=None)
    given = replace(auto, pyramid="config")
    normaliser = NormalisedFace(model, auto.face_size, auto.face_margin)
    first, state = track_sequence(frames[:2], lm, auto, model, normaliser)
    rest, _ = track_sequence(frames[2:], state, auto, model, normaliser)  # continued with its four levels
    whole, three = track_sequence(frames, lm, given, model, normaliser)
    assert (state.num_levels, three.num_levels) == (4, 3)
    followed = geodesic_angle_deg(torch.cat([first.rotation[1:], rest.rotation]).double(), truth[1:])
    lost = geodesic_angle_deg(whole.rotation[1:].double(), truth[1:])
    assert float(followed.max()) < 2.0 and float(lost.max()) > 10.0, (followed, lost)
    with pytest.raises(ValueError, match="the state holds templates for 4 pyramid levels"):
        track_sequence(frames[2:], state, given, model, normaliser)
    with pytest.raises(ValueError, match=r"pyramid must be one of \('auto', 'config'\), got 'off'"):
        FaceTrackingConfig(pyramid="off")


# ------------------------------------------------------------------------- a detector: the first frame with a face


def _black_first(clip, tmp_path: Path, black: int, name: str = "late") -> tuple[Path, Path]:
    """The clip with ``black`` black frames before it: a video file and a folder of PNG frames (both lossless)."""
    frames = read_video(clip.video)
    late = torch.cat([torch.zeros(black, *frames.shape[1:]), frames])
    video, folder = tmp_path / f"{name}.avi", tmp_path / name
    write_video(video, late)
    folder.mkdir()
    for t, frame in enumerate(read_video_uint8(video)):
        cv2.imwrite(str(folder / f"{t:03d}.png"), frame.permute(1, 2, 0).numpy()[..., ::-1])
    return video, folder


class _FaceWhereShown:
    """A stand-in detector from the rendered ground truth: the clip's first-frame landmarks in a frame that is not
    black, None in a black one; counts its calls in a file (DataLoader workers are other processes)."""

    def __init__(self, landmarks: np.ndarray, log: Path) -> None:
        self.landmarks, self.log = landmarks, log

    def __call__(self, image: np.ndarray) -> np.ndarray | None:
        with open(self.log, "a") as f:
            f.write("x")
        return self.landmarks if image.max() > 0 else None

    @property
    def calls(self) -> int:
        return len(self.log.read_text()) if self.log.exists() else 0


def test_a_detector_tracks_from_the_first_frame_with_a_face_as_the_cut_video(clips, config, tmp_path):
    """With a detector, a video whose first frames are black was an InputError ("the detector found no face in the
    first frame"), as ``torchface track --detector`` searches on. Now the dataset searches too: its items are those
    of the clip without the black frames, ``frame`` the video's frame number (the clip's plus 3), per frame and per
    clip, from a video file and from a folder of frames; the items counted without tracking are those yielded."""
    clip, black = clips[0], 3
    video, folder = _black_first(clip, tmp_path, black)
    cfg = replace(config, cache_dir=None)
    for c in (cfg, replace(cfg, clip_length=4, clip_stride=1)):
        detector = _FaceWhereShown(clip.landmarks, tmp_path / f"calls{c.clip_length}.txt")
        want = collect(VideoDataset([clip.video], _FaceWhereShown(clip.landmarks, tmp_path / "ref.txt"), c), 0)
        for data in (VideoDataset([video], detector, c), FrameFolderDataset([folder], detector, c)):
            assert data.count_items() == [len(want)] and data.stats.frames_tracked == 0  # counted, not tracked
            got = collect(data, 0)
            assert [k[1] - black for k in got] == [k[1] for k in want]
            for (_, frame), a in got.items():
                b = want[(0, frame - black)]
                assert torch.equal(a["frame"], b["frame"] + black)
                for name in a:
                    if name != "frame":
                        assert torch.equal(a[name], b[name]), name
            assert data.stats.frames_tracked == FRAMES
        # each video searched once (frames 0..3 asked about), when counted: not again when tracked
        assert detector.calls == 2 * (black + 1)


def test_a_cached_video_whose_face_appears_later_is_not_searched_again(clips, config, tmp_path):
    """The cache key holds the detected landmarks and the frame they are of; a later epoch (fresh DataLoader workers)
    reads the cache without asking the detector again, as does the dataset's own process; a new dataset searches
    once more, and finds its sequence in the cache under that key."""
    clip, black = clips[1], 2
    video, _ = _black_first(clip, tmp_path, black)
    detector = _FaceWhereShown(clip.landmarks, tmp_path / "calls.txt")
    data = VideoDataset([video], detector, config)
    first = collect(data, 1)
    assert detector.calls == black + 1 and not any(bool(it["cached"]) for it in first.values())
    assert sorted(k[1] for k in first) == list(range(black, black + FRAMES))
    for workers in (1, 0):  # a later epoch in new worker processes, then in the dataset's own
        again = collect(data, workers)
        assert detector.calls == black + 1 and all(bool(it["cached"]) for it in again.values())
        assert_items_equal(first, again, skip=("cached",))
    fresh = VideoDataset([video], detector, config)
    assert_items_equal(first, collect(fresh, 0), skip=("cached",))
    assert detector.calls == 2 * (black + 1) and fresh.stats.cache.hits == 1 and fresh.stats.frames_tracked == 0
    # the frame is in the key: the same landmarks at the first frame are another key (and its key is as before)
    content = content_hash(video)
    at_first = cache_key(content, TRACKING, clip.landmarks, "convert=False")
    assert cache_key(content, TRACKING, clip.landmarks, "convert=False", first_frame=0) == at_first
    found = cache_key(content, TRACKING, clip.landmarks, "convert=False", first_frame=black)
    assert found != at_first and [p.stem for p in data.cache.root.glob("*.npz")] == [found]


def test_a_video_without_a_face_names_the_frames_searched(clips, config, tmp_path):
    """A video in none of whose frames the detector finds a face is an InputError naming it and how many frames
    were searched, when counted and when iterated, as ``torchface track --detector`` says it."""
    video = tmp_path / "black.avi"
    write_video(video, torch.zeros(5, 3, 128, 128))
    detector = _FaceWhereShown(clips[0].landmarks, tmp_path / "calls.txt")
    message = rf"^{re.escape(str(video))}: the detector found no face in any of its 5 frames: nothing to track"
    with pytest.raises(InputError, match=message):
        VideoDataset([video], detector, config).num_items(0)
    with pytest.raises(InputError, match=message):
        list(VideoDataset([video], detector, config))
    assert detector.calls == 10


def test_a_dataset_without_a_detector_shares_no_detection_store(clips, config):
    """The store of detections shared with the workers (1128 bytes a video: the frame, the content hash and 68
    float64 points) was made in shared memory for every dataset, with or without a detector: 1.1 GB of /dev/shm
    for a million clips given their landmarks (64 MB in a Docker container by default). Without a detector only
    the counts are shared (8 bytes a video, and 24 a dataset: the record of its iterations); with one, the store."""
    n = 2000
    for detector in (False, True):
        landmarks = (lambda image: clips[0].landmarks) if detector else [clips[0].landmarks] * n
        data = VideoDataset([clips[0].video] * n, landmarks, config)
        shared = sum(t.untyped_storage().nbytes() for t in vars(data).values()
                     if isinstance(t, torch.Tensor) and t.is_shared())  # fmt: skip
        assert (shared > 1000 * n) if detector else (shared <= 8 * (n + 2) + 24)


def test_keep_going_skips_a_video_that_cannot_be_read_or_tracked(clips, config, tmp_path):
    """One bad video stopped the whole epoch, with no way on. ``DatasetConfig(keep_going=True)`` skips it as
    ``torchface track --keep-going`` does: a warning naming it, a record in ``data.skipped`` (its workers' too), its
    items left out and the others' as they were; not tried again in later epochs. A video that cannot be counted
    counts 0; one that fails only when tracked keeps its count. The default stays strict."""
    import warnings

    from training_hooks import SkippedVideoWarning

    bad = tmp_path / "bad.avi"
    bad.write_bytes(b"not a video" * 100)
    videos = [clips[0].video, bad, clips[1].video]
    landmarks = [clips[0].landmarks, clips[0].landmarks, clips[1].landmarks + 1000.0]  # video 2: outside its frame
    with pytest.raises(InputError, match="bad.avi"):
        list(VideoDataset(videos, landmarks, config))
    with pytest.raises(InputError, match="outside"):
        list(VideoDataset(videos[2:], landmarks[2:], config))
    with pytest.raises(TypeError, match="keep_going"):
        DatasetConfig(keep_going="yes")
    reference = list(VideoDataset(videos[:1], landmarks[:1], config))
    going = replace(config, keep_going=True)
    data = VideoDataset(videos, landmarks, going)
    assert data.skipped == {}
    with pytest.warns(SkippedVideoWarning) as said:
        items = list(data)
    assert sorted(str(w.message).split(" (video")[0] for w in said) == [f"skipped {bad}", f"skipped {videos[2]}"]
    assert [(int(i["video"]), int(i["frame"])) for i in items] == [(0, t) for t in range(FRAMES)]
    assert all(torch.equal(a[k], b[k]) for a, b in zip(items, reference) for k in a if k != "cached")
    assert sorted(data.skipped) == [1, 2]
    assert data.skipped[1].startswith(f"{bad}: ") and "outside" in data.skipped[2]
    assert data.skipped[2].startswith(f"{videos[2]}: ") and str(videos[2]) not in data.skipped[2][len(str(videos[2])):]
    with warnings.catch_warnings():  # a later epoch: the skipped videos are not tried again (no second warning)
        warnings.simplefilter("error")
        assert [(int(i["video"]), int(i["frame"])) for i in data] == [(0, t) for t in range(FRAMES)]
    # counts: the video that cannot be decoded counts 0 (skipped there), the one that fails when tracked keeps its own
    fresh = VideoDataset(videos, landmarks, going)
    with pytest.warns(SkippedVideoWarning, match="bad.avi"):
        assert fresh.count_items() == [FRAMES, 0, FRAMES]
    assert list(fresh.skipped) == [1]
    # DataLoader workers (video 1 -> worker 1, videos 0 and 2 -> worker 0): their records reach the caller's dataset
    loaded = VideoDataset(videos, landmarks, going)
    with warnings.catch_warnings():  # (the workers' warnings go to their stderr; forked, they keep this filter)
        warnings.simplefilter("ignore", SkippedVideoWarning)
        batches = list(DataLoader(loaded, batch_size=4, num_workers=2, multiprocessing_context="fork"))
    assert sorted(int(v) for b in batches for v in b["video"]) == [0] * FRAMES
    assert loaded.skipped == data.skipped


def test_len_and_indexing_say_what_to_use_instead(clips, config):
    """An iterable dataset: ``data[0]`` was torch's "Subclasses of Dataset should implement __getitem__" (a
    NotImplementedError, read as a bug); it is a TypeError that says what to use. ``len(data)`` stays Python's "has
    no len()": a ``__len__`` that raised made the dataset a ``collections.abc.Sized``, and Lightning's
    ``str(datamodule)``, which asks ``len()`` only of a Sized dataset, then said "Train dataloader: None" (no loader)
    instead of "size=NA". What takes "no length" from a TypeError (list(), a DataLoader) works as before."""
    from collections.abc import Sized

    data = VideoDataset([clips[0].video], [clips[0].landmarks], config)
    assert not isinstance(data, Sized)
    with pytest.raises(TypeError, match=r"has no len\(\)"):
        len(data)
    with pytest.raises(TypeError, match=r"has no len\(\)"):
        len(DataLoader(data, batch_size=2))
    with pytest.raises(TypeError, match=r"no items by index: iterate it .*data\.sequence\(i\)\[0\]"):
        data[0]
    items = list(data)  # (list() asks for a length hint: a TypeError is "none")
    assert len(items) == sum(data.count_items()) == FRAMES
    sequence, _ = data.sequence(0)  # the recipe: frame t's item
    assert all(torch.equal(sequence.item(3)[k], items[3][k]) for k in sequence.item(3))
    assert len(list(DataLoader(data, batch_size=4))) == 2
    try:
        from training_hooks.lightning import TrackedFaceDataModule
    except ImportError:  # (Lightning is optional)
        return
    assert str(TrackedFaceDataModule(data, val=data)).splitlines()[:2] == [
        "{Train dataloader: size=NA}", "{Validation dataloader: size=NA}"
    ]


def test_keep_going_does_not_skip_a_video_for_the_caches_write_error(clips, config, tmp_path):
    """With ``keep_going``, a cache that cannot be written (here a folder under a file: NotADirectoryError; a full
    disk or a read-only folder alike) skipped every video as if it could not be read, after tracking it, and for
    good: an epoch of no items, with a warning per video. The error is the cache's, not the video's: it stops the
    epoch, as without ``keep_going``; nothing is recorded as skipped."""
    import warnings

    from training_hooks import SkippedVideoWarning

    blocker = tmp_path / "not_a_folder"
    unwritable = replace(config, cache_dir=blocker / "cache")
    stopping = VideoDataset([clips[0].video], [clips[0].landmarks], unwritable)
    data = VideoDataset([clips[0].video], [clips[0].landmarks], replace(unwritable, keep_going=True))
    blocker.write_text("")  # (after the datasets are made: they refuse a cache_dir inside a file)
    with pytest.raises(OSError, match="cannot store a tracked sequence in the cache folder"):
        list(stopping)
    with warnings.catch_warnings():
        warnings.simplefilter("error", SkippedVideoWarning)
        with pytest.raises(OSError):
            list(data)
    assert data.skipped == {}


def test_a_gray_frame_channels_last_is_told_its_own_permute():
    """A gray frame streamed channels last, ``(H, W, 1)`` (an OpenCV gray image ``[..., None]``), was told "channels
    last (H, W, 3)" and the BGR flip of a colour image; it is told its own shape and the permute, which, run as
    written, makes a frame the transform takes."""
    from training_hooks.transforms import _frame_tensor

    image = torch.rand(24, 32, 1)
    with pytest.raises(ValueError, match=r"got \(24, 32, 1\) \(a gray frame channels last \(H, W, 1\): "
                       r"frame\.permute\(2, 0, 1\)\)$") as info:  # fmt: skip
        _frame_tensor(image, 0, None)
    assert "BGR" not in str(info.value) and "(H, W, 3)" not in str(info.value)
    recipe = str(info.value).rsplit(": ", 1)[1][:-1]
    assert _frame_tensor(eval(recipe, {"frame": image}), 0, None).shape == (1, 1, 24, 32)


def test_bad_cache_dir_epoch_and_indices_are_named(tmp_path, monkeypatch):
    """DatasetConfig(cache_dir="") made the working folder the cache (Path("") is "."), filling it with .npz files,
    and cache_dir=3 was pathlib's "expected str, bytes or os.PathLike object, not int"; set_epoch(1.5) and
    set_epoch("2") were taken as 1 and 2 without a word (and set_epoch("a") was int()'s message); num_items(1.0) was
    torch's message about tensor indices and worker_videos(True, 2) worker 1's videos. Each now names the setting."""
    video = tmp_path / "v.npy"
    np.save(video, np.zeros((2, 16, 16, 3), dtype=np.uint8))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match=r"^cache_dir is empty \(the working folder\): give a folder, or None"):
        DatasetConfig(cache_dir="")
    with pytest.raises(TypeError, match=r"^cache_dir must be a folder \(a str or path-like\) or None, got int$"):
        DatasetConfig(cache_dir=3)
    assert DatasetConfig(cache_dir=".").cache_dir == DatasetConfig(cache_dir=Path("")).cache_dir == tmp_path  # (meant)
    data = VideoDataset([video], [np.zeros((68, 2))])
    for bad in (1.5, "2", True):
        with pytest.raises(TypeError, match=r"^epoch must be an int >= 0, got"):
            data.set_epoch(bad)
    with pytest.raises(ValueError, match=r"^epoch must be an int >= 0, got -1$"):
        data.set_epoch(-1)
    data.set_epoch(np.int64(3))
    assert data.epoch == 3
    with pytest.raises(TypeError, match=r"^index must be an int, got float 1.0$"):
        data.num_items(1.0)
    with pytest.raises(TypeError, match=r"^worker_id must be an int, got bool True$"):
        data.worker_videos(True, 2)
    with pytest.raises(TypeError, match=r"^world_size must be an int >= 1, got float 2.0$"):
        data.worker_items(0, 1, 0, 2.0)


def test_keep_short_clips_without_clip_length_is_refused_as_clip_stride_is():
    """``keep_short_clips=True`` without ``clip_length`` was taken and did nothing (every frame is an item: there is
    no short clip to keep), while ``clip_stride`` without it was refused; both are refused alike."""
    with pytest.raises(ValueError, match=r"^keep_short_clips needs clip_length$"):
        DatasetConfig(keep_short_clips=True)
    with pytest.raises(ValueError, match=r"^keep_short_clips needs clip_length$"):
        replace(DatasetConfig(clip_length=4, keep_short_clips=True), clip_length=None)
    assert DatasetConfig(keep_short_clips=False).keep_short_clips is False  # (the default, without clips)
    assert DatasetConfig(clip_length=4, keep_short_clips=True).keep_short_clips is True


def test_relative_paths_are_the_files_they_named_when_the_dataset_was_made(clips, tmp_path, monkeypatch):
    """A relative cache_dir was kept relative and taken against the working folder when the cache was first used:
    a dataset iterated after an os.chdir (or in a DataLoader worker whose process had changed folder) filled a
    cache elsewhere and found none of its entries. It is made absolute when the config is made. Relative videos
    and landmarks files were kept relative too (Lightning and Hydra change the working folder): the epoch after an
    os.chdir read another file or none. They are made absolute when the dataset is made; the cache key (the
    content's) is the one of the absolute paths."""
    monkeypatch.chdir(tmp_path)
    config = DatasetConfig(tracking=TRACKING, cache_dir="cache")
    assert config.cache_dir == tmp_path / "cache" and config.cache_dir.is_absolute()
    assert DatasetConfig(cache_dir=Path("a/../b")).cache_dir == tmp_path / "a/../b"  # (as named: no symlink resolved)
    assert DatasetConfig(cache_dir=".").cache_dir == tmp_path
    with pytest.raises(ValueError, match=r"^cache_dir '~/cache' starts with '~', which is not expanded .*expanduser"):
        DatasetConfig(cache_dir="~/cache")  # (was a folder "~" in the working folder, without a word)
    assert not (tmp_path / "~").exists()
    (tmp_path / "a.avi").write_bytes(clips[0].video.read_bytes())
    np.save(tmp_path / "a.npy", clips[0].landmarks)
    data = VideoDataset(["a.avi"], ["a.npy"], config)
    assert data.videos == (tmp_path / "a.avi",) and data.landmarks == (tmp_path / "a.npy",)
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    first = next(iter(data))
    assert not bool(first["cached"]) and data.cache.root == tmp_path / "cache"
    assert any((tmp_path / "cache").iterdir()) and not any((tmp_path / "elsewhere").iterdir())
    again = VideoDataset([clips[0].video], [clips[0].landmarks], config)  # (made in the other folder, same config)
    assert bool(next(iter(again))["cached"])


def _no_face(image: np.ndarray) -> None:
    """A module-level detector (pickles by name)."""
    return None


class _NoFace:
    """A module-level detector class (its instances pickle)."""

    def __call__(self, image: np.ndarray) -> None:
        return None


def test_a_detector_that_cannot_be_pickled_is_named_with_what_to_do(clips):
    """A lambda or a function (or class) defined inside a function as the detector failed under a DataLoader worker
    started by spawn or forkserver (macOS's and Windows' default) with pickle's own words ("Can't pickle <function
    <lambda> at 0x...>: attribute lookup <lambda> on __main__ failed", "Can't pickle local object ..."), which name
    neither the dataset nor what to do. It is a PicklingError naming the detector and the way out; copying the
    dataset (no pickling) and module-level detectors are as before."""
    video = clips[0].video

    def local(image: np.ndarray) -> None:
        return None

    class Local:
        def __call__(self, image: np.ndarray) -> None:
            return None

    here = r"\S*test_a_detector_that_cannot_be_pickled_is_named_with_what_to_do\.<locals>"
    for detector, name in ((lambda image: None, rf"{here}\.<lambda>"), (local, rf"{here}\.local"),
                           (Local(), rf"\(an instance of {here}\.Local\)"),
                           (functools.partial(local), rf"\(a functools.partial of {here}\.local\)"),
                           (Local().__call__, rf"\(a method of {here}\.Local\)")):  # fmt: skip
        data = VideoDataset([video], detector)
        with pytest.raises(pickle.PicklingError, match=rf"^VideoDataset's detector {name} cannot be pickled \(Can't "
                           r"pickle .*\), and a DataLoader worker started by spawn or forkserver .*: make the "
                           r"detector a module-level function or an instance of a module-level class .*"
                           r'multiprocessing_context="fork"\), where the platform has it\)$'):  # fmt: skip
            pickle.dumps(data)
        assert copy.copy(data).detector is detector  # (copies do not pickle: as before)
        assert type(copy.deepcopy(data).detector) is type(detector)
    for detector in (_no_face, _NoFace(), functools.partial(_no_face), _NoFace().__call__):
        back = pickle.loads(pickle.dumps(FrameFolderDataset([video.parent], detector)))
        assert type(back.detector) is type(detector) and back.detector(np.zeros((4, 4, 3), np.uint8)) is None
    assert pickle.loads(pickle.dumps(VideoDataset([video], _no_face))).detector is _no_face
    landmarks = pickle.loads(pickle.dumps(VideoDataset([video], [clips[0].landmarks])))  # (no detector: as before)
    assert landmarks.detector is None and np.array_equal(landmarks.landmarks[0], clips[0].landmarks)
    # A spawned worker: refused when it is started (the dataset pickled for it), before it runs.
    loader = DataLoader(VideoDataset([video], lambda image: None), batch_size=None, num_workers=1,
                        multiprocessing_context="spawn")  # fmt: skip
    with warnings.catch_warnings(), pytest.raises(pickle.PicklingError, match=r"<lambda> cannot be pickled"):
        warnings.simplefilter("ignore", UserWarning)  # (torch's "Got pickle error when attempting to start ...")
        next(iter(loader))


def test_videos_shorter_than_clip_length_are_named_once_and_a_dataset_of_none_else_is_an_error(clips, config, tmp_path):
    """A clip dataset whose videos were all shorter than clip_length yielded nothing without a word (a DataLoader
    over it gave no batch), and one with some too short left them out silently. A ShortVideoWarning names them, with
    their frames, once per dataset (not by each DataLoader worker, nor each epoch, nor count_items again); a dataset
    none of whose videos gives a clip is a ValueError at the end of the epoch (each epoch), in the worker too."""
    from training_hooks import ShortVideoWarning

    short = tmp_path / "short.npy"
    np.save(short, read_video_uint8(clips[1].video)[:3].permute(0, 2, 3, 1).numpy())  # (3, H, W, 3): 3 frames
    videos, landmarks = [clips[0].video, short], [clips[0].landmarks, clips[1].landmarks]
    cfg = replace(config, clip_length=4)
    said = (f"VideoDataset: 1 of the 2 videos is shorter than clip_length and gives no clip: {short} (3 frames) "
            "(DatasetConfig.clip_length=4): left out. DatasetConfig(keep_short_clips=True) yields each as one "
            "shorter clip (collate_clips pads them)")  # fmt: skip
    data = VideoDataset(videos, landmarks, cfg)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert [(int(i["video"]), i["frame"].tolist()) for i in data] == [(0, [0, 1, 2, 3])]
        assert len(list(data)) == 1 and data.count_items() == [1, 0]  # (a later epoch, the counts: not again)
    assert [(w.category, str(w.message)) for w in caught] == [(ShortVideoWarning, said)]
    with pytest.warns(ShortVideoWarning) as caught:  # counted first (the cache, filled above, holds both)
        assert VideoDataset(videos, landmarks, cfg).count_items() == [1, 0]
    assert [str(w.message) for w in caught] == [said]
    log = tmp_path / "warnings.txt"

    def show(message, category, filename, lineno, file=None, line=None) -> None:  # (also in the forked workers)
        with open(log, "a") as f:
            f.write(f"{category.__name__}: {message}\n")

    loaded = VideoDataset(videos, landmarks, cfg)  # video 0 -> worker 0, video 1 -> worker 1: the last one warns
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.filterwarnings(  # (Python 3.12+ warns of a fork() in a process with threads: torch's here)
            "ignore", r"This process \(pid=\d+\) is multi-threaded, use of fork\(\)", DeprecationWarning
        )
        warnings.showwarning = show
        assert len(list(DataLoader(loaded, batch_size=None, num_workers=2, multiprocessing_context="fork"))) == 1
        assert loaded.count_items() == [1, 0]  # (the workers' warning is the dataset's: not again)
    assert log.read_text().splitlines() == [f"ShortVideoWarning: {said}"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # keep_short_clips: nothing left out, nothing said
        kept = VideoDataset(videos, landmarks, replace(cfg, keep_short_clips=True))
        assert [i["frame"].tolist() for i in kept] == [[0, 1, 2, 3], [4, 5], [0, 1, 2]]
    # no video long enough: an error naming them all, in one process and through a worker, every epoch
    none = VideoDataset(videos, landmarks, replace(cfg, clip_length=FRAMES + 1))
    error = (f"VideoDataset yields no item: all 2 videos are shorter than clip_length and give no clip: "
             f"{videos[0]} ({FRAMES} frames), {short} (3 frames) (DatasetConfig.clip_length={FRAMES + 1}, "
             "keep_short_clips=False). Set DatasetConfig(keep_short_clips=True) to yield each as one shorter clip "
             "(collate_clips pads them), or a clip_length of at most the shortest video's frames")  # fmt: skip
    for _ in range(2):
        with pytest.raises(ValueError, match=f"^{re.escape(error)}$"):
            list(none)
    with pytest.raises(ValueError, match=re.escape(error)):
        list(DataLoader(none, batch_size=None, num_workers=1, multiprocessing_context="fork"))
    with pytest.warns(ShortVideoWarning, match="all 2 videos are shorter"):  # counting says so, and does not raise
        assert VideoDataset(videos, landmarks, none.config).count_items() == [0, 0]


def test_a_short_video_found_by_a_detector_is_named_with_the_frame_its_face_appears_in(clips, config, tmp_path):
    """With a detector a video's frames are counted from its first face: a 9-frame video whose face appears at frame
    3 was named "(6 frames)" against clip_length=7, a count the user could not match to the file. The frame the
    count starts at is said (from a video file and from a folder of frames, counted without tracking)."""
    from training_hooks import ShortVideoWarning

    video, folder = _black_first(clips[0], tmp_path, 3)
    cfg = replace(config, cache_dir=None, clip_length=FRAMES + 1)
    for data in (VideoDataset([video], _FaceWhereShown(clips[0].landmarks, tmp_path / "calls.txt"), cfg),
                 FrameFolderDataset([folder], _FaceWhereShown(clips[0].landmarks, tmp_path / "calls.txt"), cfg)):
        with pytest.warns(ShortVideoWarning) as caught:
            assert data.count_items() == [0]
        assert [str(w.message) for w in caught] == [
            f"{type(data).__name__}: its only video is shorter than clip_length and gives no clip: {data.videos[0]} "
            f"({FRAMES} frames from frame 3, the detector's first with a face) (DatasetConfig.clip_length={FRAMES + 1})"
            ": left out. DatasetConfig(keep_short_clips=True) yields each as one shorter clip (collate_clips pads them)"
        ]


def test_loader_throughput_measures_another_dataset_of_such_items() -> None:
    """loader_throughput set a VideoDataset's epoch around its pass (RepeatedEpochWarning): another iterable of the
    same dicts (a ChainDataset of two, a user's own) met an AttributeError, no set_epoch; it is measured as it is."""
    from torch.utils.data import ChainDataset, IterableDataset

    class Faces(IterableDataset):
        def __iter__(self):
            for k in range(3):
                yield {"face": torch.zeros(3, 8, 8), "cached": torch.tensor(k % 2 == 0)}

    got = loader_throughput(ChainDataset([Faces(), Faces()]), 0, batch_size=2)
    assert got["faces"] == 6.0 and got["cached_fraction"] == 4 / 6


# --------------------------------------------------------------------------------------------- labels (targets=)


def _without_target(items: dict) -> dict:
    return {k: {name: x for name, x in item.items() if name != "target"} for k, item in items.items()}


def test_each_item_holds_its_videos_label_whatever_the_workers_or_the_order(clips, config):
    """``targets=``: each item of video i holds ``target`` = targets[i] (int64, shape ()) with 0 and 2 workers and
    shuffled, the other keys as without labels; a batch's ``target`` (default collate) is its videos' labels, (B,).
    The labels are a permutation, so an item labelled with its video's index, or another video's label, fails."""
    videos, lms = [c.video for c in clips], [c.landmarks for c in clips]
    labels = [2, 0, 1]
    plain = collect(VideoDataset(videos, lms, config), 0)  # fills the cache
    assert "target" not in next(iter(plain.values()))  # (no targets: the items as they were)
    data = VideoDataset(videos, lms, config, targets=labels)
    assert data.targets.dtype == torch.int64 and data.targets.tolist() == labels
    for workers in (0, 2):
        items = collect(data, workers)
        assert all(i["target"].dtype == torch.int64 and i["target"].shape == () for i in items.values())
        assert {k: int(i["target"]) for k, i in items.items()} == {(v, t): labels[v] for v, t in plain}
        assert_items_equal(plain, _without_target(items), skip=("cached",))
    shuffled = VideoDataset(videos, lms, replace(config, shuffle_buffer=8, seed=5), targets=labels)
    order = [(int(i["video"]), int(i["frame"]), int(i["target"])) for i in shuffled]
    assert order != sorted(order) and sorted(order) == sorted((v, t, labels[v]) for v, t in plain)
    shuffled.set_epoch(1)
    for loader in (DataLoader(data, batch_size=4, num_workers=2), DataLoader(shuffled, batch_size=4, num_workers=2)):
        batches = list(loader)
        assert sum(len(b["video"]) for b in batches) == len(plain)
        for b in batches:
            assert b["target"].shape == b["video"].shape and torch.equal(b["target"], torch.tensor(labels)[b["video"]])


def test_a_clips_label_is_one_per_clip_and_batches_with_collate_clips(clips, config):
    """Clip items hold one label each, as ``video`` (not one per frame); collate_clips batches labels of a shape
    ((2,) floats here, float64 given: the default float dtype) to (B, 2), scalar ones to (B,), with 0 and 2 workers.
    A sequence of ints with a float among them is all floats."""
    videos, lms = [c.video for c in clips], [c.landmarks for c in clips]
    clip_cfg = replace(config, clip_length=4, clip_stride=3, keep_short_clips=True)  # clips (0, 4) and (3, 6)
    labels = np.array([[0.5, -1.0], [2.0, 0.25], [1.5, 3.0]])
    data = VideoDataset(videos, lms, clip_cfg, targets=labels)
    items = list(data)
    assert len(items) == 2 * len(clips)
    expected = torch.tensor(labels, dtype=torch.get_default_dtype())
    for item in items:
        assert item["frame"].shape[0] in (3, 4) and item["target"].shape == (2,)
        assert item["target"].dtype == torch.get_default_dtype()
        assert torch.equal(item["target"], expected[int(item["video"])])
    for workers in (0, 2):
        batches = list(DataLoader(data, batch_size=4, num_workers=workers, collate_fn=collate_clips))
        assert sum(len(b["video"]) for b in batches) == len(items)
        for b in batches:
            assert b["target"].shape == (len(b["video"]), 2) and torch.equal(b["target"], expected[b["video"]])
    mixed = VideoDataset(videos, lms, clip_cfg, targets=[0.5, 1, 2])
    batch = collate_clips(list(mixed))
    assert batch["target"].dtype == torch.get_default_dtype() and batch["target"].shape == (6,)
    assert batch["target"].tolist() == [[0.5, 1.0, 2.0][v] for v in batch["video"].tolist()]


def test_labels_leave_the_cache_keys_as_they_were(clips, config, tmp_path):
    """The cache holds tracking results, not labels: a dataset with labels reads every entry one without them wrote
    and writes none of its own, and one without labels reads those a labelled one wrote; the cache folders'
    files are the same either way."""
    videos, lms = [c.video for c in clips[:2]], [c.landmarks for c in clips[:2]]

    def files(folder: Path) -> list[str]:
        return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())

    plain = collect(VideoDataset(videos, lms, config), 0)  # writes the cache
    written = files(config.cache_dir)
    labelled = VideoDataset(videos, lms, config, targets=[1, 0])
    items = collect(labelled, 0)
    assert all(bool(i["cached"]) for i in items.values()) and [int(items[(v, 0)]["target"]) for v in (0, 1)] == [1, 0]
    assert labelled.stats.cache.hits == 2 and labelled.stats.cache.misses == 0 and labelled.stats.frames_tracked == 0
    assert_items_equal(plain, _without_target(items), skip=("cached",))
    assert files(config.cache_dir) == written
    other = replace(config, cache_dir=tmp_path / "labelled_first")
    collect(VideoDataset(videos, lms, other, targets=[1, 0]), 0)  # writes the cache
    assert files(other.cache_dir) == written
    unlabelled = VideoDataset(videos, lms, other)
    assert all(bool(i["cached"]) for i in collect(unlabelled, 0).values()) and unlabelled.stats.cache.hits == 2


def test_labels_reach_a_spawned_worker_and_a_pickle_as_a_copy_of_their_own(clips, config):
    """A spawned DataLoader worker receives the dataset pickled, labels included; a plain pickle keeps them; the
    dataset holds a copy (the caller's tensor changed later changes no item); a dataset pickled before labels
    existed loads with none."""
    videos, lms = [c.video for c in clips[:2]], [c.landmarks for c in clips[:2]]
    collect(VideoDataset(videos, lms, config), 0)  # fills the cache
    labels = torch.tensor([[1.0, 2.0], [3.0, 4.0]])
    data = VideoDataset(videos, lms, config, targets=labels)
    labels[0, 0] = 9.0
    spawned = DataLoader(data, batch_size=None, num_workers=1, multiprocessing_context="spawn")
    got = {(int(i["video"]), int(i["frame"])): i["target"].tolist() for i in spawned}
    assert got == {(v, t): [[1.0, 2.0], [3.0, 4.0]][v] for v in range(2) for t in range(FRAMES)}
    assert torch.equal(pickle.loads(pickle.dumps(data)).targets, torch.tensor([[1.0, 2.0], [3.0, 4.0]]))
    state = data.__getstate__()
    del state["targets"]
    old = VideoDataset.__new__(VideoDataset)
    old.__setstate__(state)
    assert old.targets is None and "target" not in next(iter(old))


def test_a_folder_datasets_items_hold_their_labels_too(clips, config, tmp_path):
    folder = tmp_path / "frames_a"
    folder.mkdir()
    for t, img in enumerate(read_video_uint8(clips[0].video)):
        cv2.imwrite(str(folder / f"{t:04d}.png"), img.permute(1, 2, 0).flip(-1).numpy())
    data = FrameFolderDataset([folder, folder], [clips[0].landmarks] * 2, config, targets=torch.tensor([5, 3]))
    assert [(int(i["video"]), int(i["target"])) for i in data] == [(0, 5)] * FRAMES + [(1, 3)] * FRAMES


def test_bad_labels_are_refused_when_the_dataset_is_made_naming_targets(clips, config):
    """Each refusal names ``targets`` (and the entry and video at fault) and what to do, before any tracking."""
    videos, lms = [c.video for c in clips], [c.landmarks for c in clips]
    cases = [
        ([0, 1], ValueError, r"targets must have one label per video \(3\), got 2"),
        (np.zeros((2, 4)), ValueError, r"one label per video \(3\), got 2 \(an array of shape \(2, 4\)\)"),
        (torch.tensor(3), TypeError, r"got a 0-d Tensor: one label for every video is \[label\] \* 3"),
        ("abc", TypeError, "targets must be a sequence with one label per video.*got str"),
        ({str(v): 0 for v in videos}, TypeError, r"got dict: one label per video in the order of the videos"),
        ((k for k in range(3)), TypeError, "got generator"),
        ([0, None, 1], TypeError, rf"targets\[1\] \({re.escape(str(videos[1]))}\) is None: every video needs a label"),
        (["happy", "sad", "happy"], TypeError, r"targets\[0\] .* is a str \('happy'\): map class names to ints first"),
        (np.array(["happy", "sad", "happy"]), TypeError, "targets holds strings: map class names to ints"),
        (np.array(["happy", 1, 2], dtype=object), TypeError, r"targets\[0\] .* is a str"),
        ([True, False, True], TypeError, r"targets\[0\] .* is a bool \(True\): give 0 / 1 as ints"),
        (torch.tensor([True, False, True]), TypeError, "targets holds bools"),
        ([1.0, float("nan"), 2.0], ValueError, r"targets\[1\] .* is NaN: a label must be finite"),
        (torch.tensor([[0.0, 1.0], [0.0, float("inf")], [1.0, 0.0]]), ValueError, r"targets\[1\] .* holds inf"),
        ([1.0, 2.0, 1e300], ValueError, r"targets\[2\] .* is 1e\+300, past the range of torch.float32"),
        ([np.zeros(2), np.zeros(3), np.zeros(2)], ValueError, r"targets\[1\] .* has shape \(3,\), targets\[0\] \(2,\)"),
        ([1, 2, 2**70], ValueError, r"targets\[2\] .* past int64's range"),
        ([1j, 2, 3], TypeError, r"targets\[0\] .* must be an int, a float, or an array or tensor of them, got complex"),
    ]
    for targets, error, match in cases:
        with pytest.raises(error, match=match):
            VideoDataset(videos, lms, config, targets=targets)
    with pytest.raises(TypeError):  # (keyword-only: the fourth positional place stays free)
        VideoDataset(videos, lms, config, [0, 1, 2])  # type: ignore[misc]
    assert VideoDataset(videos, lms, config, targets=None).targets is None
    assert VideoDataset(videos, lms, config, targets=np.array([1, 0, 1], dtype=np.uint8)).targets.dtype == torch.int64

    class Column:  # (what NumPy reads through __array__, as a pandas column, df["label"])
        def __array__(self, dtype=None, copy=None):
            return np.array([0.5, 2.0, 1.0])

    assert VideoDataset(videos, lms, config, targets=Column()).targets.tolist() == [0.5, 2.0, 1.0]
