//! Fuzzed npz/npy parsing: arbitrary bytes and mutated valid files (byte
//! flips, truncations, insertions; stored and deflated archives) through
//! [`parse_npy`], [`read_npz_bytes`] and the replay reader
//! ([`Sequence::read_from`]). Nothing may panic, every refusal is a typed
//! error, and what parses is consistent (values = product of the shape).
//!
//! A fixed-seed run of a few hundred cases runs in `cargo test`; a longer
//! one: `PROPTEST_CASES=100000 cargo test --release -p blapose-data --test
//! fuzz_npz` (README.md: Fuzzing and abuse).

use std::io::{Cursor, Write};

use blapose_data::npz::{npy_bytes, parse_npy, read_npz_bytes, Array, NpzArchive};
use blapose_data::replay::{Sequence, DEFAULT_MAX_FRAMES, KEY_CONFIDENCE, KEY_GT_3D};
use proptest::prelude::*;

use blapose_test_support::fuzz;

/// A valid replay file: 3 frames, 17 joints, confidence, ground truth and
/// a camera, stored or deflated.
fn valid_replay(deflate: bool) -> Vec<u8> {
    let mut zip = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let options = zip::write::SimpleFileOptions::default().compression_method(if deflate {
        zip::CompressionMethod::Deflated
    } else {
        zip::CompressionMethod::Stored
    });
    let t = 3;
    let arrays = [
        ("keypoints_2d", vec![t, 17, 2], 500.0),
        ("pose_3d", vec![t, 17, 3], 0.1),
        (KEY_GT_3D, vec![t, 17, 3], 0.2),
        (KEY_CONFIDENCE, vec![t, 17], 0.9),
        ("image_size", vec![2], 1000.0),
        ("layout", vec![1], 1.0),
        ("fps", vec![], 50.0),
        ("camera_up", vec![3], 0.5),
        ("camera_focal", vec![2], 1100.0),
        ("camera_principal", vec![2], 500.0),
        ("camera_height", vec![1], 1.5),
        ("camera_distortion", vec![4], 0.01),
    ];
    for (key, shape, v) in arrays {
        let n = shape.iter().product();
        zip.start_file(format!("{key}.npy"), options).unwrap();
        zip.write_all(&npy_bytes(&Array::new(shape, vec![v; n]).unwrap()))
            .unwrap();
    }
    zip.finish().unwrap().into_inner()
}

fn check_npy(raw: &[u8]) {
    if let Ok(a) = parse_npy("k", raw) {
        assert_eq!(a.data().len(), a.shape().iter().product::<usize>());
    }
}

fn check_npz(raw: &[u8]) {
    if let Ok(npz) = read_npz_bytes(raw, |_| true) {
        for (_, a) in npz.iter() {
            assert_eq!(a.data().len(), a.shape().iter().product::<usize>());
        }
    }
    if let Ok(mut archive) = NpzArchive::new(Cursor::new(raw), "fuzz.npz") {
        let keys: Vec<String> = archive.keys().map(str::to_owned).collect();
        for key in keys {
            if let Ok(shape) = archive.shape(&key) {
                if shape.iter().product::<usize>() <= 1 << 16 {
                    let _ = archive.read(&key, &shape);
                }
            }
        }
    }
    if let Ok(seq) = Sequence::read_from(Cursor::new(raw), "fuzz.npz", None, DEFAULT_MAX_FRAMES) {
        seq.validate().expect("a loaded sequence is valid");
        let _ = seq.frame(seq.len() - 1);
    }
}

proptest! {
    #![proptest_config(fuzz::config(384, 0x6e70_7a66_757a))]

    #[test]
    fn arbitrary_bytes_are_refused_without_panicking(raw in prop::collection::vec(any::<u8>(), 0..512)) {
        check_npy(&raw);
        check_npz(&raw);
        let mut with_magic = b"\x93NUMPY\x01\x00".to_vec();
        with_magic.extend_from_slice(&raw);
        check_npy(&with_magic);
        let mut with_zip = b"PK\x03\x04".to_vec();
        with_zip.extend_from_slice(&raw);
        check_npz(&with_zip);
    }

    #[test]
    fn mutated_npy_members_parse_or_are_refused(
        shape in prop::collection::vec(0usize..5, 0..4),
        mutations in prop::collection::vec(fuzz::mutation(), 1..6),
    ) {
        let n = shape.iter().product();
        let valid = npy_bytes(&Array::new(shape, vec![1.5; n]).unwrap());
        check_npy(&fuzz::mutate(valid, &mutations, 0));
    }

    #[test]
    fn mutated_replay_files_load_or_are_refused(
        deflate in any::<bool>(),
        mutations in prop::collection::vec(fuzz::mutation(), 1..6),
    ) {
        check_npz(&fuzz::mutate(valid_replay(deflate), &mutations, 0));
    }

    #[test]
    fn mutated_npy_headers_parse_or_are_refused(
        descr in prop::sample::select(vec!["<f4", ">f4", "<f8", ">f8", "|f4", "<i8", "", "'"]),
        shape in "\\((-?[0-9]{0,22}L?, ?){0,4}\\)|\\(|[^)]{0,8}",
        fortran in prop::sample::select(vec!["False", "True", "", "x"]),
        version in 0u8..5,
        body in prop::collection::vec(any::<u8>(), 0..64),
    ) {
        let header = format!("{{'descr': '{descr}', 'fortran_order': {fortran}, 'shape': {shape}, }}\n");
        let mut raw = b"\x93NUMPY".to_vec();
        raw.extend_from_slice(&[version, 0]);
        if version >= 2 {
            raw.extend_from_slice(&(header.len() as u32).to_le_bytes());
        } else {
            raw.extend_from_slice(&(header.len() as u16).to_le_bytes());
        }
        raw.extend_from_slice(header.as_bytes());
        raw.extend_from_slice(&body);
        check_npy(&raw);
    }
}

#[test]
fn the_unmutated_replay_files_load() {
    for deflate in [false, true] {
        let seq = Sequence::read_from(
            Cursor::new(valid_replay(deflate)),
            "valid.npz",
            None,
            DEFAULT_MAX_FRAMES,
        )
        .unwrap();
        assert_eq!(seq.len(), 3);
        assert!(seq.camera.is_some() && seq.gt_3d.is_some());
    }
}
