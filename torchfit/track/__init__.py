"""Motion capture with a fitted model: silhouette tracking frame by frame, batched over
sequences."""

from torchfit.track.frame import FrameResult, PoseLayout, TrackOptions, solve_frame
from torchfit.track.silhouettes import FrameSilhouettes
from torchfit.track.start import start_poses
from torchfit.track.tracker import FrameRecord, frame_data, track

__all__ = [
    "TrackOptions",
    "PoseLayout",
    "FrameResult",
    "solve_frame",
    "FrameRecord",
    "FrameSilhouettes",
    "frame_data",
    "track",
    "start_poses",
]
