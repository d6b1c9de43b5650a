//! blapose-core: the geometry every other blapose crate stands on.
//!
//! Nothing here knows about neural networks or I/O formats: it is the
//! Human3.6M skeleton, the bone decomposition that BLAPose adjusts, the
//! Human3.6M camera model, the evaluation metrics and the 2D keypoint layouts
//! (with the input formats client and server share). One non-geometric
//! module, [`isa`], is here because both crates with CPU kernels need it and
//! this is the one crate they both depend on.
//! Keeping it dependency-light lets the server, the trainer and the benchmarks
//! share exactly one definition of each.
//!
//! Units: 3D poses are in metres unless a function says otherwise; 2D
//! keypoints are either pixels or *normalized screen coordinates* (see
//! [`camera::normalize_screen`]), and every function names which.

pub mod bones;
pub mod camera;
pub mod isa;
pub mod layouts;
pub mod lens;
pub mod level;
pub mod metrics;
pub mod missing;
pub mod model_kind;
pub mod motion;
pub mod person;
pub mod pose;
pub mod skeleton;

pub use model_kind::ModelKind;
pub use person::Sex;
pub use pose::{BoneDirections, BoneLengths, Keypoints2d, Pose};
pub use skeleton::{NUM_BONES, NUM_JOINTS};
