//! blapose-data: reading the data blapose trains and evaluates on.
//!
//! - [`npz`]: a float32 `.npz` reader/writer (the data files and the
//!   replay files).
//! - [`replay`]: the replay-file format (2D keypoints, a lifter's 3D poses,
//!   optional ground truth, camera calibration and subject) that the client
//!   streams and the example generator writes, and the result files.
//! - [`h36m`]: Human3.6M 3D poses, Stacked Hourglass detections and cameras
//!   in the layout of `../shared/data/h36m`.
//! - [`ansur`]: the ANSUR II anthropometric survey CSVs.
//! - [`root`]: where the data lives (flag, `BLAPOSE_DATA`, or
//!   `../shared/data`).
//!
//! Nothing here copies data into the repository: every reader takes the data
//! root at run time.

pub mod ansur;
pub mod h36m;
pub mod npz;
pub mod replay;
pub mod root;

pub use npz::{read_npz, write_npz, Array, Npz, NpzError};
pub use root::{data_root, running_in_ci, test_data_root, DATA_ENV};
