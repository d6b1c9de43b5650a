//! The zip directory of an untrusted archive, bounded before it is parsed.
//!
//! The zip crate reads an archive's whole central directory when it opens
//! it, one allocation per entry (its name, extra fields and comment
//! included), and the directory declares its own size: a 415 MB file with
//! 8 M entries made the replay reader peak at 4.7 GB before it read a
//! single array. A replay file has about fifteen members. So before the
//! zip crate sees an untrusted archive, [`check`] streams the file once
//! (in fixed chunks, constant memory) and counts every central-directory
//! file header signature (`PK\x01\x02`) anywhere in it, with the name,
//! extra-field and comment lengths each header declares: no directory the
//! zip crate could parse from this file (it tries earlier end-of-directory
//! records when a later one fails, so counting only the one at the end
//! would not bound it) holds more entries or bytes than these sums. A
//! file over [`MAX_ENTRIES`] or [`MAX_DIRECTORY_BYTES`] is refused. A
//! signature that happens to occur inside compressed data only adds to
//! the sums; real replay files stay far below both limits.

use std::io::{Read, Seek, SeekFrom};

/// Most central-directory entries an untrusted archive may hold (a replay
/// file has about fifteen).
pub const MAX_ENTRIES: u64 = 1024;
/// Most bytes the central directory's entries may take, headers, names,
/// extra fields and comments together.
pub const MAX_DIRECTORY_BYTES: u64 = 1 << 20;

/// A central-directory file header's signature.
const SIGNATURE: [u8; 4] = *b"PK\x01\x02";
/// A central-directory file header's fixed part, signature included.
const HEADER: usize = 46;
/// Bytes read per chunk.
const CHUNK: usize = 1 << 16;

/// What the file's central-directory headers add up to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct DirectorySize {
    /// Headers found.
    pub entries: u64,
    /// Bytes they declare (fixed parts, names, extra fields, comments).
    pub bytes: u64,
}

/// Why an archive's directory is refused.
#[derive(Debug, thiserror::Error)]
pub enum DirectoryError {
    /// More entries than [`MAX_ENTRIES`].
    #[error("the zip directory has {0} or more entries, more than the {MAX_ENTRIES} a replay file may have")]
    Entries(u64),
    /// More bytes than [`MAX_DIRECTORY_BYTES`].
    #[error("the zip directory takes {0} or more bytes, more than the {MAX_DIRECTORY_BYTES} a replay file's may")]
    Bytes(u64),
    /// The file could not be read.
    #[error("reading the zip directory: {0}")]
    Io(#[from] std::io::Error),
}

/// Count the central-directory headers of `reader` from its start, refuse
/// it past the limits, and leave it at its start again.
pub fn check<R: Read + Seek>(reader: &mut R) -> Result<DirectorySize, DirectoryError> {
    reader.seek(SeekFrom::Start(0))?;
    let mut size = DirectorySize::default();
    // `HEADER - 1` bytes carried over, so a header across chunks is seen.
    let mut buf = vec![0u8; CHUNK + HEADER];
    let mut kept = 0;
    loop {
        let n = read_some(reader, &mut buf[kept..])?;
        let end = kept + n;
        let last = n == 0;
        // Headers that start where all 46 bytes are here (or the file ends).
        let scan_to = if last {
            end
        } else {
            end.saturating_sub(HEADER - 1)
        };
        let mut at = 0;
        while let Some(i) = find(&buf[at..end]) {
            let start = at + i;
            if start >= scan_to {
                break; // seen again with the next chunk
            }
            let fixed = buf.get(start..start + HEADER);
            let variable = fixed.map_or(0, |h| {
                [28, 30, 32]
                    .iter()
                    .map(|&o| u64::from(u16::from_le_bytes([h[o], h[o + 1]])))
                    .sum()
            });
            size.entries += 1;
            size.bytes += HEADER as u64 + variable;
            if size.entries > MAX_ENTRIES {
                return Err(DirectoryError::Entries(size.entries));
            }
            if size.bytes > MAX_DIRECTORY_BYTES {
                return Err(DirectoryError::Bytes(size.bytes));
            }
            at = start + 1;
        }
        if last {
            break;
        }
        let carry = end - scan_to;
        buf.copy_within(scan_to..end, 0);
        kept = carry;
    }
    reader.seek(SeekFrom::Start(0))?;
    Ok(size)
}

fn find(hay: &[u8]) -> Option<usize> {
    hay.windows(SIGNATURE.len()).position(|w| w == SIGNATURE)
}

fn read_some(r: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut got = 0;
    while got < buf.len().min(CHUNK) {
        match r.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{Cursor, Write};

    fn archive(members: usize, name_len: usize) -> Vec<u8> {
        let mut zip = zip::ZipWriter::new(Cursor::new(Vec::new()));
        let stored = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Stored);
        for i in 0..members {
            let name = format!("{i:0>width$}.npy", width = name_len);
            zip.start_file(name, stored).unwrap();
            zip.write_all(b"x").unwrap();
        }
        zip.finish().unwrap().into_inner()
    }

    #[test]
    fn counts_every_entry_across_chunk_boundaries() {
        for members in [0, 1, 15, 700] {
            let bytes = archive(members, 90);
            assert!(bytes.len() > CHUNK || members < 700, "spans chunks");
            let size = check(&mut Cursor::new(&bytes)).unwrap();
            assert_eq!(size.entries, members as u64);
            assert_eq!(size.bytes, members as u64 * (46 + 94));
        }
    }

    #[test]
    fn too_many_entries_or_bytes_are_refused() {
        let many = archive(MAX_ENTRIES as usize + 1, 4);
        assert!(matches!(
            check(&mut Cursor::new(&many)),
            Err(DirectoryError::Entries(n)) if n == MAX_ENTRIES + 1
        ));
        // 200 entries with 8 KB names: 1.6 MB of directory.
        let long = archive(200, 8000);
        assert!(matches!(
            check(&mut Cursor::new(&long)),
            Err(DirectoryError::Bytes(_))
        ));
        let ok = archive(MAX_ENTRIES as usize, 4);
        let mut cursor = Cursor::new(&ok);
        check(&mut cursor).unwrap();
        assert_eq!(cursor.position(), 0, "rewound for the zip crate");
    }
}
