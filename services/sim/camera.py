"""The simulated camera: pinhole intrinsics from a horizontal field of view, and the camera-to-world pose
of the robot's head camera (OpenCV convention: ``x`` right, ``y`` down, ``z`` forward).

Reference settings (Explore-EQA appendix B): HFOV 120 deg, 4:3 images, camera 1.5 m above the floor,
tilted 30 deg down.
"""

from __future__ import annotations

import math

import numpy as np

from eqa.messages import Pose2D

HFOV_DEG = 120.0
CAMERA_HEIGHT = 1.5
TILT_DEG = -30.0


def intrinsics(width: int, height: int, hfov_deg: float = HFOV_DEG) -> np.ndarray:
    """3x3 pinhole matrix for a ``width x height`` image with square pixels and the given horizontal field
    of view; the principal point is the image centre, pixel centres at integer coordinates."""
    if width < 1 or height < 1:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if not 0.0 < hfov_deg < 180.0:
        raise ValueError(f"hfov_deg must be in (0, 180), got {hfov_deg}")
    f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]], np.float64)


def camera_pose(pose: Pose2D, height: float = CAMERA_HEIGHT, tilt_deg: float = TILT_DEG) -> np.ndarray:
    """4x4 camera-to-world matrix of a camera at ``height`` above the robot base ``pose``, looking along
    the robot's heading, pitched by ``tilt_deg`` (negative = down)."""
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    ct, st = math.cos(math.radians(tilt_deg)), math.sin(math.radians(tilt_deg))
    forward = np.array([c * ct, s * ct, st])
    right = np.array([s, -c, 0.0])
    down = np.cross(forward, right)
    T = np.eye(4)
    T[:3, 0] = right
    T[:3, 1] = down
    T[:3, 2] = forward
    T[:3, 3] = (pose.x, pose.y, height)
    return T


def vfov_deg(width: int, height: int, hfov_deg: float = HFOV_DEG) -> float:
    """Vertical field of view of the same pinhole camera."""
    return math.degrees(2.0 * math.atan(math.tan(math.radians(hfov_deg) / 2.0) * height / width))
