"""The choices a user may make for a bag instead of the reader (the ``--bag`` flags), free of ``rosbags``."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class BagOptions:
    """What a user may fix instead of letting the reader choose (the ``--bag`` flags)."""

    color_topic: str | None = None
    depth_topic: str | None = None
    info_topic: str | None = None
    depth_info_topic: str | None = None
    pose_topic: str | None = None
    fixed_frame: str | None = None
    camera_frame: str | None = None
    body_frame: str | None = None
    corrected_topic: str | None = None  # a SLAM system's corrected trajectory (``corrected``), never the pose source
    pair_tolerance: float = 0.02  # seconds between a colour image and its depth image
    pose_tolerance: float = 0.05  # seconds an image may lie beyond the first or last pose sample
