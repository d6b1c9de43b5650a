from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class KeypointLayout(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    KEYPOINT_LAYOUT_UNSPECIFIED: _ClassVar[KeypointLayout]
    KEYPOINT_LAYOUT_H36M_17: _ClassVar[KeypointLayout]
    KEYPOINT_LAYOUT_SH_16: _ClassVar[KeypointLayout]
    KEYPOINT_LAYOUT_COCO_17: _ClassVar[KeypointLayout]

class Model(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    MODEL_UNSPECIFIED: _ClassVar[Model]
    MODEL_ONLINE_GRU: _ClassVar[Model]
    MODEL_OFFLINE_BIGRU: _ClassVar[Model]

class Sex(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    SEX_UNSPECIFIED: _ClassVar[Sex]
    SEX_FEMALE: _ClassVar[Sex]
    SEX_MALE: _ClassVar[Sex]
KEYPOINT_LAYOUT_UNSPECIFIED: KeypointLayout
KEYPOINT_LAYOUT_H36M_17: KeypointLayout
KEYPOINT_LAYOUT_SH_16: KeypointLayout
KEYPOINT_LAYOUT_COCO_17: KeypointLayout
MODEL_UNSPECIFIED: Model
MODEL_ONLINE_GRU: Model
MODEL_OFFLINE_BIGRU: Model
SEX_UNSPECIFIED: Sex
SEX_FEMALE: Sex
SEX_MALE: Sex

class ImageSize(_message.Message):
    __slots__ = ("width", "height")
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    width: int
    height: int
    def __init__(self, width: _Optional[int] = ..., height: _Optional[int] = ...) -> None: ...

class CameraCalibration(_message.Message):
    __slots__ = ("up", "focal_x", "focal_y", "principal_x", "principal_y", "image_size", "height", "distortion")
    UP_FIELD_NUMBER: _ClassVar[int]
    FOCAL_X_FIELD_NUMBER: _ClassVar[int]
    FOCAL_Y_FIELD_NUMBER: _ClassVar[int]
    PRINCIPAL_X_FIELD_NUMBER: _ClassVar[int]
    PRINCIPAL_Y_FIELD_NUMBER: _ClassVar[int]
    IMAGE_SIZE_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    DISTORTION_FIELD_NUMBER: _ClassVar[int]
    up: _containers.RepeatedScalarFieldContainer[float]
    focal_x: float
    focal_y: float
    principal_x: float
    principal_y: float
    image_size: ImageSize
    height: float
    distortion: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, up: _Optional[_Iterable[float]] = ..., focal_x: _Optional[float] = ..., focal_y: _Optional[float] = ..., principal_x: _Optional[float] = ..., principal_y: _Optional[float] = ..., image_size: _Optional[_Union[ImageSize, _Mapping]] = ..., height: _Optional[float] = ..., distortion: _Optional[_Iterable[float]] = ...) -> None: ...

class InputFormat(_message.Message):
    __slots__ = ("layout", "image_size", "normalized")
    LAYOUT_FIELD_NUMBER: _ClassVar[int]
    IMAGE_SIZE_FIELD_NUMBER: _ClassVar[int]
    NORMALIZED_FIELD_NUMBER: _ClassVar[int]
    layout: KeypointLayout
    image_size: ImageSize
    normalized: bool
    def __init__(self, layout: _Optional[_Union[KeypointLayout, str]] = ..., image_size: _Optional[_Union[ImageSize, _Mapping]] = ..., normalized: _Optional[bool] = ...) -> None: ...

class StreamRequest(_message.Message):
    __slots__ = ("open", "resume", "frame", "close", "token_request")
    OPEN_FIELD_NUMBER: _ClassVar[int]
    RESUME_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    CLOSE_FIELD_NUMBER: _ClassVar[int]
    TOKEN_REQUEST_FIELD_NUMBER: _ClassVar[int]
    open: OpenSession
    resume: ResumeSession
    frame: Frame
    close: CloseSession
    token_request: TokenRequest
    def __init__(self, open: _Optional[_Union[OpenSession, _Mapping]] = ..., resume: _Optional[_Union[ResumeSession, _Mapping]] = ..., frame: _Optional[_Union[Frame, _Mapping]] = ..., close: _Optional[_Union[CloseSession, _Mapping]] = ..., token_request: _Optional[_Union[TokenRequest, _Mapping]] = ...) -> None: ...

class TokenRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class OpenSession(_message.Message):
    __slots__ = ("input_format", "model", "client_label", "server_lifter", "camera", "session_tokens", "subject", "motion")
    INPUT_FORMAT_FIELD_NUMBER: _ClassVar[int]
    MODEL_FIELD_NUMBER: _ClassVar[int]
    CLIENT_LABEL_FIELD_NUMBER: _ClassVar[int]
    SERVER_LIFTER_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    SESSION_TOKENS_FIELD_NUMBER: _ClassVar[int]
    SUBJECT_FIELD_NUMBER: _ClassVar[int]
    MOTION_FIELD_NUMBER: _ClassVar[int]
    input_format: InputFormat
    model: Model
    client_label: str
    server_lifter: bool
    camera: CameraCalibration
    session_tokens: bool
    subject: Subject
    motion: MotionOptions
    def __init__(self, input_format: _Optional[_Union[InputFormat, _Mapping]] = ..., model: _Optional[_Union[Model, str]] = ..., client_label: _Optional[str] = ..., server_lifter: _Optional[bool] = ..., camera: _Optional[_Union[CameraCalibration, _Mapping]] = ..., session_tokens: _Optional[bool] = ..., subject: _Optional[_Union[Subject, _Mapping]] = ..., motion: _Optional[_Union[MotionOptions, _Mapping]] = ...) -> None: ...

class Subject(_message.Message):
    __slots__ = ("height_m", "sex")
    HEIGHT_M_FIELD_NUMBER: _ClassVar[int]
    SEX_FIELD_NUMBER: _ClassVar[int]
    height_m: float
    sex: Sex
    def __init__(self, height_m: _Optional[float] = ..., sex: _Optional[_Union[Sex, str]] = ...) -> None: ...

class ResumeSession(_message.Message):
    __slots__ = ("session_id", "session_token", "session_tokens")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    SESSION_TOKEN_FIELD_NUMBER: _ClassVar[int]
    SESSION_TOKENS_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    session_token: bytes
    session_tokens: bool
    def __init__(self, session_id: _Optional[str] = ..., session_token: _Optional[bytes] = ..., session_tokens: _Optional[bool] = ...) -> None: ...

class Frame(_message.Message):
    __slots__ = ("frame_index", "keypoints_2d", "confidence", "pose_3d")
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    KEYPOINTS_2D_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    POSE_3D_FIELD_NUMBER: _ClassVar[int]
    frame_index: int
    keypoints_2d: _containers.RepeatedScalarFieldContainer[float]
    confidence: _containers.RepeatedScalarFieldContainer[float]
    pose_3d: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, frame_index: _Optional[int] = ..., keypoints_2d: _Optional[_Iterable[float]] = ..., confidence: _Optional[_Iterable[float]] = ..., pose_3d: _Optional[_Iterable[float]] = ...) -> None: ...

class CloseSession(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class StreamResponse(_message.Message):
    __slots__ = ("opened", "frame", "error", "closed", "token")
    OPENED_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    ERROR_FIELD_NUMBER: _ClassVar[int]
    CLOSED_FIELD_NUMBER: _ClassVar[int]
    TOKEN_FIELD_NUMBER: _ClassVar[int]
    opened: SessionOpened
    frame: AdjustedFrame
    error: FrameError
    closed: SessionClosed
    token: SessionToken
    def __init__(self, opened: _Optional[_Union[SessionOpened, _Mapping]] = ..., frame: _Optional[_Union[AdjustedFrame, _Mapping]] = ..., error: _Optional[_Union[FrameError, _Mapping]] = ..., closed: _Optional[_Union[SessionClosed, _Mapping]] = ..., token: _Optional[_Union[SessionToken, _Mapping]] = ...) -> None: ...

class SessionToken(_message.Message):
    __slots__ = ("token", "frames_seen")
    TOKEN_FIELD_NUMBER: _ClassVar[int]
    FRAMES_SEEN_FIELD_NUMBER: _ClassVar[int]
    token: bytes
    frames_seen: int
    def __init__(self, token: _Optional[bytes] = ..., frames_seen: _Optional[int] = ...) -> None: ...

class SessionOpened(_message.Message):
    __slots__ = ("session_id", "resumed", "frames_seen", "bone_lengths", "input_format", "model", "session_ttl_ms", "lifter", "camera", "session_token", "subject", "motion")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    RESUMED_FIELD_NUMBER: _ClassVar[int]
    FRAMES_SEEN_FIELD_NUMBER: _ClassVar[int]
    BONE_LENGTHS_FIELD_NUMBER: _ClassVar[int]
    INPUT_FORMAT_FIELD_NUMBER: _ClassVar[int]
    MODEL_FIELD_NUMBER: _ClassVar[int]
    SESSION_TTL_MS_FIELD_NUMBER: _ClassVar[int]
    LIFTER_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    SESSION_TOKEN_FIELD_NUMBER: _ClassVar[int]
    SUBJECT_FIELD_NUMBER: _ClassVar[int]
    MOTION_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    resumed: bool
    frames_seen: int
    bone_lengths: _containers.RepeatedScalarFieldContainer[float]
    input_format: InputFormat
    model: Model
    session_ttl_ms: int
    lifter: str
    camera: CameraCalibration
    session_token: bytes
    subject: Subject
    motion: MotionOptions
    def __init__(self, session_id: _Optional[str] = ..., resumed: _Optional[bool] = ..., frames_seen: _Optional[int] = ..., bone_lengths: _Optional[_Iterable[float]] = ..., input_format: _Optional[_Union[InputFormat, _Mapping]] = ..., model: _Optional[_Union[Model, str]] = ..., session_ttl_ms: _Optional[int] = ..., lifter: _Optional[str] = ..., camera: _Optional[_Union[CameraCalibration, _Mapping]] = ..., session_token: _Optional[bytes] = ..., subject: _Optional[_Union[Subject, _Mapping]] = ..., motion: _Optional[_Union[MotionOptions, _Mapping]] = ...) -> None: ...

class AdjustedFrame(_message.Message):
    __slots__ = ("frame_index", "adjusted_pose_3d", "bone_lengths", "frames_seen", "lifter", "lifted_pose_3d", "root_position", "focal_assumed", "world_pose_3d")
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    ADJUSTED_POSE_3D_FIELD_NUMBER: _ClassVar[int]
    BONE_LENGTHS_FIELD_NUMBER: _ClassVar[int]
    FRAMES_SEEN_FIELD_NUMBER: _ClassVar[int]
    LIFTER_FIELD_NUMBER: _ClassVar[int]
    LIFTED_POSE_3D_FIELD_NUMBER: _ClassVar[int]
    ROOT_POSITION_FIELD_NUMBER: _ClassVar[int]
    FOCAL_ASSUMED_FIELD_NUMBER: _ClassVar[int]
    WORLD_POSE_3D_FIELD_NUMBER: _ClassVar[int]
    frame_index: int
    adjusted_pose_3d: _containers.RepeatedScalarFieldContainer[float]
    bone_lengths: _containers.RepeatedScalarFieldContainer[float]
    frames_seen: int
    lifter: str
    lifted_pose_3d: _containers.RepeatedScalarFieldContainer[float]
    root_position: _containers.RepeatedScalarFieldContainer[float]
    focal_assumed: bool
    world_pose_3d: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, frame_index: _Optional[int] = ..., adjusted_pose_3d: _Optional[_Iterable[float]] = ..., bone_lengths: _Optional[_Iterable[float]] = ..., frames_seen: _Optional[int] = ..., lifter: _Optional[str] = ..., lifted_pose_3d: _Optional[_Iterable[float]] = ..., root_position: _Optional[_Iterable[float]] = ..., focal_assumed: _Optional[bool] = ..., world_pose_3d: _Optional[_Iterable[float]] = ...) -> None: ...

class FrameError(_message.Message):
    __slots__ = ("frame_index", "code", "message")
    FRAME_INDEX_FIELD_NUMBER: _ClassVar[int]
    CODE_FIELD_NUMBER: _ClassVar[int]
    MESSAGE_FIELD_NUMBER: _ClassVar[int]
    frame_index: int
    code: int
    message: str
    def __init__(self, frame_index: _Optional[int] = ..., code: _Optional[int] = ..., message: _Optional[str] = ...) -> None: ...

class SessionClosed(_message.Message):
    __slots__ = ("session_id", "frames_seen", "bone_lengths")
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    FRAMES_SEEN_FIELD_NUMBER: _ClassVar[int]
    BONE_LENGTHS_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    frames_seen: int
    bone_lengths: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, session_id: _Optional[str] = ..., frames_seen: _Optional[int] = ..., bone_lengths: _Optional[_Iterable[float]] = ...) -> None: ...

class CloseSessionRequest(_message.Message):
    __slots__ = ("session_id",)
    SESSION_ID_FIELD_NUMBER: _ClassVar[int]
    session_id: str
    def __init__(self, session_id: _Optional[str] = ...) -> None: ...

class CloseSessionResponse(_message.Message):
    __slots__ = ("frames_seen", "bone_lengths")
    FRAMES_SEEN_FIELD_NUMBER: _ClassVar[int]
    BONE_LENGTHS_FIELD_NUMBER: _ClassVar[int]
    frames_seen: int
    bone_lengths: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, frames_seen: _Optional[int] = ..., bone_lengths: _Optional[_Iterable[float]] = ...) -> None: ...

class AdjustSequenceRequest(_message.Message):
    __slots__ = ("input_format", "model", "num_frames", "keypoints_2d", "confidence", "poses_3d", "camera", "subject", "motion")
    INPUT_FORMAT_FIELD_NUMBER: _ClassVar[int]
    MODEL_FIELD_NUMBER: _ClassVar[int]
    NUM_FRAMES_FIELD_NUMBER: _ClassVar[int]
    KEYPOINTS_2D_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    POSES_3D_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    SUBJECT_FIELD_NUMBER: _ClassVar[int]
    MOTION_FIELD_NUMBER: _ClassVar[int]
    input_format: InputFormat
    model: Model
    num_frames: int
    keypoints_2d: _containers.RepeatedScalarFieldContainer[float]
    confidence: _containers.RepeatedScalarFieldContainer[float]
    poses_3d: _containers.RepeatedScalarFieldContainer[float]
    camera: CameraCalibration
    subject: Subject
    motion: MotionOptions
    def __init__(self, input_format: _Optional[_Union[InputFormat, _Mapping]] = ..., model: _Optional[_Union[Model, str]] = ..., num_frames: _Optional[int] = ..., keypoints_2d: _Optional[_Iterable[float]] = ..., confidence: _Optional[_Iterable[float]] = ..., poses_3d: _Optional[_Iterable[float]] = ..., camera: _Optional[_Union[CameraCalibration, _Mapping]] = ..., subject: _Optional[_Union[Subject, _Mapping]] = ..., motion: _Optional[_Union[MotionOptions, _Mapping]] = ...) -> None: ...

class MotionOptions(_message.Message):
    __slots__ = ("enabled", "frame_rate_hz")
    ENABLED_FIELD_NUMBER: _ClassVar[int]
    FRAME_RATE_HZ_FIELD_NUMBER: _ClassVar[int]
    enabled: bool
    frame_rate_hz: float
    def __init__(self, enabled: _Optional[bool] = ..., frame_rate_hz: _Optional[float] = ...) -> None: ...

class AdjustSequenceResponse(_message.Message):
    __slots__ = ("model", "adjusted_poses_3d", "bone_lengths", "root_positions", "focal_assumed", "world_poses_3d")
    MODEL_FIELD_NUMBER: _ClassVar[int]
    ADJUSTED_POSES_3D_FIELD_NUMBER: _ClassVar[int]
    BONE_LENGTHS_FIELD_NUMBER: _ClassVar[int]
    ROOT_POSITIONS_FIELD_NUMBER: _ClassVar[int]
    FOCAL_ASSUMED_FIELD_NUMBER: _ClassVar[int]
    WORLD_POSES_3D_FIELD_NUMBER: _ClassVar[int]
    model: Model
    adjusted_poses_3d: _containers.RepeatedScalarFieldContainer[float]
    bone_lengths: _containers.RepeatedScalarFieldContainer[float]
    root_positions: _containers.RepeatedScalarFieldContainer[float]
    focal_assumed: bool
    world_poses_3d: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, model: _Optional[_Union[Model, str]] = ..., adjusted_poses_3d: _Optional[_Iterable[float]] = ..., bone_lengths: _Optional[_Iterable[float]] = ..., root_positions: _Optional[_Iterable[float]] = ..., focal_assumed: _Optional[bool] = ..., world_poses_3d: _Optional[_Iterable[float]] = ...) -> None: ...

class ModelInfoRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ModelDescription(_message.Message):
    __slots__ = ("model", "name", "parameter_count", "hidden_size", "weights_source", "weights_sha256", "metadata", "camera_aware")
    class MetadataEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: str
        def __init__(self, key: _Optional[str] = ..., value: _Optional[str] = ...) -> None: ...
    MODEL_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    PARAMETER_COUNT_FIELD_NUMBER: _ClassVar[int]
    HIDDEN_SIZE_FIELD_NUMBER: _ClassVar[int]
    WEIGHTS_SOURCE_FIELD_NUMBER: _ClassVar[int]
    WEIGHTS_SHA256_FIELD_NUMBER: _ClassVar[int]
    METADATA_FIELD_NUMBER: _ClassVar[int]
    CAMERA_AWARE_FIELD_NUMBER: _ClassVar[int]
    model: Model
    name: str
    parameter_count: int
    hidden_size: int
    weights_source: str
    weights_sha256: str
    metadata: _containers.ScalarMap[str, str]
    camera_aware: bool
    def __init__(self, model: _Optional[_Union[Model, str]] = ..., name: _Optional[str] = ..., parameter_count: _Optional[int] = ..., hidden_size: _Optional[int] = ..., weights_source: _Optional[str] = ..., weights_sha256: _Optional[str] = ..., metadata: _Optional[_Mapping[str, str]] = ..., camera_aware: _Optional[bool] = ...) -> None: ...

class LifterDescription(_message.Message):
    __slots__ = ("name", "receptive_field", "parameter_count", "causal", "weights_source", "weights_sha256", "metadata")
    class MetadataEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: str
        def __init__(self, key: _Optional[str] = ..., value: _Optional[str] = ...) -> None: ...
    NAME_FIELD_NUMBER: _ClassVar[int]
    RECEPTIVE_FIELD_FIELD_NUMBER: _ClassVar[int]
    PARAMETER_COUNT_FIELD_NUMBER: _ClassVar[int]
    CAUSAL_FIELD_NUMBER: _ClassVar[int]
    WEIGHTS_SOURCE_FIELD_NUMBER: _ClassVar[int]
    WEIGHTS_SHA256_FIELD_NUMBER: _ClassVar[int]
    METADATA_FIELD_NUMBER: _ClassVar[int]
    name: str
    receptive_field: int
    parameter_count: int
    causal: bool
    weights_source: str
    weights_sha256: str
    metadata: _containers.ScalarMap[str, str]
    def __init__(self, name: _Optional[str] = ..., receptive_field: _Optional[int] = ..., parameter_count: _Optional[int] = ..., causal: _Optional[bool] = ..., weights_source: _Optional[str] = ..., weights_sha256: _Optional[str] = ..., metadata: _Optional[_Mapping[str, str]] = ...) -> None: ...

class ModelInfoResponse(_message.Message):
    __slots__ = ("models", "layouts", "server_version", "protocol", "joint_names", "bone_names", "max_sessions", "session_ttl_ms", "max_batch", "max_message_bytes", "lifter", "accepts")
    MODELS_FIELD_NUMBER: _ClassVar[int]
    LAYOUTS_FIELD_NUMBER: _ClassVar[int]
    SERVER_VERSION_FIELD_NUMBER: _ClassVar[int]
    PROTOCOL_FIELD_NUMBER: _ClassVar[int]
    JOINT_NAMES_FIELD_NUMBER: _ClassVar[int]
    BONE_NAMES_FIELD_NUMBER: _ClassVar[int]
    MAX_SESSIONS_FIELD_NUMBER: _ClassVar[int]
    SESSION_TTL_MS_FIELD_NUMBER: _ClassVar[int]
    MAX_BATCH_FIELD_NUMBER: _ClassVar[int]
    MAX_MESSAGE_BYTES_FIELD_NUMBER: _ClassVar[int]
    LIFTER_FIELD_NUMBER: _ClassVar[int]
    ACCEPTS_FIELD_NUMBER: _ClassVar[int]
    models: _containers.RepeatedCompositeFieldContainer[ModelDescription]
    layouts: _containers.RepeatedScalarFieldContainer[KeypointLayout]
    server_version: str
    protocol: str
    joint_names: _containers.RepeatedScalarFieldContainer[str]
    bone_names: _containers.RepeatedScalarFieldContainer[str]
    max_sessions: int
    session_ttl_ms: int
    max_batch: int
    max_message_bytes: int
    lifter: LifterDescription
    accepts: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, models: _Optional[_Iterable[_Union[ModelDescription, _Mapping]]] = ..., layouts: _Optional[_Iterable[_Union[KeypointLayout, str]]] = ..., server_version: _Optional[str] = ..., protocol: _Optional[str] = ..., joint_names: _Optional[_Iterable[str]] = ..., bone_names: _Optional[_Iterable[str]] = ..., max_sessions: _Optional[int] = ..., session_ttl_ms: _Optional[int] = ..., max_batch: _Optional[int] = ..., max_message_bytes: _Optional[int] = ..., lifter: _Optional[_Union[LifterDescription, _Mapping]] = ..., accepts: _Optional[_Iterable[str]] = ...) -> None: ...
