"""Which topics of a bag hold colour, depth, camera info and poses: chosen by flag, or by being the only one.

Image topics are told apart by their first message: a raw Image by its encoding (rgb8 ... mono8
is colour, 16UC1 / 32FC1 depth), a CompressedImage by its format (compressedDepth, or a 16UC1
PNG, is depth; any other is colour). Other encodings (IR mono16, yuv422, ...) are neither, and a
refusal for want of a colour or depth topic names them. A camera's
CameraInfo is found where image_transport puts it, ``camera_info`` in the image topic's namespace
or one above (``/cam/color/image_raw/compressed`` -> ``/cam/color/camera_info``), else it is the
bag's only CameraInfo topic. A bag whose topics do not fit gets a ``BagTopicError`` listing what
the bag has.
"""

from __future__ import annotations

from dataclasses import dataclass

from ogmapping.datasets.rosbag.bagfile import BagFile
from ogmapping.datasets.rosbag.images import COLOR_ENCODINGS, DEPTH_ENCODINGS, is_compressed_depth, is_plain_png_depth
from ogmapping.datasets.rosbag.options import BagOptions

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/PoseWithCovarianceStamped", "nav_msgs/msg/Odometry")
FLAGS_HINT = ("topics and the pose source are chosen with --color-topic, --depth-topic, --info-topic, "
              "--depth-info-topic, and --pose-topic or --fixed-frame")


class BagTopicError(ValueError):
    """The bag's topics do not give colour, depth, camera info and poses (the message lists them)."""


def listing(bag: BagFile) -> str:
    lines = [f"  {entry.name}  {entry.msgtype}  ({entry.count} messages)" for entry in bag.topics.values()]
    return "\n".join(lines) if lines else "  (no topics)"


def topic_error(bag: BagFile, problem: str) -> BagTopicError:
    return BagTopicError(f"{bag.path}: {problem}. The bag's topics:\n{listing(bag)}\n({FLAGS_HINT})")


def image_kind(msgtype: str, first: object | None) -> str | None:
    """'color', 'depth' or None (not an image, empty, or an encoding neither reader takes)."""
    if first is None:
        return None
    if msgtype == IMAGE:
        encoding = str(first.encoding)  # type: ignore[attr-defined]
        return "color" if encoding in COLOR_ENCODINGS else "depth" if encoding in DEPTH_ENCODINGS else None
    if msgtype == COMPRESSED:
        format = str(first.format)  # type: ignore[attr-defined]
        return "depth" if is_compressed_depth(format) or is_plain_png_depth(format) else "color"
    return None


def unsupported_note(encodings: dict[str, str]) -> str:
    """Why raw image topics hold neither colour nor depth: their encodings, for a refusal to name."""
    if not encodings:
        return ""
    found = "; ".join(f"{topic} has encoding {encoding}" for topic, encoding in encodings.items())
    return (f" ({found}, which is not supported; colour is one of {', '.join(COLOR_ENCODINGS)}, depth "
            f"{' or '.join(DEPTH_ENCODINGS)})")


def of_types(bag: BagFile, types: tuple[str, ...]) -> list[str]:
    return [entry.name for entry in bag.topics.values() if entry.msgtype in types and entry.count > 0]


@dataclass(frozen=True)
class ImageTopics:
    color: str
    depth: str
    color_info: str
    depth_info: str | None  # None: depth shares the colour camera's calibration


def _pick(bag: BagFile, kind: str, flag: str, given: str | None, candidates: list[str],
          unsupported: dict[str, str] | None = None) -> str:
    """The topic given, or the only candidate; ``unsupported`` (topic: encoding) says why others are not."""
    unsupported = unsupported or {}
    if given is not None:
        if given not in bag.topics:
            raise topic_error(bag, f"{flag} {given} is not in the bag")
        if given not in candidates:
            note = unsupported_note({given: unsupported[given]} if given in unsupported else {})
            raise topic_error(bag, f"{flag} {given} ({bag.topics[given].msgtype}) does not hold {kind}{note}")
        return given
    if len(candidates) == 1:
        return candidates[0]
    if not candidates:
        raise topic_error(bag, f"no {kind} topic{unsupported_note(unsupported)}")
    raise topic_error(bag, f"{len(candidates)} {kind} topics ({', '.join(candidates)}); pick one with {flag}")


def sibling_info(image_topic: str, infos: list[str]) -> str | None:
    """``camera_info`` in the image topic's namespace or the one above it."""
    parts = image_topic.rstrip("/").split("/")[:-1]
    for depth in (len(parts), len(parts) - 1):
        candidate = "/".join(parts[:depth]) + "/camera_info"
        if depth > 0 and candidate in infos:
            return candidate
    return None


def choose_images(bag: BagFile, options: BagOptions) -> ImageTopics:
    firsts = {name: bag.first(name) for name in of_types(bag, (IMAGE, COMPRESSED))}
    kinds = {name: image_kind(bag.topics[name].msgtype, first) for name, first in firsts.items()}
    unsupported = {name: str(first.encoding) for name, first in firsts.items()  # type: ignore[attr-defined]
                   if kinds[name] is None and first is not None and bag.topics[name].msgtype == IMAGE}
    color = _pick(bag, "colour image", "--color-topic", options.color_topic,
                  [name for name, kind in kinds.items() if kind == "color"], unsupported)
    depth = _pick(bag, "depth image", "--depth-topic", options.depth_topic,
                  [name for name, kind in kinds.items() if kind == "depth"], unsupported)
    infos = of_types(bag, (CAMERA_INFO,))
    if options.info_topic is not None:
        color_info = _pick(bag, "camera info", "--info-topic", options.info_topic, infos)
    else:
        found = sibling_info(color, infos) or (infos[0] if len(infos) == 1 else None)
        if found is None:
            raise topic_error(bag, f"no CameraInfo beside {color} and {len(infos)} elsewhere; "
                              "pick one with --info-topic")
        color_info = found
    if options.depth_info_topic is not None:
        depth_info: str | None = _pick(bag, "camera info", "--depth-info-topic", options.depth_info_topic, infos)
    else:
        depth_info = sibling_info(depth, infos)
    return ImageTopics(color, depth, color_info, None if depth_info == color_info else depth_info)
