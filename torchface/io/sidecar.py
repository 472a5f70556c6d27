"""The JSON sidecar of a tracked video: versions, settings, camera, model, timings, frame counts."""

from __future__ import annotations

import dataclasses
import enum
import functools
import json
import math
import os
import platform
from importlib import metadata
from pathlib import Path
from typing import Any

from torchface.io.errors import OutputError

__all__ = ["DEPENDENCIES", "package_versions", "to_jsonable", "write_json"]

#: Distributions whose versions the sidecar records (None when not installed).
DEPENDENCIES: tuple[str, ...] = (
    "torchface", "torch", "kornia", "numpy", "opencv-python-headless", "opencv-python", "trimesh", "matplotlib",
)  # fmt: skip


def package_versions() -> dict[str, str | None]:
    """``{"python": ..., "<distribution>": version or None}`` for :data:`DEPENDENCIES`: those of this process, looked
    up once (a new dict each call)."""
    return dict(_versions())


@functools.cache
def _versions() -> dict[str, str | None]:
    """:func:`package_versions`, looked up once per process (~13 ms: ``importlib.metadata`` reads every installed
    distribution's record, for every video's sidecar; an upgrade installed while the process runs is not what it
    runs: the modules imported before it stay)."""
    out: dict[str, str | None] = {"python": platform.python_version()}
    for name in DEPENDENCIES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def to_jsonable(value: Any) -> Any:
    """Dataclasses, enums, paths, tuples and numpy/torch scalars -> plain JSON values, torch devices and dtypes ->
    their names (``"cpu"``, ``"torch.float64"``); a NaN or infinite number (an undefined figure) -> None, so that
    the file is strict JSON (``null``)."""
    import torch

    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (torch.device, torch.dtype)):  # JobConfig(device=torch.device(...)): the sidecar raised
        return str(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, enum.Enum):
        return value.value if isinstance(value.value, (str, int, float)) else value.name
    if isinstance(value, os.PathLike):  # any path: a PurePath or an os.DirEntry too, not only a Path
        return os.fsdecode(value)
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if hasattr(value, "item") and callable(value.item) and getattr(value, "ndim", 1) == 0:
        return to_jsonable(value.item())
    if hasattr(value, "tolist"):
        return to_jsonable(value.tolist())
    return value


def write_json(path: str | os.PathLike[str], payload: dict[str, Any]) -> Path:
    """Write ``payload`` to ``<path>.partial`` then rename it to ``path`` (never half-written)."""
    p = Path(path)
    tmp = p.with_name(p.name + ".partial")
    try:
        tmp.write_text(json.dumps(to_jsonable(payload), indent=2, allow_nan=False) + "\n", encoding="utf-8")
        os.replace(tmp, p)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise OutputError(f"{p}: cannot write ({exc.strerror or exc})") from None
    return p
