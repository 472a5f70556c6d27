"""The one check of a torch device a user names: where torchface first takes one (``load_candide3(device=...)``,
``load_mesh_model``, ``FaceModel.to``, ``FaceTracker.to`` / ``.cuda``, ``NormalisedFace.to`` / ``.cuda``, the ``.to``
of ``TrackResult`` and ``LandmarkFit`` (:func:`check_to_arguments`), ``NormalisedFaceLayout``, ``TexturedMesh`` and
``LightState``, training_hooks' ``NormalisedFaceLayer`` through :mod:`torchface.extending`, the job's
``JobConfig.device``), so that a device this machine lacks is one ``ValueError`` naming it and the devices there are
(torch's own was an ``AssertionError`` "Torch not compiled with CUDA enabled" from deep inside the model's loading, an
"Expected one of cpu, cuda, ipu, xpu, ..." list of every backend torch knows for a typo, and "Tensor.item() cannot be
called on meta tensors" from the model's checks for ``"meta"``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import torch
from torch import nn

_Module = TypeVar("_Module", bound="DeviceCheckedModule")

__all__ = [
    "DeviceCheckedModule", "available_devices", "check_cuda_device", "check_device", "check_holds_data",
    "check_to_arguments", "check_to_device", "tensor_mover",
]


def available_devices() -> list[str]:
    """The devices this process can compute on, as ``--device`` / ``.to`` take them: ``cpu``, each CUDA GPU
    (``cuda:0``, ...), ``mps`` on Apple silicon, each XPU.

    Example:
        >>> available_devices()[0]
        'cpu'
    """
    names = ["cpu"]
    if torch.cuda.is_available():
        names += [f"cuda:{i}" for i in range(torch.cuda.device_count())]
    if torch.backends.mps.is_available():
        names.append("mps")
    if torch.xpu.is_available():
        names += [f"xpu:{i}" for i in range(torch.xpu.device_count())]
    return names


def check_device(device: torch.device | str | int | None) -> torch.device | None:
    """``device`` as a ``torch.device`` (None as None), or a ``ValueError`` that names it and the devices this
    machine has when it is no device name, holds no data (``meta``) or is not here (``cuda`` in a torch built without
    CUDA or on a machine without a GPU, ``cuda:7`` with fewer GPUs, ``mps`` off Apple silicon). An int is read as
    torch reads it (``.to(0)``, ``torch.device(0)``): an index of the current accelerator (``mps:0`` on Apple silicon,
    ``cuda:0`` with a GPU; CUDA's alone in an older torch). Free for the CPU (no query of any backend).

    Example:
        >>> check_device("cpu")
        device(type='cpu')
        >>> check_device("gpu0")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
            ...
        ValueError: unknown torch device 'gpu0' (expected e.g. cpu, cuda, cuda:1, mps); devices here: cpu...
    """
    if device is None or isinstance(device, torch.device) and device.type == "cpu":
        return device
    if isinstance(device, bool) or not isinstance(device, (torch.device, str, int)):
        raise TypeError(f"device must be a torch.device, a str or an int, got {type(device).__name__} {device!r}")
    if isinstance(device, int) and device >= 0:
        # (torch's reading, torch.device(0): the current accelerator's index; it was taken as CUDA's, and an Apple
        # silicon machine's .to(0) refused as "device 'cuda:0' is not available")
        accelerator = getattr(torch, "accelerator", None)  # (torch < 2.6: CUDA's)
        kind = accelerator.current_accelerator() if accelerator is not None else torch.device("cuda")
        if kind is None:  # (torch's own: "Cannot access accelerator device when none is available")
            raise ValueError(f"device {device} is not available: an int is an accelerator's (a GPU's) index, and "
                             f"this machine has none; devices here: {', '.join(available_devices())}")  # fmt: skip
        parsed = torch.device(kind.type, device)
    else:
        try:
            parsed = torch.device(device)
        except (RuntimeError, ValueError):
            raise ValueError(f"unknown torch device {device!r} (expected e.g. cpu, cuda, cuda:1, mps); devices here: "
                             f"{', '.join(available_devices())}") from None  # fmt: skip
    if parsed.type == "cpu":
        return parsed
    name = str(parsed)  # ("cuda:0" as --device takes it, not a torch.device's repr)
    here = f"devices here: {', '.join(available_devices())}"
    if parsed.type == "meta":
        raise ValueError(f"device 'meta' holds no data: use a device that computes; {here}")
    if parsed.type == "cuda":
        if not torch.backends.cuda.is_built():
            raise ValueError(f"device {name!r} is not available: this torch build sees no CUDA GPU (torch "
                             f"{torch.__version__} is built without CUDA); {here}")  # fmt: skip
        if not torch.cuda.is_available():
            raise ValueError(f"device {name!r} is not available: this torch build sees no CUDA GPU; {here}")
        if parsed.index is not None and parsed.index >= torch.cuda.device_count():
            raise ValueError(f"device {name!r} is not available: {torch.cuda.device_count()} CUDA device(s) here "
                             f"(cuda:0 to cuda:{torch.cuda.device_count() - 1}); {here}")  # fmt: skip
        return parsed
    if parsed.type == "mps":
        if not torch.backends.mps.is_available():
            raise ValueError(f"device {name!r} is not available here (MPS needs Apple silicon and a torch built with "
                             f"it); {here}")  # fmt: skip
        return parsed
    try:  # any other backend (xpu, hpu, privateuse1, ...): it must hold a tensor here
        torch.zeros(1, device=parsed)
    except Exception as exc:  # noqa: BLE001 - backends raise AssertionError, RuntimeError, ModuleNotFoundError...
        detail = " ".join(str(exc).split()) or type(exc).__name__
        raise ValueError(f"device {name!r} is not available here ({detail}); {here}") from None
    return parsed


def check_holds_data(tensor: torch.Tensor, name: str) -> None:
    """Refuse an input ``tensor`` (frames, landmarks, weights: ``name``) on the ``meta`` device, which holds shapes and
    no values, with a ``ValueError`` naming it. Inputs on any other device are moved to the model's; a meta one failed
    there, deep inside, with torch's "Cannot copy out of meta tensor; no data!" (frames) or a ``NotImplementedError``
    about ``torch.nonzero``'s meta registration (landmarks).

    Example:
        >>> check_holds_data(torch.zeros(1, 3, 4, 4, device="meta"), "frames")  # doctest: +ELLIPSIS
        Traceback (most recent call last):
            ...
        ValueError: frames are on device 'meta', which holds no values: pass them on a device that computes ...
    """
    if tensor.device.type == "meta":
        raise ValueError(f"{name} are on device 'meta', which holds no values: pass them on a device that computes "
                         "(they are moved to the model's)")  # fmt: skip


def check_to_device(*args: object, **kwargs: object) -> None:
    """:func:`check_device` of the device in an ``nn.Module.to`` / ``Tensor.to`` call's arguments (``.to("cuda")``,
    ``.to(device=..., dtype=...)``, ``.to("cuda", torch.float64)``), before torch parses them; a call without one
    (``.to(torch.float64)``, ``.to(tensor)``) passes."""
    device = kwargs.get("device", args[0] if args else None)
    if isinstance(device, (str, torch.device)) or isinstance(device, int) and not isinstance(device, bool):
        check_device(device)


def check_to_arguments(
    device: torch.device | str | int | torch.dtype | None, dtype: torch.dtype | None
) -> tuple[torch.device | None, torch.dtype | None]:
    """The ``(device, dtype)`` of a frozen dataclass's ``.to(device, dtype)`` (``TrackResult``, ``LandmarkFit``,
    ``FaceModel``), read as ``Tensor.to`` reads them: ``.to(device)``, ``.to(dtype)`` (a dtype first:
    ``result.to(torch.float64)``), ``.to(device, dtype)`` and either as a keyword; the device a ``torch.device``, a
    str or an int (:func:`check_device`: a device this machine lacks is a ``ValueError`` naming those it has), the
    dtype a floating one (their integer tensors keep theirs). Anything else is a ``TypeError`` that says what ``.to``
    takes (a result's ``.to(torch.float64)`` was refused as "device must be a torch.device, a str or an int, got
    dtype").

    Example:
        >>> check_to_arguments(torch.float64, None)
        (None, torch.float64)
        >>> check_to_arguments("cpu", torch.float32)
        (device(type='cpu'), torch.float32)
    """
    if isinstance(dtype, bool):  # (Tensor.to(dtype, non_blocking): the flags follow a dtype given first there)
        raise TypeError(f".to takes a device, then a dtype: got {dtype!r} for the dtype (non_blocking= and copy= "
                        "by keyword)")  # fmt: skip
    if isinstance(device, torch.dtype):  # (.to(torch.float64), as Tensor.to and nn.Module.to take it)
        if dtype is not None:
            raise TypeError(f".to takes a device, then a dtype: got two dtypes, {device} and {dtype}")
        device, dtype = None, device
    if isinstance(device, torch.Tensor):  # (Tensor.to(other): its device and dtype)
        raise TypeError(".to takes a device and / or a floating dtype, not a tensor: .to(other.device, other.dtype) "
                        "for another tensor's")  # fmt: skip
    if device is not None and (isinstance(device, bool) or not isinstance(device, (torch.device, str, int))):
        raise TypeError(f".to takes a device (a torch.device, a str such as 'cuda', an int) and / or a floating "
                        f"torch.dtype, got {type(device).__name__} {device!r}")  # fmt: skip
    if dtype is not None and (not isinstance(dtype, torch.dtype) or not dtype.is_floating_point):
        raise TypeError(f"dtype must be a floating torch.dtype or None (the integer fields keep theirs), got {dtype!r}")
    return check_device(device), dtype


def tensor_mover(
    device: torch.device | str | int | torch.dtype | None = None, dtype: torch.dtype | None = None,
    non_blocking: bool = False, copy: bool = False,
) -> Callable[[torch.Tensor], torch.Tensor]:
    """What the ``.to`` of a frozen dataclass of tensors (``TrackResult``, ``LandmarkFit``, ``NormalisedFaceLayout``,
    ``TexturedMesh``, ``LightState``, ``FaceModel``) does to each of its tensors: ``Tensor.to(device, dtype,
    non_blocking=..., copy=...)``, the dtype for the floating tensors alone (integer and bool ones keep theirs).
    ``device`` and ``dtype`` are read by :func:`check_to_arguments`; ``non_blocking`` and ``copy`` are bools, as
    ``Tensor.to`` takes them: ``copy=True`` copies every tensor (none is shared with the original),
    ``non_blocking=True`` lets a copy between the CPU and a GPU run asynchronously (values copied to the CPU are to be read after a
    ``torch.cuda.synchronize()``, as ``Tensor.to``'s are). They were refused ("got an unexpected keyword argument
    'non_blocking'") although the docs say these ``.to`` take their arguments as ``Tensor.to`` does.

    Example:
        >>> move = tensor_mover(torch.float64, copy=True)
        >>> move(torch.zeros(2)).dtype, move(torch.zeros(2, dtype=torch.int64)).dtype
        (torch.float64, torch.int64)
    """
    device, dtype = check_to_arguments(device, dtype)  # (a device not here: a ValueError naming those here)
    for name, flag in (("non_blocking", non_blocking), ("copy", copy)):
        if not isinstance(flag, bool):  # (torch's own: "argument 'non_blocking' must be bool, not int")
            raise TypeError(f"{name} must be a bool, as Tensor.to takes it, got {type(flag).__name__} {flag!r}")

    def move(t: torch.Tensor) -> torch.Tensor:
        return t.to(device=device, dtype=dtype if t.is_floating_point() else None, non_blocking=non_blocking,
                    copy=copy)  # fmt: skip

    return move


def check_cuda_device(device: torch.device | str | int | None) -> None:
    """:func:`check_device` of ``nn.Module.cuda(device)``'s argument (None: the current CUDA device, an int: its
    index)."""
    check_device(torch.device("cuda") if device is None else torch.device("cuda", device) if isinstance(device, int)
                 else device)  # fmt: skip


class DeviceCheckedModule(nn.Module):
    """An ``nn.Module`` whose ``.to`` and ``.cuda`` check the device first (:func:`check_to_device`,
    :func:`check_cuda_device`): one ``ValueError`` naming a device this machine lacks and those it has. The base of
    ``FaceTracker``, ``NormalisedFace`` and training_hooks' ``NormalisedFaceLayer`` (a parent network's ``.to`` moves
    them through ``_apply``, which never sees the device's name: torch's own error there). Both return the module, typed
    as its own class (they were typed ``Any``: ``NormalisedFace(model).to("cpu")`` lost its type to a checker)."""

    def to(self: _Module, *args: Any, **kwargs: Any) -> _Module:  # type: ignore[override]
        """``nn.Module.to``; a device this machine lacks is a ``ValueError`` naming the devices it has."""
        check_to_device(*args, **kwargs)
        return super().to(*args, **kwargs)

    def cuda(self: _Module, device: int | torch.device | None = None) -> _Module:  # type: ignore[override]
        """``nn.Module.cuda``; without that GPU a ``ValueError`` naming the devices this machine has."""
        check_cuda_device(device)
        return super().cuda(device)
