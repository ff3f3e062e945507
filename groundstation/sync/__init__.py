"""Time alignment of IMU, attitude and mocap streams (pure: time comes in with the data)."""

from groundstation.sync.aligner import NoPose, Pose, PoseBuffer, slerp

__all__ = ["NoPose", "Pose", "PoseBuffer", "slerp"]
