"""torchface: 3D face tracking in PyTorch (pose, expression and illumination in one minimisation per frame).

Pipeline, one sub-package per stage: ``model`` -> ``geometry`` -> ``rendering`` (rasterizer, visibility,
shading) -> ``appearance`` -> ``solver`` -> ``template`` -> ``tracker`` -> ``normalise``.
``synth`` renders test sequences with ground truth. Conventions: :mod:`torchface.conventions`.

The names below (and the sub-packages they bring) are imported on first use, not by ``import torchface``: the
``torchface`` command (:mod:`torchface.cli`) imports this package before its ``main`` runs, and importing torch
there took seconds before ``--help`` or an argument error, and printed a long traceback on a Ctrl-C.
"""

from __future__ import annotations

import importlib
import importlib.util
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

__all__ = ["Backend", "FaceTracker", "Intrinsics", "NormalisedFace", "TrackResult", "TrackerConfig", "load_candide3"]

#: Where each public name lives.
_SOURCES = {
    "Backend": "torchface.backend",
    "Intrinsics": "torchface.geometry.camera",
    "load_candide3": "torchface.model.candide",
    "NormalisedFace": "torchface.normalise",
    "FaceTracker": "torchface.tracker",
    "TrackerConfig": "torchface.tracker",
    "TrackResult": "torchface.tracker",
}

if TYPE_CHECKING:
    from torchface.backend import Backend
    from torchface.geometry.camera import Intrinsics
    from torchface.model.candide import load_candide3
    from torchface.normalise import NormalisedFace
    from torchface.tracker import FaceTracker, TrackerConfig, TrackResult


def __getattr__(name: str) -> Any:
    """A public name from its module, or a sub-package (``torchface.tracker``), imported on first use."""
    if name in _SOURCES:
        value = getattr(importlib.import_module(_SOURCES[name]), name)
        globals()[name] = value
        return value
    # (an identifier alone: hasattr(torchface, "foo.bar") raised ModuleNotFoundError, and "tracker.step" gave
    # torchface.tracker.step, as no attribute lookup should)
    if name.isidentifier() and not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
