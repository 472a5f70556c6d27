"""torchface: 3D face tracking in PyTorch (pose, expression and illumination in one minimisation per frame).

Pipeline, one sub-package per stage: ``model`` -> ``geometry`` -> ``rendering`` (rasterizer, visibility,
shading) -> ``appearance`` -> ``solver`` -> ``template`` -> ``tracker`` -> ``normalise``.
``synth`` renders test sequences with ground truth. Conventions: :mod:`torchface.conventions`.
"""

__version__ = "0.1.0"

from torchface.backend import Backend  # noqa: E402
from torchface.geometry.camera import Intrinsics  # noqa: E402
from torchface.model.candide import load_candide3  # noqa: E402
from torchface.normalise import NormalisedFace  # noqa: E402
from torchface.tracker import FaceTracker, TrackerConfig, TrackResult  # noqa: E402

__all__ = ["Backend", "FaceTracker", "Intrinsics", "NormalisedFace", "TrackResult", "TrackerConfig", "load_candide3"]
