//! The person in a replay file, as far as it is known.
//!
//! A stature (and sex) given with a sequence lets the server answer with
//! the stature regression's lengths; the file stores it and the client
//! sends it, so it is one type, here below both.

use blapose_core::Sex;

/// The person's body as far as the client knows it (`OpenSession.subject`,
/// `AdjustSequenceRequest.subject`): with it the server answers with the
/// stature regression's lengths for that height (and sex). The server
/// accepts statures of 1.0 to 2.3 m and refuses others, naming the field.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Subject {
    /// Stature, metres.
    pub height_m: f32,
    /// Sex, if known.
    pub sex: Option<Sex>,
}

impl std::fmt::Display for Subject {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:.2} m", self.height_m)?;
        match self.sex {
            Some(Sex::Female) => write!(f, ", female"),
            Some(Sex::Male) => write!(f, ", male"),
            None => Ok(()),
        }
    }
}
