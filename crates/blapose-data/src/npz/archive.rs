//! Reading `.npz` archives and `.npy` members, bounded by what they declare.
//!
//! Every read goes header first: the `.npy` header (at most
//! [`MAX_NPY_HEADER`] bytes) gives dtype and shape, and the values are then
//! read in small chunks, exactly as many bytes as the shape needs, plus one
//! byte to prove the member ends there. So a reader never allocates from a
//! size it has not seen inflated: not from the zip directory's declared
//! size (which a crafted file sets at will) and not from a header's shape
//! beyond the bytes that really follow it. [`NpzArchive`] adds the checks
//! for untrusted files: only the members asked for are opened, and the
//! caller's expected shape is enforced before any value is read.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufReader, Cursor, Read, Seek};
use std::path::{Path, PathBuf};

use rayon::prelude::*;

use super::{check_declared_shape, product, Array, Npz, NpzError};

/// The longest `.npy` header read (NumPy's own loader refuses headers over
/// 10,000 bytes unless told otherwise; ours are 118 bytes).
pub const MAX_NPY_HEADER: usize = 65_536;

/// Values are read in chunks of this many bytes, so a header's shape never
/// sizes an allocation beyond the data that follows it.
const CHUNK: usize = 1 << 16;

/// The float dtypes a `.npy` member may hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dtype {
    /// `<f4` (or `|f4`).
    F4Le,
    /// `>f4`.
    F4Be,
    /// `<f8`.
    F8Le,
    /// `>f8`.
    F8Be,
}

impl Dtype {
    /// Bytes per value.
    pub fn size(self) -> usize {
        match self {
            Dtype::F4Le | Dtype::F4Be => 4,
            Dtype::F8Le | Dtype::F8Be => 8,
        }
    }

    fn decode(self, c: &[u8]) -> f32 {
        match self {
            Dtype::F4Le => f32::from_le_bytes([c[0], c[1], c[2], c[3]]),
            Dtype::F4Be => f32::from_be_bytes([c[0], c[1], c[2], c[3]]),
            Dtype::F8Le => {
                f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]) as f32
            }
            Dtype::F8Be => {
                f64::from_be_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]) as f32
            }
        }
    }
}

/// What a `.npy` header declares.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NpyHeader {
    /// The values' dtype.
    pub dtype: Dtype,
    /// The array's shape (C order).
    pub shape: Vec<usize>,
}

impl NpyHeader {
    /// Bytes of values the header promises (`None` if that overflows).
    pub fn data_bytes(&self) -> Option<usize> {
        product(&self.shape)?.checked_mul(self.dtype.size())
    }
}

fn bad(key: &str, reason: impl Into<String>) -> NpzError {
    NpzError::BadNpy {
        key: key.to_owned(),
        reason: reason.into(),
    }
}

/// Fill `buf` from `r`; the number of bytes read (short only at the end).
fn fill(key: &str, r: &mut impl Read, buf: &mut [u8]) -> Result<usize, NpzError> {
    let mut got = 0;
    while got < buf.len() {
        match r.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(bad(key, format!("decompression failed: {e}"))),
        }
    }
    Ok(got)
}

/// Read a `.npy` header from the start of `r`, reading nothing past it.
pub fn read_npy_header(key: &str, r: &mut impl Read) -> Result<NpyHeader, NpzError> {
    let mut prefix = [0u8; 10];
    if fill(key, r, &mut prefix)? < 10 || &prefix[..6] != b"\x93NUMPY" {
        return Err(bad(key, "missing \\x93NUMPY magic"));
    }
    let header_len = match prefix[6] {
        1 => u16::from_le_bytes([prefix[8], prefix[9]]) as usize,
        2 | 3 => {
            let mut rest = [0u8; 2];
            if fill(key, r, &mut rest)? < 2 {
                return Err(bad(key, "truncated header"));
            }
            u32::from_le_bytes([prefix[8], prefix[9], rest[0], rest[1]]) as usize
        }
        v => return Err(bad(key, format!("unsupported format version {v}"))),
    };
    if header_len > MAX_NPY_HEADER {
        return Err(bad(
            key,
            format!("header of {header_len} bytes (at most {MAX_NPY_HEADER})"),
        ));
    }
    let mut raw = vec![0u8; header_len];
    if fill(key, r, &mut raw)? < header_len {
        return Err(bad(key, "truncated header"));
    }
    let header = std::str::from_utf8(&raw).map_err(|_| bad(key, "header is not text"))?;
    parse_header_text(key, header)
}

fn parse_header_text(key: &str, header: &str) -> Result<NpyHeader, NpzError> {
    let descr = header_value(header, "descr")
        .and_then(|v| {
            v.trim()
                .strip_prefix('\'')
                .and_then(|v| v.split('\'').next())
        })
        .ok_or_else(|| bad(key, "header has no 'descr'"))?;
    let fortran = header_value(header, "fortran_order")
        .ok_or_else(|| bad(key, "header has no 'fortran_order'"))?;
    if fortran.trim_start().starts_with("True") {
        return Err(NpzError::FortranOrder {
            key: key.to_owned(),
        });
    }
    let shape_text = header_value(header, "shape")
        .and_then(|v| v.trim_start().strip_prefix('('))
        .and_then(|v| v.split(')').next())
        .ok_or_else(|| bad(key, "header has no 'shape' tuple"))?;
    let shape = shape_text
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.trim_end_matches('L')
                .parse::<usize>()
                .map_err(|_| bad(key, format!("bad shape entry {s:?}")))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let dtype = match descr {
        "<f4" | "|f4" => Dtype::F4Le,
        ">f4" => Dtype::F4Be,
        "<f8" => Dtype::F8Le,
        ">f8" => Dtype::F8Be,
        other => {
            return Err(NpzError::UnsupportedDtype {
                key: key.to_owned(),
                descr: other.to_owned(),
            })
        }
    };
    let header = NpyHeader { dtype, shape };
    header
        .data_bytes()
        .ok_or_else(|| bad(key, "shape overflows"))?;
    Ok(header)
}

/// The text after `'name':` in a NumPy header dict.
fn header_value<'a>(header: &'a str, name: &str) -> Option<&'a str> {
    let pat = format!("'{name}'");
    let at = header.find(&pat)? + pat.len();
    header[at..].trim_start().strip_prefix(':')
}

/// Read the values `header` declares from `r` (positioned after the
/// header): exactly that many bytes, then one more read to check that
/// nothing follows. Memory grows with the bytes actually read.
fn read_npy_values(key: &str, r: &mut impl Read, header: &NpyHeader) -> Result<Array, NpzError> {
    let need = header
        .data_bytes()
        .ok_or_else(|| bad(key, "shape overflows"))?;
    let size = header.dtype.size();
    let total = need / size;
    let mut data: Vec<f32> = Vec::new();
    let mut chunk = vec![0u8; need.clamp(1, CHUNK)];
    let mut read = 0;
    while read < need {
        let want = (need - read).min(CHUNK);
        // Capacity doubles with the values read, capped at the total: a
        // header's shape alone sizes nothing, and a full read ends with
        // exactly the capacity it needs.
        if data.capacity() - data.len() < want / size {
            let more = data.len().max(CHUNK / size).min(total - data.len());
            data.reserve_exact(more);
        }
        let got = fill(key, r, &mut chunk[..want])?;
        data.extend(
            chunk[..got - got % size]
                .chunks_exact(size)
                .map(|c| header.dtype.decode(c)),
        );
        read += got;
        if got < want {
            return Err(bad(
                key,
                format!(
                    "shape {:?} needs {need} bytes of data, found {read}",
                    header.shape
                ),
            ));
        }
    }
    if fill(key, r, &mut chunk[..1])? != 0 {
        return Err(bad(
            key,
            format!(
                "shape {:?} needs {need} bytes of data, found more",
                header.shape
            ),
        ));
    }
    Ok(Array {
        shape: header.shape.clone(),
        data,
    })
}

/// Parse one `.npy` byte string.
pub fn parse_npy(key: &str, mut raw: &[u8]) -> Result<Array, NpzError> {
    let header = read_npy_header(key, &mut raw)?;
    read_npy_values(key, &mut raw, &header)
}

/// Read every array of an npz file.
pub fn read_npz(path: impl AsRef<Path>) -> Result<Npz, NpzError> {
    read_npz_filtered(path, |_| true)
}

/// Read the arrays whose key satisfies `keep` (e.g. one subject's
/// sequences); entries are decompressed in parallel. For trusted data sets:
/// each array is as large as its header says (if the data is there); files
/// from elsewhere go through [`NpzArchive`].
pub fn read_npz_filtered(
    path: impl AsRef<Path>,
    keep: impl Fn(&str) -> bool + Sync,
) -> Result<Npz, NpzError> {
    let path = path.as_ref();
    let bytes = std::fs::read(path).map_err(|source| NpzError::Io {
        path: path.to_owned(),
        source,
    })?;
    read_npz_bytes(&bytes, keep).map_err(|e| match e {
        NpzError::Zip { source, .. } => NpzError::Zip {
            path: path.to_owned(),
            source,
        },
        e => e,
    })
}

/// Parse an in-memory npz archive (see [`read_npz_filtered`]).
pub fn read_npz_bytes(bytes: &[u8], keep: impl Fn(&str) -> bool + Sync) -> Result<Npz, NpzError> {
    let zip_err = |source| NpzError::Zip {
        path: PathBuf::from("<memory>"),
        source,
    };
    let archive = zip::ZipArchive::new(Cursor::new(bytes)).map_err(zip_err)?;
    let wanted: Vec<(usize, String)> = archive
        .file_names()
        .filter_map(|name| {
            let key = name.strip_suffix(".npy").unwrap_or(name);
            keep(key).then(|| (name, key.to_owned()))
        })
        .filter_map(|(name, key)| archive.index_for_name(name).map(|i| (i, key)))
        .collect();
    let arrays = wanted
        .into_par_iter()
        .map(|(index, key)| {
            let mut archive = archive.clone();
            let mut entry = archive.by_index(index).map_err(zip_err)?;
            let header = read_npy_header(&key, &mut entry)?;
            let array = read_npy_values(&key, &mut entry, &header)?;
            Ok((key, array))
        })
        .collect::<Result<BTreeMap<_, _>, NpzError>>()?;
    Ok(Npz { arrays })
}

/// An npz archive from an untrusted source, read member by member with
/// the caller's shapes enforced before any value is read.
///
/// Opening reads only the zip directory, after counting it within
/// [`super::directory`]'s limits; [`NpzArchive::shape`] inflates a
/// member's header only; [`NpzArchive::read`] refuses a member whose
/// declared size exceeds what the expected shape needs (before inflating)
/// and reads at most that many bytes plus one.
pub struct NpzArchive<R = BufReader<File>> {
    zip: zip::ZipArchive<R>,
    path: PathBuf,
}

impl NpzArchive {
    /// Open a file (reads its zip directory, nothing else).
    pub fn open(path: impl AsRef<Path>) -> Result<Self, NpzError> {
        let path = path.as_ref();
        let file = File::open(path).map_err(|source| NpzError::Io {
            path: path.to_owned(),
            source,
        })?;
        Self::new(BufReader::new(file), path)
    }
}

impl<R: Read + Seek> NpzArchive<R> {
    /// An archive read from `reader`; `path` names it in errors. Its zip
    /// directory is bounded before it is parsed ([`super::directory`]).
    pub fn new(mut reader: R, path: impl Into<PathBuf>) -> Result<Self, NpzError> {
        let path = path.into();
        if let Err(source) = super::directory::check(&mut reader) {
            return Err(NpzError::Directory { path, source });
        }
        match zip::ZipArchive::new(reader) {
            Ok(zip) => Ok(Self { zip, path }),
            Err(source) => Err(NpzError::Zip { path, source }),
        }
    }

    /// The file's name, as given.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Whether the archive has a member for `key`.
    pub fn contains(&self, key: &str) -> bool {
        self.zip.index_for_name(&format!("{key}.npy")).is_some()
    }

    /// The keys of the `.npy` members, in archive order.
    pub fn keys(&self) -> impl Iterator<Item = &str> {
        self.zip
            .file_names()
            .filter_map(|name| name.strip_suffix(".npy"))
    }

    fn member(&mut self, key: &str) -> Result<zip::read::ZipFile<'_, R>, NpzError> {
        let Some(index) = self.zip.index_for_name(&format!("{key}.npy")) else {
            let mut available: Vec<&str> = self.keys().take(8).collect();
            if self.zip.len() > 8 {
                available.push("...");
            }
            return Err(NpzError::MissingKey {
                key: key.to_owned(),
                available: available.join(", "),
            });
        };
        let path = self.path.clone();
        self.zip
            .by_index(index)
            .map_err(|source| NpzError::Zip { path, source })
    }

    /// The dtype and shape `key`'s header declares (only the header is
    /// inflated).
    pub fn header(&mut self, key: &str) -> Result<NpyHeader, NpzError> {
        read_npy_header(key, &mut self.member(key)?)
    }

    /// The shape `key`'s header declares (only the header is inflated).
    pub fn shape(&mut self, key: &str) -> Result<Vec<usize>, NpzError> {
        Ok(self.header(key)?.shape)
    }

    /// Read `key`, which must have shape `expected` exactly: a member the
    /// zip directory declares larger than such an array's `.npy` can be is
    /// refused before inflating, a header with another shape before any
    /// value is read, and at most the declared values' bytes plus one are
    /// inflated.
    pub fn read(&mut self, key: &str, expected: &[usize]) -> Result<Array, NpzError> {
        let pattern: Vec<Option<usize>> = expected.iter().copied().map(Some).collect();
        let values = product(expected).ok_or_else(|| bad(key, "expected shape overflows"))?;
        let limit = values.saturating_mul(8).saturating_add(12 + MAX_NPY_HEADER) as u64;
        let mut entry = self.member(key)?;
        if entry.size() > limit {
            return Err(NpzError::TooLarge {
                key: key.to_owned(),
                declared: entry.size(),
                limit,
                expected: super::shape_pattern(&pattern),
            });
        }
        let header = read_npy_header(key, &mut entry)?;
        check_declared_shape(key, &header.shape, &pattern)?;
        read_npy_values(key, &mut entry, &header)
    }
}
