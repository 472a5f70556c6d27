"""The tracker: initial fit (Eq. 2), per-frame joint minimisation (Eq. 20), batched streams."""

from torchface.backend import Backend
from torchface.tracker.fit import CANDIDE3_VERTICAL_UNITS, FitConfig, LandmarkFit, fit_landmarks, held_shape_indices
from torchface.tracker.lookahead import (
    LookaheadConfig, lookahead_fit, refine_first_fit, select_keyframes, view_yaw_deg,
)
from torchface.tracker.managed import (
    LandmarkDetector,
    ManagementState,
    check_detector,
    estimate_confidence,
    initialise_managed,
    managed_step,
)
from torchface.tracker.module import FaceTracker
from torchface.tracker.objective import frame_residuals, warp_points
from torchface.tracker.params import ParamLayout
from torchface.tracker.smoothing import (
    OneEuroConfig,
    OneEuroState,
    ResultSmoother,
    SmoothingConfig,
    SmoothingState,
    one_euro_alpha,
    one_euro_rotation_step,
    one_euro_step,
    reanchored_streams,
    smooth_pose_series,
    smooth_result,
)
from torchface.template.management import TemplateConfig
from torchface.tracker.step import (
    StartFailure,
    TrackerConfig,
    TrackerState,
    TrackResult,
    TrackSolver,
    TrackStatus,
    face_width_px,
    gray_pyramid,
    initialise,
    level_intrinsics,
    pyramid_for_faces,
    track_step,
)

__all__ = [
    "CANDIDE3_VERTICAL_UNITS",
    "Backend",
    "FaceTracker",
    "FitConfig",
    "LandmarkDetector",
    "LandmarkFit",
    "LookaheadConfig",
    "ManagementState",
    "OneEuroConfig",
    "OneEuroState",
    "ParamLayout",
    "ResultSmoother",
    "SmoothingConfig",
    "SmoothingState",
    "StartFailure",
    "TemplateConfig",
    "TrackResult",
    "TrackSolver",
    "TrackStatus",
    "TrackerConfig",
    "TrackerState",
    "check_detector",
    "estimate_confidence",
    "face_width_px",
    "fit_landmarks",
    "frame_residuals",
    "gray_pyramid",
    "held_shape_indices",
    "initialise",
    "initialise_managed",
    "level_intrinsics",
    "lookahead_fit",
    "managed_step",
    "one_euro_alpha",
    "one_euro_rotation_step",
    "one_euro_step",
    "pyramid_for_faces",
    "reanchored_streams",
    "refine_first_fit",
    "select_keyframes",
    "smooth_pose_series",
    "smooth_result",
    "view_yaw_deg",
    "track_step",
    "warp_points",
]
