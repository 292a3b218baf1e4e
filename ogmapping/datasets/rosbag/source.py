"""``RosBag``: a recorded ROS 1 or ROS 2 bag as a random-access ``FrameSource``.

Opening a bag chooses its topics (``topics``), reads its calibration, TF and pose topic (and a SLAM
system's corrected trajectory, ``corrected``), reads every image's header to pair colour with depth
(``pairing``) and gives each pair the camera's pose at the colour stamp (``poses``); pairs without a
pose are dropped. Frames are decoded on demand: the images of frame N are found again by their place
in the bag (``bagfile``). A frame's colour camera's pose is that of the colour images' optical frame
(``--camera-frame`` overrides it); depth from another optical frame than the colour images' gets
``depth_to_color`` from TF and is registered onto colour later (``preprocess.register_depth``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

from ogmapping.datasets.base import FrameSource
from ogmapping.datasets.rosbag import images
from ogmapping.datasets.rosbag.bagfile import BagFile
from ogmapping.datasets.rosbag.calibration import Calibration, check_size, undistort
from ogmapping.datasets.rosbag.corrected import Corrected, read_corrected
from ogmapping.datasets.rosbag.headers import normalise_frame, read_header
from ogmapping.datasets.rosbag.options import BagOptions
from ogmapping.datasets.rosbag.pairing import StampedImage, pair_images
from ogmapping.datasets.rosbag.poses import choose_pose_source, read_tf
from ogmapping.datasets.rosbag.topics import COMPRESSED, choose_images, topic_error
from ogmapping.frames.camera import Intrinsics, validate_pose
from ogmapping.frames.frame import Frame

OPTICAL_SUFFIXES = ("optical_frame", "_optical")
DEPTH_SHARES_COLOUR = " (the colour camera's; name the depth camera's with --depth-info-topic)"


@dataclass(frozen=True)
class _Entry:
    color: StampedImage
    depth: StampedImage
    c2w: np.ndarray


class RosBag(FrameSource):
    """Frames of one bag; ``options`` are the fields of ``BagOptions`` (the ``--bag`` flags)."""

    def __init__(self, path: str | Path, **options: object) -> None:
        self.options = BagOptions(**options)  # type: ignore[arg-type]
        self.bag = BagFile(path)
        self.name = f"bag:{self.bag.path}"
        self._notes: list[str] = []
        self.topics = choose_images(self.bag, self.options)
        self.color_calibration = self._calibration(self.topics.color_info)
        depth_info = self.topics.depth_info
        self.depth_calibration = self._calibration(depth_info) if depth_info else self.color_calibration
        self._color_maps = self.color_calibration.undistortion_maps()
        self._depth_maps = self.depth_calibration.undistortion_maps()
        self._color_k = self.color_calibration.intrinsics()
        self._depth_k = self.depth_calibration.intrinsics()

        colors, depths = self._index()
        self.color_frame, self.depth_frame = colors[0].frame_id, depths[0].frame_id
        camera = normalise_frame(self.options.camera_frame or "") or self.color_frame
        if not camera:
            raise topic_error(self.bag, f"the images on {self.topics.color} have no header.frame_id; "
                              "pass --camera-frame")
        self.camera_frame = camera
        self.tree = read_tf(self.bag)
        self.pose_source = choose_pose_source(self.bag, self.options, camera, self.tree)
        self._check_frames()
        self._corrected: Corrected | None = None
        if self.options.corrected_topic is not None:
            self._corrected = read_corrected(self.bag, self.options.corrected_topic, self.pose_source,
                                             self.options.body_frame)
            self.corrected = self._corrected.trajectory

        pairing = pair_images(colors, depths, self.options.pair_tolerance)
        self._entries = []
        for color, depth in pairing.pairs:
            c2w = self.pose_source.at(color.stamp_ns)
            if c2w is not None:
                self._entries.append(_Entry(color, depth, validate_pose(c2w, f"pose at {color.stamp_ns} ns")))
        self._counts = (len(colors), len(depths), len(pairing.pairs), pairing.unpaired_color)
        if not self._entries:
            raise ValueError(f"{self.bag.path}: no frame: {len(colors)} colour and {len(depths)} depth images, "
                             f"{len(pairing.pairs)} pairs within {self.options.pair_tolerance} s, none with a pose "
                             f"from {self.pose_source.description} within {self.options.pose_tolerance} s")

    def _calibration(self, topic: str) -> Calibration:
        message = self.bag.first(topic)
        try:
            return Calibration.from_message(message)
        except ValueError as error:
            raise ValueError(f"{self.bag.path}: {topic}: {error}") from error

    def _index(self) -> tuple[list[StampedImage], list[StampedImage]]:
        """Stamp and frame of every colour and depth image, read from the headers alone."""
        found: dict[str, list[StampedImage]] = {self.topics.color: [], self.topics.depth: []}
        for ref, _, raw in self.bag.scan(list(found)):
            header = read_header(raw, self.bag.ros2)
            found[ref.topic].append(StampedImage(ref, header.stamp_ns, header.frame_id))
        for topic, stamped in found.items():
            if not stamped:
                raise topic_error(self.bag, f"{topic} has no messages")
            if all(image.stamp_ns == 0 for image in stamped):  # a driver that never sets header.stamp
                self._notes.append(f"{topic} has no header stamps: the bag's receive times stand in for them")
                stamped[:] = [StampedImage(i.ref, i.ref.bag_time_ns, i.frame_id) for i in stamped]
            stamped.sort(key=lambda image: image.stamp_ns)
        return found[self.topics.color], found[self.topics.depth]

    def _check_frames(self) -> None:
        """Notes on what the reader assumed about frames, for ``report``."""
        if not self.camera_frame.endswith(OPTICAL_SUFFIXES):
            self._notes.append(f"camera frame {self.camera_frame!r} is not named *_optical_frame: its axes are taken "
                               "as an optical frame's (x right, y down, z forward), as REP 103 asks of image frames")
        if self.color_frame and self.depth_frame and self.depth_frame != self.color_frame:
            if self.tree.connected(self.color_frame, self.depth_frame):
                self._notes.append(f"depth is in {self.depth_frame!r}: registered onto {self.color_frame!r} "
                                   "through TF")
            else:
                self._notes.append(f"depth is in {self.depth_frame!r}, colour in {self.color_frame!r}, and TF does "
                                   "not connect them: taken as one optical centre")

    def __len__(self) -> int:
        return len(self._entries)

    @property
    def intrinsics(self) -> Intrinsics:
        return self._color_k

    def report(self) -> list[str]:
        colors, depths, pairs, unpaired = self._counts
        depth_camera = (f"{self.topics.depth_info}: {self.depth_calibration.describe()}" if self.topics.depth_info
                        else "the colour camera's")
        return [
            f"colour {self.topics.color} ({self.bag.topics[self.topics.color].msgtype}), {colors} images; "
            f"{self.topics.color_info}: {self.color_calibration.describe()}",
            f"depth {self.topics.depth} ({self.bag.topics[self.topics.depth].msgtype}), {depths} images; "
            f"calibration {depth_camera}",
            f"poses: {self.pose_source.description}",
            *([f"corrected poses: {self._corrected.description}"] if self._corrected else []),
            f"{len(self)} frames: {unpaired} colour images without depth within {self.options.pair_tolerance} s, "
            f"{pairs - len(self)} pairs without a pose within {self.options.pose_tolerance} s",
            *self._notes,
        ]

    def _decode(self, image: StampedImage, depth: bool) -> np.ndarray:
        """The image, its size checked against its CameraInfo: a compressed one's before it is decoded."""
        topic = image.ref.topic
        message = self.bag.load(image.ref)
        compressed = self.bag.topics[topic].msgtype == COMPRESSED
        whose = "" if not depth or self.topics.depth_info else DEPTH_SHARES_COLOUR
        check = partial(check_size, self.depth_calibration if depth else self.color_calibration, whose=whose)
        try:
            if depth:
                decoded = images.compressed_depth(message, check) if compressed else images.image_depth(message)
            else:
                decoded = images.compressed_color(message, check) if compressed else images.image_color(message)
            check(decoded.shape[1], decoded.shape[0])
        except ValueError as error:
            raise ValueError(f"{self.bag.path}: {topic} at {image.stamp_ns} ns: {error}") from error
        return decoded

    def _load(self, position: int) -> Frame:
        entry = self._entries[position]
        rgb = self._decode(entry.color, depth=False)
        depth = self._decode(entry.depth, depth=True)
        depth_to_color = None
        if entry.color.frame_id and entry.depth.frame_id and entry.depth.frame_id != entry.color.frame_id:
            depth_to_color = self.tree.lookup(entry.color.frame_id, entry.depth.frame_id, entry.depth.stamp_ns,
                                              round(self.options.pose_tolerance * 1e9))
        return Frame(
            index=position,
            rgb=undistort(rgb, self._color_maps, nearest=False),
            depth=undistort(depth, self._depth_maps, nearest=True),
            color_intrinsics=self._color_k,
            depth_intrinsics=self._depth_k,
            c2w=entry.c2w.copy(),
            timestamp=entry.color.stamp_ns * 1e-9,
            depth_to_color=depth_to_color,
        )
