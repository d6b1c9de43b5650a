//! Zip bombs against the replay reader, with its peak allocation counted.
//!
//! A replay file comes from anywhere, and an npz member declares its own
//! size: 2 GiB of zeros deflate to about 2 MB. Loading must cost about the
//! memory of the arrays returned, whether the bomb is a member the format
//! does not use, a used member whose directory entry says 2 GiB, one whose
//! directory entry lies (says the right size, inflates to 2 GiB), or a
//! header declaring a huge shape. A counting global allocator measures the
//! peak bytes allocated while `Sequence::load` runs (a zip directory of
//! too many entries is refused before it is parsed); one test function runs
//! the cases in turn, in a test binary of its own, so nothing else
//! allocates meanwhile. The bomb is deflated once, streamed from a zero
//! buffer (never 2 GiB in memory), and copied raw into each archive.

use std::alloc::{GlobalAlloc, Layout, System};
use std::io::{Cursor, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use blapose_data::npz::{npy_bytes, Array, NpzError};
use blapose_data::replay::{Sequence, SequenceError, KEY_IMAGE_SIZE, KEY_KEYPOINTS, KEY_POSE_3D};
use zip::write::SimpleFileOptions;

struct Counting;

static CURRENT: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

fn grew(by: usize) {
    let now = CURRENT.fetch_add(by, Ordering::Relaxed) + by;
    PEAK.fetch_max(now, Ordering::Relaxed);
}

// SAFETY: forwards to the system allocator; only counts sizes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        grew(layout.size());
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        CURRENT.fetch_sub(layout.size(), Ordering::Relaxed);
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        grew(layout.size());
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // Counted as a fresh block beside the old one, the worst case.
        grew(new_size);
        CURRENT.fetch_sub(layout.size(), Ordering::Relaxed);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// The peak bytes allocated (above what was live before) while `f` runs.
fn peak_of<T>(f: impl FnOnce() -> T) -> (T, usize) {
    let base = CURRENT.load(Ordering::Relaxed);
    PEAK.store(base, Ordering::Relaxed);
    let out = f();
    (out, PEAK.load(Ordering::Relaxed) - base)
}

const FRAMES: usize = 2_000;
const BOMB_BYTES: u64 = 1 << 31;

fn deflated() -> SimpleFileOptions {
    SimpleFileOptions::default().compression_method(zip::CompressionMethod::Deflated)
}

fn npy_header(shape: &str) -> Vec<u8> {
    let header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}\n");
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out
}

/// A one-member archive: a `(FRAMES, 17, 3)` header and then 2 GiB of
/// zeros, streamed through the deflater.
fn bomb_archive() -> Vec<u8> {
    let mut zip = zip::ZipWriter::new(Cursor::new(Vec::new()));
    zip.start_file("bomb.npy", deflated()).unwrap();
    zip.write_all(&npy_header(&format!("({FRAMES}, 17, 3)")))
        .unwrap();
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..BOMB_BYTES >> 20 {
        zip.write_all(&zeros).unwrap();
    }
    zip.finish().unwrap().into_inner()
}

/// A valid replay file's members, with `replace` standing in for
/// `pose_3d` when given, and the bomb copied in under each name of `bombs`.
fn replay_file(bomb: &[u8], replace: Option<&[u8]>, bombs: &[&str]) -> Vec<u8> {
    let mut zip = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let kp = Array::new(vec![FRAMES, 17, 2], vec![100.0; FRAMES * 34]).unwrap();
    let pose = Array::new(vec![FRAMES, 17, 3], vec![0.1; FRAMES * 51]).unwrap();
    let size = Array::new(vec![2], vec![1000.0, 1000.0]).unwrap();
    for (key, array) in [
        (KEY_KEYPOINTS, kp),
        (KEY_POSE_3D, pose),
        (KEY_IMAGE_SIZE, size),
    ] {
        if bombs.contains(&key) {
            continue;
        }
        if key == KEY_POSE_3D {
            if let Some(raw) = replace {
                zip.start_file(format!("{key}.npy"), deflated()).unwrap();
                zip.write_all(raw).unwrap();
                continue;
            }
        }
        zip.start_file(format!("{key}.npy"), deflated()).unwrap();
        zip.write_all(&npy_bytes(&array)).unwrap();
    }
    let mut source = zip::ZipArchive::new(Cursor::new(bomb)).unwrap();
    for name in bombs {
        zip.raw_copy_file_rename(source.by_index(0).unwrap(), format!("{name}.npy"))
            .unwrap();
    }
    zip.finish().unwrap().into_inner()
}

/// Set the uncompressed size of member `name` in its local header and its
/// central directory entry (the directory then lies about the bomb).
fn declare_size(archive: &mut [u8], name: &str, size: u32) {
    let mut patched = 0;
    for at in 0..archive.len().saturating_sub(46) {
        let (size_at, name_len_at, name_at) = match &archive[at..at + 4] {
            b"PK\x03\x04" => (22, 26, 30),
            b"PK\x01\x02" => (24, 28, 46),
            _ => continue,
        };
        let name_len =
            u16::from_le_bytes([archive[at + name_len_at], archive[at + name_len_at + 1]]) as usize;
        if archive.get(at + name_at..at + name_at + name_len) == Some(name.as_bytes()) {
            archive[at + size_at..at + size_at + 4].copy_from_slice(&size.to_le_bytes());
            patched += 1;
        }
    }
    assert_eq!(patched, 2, "local header and directory entry of {name}");
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, bytes).unwrap();
    path
}

#[test]
fn zip_bombs_cost_no_more_than_the_arrays_returned() {
    let dir = std::env::temp_dir().join(format!("blapose-bomb-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let bomb = bomb_archive();
    assert!(
        bomb.len() < 4 << 20,
        "2 GiB deflate to {} bytes",
        bomb.len()
    );

    // The valid file: its arrays are what a load returns.
    let valid = write(&dir, "valid.npz", &replay_file(&bomb, None, &[]));
    let (seq, clean_peak) = peak_of(|| Sequence::load(&valid, None).unwrap());
    let returned = FRAMES * (34 + 51) * 4;
    assert_eq!(seq.len(), FRAMES);
    drop(seq);
    eprintln!("valid file: returns {returned} bytes, peak {clean_peak}");
    assert!(clean_peak < 2 * returned + (1 << 20), "{clean_peak}");

    // Unused members: never opened, however many.
    for count in [1, 6] {
        let names: Vec<String> = (0..count).map(|i| format!("junk{i}")).collect();
        let names: Vec<&str> = names.iter().map(String::as_str).collect();
        let file = write(&dir, "unused.npz", &replay_file(&bomb, None, &names));
        let (seq, peak) = peak_of(|| Sequence::load(&file, None).unwrap());
        assert_eq!(seq.len(), FRAMES);
        drop(seq);
        eprintln!("{count} unused 2 GiB member(s): peak {peak}");
        assert!(peak < 2 * returned + (1 << 20), "{peak}");
    }

    // A used member the directory declares at 2 GiB: refused uninflated.
    let mut archive = replay_file(&bomb, None, &[KEY_POSE_3D]);
    let declared = write(&dir, "declared.npz", &archive);
    let (result, peak) = peak_of(|| Sequence::load(&declared, None));
    let e = result.unwrap_err();
    eprintln!("used member declared 2 GiB: {e}; peak {peak}");
    assert!(
        matches!(&e, SequenceError::Npz { error: NpzError::TooLarge { key, .. }, .. } if key == KEY_POSE_3D),
        "{e}"
    );
    assert!(peak < returned, "{peak}");

    // The same member with the directory saying the right size: inflated
    // only to the bytes its shape needs plus one.
    let npy_len = npy_header(&format!("({FRAMES}, 17, 3)")).len() + FRAMES * 51 * 4;
    declare_size(&mut archive, "pose_3d.npy", npy_len as u32);
    let lying = write(&dir, "lying.npz", &archive);
    let (result, peak) = peak_of(|| Sequence::load(&lying, None));
    let e = result.unwrap_err();
    eprintln!("used member declared {npy_len} bytes, inflating to 2 GiB: {e}; peak {peak}");
    assert!(
        matches!(&e, SequenceError::Npz { error: NpzError::BadNpy { key, reason }, .. } if key == KEY_POSE_3D && reason.contains("found more")),
        "{e}"
    );
    assert!(peak < 2 * returned + (1 << 20), "{peak}");

    // Headers declaring huge shapes: refused before any value is read.
    for shape in ["(1099511627776, 17, 3)", "(900001, 17, 3)"] {
        let file = write(
            &dir,
            "shape.npz",
            &replay_file(&bomb, Some(&npy_header(shape)), &[]),
        );
        let (result, peak) = peak_of(|| Sequence::load(&file, None));
        let e = result.unwrap_err();
        eprintln!("pose_3d header {shape}: {e}; peak {peak}");
        assert!(
            matches!(
                e,
                SequenceError::TooManyFrames {
                    key: KEY_POSE_3D,
                    max: 900_000,
                    ..
                }
            ),
            "{e}"
        );
        assert!(peak < 1 << 20, "{peak}");
    }
    // A directory bomb: a valid replay file with 60,000 empty members more
    // (the report's had 8 M): refused before the directory is parsed.
    let mut zip = zip::ZipWriter::new_append(Cursor::new(replay_file(&bomb, None, &[]))).unwrap();
    let stored = SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for i in 0..60_000 {
        zip.start_file(format!("j{i}.npy"), stored).unwrap();
    }
    let entries = write(&dir, "directory.npz", &zip.finish().unwrap().into_inner());
    let (result, peak) = peak_of(|| Sequence::load(&entries, None));
    let e = result.unwrap_err();
    eprintln!("60,003 directory entries: {e}; peak {peak}");
    assert!(
        matches!(
            &e,
            SequenceError::Npz {
                error: NpzError::Directory { .. },
                ..
            }
        ),
        "{e}"
    );
    assert!(e.to_string().contains("entries"), "{e}");
    assert!(peak < 1 << 20, "{peak}");
    // The bound is the caller's.
    let e = Sequence::load_with_max_frames(&valid, None, FRAMES - 1).unwrap_err();
    assert!(e.to_string().contains("more than the limit of 1999"), "{e}");
    assert!(Sequence::load_with_max_frames(&valid, None, FRAMES).is_ok());
    std::fs::remove_dir_all(&dir).ok();
}
