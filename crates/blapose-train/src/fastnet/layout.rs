//! Where every tensor of a bone-length network lives in [`FastNet`]'s
//! flat parameter vector, by the reference models' tensor names.
//!
//! [`FastNet`]: super::FastNet

use std::ops::Range;

use blapose_core::skeleton::NUM_BONES;
use blapose_model::names::{GruNames, EMBED_BIAS, EMBED_WEIGHT, FC_WEIGHT};
use blapose_model::{ModelKind, EMBED_DIM, FEATURES, GATES, HIDDEN, INPUT_DIM};

/// Where one GRU direction's tensors live in the flat parameter vector.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GruLayout {
    /// `[1536, 256]`.
    pub w_ih: Range<usize>,
    /// `[1536, 512]`.
    pub w_hh: Range<usize>,
    /// `[1536]`.
    pub b_ih: Range<usize>,
    /// `[1536]`.
    pub b_hh: Range<usize>,
}

/// Where every tensor lives in the flat parameter vector.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Layout {
    /// Model kind.
    pub kind: ModelKind,
    /// `[256, 34]`.
    pub embed_w: Range<usize>,
    /// `[256]`.
    pub embed_b: Range<usize>,
    /// The two GRU directions in run order (see [`GruNames::for_kind`]).
    pub gru: [GruLayout; 2],
    /// `[16, 1024]`.
    pub fc_w: Range<usize>,
    /// Total number of parameters.
    pub len: usize,
}

impl Layout {
    /// The layout of `kind`.
    pub fn new(kind: ModelKind) -> Self {
        let mut at = 0usize;
        let mut take = |n: usize| {
            let r = at..at + n;
            at += n;
            r
        };
        let embed_w = take(EMBED_DIM * INPUT_DIM);
        let embed_b = take(EMBED_DIM);
        let mut gru = || GruLayout {
            w_ih: take(GATES * EMBED_DIM),
            w_hh: take(GATES * HIDDEN),
            b_ih: take(GATES),
            b_hh: take(GATES),
        };
        let g0 = gru();
        let g1 = gru();
        let fc_w = take(NUM_BONES * FEATURES);
        Self {
            kind,
            embed_w,
            embed_b,
            gru: [g0, g1],
            fc_w,
            len: at,
        }
    }

    /// `(tensor name, range, shape)` of every tensor.
    pub fn tensors(&self) -> Vec<(String, Range<usize>, Vec<usize>)> {
        let mut out = vec![
            (
                EMBED_WEIGHT.to_string(),
                self.embed_w.clone(),
                vec![EMBED_DIM, INPUT_DIM],
            ),
            (
                EMBED_BIAS.to_string(),
                self.embed_b.clone(),
                vec![EMBED_DIM],
            ),
        ];
        for (g, names) in self.gru.iter().zip(GruNames::for_kind(self.kind)) {
            out.push((names.weight_ih, g.w_ih.clone(), vec![GATES, EMBED_DIM]));
            out.push((names.weight_hh, g.w_hh.clone(), vec![GATES, HIDDEN]));
            out.push((names.bias_ih, g.b_ih.clone(), vec![GATES]));
            out.push((names.bias_hh, g.b_hh.clone(), vec![GATES]));
        }
        out.push((
            FC_WEIGHT.to_string(),
            self.fc_w.clone(),
            vec![NUM_BONES, FEATURES],
        ));
        out
    }
}
