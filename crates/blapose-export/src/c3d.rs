//! C3D, the biomechanics interchange format (Vicon, Qualisys, Visual3D,
//! OpenSim through ezc3d, MATLAB toolkits).
//!
//! Written here from the C3D.ORG user guide rather than with a crate: the
//! Rust C3D crates are young and rarely released, and what blapose needs is
//! the small, stable core of the format: 3D points, no analog channels. The
//! file is 512-byte blocks, Intel (little-endian) byte order, processor type
//! 84, float data:
//!
//! - block 1, the header: parameter section at block 2, key `0x50`, point
//!   count, first and last frame, scale `-1.0` (negative: float data), data
//!   start block, frame rate;
//! - the parameter section (blocks 2..): group `POINT` with `USED`, `SCALE`,
//!   `RATE`, `DATA_START`, `FRAMES`, `LABELS` (the 17 joint names),
//!   `DESCRIPTIONS`, `UNITS` (`mm`), `X_SCREEN`/`Y_SCREEN` (`+X`, `+Z`: Z is
//!   up); `ANALOG` with `USED` 0 and `RATE` 0; `TRIAL` with the first and last
//!   frame as 32-bit values (`ACTUAL_START_FIELD`, `ACTUAL_END_FIELD`);
//!   `MANUFACTURER`;
//! - the data: per frame, per joint, `x y z` in millimetres (Z-up frame,
//!   [`crate::axes`]) and a fourth float, 0 (residual 0, no camera mask: a
//!   valid point), all `f32`.
//!
//! The tests read it back with an independent reader (Python's `ezc3d` and
//! `c3d`, `tests/export/`); the unit tests here parse the layout by hand.

use std::io::Write;

use blapose_core::skeleton::JOINT_NAMES;

use crate::error::ExportError;
use crate::motion::Motion;

const BLOCK: usize = 512;
/// Processor type: Intel (little-endian IEEE floats).
const INTEL: u8 = 84;
/// The most frames a C3D can count in its header and `POINT:FRAMES`
/// (unsigned 16-bit).
pub const MAX_FRAMES: usize = 65_535;

/// A parameter's value.
enum Value {
    I16(Vec<i16>, Vec<u8>),
    F32(Vec<f32>, Vec<u8>),
    /// Strings padded to one length: dimensions `[len, count]`.
    Chars(Vec<String>),
}

struct Param {
    name: &'static str,
    desc: &'static str,
    value: Value,
}

struct Group {
    name: &'static str,
    desc: &'static str,
    params: Vec<Param>,
}

fn scalar_i16(name: &'static str, desc: &'static str, v: i16) -> Param {
    Param {
        name,
        desc,
        value: Value::I16(vec![v], vec![]),
    }
}

fn scalar_f32(name: &'static str, desc: &'static str, v: f32) -> Param {
    Param {
        name,
        desc,
        value: Value::F32(vec![v], vec![]),
    }
}

fn chars(name: &'static str, desc: &'static str, v: &[&str]) -> Param {
    Param {
        name,
        desc,
        value: Value::Chars(v.iter().map(|s| s.to_string()).collect()),
    }
}

/// One parameter record (without the 2-byte "next" offset's value, filled by the caller).
fn param_bytes(group_id: i8, p: &Param) -> Vec<u8> {
    let mut b = vec![p.name.len() as u8, group_id as u8];
    b.extend_from_slice(p.name.as_bytes());
    b.extend_from_slice(&[0, 0]); // offset to the next record, set later
    match &p.value {
        Value::I16(v, dims) => {
            b.extend_from_slice(&[2, dims.len() as u8]);
            b.extend_from_slice(dims);
            v.iter().for_each(|x| b.extend_from_slice(&x.to_le_bytes()));
        }
        Value::F32(v, dims) => {
            b.extend_from_slice(&[4, dims.len() as u8]);
            b.extend_from_slice(dims);
            v.iter().for_each(|x| b.extend_from_slice(&x.to_le_bytes()));
        }
        Value::Chars(strings) => {
            let len = strings.iter().map(String::len).max().unwrap_or(0).max(1);
            if strings.len() == 1 {
                b.extend_from_slice(&[0xff, 1, len as u8]);
            } else {
                b.extend_from_slice(&[0xff, 2, len as u8, strings.len() as u8]);
            }
            for s in strings {
                b.extend_from_slice(format!("{s:<len$}").as_bytes());
            }
        }
    }
    b.push(p.desc.len() as u8);
    b.extend_from_slice(p.desc.as_bytes());
    b
}

fn group_bytes(id: i8, g: &Group) -> Vec<u8> {
    let mut b = vec![g.name.len() as u8, (-id) as u8];
    b.extend_from_slice(g.name.as_bytes());
    b.extend_from_slice(&[0, 0]);
    b.push(g.desc.len() as u8);
    b.extend_from_slice(g.desc.as_bytes());
    b
}

/// The parameter section (padded to whole blocks) for `frames` frames
/// whose data starts at block `data_start`.
fn parameters(motion: &Motion, data_start: u16) -> Vec<u8> {
    let frames = motion.len();
    let fps = motion.fps() as f32;
    let groups = [
        Group {
            name: "POINT",
            desc: "3D joint centres",
            params: vec![
                scalar_i16("USED", "number of points", JOINT_NAMES.len() as i16),
                scalar_f32("SCALE", "negative: float data", -1.0),
                scalar_f32("RATE", "frames per second", fps),
                scalar_i16("DATA_START", "first block of the data", data_start as i16),
                // Unsigned 16-bit in a signed field (readers take it as unsigned).
                scalar_i16("FRAMES", "number of frames", frames as u16 as i16),
                chars("LABELS", "joint names", &JOINT_NAMES),
                chars(
                    "DESCRIPTIONS",
                    "Human3.6M joint centres",
                    &JOINT_NAMES.map(|_| "blapose joint centre"),
                ),
                chars("UNITS", "length unit", &["mm"]),
                chars("X_SCREEN", "screen right", &["+X"]),
                chars("Y_SCREEN", "screen up: Z is up", &["+Z"]),
            ],
        },
        Group {
            name: "ANALOG",
            desc: "no analog channels",
            // RATE / POINT:RATE must equal the header's analog samples per frame (0).
            params: vec![
                scalar_i16("USED", "number of channels", 0),
                scalar_f32("RATE", "samples per second", 0.0),
            ],
        },
        Group {
            name: "TRIAL",
            desc: "frame range",
            params: vec![
                Param {
                    name: "ACTUAL_START_FIELD",
                    desc: "first frame, 32-bit",
                    value: Value::I16(vec![1, 0], vec![2]),
                },
                Param {
                    name: "ACTUAL_END_FIELD",
                    desc: "last frame, 32-bit",
                    value: Value::I16(
                        vec![(frames & 0xffff) as u16 as i16, (frames >> 16) as i16],
                        vec![2],
                    ),
                },
            ],
        },
        Group {
            name: "MANUFACTURER",
            desc: "who wrote the file",
            params: vec![
                chars("COMPANY", "", &["blapose"]),
                chars("SOFTWARE", "", &["blapose-export"]),
                chars("VERSION_LABEL", "", &[env!("CARGO_PKG_VERSION")]),
            ],
        },
    ];
    let mut records: Vec<Vec<u8>> = Vec::new();
    for (g, group) in groups.iter().enumerate() {
        let id = g as i8 + 1;
        records.push(group_bytes(id, group));
        records.extend(group.params.iter().map(|p| param_bytes(id, p)));
    }
    let count = records.len();
    let mut body = Vec::new();
    for (i, mut rec) in records.into_iter().enumerate() {
        // "Next" counts from the offset field (after the name) to the next
        // record; 0 on the last one ends the section.
        let at = 2 + rec[0] as usize;
        let next = if i + 1 == count {
            0
        } else {
            (rec.len() - at) as i16
        };
        rec[at..at + 2].copy_from_slice(&next.to_le_bytes());
        body.extend_from_slice(&rec);
    }
    let blocks = (4 + body.len()).div_ceil(BLOCK);
    let mut section = vec![1u8, 0x50, blocks as u8, INTEL];
    section.extend_from_slice(&body);
    section.resize(blocks * BLOCK, 0);
    section
}

/// Write `motion` as C3D to `out`: 17 points named as the joints,
/// millimetres, Z up.
pub fn write_c3d<W: Write>(motion: &Motion, out: W) -> Result<(), ExportError> {
    let frames = motion.len();
    if frames > MAX_FRAMES {
        return Err(ExportError::TooManyFrames {
            format: "C3D",
            max: MAX_FRAMES,
            frames,
        });
    }
    // The parameter section's size does not depend on DATA_START's value.
    let param_blocks = parameters(motion, 0).len() / BLOCK;
    let data_start = (2 + param_blocks) as u16;
    let params = parameters(motion, data_start);

    let mut header = vec![0u8; BLOCK];
    let mut put16 =
        |word: usize, v: u16| header[2 * (word - 1)..2 * word].copy_from_slice(&v.to_le_bytes());
    put16(1, u16::from_le_bytes([2, 0x50]));
    put16(2, JOINT_NAMES.len() as u16);
    put16(3, 0); // analog samples per 3D frame, all channels
    put16(4, 1); // first frame
    put16(5, frames as u16); // last frame
    put16(6, 0); // maximum interpolation gap
    put16(9, data_start);
    put16(10, 0); // analog samples per frame
    header[12..16].copy_from_slice(&(-1.0f32).to_le_bytes()); // words 7-8: scale
    header[20..24].copy_from_slice(&(motion.fps() as f32).to_le_bytes()); // words 11-12: rate

    let mut out = std::io::BufWriter::with_capacity(1 << 16, out);
    out.write_all(&header)?;
    out.write_all(&params)?;
    let mut buf = Vec::with_capacity(17 * 16);
    for t in 0..frames {
        buf.clear();
        for p in motion.z_up_mm(t) {
            for v in p {
                buf.extend_from_slice(&(v as f32).to_le_bytes());
            }
            buf.extend_from_slice(&0.0f32.to_le_bytes());
        }
        out.write_all(&buf)?;
    }
    let written = frames * 17 * 16;
    let pad = written.div_ceil(BLOCK) * BLOCK - written;
    out.write_all(&vec![0u8; pad])?;
    out.flush()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_core::Pose;

    fn motion(frames: usize) -> Motion {
        let pose: Pose =
            std::array::from_fn(|j| [0.05 * j as f32, -0.1 * j as f32, 0.02 * (j % 3) as f32]);
        let lengths = blapose_core::bones::bone_lengths(&pose);
        Motion::new(&vec![pose; frames], &lengths, 60.0).unwrap()
    }

    fn u16_at(b: &[u8], word: usize) -> u16 {
        u16::from_le_bytes([b[2 * (word - 1)], b[2 * word - 1]])
    }

    /// `(group, name, type, dimensions, raw data)`.
    type Record = (String, String, i8, Vec<u8>, Vec<u8>);

    /// A minimal reader of the parameter records this writer writes.
    fn read_params(file: &[u8]) -> Vec<Record> {
        let start = (file[0] as usize - 1) * BLOCK;
        assert_eq!(file[start + 3], INTEL);
        let mut groups = std::collections::HashMap::new();
        let mut out = Vec::new();
        let mut at = start + 4;
        loop {
            let n = file[at] as usize;
            let id = file[at + 1] as i8;
            let name = String::from_utf8(file[at + 2..at + 2 + n].to_vec()).unwrap();
            let off_at = at + 2 + n;
            let next = i16::from_le_bytes([file[off_at], file[off_at + 1]]);
            if id < 0 {
                groups.insert(-id, name);
            } else {
                let ty = file[off_at + 2] as i8;
                let nd = file[off_at + 3] as usize;
                let dims = file[off_at + 4..off_at + 4 + nd].to_vec();
                let count: usize = dims.iter().map(|&d| d as usize).product::<usize>().max(1);
                let size = count * ty.unsigned_abs() as usize;
                let data = file[off_at + 4 + nd..off_at + 4 + nd + size].to_vec();
                out.push((groups[&id].clone(), name, ty, dims, data));
            }
            if next == 0 {
                break;
            }
            at = off_at + next as usize;
        }
        out
    }

    #[test]
    fn header_parameters_and_data_agree() {
        let m = motion(3);
        let mut file = Vec::new();
        write_c3d(&m, &mut file).unwrap();
        assert_eq!(file.len() % BLOCK, 0);
        assert_eq!((file[0], file[1]), (2, 0x50));
        assert_eq!(
            (u16_at(&file, 2), u16_at(&file, 4), u16_at(&file, 5)),
            (17, 1, 3)
        );
        assert_eq!(f32::from_le_bytes(file[12..16].try_into().unwrap()), -1.0);
        assert_eq!(f32::from_le_bytes(file[20..24].try_into().unwrap()), 60.0);
        let params = read_params(&file);
        let get = |g: &str, n: &str| {
            params
                .iter()
                .find(|p| p.0 == g && p.1 == n)
                .unwrap()
                .clone()
        };
        let used = get("POINT", "USED");
        assert_eq!(i16::from_le_bytes([used.4[0], used.4[1]]), 17);
        let labels = get("POINT", "LABELS");
        assert_eq!((labels.2, labels.3.clone()), (-1, vec![10, 17]));
        let text = String::from_utf8(labels.4).unwrap();
        assert_eq!(text[10..20].trim(), "r_hip");
        assert_eq!(get("POINT", "UNITS").4, b"mm");
        let start = u16_at(&file, 9);
        let ds = get("POINT", "DATA_START").4;
        assert_eq!(i16::from_le_bytes([ds[0], ds[1]]) as u16, start);
        // Frame 2, joint 5: millimetres in the Z-up frame.
        let at = (start as usize - 1) * BLOCK + (2 * 17 + 5) * 16;
        let got: Vec<f32> = (0..4)
            .map(|k| f32::from_le_bytes(file[at + 4 * k..at + 4 * k + 4].try_into().unwrap()))
            .collect();
        let want = m.z_up_mm(2)[5];
        for k in 0..3 {
            assert!((got[k] as f64 - want[k]).abs() < 1e-3);
        }
        assert_eq!(got[3], 0.0);
    }

    #[test]
    fn frame_counts_past_16_bits_signed_and_unsigned() {
        let m = motion(40_000);
        let mut file = Vec::new();
        write_c3d(&m, &mut file).unwrap();
        assert_eq!(u16_at(&file, 5), 40_000);
        let end = read_params(&file)
            .into_iter()
            .find(|p| p.1 == "ACTUAL_END_FIELD")
            .unwrap()
            .4;
        assert_eq!(u16::from_le_bytes([end[0], end[1]]), 40_000);
        let e = write_c3d(&motion(MAX_FRAMES + 1), Vec::new()).unwrap_err();
        assert!(
            e.to_string().contains("C3D holds at most 65535 frames"),
            "{e}"
        );
    }
}
