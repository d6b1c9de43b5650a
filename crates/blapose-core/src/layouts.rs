//! 2D keypoint layouts and their conversion to the Human3.6M 17-joint order
//! the bone-length model consumes.
//!
//! Detectors emit different joint sets; the model only understands
//! Human3.6M-17. Each conversion copies the joints a layout has and
//! synthesizes the ones it lacks from its neighbours. The synthesis
//! coefficients were fitted, and the quality measured, on the real data in
//! `../shared/data/h36m` (see "Measured quality" below and the
//! `*_quality_on_test_subjects` tests in `blapose-data/tests/h36m_real.rs`).
//!
//! # Layouts
//!
//! - [`KeypointLayout::H36m17`]: native, copied unchanged.
//! - [`KeypointLayout::Sh16`]: the 16-joint Stacked Hourglass / MPII layout
//!   of `detections_sh.npz` (`sh_16` in `cameras.json`): r_ankle, r_knee,
//!   r_hip, l_hip, l_knee, l_ankle, pelvis, spine, thorax, head(top),
//!   r_wrist, r_elbow, r_shoulder, l_shoulder, l_elbow, l_wrist. Copied:
//!   pelvis, hips, knees, ankles, thorax, shoulders, elbows, wrists.
//!   Synthesized (`lerp(a, b, f) = a + f (b - a)`):
//!   `neck_nose = lerp(thorax, head_top, 0.22)`,
//!   `head = lerp(thorax, head_top, 0.48)` (the detector's head *top* is not
//!   Human3.6M's head joint: copying it is 23 px off) and
//!   `spine = lerp(pelvis, thorax, 0.51)` (the detector's own "spine" point
//!   lies elsewhere: copying it is 46 px off, the synthesis 7 px).
//! - [`KeypointLayout::Coco17`]: what most detectors emit: nose, l_eye,
//!   r_eye, l_ear, r_ear, l_shoulder, r_shoulder, l_elbow, r_elbow, l_wrist,
//!   r_wrist, l_hip, r_hip, l_knee, r_knee, l_ankle, r_ankle. Copied: limbs,
//!   hips, shoulders; `neck_nose = nose`. Synthesized:
//!   `pelvis = mid-hips`, `thorax = lerp(mid-shoulders, nose, 0.37)`,
//!   `spine = lerp(pelvis, thorax, 0.49)`, `head = lerp(thorax, nose, 1.84)`
//!   (beyond the nose). Eyes and ears are unused: their relation to
//!   Human3.6M's joints cannot be measured on this data.
//!
//! The coefficients are least-squares fits on the *training* subjects (S1,
//! S5, S6, S7, S8; every 5th frame, all cameras): SH16 against the real
//! detections, COCO-17 on projected ground truth. The ignored test
//! `calibrate_layout_constants` in `blapose-data/tests/h36m_real.rs`
//! re-derives them.
//!
//! # Measured quality (test subjects S9 + S11, all frames, all cameras)
//!
//! SH16 detections converted to H36M-17 vs the ground truth projected with
//! `cameras.json`, median pixel distance per joint (images ~1000 px wide):
//!
//! | joint | px | joint | px | joint | px |
//! |---|---|---|---|---|---|
//! | pelvis | 7.9 | spine | 7.3 | l_shoulder | 7.3 |
//! | r_hip | 11.1 | thorax | 7.7 | l_elbow | 7.5 |
//! | r_knee | 7.6 | neck_nose* | 7.8 | l_wrist | 7.2 |
//! | r_ankle | 12.4 | head* | 9.5 | r_shoulder | 7.3 |
//! | l_hip | 9.4 | | | r_elbow | 7.1 |
//! | l_knee | 9.3 | | | r_wrist | 7.6 |
//! | l_ankle | 17.1 | all joints | 8.7 | | |
//!
//! (* synthesized; spine too.) Most of the error is the detector's, not the
//! conversion's: copied joints are 7-17 px off.
//!
//! COCO-17: no COCO detections exist in the data, so only the synthesis is
//! measured, with projected ground truth standing in for a perfect COCO
//! detector (nose = Human3.6M neck_nose): pelvis 0.2 px, spine 5.9 px,
//! thorax 4.7 px, head 15.0 px. This bounds the error from below: real COCO
//! hips sit lower and wider than Human3.6M's and a real nose is not
//! Human3.6M's neck_nose, offsets this data cannot measure.
//!
//! # Input formats
//!
//! A client's keypoints are a layout plus a unit: pixels of an image of a
//! known size, or normalized screen coordinates
//! ([`crate::camera::normalize_screen`]). [`Coordinates`] and
//! [`InputFormat`] are that pair, defined here once so the client library
//! (which builds them) and the server (which validates and echoes them)
//! share one type; `blapose-proto` converts them to and from the wire.

use std::fmt;
use std::str::FromStr;

use crate::camera::normalize_screen;
use crate::pose::Keypoints2d;
use crate::skeleton::{joint_index, JOINT_NAMES, NUM_JOINTS};

/// SH16: `neck_nose = thorax + f * (head_top - thorax)`.
pub const SH16_NECK_FRACTION: f32 = 0.22;
/// SH16: `spine = pelvis + f * (thorax - pelvis)` (the detector's own
/// "spine" is a different point, see the module docs).
pub const SH16_SPINE_FRACTION: f32 = 0.51;
/// SH16: `head = thorax + f * (head_top - thorax)`.
pub const SH16_HEAD_FRACTION: f32 = 0.48;
/// COCO-17: `thorax = mid_shoulders + f * (nose - mid_shoulders)`.
pub const COCO_THORAX_FRACTION: f32 = 0.37;
/// COCO-17: `spine = pelvis + f * (thorax - pelvis)`.
pub const COCO_SPINE_FRACTION: f32 = 0.49;
/// COCO-17: `head = thorax + f * (nose - thorax)` (f > 1: beyond the nose).
pub const COCO_HEAD_FACTOR: f32 = 1.84;

/// Joint names of the SH16 layout, in its order.
pub const SH16_JOINTS: [&str; 16] = [
    "r_ankle",
    "r_knee",
    "r_hip",
    "l_hip",
    "l_knee",
    "l_ankle",
    "pelvis",
    "spine",
    "thorax",
    "head",
    "r_wrist",
    "r_elbow",
    "r_shoulder",
    "l_shoulder",
    "l_elbow",
    "l_wrist",
];

/// Joint names of the COCO-17 layout, in its order.
pub const COCO17_JOINTS: [&str; 17] = [
    "nose",
    "l_eye",
    "r_eye",
    "l_ear",
    "r_ear",
    "l_shoulder",
    "r_shoulder",
    "l_elbow",
    "r_elbow",
    "l_wrist",
    "r_wrist",
    "l_hip",
    "r_hip",
    "l_knee",
    "r_knee",
    "l_ankle",
    "r_ankle",
];

/// Why keypoints could not be converted.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LayoutError {
    /// The frame has the wrong number of joints for its layout.
    #[error("layout {layout} has {expected} joints, got {got}")]
    WrongJointCount {
        /// The layout.
        layout: KeypointLayout,
        /// Its joint count.
        expected: usize,
        /// Joints given.
        got: usize,
    },
    /// A keypoint is NaN or infinite.
    #[error("layout {layout}: joint {joint} ({name}) is not finite")]
    NonFinite {
        /// The layout.
        layout: KeypointLayout,
        /// Joint index in that layout.
        joint: usize,
        /// Joint name in that layout.
        name: &'static str,
    },
    /// The flat buffer is not a whole number of frames.
    #[error("layout {layout}: {len} values is not a whole number of frames of {per_frame}")]
    RaggedBuffer {
        /// The layout.
        layout: KeypointLayout,
        /// Buffer length.
        len: usize,
        /// Values per frame.
        per_frame: usize,
    },
    /// An unknown layout name.
    #[error("unknown keypoint layout {0:?} (expected one of h36m17, sh16, coco17)")]
    Unknown(String),
}

/// A 2D keypoint layout.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum KeypointLayout {
    /// Human3.6M 17 joints (native).
    H36m17,
    /// Stacked Hourglass / MPII 16 joints (`sh_16`).
    Sh16,
    /// COCO 17 keypoints.
    Coco17,
}

impl KeypointLayout {
    /// Every layout.
    pub const ALL: [KeypointLayout; 3] = [Self::H36m17, Self::Sh16, Self::Coco17];

    /// Canonical name (`h36m17`, `sh16`, `coco17`), accepted by `FromStr`.
    pub fn name(&self) -> &'static str {
        match self {
            Self::H36m17 => "h36m17",
            Self::Sh16 => "sh16",
            Self::Coco17 => "coco17",
        }
    }

    /// Joint names in the layout's order.
    pub fn joint_names(&self) -> &'static [&'static str] {
        match self {
            Self::H36m17 => &JOINT_NAMES,
            Self::Sh16 => &SH16_JOINTS,
            Self::Coco17 => &COCO17_JOINTS,
        }
    }

    /// Number of joints per frame.
    pub fn num_joints(&self) -> usize {
        self.joint_names().len()
    }

    fn validate(&self, points: &[[f32; 2]]) -> Result<(), LayoutError> {
        if points.len() != self.num_joints() {
            return Err(LayoutError::WrongJointCount {
                layout: *self,
                expected: self.num_joints(),
                got: points.len(),
            });
        }
        if let Some(joint) = points
            .iter()
            .position(|p| !(p[0].is_finite() && p[1].is_finite()))
        {
            return Err(LayoutError::NonFinite {
                layout: *self,
                joint,
                name: self.joint_names()[joint],
            });
        }
        Ok(())
    }

    /// Convert one frame to Human3.6M-17 order (same units as the input:
    /// pixels or normalized coordinates both work, every rule is affine).
    pub fn to_h36m17(&self, points: &[[f32; 2]]) -> Result<Keypoints2d, LayoutError> {
        self.validate(points)?;
        Ok(match self {
            Self::H36m17 => std::array::from_fn(|j| points[j]),
            Self::Sh16 => sh16_to_h36m(points),
            Self::Coco17 => coco17_to_h36m(points),
        })
    }

    /// Which Human3.6M-17 joints a frame has when only the joints
    /// `present` (this layout's order) were detected: a converted joint is
    /// missing when any joint it is made from is (e.g. COCO-17's thorax,
    /// made from the shoulders and the nose). Found by converting the
    /// missing joints' indicator through the same (affine) rules.
    pub fn present_h36m17(&self, present: &[bool]) -> Result<[bool; NUM_JOINTS], LayoutError> {
        let indicator: Vec<[f32; 2]> = present
            .iter()
            .map(|&p| [if p { 0.0 } else { 1.0 }, 0.0])
            .collect();
        let converted = self.to_h36m17(&indicator)?;
        Ok(std::array::from_fn(|j| converted[j][0].abs() < 1e-6))
    }

    /// Convert a flat buffer of frames (`T * num_joints * 2` values).
    pub fn sequence_to_h36m17(&self, flat: &[f32]) -> Result<Vec<Keypoints2d>, LayoutError> {
        let per_frame = self.num_joints() * 2;
        if !flat.len().is_multiple_of(per_frame) {
            return Err(LayoutError::RaggedBuffer {
                layout: *self,
                len: flat.len(),
                per_frame,
            });
        }
        let mut frame = vec![[0.0f32; 2]; self.num_joints()];
        flat.chunks_exact(per_frame)
            .map(|c| {
                for (j, p) in frame.iter_mut().enumerate() {
                    *p = [c[2 * j], c[2 * j + 1]];
                }
                self.to_h36m17(&frame)
            })
            .collect()
    }
}

fn lerp(a: [f32; 2], b: [f32; 2], t: f32) -> [f32; 2] {
    [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])]
}

/// Index of a Human3.6M joint by name; only called with names from
/// [`JOINT_NAMES`] that the tests cover.
fn h(name: &str) -> usize {
    joint_index(name).unwrap_or(0)
}

fn by_name(names: &[&str], points: &[[f32; 2]], name: &str) -> [f32; 2] {
    names
        .iter()
        .position(|n| *n == name)
        .map_or([0.0; 2], |i| points[i])
}

fn sh16_to_h36m(points: &[[f32; 2]]) -> Keypoints2d {
    let mut out = [[0.0f32; 2]; NUM_JOINTS];
    for (j, name) in JOINT_NAMES.iter().enumerate() {
        if let Some(s) = SH16_JOINTS.iter().position(|n| n == name) {
            out[j] = points[s];
        }
    }
    let (pelvis, thorax, top) = (out[h("pelvis")], out[h("thorax")], out[h("head")]);
    out[h("neck_nose")] = lerp(thorax, top, SH16_NECK_FRACTION);
    out[h("spine")] = lerp(pelvis, thorax, SH16_SPINE_FRACTION);
    out[h("head")] = lerp(thorax, top, SH16_HEAD_FRACTION);
    out
}

fn coco17_to_h36m(points: &[[f32; 2]]) -> Keypoints2d {
    let mut out = [[0.0f32; 2]; NUM_JOINTS];
    for (j, name) in JOINT_NAMES.iter().enumerate() {
        if let Some(s) = COCO17_JOINTS.iter().position(|n| n == name) {
            out[j] = points[s];
        }
    }
    let c = |n| by_name(&COCO17_JOINTS, points, n);
    let pelvis = lerp(c("r_hip"), c("l_hip"), 0.5);
    let thorax = lerp(
        lerp(c("r_shoulder"), c("l_shoulder"), 0.5),
        c("nose"),
        COCO_THORAX_FRACTION,
    );
    out[h("pelvis")] = pelvis;
    out[h("thorax")] = thorax;
    out[h("spine")] = lerp(pelvis, thorax, COCO_SPINE_FRACTION);
    out[h("neck_nose")] = c("nose");
    out[h("head")] = lerp(thorax, c("nose"), COCO_HEAD_FACTOR);
    out
}

/// How keypoints are expressed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Coordinates {
    /// Pixels of an image of this size (both > 0 where a format is
    /// validated).
    Pixels {
        /// Image width in pixels.
        width: u32,
        /// Image height in pixels.
        height: u32,
    },
    /// Already normalized screen coordinates (`x/w*2-1`, `y/w*2-h/w`).
    Normalized,
}

impl Coordinates {
    /// A point given in these coordinates, in normalized screen
    /// coordinates: [`normalize_screen`] for pixels, unchanged otherwise.
    #[inline]
    pub fn normalize(self, point: [f32; 2]) -> [f32; 2] {
        match self {
            Coordinates::Pixels { width, height } => normalize_screen(point, width, height),
            Coordinates::Normalized => point,
        }
    }
}

/// Layout plus coordinate convention of a session's (or a sequence's)
/// keypoints; fixed for a session's life.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct InputFormat {
    /// Joint order.
    pub layout: KeypointLayout,
    /// Pixels or normalized coordinates.
    pub coordinates: Coordinates,
}

impl InputFormat {
    /// Pixel keypoints of an image `width` x `height`.
    pub const fn pixels(layout: KeypointLayout, width: u32, height: u32) -> Self {
        InputFormat {
            layout,
            coordinates: Coordinates::Pixels { width, height },
        }
    }
}

impl fmt::Display for KeypointLayout {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for KeypointLayout {
    type Err = LayoutError;

    /// Accepts the canonical names and common spellings, case-insensitively:
    /// `h36m17`/`h36m`/`h36m_17`, `sh16`/`sh_16`/`mpii`, `coco17`/`coco`/`coco_17`.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.to_ascii_lowercase().replace(['-', '_'], "").as_str() {
            "h36m17" | "h36m" | "human36m" => Ok(Self::H36m17),
            "sh16" | "sh" | "mpii" | "mpii16" => Ok(Self::Sh16),
            "coco17" | "coco" => Ok(Self::Coco17),
            _ => Err(LayoutError::Unknown(s.to_owned())),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn missing_source_joints_make_their_converted_joints_missing() {
        let all = KeypointLayout::Coco17.present_h36m17(&[true; 17]).unwrap();
        assert!(all.iter().all(|&p| p));
        // COCO's eyes and ears feed no Human3.6M joint; the nose feeds the
        // thorax, spine, neck/nose and head.
        let mut face = [true; 17];
        for name in ["l_eye", "r_eye", "l_ear", "r_ear"] {
            face[COCO17_JOINTS.iter().position(|n| *n == name).unwrap()] = false;
        }
        assert!(KeypointLayout::Coco17
            .present_h36m17(&face)
            .unwrap()
            .iter()
            .all(|&p| p));
        face[COCO17_JOINTS.iter().position(|n| *n == "nose").unwrap()] = false;
        let got = KeypointLayout::Coco17.present_h36m17(&face).unwrap();
        let missing: Vec<&str> = (0..NUM_JOINTS)
            .filter(|&j| !got[j])
            .map(|j| JOINT_NAMES[j])
            .collect();
        assert_eq!(missing, ["spine", "thorax", "neck_nose", "head"]);
        let mut h = [true; NUM_JOINTS];
        h[3] = false;
        assert_eq!(KeypointLayout::H36m17.present_h36m17(&h).unwrap(), h);
        assert!(KeypointLayout::Sh16.present_h36m17(&[true; 3]).is_err());
    }

    #[test]
    fn names_round_trip() {
        for l in KeypointLayout::ALL {
            assert_eq!(l.name().parse::<KeypointLayout>().unwrap(), l);
            assert_eq!(l.to_string(), l.name());
        }
        assert_eq!(
            "SH_16".parse::<KeypointLayout>().unwrap(),
            KeypointLayout::Sh16
        );
        assert_eq!(
            "coco-17".parse::<KeypointLayout>().unwrap(),
            KeypointLayout::Coco17
        );
        assert!(matches!(
            "openpose25".parse::<KeypointLayout>(),
            Err(LayoutError::Unknown(_))
        ));
        assert_eq!(KeypointLayout::Sh16.num_joints(), 16);
        assert_eq!(KeypointLayout::Coco17.num_joints(), 17);
    }

    #[test]
    fn coordinates_normalize_pixels_only() {
        let p = [250.0, 480.0];
        let pixels = InputFormat::pixels(KeypointLayout::Sh16, 1000, 1002);
        assert_eq!(pixels.layout, KeypointLayout::Sh16);
        assert_eq!(
            pixels.coordinates.normalize(p),
            normalize_screen(p, 1000, 1002)
        );
        assert_eq!(Coordinates::Normalized.normalize(p), p);
    }

    #[test]
    fn every_h36m_joint_is_copied_or_synthesized() {
        // give each source joint a distinct value and check the targets
        let sh: Vec<[f32; 2]> = (0..16).map(|i| [i as f32, 100.0 + i as f32]).collect();
        let out = KeypointLayout::Sh16.to_h36m17(&sh).unwrap();
        assert_eq!(out[h("r_ankle")], [0.0, 100.0]);
        assert_eq!(out[h("pelvis")], [6.0, 106.0]);
        let hd = out[h("head")];
        assert!((hd[0] - (8.0 + SH16_HEAD_FRACTION)).abs() < 1e-5, "{hd:?}");
        let sp = out[h("spine")];
        assert!(
            (sp[0] - (6.0 + 2.0 * SH16_SPINE_FRACTION)).abs() < 1e-5,
            "{sp:?}"
        );
        assert_eq!(out[h("r_wrist")], [10.0, 110.0]);
        assert_eq!(out[h("l_shoulder")], [13.0, 113.0]);
        let nn = out[h("neck_nose")];
        assert!((nn[0] - (8.0 + SH16_NECK_FRACTION)).abs() < 1e-5, "{nn:?}");

        let coco: Vec<[f32; 2]> = (0..17).map(|i| [i as f32, -(i as f32)]).collect();
        let out = KeypointLayout::Coco17.to_h36m17(&coco).unwrap();
        assert_eq!(out[h("pelvis")], [11.5, -11.5]);
        let th = out[h("thorax")];
        assert!(
            (th[0] - 5.5 * (1.0 - COCO_THORAX_FRACTION)).abs() < 1e-5,
            "{th:?}"
        );
        assert_eq!(out[h("neck_nose")], [0.0, 0.0]);
        assert_eq!(out[h("l_wrist")], [9.0, -9.0]);
        assert_eq!(out[h("r_ankle")], [16.0, -16.0]);
        let sp = out[h("spine")];
        assert!((sp[0] - (11.5 + (th[0] - 11.5) * COCO_SPINE_FRACTION)).abs() < 1e-5);
        let hd = out[h("head")];
        assert!(
            (hd[0] - th[0] * (1.0 - COCO_HEAD_FACTOR)).abs() < 1e-4,
            "{hd:?}"
        );

        let native: Vec<[f32; 2]> = (0..17).map(|i| [i as f32, 1.0]).collect();
        assert_eq!(
            KeypointLayout::H36m17.to_h36m17(&native).unwrap()[16],
            [16.0, 1.0]
        );
    }

    #[test]
    fn bad_input_is_a_typed_error() {
        let e = KeypointLayout::Sh16.to_h36m17(&[[0.0; 2]; 17]).unwrap_err();
        assert_eq!(
            e,
            LayoutError::WrongJointCount {
                layout: KeypointLayout::Sh16,
                expected: 16,
                got: 17
            }
        );
        let mut pts = [[0.0f32; 2]; 17];
        pts[5][1] = f32::NAN;
        let e = KeypointLayout::Coco17.to_h36m17(&pts).unwrap_err();
        assert_eq!(
            e,
            LayoutError::NonFinite {
                layout: KeypointLayout::Coco17,
                joint: 5,
                name: "l_shoulder"
            }
        );
        assert!(e.to_string().contains("l_shoulder"));
        assert!(matches!(
            KeypointLayout::Sh16.sequence_to_h36m17(&[0.0; 33]),
            Err(LayoutError::RaggedBuffer { per_frame: 32, .. })
        ));
        assert_eq!(
            KeypointLayout::Sh16
                .sequence_to_h36m17(&[1.0; 64])
                .unwrap()
                .len(),
            2
        );
    }
}
