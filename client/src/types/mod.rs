//! Typed mirrors of the wire messages.
//!
//! The generated protobuf types carry flat `Vec<f32>`s and bare `i32` enum
//! numbers; callers of the library should instead see poses as
//! [`blapose_core::Pose`] and layouts as an enum, with the conversion (and
//! its validation) done once, here. A server answer whose arrays have the
//! wrong length is a protocol violation, reported as such rather than
//! turning into a panic or a silently truncated pose.
//!
//! What client and server share is not written here: the layouts,
//! [`Coordinates`], [`InputFormat`], [`ModelKind`] and [`Sex`] are
//! blapose-core's, their wire mapping is `blapose_proto::convert`'s, a
//! calibration's value checks and height limits are `blapose_core::level`'s
//! (the server's own), and what a replay file shares with a request
//! ([`CameraCalibration`], [`Subject`], [`FrameInput`]) is
//! `blapose_data::replay`'s; all are re-exported. This module adds the
//! client's view, one concept a module:
//!
//! - [`wire`]: the messages built from those shared types ([`ToProto`])
//!   and read back from the server's echoes;
//! - [`frames`]: the answer to one frame ([`AdjustedFrame`]);
//! - [`session_info`]: a session as opened, resumed and closed
//!   ([`SessionInfo`], [`SessionToken`], [`SessionSummary`]);
//! - [`info`]: what the server runs ([`ModelInfo`]).

pub mod frames;
pub mod info;
pub mod session_info;
pub mod wire;

pub use blapose_core::layouts::{Coordinates, InputFormat, KeypointLayout};
pub use blapose_core::level::{MAX_CAMERA_HEIGHT, MIN_CAMERA_HEIGHT};
pub use blapose_core::{ModelKind, Sex};
pub use blapose_data::replay::{
    layout_code, layout_from_code, CameraCalibration, CameraError, FrameInput, Subject,
};
pub use blapose_proto::convert::{layout_from_proto, layout_to_proto};

pub use frames::{AdjustedFrame, LiftedPose, PlacedRoot};
pub use info::{LifterDescription, ModelDescription, ModelInfo};
pub use session_info::{SessionInfo, SessionSummary, SessionToken};
pub use wire::{camera_from_proto, subject_from_proto, ToProto};
