//! The architecture of a trained lifter, defined once for everyone who
//! handles one: `blapose train-lifter` builds and trains the network it
//! describes and records it in the weights file's metadata ([`LifterArch`]
//! under `arch`), the server reads it back to rebuild the network, and the
//! evaluation picks the fastest exact form from it.
//!
//! Why it lives here, in the lower crate, rather than in the trainer: the
//! metadata is the one contract between the trainer and everything that
//! serves or evaluates its files, so the trainer's configuration *is* the
//! type the server parses; there is no second copy of the fields to drift.
//! The JSON spelling (`{"model":"videopose","filter_width":3,...}`) is that
//! of the shipped `models/lifter_*.safetensors` and must not change: the
//! tests pin it.
//!
//! [`LifterKind`] selects an architecture without its size (the `--model`
//! flag; the `model` tag of the JSON). The published reference models of
//! the paper's efficiency table are another concept,
//! [`crate::ReferenceLifter`].

use serde::{Deserialize, Serialize};

use crate::VideoPose3dConfig;

/// Which trainable lifter architecture: the `model` tag of a
/// [`LifterArch`] and the value of `blapose train-lifter --model`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum LifterKind {
    /// Martinez et al. 2017 residual MLP, single frame.
    Mlp,
    /// VideoPose3D-style temporal convolutions.
    VideoPose,
}

impl LifterKind {
    /// Every kind, in the order the command line lists them.
    pub const ALL: [LifterKind; 2] = [LifterKind::Mlp, LifterKind::VideoPose];

    /// Flag and metadata spelling: `mlp`, `videopose`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Mlp => "mlp",
            Self::VideoPose => "videopose",
        }
    }

    /// One line for a command's help.
    pub fn description(self) -> &'static str {
        match self {
            Self::Mlp => "Martinez et al. 2017 residual MLP, single frame",
            Self::VideoPose => "VideoPose3D-style temporal convolutions",
        }
    }
}

impl std::fmt::Display for LifterKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A name that is not a [`LifterKind`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown lifter architecture {0:?} (expected mlp or videopose)")]
pub struct UnknownLifterKind(pub String);

impl std::str::FromStr for LifterKind {
    type Err = UnknownLifterKind;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|k| k.as_str() == s)
            .ok_or_else(|| UnknownLifterKind(s.to_string()))
    }
}

/// Size of a VideoPose3D-style temporal lifter: `blocks + 1` layers, all
/// of filter width `filter_width`, so the receptive field is
/// `filter_width^(blocks + 1)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct VideoPoseArch {
    /// Filter width of every layer (odd).
    pub filter_width: usize,
    /// Residual blocks after the expanding convolution.
    pub blocks: usize,
    /// Convolution channels.
    pub channels: usize,
    /// Dropout probability (training only; no effect at inference).
    #[serde(default)]
    pub dropout: f32,
    /// Causal convolutions: the pose belongs to the window's last frame.
    pub causal: bool,
}

impl Default for VideoPoseArch {
    /// `blapose train-lifter --model videopose`'s size: 27 frames
    /// (`3,3,3`), 512 channels, dropout 0.25, centred — the reference's
    /// 27-frame model at half its width, which a 2-core CPU trains in about
    /// two hours.
    fn default() -> Self {
        Self {
            filter_width: 3,
            blocks: 2,
            channels: 512,
            dropout: 0.25,
            causal: false,
        }
    }
}

impl VideoPoseArch {
    /// Frames one pose depends on, `filter_width^(blocks + 1)`; `None` if
    /// that overflows.
    pub fn receptive_field(&self) -> Option<usize> {
        let layers = u32::try_from(self.blocks).ok()?.checked_add(1)?;
        self.filter_width.checked_pow(layers)
    }

    /// The trainer's short name: `videopose27-causal`, `videopose243`.
    pub fn name(&self) -> String {
        let rf = self
            .receptive_field()
            .map_or_else(|| "?".to_string(), |r| r.to_string());
        format!("videopose{rf}{}", if self.causal { "-causal" } else { "" })
    }

    /// The inference network of this size ([`crate::VideoPose3d`], the
    /// form the server and the evaluation run).
    pub fn config(&self) -> VideoPose3dConfig {
        VideoPose3dConfig {
            filter_widths: vec![self.filter_width; self.blocks.saturating_add(1)],
            channels: self.channels,
            causal: self.causal,
        }
    }
}

/// Size of the residual MLP of Martinez et al. 2017 (single frame).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MlpArch {
    /// Hidden width.
    pub hidden: usize,
    /// Residual blocks.
    pub blocks: usize,
    /// Dropout probability (training only).
    #[serde(default)]
    pub dropout: f32,
}

impl Default for MlpArch {
    /// The paper's size (`blapose train-lifter --model mlp`'s): hidden
    /// width 1024, 2 blocks, dropout 0.5.
    fn default() -> Self {
        Self {
            hidden: 1024,
            blocks: 2,
            dropout: 0.5,
        }
    }
}

/// A lifter architecture with its size: what a weights file needs to
/// rebuild the network, tagged by `model` as the trainer writes it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "model", rename_all = "lowercase")]
pub enum LifterArch {
    /// `"mlp"`: the single-frame residual MLP (trainable and evaluated;
    /// not servable).
    Mlp(MlpArch),
    /// `"videopose"`: temporal convolutions (servable when causal).
    #[serde(rename = "videopose")]
    VideoPose(VideoPoseArch),
}

impl LifterArch {
    /// The architecture's kind.
    pub fn kind(&self) -> LifterKind {
        match self {
            Self::Mlp(_) => LifterKind::Mlp,
            Self::VideoPose(_) => LifterKind::VideoPose,
        }
    }

    /// The `model` tag: `mlp`, `videopose`.
    pub fn model(&self) -> &'static str {
        self.kind().as_str()
    }

    /// The default size of `kind` ([`MlpArch::default`],
    /// [`VideoPoseArch::default`]).
    pub fn default_for(kind: LifterKind) -> Self {
        match kind {
            LifterKind::Mlp => Self::Mlp(MlpArch::default()),
            LifterKind::VideoPose => Self::VideoPose(VideoPoseArch::default()),
        }
    }

    /// A short name for tables: `mlp`, `videopose27`, `videopose27-causal`.
    pub fn name(&self) -> String {
        match self {
            Self::Mlp(_) => "mlp".into(),
            Self::VideoPose(a) => a.name(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The JSON of the shipped `models/lifter_*.safetensors` (their
    /// `arch`, verbatim): it parses, and writes back byte for byte.
    #[test]
    fn shipped_spellings_round_trip_byte_for_byte() {
        let cases = [
            (
                r#"{"model":"mlp","hidden":1024,"blocks":2,"dropout":0.5}"#,
                LifterArch::Mlp(MlpArch::default()),
            ),
            (
                r#"{"model":"videopose","filter_width":3,"blocks":2,"channels":512,"dropout":0.25,"causal":false}"#,
                LifterArch::VideoPose(VideoPoseArch::default()),
            ),
            (
                r#"{"model":"videopose","filter_width":3,"blocks":2,"channels":512,"dropout":0.25,"causal":true}"#,
                LifterArch::VideoPose(VideoPoseArch {
                    causal: true,
                    ..VideoPoseArch::default()
                }),
            ),
        ];
        for (json, arch) in cases {
            assert_eq!(serde_json::to_string(&arch).unwrap(), json);
            assert_eq!(serde_json::from_str::<LifterArch>(json).unwrap(), arch);
        }
        // Files without a dropout (it has no effect at inference) load.
        let bare: LifterArch =
            serde_json::from_str(r#"{"model":"mlp","hidden":8,"blocks":1}"#).unwrap();
        assert_eq!(
            bare,
            LifterArch::Mlp(MlpArch {
                hidden: 8,
                blocks: 1,
                dropout: 0.0
            })
        );
    }

    #[test]
    fn kinds_names_and_defaults() {
        for kind in LifterKind::ALL {
            assert_eq!(kind.as_str().parse::<LifterKind>(), Ok(kind));
            let arch = LifterArch::default_for(kind);
            assert_eq!(arch.kind(), kind);
            assert_eq!(arch.model(), kind.to_string());
        }
        assert!("temporal".parse::<LifterKind>().is_err());
        let vp = VideoPoseArch {
            causal: true,
            ..VideoPoseArch::default()
        };
        assert_eq!(LifterArch::VideoPose(vp).name(), "videopose27-causal");
        assert_eq!(LifterArch::Mlp(MlpArch::default()).name(), "mlp");
        let huge = VideoPoseArch {
            blocks: usize::MAX,
            ..vp
        };
        assert_eq!(huge.receptive_field(), None);
        assert_eq!(huge.name(), "videopose?-causal");
        assert_eq!(vp.config().filter_widths, vec![3, 3, 3]);
    }
}
