//! A float32 `.npz` reader and writer.
//!
//! NumPy's `.npz` is a zip archive of `.npy` files, one per named array.
//! The Human3.6M data and the client's replay files only hold
//! little-endian float arrays, so this module supports exactly that: arrays
//! of `f4` or `f8` (either byte order; `f8` is converted to `f32`), C order,
//! any rank. [`read_npz`] decodes every entry in parallel from an in-memory
//! copy of the archive, which is what makes loading the 90 MB of deflated
//! Human3.6M poses take well under a second on two cores.
//!
//! Files from elsewhere (replay files) are read with [`NpzArchive`]
//! instead: a zip member declares its own size and a 2 MB file can inflate
//! to gigabytes, so it opens only the members asked for, reads each one's
//! `.npy` header first, refuses a shape other than the caller's and a
//! declared size beyond what that shape needs before inflating anything,
//! and then reads at most the bytes the shape needs plus one (the zip
//! directory may lie). Both readers parse headers and values the same way
//! ([`read_npy_header`], [`parse_npy`]) and never allocate more than the
//! data actually inflated.
//!
//! Keys are entry names without the `.npy` suffix and may contain `/` and
//! spaces (`S9/Walking 1`), exactly as `numpy.savez` writes them.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use blapose_core::{Keypoints2d, Pose};

mod archive;
pub mod directory;

pub use archive::{
    parse_npy, read_npy_header, read_npz, read_npz_bytes, read_npz_filtered, Dtype, NpyHeader,
    NpzArchive, MAX_NPY_HEADER,
};

/// Why an npz file or array could not be read, written or used.
#[derive(Debug, thiserror::Error)]
pub enum NpzError {
    /// The file could not be opened, read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The file is not a readable zip archive.
    #[error("{path}: not a valid npz (zip) archive: {source}")]
    Zip {
        /// The file.
        path: PathBuf,
        /// The zip error.
        #[source]
        source: zip::result::ZipError,
    },
    /// An entry is not a valid `.npy` array.
    #[error("array {key:?}: invalid .npy data: {reason}")]
    BadNpy {
        /// The array's key.
        key: String,
        /// What is wrong.
        reason: String,
    },
    /// An entry holds a dtype other than float32/float64.
    #[error("array {key:?}: unsupported dtype {descr:?} (only float32 and float64)")]
    UnsupportedDtype {
        /// The array's key.
        key: String,
        /// NumPy's dtype descriptor.
        descr: String,
    },
    /// An entry is stored in Fortran order.
    #[error("array {key:?}: Fortran-order arrays are not supported")]
    FortranOrder {
        /// The array's key.
        key: String,
    },
    /// The archive's zip directory is larger than a replay file's can be
    /// (refused before it is parsed).
    #[error("{path}: {source}")]
    Directory {
        /// The file.
        path: PathBuf,
        /// What is too large.
        #[source]
        source: directory::DirectoryError,
    },
    /// A requested key is not in the archive.
    #[error("no array named {key:?} (available: {available})")]
    MissingKey {
        /// The requested key.
        key: String,
        /// Some of the keys that exist.
        available: String,
    },
    /// An array does not have the expected shape.
    #[error("array {key:?} has shape {actual:?}, expected {expected}")]
    Shape {
        /// The array's key.
        key: String,
        /// The expected shape (`_` = any size).
        expected: String,
        /// The actual shape.
        actual: Vec<usize>,
    },
    /// A member's declared (inflated) size is more than the shape the
    /// caller expects can take: refused before anything is inflated.
    #[error("array {key:?}: the archive declares {declared} bytes, more than the {limit} an array of shape {expected} can take")]
    TooLarge {
        /// The array's key.
        key: String,
        /// The size the zip directory declares.
        declared: u64,
        /// The most bytes a `.npy` of the expected shape takes.
        limit: u64,
        /// The expected shape.
        expected: String,
    },
    /// Data length and shape disagree.
    #[error("shape {shape:?} needs {needed} values, got {got}")]
    DataLength {
        /// The shape.
        shape: Vec<usize>,
        /// Product of the shape.
        needed: usize,
        /// Values given.
        got: usize,
    },
}

/// A named n-dimensional float32 array (C order).
#[derive(Debug, Clone, PartialEq)]
pub struct Array {
    shape: Vec<usize>,
    data: Vec<f32>,
}

fn product(shape: &[usize]) -> Option<usize> {
    shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d))
}

impl Array {
    /// An array of the given shape; `data.len()` must equal the product of
    /// `shape`.
    pub fn new(shape: Vec<usize>, data: Vec<f32>) -> Result<Self, NpzError> {
        match product(&shape) {
            Some(n) if n == data.len() => Ok(Self { shape, data }),
            n => Err(NpzError::DataLength {
                shape,
                needed: n.unwrap_or(usize::MAX),
                got: data.len(),
            }),
        }
    }

    /// A `(T, 17, 3)` array of poses.
    pub fn from_poses(poses: &[Pose]) -> Self {
        let data = blapose_core::pose::poses_as_flat(poses).to_vec();
        Self {
            shape: vec![poses.len(), blapose_core::NUM_JOINTS, 3],
            data,
        }
    }

    /// A `(T, J, D)` array of fixed-size frames (e.g. keypoints).
    pub fn from_frames<const J: usize, const D: usize>(frames: &[[[f32; D]; J]]) -> Self {
        Self {
            shape: vec![frames.len(), J, D],
            data: frames.as_flattened().as_flattened().to_vec(),
        }
    }

    /// A `(T, 17, 2)` array of Human3.6M keypoints.
    pub fn from_keypoints(frames: &[Keypoints2d]) -> Self {
        Self::from_frames(frames)
    }

    /// The shape.
    pub fn shape(&self) -> &[usize] {
        &self.shape
    }

    /// The values in C order.
    pub fn data(&self) -> &[f32] {
        &self.data
    }

    /// Split into shape and values.
    pub fn into_parts(self) -> (Vec<usize>, Vec<f32>) {
        (self.shape, self.data)
    }

    /// Whether the shape matches `expected` (`None` = any size).
    pub fn has_shape(&self, expected: &[Option<usize>]) -> bool {
        check_declared_shape("", &self.shape, expected).is_ok()
    }

    /// Copy a `(T, J, D)` array into frames, checking the shape.
    pub fn to_frames<const J: usize, const D: usize>(
        &self,
        key: &str,
    ) -> Result<Vec<[[f32; D]; J]>, NpzError> {
        check_shape(key, self, &[None, Some(J), Some(D)])?;
        Ok(self
            .data
            .chunks_exact(J * D)
            .map(|c| std::array::from_fn(|j| std::array::from_fn(|d| c[j * D + d])))
            .collect())
    }
}

fn shape_pattern(expected: &[Option<usize>]) -> String {
    let dims: Vec<String> = expected
        .iter()
        .map(|d| d.map_or("_".to_owned(), |d| d.to_string()))
        .collect();
    format!("({})", dims.join(", "))
}

fn check_shape(key: &str, a: &Array, expected: &[Option<usize>]) -> Result<(), NpzError> {
    check_declared_shape(key, &a.shape, expected)
}

/// Check a shape (e.g. a header's, before its data is read) against a
/// pattern (`None` = any size), naming the key and the pattern.
pub fn check_declared_shape(
    key: &str,
    shape: &[usize],
    expected: &[Option<usize>],
) -> Result<(), NpzError> {
    let fits = shape.len() == expected.len()
        && shape
            .iter()
            .zip(expected)
            .all(|(a, e)| e.is_none_or(|e| e == *a));
    if fits {
        Ok(())
    } else {
        Err(NpzError::Shape {
            key: key.to_owned(),
            expected: shape_pattern(expected),
            actual: shape.to_vec(),
        })
    }
}

/// The arrays of one npz file, by key (sorted).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Npz {
    arrays: BTreeMap<String, Array>,
}

impl Npz {
    /// An empty set of arrays (to fill and [`write_npz`]).
    pub fn new() -> Self {
        Self::default()
    }

    /// Add or replace an array.
    pub fn insert(&mut self, key: impl Into<String>, array: Array) {
        self.arrays.insert(key.into(), array);
    }

    /// Number of arrays.
    pub fn len(&self) -> usize {
        self.arrays.len()
    }

    /// Whether there are no arrays.
    pub fn is_empty(&self) -> bool {
        self.arrays.is_empty()
    }

    /// Whether `key` exists.
    pub fn contains(&self, key: &str) -> bool {
        self.arrays.contains_key(key)
    }

    /// Keys in sorted order.
    pub fn keys(&self) -> impl Iterator<Item = &str> {
        self.arrays.keys().map(String::as_str)
    }

    /// `(key, array)` pairs in key order.
    pub fn iter(&self) -> impl Iterator<Item = (&str, &Array)> {
        self.arrays.iter().map(|(k, v)| (k.as_str(), v))
    }

    fn missing(&self, key: &str) -> NpzError {
        let mut available: Vec<&str> = self.keys().take(8).collect();
        if self.len() > 8 {
            available.push("...");
        }
        NpzError::MissingKey {
            key: key.to_owned(),
            available: available.join(", "),
        }
    }

    /// The array named `key`.
    pub fn get(&self, key: &str) -> Result<&Array, NpzError> {
        self.arrays.get(key).ok_or_else(|| self.missing(key))
    }

    /// The array named `key`, checked against a shape pattern (`None` = any
    /// size), e.g. `&[None, Some(17), Some(3)]`.
    pub fn get_shaped(&self, key: &str, expected: &[Option<usize>]) -> Result<&Array, NpzError> {
        let a = self.get(key)?;
        check_shape(key, a, expected)?;
        Ok(a)
    }

    /// Remove and return the array named `key`.
    pub fn remove(&mut self, key: &str) -> Result<Array, NpzError> {
        match self.arrays.remove(key) {
            Some(a) => Ok(a),
            None => Err(self.missing(key)),
        }
    }

    /// A `(T, 17, 3)` array as poses.
    pub fn poses(&self, key: &str) -> Result<Vec<Pose>, NpzError> {
        self.get(key)?.to_frames(key)
    }

    /// A `(T, J, D)` array as fixed-size frames.
    pub fn frames<const J: usize, const D: usize>(
        &self,
        key: &str,
    ) -> Result<Vec<[[f32; D]; J]>, NpzError> {
        self.get(key)?.to_frames(key)
    }

    /// A single value (shape `()` or `(1,)`).
    pub fn scalar(&self, key: &str) -> Result<f32, NpzError> {
        let a = self.get(key)?;
        match (a.shape.len(), a.data.as_slice()) {
            (0, [v]) | (1, [v]) => Ok(*v),
            _ => Err(NpzError::Shape {
                key: key.to_owned(),
                expected: "() or (1,)".into(),
                actual: a.shape.clone(),
            }),
        }
    }
}

/// Serialize one array as `.npy` (format 1.0, little-endian float32).
pub fn npy_bytes(array: &Array) -> Vec<u8> {
    let dims: Vec<String> = array.shape.iter().map(|d| d.to_string()).collect();
    let shape = match dims.len() {
        1 => format!("({},)", dims[0]),
        _ => format!("({})", dims.join(", ")),
    };
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}");
    // Pad so that magic + length + header ends on a 64-byte boundary.
    let unpadded = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + 4 * array.data.len());
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    // Headers stay far below 64 KiB: rank * 21 digits at most.
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for v in &array.data {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// Write arrays to a deflate-compressed npz (`numpy.load` reads it).
pub fn write_npz(path: impl AsRef<Path>, npz: &Npz) -> Result<(), NpzError> {
    let path = path.as_ref();
    let io = |source| NpzError::Io {
        path: path.to_owned(),
        source,
    };
    let file = File::create(path).map_err(io)?;
    write_npz_to(BufWriter::new(file), npz, path)?
        .flush()
        .map_err(io)
}

/// [`write_npz`] into `out` (e.g. a `Cursor<Vec<u8>>` for bytes in
/// memory), `path` naming it in errors; `out` back once the archive is
/// finished.
pub fn write_npz_to<W: Write + std::io::Seek>(
    out: W,
    npz: &Npz,
    path: &Path,
) -> Result<W, NpzError> {
    let io = |source| NpzError::Io {
        path: path.to_owned(),
        source,
    };
    let zip_err = |source| NpzError::Zip {
        path: path.to_owned(),
        source,
    };
    let mut zip = zip::ZipWriter::new(out);
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated)
        .large_file(
            npz.arrays
                .values()
                .any(|a| a.data.len() * 4 > u32::MAX as usize / 2),
        );
    for (key, array) in &npz.arrays {
        zip.start_file(format!("{key}.npy"), options)
            .map_err(zip_err)?;
        zip.write_all(&npy_bytes(array)).map_err(io)?;
    }
    zip.finish().map_err(zip_err)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Cursor;

    fn temp(name: &str) -> PathBuf {
        std::env::temp_dir().join(format!("blapose-npz-{}-{name}", std::process::id()))
    }

    #[test]
    fn write_read_round_trip() {
        let mut npz = Npz::new();
        let poses: Vec<Pose> = (0..4)
            .map(|t| std::array::from_fn(|j| [t as f32, j as f32, -1.5]))
            .collect();
        npz.insert("S9/Walking 1", Array::from_poses(&poses));
        npz.insert("scalar", Array::new(vec![], vec![2.5]).unwrap());
        npz.insert("vec", Array::new(vec![3], vec![1.0, 2.0, 3.0]).unwrap());
        npz.insert("empty", Array::new(vec![0, 17, 2], vec![]).unwrap());
        let path = temp("rt.npz");
        write_npz(&path, &npz).unwrap();
        let back = read_npz(&path).unwrap();
        std::fs::remove_file(&path).ok();
        assert_eq!(back, npz);
        assert_eq!(back.poses("S9/Walking 1").unwrap(), poses);
        assert_eq!(back.scalar("scalar").unwrap(), 2.5);
        assert_eq!(back.frames::<17, 2>("empty").unwrap().len(), 0);
        assert_eq!(
            back.keys().collect::<Vec<_>>(),
            ["S9/Walking 1", "empty", "scalar", "vec"]
        );
    }

    #[test]
    fn reads_uncompressed_archives_like_numpy_savez() {
        // numpy.savez stores entries uncompressed; savez_compressed deflates
        // (the Human3.6M files). Both must read.
        let mut buf = Cursor::new(Vec::new());
        let mut zip = zip::ZipWriter::new(&mut buf);
        let stored = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Stored);
        zip.start_file("a.npy", stored).unwrap();
        zip.write_all(&npy_bytes(&Array::new(vec![2], vec![1.0, 2.0]).unwrap()))
            .unwrap();
        zip.start_file("skip/me.npy", stored).unwrap();
        zip.write_all(&npy_bytes(&Array::new(vec![1], vec![0.0]).unwrap()))
            .unwrap();
        zip.finish().unwrap();
        let npz = read_npz_bytes(buf.get_ref(), |k| !k.starts_with("skip/")).unwrap();
        assert_eq!(npz.keys().collect::<Vec<_>>(), ["a"]);
        assert_eq!(npz.get("a").unwrap().data(), [1.0, 2.0]);
    }

    #[test]
    fn header_is_numpy_compatible() {
        let a = Array::new(vec![2, 3], vec![0.0; 6]).unwrap();
        let b = npy_bytes(&a);
        let hl = u16::from_le_bytes([b[8], b[9]]) as usize;
        assert_eq!((10 + hl) % 64, 0);
        assert_eq!(b[10 + hl - 1], b'\n');
        assert!(std::str::from_utf8(&b[10..10 + hl])
            .unwrap()
            .starts_with("{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }"));
        assert_eq!(b.len(), 10 + hl + 24);
        let one = npy_bytes(&Array::new(vec![5], vec![0.0; 5]).unwrap());
        assert!(std::str::from_utf8(&one[10..70])
            .unwrap()
            .contains("'shape': (5,)"));
    }

    fn npy_with(descr: &str, shape: &str, fortran: &str, body: &[u8]) -> Vec<u8> {
        let header =
            format!("{{'descr': '{descr}', 'fortran_order': {fortran}, 'shape': {shape}, }}\n");
        let mut out = b"\x93NUMPY\x01\x00".to_vec();
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
        out.extend_from_slice(header.as_bytes());
        out.extend_from_slice(body);
        out
    }

    #[test]
    fn float64_and_big_endian_are_converted() {
        let body: Vec<u8> = [1.5f64, -2.25]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let a = parse_npy("x", &npy_with("<f8", "(2,)", "False", &body)).unwrap();
        assert_eq!(a.data(), [1.5, -2.25]);
        let body: Vec<u8> = [3.0f32].iter().flat_map(|v| v.to_be_bytes()).collect();
        let a = parse_npy("x", &npy_with(">f4", "(1, 1)", "False", &body)).unwrap();
        assert_eq!((a.shape(), a.data()), (&[1usize, 1][..], &[3.0f32][..]));
    }

    #[test]
    fn bad_npy_is_a_typed_error() {
        assert!(matches!(
            parse_npy("k", b"not numpy at all"),
            Err(NpzError::BadNpy { .. })
        ));
        let e = parse_npy("k", &npy_with("<i8", "(1,)", "False", &[0; 8])).unwrap_err();
        assert!(
            matches!(&e, NpzError::UnsupportedDtype { descr, .. } if descr == "<i8"),
            "{e}"
        );
        let e = parse_npy("k", &npy_with("<f4", "(2,)", "True", &[0; 8])).unwrap_err();
        assert!(matches!(e, NpzError::FortranOrder { .. }));
        let e = parse_npy("k", &npy_with("<f4", "(3,)", "False", &[0; 8])).unwrap_err();
        assert!(e.to_string().contains("needs 12 bytes"), "{e}");
        let e = parse_npy("k", &npy_with("<f4", "(a, 2)", "False", &[0; 8])).unwrap_err();
        assert!(matches!(e, NpzError::BadNpy { .. }), "{e}");
        let mut truncated = npy_with("<f4", "(1,)", "False", &[0; 4]);
        truncated.truncate(20);
        assert!(matches!(
            parse_npy("k", &truncated),
            Err(NpzError::BadNpy { .. })
        ));
        // a huge shape must not allocate or overflow
        let e = parse_npy(
            "k",
            &npy_with(
                "<f4",
                "(99999999999, 99999999999, 99999999999)",
                "False",
                &[],
            ),
        )
        .unwrap_err();
        assert!(matches!(e, NpzError::BadNpy { .. }), "{e}");
    }

    #[test]
    fn missing_keys_and_wrong_shapes_name_the_problem() {
        let mut npz = Npz::new();
        npz.insert("a", Array::new(vec![2, 16, 2], vec![0.0; 64]).unwrap());
        let e = npz.get("b").unwrap_err();
        assert!(matches!(&e, NpzError::MissingKey { key, .. } if key == "b"));
        assert!(e.to_string().contains("available: a"), "{e}");
        let e = npz.poses("a").unwrap_err();
        assert_eq!(
            e.to_string(),
            "array \"a\" has shape [2, 16, 2], expected (_, 17, 3)"
        );
        assert!(npz.get_shaped("a", &[None, Some(16), Some(2)]).is_ok());
        assert!(npz.scalar("a").is_err());
        assert!(matches!(
            Array::new(vec![2, 2], vec![0.0; 3]),
            Err(NpzError::DataLength {
                needed: 4,
                got: 3,
                ..
            })
        ));
        assert!(npz.remove("zz").is_err());
    }

    #[test]
    fn archives_read_only_checked_shapes() {
        let mut npz = Npz::new();
        npz.insert("a", Array::new(vec![2, 3], vec![1.0; 6]).unwrap());
        npz.insert("big", Array::new(vec![20_000], vec![0.0; 20_000]).unwrap());
        let path = temp("archive.npz");
        write_npz(&path, &npz).unwrap();
        let mut archive = NpzArchive::open(&path).unwrap();
        assert!(archive.contains("a") && !archive.contains("zz"));
        assert_eq!(archive.shape("a").unwrap(), [2, 3]);
        assert_eq!(archive.read("a", &[2, 3]).unwrap().data(), [1.0; 6]);
        let e = archive.read("a", &[3, 2]).unwrap_err();
        assert_eq!(
            e.to_string(),
            "array \"a\" has shape [2, 3], expected (3, 2)"
        );
        // Declared larger than two values can be: refused uninflated.
        let e = archive.read("big", &[2]).unwrap_err();
        assert!(
            matches!(&e, NpzError::TooLarge { key, expected, .. } if key == "big" && expected == "(2)"),
            "{e}"
        );
        assert!(matches!(
            archive.read("zz", &[1]),
            Err(NpzError::MissingKey { .. })
        ));
        std::fs::remove_file(&path).ok();
    }

    #[test]
    fn garbage_files_are_typed_errors() {
        let path = temp("garbage.npz");
        std::fs::write(&path, b"this is not a zip file").unwrap();
        let e = read_npz(&path).unwrap_err();
        std::fs::remove_file(&path).ok();
        assert!(matches!(e, NpzError::Zip { .. }), "{e}");
        assert!(matches!(
            read_npz(temp("absent.npz")),
            Err(NpzError::Io { .. })
        ));
    }
}
