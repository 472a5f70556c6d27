"""The Lightning adapter (skipped when Lightning is not installed) and the guarantee that torchface and
training_hooks import without it."""

from __future__ import annotations

import math
import subprocess
import sys
import warnings
from dataclasses import replace

import pytest
import torch
from torch.utils.data import DataLoader

from training_hooks import VideoDataset, tracking_quality
from training_hooks.hooks import TrackingQualityLogger

# Lightning 2.x's pytree helper makes a torch LeafSpec, which torch 2.10+ deprecates: a third-party FutureWarning,
# ignored by its message, category and the module it is attributed to. A mark, not pyproject's filterwarnings: a
# command line's ``-W error`` takes precedence over the configuration's filters, not over a mark's.
pytestmark = pytest.mark.filterwarnings(
    r"ignore:`isinstance\(treespec, LeafSpec\)` is deprecated:FutureWarning:lightning\.pytorch\.utilities\._pytree"
)


def test_imports_do_not_need_lightning():
    code = (
        "import sys, torchface, training_hooks, training_hooks.datasets, training_hooks.hooks;"
        "bad = [m for m in sys.modules if m.split('.')[0] in ('lightning', 'pytorch_lightning')];"
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


pl = pytest.importorskip("lightning.pytorch", reason="PyTorch Lightning is not installed (optional extra 'lightning')")


class TinyModel(pl.LightningModule):
    """A linear classifier of the mean face colour, trained with the confidence-weighted loss."""

    def __init__(self) -> None:
        super().__init__()
        self.net = torch.nn.Linear(3, 2)

    def training_step(self, batch, batch_idx):
        from training_hooks import confidence_weighted_loss

        logits = self.net(batch["face"].mean((-1, -2)))
        loss = torch.nn.functional.cross_entropy(logits, batch["video"] % 2, reduction="none")
        return confidence_weighted_loss(loss, batch["confidence"])

    def validation_step(self, batch, batch_idx):
        pass

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


class Recorder(TinyModel):
    """TinyModel that records the (video, frame) items of each epoch's training batches, in order."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: dict[int, list[tuple[int, int]]] = {}

    def training_step(self, batch, batch_idx):
        order = self.seen.setdefault(self.current_epoch, [])
        order.extend(zip(batch["video"].tolist(), batch["frame"].tolist()))
        return super().training_step(batch, batch_idx)


# TinyModel has a validation_step; a module without validation data has Lightning say it skips the loop (its notice,
# right for these tests' model; before, the module's [] drew "Total length of `list` across ranks is zero" instead).
NO_VAL_NOTICE = pytest.mark.filterwarnings(r"ignore:You defined a `validation_step` but have no `val_dataloader`")


def test_callback_logs_batch_and_epoch_quality(clips, config):
    from training_hooks.lightning import TrackedFaceDataModule, TrackingQualityCallback

    data = VideoDataset([c.video for c in clips[:2]], [c.landmarks for c in clips[:2]], config)
    items = list(data)  # fills the cache; the reference statistics
    batches = list(DataLoader(data, batch_size=4))
    expected = TrackingQualityLogger()
    for b in batches:
        expected.update(b)
    callback = TrackingQualityCallback()
    trainer = pl.Trainer(
        max_epochs=1, callbacks=[callback], logger=False, enable_checkpointing=False, enable_progress_bar=False,
        enable_model_summary=False, accelerator="cpu", num_sanity_val_steps=0,
    )  # fmt: skip
    module = TrackedFaceDataModule(data, val=data, batch_size=4, num_workers=0)
    trainer.fit(TinyModel(), datamodule=module)
    metrics = {k: float(v) for k, v in trainer.callback_metrics.items()}
    epoch = expected.compute()
    assert epoch["frames"] == len(items)
    for stage in ("train_epoch", "val_epoch"):
        for key in ("confidence_mean", "confidence_min", "success_fraction", "yaw_deg_std", "cached_fraction"):
            name = f"tracking/{stage}/{key}"
            assert math.isclose(metrics[name], epoch[key], rel_tol=1e-5, abs_tol=1e-6), (name, epoch[key])
    # the last training batch's own statistics were logged per step
    last = tracking_quality(batches[-1])
    assert math.isclose(metrics["tracking/train/confidence_mean"], last["confidence_mean"], rel_tol=1e-5)


def test_datamodule_picks_the_clip_collate_and_checks_input(clips, config):
    from training_hooks.lightning import TrackedFaceDataModule

    clip_cfg = replace(config, clip_length=4, keep_short_clips=True)
    clip_data = VideoDataset([clips[0].video], [clips[0].landmarks], clip_cfg)
    batch = next(iter(TrackedFaceDataModule(clip_data, batch_size=2).train_dataloader()))
    assert batch["face"].shape[:2] == (2, 4) and batch["frame_mask"].sum(1).tolist() == [4, 2]
    assert TrackedFaceDataModule(clip_data).val_dataloader() == []
    with pytest.raises(TypeError, match="VideoDataset"):
        TrackedFaceDataModule([1, 2, 3])
    # counts as the settings take them: 2.5 was cut to 2 and True taken as a batch of 1
    for bad in (2.5, True, "8"):
        with pytest.raises(TypeError, match="batch_size"):
            TrackedFaceDataModule(clip_data, batch_size=bad)
    with pytest.raises(ValueError, match="num_workers"):
        TrackedFaceDataModule(clip_data, num_workers=-1)


@NO_VAL_NOTICE
def test_datamodule_shuffles_each_epoch_anew_with_the_trainers_defaults(clips, config):
    """Lightning builds the training loader once and calls ``set_epoch`` on samplers alone (an iterable dataset's
    loader has none): with the trainer's defaults every epoch repeated epoch 0's shuffled order. Each epoch now
    yields the order of ``set_epoch(epoch)``, as with ``reload_dataloaders_every_n_epochs=1``."""
    from training_hooks.lightning import TrackedFaceDataModule

    data = VideoDataset([c.video for c in clips[:2]], [c.landmarks for c in clips[:2]], replace(config, shuffle_buffer=8))
    expected = []
    for epoch in range(3):
        data.set_epoch(epoch)
        expected.append([(int(i["video"]), int(i["frame"])) for i in data])
    assert expected[0] != expected[1] and expected[1] != expected[2]

    module = Recorder()
    trainer = pl.Trainer(
        max_epochs=3, logger=False, enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
        accelerator="cpu", num_sanity_val_steps=0,
    )  # fmt: skip
    trainer.fit(module, datamodule=TrackedFaceDataModule(data, batch_size=4, num_workers=0))
    assert [module.seen[e] for e in range(3)] == expected


def test_the_datamodules_loaders_never_tell_a_repeated_order(clips, config):
    """RepeatedEpochWarning tells a plain loop that repeats a shuffled order (no ``set_epoch`` between two
    iterations). The module's loaders call ``set_epoch`` before each iteration: the training one the trainer's
    epoch, the validation one its dataset's own (a shuffled validation set, iterated by the sanity check and every
    epoch in one order: by design), with a trainer and without. None is told. (Without a trainer the training loader
    leaves the epoch to the loop: test_a_plain_loop_over_the_datamodules_training_loader.)"""
    from training_hooks import RepeatedEpochWarning
    from training_hooks.lightning import TrackedFaceDataModule

    shuffled = replace(config, shuffle_buffer=8)
    data = VideoDataset([c.video for c in clips[:2]], [c.landmarks for c in clips[:2]], shuffled)
    val = VideoDataset([clips[2].video], [clips[2].landmarks], shuffled)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        trainer = pl.Trainer(
            max_epochs=2, logger=False, enable_checkpointing=False, enable_progress_bar=False,
            enable_model_summary=False, accelerator="cpu",
        )  # fmt: skip
        trainer.fit(TinyModel(), datamodule=TrackedFaceDataModule(data, val=val, batch_size=4))
        module = TrackedFaceDataModule(data, val=val, batch_size=4)  # no trainer
        train, validation = module.train_dataloader(), module.val_dataloader()
        for epoch in range(2):
            module.train.set_epoch(epoch)  # (the loop's own epochs)
            assert list(train) and list(validation)
    assert not [w for w in caught if issubclass(w.category, RepeatedEpochWarning)]
    assert val.epoch == 0
    with pytest.warns(RepeatedEpochWarning):  # (a plain loop over either is told)
        for _ in range(2):
            list(DataLoader(val, batch_size=4))


def test_a_plain_loop_over_the_datamodules_training_loader(clips, config):
    """Without a trainer the training loader set its dataset's own epoch before each iteration, so a plain loop
    over ``module.train_dataloader()`` that forgot ``set_epoch`` repeated the first epoch's shuffled order every
    epoch without a word. It now sets none, as a plain ``DataLoader``: the forgotten ``set_epoch`` is told, and the
    loop's own ``module.train.set_epoch(epoch)`` draws a new order each epoch."""
    from training_hooks import RepeatedEpochWarning
    from training_hooks.lightning import TrackedFaceDataModule

    shuffled = replace(config, shuffle_buffer=8)
    videos, landmarks = [c.video for c in clips[:2]], [c.landmarks for c in clips[:2]]
    module = TrackedFaceDataModule(VideoDataset(videos, landmarks, shuffled), batch_size=4)
    loader = module.train_dataloader()
    with pytest.warns(RepeatedEpochWarning, match="set_epoch"):
        orders = [[(int(v), int(f)) for b in loader for v, f in zip(b["video"], b["frame"])] for _ in range(2)]
    assert orders[0] == orders[1] and module.train.epoch == 0  # (the order the warning tells of)
    module = TrackedFaceDataModule(VideoDataset(videos, landmarks, shuffled), batch_size=4)
    loader = module.train_dataloader()
    with warnings.catch_warnings():
        warnings.simplefilter("error", RepeatedEpochWarning)
        orders = []
        for epoch in range(2):
            module.train.set_epoch(epoch)
            orders.append([(int(v), int(f)) for b in loader for v, f in zip(b["video"], b["frame"])])
    assert orders[0] != orders[1] and sorted(orders[0]) == sorted(orders[1])


def test_datamodule_passes_the_loader_settings_through(clips, config):
    """``TrackedFaceDataModule`` took batch size, workers and collate alone: ``pin_memory``, ``persistent_workers``,
    ``prefetch_factor``, ``multiprocessing_context``, ``drop_last`` and ``timeout`` were a TypeError. Both loaders get
    them (``drop_last`` the training one only); the defaults: persistent workers when there are workers, pinned
    memory when the trainer runs on a CUDA device; settings a ``DataLoader`` would refuse later are refused here."""
    from types import SimpleNamespace

    from training_hooks.lightning import TrackedFaceDataModule

    data = VideoDataset([clips[0].video], [clips[0].landmarks], config)
    module = TrackedFaceDataModule(
        data, val=data, batch_size=2, num_workers=2, pin_memory=False, persistent_workers=False, prefetch_factor=3,
        multiprocessing_context="spawn", drop_last=True, timeout=30.0,
    )  # fmt: skip
    for loader, last in ((module.train_dataloader(), True), (module.val_dataloader(), False)):
        assert (loader.num_workers, loader.pin_memory, loader.persistent_workers, loader.prefetch_factor) == (2, False,
                                                                                                            False, 3)
        assert loader.multiprocessing_context.get_start_method() == "spawn"
        assert (loader.drop_last, loader.timeout) == (last, 30.0)
    # defaults: persistent workers with workers (none to keep without), pinning as the trainer's device says
    defaults = TrackedFaceDataModule(data, val=data, num_workers=2)
    assert defaults.train_dataloader().persistent_workers and defaults.val_dataloader().persistent_workers
    assert not TrackedFaceDataModule(data).train_dataloader().persistent_workers
    assert not defaults.train_dataloader().pin_memory  # (no trainer)
    for device, pinned in (("cuda", True), ("cpu", False)):
        defaults.trainer = SimpleNamespace(strategy=SimpleNamespace(root_device=torch.device(device)), current_epoch=0)
        assert defaults.val_dataloader().pin_memory is pinned
    defaults.trainer = None
    for bad, error, says in (
        (dict(persistent_workers=True), ValueError, "persistent_workers=True needs num_workers > 0"),
        (dict(prefetch_factor=2), ValueError, "prefetch_factor=2 needs num_workers > 0"),
        (dict(multiprocessing_context="spawn"), ValueError, "needs num_workers > 0"),
        (dict(timeout=5), ValueError, "timeout=5.0 needs num_workers > 0"),
        (dict(num_workers=1, multiprocessing_context="spwan"), ValueError, "multiprocessing_context must be one of"),
        (dict(num_workers=1, multiprocessing_context=3), TypeError, "multiprocessing_context must be"),
        (dict(num_workers=1, prefetch_factor=0), ValueError, "prefetch_factor"),
        (dict(num_workers=1, timeout=-1.0), ValueError, "timeout must be finite seconds >= 0"),
        (dict(num_workers=1, timeout=float("nan")), ValueError, "timeout must be finite seconds >= 0"),
        (dict(pin_memory="yes"), TypeError, "pin_memory"),
        (dict(drop_last=1), TypeError, "drop_last"),
    ):
        with pytest.raises(error, match=says):
            TrackedFaceDataModule(data, **bad)


@NO_VAL_NOTICE
def test_datamodule_persistent_workers_shuffle_each_epoch_anew(clips, config, capfd):
    """Two persistent workers (the default with workers) over three epochs of a trainer: each epoch's items are the
    epoch's ``set_epoch`` order of two workers (the workers, kept, see the epoch through the dataset's shared
    memory), and the same whatever torch's random state (the shuffling is seeded by ``DatasetConfig.seed``). No
    worker tells a RepeatedEpochWarning (the loader calls ``set_epoch`` before each epoch)."""
    from torch.utils.data import DataLoader

    from training_hooks.lightning import TrackedFaceDataModule

    shuffled = replace(config, shuffle_buffer=8)
    data = VideoDataset([c.video for c in clips[:2]], [c.landmarks for c in clips[:2]], shuffled)
    expected = []
    for epoch in range(3):
        data.set_epoch(epoch)  # (fills the cache: the workers read it)
        order = [(v, f) for b in DataLoader(data, batch_size=4, num_workers=2)
                 for v, f in zip(b["video"].tolist(), b["frame"].tolist())]  # fmt: skip
        expected.append(order)
    assert expected[0] != expected[1] and expected[1] != expected[2]

    torch.manual_seed(1234)
    module = Recorder()
    data.set_epoch(0)
    datamodule = TrackedFaceDataModule(data, batch_size=4, num_workers=2)
    trainer = pl.Trainer(
        max_epochs=3, logger=False, enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
        accelerator="cpu", num_sanity_val_steps=0,
    )  # fmt: skip
    capfd.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("always")  # (the forked workers keep the filter and the writer to stderr)
        warnings.showwarning = lambda message, category, *args, **kwargs: print(f"{category.__name__}: {message}",
                                                                                file=sys.stderr, flush=True)
        trainer.fit(module, datamodule=datamodule)
    assert "RepeatedEpochWarning" not in capfd.readouterr().err
    assert datamodule.persistent_workers
    assert [module.seen[e] for e in range(3)] == expected


@NO_VAL_NOTICE
def test_datamodule_without_validation_data_runs_no_validation_loop_without_a_word(clips, config):
    """Without ``val``, the module's ``val_dataloader`` gave ``[]``, which the trainer asked for and warned about at
    every fit ("Total length of `list` across ranks is zero. Please make sure this was your intention."). It now
    shows as not implemented, as in a ``LightningDataModule`` without one: no validation, no such warning (Lightning's
    own "no `val_dataloader`" notice for a module with a ``validation_step``). With ``val``, validation runs."""
    import copy
    import pickle
    import warnings

    from lightning.pytorch.utilities.model_helpers import is_overridden

    from training_hooks.lightning import TrackedFaceDataModule

    data = VideoDataset([clips[0].video], [clips[0].landmarks], config)
    list(data)  # (fills the cache)
    none = TrackedFaceDataModule(data, batch_size=4)
    assert not is_overridden("val_dataloader", none) and none.val_dataloader() == []
    assert is_overridden("val_dataloader", TrackedFaceDataModule(data, val=data))
    for again in (pickle.loads(pickle.dumps(none)), copy.deepcopy(none)):
        assert not is_overridden("val_dataloader", again) and again.val_dataloader() == []
        assert again.val_dataloader.args[0] is again  # (bound to the copy, not to the original)

    class Counting(TinyModel):
        validated = 0

        def validation_step(self, batch, batch_idx):
            Counting.validated += 1

    for module, expected in ((none, 0), (TrackedFaceDataModule(data, val=data, batch_size=4), 2)):
        Counting.validated = 0
        trainer = pl.Trainer(
            max_epochs=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
            enable_model_summary=False, accelerator="cpu", num_sanity_val_steps=0,
        )  # fmt: skip
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            trainer.fit(Counting(), datamodule=module)
        assert Counting.validated == expected
        assert not [w for w in caught if "Total length" in str(w.message)], [str(w.message) for w in caught]


@NO_VAL_NOTICE
def test_datamodule_validates_on_a_subclass_loader_or_a_val_set_in_setup(clips, config):
    """The module without ``val`` hid ``val_dataloader`` behind an instance attribute made in ``__init__``: a
    subclass's own ``val_dataloader`` was never called (the trainer saw none, and calling it gave ``[]``), and a
    ``val`` set in ``setup`` (Lightning's place for datasets) ran no validation, without a word. Both validate, as
    before that change; a module that never gets ``val`` still shows none."""
    from lightning.pytorch.utilities.model_helpers import is_overridden

    from training_hooks.lightning import TrackedFaceDataModule

    data = VideoDataset([clips[0].video], [clips[0].landmarks], config)
    list(data)  # (fills the cache)

    class OwnLoader(TrackedFaceDataModule):
        def val_dataloader(self):
            return DataLoader(data, batch_size=4)

    class ValInSetup(TrackedFaceDataModule):
        def setup(self, stage):
            self.val = data

    class Counting(TinyModel):
        validated = 0

        def validation_step(self, batch, batch_idx):
            Counting.validated += 1

    assert is_overridden("val_dataloader", OwnLoader(data)) and isinstance(OwnLoader(data).val_dataloader(), DataLoader)
    for module, expected in ((OwnLoader(data, batch_size=4), 2), (ValInSetup(data, batch_size=4), 2),
                             (TrackedFaceDataModule(data, batch_size=4), 0)):  # fmt: skip
        Counting.validated = 0
        trainer = pl.Trainer(
            max_epochs=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
            enable_model_summary=False, accelerator="cpu", num_sanity_val_steps=0,
        )  # fmt: skip
        trainer.fit(Counting(), datamodule=module)
        assert Counting.validated == expected, type(module).__name__


class _SlowFrames:
    """``open_frames``' reader of a slow machine: ``delay`` seconds before each frame after the first."""

    def __init__(self, reader, delay: float) -> None:
        self.reader, self.delay, self.info, self.read = reader, delay, reader.info, 0

    def __iter__(self):
        return self

    def __next__(self):
        if self.read:
            import time

            time.sleep(self.delay)
        self.read += 1
        return next(self.reader)

    def close(self) -> None:
        self.reader.close()


def test_datamodule_timeout_is_the_wait_for_a_whole_videos_tracking(clips, config, monkeypatch):
    """The documented limit of ``timeout`` (docs/training-hooks.md): a worker yields nothing of a video before it has
    tracked all of it, so a timeout longer than any one frame's reading and tracking (here 2 s against 1 s a frame)
    but shorter than the video's (5 s for its 6 frames) trips at the first batch. The reader is slowed in the
    forked worker; the first item waits for the whole video, not for its frame."""
    import training_hooks.datasets as datasets_module
    from training_hooks.lightning import TrackedFaceDataModule

    opened = datasets_module.open_frames
    monkeypatch.setattr(datasets_module, "open_frames", lambda *a, **k: _SlowFrames(opened(*a, **k), 1.0))
    data = VideoDataset([clips[0].video], [clips[0].landmarks], replace(config, cache_dir=None))
    loader = TrackedFaceDataModule(data, batch_size=1, num_workers=1, multiprocessing_context="fork", timeout=2.0,
                                   persistent_workers=False).train_dataloader()  # fmt: skip
    batches = iter(loader)
    with pytest.raises(RuntimeError, match=r"DataLoader timed out after 2(\.0)? seconds"):
        next(batches)
    for worker in batches._workers:  # (stop the sleeping worker now, not after the loader's 5 s join)
        worker.terminate()
    del batches
