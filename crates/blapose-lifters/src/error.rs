//! The one error type of this crate.
//!
//! Shape mistakes are the errors callers actually make with lifters (a
//! window of the wrong length, 3 features instead of 2), so they get their
//! own variant with both shapes spelled out; everything candle reports is
//! wrapped unchanged.

/// Why a lifter could not be built or run.
#[derive(Debug, thiserror::Error)]
pub enum LifterError {
    /// An input tensor has the wrong shape.
    #[error("{what}: expected shape {expected}, got {got:?}")]
    Shape {
        /// Which input.
        what: &'static str,
        /// The expected shape, in words (e.g. `"(B, 243, 17, 2)"`).
        expected: String,
        /// The shape received.
        got: Vec<usize>,
    },
    /// A configuration that the architecture cannot represent.
    #[error("invalid configuration: {0}")]
    Config(String),
    /// A tensor operation failed (including missing or misshapen weights).
    #[error(transparent)]
    Candle(#[from] candle_core::Error),
}

/// Result alias for this crate.
pub type Result<T> = std::result::Result<T, LifterError>;

/// Check that `t` has exactly `expected` dims; `None` entries match any size.
pub(crate) fn expect_dims(
    t: &candle_core::Tensor,
    what: &'static str,
    expected: &[Option<usize>],
) -> Result<()> {
    let got = t.dims();
    let ok = got.len() == expected.len()
        && got
            .iter()
            .zip(expected)
            .all(|(g, e)| e.is_none_or(|e| e == *g));
    if ok {
        return Ok(());
    }
    let words: Vec<String> = expected
        .iter()
        .enumerate()
        .map(|(i, e)| match e {
            Some(n) => n.to_string(),
            None if i == 0 => "B".to_string(),
            None => "_".to_string(),
        })
        .collect();
    Err(LifterError::Shape {
        what,
        expected: format!("({})", words.join(", ")),
        got: got.to_vec(),
    })
}
