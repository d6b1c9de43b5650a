//! Replay files: a recorded sequence of 2D keypoints and lifted 3D poses.
//!
//! The client streams them and the example generator writes them, so the
//! format lives here, below both, with one implementation of each direction.
//! A replay file is a float32 `.npz` (read and written with [`crate::npz`])
//! holding:
//!
//! | key            | shape       | meaning                                          |
//! |----------------|-------------|--------------------------------------------------|
//! | `keypoints_2d` | `(T, J, 2)` | 2D keypoints in pixels, `J` joints of the layout |
//! | `pose_3d`      | `(T, 17, 3)`| a lifter's 3D poses, metres, Human3.6M order     |
//! | `image_size`   | `(2,)`      | `[width, height]` in pixels (positive integers)  |
//! | `layout`       | `()`/`(1,)` | optional keypoint layout code, see below         |
//! | `gt_3d`        | `(T, 17, 3)`| optional ground truth, same frame as `pose_3d`   |
//! | `confidence`   | `(T, J)`    | optional per-joint detector confidence (>= 0); below 0.1 a joint is missing and its keypoint not read (NaN allowed) |
//! | `fps`          | `()`/`(1,)` | optional frame rate of the recording             |
//! | `camera_up`    | `(3,)`      | optional: world up in camera axes (x right, y down, z forward) |
//! | `camera_focal` | `(2,)`      | optional: `[fx, fy]` focal lengths in pixels, > 0 |
//! | `camera_principal` | `(2,)`  | optional: `[cx, cy]` principal point in pixels   |
//! | `camera_height` | `()`/`(1,)` | optional: camera height above the floor, metres (0.3 to 10) |
//! | `camera_distortion` | `(4,)`/`(5,)` | optional: OpenCV's `k1, k2, p1, p2[, k3]` for keypoints detected in the raw image |
//! | `subject_height` | `()`/`(1,)` | optional: the person's stature, metres |
//! | `subject_sex`  | `()`/`(1,)` | optional, with `subject_height`: 1 female, 2 male |
//!
//! An npz of float32 arrays cannot hold a string, so the layout is a numeric
//! code equal to the protocol's `KeypointLayout` number: `1` = H36M-17,
//! `2` = SH-16 (Stacked Hourglass/MPII), `3` = COCO-17. Without a `layout`
//! array it is inferred from `J`: 17 joints = H36M-17, 16 = SH-16 (COCO-17
//! files must say so, since COCO also has 17 joints).
//!
//! The `camera_*` arrays are the camera's calibration
//! ([`CameraCalibration`], for `image_size`-pixel keypoints): `camera_up`,
//! `camera_focal` and `camera_principal` all three or none, and
//! `camera_height` optional but only with those three. `camera_up` is the
//! direction of world "up" in camera coordinates, any non-zero length; for a
//! camera with world-to-camera rotation `R` and world z up it is `R`'s third
//! column. `camera_height` is the camera's height above the floor in metres
//! (with world z up and the floor at z = 0, its centre's z), 0.3 to 10;
//! leave the key out when it is unknown (a 0 is refused, not read as
//! "unknown"). The shipped camera-aware models need it (they scale each
//! frame to the floor with it); other models ignore it. The CLI sends a
//! file's calibration only when told to (`--camera`); the server's
//! camera-aware models then serve it.
//!
//! Loading checks everything a server would refuse (shapes, frame counts,
//! non-finite values, image size, a partial or invalid calibration) and
//! names the key, frame and joint, so a bad file fails before any network
//! traffic. A file is untrusted input: [`Sequence::load`] opens only these
//! members, checks each header's shape (at most [`DEFAULT_MAX_FRAMES`]
//! frames, or the caller's bound) before reading values, and never inflates
//! a member past what that shape needs ([`crate::npz::NpzArchive`]).
//!
//! Modules: [`keys`] (array names, layout codes), [`sequence`] (the file's
//! content: [`Sequence`], [`FrameInput`]), [`camera`] and [`subject`]
//! (what it may say about the camera and the person), [`output`] (the
//! result files), [`error`] ([`SequenceError`]).

pub mod camera;
mod camera_keys;
pub mod error;
pub mod keys;
pub mod output;
pub mod sequence;
mod source;
pub mod subject;

pub use camera::{CameraCalibration, CameraError};
pub use error::SequenceError;
pub use keys::*;
pub use output::{read_adjusted, read_lifted, write_adjusted, write_adjusted_placed};
pub use sequence::{FrameInput, Sequence, DEFAULT_MAX_FRAMES};
pub use subject::Subject;
