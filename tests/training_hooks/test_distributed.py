"""DDP: the datasets split their videos between the ranks of a torch.distributed group (and between each rank's
DataLoader workers), every item once, each equal to the single-process one; TrackingQualityLogger's epoch
statistics over every rank. Two real gloo processes on the CPU (one run shared by the tests of this file)."""

from __future__ import annotations

import pickle
import warnings
from dataclasses import replace
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch.utils.data import DataLoader

from training_hooks import DatasetConfig, DistributedWarning, TrackingQualityLogger, VideoDataset

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
    rank), its quality logger, and the (rank, world size) of copies of the dataset unpickled outside the group."""
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=WORLD)
    out: dict[str, object] = {}
    try:
        config = DatasetConfig(tracking=TRACKING, cache_dir=Path(out_dir) / "cache")
        data = VideoDataset(videos, landmarks, config)
        clip_data = VideoDataset(videos, landmarks, replace(config, **CLIPS))
        with warnings.catch_warnings():
            warnings.simplefilter("error", DistributedWarning)
            out["frames"] = keyed(DataLoader(data, batch_size=None, num_workers=2, multiprocessing_context="fork"))
            spawned = DataLoader(clip_data, batch_size=None, num_workers=1, multiprocessing_context="spawn")
            out["clips"] = keyed(spawned)
        log = TrackingQualityLogger()
        items = list(out["frames"].values())
        for start in range(0, len(items), 4):
            log.update(torch.utils.data.default_collate(items[start : start + 4]))
        out["quality_local"], out["quality_all"] = log.compute(), log.compute(sync_dist=True)
        sent = pickle.dumps(data)
        every = pickle.dumps(VideoDataset(videos, landmarks, DatasetConfig(tracking=TRACKING, shard_ranks=False)))
        dist.barrier()
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
    """Fewer videos than ranks: rank 3 of 4 yields nothing and says so (DistributedWarning), once per dataset;
    with shard_ranks=False every rank yields every item, without a warning."""
    monkeypatch.setattr(torch.distributed, "is_available", lambda: True)
    monkeypatch.setattr(torch.distributed, "is_initialized", lambda: True)
    monkeypatch.setattr(torch.distributed, "get_world_size", lambda group=None: 4)
    monkeypatch.setattr(torch.distributed, "get_rank", lambda group=None: 3)
    videos, landmarks = [c.video for c in clips], [c.landmarks for c in clips]
    data = VideoDataset(videos, landmarks, replace(config, cache_dir=None))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert list(data) == [] and list(data) == []
    assert [type(w.message) for w in caught] == [DistributedWarning]
    assert "rank 3 gets none" in str(caught[0].message)
    one = VideoDataset(videos[:1], landmarks[:1], replace(config, cache_dir=None, shard_ranks=False))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(list(one)) == FRAMES
