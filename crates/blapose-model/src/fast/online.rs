//! One online GRU step for a batch of independent sessions — the serving
//! hot path.
//!
//! A call takes one frame per session (`B x 34`), the sessions' states
//! (`B x 2 x 512`, GRU `gru.0` then `gru.1`) and writes the new states in
//! place plus each session's 16 (pair-averaged) bone lengths predicted from
//! its new state. Per call:
//!
//! 1. every input value is checked to be finite — a NaN is refused before
//!    any state is touched (the whole call is refused, naming the row);
//! 2. the frames are embedded (`relu(W x + b)`) and each GRU's kernel
//!    inputs are packed, the two GRUs in parallel;
//! 3. the 64 panels (2 GRUs x 32) are split into contiguous ranges, one per
//!    thread; each thread streams its panels once, applying each to all
//!    rows tile by tile ([`super::kernel`]), writing new states into scratch
//!    and accumulating its share of the outputs. From
//!    `kernel::BLOCKED_MIN_ROWS` rows on, a panel is applied in L1-sized
//!    blocks of its input indices (`kernel::run_blocked`): with only 2 rows
//!    per AVX2 tile, re-streaming the whole panel from L2 for every tile
//!    made large batches L2-bandwidth bound;
//! 4. each thread checks its new states for non-finite values (absurd
//!    inputs can overflow) while they are in cache; each panel's share of
//!    the outputs is kept apart and the shares are summed in panel order,
//!    so a step's result does not depend on the thread count or on the
//!    order panels ran in (below): a session restored on another replica,
//!    or sharing a batch differently, gets the same bits. Only if
//!    everything is finite are the states copied over the caller's and the
//!    outputs written.
//!
//! With [`Precision::Bf16`] step 2 packs each GRU's inputs row-major in
//! bf16 instead and step 3 runs the bf16 kernels (`kernel::run_bf16`: AMX
//! tiles, 16 rows per block, or `vdpbf16ps`); everything else is shared.
//!
//! At batch 1 the step is bound by streaming the 9.4 MB of f32 weights from
//! L3, so the panel order alternates between calls: the panels used last
//! in one call are used first in the next, while they are still in L2.
//! All buffers live in a reusable [`StepScratch`]; a step allocates nothing
//! once the scratch has seen the largest batch, except that with worker
//! threads rayon's job queue allocates one small block per 63 steps (each
//! step enters the pool once).

use std::ops::Range;

use super::kernel::{self, TileArgs, BLOCK_ACC, BLOCK_WBUF};
use super::pack::{AlignedBuf, AlignedBuf16, PackedEmbed, PackedGru, PackedHead, LANES, PANELS};
use super::{build_pool, check_finite, Bf16Unit, EngineOptions, Isa, Precision};
use crate::names::{GruNames, EMBED_BIAS, EMBED_WEIGHT, FC_WEIGHT};
use crate::{
    LoadedWeights, ModelError, ModelKind, EMBED_DIM, HIDDEN, INPUT_DIM, OUTPUT_DIM, STATE_DIM,
};

/// Work items: (GRU, panel) pairs.
const ITEMS: usize = 2 * PANELS;

/// The fast online (two-GRU) model.
pub struct OnlineGruEngine {
    isa: Isa,
    /// The bf16 unit when the weights are bf16.
    bf16: Option<Bf16Unit>,
    threads: usize,
    pool: Option<rayon::ThreadPool>,
    embed: PackedEmbed,
    grus: [PackedGru; 2],
    head: PackedHead,
}

impl std::fmt::Debug for OnlineGruEngine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("OnlineGruEngine")
            .field("isa", &self.isa)
            .field("bf16", &self.bf16)
            .field("threads", &self.threads)
            .finish_non_exhaustive()
    }
}

/// Rows of bf16 packed inputs a batch needs per GRU: AMX reads whole
/// blocks of 16 rows.
fn bf16_rows(batch: usize) -> usize {
    batch.next_multiple_of(16)
}

/// Reusable buffers for [`OnlineGruEngine::step`].
#[derive(Clone)]
pub struct StepScratch {
    batch: usize,
    threads: usize,
    embedded: Vec<f32>,
    packed: Vec<f32>,
    /// bf16 engines: per GRU, `bf16_rows(batch)` rows of 768 bf16 inputs
    /// (empty until a bf16 engine needs it).
    packed16: AlignedBuf16,
    new_state: AlignedBuf,
    partial_out: Vec<f32>,
    /// Per thread: the blocked kernel's partial sums (`batch * BLOCK_ACC`).
    block_acc: AlignedBuf,
    /// Per thread: the blocked kernel's f16-widening buffer (`BLOCK_WBUF`).
    block_wbuf: AlignedBuf,
    reverse: bool,
}

impl StepScratch {
    /// Buffers for batches up to `max_batch` on an engine with `threads` threads.
    pub fn new(max_batch: usize, threads: usize) -> Self {
        let batch = max_batch.max(1);
        let threads = threads.max(1);
        Self {
            batch,
            threads,
            embedded: vec![0.0; batch * EMBED_DIM],
            packed: vec![0.0; 2 * batch * (EMBED_DIM + HIDDEN)],
            packed16: AlignedBuf16::zeros(0),
            new_state: AlignedBuf::zeros(ITEMS * batch * LANES),
            partial_out: vec![0.0; ITEMS * batch * OUTPUT_DIM],
            block_acc: AlignedBuf::zeros(threads * batch * BLOCK_ACC),
            block_wbuf: AlignedBuf::zeros(threads * BLOCK_WBUF),
            reverse: false,
        }
    }

    /// Largest batch these buffers hold without reallocating.
    pub fn capacity(&self) -> usize {
        self.batch
    }

    fn ensure(&mut self, batch: usize, threads: usize, bf16: bool) {
        if batch > self.batch || threads > self.threads {
            let reverse = self.reverse;
            *self = StepScratch::new(batch.max(self.batch), threads.max(self.threads));
            self.reverse = reverse;
        }
        let need16 = 2 * bf16_rows(self.batch) * (EMBED_DIM + HIDDEN);
        if bf16 && self.packed16.as_slice().len() < need16 {
            self.packed16 = AlignedBuf16::zeros(need16);
        }
    }
}

/// One thread's (or a group of threads') share of the step's mutable
/// buffers; split in two along with the panels.
struct ThreadBufs<'a> {
    /// New states of the group's panels, `[panel][row][16]`.
    new_state: &'a mut [f32],
    /// Per panel: output share, `batch x 16`.
    partial: &'a mut [f32],
    /// Per thread: blocked-kernel partial sums.
    acc: &'a mut [f32],
    /// Per thread: blocked-kernel weight buffer.
    wbuf: &'a mut [f32],
}

impl<'a> ThreadBufs<'a> {
    /// The buffers of the first `threads` threads (owning `panels` panels)
    /// and of the rest.
    fn split(self, panels: usize, threads: usize, batch: usize) -> (Self, Self) {
        let (s_l, s_r) = self.new_state.split_at_mut(panels * batch * LANES);
        let (p_l, p_r) = self.partial.split_at_mut(panels * batch * OUTPUT_DIM);
        let (a_l, a_r) = self.acc.split_at_mut(threads * batch * BLOCK_ACC);
        let (w_l, w_r) = self.wbuf.split_at_mut(threads * BLOCK_WBUF);
        (
            Self {
                new_state: s_l,
                partial: p_l,
                acc: a_l,
                wbuf: w_l,
            },
            Self {
                new_state: s_r,
                partial: p_r,
                acc: a_r,
                wbuf: w_r,
            },
        )
    }
}

/// Read-only operands shared by the worker threads of one step.
struct StepCtx<'a> {
    batch: usize,
    /// Per GRU: the kernel's packed inputs, `batch * 768` floats.
    packed: [&'a [f32]; 2],
    /// bf16 engines, per GRU: `bf16_rows(batch)` rows of 768 bf16 inputs.
    packed16: [&'a [u16]; 2],
    hidden: &'a [f32],
    reverse: bool,
}

impl OnlineGruEngine {
    /// Build from online (`gru`) weights with `threads` worker threads,
    /// f32 weights and the best instruction set of this CPU.
    pub fn new(weights: &LoadedWeights, threads: usize) -> Result<Self, ModelError> {
        Self::with_options(weights, EngineOptions::threads(threads))
    }

    /// As [`Self::new`] with an explicit instruction set (tests, benchmarks).
    pub fn with_isa(weights: &LoadedWeights, threads: usize, isa: Isa) -> Result<Self, ModelError> {
        Self::with_options(
            weights,
            EngineOptions {
                isa: Some(isa),
                ..EngineOptions::threads(threads)
            },
        )
    }

    /// Build with explicit [`EngineOptions`].
    pub fn with_options(weights: &LoadedWeights, opts: EngineOptions) -> Result<Self, ModelError> {
        crate::expect_kind(ModelKind::Gru, weights.kind())?;
        let isa = opts.resolved_isa()?;
        let bf16 = opts.resolved_bf16(isa)?;
        let threads = opts.threads;
        let pack = |n: &GruNames| -> Result<PackedGru, ModelError> {
            Ok(PackedGru::new(
                Some((&weights.values(&n.weight_ih)?, &weights.values(&n.bias_ih)?)),
                &weights.values(&n.weight_hh)?,
                &weights.values(&n.bias_hh)?,
                opts.precision,
            ))
        };
        let [na, nb] = GruNames::for_kind(ModelKind::Gru);
        Ok(Self {
            isa,
            bf16,
            threads: threads.max(1),
            pool: build_pool(threads, "blapose-online")?,
            embed: PackedEmbed::new(&weights.values(EMBED_WEIGHT)?, &weights.values(EMBED_BIAS)?),
            grus: [pack(&na)?, pack(&nb)?],
            head: PackedHead::new(&weights.values(FC_WEIGHT)?),
        })
    }

    /// The instruction set in use.
    pub fn isa(&self) -> Isa {
        self.isa
    }

    /// The storage precision of the GRU weights.
    pub fn precision(&self) -> Precision {
        self.grus[0].precision()
    }

    /// The bf16 unit the products run on (`None` unless the precision is
    /// [`Precision::Bf16`]).
    pub fn bf16_unit(&self) -> Option<Bf16Unit> {
        self.bf16
    }

    /// Worker threads per step.
    pub fn threads(&self) -> usize {
        self.threads
    }

    /// Whether a step of `batch` sessions uses the cache-blocked kernel
    /// (large batches with AVX2; see the module docs). Results agree either
    /// way; this is for tests and benchmarks.
    pub fn is_cache_blocked(&self, batch: usize) -> bool {
        kernel::use_blocked(self.isa, batch)
    }

    /// Scratch sized for batches up to `max_batch` on this engine.
    pub fn scratch(&self, max_batch: usize) -> StepScratch {
        let mut scratch = StepScratch::new(max_batch, self.threads);
        scratch.ensure(max_batch.max(1), self.threads, self.bf16.is_some());
        scratch
    }

    /// Advance `B = inputs.len() / 34` sessions by one frame.
    ///
    /// `inputs`: `B x 34` normalized keypoints; `hidden`: `B x 1024` states
    /// (`gru.0` then `gru.1`), updated in place; `out`: `B x 16` bone
    /// lengths predicted from the new states. On error nothing in `hidden`
    /// or `out` is changed.
    pub fn step(
        &self,
        inputs: &[f32],
        hidden: &mut [f32],
        out: &mut [f32],
        scratch: &mut StepScratch,
    ) -> Result<(), ModelError> {
        let batch = inputs.len() / INPUT_DIM;
        if batch == 0 || !inputs.len().is_multiple_of(INPUT_DIM) {
            return Err(ModelError::BadLength {
                what: "inputs (B x 34)",
                expected: batch.max(1) * INPUT_DIM,
                found: inputs.len(),
            });
        }
        for (what, len, want) in [
            ("hidden (B x 1024)", hidden.len(), batch * STATE_DIM),
            ("out (B x 16)", out.len(), batch * OUTPUT_DIM),
        ] {
            if len != want {
                return Err(ModelError::BadLength {
                    what,
                    expected: want,
                    found: len,
                });
            }
        }
        check_finite(inputs, INPUT_DIM)?;
        scratch.ensure(batch, self.threads, self.bf16.is_some());
        scratch.reverse = !scratch.reverse;
        // One pool entry per step: inside it the phases fork with
        // `rayon::join`, which allocates nothing (each `install` from outside
        // the pool pushes a job into rayon's injector, which allocates a
        // block every 63 jobs).
        match &self.pool {
            Some(pool) => pool.install(|| self.step_valid(batch, inputs, hidden, out, scratch)),
            None => self.step_valid(batch, inputs, hidden, out, scratch),
        }
    }

    /// [`Self::step`] after the argument checks, on the pool's threads.
    fn step_valid(
        &self,
        batch: usize,
        inputs: &[f32],
        hidden: &mut [f32],
        out: &mut [f32],
        scratch: &mut StepScratch,
    ) -> Result<(), ModelError> {
        let embedded = &mut scratch.embedded[..batch * EMBED_DIM];
        for (x, e) in inputs
            .chunks_exact(INPUT_DIM)
            .zip(embedded.chunks_exact_mut(EMBED_DIM))
        {
            self.embed.apply_fast(self.isa, x, e);
        }

        let k_total = EMBED_DIM + HIDDEN;
        let embedded = &scratch.embedded[..batch * EMBED_DIM];
        let rows16 = bf16_rows(batch);
        if self.bf16.is_some() {
            let (packed_a, packed_b) = scratch.packed16.as_mut_slice()[..2 * rows16 * k_total]
                .split_at_mut(rows16 * k_total);
            let pack = |g: usize, packed: &mut [u16]| {
                #[cfg(target_arch = "x86_64")]
                // SAFETY: the engine holds a bf16 unit only after
                // `resolved_bf16` confirmed AVX512-BF16.
                unsafe {
                    kernel::bf16::pack_rows(
                        batch,
                        EMBED_DIM,
                        |b| &embedded[b * EMBED_DIM..(b + 1) * EMBED_DIM],
                        |b| &hidden[b * STATE_DIM + g * HIDDEN..b * STATE_DIM + (g + 1) * HIDDEN],
                        packed,
                    );
                }
                #[cfg(not(target_arch = "x86_64"))]
                let _ = (g, packed);
            };
            self.per_gru(|| pack(0, packed_a), || pack(1, packed_b));
        } else {
            let (packed_a, packed_b) =
                scratch.packed[..2 * batch * k_total].split_at_mut(batch * k_total);
            let pack = |g: usize, packed: &mut [f32]| {
                kernel::pack_rows(
                    self.isa,
                    batch,
                    EMBED_DIM,
                    |b| &embedded[b * EMBED_DIM..(b + 1) * EMBED_DIM],
                    |b| &hidden[b * STATE_DIM + g * HIDDEN..b * STATE_DIM + (g + 1) * HIDDEN],
                    packed,
                );
            };
            self.per_gru(|| pack(0, packed_a), || pack(1, packed_b));
        }

        let (packed_a, packed_b) = scratch.packed[..2 * batch * k_total].split_at(batch * k_total);
        let packed16 = if self.bf16.is_some() {
            scratch.packed16.as_slice()[..2 * rows16 * k_total].split_at(rows16 * k_total)
        } else {
            (&[][..], &[][..])
        };
        let ctx = StepCtx {
            batch,
            packed: [packed_a, packed_b],
            packed16: [packed16.0, packed16.1],
            hidden,
            reverse: scratch.reverse,
        };
        let bufs = ThreadBufs {
            new_state: &mut scratch.new_state.as_mut_slice()[..ITEMS * batch * LANES],
            partial: &mut scratch.partial_out[..ITEMS * batch * OUTPUT_DIM],
            acc: &mut scratch.block_acc.as_mut_slice()[..self.threads * batch * BLOCK_ACC],
            wbuf: &mut scratch.block_wbuf.as_mut_slice()[..self.threads * BLOCK_WBUF],
        };
        let states_ok = self.run_items(0..ITEMS, bufs, self.threads, &ctx);

        // Commit only if every new state and output is finite. The panels'
        // output shares are summed, in panel order, into panel 0's share
        // (scratch), not `out`.
        let new_state = &scratch.new_state.as_slice()[..ITEMS * batch * LANES];
        let (y, others) =
            scratch.partial_out[..ITEMS * batch * OUTPUT_DIM].split_at_mut(batch * OUTPUT_DIM);
        for share in others.chunks_exact(batch * OUTPUT_DIM) {
            for (yo, p) in y.iter_mut().zip(share) {
                *yo += p;
            }
        }
        if !(states_ok && all_finite(y)) {
            let bad_row = (0..batch).find(|&b| {
                let h_ok = (0..ITEMS).all(|i| {
                    let start = (i * batch + b) * LANES;
                    all_finite(&new_state[start..start + LANES])
                });
                !(h_ok && all_finite(&y[b * OUTPUT_DIM..(b + 1) * OUTPUT_DIM]))
            });
            return Err(ModelError::NonFiniteState {
                row: bad_row.unwrap_or(0),
            });
        }
        out.copy_from_slice(y);
        for (i, chunk) in new_state.chunks_exact(batch * LANES).enumerate() {
            let col = (i / PANELS) * HIDDEN + (i % PANELS) * LANES;
            for (b, units) in chunk.chunks_exact(LANES).enumerate() {
                hidden[b * STATE_DIM + col..b * STATE_DIM + col + LANES].copy_from_slice(units);
            }
        }
        Ok(())
    }

    /// Run `a` and `b` (one per GRU) in parallel when the engine has
    /// threads (called inside its pool), else one after the other.
    fn per_gru(&self, a: impl FnOnce() + Send, b: impl FnOnce() + Send) {
        if self.threads > 1 {
            rayon::join(a, b);
        } else {
            a();
            b();
        }
    }

    /// Process `items` with `threads` threads: split in two and recurse
    /// with `rayon::join` (no allocation), one range per thread at the leaves.
    /// Returns whether every new state is finite.
    fn run_items(
        &self,
        items: Range<usize>,
        bufs: ThreadBufs,
        threads: usize,
        ctx: &StepCtx,
    ) -> bool {
        if threads <= 1 {
            return self.work(items, bufs, ctx);
        }
        let left = threads / 2;
        let mid = items.start + items.len() * left / threads;
        let (b_l, b_r) = bufs.split(mid - items.start, left, ctx.batch);
        let (ok_l, ok_r) = rayon::join(
            || self.run_items(items.start..mid, b_l, left, ctx),
            || self.run_items(mid..items.end, b_r, threads - left, ctx),
        );
        ok_l && ok_r
    }

    /// One thread's share: panels `items`, all rows. Returns whether all
    /// of its new states are finite (checked while they are in cache).
    fn work(&self, items: Range<usize>, bufs: ThreadBufs, ctx: &StepCtx) -> bool {
        let batch = ctx.batch;
        let ThreadBufs {
            new_state,
            partial,
            acc,
            wbuf,
        } = bufs;
        let acc = &mut acc[..batch * BLOCK_ACC];
        let wbuf = &mut wbuf[..BLOCK_WBUF];
        assert_eq!(new_state.len(), items.len() * batch * LANES);
        assert_eq!(partial.len(), items.len() * batch * OUTPUT_DIM);
        assert!(ctx
            .packed
            .iter()
            .all(|p| p.len() == batch * (EMBED_DIM + HIDDEN)));
        assert!(
            self.bf16.is_none()
                || ctx
                    .packed16
                    .iter()
                    .all(|p| p.len() == bf16_rows(batch) * (EMBED_DIM + HIDDEN))
        );
        assert_eq!(ctx.hidden.len(), batch * STATE_DIM);
        let first = items.start;
        let mut run_item = |i: usize| {
            let (g, p) = (i / PANELS, i % PANELS);
            let gru = &self.grus[g];
            let out = &mut new_state[(i - first) * batch * LANES..(i - first + 1) * batch * LANES];
            let y = &mut partial
                [(i - first) * batch * OUTPUT_DIM..(i - first + 1) * batch * OUTPUT_DIM];
            y.fill(0.0);
            let args = TileArgs {
                w: gru.panel_ptr(p),
                half: gru.is_half(),
                k_in: gru.k_in,
                bias: gru.bias(p).as_ptr(),
                x: ctx.packed[g].as_ptr(),
                h: ctx.hidden[g * HIDDEN..].as_ptr(),
                h_stride: STATE_DIM,
                unit0: p * LANES,
                pre: std::ptr::null(),
                pre_stride: 0,
                out: out.as_mut_ptr(),
                out_stride: LANES,
                save: std::ptr::null_mut(),
                save_stride: 0,
                fc: self.head.panel(g, p).as_ptr(),
                y: y.as_mut_ptr(),
                y_stride: OUTPUT_DIM,
            };
            // SAFETY: the asserts above and the slice bounds give every row
            // its operands: `packed[g]` holds `batch` rows of 768 packed by
            // `pack_rows` for `self.isa`, `hidden`
            // `batch` rows of 1024 (this GRU's 512 start at g * 512), `out`
            // `batch` rows of 16, `y` `batch` rows of 16; panels, biases and
            // output weights come from the packers with their full sizes and
            // 64-byte alignment; `self.isa` was checked at construction;
            // k_in = 256 is a multiple of the block size; `acc` and `wbuf`
            // are this thread's aligned blocked-kernel buffers. bf16: the
            // panel is a paired bf16 one (the engine's precision),
            // `packed16[g]` holds `bf16_rows(batch)` rows of 768 bf16 inputs
            // (checked above) and the unit was confirmed at construction.
            unsafe {
                match self.bf16 {
                    Some(unit) => kernel::run_bf16(
                        unit,
                        batch,
                        &args,
                        ctx.packed16[g].as_ptr(),
                        EMBED_DIM + HIDDEN,
                    ),
                    None => kernel::run_blocked(self.isa, batch, &args, acc, wbuf),
                }
            };
        };
        if ctx.reverse {
            items.rev().for_each(&mut run_item);
        } else {
            items.for_each(&mut run_item);
        }
        all_finite(new_state)
    }
}

/// Whether every value is finite, as one branch-free pass the compiler
/// vectorizes (an exponent of all ones marks Inf and NaN).
fn all_finite(values: &[f32]) -> bool {
    values.iter().fold(0u32, |bad, v| {
        bad | u32::from(v.to_bits() & 0x7f80_0000 == 0x7f80_0000)
    }) == 0
}
