//! Weights rearranged for the fast kernels.
//!
//! PyTorch stores a GRU as three gate blocks of rows (r | z | n), so one
//! hidden unit's three gate rows are 512 rows apart and a kernel that wants
//! all three gates of a unit at once would stream three distant places. Here
//! each GRU is cut into *panels* of [`LANES`] = 16 hidden units (one
//! AVX-512 register, two AVX2 registers); a panel stores, for every input
//! index `k`, the 16 r-weights, 16 z-weights and 16 n-weights of its units
//! next to each other (`[k][gate][lane]`, 192 contiguous bytes per `k`).
//! One sequential pass over a panel therefore yields all three gate
//! pre-activations of 16 units, ready for the fused epilogue. The input part
//! (`k < 256`, `W_ih`) precedes the recurrent part (`W_hh`) inside the panel
//! so the online step streams each panel exactly once. Buffers are 64-byte
//! aligned so every 16-float row is one cache line.
//!
//! The biases are pre-combined per panel (`b_ir + b_hr`, `b_iz + b_hz`,
//! `b_in`, `b_hn`) and the output layer has the symmetric-pair averaging
//! folded in (`S · W_fc`), cut per panel as `[unit][output]` so a panel's
//! new states can update the 16 outputs while still in registers.
//!
//! bf16 panels ([`Precision::Bf16`]) keep the same panels but pair
//! neighbouring input indices: for every pair `(2j, 2j+1)` they store, per
//! gate and lane, the two weights next to each other (`[j][gate][lane][2]`,
//! 192 bytes per pair). That is the operand layout of both bf16 units: one
//! 64-byte gate row is what `vdpbf16ps` multiplies by a broadcast input
//! pair, and 16 such rows at a stride of 192 bytes are an AMX `B` tile
//! ("VNNI" layout: 32 inputs x 16 units).

use super::Isa;
use crate::symmetry::averaging_matrix;
use crate::{EMBED_DIM, FEATURES, GATES, HIDDEN, INPUT_DIM, OUTPUT_DIM};

/// Hidden units per panel.
pub(crate) const LANES: usize = 16;
/// Panels per GRU direction.
pub(crate) const PANELS: usize = HIDDEN / LANES;
/// Floats per `k` inside a panel (three gates x 16 lanes).
pub(crate) const ROW: usize = 3 * LANES;
/// Floats of combined biases per panel.
pub(crate) const PANEL_BIAS: usize = 4 * LANES;
/// Floats of output weights per panel (`[unit][output]`).
pub(crate) const PANEL_FC: usize = LANES * OUTPUT_DIM;

#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Line([f32; 16]);

/// A zero-initialized, 64-byte aligned f32 buffer.
#[derive(Clone)]
pub(crate) struct AlignedBuf {
    lines: Vec<Line>,
    len: usize,
}

impl AlignedBuf {
    pub(crate) fn zeros(len: usize) -> Self {
        Self {
            lines: vec![Line([0.0; 16]); len.div_ceil(16)],
            len,
        }
    }

    pub(crate) fn as_slice(&self) -> &[f32] {
        // SAFETY: `Line` is `repr(C)` over `[f32; 16]`, so the lines are a
        // contiguous run of `16 * lines.len() >= len` initialized floats.
        unsafe { std::slice::from_raw_parts(self.lines.as_ptr().cast::<f32>(), self.len) }
    }

    pub(crate) fn as_mut_slice(&mut self) -> &mut [f32] {
        // SAFETY: as in `as_slice`, and `&mut self` guarantees exclusivity.
        unsafe { std::slice::from_raw_parts_mut(self.lines.as_mut_ptr().cast::<f32>(), self.len) }
    }
}

#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Line16([u16; 32]);

/// A zero-initialized, 64-byte aligned buffer of f16 bit patterns.
#[derive(Clone)]
pub(crate) struct AlignedBuf16 {
    lines: Vec<Line16>,
    len: usize,
}

impl AlignedBuf16 {
    fn from_f32(values: &[f32]) -> Self {
        Self::from_fn(values.len(), |i| half::f16::from_f32(values[i]).to_bits())
    }

    /// `len` values, value `i` being `f(i)`.
    pub(crate) fn from_fn(len: usize, f: impl Fn(usize) -> u16) -> Self {
        let mut lines = vec![Line16([0; 32]); len.div_ceil(32)];
        for i in 0..len {
            lines[i / 32].0[i % 32] = f(i);
        }
        Self { lines, len }
    }

    /// A zero-initialized buffer of `len` values.
    pub(crate) fn zeros(len: usize) -> Self {
        Self {
            lines: vec![Line16([0; 32]); len.div_ceil(32)],
            len,
        }
    }

    pub(crate) fn as_mut_slice(&mut self) -> &mut [u16] {
        // SAFETY: as in `as_slice`, and `&mut self` guarantees exclusivity.
        unsafe { std::slice::from_raw_parts_mut(self.lines.as_mut_ptr().cast::<u16>(), self.len) }
    }

    pub(crate) fn as_slice(&self) -> &[u16] {
        // SAFETY: `Line16` is `repr(C)` over `[u16; 32]`: a contiguous run of
        // `32 * lines.len() >= len` initialized values.
        unsafe { std::slice::from_raw_parts(self.lines.as_ptr().cast::<u16>(), self.len) }
    }
}

/// Storage type of the panel weights.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum Precision {
    /// f32 weights: agrees with the reference to ~1e-6.
    #[default]
    F32,
    /// f16 weights, f32 arithmetic: half the memory traffic (the batch-1
    /// step is bound by it) at ~1e-3 relative error per weight.
    F16,
    /// bf16 weights, and the matrix products' inputs (frame embedding and
    /// previous state) rounded to bf16, multiplied on the CPU's bf16 units
    /// (AVX512-BF16 or AMX, [`crate::fast::Bf16Unit`]) with f32
    /// accumulation; biases, gates, states and the output layer stay f32.
    /// Needs AVX512-BF16 (engines refuse it otherwise).
    Bf16,
}

impl Precision {
    /// Lower-case name (`f32`, `f16`, `bf16`).
    pub const fn as_str(self) -> &'static str {
        match self {
            Precision::F32 => "f32",
            Precision::F16 => "f16",
            Precision::Bf16 => "bf16",
        }
    }
}

impl std::fmt::Display for Precision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for Precision {
    type Err = crate::ModelError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "f32" => Ok(Precision::F32),
            "f16" => Ok(Precision::F16),
            "bf16" => Ok(Precision::Bf16),
            _ => Err(crate::ModelError::Config(format!(
                "unknown precision {s:?} (expected f32, f16 or bf16)"
            ))),
        }
    }
}

#[derive(Clone)]
enum PanelWeights {
    F32(AlignedBuf),
    F16(AlignedBuf16),
    /// Pair-interleaved bf16 bit patterns (see the module docs).
    Bf16(AlignedBuf16),
}

/// One GRU direction in panel layout.
#[derive(Clone)]
pub(crate) struct PackedGru {
    /// Input width inside each panel: 256 (online) or 0 (input part
    /// precomputed by the caller, offline).
    pub k_in: usize,
    w: PanelWeights,
    bias: AlignedBuf,
}

impl PackedGru {
    /// Floats per panel.
    pub(crate) fn panel_len(&self) -> usize {
        (self.k_in + HIDDEN) * ROW
    }

    /// Pack a PyTorch GRU direction. With `input = Some((W_ih, b_ih))` the
    /// panels contain `W_ih` and the biases are `[b_ir+b_hr, b_iz+b_hz,
    /// b_in, b_hn]`; with `None`, only `W_hh` and `[b_hr, b_hz, 0, b_hn]`
    /// (the caller supplies `W_ih x + b_ih` as pre-activations).
    pub(crate) fn new(
        input: Option<(&[f32], &[f32])>,
        w_hh: &[f32],
        b_hh: &[f32],
        precision: Precision,
    ) -> Self {
        assert_eq!(w_hh.len(), GATES * HIDDEN);
        assert_eq!(b_hh.len(), GATES);
        if let Some((w_ih, b_ih)) = input {
            assert_eq!(w_ih.len(), GATES * EMBED_DIM);
            assert_eq!(b_ih.len(), GATES);
        }
        let k_in = if input.is_some() { EMBED_DIM } else { 0 };
        let panel_len = (k_in + HIDDEN) * ROW;
        let mut w = AlignedBuf::zeros(PANELS * panel_len);
        let mut bias = AlignedBuf::zeros(PANELS * PANEL_BIAS);
        let ws = w.as_mut_slice();
        let bs = bias.as_mut_slice();
        for p in 0..PANELS {
            let panel = &mut ws[p * panel_len..(p + 1) * panel_len];
            for gate in 0..3 {
                for lane in 0..LANES {
                    let row = gate * HIDDEN + p * LANES + lane;
                    if let Some((w_ih, _)) = input {
                        for k in 0..k_in {
                            panel[k * ROW + gate * LANES + lane] = w_ih[row * EMBED_DIM + k];
                        }
                    }
                    for k in 0..HIDDEN {
                        panel[(k_in + k) * ROW + gate * LANES + lane] = w_hh[row * HIDDEN + k];
                    }
                    let b = &mut bs[p * PANEL_BIAS..(p + 1) * PANEL_BIAS];
                    let input_bias = input.map_or(0.0, |(_, b_ih)| b_ih[row]);
                    match gate {
                        0 | 1 => b[gate * LANES + lane] = input_bias + b_hh[row],
                        _ => {
                            b[2 * LANES + lane] = input_bias;
                            b[3 * LANES + lane] = b_hh[row];
                        }
                    }
                }
            }
        }
        let w = match precision {
            Precision::F32 => PanelWeights::F32(w),
            Precision::F16 => PanelWeights::F16(AlignedBuf16::from_f32(w.as_slice())),
            Precision::Bf16 => {
                let f = w.as_slice();
                PanelWeights::Bf16(AlignedBuf16::from_fn(f.len(), |i| {
                    // position i of the paired layout holds weight (k, col)
                    let (p, j) = (i / panel_len, i % panel_len);
                    let (pair, rest) = (j / (2 * ROW), j % (2 * ROW));
                    let (col, odd) = (rest / 2, rest % 2);
                    let k = 2 * pair + odd;
                    half::bf16::from_f32(f[p * panel_len + k * ROW + col]).to_bits()
                }))
            }
        };
        Self { k_in, w, bias }
    }

    /// Whether the panels hold f16 weights.
    pub(crate) fn is_half(&self) -> bool {
        matches!(self.w, PanelWeights::F16(_))
    }

    /// The storage precision of the panels.
    pub(crate) fn precision(&self) -> Precision {
        match self.w {
            PanelWeights::F32(_) => Precision::F32,
            PanelWeights::F16(_) => Precision::F16,
            PanelWeights::Bf16(_) => Precision::Bf16,
        }
    }

    /// Start of panel `p`'s weights (f32, f16 or paired bf16 values, see
    /// [`Self::precision`]);
    /// the panel holds [`Self::panel_len`] values.
    #[inline]
    pub(crate) fn panel_ptr(&self, p: usize) -> *const u8 {
        let n = self.panel_len();
        match &self.w {
            PanelWeights::F32(w) => w.as_slice()[p * n..(p + 1) * n].as_ptr().cast(),
            PanelWeights::F16(w) | PanelWeights::Bf16(w) => {
                w.as_slice()[p * n..(p + 1) * n].as_ptr().cast()
            }
        }
    }

    /// Combined biases of panel `p`.
    #[inline]
    pub(crate) fn bias(&self, p: usize) -> &[f32] {
        &self.bias.as_slice()[p * PANEL_BIAS..(p + 1) * PANEL_BIAS]
    }
}

/// The embedding `relu(W x + b)` with `W` transposed to `[34][256]`, so an
/// input value scales one contiguous row (a vectorizable axpy).
#[derive(Clone)]
pub(crate) struct PackedEmbed {
    wt: Vec<f32>,
    b: Vec<f32>,
}

impl PackedEmbed {
    pub(crate) fn new(w: &[f32], b: &[f32]) -> Self {
        assert_eq!(w.len(), EMBED_DIM * INPUT_DIM);
        assert_eq!(b.len(), EMBED_DIM);
        let mut wt = vec![0.0; INPUT_DIM * EMBED_DIM];
        for j in 0..EMBED_DIM {
            for k in 0..INPUT_DIM {
                wt[k * EMBED_DIM + j] = w[j * INPUT_DIM + k];
            }
        }
        Self { wt, b: b.to_vec() }
    }

    /// [`Self::apply`] compiled for the widest vectors `isa` allows.
    #[inline]
    pub(crate) fn apply_fast(&self, isa: Isa, x: &[f32], out: &mut [f32]) {
        match isa {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: engines only hold an `Isa` that `require()` confirmed.
            Isa::Avx2 | Isa::Avx512 => unsafe { self.apply_avx2(x, out) },
            _ => self.apply(x, out),
        }
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn apply_avx2(&self, x: &[f32], out: &mut [f32]) {
        self.apply(x, out)
    }

    /// `out = relu(W x + b)` for one frame (`x`: 34, `out`: 256).
    #[inline(always)]
    pub(crate) fn apply(&self, x: &[f32], out: &mut [f32]) {
        let out = &mut out[..EMBED_DIM];
        out.copy_from_slice(&self.b);
        for (k, &xk) in x[..INPUT_DIM].iter().enumerate() {
            let row = &self.wt[k * EMBED_DIM..(k + 1) * EMBED_DIM];
            for (o, &w) in out.iter_mut().zip(row) {
                *o += w * xk;
            }
        }
        for o in out.iter_mut() {
            *o = o.max(0.0);
        }
    }

    /// `W^T` (`[34][256]`) and `b`, for a batched GEMM.
    pub(crate) fn parts(&self) -> (&[f32], &[f32]) {
        (&self.wt, &self.b)
    }
}

/// The output layer with pair averaging folded in, per panel.
#[derive(Clone)]
pub(crate) struct PackedHead {
    /// `[feature block 0..2][panel][unit][output]`.
    fc: AlignedBuf,
}

impl PackedHead {
    /// From the PyTorch `fc.weight` (`[16][1024]`).
    pub(crate) fn new(fc_w: &[f32]) -> Self {
        assert_eq!(fc_w.len(), OUTPUT_DIM * FEATURES);
        let s = averaging_matrix();
        let mut fc = AlignedBuf::zeros(FEATURES * OUTPUT_DIM);
        let f = fc.as_mut_slice();
        for feat in 0..FEATURES {
            for o in 0..OUTPUT_DIM {
                // (S W)[o][feat] = sum_i S[o][i] W[i][feat]
                let v: f32 = (0..OUTPUT_DIM)
                    .map(|i| s[o][i] * fc_w[i * FEATURES + feat])
                    .sum();
                f[feat * OUTPUT_DIM + o] = v;
            }
        }
        Self { fc }
    }

    /// Output weights of feature block `block` (0: features 0..512, 1:
    /// 512..1024), panel `p`: `[unit][output]`.
    #[inline]
    pub(crate) fn panel(&self, block: usize, p: usize) -> &[f32] {
        let start = (block * PANELS + p) * PANEL_FC;
        &self.fc.as_slice()[start..start + PANEL_FC]
    }

    /// Full head on sigmoid-activated features `s` (1024), accumulated in f64
    /// order-independent enough for the offline path.
    pub(crate) fn apply(&self, s: &[f32]) -> [f32; OUTPUT_DIM] {
        let f = self.fc.as_slice();
        let mut y = [0.0f32; OUTPUT_DIM];
        for (feat, &sv) in s[..FEATURES].iter().enumerate() {
            for (o, yo) in y.iter_mut().enumerate() {
                *yo += f[feat * OUTPUT_DIM + o] * sv;
            }
        }
        y
    }
}
