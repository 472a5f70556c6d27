"""PyTorch Lightning adapter (optional: needs ``pip install "torchface[lightning]"``).

- :class:`TrackingQualityCallback` logs :func:`~training_hooks.hooks.tracking_quality` of every batch (per step)
  and of the epoch through ``pl_module.log_dict``, for training and validation;
- :class:`TrackedFaceDataModule` wraps the tracked datasets in ``DataLoader`` s (workers, the right collate, the
  epoch passed to the shuffling).

This module imports Lightning (``lightning.pytorch``, else the older ``pytorch_lightning``); nothing else in
torchface or :mod:`training_hooks` does, so they work without it.
"""

from __future__ import annotations

import functools
import math
import multiprocessing
from collections.abc import Callable, Iterator, Mapping
from multiprocessing.context import BaseContext
from typing import Any

from torch.utils.data import DataLoader

try:
    import lightning.pytorch as pl
except ImportError:  # pragma: no cover - depends on what is installed
    try:
        import pytorch_lightning as pl  # type: ignore[no-redef]
    except ImportError:
        raise ImportError(
            "training_hooks.lightning needs PyTorch Lightning: pip install \"torchface[lightning]\" (or lightning)"
        ) from None

from torchface.extending import check_bool, check_int, check_optional_int, check_real
from training_hooks.collate import collate_clips
from training_hooks.datasets import VideoDataset
from training_hooks.hooks import TrackingQualityLogger

__all__ = ["TrackedFaceDataModule", "TrackingQualityCallback"]


class TrackingQualityCallback(pl.Callback):
    """Log the tracking quality of the batches a module trains and validates on.

    Per batch (``on_step``) it logs ``<prefix>train/<stat>`` (or ``val/``), and at the end of each epoch
    ``<prefix>train_epoch/<stat>`` over every frame of the epoch (:class:`~training_hooks.hooks.TrackingQualityLogger`),
    with ``<stat>`` the keys of :func:`~training_hooks.hooks.tracking_quality`. Under DDP the step statistics are
    the rank's own batch, and the epoch statistics cover every rank's frames
    (:meth:`TrackingQualityLogger.compute(sync_dist=True) <training_hooks.hooks.TrackingQualityLogger.compute>`).

    Args:
        prefix: prepended to every logged name.
        select: maps the batch the module receives to the dataset batch dict (default: the batch itself, which
            must then be a dict with ``confidence``).
        log_steps: also log per batch (else only per epoch).

    Example:
        >>> # trainer = lightning.pytorch.Trainer(callbacks=[TrackingQualityCallback()])
    """

    def __init__(
        self,
        prefix: str = "tracking/",
        select: Callable[[Any], Mapping[str, Any]] | None = None,
        log_steps: bool = True,
    ) -> None:
        super().__init__()
        self.prefix = str(prefix)
        self.select = select
        self.log_steps = bool(log_steps)
        self.loggers = {"train": TrackingQualityLogger(), "val": TrackingQualityLogger()}

    def _batch(self, batch: Any) -> Mapping[str, Any]:
        return self.select(batch) if self.select is not None else batch

    def _on_batch(self, stage: str, pl_module: pl.LightningModule, batch: Any) -> None:
        stats = self.loggers[stage].update(self._batch(batch))
        if self.log_steps and stats.get("frames", 0.0) > 0:
            size = int(stats["samples"])
            named = {f"{self.prefix}{stage}/{k}": v for k, v in stats.items()}
            pl_module.log_dict(named, on_step=True, on_epoch=False, batch_size=size)

    def _on_epoch_end(self, stage: str, pl_module: pl.LightningModule) -> None:
        stats = self.loggers[stage].compute(sync_dist=True)  # (every rank runs this hook)
        if stats.get("frames", 0.0) > 0:
            named = {f"{self.prefix}{stage}_epoch/{k}": v for k, v in stats.items()}
            # (already every rank's; sync_dist keeps Lightning from asking for it, the values being equal on all ranks)
            pl_module.log_dict(named, on_step=False, on_epoch=True, sync_dist=True)
        self.loggers[stage].reset()

    def on_train_batch_start(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch: Any, batch_idx: int
    ) -> None:
        self._on_batch("train", pl_module, batch)

    def on_validation_batch_start(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch: Any, batch_idx: int, dataloader_idx: int = 0
    ) -> None:
        if not trainer.sanity_checking:
            self._on_batch("val", pl_module, batch)

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._on_epoch_end("train", pl_module)

    def on_validation_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if trainer.sanity_checking:
            self.loggers["val"].reset()
            return
        self._on_epoch_end("val", pl_module)


class _EpochLoader(DataLoader):
    """A ``DataLoader`` that hands its dataset ``epoch()`` (:meth:`VideoDataset.set_epoch
    <training_hooks.datasets.VideoDataset.set_epoch>`; None: no call) each time an epoch's iteration starts
    (:class:`TrackedFaceDataModule`'s loaders: the training one the trainer's epoch, None without a trainer; the
    validation one the epoch its dataset has, the same order on purpose). An iteration that follows a ``set_epoch``
    is not told it repeats an order (:class:`~training_hooks.datasets.RepeatedEpochWarning`: a shuffled validation
    set repeats it by design); the training loader without a trainer leaves the epoch to the caller's loop, as a
    plain ``DataLoader`` does, and a loop that forgets ``set_epoch`` is told."""

    def __init__(self, *args: Any, epoch: Callable[[], int | None], **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._epoch_of = epoch

    def __iter__(self) -> Iterator[Any]:  # type: ignore[override]
        epoch = self._epoch_of()
        if epoch is not None:
            dataset: VideoDataset = self.dataset  # type: ignore[assignment]
            dataset.set_epoch(epoch)
        return super().__iter__()


def _kept_epoch(dataset: VideoDataset) -> int:
    """The validation loader's epoch (:class:`_EpochLoader`, through ``functools.partial``): the one its dataset
    has."""
    return dataset.epoch


class _OptionalValidation:
    """:meth:`TrackedFaceDataModule.val_dataloader`, shown to the trainer as not implemented while the module has no
    validation dataset (``val`` None), as in a ``LightningDataModule`` without one (Lightning looks at the method,
    ``is_overridden``), so that it runs no validation without a word: it asked for the loader, got ``[]`` and warned
    "Total length of `list` across ranks is zero. Please make sure this was your intention." at every fit. Called
    directly, it still gives ``[]``. Looked up on each access (not set on the instance when it is made), so that a
    ``val`` set later (in ``setup``) is validated on, and a subclass's own ``val_dataloader`` is its own (an instance
    attribute hid both: no validation, without a word)."""

    def __init__(self, method: Callable[[TrackedFaceDataModule], DataLoader | list]) -> None:
        self.method = method

    def __get__(self, module: TrackedFaceDataModule | None, owner: type | None = None) -> Any:
        if module is None:
            return self.method
        if getattr(module, "val", None) is not None:
            return self.method.__get__(module, owner)
        empty = functools.partial(self.method, module)
        # (is_overridden compares the code of the unwrapped method with LightningDataModule's)
        empty.__wrapped__ = pl.LightningDataModule.val_dataloader  # type: ignore[attr-defined]
        return empty


class TrackedFaceDataModule(pl.LightningDataModule):
    """``LightningDataModule`` over tracked datasets (:class:`~training_hooks.datasets.VideoDataset` /
    :class:`~training_hooks.datasets.FrameFolderDataset`).

    Args:
        train: the training dataset.
        val: the validation dataset, or None (no validation: the trainer sees no ``val_dataloader`` while ``val``
            is None; one set later, e.g. in ``setup``, is validated on).
        batch_size: items per batch.
        num_workers: ``DataLoader`` workers (tracking runs in them).
        collate_fn: None picks :func:`~training_hooks.collate.collate_clips` for clip datasets and PyTorch's default
            for frame datasets.

    The other ``DataLoader`` settings (keyword-only; both loaders get them):

    Args:
        pin_memory: page-locked batches for a fast copy to the GPU. None (the default): True when the attached
            trainer runs on a CUDA device (``trainer.strategy.root_device``), else False (no trainer, CPU training:
            PyTorch warns that pinning without an accelerator does nothing).
        persistent_workers: keep the workers (and each one's dataset copy: the face model loaded once, the cache
            opened once) from one epoch to the next instead of starting them again. None (the default): True when
            ``num_workers > 0`` (each epoch started ``num_workers`` processes again, each importing torchface and
            loading the model; the epoch still reaches the persistent workers' datasets, shared memory). True with
            ``num_workers = 0`` is refused, as ``DataLoader`` refuses it.
        prefetch_factor: batches each worker loads ahead (None: PyTorch's default, 2 with workers); needs
            ``num_workers > 0``.
        multiprocessing_context: how the workers are started: ``"fork"``, ``"spawn"``, ``"forkserver"`` or a
            ``multiprocessing`` context (None: the platform's default); needs ``num_workers > 0``.
        drop_last: leave out the training loader's last, smaller batch of each worker (a ``DataLoader`` batches
            each worker's items separately); the validation loader keeps every item.
        timeout: seconds to wait for a worker's batch before raising (0, the default: no limit). A worker yields
            nothing of a video until it has tracked the whole video (:mod:`training_hooks.datasets`: its items come
            from the tracked sequence), so the wait for a batch includes tracking every video whose items it
            holds (more than one where a video has fewer items than ``batch_size`` plus
            :attr:`DatasetConfig.shuffle_buffer <training_hooks.datasets.DatasetConfig.shuffle_buffer>`), and for
            the first batch also the worker's start (a spawned one imports torch and torchface), the counting of
            its videos on every rank under DDP (:attr:`DatasetConfig.rank_balance
            <training_hooks.datasets.DatasetConfig.rank_balance>`: video files decoded through) and a detector's
            search for the first face. A timeout shorter than that raises PyTorch's "DataLoader timed out after N
            seconds" though nothing is wrong: give more than the longest video's tracking takes on the machine
            that trains (time it: :func:`~training_hooks.datasets.loader_throughput`, or ``data.sequence(i)`` of
            the longest video), or 0. It is not checked against the videos: their tracking time is not known
            before they are tracked (a cached video is read in a fraction of it).

    There is no ``shuffle``, ``sampler`` or ``generator``: the datasets are iterable, and their shuffling is
    :attr:`DatasetConfig.shuffle_buffer <training_hooks.datasets.DatasetConfig.shuffle_buffer>`, seeded by
    :attr:`DatasetConfig.seed <training_hooks.datasets.DatasetConfig.seed>` and the epoch alone (not by torch's
    random state, nor a ``DataLoader`` generator: the same items in the same order on every run). Workers' items
    interleave in turn (``DataLoader(in_order=True)``, PyTorch's default), so the order is reproducible.

    Each training epoch's iteration of the loader passes the trainer's epoch to
    :meth:`~training_hooks.datasets.VideoDataset.set_epoch` first, so that the shuffling
    (:attr:`DatasetConfig.shuffle_buffer <training_hooks.datasets.DatasetConfig.shuffle_buffer>`) draws a new order
    every epoch with the trainer's defaults too (Lightning builds the loader once and calls ``set_epoch`` on samplers
    alone, which an iterable dataset's loader has none of: every epoch repeated the first one's order unless the
    trainer had ``reload_dataloaders_every_n_epochs=1``). The validation loader passes its dataset's own epoch
    (the same order each time, on purpose): neither is told
    :class:`~training_hooks.datasets.RepeatedEpochWarning`. Without a trainer the training loader sets no epoch, as a
    plain ``DataLoader``: a loop of its own calls ``module.train.set_epoch(epoch)`` before each epoch, and one that
    forgets is told (it repeated the first epoch's order silently before).

    Distributed (DDP) training: each rank's loaders yield that rank's share of the videos (video ``i`` -> rank
    ``i % world_size``, :mod:`training_hooks.datasets`, "Sharding"; the datasets are iterable, so Lightning adds no
    ``DistributedSampler``), and every rank the same number of batches (:attr:`DatasetConfig.rank_balance
    <training_hooks.datasets.DatasetConfig.rank_balance>`, ``PAD`` by default), as ``num_workers`` is the same on
    every rank.
    """

    def __init__(
        self,
        train: VideoDataset,
        val: VideoDataset | None = None,
        batch_size: int = 32,
        num_workers: int = 0,
        collate_fn: Callable[[list[dict[str, Any]]], dict[str, Any]] | None = None,
        *,
        pin_memory: bool | None = None,
        persistent_workers: bool | None = None,
        prefetch_factor: int | None = None,
        multiprocessing_context: str | BaseContext | None = None,
        drop_last: bool = False,
        timeout: float = 0.0,
    ) -> None:
        super().__init__()
        for name, ds in (("train", train), ("val", val)):
            if ds is not None and not isinstance(ds, VideoDataset):
                raise TypeError(f"{name} must be a VideoDataset or FrameFolderDataset, got {type(ds).__name__}")
        # (a float was cut, 2.5 -> 2, True taken as 1 and "8" a comparison's TypeError: the settings' rule for counts)
        self.batch_size = check_int(batch_size, "batch_size", 1)
        self.num_workers = check_int(num_workers, "num_workers", 0)
        self.train, self.val, self.collate_fn = train, val, collate_fn
        # (checked here, not when the trainer first asks for a loader: DataLoader's own messages came then)
        workers = self.num_workers > 0
        self.pin_memory = None if pin_memory is None else check_bool(pin_memory, "pin_memory")
        self.persistent_workers = workers if persistent_workers is None else check_bool(
            persistent_workers, "persistent_workers")  # fmt: skip
        if self.persistent_workers and not workers:
            raise ValueError("persistent_workers=True needs num_workers > 0 (with 0 the loading runs in the "
                             "training process: there are no workers to keep)")  # fmt: skip
        self.prefetch_factor = check_optional_int(prefetch_factor, "prefetch_factor", 1)
        if self.prefetch_factor is not None and not workers:
            raise ValueError(f"prefetch_factor={self.prefetch_factor} needs num_workers > 0 (each worker loads that "
                             "many batches ahead; with 0 there are none)")  # fmt: skip
        if multiprocessing_context is not None:
            if isinstance(multiprocessing_context, str):
                methods = multiprocessing.get_all_start_methods()
                if multiprocessing_context not in methods:
                    raise ValueError(f"multiprocessing_context must be one of {methods} or a multiprocessing "
                                     f"context, got {multiprocessing_context!r}")  # fmt: skip
            elif not isinstance(multiprocessing_context, BaseContext):
                raise TypeError("multiprocessing_context must be a start method's name or a multiprocessing "
                                f"context, got {type(multiprocessing_context).__name__}")  # fmt: skip
            if not workers:
                raise ValueError(f"multiprocessing_context={multiprocessing_context!r} needs num_workers > 0 (it "
                                 "starts the workers; with 0 there are none)")  # fmt: skip
        self.multiprocessing_context = multiprocessing_context
        self.drop_last = check_bool(drop_last, "drop_last")
        self.timeout = float(check_real(timeout, "timeout"))
        if not 0.0 <= self.timeout < math.inf:  # (NaN too)
            raise ValueError(f"timeout must be finite seconds >= 0 (0: no limit), got {timeout}")
        if self.timeout > 0 and not workers:
            raise ValueError(f"timeout={self.timeout} needs num_workers > 0 (it bounds the wait for a worker's batch)")

    def _pin(self) -> bool:
        """:attr:`pin_memory` as given, or (None) whether the attached trainer runs on a CUDA device."""
        if self.pin_memory is not None:
            return self.pin_memory
        trainer = getattr(self, "trainer", None)
        if trainer is None:
            return False
        return trainer.strategy.root_device.type == "cuda"

    def _loader(self, dataset: VideoDataset, epochs: bool = False) -> DataLoader:
        collate = self.collate_fn
        if collate is None and dataset.config.clip_length is not None:
            collate = collate_clips
        kwargs: dict[str, Any] = dict(
            batch_size=self.batch_size, num_workers=self.num_workers, collate_fn=collate, pin_memory=self._pin(),
            drop_last=self.drop_last and epochs, timeout=self.timeout, persistent_workers=self.persistent_workers,
            prefetch_factor=self.prefetch_factor, multiprocessing_context=self.multiprocessing_context,
        )  # fmt: skip
        epoch = self._trainer_epoch if epochs else functools.partial(_kept_epoch, dataset)
        return _EpochLoader(dataset, epoch=epoch, **kwargs)

    def _trainer_epoch(self) -> int | None:
        """The attached trainer's current epoch, or None without a trainer."""
        trainer = getattr(self, "trainer", None)
        return None if trainer is None else int(trainer.current_epoch)

    def train_dataloader(self) -> DataLoader:
        epoch = self._trainer_epoch()
        if epoch is not None:
            self.train.set_epoch(epoch)
        return self._loader(self.train, epochs=True)

    @_OptionalValidation
    def val_dataloader(self) -> DataLoader | list:
        """The validation loader; ``[]`` without a validation dataset, where the trainer does not ask for it
        (:class:`_OptionalValidation`)."""
        return [] if self.val is None else self._loader(self.val)
