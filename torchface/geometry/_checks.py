"""Input validation shared by the geometry modules (public-boundary checks, never inside hot loops)."""

from __future__ import annotations

import torch

from torchface.geometry.camera import Intrinsics


def check_tensor(x: object, name: str, trailing: tuple[int, ...], min_dim: int | None = None) -> torch.Tensor:
    """Check that ``x`` is a floating tensor whose last dimensions are ``trailing``.

    Args:
        x: the value to check.
        name: argument name used in error messages.
        trailing: required sizes of the last ``len(trailing)`` dimensions.
        min_dim: minimum number of dimensions (defaults to ``len(trailing)``).

    Returns:
        ``x`` unchanged.

    Raises:
        TypeError: ``x`` is not a floating-point tensor.
        ValueError: its shape does not end with ``trailing`` or it has too few dimensions.
    """
    if not isinstance(x, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got dtype {x.dtype}")
    need = len(trailing) if min_dim is None else min_dim
    if x.dim() < need or tuple(x.shape[x.dim() - len(trailing) :]) != trailing:
        want = "(..., " + ", ".join(str(s) for s in trailing) + ")"
        raise ValueError(f"{name} must have shape {want} with at least {need} dims, got {tuple(x.shape)}")
    return x


def check_exact_dim(x: torch.Tensor, name: str, dims: tuple[int, ...], shape_doc: str) -> None:
    """Raise ``ValueError`` unless ``x.dim()`` is one of ``dims`` (``shape_doc`` names the expected shapes)."""
    if x.dim() not in dims:
        raise ValueError(f"{name} must be {shape_doc}, got shape {tuple(x.shape)}")


def check_intrinsics(intrinsics: object) -> Intrinsics:
    """Raise ``TypeError`` unless ``intrinsics`` is an :class:`Intrinsics`."""
    if not isinstance(intrinsics, Intrinsics):
        raise TypeError(f"intrinsics must be torchface.geometry.Intrinsics, got {type(intrinsics).__name__}")
    return intrinsics


def check_batch(b1: int, b2: int, name1: str, name2: str) -> None:
    """Raise ``ValueError`` unless two batch sizes agree or one of them is 1 (broadcast)."""
    if b1 != b2 and b1 != 1 and b2 != 1:
        raise ValueError(f"batch sizes of {name1} ({b1}) and {name2} ({b2}) must match or be 1")


def promoted(*tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """``tensors`` in their promoted dtype (float32 against float64: float64), as torch's elementwise operations
    promote; a matmul of mixed dtypes raised "expected scalar type Float but found Double"."""
    dtype = tensors[0].dtype
    for x in tensors[1:]:
        dtype = torch.promote_types(dtype, x.dtype)
    return tuple(x.to(dtype) for x in tensors)


def check_broadcast(a: torch.Tensor, b: torch.Tensor, name_a: str, name_b: str, trailing: int) -> None:
    """Raise ``ValueError`` unless the leading dimensions of ``a`` and ``b`` (all but their last ``trailing``)
    broadcast (their mismatch was torch's RuntimeError "The size of tensor a (4) must match ...")."""
    lead_a, lead_b = tuple(a.shape[: a.dim() - trailing]), tuple(b.shape[: b.dim() - trailing])
    try:
        torch.broadcast_shapes(lead_a, lead_b)
    except RuntimeError:
        raise ValueError(f"batch shapes of {name_a} {lead_a} and {name_b} {lead_b} must broadcast") from None
