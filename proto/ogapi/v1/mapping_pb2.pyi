from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class ColorEncoding(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    COLOR_ENCODING_UNSPECIFIED: _ClassVar[ColorEncoding]
    COLOR_JPEG: _ClassVar[ColorEncoding]
    COLOR_PNG: _ClassVar[ColorEncoding]
    COLOR_RAW_RGB8: _ClassVar[ColorEncoding]
    COLOR_RAW_F32: _ClassVar[ColorEncoding]

class DepthEncoding(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    DEPTH_ENCODING_UNSPECIFIED: _ClassVar[DepthEncoding]
    DEPTH_PNG16: _ClassVar[DepthEncoding]
    DEPTH_RAW_F32: _ClassVar[DepthEncoding]

class RenderOutput(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    RENDER_OUTPUT_UNSPECIFIED: _ClassVar[RenderOutput]
    RENDER_OUTPUT_COLOR: _ClassVar[RenderOutput]
    RENDER_OUTPUT_DEPTH: _ClassVar[RenderOutput]
COLOR_ENCODING_UNSPECIFIED: ColorEncoding
COLOR_JPEG: ColorEncoding
COLOR_PNG: ColorEncoding
COLOR_RAW_RGB8: ColorEncoding
COLOR_RAW_F32: ColorEncoding
DEPTH_ENCODING_UNSPECIFIED: DepthEncoding
DEPTH_PNG16: DepthEncoding
DEPTH_RAW_F32: DepthEncoding
RENDER_OUTPUT_UNSPECIFIED: RenderOutput
RENDER_OUTPUT_COLOR: RenderOutput
RENDER_OUTPUT_DEPTH: RenderOutput

class ColorImage(_message.Message):
    __slots__ = ("encoding", "data")
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    encoding: ColorEncoding
    data: bytes
    def __init__(self, encoding: _Optional[_Union[ColorEncoding, str]] = ..., data: _Optional[bytes] = ...) -> None: ...

class DepthImage(_message.Message):
    __slots__ = ("encoding", "data", "depth_scale")
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    DEPTH_SCALE_FIELD_NUMBER: _ClassVar[int]
    encoding: DepthEncoding
    data: bytes
    depth_scale: float
    def __init__(self, encoding: _Optional[_Union[DepthEncoding, str]] = ..., data: _Optional[bytes] = ..., depth_scale: _Optional[float] = ...) -> None: ...

class CameraIntrinsics(_message.Message):
    __slots__ = ("fx", "fy", "cx", "cy", "width", "height")
    FX_FIELD_NUMBER: _ClassVar[int]
    FY_FIELD_NUMBER: _ClassVar[int]
    CX_FIELD_NUMBER: _ClassVar[int]
    CY_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    def __init__(self, fx: _Optional[float] = ..., fy: _Optional[float] = ..., cx: _Optional[float] = ..., cy: _Optional[float] = ..., width: _Optional[int] = ..., height: _Optional[int] = ...) -> None: ...

class CreateSessionRequest(_message.Message):
    __slots__ = ("preset", "overrides", "label", "realtime")
    class OverridesEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: str
        def __init__(self, key: _Optional[str] = ..., value: _Optional[str] = ...) -> None: ...
    PRESET_FIELD_NUMBER: _ClassVar[int]
    OVERRIDES_FIELD_NUMBER: _ClassVar[int]
    LABEL_FIELD_NUMBER: _ClassVar[int]
    REALTIME_FIELD_NUMBER: _ClassVar[int]
    preset: str
    overrides: _containers.ScalarMap[str, str]
    label: str
    realtime: bool
    def __init__(self, preset: _Optional[str] = ..., overrides: _Optional[_Mapping[str, str]] = ..., label: _Optional[str] = ..., realtime: _Optional[bool] = ...) -> None: ...

class SessionCredentials(_message.Message):
    __slots__ = ("session_id", "token", "config_json", "device", "recording")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    TOKEN_FIELD_NUMBER: _ClassVar[int]
    CONFIG_JSON_FIELD_NUMBER: _ClassVar[int]
    DEVICE_FIELD_NUMBER: _ClassVar[int]
    RECORDING_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    token: str
    config_json: str
    device: str
    recording: str
    def __init__(self, session_id: _Optional[str] = ..., token: _Optional[str] = ..., config_json: _Optional[str] = ..., device: _Optional[str] = ..., recording: _Optional[str] = ...) -> None: ...

class SessionConfig(_message.Message):
    __slots__ = ("session_id", "preset", "overrides", "config_json", "device", "label", "created_unix", "server_version", "restored_from_sha256", "realtime")
    class OverridesEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: str
        def __init__(self, key: _Optional[str] = ..., value: _Optional[str] = ...) -> None: ...
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    PRESET_FIELD_NUMBER: _ClassVar[int]
    OVERRIDES_FIELD_NUMBER: _ClassVar[int]
    CONFIG_JSON_FIELD_NUMBER: _ClassVar[int]
    DEVICE_FIELD_NUMBER: _ClassVar[int]
    LABEL_FIELD_NUMBER: _ClassVar[int]
    CREATED_UNIX_FIELD_NUMBER: _ClassVar[int]
    SERVER_VERSION_FIELD_NUMBER: _ClassVar[int]
    RESTORED_FROM_SHA256_FIELD_NUMBER: _ClassVar[int]
    REALTIME_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    preset: str
    overrides: _containers.ScalarMap[str, str]
    config_json: str
    device: str
    label: str
    created_unix: float
    server_version: str
    restored_from_sha256: str
    realtime: bool
    def __init__(self, session_id: _Optional[str] = ..., preset: _Optional[str] = ..., overrides: _Optional[_Mapping[str, str]] = ..., config_json: _Optional[str] = ..., device: _Optional[str] = ..., label: _Optional[str] = ..., created_unix: _Optional[float] = ..., server_version: _Optional[str] = ..., restored_from_sha256: _Optional[str] = ..., realtime: _Optional[bool] = ...) -> None: ...

class Frame(_message.Message):
    __slots__ = ("index", "timestamp", "color", "depth", "color_intrinsics", "depth_intrinsics", "depth_to_color", "c2w")
    INDEX_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMP_FIELD_NUMBER: _ClassVar[int]
    COLOR_FIELD_NUMBER: _ClassVar[int]
    DEPTH_FIELD_NUMBER: _ClassVar[int]
    COLOR_INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    DEPTH_INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    DEPTH_TO_COLOR_FIELD_NUMBER: _ClassVar[int]
    C2W_FIELD_NUMBER: _ClassVar[int]
    index: int
    timestamp: float
    color: ColorImage
    depth: DepthImage
    color_intrinsics: CameraIntrinsics
    depth_intrinsics: CameraIntrinsics
    depth_to_color: _containers.RepeatedScalarFieldContainer[float]
    c2w: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, index: _Optional[int] = ..., timestamp: _Optional[float] = ..., color: _Optional[_Union[ColorImage, _Mapping]] = ..., depth: _Optional[_Union[DepthImage, _Mapping]] = ..., color_intrinsics: _Optional[_Union[CameraIntrinsics, _Mapping]] = ..., depth_intrinsics: _Optional[_Union[CameraIntrinsics, _Mapping]] = ..., depth_to_color: _Optional[_Iterable[float]] = ..., c2w: _Optional[_Iterable[float]] = ...) -> None: ...

class Error(_message.Message):
    __slots__ = ("code", "code_name", "message")
    CODE_FIELD_NUMBER: _ClassVar[int]
    CODE_NAME_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    code: int
    code_name: str
    message: str
    def __init__(self, code: _Optional[int] = ..., code_name: _Optional[str] = ..., message: _Optional[str] = ...) -> None: ...

class FrameAck(_message.Message):
    __slots__ = ("index", "accepted", "sequence", "keyframe", "anchors", "gaussians", "iterations", "latency_seconds", "process_seconds", "queue_depth", "error", "skipped", "unrecorded", "pose_correction")
    INDEX_FIELD_NUMBER: _ClassVar[int]
    ACCEPTED_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    KEYFRAME_FIELD_NUMBER: _ClassVar[int]
    ANCHORS_FIELD_NUMBER: _ClassVar[int]
    GAUSSIANS_FIELD_NUMBER: _ClassVar[int]
    ITERATIONS_FIELD_NUMBER: _ClassVar[int]
    LATENCY_SECONDS_FIELD_NUMBER: _ClassVar[int]
    PROCESS_SECONDS_FIELD_NUMBER: _ClassVar[int]
    QUEUE_DEPTH_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    SKIPPED_FIELD_NUMBER: _ClassVar[int]
    UNRECORDED_FIELD_NUMBER: _ClassVar[int]
    POSE_CORRECTION_FIELD_NUMBER: _ClassVar[int]
    index: int
    accepted: bool
    sequence: int
    keyframe: bool
    anchors: int
    gaussians: int
    iterations: int
    latency_seconds: float
    process_seconds: float
    queue_depth: int
    error: Error
    skipped: bool
    unrecorded: bool
    pose_correction: PoseCorrection
    def __init__(self, index: _Optional[int] = ..., accepted: _Optional[bool] = ..., sequence: _Optional[int] = ..., keyframe: _Optional[bool] = ..., anchors: _Optional[int] = ..., gaussians: _Optional[int] = ..., iterations: _Optional[int] = ..., latency_seconds: _Optional[float] = ..., process_seconds: _Optional[float] = ..., queue_depth: _Optional[int] = ..., error: _Optional[_Union[Error, _Mapping]] = ..., skipped: _Optional[bool] = ..., unrecorded: _Optional[bool] = ..., pose_correction: _Optional[_Union[PoseCorrection, _Mapping]] = ...) -> None: ...

class PoseCorrection(_message.Message):
    __slots__ = ("translation", "rotation", "clamped", "refined_c2w")
    TRANSLATION_FIELD_NUMBER: _ClassVar[int]
    ROTATION_FIELD_NUMBER: _ClassVar[int]
    CLAMPED_FIELD_NUMBER: _ClassVar[int]
    REFINED_C2W_FIELD_NUMBER: _ClassVar[int]
    translation: _containers.RepeatedScalarFieldContainer[float]
    rotation: _containers.RepeatedScalarFieldContainer[float]
    clamped: bool
    refined_c2w: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, translation: _Optional[_Iterable[float]] = ..., rotation: _Optional[_Iterable[float]] = ..., clamped: _Optional[bool] = ..., refined_c2w: _Optional[_Iterable[float]] = ...) -> None: ...

class CorrectedPose(_message.Message):
    __slots__ = ("sequence", "timestamp", "c2w")
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMP_FIELD_NUMBER: _ClassVar[int]
    C2W_FIELD_NUMBER: _ClassVar[int]
    sequence: int
    timestamp: float
    c2w: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, sequence: _Optional[int] = ..., timestamp: _Optional[float] = ..., c2w: _Optional[_Iterable[float]] = ...) -> None: ...

class CorrectPosesRequest(_message.Message):
    __slots__ = ("session_id", "poses")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    POSES_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    poses: _containers.RepeatedCompositeFieldContainer[CorrectedPose]
    def __init__(self, session_id: _Optional[str] = ..., poses: _Optional[_Iterable[_Union[CorrectedPose, _Mapping]]] = ...) -> None: ...

class CorrectPosesResponse(_message.Message):
    __slots__ = ("keyframes", "frames", "anchors_moved", "after_sequence")
    KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    ANCHORS_MOVED_FIELD_NUMBER: _ClassVar[int]
    AFTER_SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    keyframes: int
    frames: int
    anchors_moved: int
    after_sequence: int
    def __init__(self, keyframes: _Optional[int] = ..., frames: _Optional[int] = ..., anchors_moved: _Optional[int] = ..., after_sequence: _Optional[int] = ...) -> None: ...

class PoseCorrections(_message.Message):
    __slots__ = ("after_sequence", "poses")
    AFTER_SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    POSES_FIELD_NUMBER: _ClassVar[int]
    after_sequence: int
    poses: _containers.RepeatedCompositeFieldContainer[CorrectedPose]
    def __init__(self, after_sequence: _Optional[int] = ..., poses: _Optional[_Iterable[_Union[CorrectedPose, _Mapping]]] = ...) -> None: ...

class RenderRequest(_message.Message):
    __slots__ = ("session_id", "c2w", "intrinsics", "outputs", "color_encoding", "depth_encoding", "jpeg_quality", "sequence", "timestamp")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    C2W_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    OUTPUTS_FIELD_NUMBER: _ClassVar[int]
    COLOR_ENCODING_FIELD_NUMBER: _ClassVar[int]
    DEPTH_ENCODING_FIELD_NUMBER: _ClassVar[int]
    JPEG_QUALITY_FIELD_NUMBER: _ClassVar[int]
    SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMP_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    c2w: _containers.RepeatedScalarFieldContainer[float]
    intrinsics: CameraIntrinsics
    outputs: _containers.RepeatedScalarFieldContainer[RenderOutput]
    color_encoding: ColorEncoding
    depth_encoding: DepthEncoding
    jpeg_quality: int
    sequence: int
    timestamp: float
    def __init__(self, session_id: _Optional[str] = ..., c2w: _Optional[_Iterable[float]] = ..., intrinsics: _Optional[_Union[CameraIntrinsics, _Mapping]] = ..., outputs: _Optional[_Iterable[_Union[RenderOutput, str]]] = ..., color_encoding: _Optional[_Union[ColorEncoding, str]] = ..., depth_encoding: _Optional[_Union[DepthEncoding, str]] = ..., jpeg_quality: _Optional[int] = ..., sequence: _Optional[int] = ..., timestamp: _Optional[float] = ...) -> None: ...

class RenderResponse(_message.Message):
    __slots__ = ("color", "depth", "width", "height", "render_seconds")
    COLOR_FIELD_NUMBER: _ClassVar[int]
    DEPTH_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    RENDER_SECONDS_FIELD_NUMBER: _ClassVar[int]
    color: ColorImage
    depth: DepthImage
    width: int
    height: int
    render_seconds: float
    def __init__(self, color: _Optional[_Union[ColorImage, _Mapping]] = ..., depth: _Optional[_Union[DepthImage, _Mapping]] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., render_seconds: _Optional[float] = ...) -> None: ...

class GetStatsRequest(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class Stats(_message.Message):
    __slots__ = ("session_id", "preset", "device", "frames", "keyframes", "anchors", "anchors_per_level", "gaussians", "iterations", "timings", "frames_received", "frames_rejected", "queue_depth", "processing_fps", "uptime_seconds", "engine_json", "config_json", "last_sequence", "last_index", "mapped_sequence", "frames_skipped", "poses")
    class TimingsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: float
        def __init__(self, key: _Optional[str] = ..., value: _Optional[float] = ...) -> None: ...
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    PRESET_FIELD_NUMBER: _ClassVar[int]
    DEVICE_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    ANCHORS_FIELD_NUMBER: _ClassVar[int]
    ANCHORS_PER_LEVEL_FIELD_NUMBER: _ClassVar[int]
    GAUSSIANS_FIELD_NUMBER: _ClassVar[int]
    ITERATIONS_FIELD_NUMBER: _ClassVar[int]
    TIMINGS_FIELD_NUMBER: _ClassVar[int]
    FRAMES_RECEIVED_FIELD_NUMBER: _ClassVar[int]
    FRAMES_REJECTED_FIELD_NUMBER: _ClassVar[int]
    QUEUE_DEPTH_FIELD_NUMBER: _ClassVar[int]
    PROCESSING_FPS_FIELD_NUMBER: _ClassVar[int]
    UPTIME_SECONDS_FIELD_NUMBER: _ClassVar[int]
    ENGINE_JSON_FIELD_NUMBER: _ClassVar[int]
    CONFIG_JSON_FIELD_NUMBER: _ClassVar[int]
    LAST_SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    LAST_INDEX_FIELD_NUMBER: _ClassVar[int]
    MAPPED_SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    FRAMES_SKIPPED_FIELD_NUMBER: _ClassVar[int]
    POSES_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    preset: str
    device: str
    frames: int
    keyframes: int
    anchors: int
    anchors_per_level: _containers.RepeatedScalarFieldContainer[int]
    gaussians: int
    iterations: int
    timings: _containers.ScalarMap[str, float]
    frames_received: int
    frames_rejected: int
    queue_depth: int
    processing_fps: float
    uptime_seconds: float
    engine_json: str
    config_json: str
    last_sequence: int
    last_index: int
    mapped_sequence: int
    frames_skipped: int
    poses: PoseSummary
    def __init__(self, session_id: _Optional[str] = ..., preset: _Optional[str] = ..., device: _Optional[str] = ..., frames: _Optional[int] = ..., keyframes: _Optional[int] = ..., anchors: _Optional[int] = ..., anchors_per_level: _Optional[_Iterable[int]] = ..., gaussians: _Optional[int] = ..., iterations: _Optional[int] = ..., timings: _Optional[_Mapping[str, float]] = ..., frames_received: _Optional[int] = ..., frames_rejected: _Optional[int] = ..., queue_depth: _Optional[int] = ..., processing_fps: _Optional[float] = ..., uptime_seconds: _Optional[float] = ..., engine_json: _Optional[str] = ..., config_json: _Optional[str] = ..., last_sequence: _Optional[int] = ..., last_index: _Optional[int] = ..., mapped_sequence: _Optional[int] = ..., frames_skipped: _Optional[int] = ..., poses: _Optional[_Union[PoseSummary, _Mapping]] = ...) -> None: ...

class PoseSummary(_message.Message):
    __slots__ = ("refined_keyframes", "mean_correction_m", "max_correction_m", "mean_correction_deg", "max_correction_deg", "clamped_keyframes")
    REFINED_KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    MEAN_CORRECTION_M_FIELD_NUMBER: _ClassVar[int]
    MAX_CORRECTION_M_FIELD_NUMBER: _ClassVar[int]
    MEAN_CORRECTION_DEG_FIELD_NUMBER: _ClassVar[int]
    MAX_CORRECTION_DEG_FIELD_NUMBER: _ClassVar[int]
    CLAMPED_KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    refined_keyframes: int
    mean_correction_m: float
    max_correction_m: float
    mean_correction_deg: float
    max_correction_deg: float
    clamped_keyframes: int
    def __init__(self, refined_keyframes: _Optional[int] = ..., mean_correction_m: _Optional[float] = ..., max_correction_m: _Optional[float] = ..., mean_correction_deg: _Optional[float] = ..., max_correction_deg: _Optional[float] = ..., clamped_keyframes: _Optional[int] = ...) -> None: ...

class GetSnapshotRequest(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class SnapshotChunk(_message.Message):
    __slots__ = ("data", "offset", "total_bytes", "sha256")
    DATA_FIELD_NUMBER: _ClassVar[int]
    OFFSET_FIELD_NUMBER: _ClassVar[int]
    TOTAL_BYTES_FIELD_NUMBER: _ClassVar[int]
    SHA256_FIELD_NUMBER: _ClassVar[int]
    data: bytes
    offset: int
    total_bytes: int
    sha256: str
    def __init__(self, data: _Optional[bytes] = ..., offset: _Optional[int] = ..., total_bytes: _Optional[int] = ..., sha256: _Optional[str] = ...) -> None: ...

class RestoreChunk(_message.Message):
    __slots__ = ("data", "label")
    DATA_FIELD_NUMBER: _ClassVar[int]
    LABEL_FIELD_NUMBER: _ClassVar[int]
    data: bytes
    label: str
    def __init__(self, data: _Optional[bytes] = ..., label: _Optional[str] = ...) -> None: ...

class ListSessionsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class SessionInfo(_message.Message):
    __slots__ = ("session_id", "preset", "label", "device", "created_unix", "frames", "anchors", "queue_depth", "streaming", "recording", "last_sequence", "last_index")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    PRESET_FIELD_NUMBER: _ClassVar[int]
    LABEL_FIELD_NUMBER: _ClassVar[int]
    DEVICE_FIELD_NUMBER: _ClassVar[int]
    CREATED_UNIX_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    ANCHORS_FIELD_NUMBER: _ClassVar[int]
    QUEUE_DEPTH_FIELD_NUMBER: _ClassVar[int]
    STREAMING_FIELD_NUMBER: _ClassVar[int]
    RECORDING_FIELD_NUMBER: _ClassVar[int]
    LAST_SEQUENCE_FIELD_NUMBER: _ClassVar[int]
    LAST_INDEX_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    preset: str
    label: str
    device: str
    created_unix: float
    frames: int
    anchors: int
    queue_depth: int
    streaming: bool
    recording: str
    last_sequence: int
    last_index: int
    def __init__(self, session_id: _Optional[str] = ..., preset: _Optional[str] = ..., label: _Optional[str] = ..., device: _Optional[str] = ..., created_unix: _Optional[float] = ..., frames: _Optional[int] = ..., anchors: _Optional[int] = ..., queue_depth: _Optional[int] = ..., streaming: _Optional[bool] = ..., recording: _Optional[str] = ..., last_sequence: _Optional[int] = ..., last_index: _Optional[int] = ...) -> None: ...

class ListSessionsResponse(_message.Message):
    __slots__ = ("sessions",)
    SESSIONS_FIELD_NUMBER: _ClassVar[int]
    sessions: _containers.RepeatedCompositeFieldContainer[SessionInfo]
    def __init__(self, sessions: _Optional[_Iterable[_Union[SessionInfo, _Mapping]]] = ...) -> None: ...

class CloseSessionRequest(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class CloseSessionResponse(_message.Message):
    __slots__ = ("stats", "recording", "snapshot")
    STATS_FIELD_NUMBER: _ClassVar[int]
    RECORDING_FIELD_NUMBER: _ClassVar[int]
    SNAPSHOT_FIELD_NUMBER: _ClassVar[int]
    stats: Stats
    recording: str
    snapshot: str
    def __init__(self, stats: _Optional[_Union[Stats, _Mapping]] = ..., recording: _Optional[str] = ..., snapshot: _Optional[str] = ...) -> None: ...
