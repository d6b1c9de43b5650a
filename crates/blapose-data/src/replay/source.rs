//! Where a sequence's arrays come from: arrays already in memory ([`Npz`])
//! or an archive on disk ([`NpzArchive`]).
//!
//! One loader serves both, and it asks for a shape before the values: on
//! an archive that reads only a member's `.npy` header, so every shape and
//! frame count is checked (against the frame limit and against each
//! other) before a value is inflated, and each member is then read with
//! exactly the shape it was checked for.

use std::io::{Read, Seek};

use crate::npz::{Array, Npz, NpzArchive, NpzError};

/// Arrays by key, shape first.
pub(crate) trait ArraySource {
    /// Whether `key` is present.
    fn has(&self, key: &str) -> bool;
    /// The shape of `key` (from the header only, where there is one).
    fn shape_of(&mut self, key: &str) -> Result<Vec<usize>, NpzError>;
    /// The array `key`, whose shape must be `shape`.
    fn read(&mut self, key: &str, shape: &[usize]) -> Result<Array, NpzError>;
}

impl ArraySource for &Npz {
    fn has(&self, key: &str) -> bool {
        self.contains(key)
    }

    fn shape_of(&mut self, key: &str) -> Result<Vec<usize>, NpzError> {
        Ok(self.get(key)?.shape().to_vec())
    }

    fn read(&mut self, key: &str, shape: &[usize]) -> Result<Array, NpzError> {
        let pattern: Vec<Option<usize>> = shape.iter().copied().map(Some).collect();
        self.get_shaped(key, &pattern).cloned()
    }
}

impl<R: Read + Seek> ArraySource for NpzArchive<R> {
    fn has(&self, key: &str) -> bool {
        self.contains(key)
    }

    fn shape_of(&mut self, key: &str) -> Result<Vec<usize>, NpzError> {
        self.shape(key)
    }

    fn read(&mut self, key: &str, shape: &[usize]) -> Result<Array, NpzError> {
        NpzArchive::read(self, key, shape)
    }
}

/// A single value (shape `()` or `(1,)`), checked before it is read.
pub(crate) fn scalar(source: &mut impl ArraySource, key: &str) -> Result<f32, NpzError> {
    let shape = source.shape_of(key)?;
    if shape.len() > 1 || shape.first().is_some_and(|&n| n != 1) {
        return Err(NpzError::Shape {
            key: key.to_owned(),
            expected: "() or (1,)".into(),
            actual: shape,
        });
    }
    Ok(source.read(key, &shape)?.data()[0])
}
