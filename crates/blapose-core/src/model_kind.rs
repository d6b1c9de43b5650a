//! Which of the paper's two bone-length models: one name for the concept
//! across the trainer, the server, the wire conversion and the clients.
//!
//! It lives in the geometry crate, not beside the networks, because the
//! client library names a model too and must not pull the networks in.

/// Which of the paper's two bone-length models.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ModelKind {
    /// Online model: two unidirectional GRUs fed the same stream (causal;
    /// what a stream runs).
    Gru,
    /// Offline model: one bidirectional GRU over the whole sequence.
    BiGru,
}

/// A model kind name that is neither `gru` nor `bigru`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown model kind {0:?} (expected \"gru\" or \"bigru\")")]
pub struct UnknownModelKind(pub String);

impl ModelKind {
    /// Both kinds, online first.
    pub const ALL: [ModelKind; 2] = [ModelKind::Gru, ModelKind::BiGru];

    /// The name used on command lines and in weights metadata.
    pub const fn as_str(self) -> &'static str {
        match self {
            ModelKind::Gru => "gru",
            ModelKind::BiGru => "bigru",
        }
    }
}

impl std::fmt::Display for ModelKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for ModelKind {
    type Err = UnknownModelKind;

    /// `gru` or `bigru` (also `bi-gru`; any case).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "gru" => Ok(ModelKind::Gru),
            "bigru" | "bi-gru" => Ok(ModelKind::BiGru),
            _ => Err(UnknownModelKind(s.to_string())),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kind_round_trips_through_strings() {
        for kind in ModelKind::ALL {
            assert_eq!(kind.to_string().parse::<ModelKind>().unwrap(), kind);
        }
        assert_eq!("BiGRU".parse::<ModelKind>().unwrap(), ModelKind::BiGru);
        assert!("lstm".parse::<ModelKind>().is_err());
    }
}
