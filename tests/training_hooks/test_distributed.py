"""DDP: the datasets split their videos between the ranks of a torch.distributed group (and between each rank's
DataLoader workers), every item once, each equal to the single-process one; TrackingQualityLogger's epoch
statistics over every rank. Two real gloo processes on the CPU (one run shared by the tests of this file)."""

from __future__ import annotations

import functools
import pickle
import re
import sys
import warnings
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch.utils.data import DataLoader

import training_hooks.datasets
from torchface.synth.io import read_video, read_video_uint8, write_video
from training_hooks import (
    DatasetConfig,
    DistributedWarning,
    FrameFolderDataset,
    RankBalance,
    RepeatedEpochWarning,
    ShortVideoWarning,
    TrackingQualityLogger,
    VideoDataset,
)

from th_data import FRAMES, TRACKING

pytestmark = pytest.mark.skipif(
    not (dist.is_available() and dist.is_gloo_available()), reason="needs torch.distributed with gloo"
)
WORLD = 2
CLIPS = dict(clip_length=4, clip_stride=3, keep_short_clips=True)  # clips (0, 4) and (3, 6) of each video


def keyed(loader) -> dict[tuple[int, int], dict[str, torch.Tensor]]:
    """Every item of one epoch keyed by (video, first frame); an item delivered twice fails."""
    out = {}
    for item in loader:
        k = (int(item["video"]), int(item["frame"].reshape(-1)[0]))
        assert k not in out, f"item {k} delivered twice"
        out[k] = item
    return out


def _rank(rank: int, init_file: str, videos: list[str], landmarks: list, out_dir: str) -> None:
    """One rank: its frame items tracked in 2 forked DataLoader workers (they inherit the group), its clip items
    read back from the cache by 1 spawned worker (no group there: the dataset pickled by the rank carries its
    rank), both without balancing (RankBalance.UNEVEN); the batches of the default, balanced dataset; its quality
    logger, and the (rank, world size) of copies of the dataset unpickled outside the group."""
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=WORLD)
    out: dict[str, object] = {}
    try:
        balanced = DatasetConfig(tracking=TRACKING, cache_dir=Path(out_dir) / "cache")
        config = replace(balanced, rank_balance=RankBalance.UNEVEN)
        data = VideoDataset(videos, landmarks, config)
        clip_data = VideoDataset(videos, landmarks, replace(config, **CLIPS))
        with warnings.catch_warnings():
            warnings.simplefilter("error", DistributedWarning)
            out["frames"] = keyed(DataLoader(data, batch_size=None, num_workers=2, multiprocessing_context="fork"))
            # Every rank's frames are tracked and stored before any rank goes on: rank 1's balanced loader repeats
            # rank 0's video 2, and a rank 0 running late read rank 1's entry in its frames stage (cached=True).
            dist.barrier()
            spawned = DataLoader(clip_data, batch_size=None, num_workers=1, multiprocessing_context="spawn")
            out["clips"] = keyed(spawned)
            loader = DataLoader(VideoDataset(videos, landmarks, balanced), batch_size=4, num_workers=2)
            out["batches"] = [{k: b[k] for k in b if k != "cached"} for b in loader]
        log = TrackingQualityLogger()
        items = list(out["frames"].values())
        for start in range(0, len(items), 4):
            log.update(torch.utils.data.default_collate(items[start : start + 4]))
        out["quality_local"], out["quality_all"] = log.compute(), log.compute(sync_dist=True)
        sent = pickle.dumps(data)
        every = pickle.dumps(VideoDataset(videos, landmarks, DatasetConfig(tracking=TRACKING, shard_ranks=False)))
        dist.barrier()
        out["cache_entries"] = sorted(p.name for p in (Path(out_dir) / "cache").glob("*.npz"))  # (every stage done)
    finally:
        dist.destroy_process_group()
    received = pickle.loads(sent)  # no group here: the sender's (rank, world size) split the videos
    out["received_group"] = received.rank_and_world_size()
    out["received_videos"] = [received.worker_videos(w, 2, *received.rank_and_world_size()) for w in range(2)]
    out["every_group"] = pickle.loads(every).rank_and_world_size()
    out["fresh_group"] = VideoDataset(videos, landmarks, DatasetConfig(tracking=TRACKING)).rank_and_world_size()
    torch.save(out, Path(out_dir) / f"rank{rank}.pt")


@pytest.fixture(scope="module")
def ddp_run(clips, tmp_path_factory) -> list[dict]:
    out_dir = tmp_path_factory.mktemp("ddp")
    videos = [str(c.video) for c in clips]
    landmarks = [c.landmarks for c in clips]
    # forked ranks: no second import of torch and torchface per rank
    args = (str(out_dir / "init"), videos, landmarks, str(out_dir))
    mp.start_processes(_rank, args=args, nprocs=WORLD, join=True, start_method="fork")
    return [torch.load(out_dir / f"rank{r}.pt", weights_only=False) for r in range(WORLD)]


@pytest.fixture(scope="module")
def single(clips, tmp_path_factory) -> dict[str, dict]:
    """The single-process epochs (no process group) the ranks' items must equal (the clips read the frames'
    cache, as the ranks' do)."""
    videos, landmarks = [c.video for c in clips], [c.landmarks for c in clips]
    config = DatasetConfig(tracking=TRACKING, cache_dir=tmp_path_factory.mktemp("ddp_cache"))
    frames = keyed(VideoDataset(videos, landmarks, config))
    clip_items = keyed(VideoDataset(videos, landmarks, replace(config, **CLIPS)))
    return {"frames": frames, "clips": clip_items}


def assert_union_is_every_item_once(per_rank: list[dict], reference: dict) -> None:
    keys = [k for items in per_rank for k in items]
    assert len(keys) == len(set(keys)), "an item came from two ranks"
    assert set(keys) == set(reference)
    for items in per_rank:
        for k, item in items.items():
            assert item.keys() == reference[k].keys()
            for name in item:
                assert torch.equal(item[name], reference[k][name]), f"item {k}: {name} differs"


def test_ranks_split_the_videos_and_their_items_equal_the_single_process_ones(ddp_run, single, clips):
    """Every rank yielded every item (each tracked every video, an epoch showed each item once per rank): now
    rank r gets the videos i % 2 == r, the union is every item once and each equals the one-process item
    (clips read in a spawned DataLoader worker of each rank here)."""
    assert len(single["frames"]) == len(clips) * FRAMES and len(single["clips"]) == len(clips) * 2
    # One entry per video, written by the forked frame workers. More: a spawned clip worker, which imports the code
    # afresh, computed other keys and tracked again (cached False): the code changed on disk during the run (a merge
    # that added a config field changes every key's repr part).
    assert len(ddp_run[0]["cache_entries"]) == len(clips), (
        "a spawned worker computed other cache keys than its rank (was the code changed on disk during the run?)"
    )
    assert_union_is_every_item_once([r["clips"] for r in ddp_run], single["clips"])
    assert [sorted({v for v, _ in r["clips"]}) for r in ddp_run] == [[0, 2], [1]]
    assert all(bool(item["cached"]) for r in ddp_run for item in r["clips"].values())


def test_each_ranks_dataloader_workers_split_its_videos(ddp_run, single):
    """num_workers=2 inside each rank: rank 0's workers track videos 0 and 2, rank 1's worker 0 video 1 (its
    worker 1 has none); every frame item once, equal to the single-process one."""
    assert_union_is_every_item_once([r["frames"] for r in ddp_run], single["frames"])
    # the DataLoader alternates between rank 0's workers: video 0 (worker 0), then video 2 (worker 1)
    assert [k[0] for k in list(ddp_run[0]["frames"])[:2]] == [0, 2]


def test_a_dataset_pickled_in_the_group_keeps_its_rank_where_no_group_is_initialised(ddp_run):
    """A DataLoader worker started by spawn has no process group: the dataset its rank pickled still splits by
    that rank; a dataset built there, or with shard_ranks=False, does not split."""
    assert [r["received_group"] for r in ddp_run] == [(0, WORLD), (1, WORLD)]
    assert [r["received_videos"] for r in ddp_run] == [[[0], [2]], [[1], []]]
    assert [r["every_group"] for r in ddp_run] == [(0, 1), (0, 1)]
    assert [r["fresh_group"] for r in ddp_run] == [(0, 1), (0, 1)]


def test_balanced_ranks_take_the_same_number_of_batches(ddp_run, single):
    """The default RankBalance.PAD: rank 0's workers have 6 frames each (videos 0 and 2), rank 1's worker 0 has
    6 (video 1) and its worker 1 none, so rank 1 took 2 batches of 4 fewer than rank 0 and a DDP loop hung. Now
    rank 1's worker 1 repeats video 2 (its worker's video on rank 0): the same batches on both ranks, every item
    equal to the single-process one."""
    assert [[len(b["frame"]) for b in r["batches"]] for r in ddp_run] == [[4, 4, 2, 2]] * 2
    seen = set()
    for run in ddp_run:
        for batch in run["batches"]:
            for j in range(len(batch["frame"])):
                k = (int(batch["video"][j]), int(batch["frame"][j]))
                seen.add(k)
                for name, value in batch.items():
                    assert torch.equal(value[j], single["frames"][k][name]), f"item {k}: {name} differs"
    assert seen == set(single["frames"])
    assert sorted({int(v) for b in ddp_run[1]["batches"] for v in b["video"]}) == [1, 2]


def test_tracking_quality_logger_syncs_the_epoch_over_the_ranks(ddp_run, single):
    """compute(sync_dist=True) gives the statistics of every rank's frames (the single-process epoch's); compute()
    stays the rank's own."""
    reference = TrackingQualityLogger()
    reference.update(torch.utils.data.default_collate(list(single["frames"].values())))
    expected = reference.compute()
    for run in ddp_run:
        assert run["quality_all"].keys() == expected.keys()
        for name, value in expected.items():
            assert run["quality_all"][name] == pytest.approx(value, rel=1e-9, abs=1e-12), name
    assert [r["quality_local"]["frames"] for r in ddp_run] == [2 * FRAMES, FRAMES]


# --------------------------------------------------------------------------------------------- one process


def test_worker_videos_of_ranks_and_workers(clips, config):
    data = VideoDataset([clips[0].video] * 5, [clips[0].landmarks] * 5, config)
    assert data.worker_videos(1, 2) == [1, 3]  # no group: i % num_workers
    split = {(r, w): data.worker_videos(w, 2, r, 2) for r in range(2) for w in range(2)}
    assert split == {(0, 0): [0, 4], (0, 1): [2], (1, 0): [1], (1, 1): [3]}
    shuffled = VideoDataset([clips[0].video] * 5, [clips[0].landmarks] * 5, replace(config, shuffle_buffer=4))
    parts = [shuffled.worker_videos(w, 2, r, 3) for r in range(3) for w in range(2)]
    assert sorted(i for p in parts for i in p) == list(range(5))
    with pytest.raises(ValueError, match="rank must be in"):
        data.worker_videos(0, 1, 2, 2)
    with pytest.raises(TypeError, match="shard_ranks"):
        DatasetConfig(shard_ranks=1)


def test_a_rank_without_a_video_warns_once(clips, config, monkeypatch):
    """Fewer videos than ranks (3 for 4): rank 3 has none. It repeats video 0's frames (PAD, the default: the
    count of the fullest rank) and says so (DistributedWarning), once per dataset; with DROP every rank yields
    nothing and says so; with shard_ranks=False every rank yields every item, without a warning."""
    monkeypatch.setattr(torch.distributed, "is_available", lambda: True)
    monkeypatch.setattr(torch.distributed, "is_initialized", lambda: True)
    monkeypatch.setattr(torch.distributed, "get_world_size", lambda group=None: 4)
    monkeypatch.setattr(torch.distributed, "get_rank", lambda group=None: 3)
    videos, landmarks = [c.video for c in clips], [c.landmarks for c in clips]
    data = VideoDataset(videos, landmarks, replace(config, cache_dir=None))
    drop = VideoDataset(videos, landmarks, replace(config, cache_dir=None, rank_balance=RankBalance.DROP))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert [(int(it["video"]), int(it["frame"])) for it in data] == [(0, t) for t in range(FRAMES)]
        assert len(list(data)) == FRAMES
        assert list(drop) == []
        monkeypatch.setattr(torch.distributed, "get_rank", lambda group=None: 0)
        assert list(drop) == []  # (rank 0 too, without a second warning)
    assert [type(w.message) for w in caught] == [DistributedWarning] * 2
    assert "rank 3 gets none and repeats items" in str(caught[0].message)
    assert "with RankBalance.DROP every rank yields no item (rank 3 has no video)" in str(caught[1].message)
    one = VideoDataset(videos[:1], landmarks[:1], replace(config, cache_dir=None, shard_ranks=False))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(list(one)) == FRAMES


def test_a_ranks_forgotten_set_epoch_is_told_and_another_ranks_order_is_not(clips, config, monkeypatch):
    """Under DDP each rank holds its own dataset, whose record tells its repeated shuffled order
    (RepeatedEpochWarning) as without a group. The rank and world size are part of the order: one dataset iterated
    as rank 0, then 1, then 0 of 2 (each another order than the last) is not told; rank 0 again is, once; a
    ``set_epoch`` before each epoch never is."""
    rank = [0]
    monkeypatch.setattr(torch.distributed, "is_available", lambda: True)
    monkeypatch.setattr(torch.distributed, "is_initialized", lambda: True)
    monkeypatch.setattr(torch.distributed, "get_world_size", lambda group=None: 2)
    monkeypatch.setattr(torch.distributed, "get_rank", lambda group=None: rank[0])
    videos, landmarks = [c.video for c in clips], [c.landmarks for c in clips]
    shuffled = replace(config, shuffle_buffer=4, rank_balance=RankBalance.UNEVEN)
    data, anew = VideoDataset(videos, landmarks, shuffled), VideoDataset(videos, landmarks, shuffled)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for rank[0] in (0, 1, 0):
            list(data)
        assert caught == []
        for _ in range(2):
            list(data)  # (rank 0 again: told once)
        for epoch in range(3):
            anew.set_epoch(epoch)
            list(anew)
    assert [w.category for w in caught] == [RepeatedEpochWarning]
    assert "epoch 0" in str(caught[0].message) and "data.set_epoch(epoch)" in str(caught[0].message)


# --------------------------------------------------------------------------------------------- equal counts (simulated)


LENGTHS = (6, 2, 5, 3, 4)  # rank 0 of 2: videos 0, 4 (worker 0) and 2 (worker 1); rank 1: 1 (worker 0) and 3


@pytest.fixture
def uneven(clips, tmp_path) -> tuple[list[Path], list]:
    """Five .npy videos of LENGTHS frames (the first frames of the rendered clips)."""
    videos, landmarks = [], []
    for i, n in enumerate(LENGTHS):
        clip = clips[i % len(clips)]
        path = tmp_path / f"v{i}.npy"
        np.save(path, read_video_uint8(clip.video, n).permute(0, 2, 3, 1).numpy())
        videos.append(path)
        landmarks.append(clip.landmarks)
    return videos, landmarks


def simulate(monkeypatch, rank: int, world: int, worker: int = 0, workers: int | None = None) -> None:
    """Make the datasets see rank `rank` of a `world`-rank group, inside DataLoader worker `worker` of `workers`
    (None: the real workers of a DataLoader, or the calling process)."""
    monkeypatch.setattr(torch.distributed, "is_available", lambda: True)
    monkeypatch.setattr(torch.distributed, "is_initialized", lambda: True)
    monkeypatch.setattr(torch.distributed, "get_world_size", lambda group=None: world)
    monkeypatch.setattr(torch.distributed, "get_rank", lambda group=None: rank)
    info = SimpleNamespace(id=worker, num_workers=workers)
    real = torch.utils.data.get_worker_info
    monkeypatch.setattr(training_hooks.datasets, "get_worker_info", real if workers is None else lambda: info)


def epoch(data, monkeypatch, rank: int, world: int, workers: int) -> list[list[tuple[int, int]]]:
    """(video, frame) of the items each worker of simulated rank `rank` yields."""
    out = []
    for worker in range(workers):
        simulate(monkeypatch, rank, world, worker, workers)
        out.append([(int(it["video"]), int(it["frame"])) for it in data])
    return out


def test_ranks_yield_equal_counts_per_worker_by_default(uneven, config, monkeypatch):
    """Videos of 6, 2, 5, 3 and 4 frames on 2 ranks x 2 workers: rank 0's workers had 10 and 5 items, rank 1's 2
    and 3, so a DDP loop hung after rank 1's last batch. Now (RankBalance.PAD, the default) each worker yields as
    many as the same worker of the fullest rank, repeating its own items from its first video on; every item
    equals the single-process one and the union is every item; batch counts are equal in a real DataLoader."""
    videos, landmarks = uneven
    reference = {(int(it["video"]), int(it["frame"])): it for it in VideoDataset(videos, landmarks, config)}
    data = VideoDataset(videos, landmarks, config)
    assert data.config.rank_balance is RankBalance.PAD
    ranks = [epoch(data, monkeypatch, r, 2, 2) for r in range(2)]
    assert [[len(w) for w in r] for r in ranks] == [[10, 5], [10, 5]]
    assert ranks[0] == [[(0, t) for t in range(6)] + [(4, t) for t in range(4)], [(2, t) for t in range(5)]]
    assert ranks[1] == [[(1, t % 2) for t in range(10)], [(3, 0), (3, 1), (3, 2), (3, 0), (3, 1)]]
    assert {k for r in ranks for w in r for k in w} == set(reference)
    assert [data.worker_items(w, 2, r, 2) for r in range(2) for w in range(2)] == [10, 5, 10, 5]
    # the items themselves: the repeated ones equal the originals (rank 1, worker 0, read from the cache)
    simulate(monkeypatch, 1, 2, 0, 2)
    for it in data:
        k = (int(it["video"]), int(it["frame"]))
        assert all(torch.equal(it[name], reference[k][name]) for name in it if name != "cached")
    # a real DataLoader (2 forked workers, which inherit the simulated group): equal batch counts. The workers
    # count the videos' frames for the first epoch only: the counts reach the dataset and the next workers.
    fresh = VideoDataset(videos, landmarks, config)
    batches = []
    for rank in range(2):
        simulate(monkeypatch, rank, 2)
        loader = DataLoader(fresh, batch_size=4, num_workers=2, multiprocessing_context="fork")
        batches.append([len(b["frame"]) for b in loader])
        monkeypatch.setattr(training_hooks.datasets, "_count_frames", None)  # (counting again would fail)
    assert batches[0] == batches[1] == [4, 4, 4, 1, 2]  # per worker: 10 = 4 + 4 + 2, 5 = 4 + 1
    assert fresh.count_items() == list(LENGTHS)


def test_skipped_videos_keep_the_ranks_counts_equal(uneven, config, monkeypatch):
    """``DatasetConfig(keep_going=True)`` under DDP: a skipped video must not leave its rank short of items (DDP hangs
    at the end of the epoch). Video 4 (rank 0, worker 0) fails when tracked (landmarks outside its frame): it keeps
    its count and its worker repeats its other video's items in its place; video 3 (rank 1, worker 1) cannot be read
    at all: it counts 0 on every rank, and its worker repeats those of its worker's videos on the other rank. Every
    worker yields the balanced count, as without a skip."""
    from training_hooks import SkippedVideoWarning

    videos, landmarks = list(uneven[0]), list(uneven[1])
    landmarks[4] = landmarks[4] + 1000.0
    broken = videos[3].with_name("broken.npy")
    broken.write_bytes(b"not an array" * 10)
    videos[3] = broken
    data = VideoDataset(videos, landmarks, replace(config, keep_going=True))
    with pytest.warns(SkippedVideoWarning) as said:
        ranks = [epoch(data, monkeypatch, r, 2, 2) for r in range(2)]
    assert sorted(data.skipped) == [3, 4] and len(said) == 2
    assert [[len(w) for w in r] for r in ranks] == [[10, 5], [10, 5]]
    assert ranks[0] == [[(0, t) for t in range(6)] + [(0, t) for t in range(4)], [(2, t) for t in range(5)]]
    assert ranks[1] == [[(1, t % 2) for t in range(10)], [(2, t) for t in range(5)]]
    assert data.count_items() == [6, 2, 5, 0, 4]
    assert [data.worker_items(w, 2, r, 2) for r in range(2) for w in range(2)] == [10, 5, 10, 5]
    drop = VideoDataset(videos, landmarks, replace(config, keep_going=True, rank_balance=RankBalance.DROP))
    with pytest.warns(SkippedVideoWarning):
        assert [[len(w) for w in epoch(drop, monkeypatch, r, 2, 2)] for r in range(2)] == [[2, 0], [2, 0]]


def test_repeated_items_hold_their_own_videos_label_and_a_skipped_videos_goes_nowhere(uneven, config, monkeypatch):
    """``targets=`` under 2 ranks x 2 workers (RankBalance.PAD): every item holds its video's label, the items a
    short worker repeats too (rank 1's worker 0 repeats video 1 five times, worker 1 video 3); with keep_going, the
    items repeated in a skipped video's place (video 4, rank 0's worker 0: video 0's again) hold video 0's, and no
    item holds the skipped one's. The labels are not the videos' indices."""
    from training_hooks import SkippedVideoWarning

    videos, landmarks = list(uneven[0]), list(uneven[1])
    labels = [3, 1, 4, 0, 2]

    def labelled(data) -> list[list[tuple[int, int, int]]]:
        out = []
        for rank in range(2):
            for worker in range(2):
                simulate(monkeypatch, rank, 2, worker, 2)
                out.append([(int(it["video"]), int(it["frame"]), int(it["target"])) for it in data])
        return out

    def plain(runs) -> list[list[tuple[int, int]]]:
        return [[(v, t) for v, t, _ in run] for run in runs]

    runs = labelled(VideoDataset(videos, landmarks, config, targets=labels))
    unlabelled = VideoDataset(videos, landmarks, config)
    assert plain(runs) == [w for r in range(2) for w in epoch(unlabelled, monkeypatch, r, 2, 2)]  # (the same items)
    assert [len(run) for run in runs] == [10, 5, 10, 5]
    assert all(label == labels[v] for run in runs for v, _, label in run)
    landmarks[4] = landmarks[4] + 1000.0  # (video 4 fails when tracked: its worker repeats video 0's items)
    with pytest.warns(SkippedVideoWarning):
        runs = labelled(VideoDataset(videos, landmarks, replace(config, keep_going=True), targets=labels))
    assert runs[0] == [(0, t, 3) for t in range(6)] + [(0, t, 3) for t in range(4)]
    assert all(label == labels[v] for run in runs for v, _, label in run)
    assert 2 not in {label for run in runs for _, _, label in run}


@pytest.mark.parametrize("mode", [RankBalance.PAD, RankBalance.DROP])
def test_a_worker_left_nothing_to_repeat_says_so_instead_of_ending_short(uneven, config, monkeypatch, mode):
    """Worker 1 repeats from videos 2 (rank 0, 5 items) and 3 (rank 1, 3 items). Each rank holds its own dataset;
    on rank 0 both fail to read (an ``OSError``, e.g. a node's flaky disk), on rank 1 neither does. Rank 0's worker 1
    yielded 0 items where rank 1's yielded 5 (PAD) or 3 (DROP), without a word: DDP hung at the end of the epoch.
    It now raises, naming the skipped videos; the other worker, and the other rank, yield the balanced count."""
    from training_hooks import SkippedVideoWarning

    videos, landmarks = uneven
    cfg = replace(config, keep_going=True, rank_balance=mode)
    target = 5 if mode is RankBalance.PAD else 3
    flaky = VideoDataset(videos, landmarks, cfg)  # rank 0's
    read = flaky._read_or_track

    def failing(index):
        if index in (2, 3):
            raise OSError(5, "Input/output error", str(videos[index]))
        return read(index)

    monkeypatch.setattr(flaky, "_read_or_track", failing)
    fine = VideoDataset(videos, landmarks, cfg)  # rank 1's
    simulate(monkeypatch, 1, 2, 1, 2)
    assert len(list(fine)) == target == fine.worker_items(1, 2, 1, 2)
    simulate(monkeypatch, 0, 2, 0, 2)
    assert len(list(flaky)) == flaky.worker_items(0, 2, 0, 2)  # (worker 0: nothing skipped)
    simulate(monkeypatch, 0, 2, 1, 2)
    with pytest.warns(SkippedVideoWarning), pytest.raises(RuntimeError) as raised:
        list(flaky)
    said = str(raised.value)
    assert said.startswith(f"VideoDataset: DataLoader worker 1 of rank 0 yielded 0 of the {target} items")
    assert "DDP would hang" in said and "RankBalance.UNEVEN" in said
    assert f"its own 1 video (5 items counted): 1 skipped ({videos[2]})" in said
    assert f"the 1 video of its worker on the other ranks, repeated in their place: 1 skipped ({videos[3]})" in said
    assert sorted(flaky.skipped) == [2, 3]


def test_drop_and_uneven_rank_balance(uneven, config, monkeypatch):
    """RankBalance.DROP: each worker yields as few as the same worker of the emptiest rank (the first ones of its
    own); UNEVEN: the rank's own items, as before."""
    videos, landmarks = uneven
    drop = VideoDataset(videos, landmarks, replace(config, rank_balance=RankBalance.DROP))
    assert [epoch(drop, monkeypatch, r, 2, 2) for r in range(2)] == [
        [[(0, 0), (0, 1)], [(2, 0), (2, 1), (2, 2)]],
        [[(1, 0), (1, 1)], [(3, 0), (3, 1), (3, 2)]],
    ]
    assert drop.stats.videos == 4  # video 4 (rank 0, worker 0, after its first 2 items) was not even read
    keep = VideoDataset(videos, landmarks, replace(config, rank_balance=RankBalance.UNEVEN))
    assert [[len(w) for w in epoch(keep, monkeypatch, r, 2, 2)] for r in range(2)] == [[10, 5], [2, 3]]
    # one process (no group): never balanced, every item once
    simulate(monkeypatch, 0, 1)
    assert len(list(drop)) == sum(LENGTHS)
    with pytest.raises(TypeError, match="rank_balance"):
        DatasetConfig(rank_balance="pad")


def test_item_counts_without_tracking(clips, uneven, config, tmp_path, monkeypatch):
    """num_items counts a video file's, a folder's and an array's items without tracking; clip settings apply. A
    rank whose video has no clip (2 frames, clips of 3) repeats those of its worker's videos on other ranks."""
    videos, landmarks = uneven
    folder = tmp_path / "frames"
    folder.mkdir()
    for t, frame in enumerate(read_video_uint8(clips[0].video)):
        cv2.imwrite(str(folder / f"{t}.png"), frame.permute(1, 2, 0).numpy()[..., ::-1])
    data = VideoDataset([clips[0].video, *videos], [clips[0].landmarks, *landmarks], config)
    assert data.count_items() == [FRAMES, *LENGTHS] and data.stats.videos == 0
    clip_data = VideoDataset(videos, landmarks, replace(config, clip_length=3, clip_stride=2))
    with pytest.warns(ShortVideoWarning, match=rf"1 of the 5 videos is shorter .*: {re.escape(str(videos[1]))} \(2 "):
        assert clip_data.count_items() == [2, 0, 2, 1, 1]
    simulate(monkeypatch, 1, 5)  # one video per rank: rank 1's has no clip, the fullest rank's 2
    assert [(int(it["video"]), int(it["frame"][0])) for it in clip_data] == [(0, 0), (0, 2)]
    assert FrameFolderDataset([folder], [clips[0].landmarks], config).count_items() == [FRAMES]


def test_a_video_whose_face_appears_later_is_counted_from_that_frame(clips, config, tmp_path, monkeypatch):
    """With a detector, a video's items are those from the first frame with a face on (the black frames before it
    are searched, not tracked): the counts that balance the ranks are counted so, without tracking, and a rank
    yields exactly the count promised. A 3-black-frame + 6-frame video was counted 9 items (its decoded frames), so
    the rank with a 4-frame video repeated items up to 9 while the other gave 6."""
    late = tmp_path / "late.npy"
    frames = read_video_uint8(clips[0].video)
    np.save(late, torch.cat([torch.zeros(3, *frames.shape[1:], dtype=torch.uint8), frames]).permute(0, 2, 3, 1))
    short = tmp_path / "short.avi"
    write_video(short, read_video(clips[1].video, 4))
    first = {bytes(frames[0].permute(1, 2, 0).numpy()): clips[0].landmarks,
             bytes(read_video_uint8(short)[0].permute(1, 2, 0).numpy()): clips[1].landmarks}  # fmt: skip
    calls = []

    def detector(image: np.ndarray) -> np.ndarray | None:  # the first face frame's ground truth; black: no face
        calls.append(image.max())
        return first[bytes(image)] if image.max() > 0 else None

    for c, counts in ((config, [6, 4]), (replace(config, **CLIPS), [2, 1])):
        data = VideoDataset([late, short], detector, replace(c, cache_dir=None))
        calls.clear()
        assert data.count_items() == counts and data.stats.frames_tracked == 0 and len(calls) == 5
        assert [data.worker_items(0, 1, r, 2) for r in range(2)] == [counts[0]] * 2
        ranks = []
        for r in range(2):
            simulate(monkeypatch, r, 2, 0, 1)
            ranks.append([(int(it["video"]), int(it["frame"].reshape(-1)[0])) for it in data])
        assert [len(r) for r in ranks] == [counts[0]] * 2 and len(calls) == 5  # (searched once: when counted)
        assert {f for v, f in ranks[0]} == ({3, 4, 5, 6, 7, 8} if c.clip_length is None else {3, 6})


def test_a_cached_video_is_counted_without_decoding(clips, config, tmp_path, monkeypatch):
    """Every rank counts every video (RankBalance.PAD), and each video file was decoded through to count its frames,
    at every run start, its tracked sequence in the cache or not. Now a video whose sequence is in the cache (the key
    tracking uses: landmarks as arrays, tensors or files) is hashed and the count stored with it taken, equal to the
    decoded one, for clips too; one not in the cache, with a damaged record or with a detector's landmarks is
    decoded."""
    lengths = [6, 2, 5]
    videos = [tmp_path / f"w{i}.avi" for i in range(3)]
    for path, clip, n in zip(videos, clips, lengths):
        write_video(path, read_video(clip.video, n))
    csv = tmp_path / "lm1.csv"
    np.savetxt(csv, clips[1].landmarks, delimiter=",", fmt="%.17g")
    sources = [clips[0].landmarks, csv, torch.from_numpy(clips[2].landmarks)]
    clip_config = replace(config, **CLIPS)
    decoded = VideoDataset(videos, sources, replace(config, cache_dir=None)).count_items()
    decoded_clips = VideoDataset(videos, sources, replace(clip_config, cache_dir=None)).count_items()
    assert decoded == lengths and decoded_clips == [2, 1, 2]
    tracked = VideoDataset(videos[:2], sources[:2], config)
    assert len(list(tracked)) == 8 and tracked.stats.cache.writes == 2  # videos 0 and 1 are in the cache

    def no_decoding(*args, **kwargs):
        raise AssertionError("a video was decoded to count its frames")

    real_count = training_hooks.datasets._count_frames
    counted: list[Path] = []
    with monkeypatch.context() as m:
        m.setattr(training_hooks.datasets, "_count_frames", no_decoding)
        m.setattr(training_hooks.datasets, "open_frames", no_decoding)
        m.setattr(cv2, "VideoCapture", no_decoding)
        assert VideoDataset(videos[:2], sources[:2], config).count_items() == decoded[:2]
        assert VideoDataset(videos[:2], sources[:2], clip_config).count_items() == decoded_clips[:2]
    monkeypatch.setattr(training_hooks.datasets, "_count_frames", lambda p, *a: counted.append(p) or real_count(p, *a))
    data = VideoDataset(videos, sources, config)
    assert data.count_items() == decoded and counted == [videos[2]] and data.stats.cache.hits == 0
    # a damaged record is not read (the file is left to load(), which deletes it), nor one of another key
    entry = next(data.cache.root.glob("*.npz"))
    key = entry.stem
    assert data.cache.num_frames(key) in lengths[:2] and data.cache.num_frames("0" * 64) is None
    entry.write_bytes(entry.read_bytes()[:-100])
    assert data.cache.num_frames(key) is None and entry.exists()
    counted.clear()
    assert VideoDataset(videos, sources, config).count_items() == decoded and len(counted) == 2
    # a detector's landmarks are not known before the video is searched for its first face (decoded up to it,
    # here its first frame); then the count stored with its sequence is taken where the cache has it (video 0,
    # tracked again if its file was the damaged one), else the video is decoded through (video 2)
    assert len(list(VideoDataset(videos[:1], sources[:1], config))) == lengths[0]
    counted.clear()
    detected = VideoDataset([videos[0], videos[2]], lambda image: clips[0].landmarks, config)
    assert detected.count_items() == [decoded[0], decoded[2]] and counted == [videos[2]]


def test_a_rank_without_a_video_warns_once_in_its_first_worker(clips, config, monkeypatch, tmp_path):
    """Fewer videos than ranks: a DistributedWarning used to come from every DataLoader worker of the rank, in
    every epoch (each worker's copy of the dataset started afresh): 4 for 2 workers and 2 epochs. Now once per
    dataset: worker 0 warns, and the flag it sets is shared with the rank's dataset and the later workers' copies."""
    videos, landmarks = [c.video for c in clips[:1]], [clips[0].landmarks]
    data = VideoDataset(videos, landmarks, replace(config, rank_balance=RankBalance.UNEVEN))
    simulate(monkeypatch, 1, 2)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert list(data) == []
        assert list(data) == []
    assert [str(w.message) for w in caught] == [
        "VideoDataset has 1 videos for 2 torch.distributed ranks: rank 1 gets none and yields no item (DDP training "
        "needs every rank to take the same number of steps: RankBalance.PAD)"
    ]
    log = tmp_path / "warnings.txt"

    def show(message, category, filename, lineno, file=None, line=None) -> None:  # (also in the forked workers)
        with open(log, "a") as f:
            f.write(f"{category.__name__}: {message}\n")

    fresh = VideoDataset(videos, landmarks, config)  # PAD: rank 1 repeats video 0's frames
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.filterwarnings(  # (Python 3.12+ warns of a fork() in a process with threads: torch's here)
            "ignore", r"This process \(pid=\d+\) is multi-threaded, use of fork\(\)", DeprecationWarning
        )
        warnings.showwarning = show
        for _ in range(2):  # two epochs of 2 forked workers
            loader = DataLoader(fresh, batch_size=None, num_workers=2, multiprocessing_context="fork")
            assert len(list(loader)) == FRAMES
        assert len(list(fresh)) == FRAMES  # and in the rank's own process
    assert int(fresh._shared[training_hooks.datasets._WARNED]) == 1  # set in a worker, seen by the rank's dataset
    assert log.read_text().splitlines() == [
        "DistributedWarning: VideoDataset has 1 videos for 2 torch.distributed ranks: rank 1 gets none and repeats "
        "items of other ranks' videos (tracking them again)"
    ]


def test_a_long_count_says_how_far_it_has_got_from_one_process(uneven, config, monkeypatch, capsys):
    """Counting the videos' items (each video file decoded through; with a detector, searched for its first face)
    comes before the first batch under DDP and in count_items(): over 200 videos, minutes without a word. A count
    that takes longer than DatasetConfig.progress_after (here 0: from its first video) says how far it has got on
    stderr, in whole lines, from rank 0's DataLoader worker 0 alone; a count that takes less than the default 5 s,
    one already made, and progress_after=None say nothing; without a stderr (pythonw) nothing is said on stdout."""
    videos, landmarks = uneven
    cfg = replace(config, cache_dir=None, progress_after=0)
    detector = functools.partial(_first_frame_face, {bytes(np.load(v)[0]): lm for v, lm in zip(videos, landmarks)})

    def said() -> list[str]:  # (the seconds as N: a busy machine takes more than 0.5 s)
        return [re.sub(r" in \d+ s\b", " in N s", line) for line in capsys.readouterr().err.splitlines()]

    data = VideoDataset(videos, detector, cfg)
    assert data.count_items() == list(LENGTHS) and data.stats.frames_tracked == 0
    assert said() == [
        "VideoDataset: counting the items of 5 videos: 1 counted in N s (count_items(); each video file is decoded "
        "through, and with a detector searched for its first face, once per dataset: DatasetConfig("
        "progress_after=None) says nothing)",
        "VideoDataset: counted the items of 5 videos in N s",
    ]
    assert data.count_items() == list(LENGTHS) and said() == []  # (counted: nothing to say)
    # under DDP each worker counts its videos on every rank before its first batch (the same path: __iter__)
    for rank, worker in ((1, 0), (0, 1), (0, 0)):
        simulate(monkeypatch, rank, 2, worker, 2)
        assert VideoDataset(videos, landmarks, cfg).worker_items(worker, 2, rank, 2) == [10, 5][worker]
        if (rank, worker) != (0, 0):
            assert said() == []
    assert said() == [
        "VideoDataset: counting the items of 3 videos: 1 counted in N s (to give every rank's worker 0 as many "
        "items, DatasetConfig.rank_balance; each video file is decoded through, and with a detector searched for "
        "its first face, once per dataset: DatasetConfig(progress_after=None) says nothing)",
        "VideoDataset: counted the items of 3 videos in N s",
    ]
    # the first batch: the count, then the wait for the first item (its worker tracks its first video whole)
    assert next(iter(VideoDataset(videos, landmarks, cfg)))["video"] == 0
    assert said()[2:] == [
        "VideoDataset: the first item: 0 videos tracked in N s, v0.npy: 1 frame tracked (each video is tracked whole "
        "before its items are yielded, with a detector from its first face on: DatasetConfig(progress_after=None) "
        "says nothing)",
        "VideoDataset: the first item came in N s",
    ]
    # one long video (here a face from frame 2 on) said nothing until it was counted, a count's last video nothing
    # at all: a line is due at each frame read too
    late = {bytes(np.load(videos[0])[2]): landmarks[0]}
    assert VideoDataset(videos[:1], functools.partial(_first_frame_face, late), cfg).count_items() == [4]
    assert said() == [
        "VideoDataset: counting the items of 1 video: 0 counted in N s, v0.npy: 1 frame searched for its first face "
        "(count_items(); each video file is decoded through, and with a detector searched for its first face, once "
        "per dataset: DatasetConfig(progress_after=None) says nothing)",
        "VideoDataset: counted the items of 1 video in N s",
    ]
    for quiet in (replace(cfg, progress_after=None), replace(cfg, progress_after=DatasetConfig().progress_after)):
        assert VideoDataset(videos, detector, quiet).count_items() == list(LENGTHS)
        assert VideoDataset(videos, landmarks, quiet).worker_items(0, 2, 0, 2) == 10 and said() == []
        assert next(iter(VideoDataset(videos, landmarks, quiet)))["video"] == 0 and said() == []
    with monkeypatch.context() as m:  # no stderr (pythonw, a detached process): nothing said, not on stdout instead
        m.setattr(sys, "stderr", None)
        assert VideoDataset(videos, detector, cfg).count_items() == list(LENGTHS)
    assert capsys.readouterr() == ("", "")


def _first_frame_face(faces: dict[bytes, np.ndarray], image: np.ndarray) -> np.ndarray | None:
    """A stand-in detector: the ground-truth landmarks of a video whose first frame ``image`` is."""
    return faces.get(bytes(image))


def _tracking_log(data, monkeypatch) -> list[int]:
    """The videos `data` reads or tracks (its _read_or_track calls, a skipped one's too), in order."""
    calls: list[int] = []
    real = data._read_or_track
    monkeypatch.setattr(data, "_read_or_track", lambda index: calls.append(index) or real(index))
    return calls


def test_a_repeated_video_is_not_tracked_twice(uneven, config, monkeypatch):
    """Without a cache, the items a worker repeats in place of a skipped video's (DatasetConfig.keep_going) came
    from tracking its first video a second time: rank 0's worker 0 (videos 0 and 4, 6 + 4 items; video 4 fails when
    tracked) read videos [0, 4, 0]. It now repeats the sequence it still holds: [0, 4], the same 10 items. Rank 1's
    worker 0 (video 1 fails, and video 4 where it repeats its worker's videos on rank 0) read [1, 0, 4, 0] to give
    its 10 items (video 0's 6 frames, then 4 of them again); now [1, 0, 4]."""
    from training_hooks import SkippedVideoWarning

    videos, landmarks = list(uneven[0]), list(uneven[1])
    landmarks[4] = landmarks[4] + 1000.0  # (outside its frame: fails when tracked, not when counted)
    cfg = replace(config, cache_dir=None, keep_going=True)
    data = VideoDataset(videos, landmarks, cfg)
    calls = _tracking_log(data, monkeypatch)
    simulate(monkeypatch, 0, 2, 0, 2)
    with pytest.warns(SkippedVideoWarning):
        items = [(int(it["video"]), int(it["frame"])) for it in data]
    assert items == [(0, t) for t in range(6)] + [(0, t) for t in range(4)]
    assert calls == [0, 4] and data.stats.frames_tracked == 6
    landmarks[1] = landmarks[1] + 1000.0
    other = VideoDataset(videos, landmarks, cfg)  # rank 1's
    calls = _tracking_log(other, monkeypatch)
    simulate(monkeypatch, 1, 2, 0, 2)
    with pytest.warns(SkippedVideoWarning):
        items = [(int(it["video"]), int(it["frame"])) for it in other]
    assert items == [(0, t) for t in range(6)] + [(0, t) for t in range(4)]
    assert calls == [1, 0, 4] and other.stats.frames_tracked == 6


def test_a_short_worker_says_what_happened_without_a_skip(uneven, config, monkeypatch):
    """A worker left nothing to repeat blamed skipped videos ("the videos it repeats in place of skipped ones were
    skipped too (none; .skipped says why)") where none was skipped: here its video and its worker's video on the
    other rank were counted one 4-frame clip each, then replaced by 2-frame files before the epoch (0 clips). The
    message now says that, with the counts, and names no skip."""
    videos, landmarks = list(uneven[0][:2]), list(uneven[1][:2])
    np.save(videos[1], np.load(videos[0]))  # (6 frames, as video 0)
    data = VideoDataset(videos, landmarks, replace(config, cache_dir=None, clip_length=4))
    assert data.count_items() == [1, 1]
    for path in videos:
        np.save(path, np.load(path)[:2])
    simulate(monkeypatch, 0, 2, 0, 1)
    with pytest.raises(RuntimeError) as raised:
        list(data)
    said = str(raised.value)
    assert said.startswith("VideoDataset: DataLoader worker 0 of rank 0 yielded 0 of the 1 items")
    assert "skipped" not in said and "DDP would hang" in said
    fewer = "1 gave fewer items when tracked than counted"
    assert f"its own 1 video (1 items counted): {fewer} ({videos[0]}: 0 of 1" in said
    assert f"the 1 video of its worker on the other ranks, repeated in their place: {fewer} ({videos[1]}" in said
    assert f"({videos[1]}: 0 of 1: a file changed or replaced since the dataset counted it?)" in said


def test_two_processes_counting_a_video_that_cannot_be_read_warn_once(uneven, config, monkeypatch, tmp_path):
    """Two processes of one dataset (a rank's DataLoader worker and the rank itself planning its steps with
    count_items(), here two forked processes) counting the same video that cannot be read at the same time: each
    found it not skipped yet when it failed (the first warned before recording it, and its warning took a while to
    show: a busy stderr), and both gave the SkippedVideoWarning. Now a process records the skip before it warns, and
    one that finds it recorded says nothing (and counts it 0)."""
    import multiprocessing
    import time

    videos, landmarks = uneven
    data = VideoDataset(videos, landmarks, replace(config, cache_dir=None, keep_going=True))
    log = tmp_path / "warnings.txt"

    delay = [0.3]  # (set per process: the second fails 0.2 s after the first, while the first's warning shows)

    def slow_failure(path, *args):
        time.sleep(delay[0])  # (both processes fail after both have begun)
        raise training_hooks.datasets.InputError(f"{path}: cannot decode")

    def count(index: int) -> None:
        delay[0] = 0.3 + 0.2 * index

        def show(message, category, filename, lineno, file=None, line=None) -> None:
            time.sleep(0.5)
            with open(log, "a") as f:
                f.write(f"{category.__name__}: {message}\n")

        warnings.simplefilter("always")
        warnings.showwarning = show
        assert data.num_items(3) == 0

    monkeypatch.setattr(training_hooks.datasets, "_count_frames", slow_failure)
    fork = multiprocessing.get_context("fork")
    processes = [fork.Process(target=count, args=(i,)) for i in range(2)]
    for p in processes:
        p.start()
    for p in processes:
        p.join(30)
    assert [p.exitcode for p in processes] == [0, 0]
    assert log.read_text().splitlines() == [
        f"SkippedVideoWarning: skipped {videos[3]} (video 3): cannot decode (DatasetConfig(keep_going=True): its "
        "items are left out; the dataset's .skipped records it)"
    ]
    assert data.skipped == {3: f"{videos[3]}: cannot decode"} and data.count_items()[3] == 0


def test_processes_that_find_a_warning_due_at_the_same_moment_give_it_once(uneven, config, monkeypatch, tmp_path):
    """The once-per-dataset warnings (SkippedVideoWarning of a video, ShortVideoWarning, DistributedWarning) were
    decided by a flag in shared memory, checked, then set: two processes (DataLoader workers ending their passes
    together, a worker and the caller's count_items()) that both checked it within the microseconds before either
    set it both warned. Here two forked processes are held at a barrier right there, after the check: with the
    flags alone (the dataset's claims removed, as a dataset pickled before them has none) both warn; with the
    claims (a marker created with O_CREAT | O_EXCL in the dataset's private folder) exactly one does."""
    import multiprocessing

    fork = multiprocessing.get_context("fork")
    videos, landmarks = uneven
    real = VideoDataset._claim

    def fail(path, *args):
        raise training_hooks.datasets.InputError(f"{path}: cannot decode")

    def race(data: VideoDataset, act, name: str) -> list[str]:
        log = tmp_path / f"{name}.txt"
        barrier = fork.Barrier(2, timeout=20)

        def claim(self, what: str) -> bool:  # both processes have found the flag unset: the window
            barrier.wait()
            return real(self, what)

        def show(message, category, *args, **kwargs) -> None:
            with log.open("a") as f:
                f.write(f"{category.__name__}\n")

        def run() -> None:
            warnings.simplefilter("ignore")
            warnings.simplefilter("always", UserWarning)  # (the dataset's warnings)
            warnings.showwarning = show
            act(data)

        with monkeypatch.context() as m:
            m.setattr(VideoDataset, "_claim", claim)
            processes = [fork.Process(target=run) for _ in range(2)]
            for p in processes:
                p.start()
            for p in processes:
                p.join(30)
        assert [p.exitcode for p in processes] == [0, 0]
        return log.read_text().splitlines()

    monkeypatch.setattr(training_hooks.datasets, "_count_frames", fail)
    cases = {
        "SkippedVideoWarning": (dict(keep_going=True), lambda data: data.num_items(3)),
        "ShortVideoWarning": (dict(clip_length=5), lambda data: data._report_short(0, 1, final=False)),
        "DistributedWarning": ({}, lambda data: data._warn_distributed(6, 8)),  # (8 ranks, 5 videos)
    }
    for category, (settings, act) in cases.items():
        for claims, count in ((False, 2), (True, 1)):
            data = VideoDataset(videos, landmarks, replace(config, cache_dir=None, **settings))
            if category == "ShortVideoWarning":
                for i, n in enumerate(LENGTHS):  # (every video's frames known: the warning is due)
                    data._record_frames(i, n)
            if not claims:
                data._claims = None
            assert race(data, act, f"{category}-{claims}") == [category] * count, (category, claims)
        if category == "SkippedVideoWarning":
            assert data.skipped == {3: f"{videos[3]}: cannot decode"}  # (recorded once, whole)


def test_a_rank_of_uneven_ranks_finds_a_dataset_with_no_clip_at_all(uneven, config, monkeypatch):
    """Under DDP with RankBalance.UNEVEN a rank knew only its own videos' frame counts: a dataset none of whose
    videos gives a clip yielded nothing on every rank without a word (the ValueError of one process never came).
    A rank whose own videos give no clip counts the others' (until one gives a clip): the error where none does,
    nothing where another rank's video has a clip."""
    videos, landmarks = uneven
    cfg = replace(config, rank_balance=RankBalance.UNEVEN)
    simulate(monkeypatch, 1, 2)  # rank 1: videos 1 and 3 (2 and 3 frames)
    with pytest.raises(ValueError, match=r"^VideoDataset yields no item: all 5 videos are shorter than clip_length"):
        list(VideoDataset(videos, landmarks, replace(cfg, clip_length=max(LENGTHS) + 1)))
    with pytest.warns(ShortVideoWarning):  # (video 0, 6 frames, gives rank 0 a clip: rank 1 yields none, no error)
        assert list(VideoDataset(videos, landmarks, replace(cfg, clip_length=max(LENGTHS)))) == []
