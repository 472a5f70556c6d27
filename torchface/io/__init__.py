"""Input and output of the tracking job: validated frame reading, landmark files, the per-frame CSV, the JSON
sidecar. Errors about user input are :class:`InputError` / :class:`OutputError` with one-line messages."""

from torchface.io.errors import InputError, OutputError
from torchface.io.landmarks import NUM_LANDMARKS, check_landmarks, mirror_landmarks, read_landmarks
from torchface.io.sidecar import package_versions, to_jsonable, write_json
from torchface.io.table import TrackCsvWriter, openface_euler, read_track_csv, result_rows, track_columns
from torchface.io.video import FrameReader, VideoInfo, frame_to_tensor, open_frames

__all__ = [
    "FrameReader",
    "InputError",
    "NUM_LANDMARKS",
    "OutputError",
    "TrackCsvWriter",
    "VideoInfo",
    "check_landmarks",
    "frame_to_tensor",
    "mirror_landmarks",
    "open_frames",
    "openface_euler",
    "package_versions",
    "read_landmarks",
    "read_track_csv",
    "result_rows",
    "to_jsonable",
    "track_columns",
    "write_json",
]
