//! What blapose knows of a person beyond their keypoints.
//!
//! One definition of [`Sex`] serves the survey reader (ANSUR II's `Gender`
//! column), the stature regression, the wire conversion and the client:
//! they all mean the same two values, so they share one type.

/// A person's sex, when given (the stature regression has a line per sex;
/// the survey records it per person).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Sex {
    /// Female.
    Female,
    /// Male.
    Male,
}

impl Sex {
    /// The lowercase name used on command lines and in reports.
    pub const fn as_str(self) -> &'static str {
        match self {
            Sex::Female => "female",
            Sex::Male => "male",
        }
    }
}

impl std::fmt::Display for Sex {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A sex name that is neither `female` nor `male`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown sex {0:?}: expected female or male")]
pub struct UnknownSex(pub String);

impl std::str::FromStr for Sex {
    type Err = UnknownSex;

    /// `female` or `male` (any case, `f`/`m` too).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "female" | "f" => Ok(Sex::Female),
            "male" | "m" => Ok(Sex::Male),
            _ => Err(UnknownSex(s.to_string())),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_unknown_names_are_refused() {
        for sex in [Sex::Female, Sex::Male] {
            assert_eq!(sex.to_string().parse::<Sex>().unwrap(), sex);
        }
        assert_eq!("Male".parse::<Sex>().unwrap(), Sex::Male);
        assert!("x".parse::<Sex>().is_err());
    }
}
