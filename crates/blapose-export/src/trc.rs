//! TRC, OpenSim's marker file: the input of its scaling and inverse
//! kinematics tools, and a plain tab-separated text any script can read.
//!
//! Layout (tab-separated, OpenSim's `TRCFileAdapter` reads it):
//!
//! ```text
//! PathFileType  4  (X/Y/Z)  NAME
//! DataRate  CameraRate  NumFrames  NumMarkers  Units  OrigDataRate  OrigDataStartFrame  OrigNumFrames
//! 50.000000  50.000000  124  17  mm  50.000000  1  124
//! Frame#  Time  pelvis  <tab><tab>r_hip ...
//!               X1  Y1  Z1  X2  Y2  Z2 ...
//! <blank line>
//! 1  0.000000  x y z (17 markers) ...
//! ```
//!
//! One marker per joint, named as the joints, millimetres (four decimals),
//! Z-up frame ([`crate::axes`]). OpenSim's own models are Y up: rotate the
//! markers -90 degrees about X in the IK setup (or export Y up by hand from
//! the Y-up BVH frame) when a model expects that.

use std::io::Write;

use blapose_core::skeleton::JOINT_NAMES;

use crate::error::ExportError;
use crate::motion::Motion;
use crate::text::push_fixed;

/// Write `motion` as a TRC to `out`; `name` is the file name recorded in
/// the first line.
pub fn write_trc<W: Write>(motion: &Motion, out: W, name: &str) -> Result<(), ExportError> {
    let mut out = std::io::BufWriter::with_capacity(1 << 16, out);
    let (fps, frames, markers) = (motion.fps(), motion.len(), JOINT_NAMES.len());
    writeln!(out, "PathFileType\t4\t(X/Y/Z)\t{name}")?;
    writeln!(out, "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames")?;
    writeln!(
        out,
        "{fps:.6}\t{fps:.6}\t{frames}\t{markers}\tmm\t{fps:.6}\t1\t{frames}"
    )?;
    // Each marker spans three columns: its name, then two empty cells.
    writeln!(out, "Frame#\tTime\t{}", JOINT_NAMES.join("\t\t\t"))?;
    let axes: Vec<String> = (1..=markers).map(|k| format!("X{k}\tY{k}\tZ{k}")).collect();
    writeln!(out, "\t\t{}", axes.join("\t"))?;
    writeln!(out)?;
    let mut line = String::with_capacity(1024);
    for t in 0..frames {
        use std::fmt::Write as _;
        line.clear();
        write!(line, "{}\t{:.6}", t + 1, t as f64 / fps).expect("string");
        for v in motion.z_up_mm(t).iter().flatten() {
            line.push('\t');
            push_fixed(&mut line, *v, 4);
        }
        line.push('\n');
        out.write_all(line.as_bytes())?;
    }
    out.flush()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::Pose;

    #[test]
    fn header_and_rows() {
        let pose: Pose =
            std::array::from_fn(|j| [0.05 * j as f32, -0.1 * j as f32, 0.02 * (j % 3) as f32]);
        let lengths = blapose_core::bones::bone_lengths(&pose);
        let m = Motion::new(&[pose, pose], &lengths, 50.0).unwrap();
        let mut out = Vec::new();
        write_trc(&m, &mut out, "walk.trc").unwrap();
        let text = String::from_utf8(out).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "PathFileType\t4\t(X/Y/Z)\twalk.trc");
        assert_eq!(lines[2], "50.000000\t50.000000\t2\t17\tmm\t50.000000\t1\t2");
        let names: Vec<&str> = lines[3].split('\t').filter(|s| !s.is_empty()).collect();
        assert_eq!(names.len(), 19);
        assert_eq!(names[2], "pelvis");
        assert_eq!(lines[3].split('\t').count(), 2 + 3 * 17 - 2);
        assert_eq!(lines[4].split('\t').count(), 2 + 3 * 17);
        assert_eq!(lines[5], "");
        let row: Vec<f64> = lines[7].split('\t').map(|v| v.parse().unwrap()).collect();
        assert_eq!(row.len(), 2 + 51);
        assert_eq!((row[0], row[1]), (2.0, 0.02));
        let want = m.z_up_mm(1);
        for j in 0..17 {
            for k in 0..3 {
                assert!((row[2 + 3 * j + k] - want[j][k]).abs() < 1e-4);
            }
        }
    }
}
