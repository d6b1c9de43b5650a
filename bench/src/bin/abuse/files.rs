//! The hostile replay files the script hands the readers: a zip bomb
//! (`bomb`: one member inflating to 2 GiB) and a central-directory bomb
//! (`dirbomb`: a valid replay file with millions of directory entries
//! more, each a few dozen bytes the zip reader would allocate for).

use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use anyhow::{ensure, Context, Result};

use crate::client::frames;

/// The zip-bomb replay file: a valid replay file whose `pose_3d` is a
/// right header followed by 2 GiB of zeros (about 2 MB deflated).
pub(crate) fn bomb(out: &Path) -> Result<()> {
    let (_, frames) = frames()?;
    let t = frames.len();
    let file = std::fs::File::create(out)?;
    let mut zip = zip::ZipWriter::new(std::io::BufWriter::new(file));
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    let npy = |shape: String| {
        let header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}\n");
        let mut out = b"\x93NUMPY\x01\x00".to_vec();
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
        out.extend_from_slice(header.as_bytes());
        out
    };
    zip.start_file("keypoints_2d.npy", options)?;
    zip.write_all(&npy(format!("({t}, 17, 2)")))?;
    for f in &frames {
        for v in &f.keypoints_2d {
            zip.write_all(&v.to_le_bytes())?;
        }
    }
    zip.start_file("image_size.npy", options)?;
    zip.write_all(&npy("(2,)".into()))?;
    for v in [1920f32, 1080.0] {
        zip.write_all(&v.to_le_bytes())?;
    }
    zip.start_file("pose_3d.npy", options)?;
    zip.write_all(&npy(format!("({t}, 17, 3)")))?;
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..2048 {
        zip.write_all(&zeros)?;
    }
    zip.finish()?.flush()?;
    println!(
        "bomb: {} ({} bytes; pose_3d inflates to 2 GiB)",
        out.display(),
        std::fs::metadata(out)?.len()
    );
    Ok(())
}

/// The replay file every directory bomb starts from (a valid one: the
/// readers must refuse it for its directory, not for a missing array).
fn example() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../examples/cmu_02_02_walk.npz")
}

/// The end-of-central-directory record of a zip without a comment: where
/// its directory starts and how long it is.
fn directory_of(zip: &[u8]) -> Result<(usize, usize, u64)> {
    let end = zip.len().checked_sub(22).context("too short for a zip")?;
    let eocd = &zip[end..];
    ensure!(
        eocd[..4] == *b"PK\x05\x06",
        "no end record at the end (a comment?)"
    );
    let u16_at = |o: usize| u64::from(u16::from_le_bytes([eocd[o], eocd[o + 1]]));
    let u32_at = |o: usize| u32::from_le_bytes([eocd[o], eocd[o + 1], eocd[o + 2], eocd[o + 3]]);
    let (entries, size, offset) = (u16_at(10), u32_at(12) as usize, u32_at(16) as usize);
    ensure!(
        offset + size == end,
        "the directory does not end at the end record"
    );
    Ok((offset, size, entries))
}

/// A central-directory entry (46 bytes and the name) for an empty stored
/// member whose local header is at `offset`.
fn directory_entry(out: &mut impl Write, name: &[u8], offset: u32) -> std::io::Result<()> {
    let mut e = Vec::with_capacity(46 + name.len());
    e.extend_from_slice(b"PK\x01\x02");
    e.extend_from_slice(&[45, 0, 20, 0]); // made by, needed: zip 4.5, 2.0
    e.extend_from_slice(&[0; 4]); // flags, method: stored
    e.extend_from_slice(&[0, 0, 0x21, 0]); // time, date: 1980-01-01
    e.extend_from_slice(&[0; 12]); // crc, sizes: empty
    e.extend_from_slice(&(name.len() as u16).to_le_bytes());
    e.extend_from_slice(&[0; 12]); // extra, comment, disk, attributes
    e.extend_from_slice(&offset.to_le_bytes());
    e.extend_from_slice(name);
    out.write_all(&e)
}

/// A central-directory bomb: the example replay file with `extra` entries
/// more in its directory, all for one empty member (6 hex digits a name:
/// 52 bytes an entry, so 8 M of them make the 415 MB file the readers once
/// peaked at 4.7 GB on). Zip64 end records carry the count past 65,535,
/// so a reader that believes the end record and one that scans for entries
/// both see all of them.
pub(crate) fn dirbomb(out: &Path, extra: u64) -> Result<()> {
    let valid = std::fs::read(example())?;
    let (offset, size, entries) = directory_of(&valid)?;
    let mut w = BufWriter::with_capacity(1 << 20, std::fs::File::create(out)?);
    w.write_all(&valid[..offset])?;
    let pad = u32::try_from(offset).context("the example is over 4 GB")?;
    let name = b"pad.npy";
    let mut local = b"PK\x03\x04".to_vec();
    local.extend_from_slice(&[20, 0, 0, 0, 0, 0, 0, 0, 0x21, 0]);
    local.extend_from_slice(&[0; 12]);
    local.extend_from_slice(&(name.len() as u16).to_le_bytes());
    local.extend_from_slice(&[0, 0]);
    local.extend_from_slice(name);
    w.write_all(&local)?;
    let directory_at = (offset + local.len()) as u64;
    w.write_all(&valid[offset..offset + size])?;
    let width = 6.max(format!("{extra:x}").len());
    for i in 0..extra {
        directory_entry(&mut w, format!("{i:0width$x}").as_bytes(), pad)?;
    }
    let total = entries + extra;
    let directory_size = size as u64 + extra * (46 + width as u64);
    let zip64_at = directory_at + directory_size;
    // Zip64 end record, its locator, then the classic end record saying
    // "see zip64".
    let mut end = b"PK\x06\x06".to_vec();
    end.extend_from_slice(&44u64.to_le_bytes());
    end.extend_from_slice(&[45, 0, 45, 0]);
    end.extend_from_slice(&[0; 8]);
    for v in [total, total, directory_size, directory_at] {
        end.extend_from_slice(&v.to_le_bytes());
    }
    end.extend_from_slice(b"PK\x06\x07");
    end.extend_from_slice(&0u32.to_le_bytes());
    end.extend_from_slice(&zip64_at.to_le_bytes());
    end.extend_from_slice(&1u32.to_le_bytes());
    end.extend_from_slice(b"PK\x05\x06");
    end.extend_from_slice(&[0; 4]);
    end.extend_from_slice(&[0xff; 12]);
    end.extend_from_slice(&[0, 0]);
    w.write_all(&end)?;
    w.into_inner().map_err(|e| e.into_error())?.sync_all()?;
    println!(
        "dirbomb: {} ({} bytes; {total} directory entries)",
        out.display(),
        std::fs::metadata(out)?.len()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_directory_bomb_is_a_zip64_archive_with_every_entry_the_readers_refuse() {
        let out = std::env::temp_dir().join(format!("abuse-dirbomb-{}.npz", std::process::id()));
        dirbomb(&out, 70_000).unwrap();
        // A reader that believes the end records (the zip crate, as
        // Python's zipfile) finds every entry: past 65,535, only zip64
        // end records can say so.
        let archive = zip::ZipArchive::new(std::fs::File::open(&out).unwrap()).unwrap();
        assert_eq!(archive.len(), 15 + 70_000);
        assert!(archive.file_names().any(|n| n == "pose_3d.npy"));
        // The replay reader refuses it for its directory.
        let refused = blapose_client::Sequence::load(&out, None).unwrap_err();
        assert!(refused.to_string().contains("entries"), "{refused}");
        std::fs::remove_file(&out).unwrap();
    }
}
