//! Tensor names and shapes of the two models — the weights-file contract.
//!
//! The names are exactly the `state_dict` keys of the paper's reference
//! PyTorch module (`BoneLengthModel` with `num_layers=1`): the embedding is
//! `expand_conv`, the online model's two GRUs are the `nn.ModuleList`
//! entries `gru.0` / `gru.1`, the offline model's bidirectional GRU is `gru`
//! with `_reverse` tensors for the backward direction, and the output layer
//! is `fc`. Keeping them lets a reference checkpoint be converted to
//! safetensors with no renaming, and lets our files load in PyTorch with
//! `load_state_dict(strict=True)`. Gate order inside the GRU matrices is
//! PyTorch's: rows `[0, 512)` reset (r), `[512, 1024)` update (z),
//! `[1024, 1536)` new (n).

use crate::{ModelKind, EMBED_DIM, FEATURES, GATES, HIDDEN, INPUT_DIM, OUTPUT_DIM};

/// Embedding weight, `[256, 34]`.
pub const EMBED_WEIGHT: &str = "expand_conv.weight";
/// Embedding bias, `[256]`.
pub const EMBED_BIAS: &str = "expand_conv.bias";
/// Output layer weight, `[16, 1024]` (no bias).
pub const FC_WEIGHT: &str = "fc.weight";
/// Prefix of the online model's first GRU.
pub const GRU_ONLINE_A: &str = "gru.0";
/// Prefix of the online model's second GRU.
pub const GRU_ONLINE_B: &str = "gru.1";
/// Prefix of the offline model's bidirectional GRU.
pub const GRU_BIDIRECTIONAL: &str = "gru";
/// Suffix of the backward direction's tensors in a bidirectional GRU.
pub const REVERSE_SUFFIX: &str = "_reverse";

/// Names of the four tensors of one GRU direction.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GruNames {
    /// Input-to-hidden weights, `[1536, 256]`.
    pub weight_ih: String,
    /// Hidden-to-hidden weights, `[1536, 512]`.
    pub weight_hh: String,
    /// Input-to-hidden bias, `[1536]`.
    pub bias_ih: String,
    /// Hidden-to-hidden bias, `[1536]`.
    pub bias_hh: String,
}

impl GruNames {
    /// Names of a layer-0 GRU direction under `prefix` (`suffix` is `""` or
    /// [`REVERSE_SUFFIX`]).
    pub fn new(prefix: &str, suffix: &str) -> Self {
        Self {
            weight_ih: format!("{prefix}.weight_ih_l0{suffix}"),
            weight_hh: format!("{prefix}.weight_hh_l0{suffix}"),
            bias_ih: format!("{prefix}.bias_ih_l0{suffix}"),
            bias_hh: format!("{prefix}.bias_hh_l0{suffix}"),
        }
    }

    /// The two GRU directions of `kind`, in the order the models run them:
    /// for [`ModelKind::Gru`] `gru.0` then `gru.1`; for [`ModelKind::BiGru`]
    /// forward then backward.
    pub fn for_kind(kind: ModelKind) -> [GruNames; 2] {
        match kind {
            ModelKind::Gru => [
                GruNames::new(GRU_ONLINE_A, ""),
                GruNames::new(GRU_ONLINE_B, ""),
            ],
            ModelKind::BiGru => [
                GruNames::new(GRU_BIDIRECTIONAL, ""),
                GruNames::new(GRU_BIDIRECTIONAL, REVERSE_SUFFIX),
            ],
        }
    }
}

/// Every tensor a model of `kind` has, with its shape, in a stable order.
pub fn tensor_specs(kind: ModelKind) -> Vec<(String, Vec<usize>)> {
    let mut specs = vec![
        (EMBED_WEIGHT.to_string(), vec![EMBED_DIM, INPUT_DIM]),
        (EMBED_BIAS.to_string(), vec![EMBED_DIM]),
    ];
    for g in GruNames::for_kind(kind) {
        specs.push((g.weight_ih, vec![GATES, EMBED_DIM]));
        specs.push((g.weight_hh, vec![GATES, HIDDEN]));
        specs.push((g.bias_ih, vec![GATES]));
        specs.push((g.bias_hh, vec![GATES]));
    }
    specs.push((FC_WEIGHT.to_string(), vec![OUTPUT_DIM, FEATURES]));
    specs
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::PARAMS;

    #[test]
    fn specs_count_exactly_the_paper_parameters() {
        for kind in [ModelKind::Gru, ModelKind::BiGru] {
            let total: usize = tensor_specs(kind)
                .iter()
                .map(|(_, s)| s.iter().product::<usize>())
                .sum();
            assert_eq!(total, PARAMS, "{kind}");
        }
    }

    #[test]
    fn names_follow_pytorch_state_dict_keys() {
        let [f, b] = GruNames::for_kind(ModelKind::BiGru);
        assert_eq!(f.weight_ih, "gru.weight_ih_l0");
        assert_eq!(b.bias_hh, "gru.bias_hh_l0_reverse");
        let [a, b] = GruNames::for_kind(ModelKind::Gru);
        assert_eq!(a.weight_hh, "gru.0.weight_hh_l0");
        assert_eq!(b.bias_ih, "gru.1.bias_ih_l0");
    }
}
