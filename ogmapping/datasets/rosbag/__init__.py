"""ROS 1 ``.bag`` and ROS 2 bags (sqlite3, MCAP) as a frame source, through the pure-Python ``rosbags``.

The modules, one idea each: ``layout`` (is this path a bag), ``options`` (the user's choices, the
``--bag`` flags), ``bagfile`` (an open bag: topics, messages, one message again), ``headers`` (a
message's stamp and frame without decoding its image), ``images`` (Image / CompressedImage to colour and metres),
``calibration`` (CameraInfo to intrinsics, undistortion), ``transforms`` (TF trees, interpolated
tracks), ``topics`` (which topics hold what, chosen by flag or because there is exactly one),
``poses`` (TF or a pose topic, as camera-to-world at an image stamp), ``corrected`` (a SLAM system's
corrected trajectory on a topic, as the frames' poses), ``pairing`` (colour with depth by stamp) and
``source`` (``RosBag``, the ``FrameSource``).

Conventions: ROS optical frames (``*_optical_frame``, REP 103) have OpenCV's axes, x right, y down,
z forward, which are ours, so a pose of the image's frame is a ``c2w`` as it is. CameraInfo K has
integer pixel centres and gets +0.5 on cx, cy like every dataset here (``base.opencv_intrinsics``).
``rosbags`` is imported only when a bag is opened: without the ``robots`` extra the other readers work.
"""

from ogmapping.datasets.rosbag.layout import is_bag

__all__ = ["is_bag"]
