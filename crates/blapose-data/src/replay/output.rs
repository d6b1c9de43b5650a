//! The result files `blapose-client --out` writes: adjusted poses and the
//! bone lengths applied to each frame (and a server lifter's poses).
//!
//! Written and read here, beside the input format, so a result file is
//! read back by the same code that wrote it.

use std::path::Path;

use blapose_core::skeleton::NUM_BONES;
use blapose_core::{BoneLengths, Pose};

use super::error::SequenceError;
use super::keys::{KEY_ADJUSTED, KEY_BONE_LENGTHS, KEY_LIFTED, KEY_ROOT};
use crate::npz::{read_npz, write_npz, Array, Npz};

/// Write an adjustment result: `adjusted_3d` `(T, 17, 3)`, `bone_lengths`
/// `(T, 16)` and, unless `lifted` is empty (the poses were the client's),
/// `lifted_3d` `(T, 17, 3)`: the server lifter's poses the adjustment
/// started from, which the caller has no other copy of.
pub fn write_adjusted(
    path: impl AsRef<Path>,
    adjusted: &[Pose],
    bone_lengths: &[BoneLengths],
    lifted: &[Pose],
) -> Result<(), SequenceError> {
    write_adjusted_placed(path, adjusted, bone_lengths, lifted, &[])
}

/// [`write_adjusted`], plus each frame's placed pelvis ([`KEY_ROOT`],
/// `T x 3`, camera space, metres) when `roots` is not empty (it must then
/// have one row per frame).
pub fn write_adjusted_placed(
    path: impl AsRef<Path>,
    adjusted: &[Pose],
    bone_lengths: &[BoneLengths],
    lifted: &[Pose],
    roots: &[[f32; 3]],
) -> Result<(), SequenceError> {
    let path = path.as_ref();
    if !roots.is_empty() && roots.len() != adjusted.len() {
        return Err(SequenceError::OutputMismatch {
            poses: adjusted.len(),
            lengths: roots.len(),
        });
    }
    if adjusted.len() != bone_lengths.len() {
        return Err(SequenceError::OutputMismatch {
            poses: adjusted.len(),
            lengths: bone_lengths.len(),
        });
    }
    if !lifted.is_empty() && lifted.len() != adjusted.len() {
        return Err(SequenceError::LiftedMismatch {
            poses: adjusted.len(),
            lifted: lifted.len(),
        });
    }
    let npz_err = |source| SequenceError::Npz {
        path: path.to_owned(),
        error: source,
    };
    let mut npz = Npz::new();
    npz.insert(KEY_ADJUSTED, Array::from_poses(adjusted));
    let flat = bone_lengths.as_flattened().to_vec();
    npz.insert(
        KEY_BONE_LENGTHS,
        Array::new(vec![bone_lengths.len(), NUM_BONES], flat).map_err(npz_err)?,
    );
    if !lifted.is_empty() {
        npz.insert(KEY_LIFTED, Array::from_poses(lifted));
    }
    if !roots.is_empty() {
        let flat = roots.as_flattened().to_vec();
        npz.insert(
            KEY_ROOT,
            Array::new(vec![roots.len(), 3], flat).map_err(npz_err)?,
        );
    }
    write_npz(path, &npz).map_err(npz_err)
}

/// Read the server lifter's poses (`lifted_3d`) from what
/// [`write_adjusted`] wrote; `None` when the file has none.
pub fn read_lifted(path: impl AsRef<Path>) -> Result<Option<Vec<Pose>>, SequenceError> {
    let path = path.as_ref();
    let npz_err = |source| SequenceError::Npz {
        path: path.to_owned(),
        error: source,
    };
    let npz = read_npz(path).map_err(npz_err)?;
    if !npz.contains(KEY_LIFTED) {
        return Ok(None);
    }
    npz.poses(KEY_LIFTED).map(Some).map_err(npz_err)
}

/// Read back what [`write_adjusted`] wrote.
pub fn read_adjusted(
    path: impl AsRef<Path>,
) -> Result<(Vec<Pose>, Vec<BoneLengths>), SequenceError> {
    let path = path.as_ref();
    let npz_err = |source| SequenceError::Npz {
        path: path.to_owned(),
        error: source,
    };
    let npz = read_npz(path).map_err(npz_err)?;
    let adjusted = npz.poses(KEY_ADJUSTED).map_err(npz_err)?;
    let lengths = npz
        .get_shaped(KEY_BONE_LENGTHS, &[None, Some(NUM_BONES)])
        .map_err(npz_err)?;
    let lengths = lengths
        .data()
        .chunks_exact(NUM_BONES)
        .map(|c| std::array::from_fn(|b| c[b]))
        .collect();
    Ok((adjusted, lengths))
}
