//! The fused GRU panel kernel: one pass over a panel's weights produces the
//! r, z and n pre-activations of 16 hidden units for a tile of batch rows,
//! and the epilogue turns them into new states (and, optionally, their
//! contribution to the 16 outputs) while they are still in registers.
//!
//! Every weight loaded from memory is multiplied into all rows of the tile,
//! so at batch sizes above one the weights are re-read `rows / tile` times
//! from L2 instead of once per row. The kernels exist in three versions
//! (scalar, AVX2, AVX-512) with identical layout and arithmetic order per
//! lane; `tile` dispatches on the [`Isa`] chosen at engine construction.
//!
//! A tile holds as many rows as the registers allow (2 for AVX2), so at
//! large batches a whole panel (147 KB) would be re-streamed from L2 once
//! per tile, and the step becomes bound by L2 bandwidth (measured: 25% of
//! the FMA peak at batch 64). [`run_blocked`] therefore cuts the panel into
//! blocks of [`KC`] input indices that stay in L1 while every tile uses
//! them, keeping the tiles' partial sums in a small scratch buffer; it is
//! what the online step uses from [`BLOCKED_MIN_ROWS`] rows on (AVX2).
//! Its 2-row inner loop is written in assembly so that the 12 accumulators,
//! 2 broadcasts and 2 weight registers fit the 16 `ymm` registers exactly.
//!
//! bf16 panels ([`crate::fast::Precision::Bf16`]) run on the CPU's bf16
//! units instead ([`run_bf16`]): `vdpbf16ps` (`bf16`) or AMX tiles
//! (`amx`), with the inputs packed row-major in bf16 and the same epilogue
//! as the AVX-512 kernels.

pub(crate) mod scalar;

#[cfg(target_arch = "x86_64")]
pub(crate) mod amx;
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx2;
#[cfg(target_arch = "x86_64")]
pub(crate) mod avx512;
#[cfg(target_arch = "x86_64")]
pub(crate) mod bf16;

use super::{Bf16Unit, Isa};
use crate::HIDDEN;

/// Raw operands of one kernel call. Row `b` of an operand starts at
/// `ptr + b * stride`.
///
/// Contract (checked by the callers, relied on by the kernels): `w` points
/// to a full 64-byte aligned panel of `(k_in + 512) * 48` values, f32 or
/// (when `half`) f16 bit patterns; `bias` to
/// 64 floats; `x` to the rows' inputs packed by [`pack_rows`] (`k_in`
/// input values then the 512 previous state values, `[k][row]` per tile);
/// `h` rows hold 512 floats (the previous state of this GRU direction) and
/// the panel's units start at `unit0`; `pre` is null or its rows hold 1536
/// input pre-activations in PyTorch gate order (`[r|z|n]` x 512, the kernel
/// reads the panel's units of each gate); `out` rows have room for 16
/// floats; `save` is null or its rows hold 2048 floats `[r|z|n|W_hn h+b_hn]`
/// x 512 of which the panel's units are written (for training); `fc` is null or
/// holds 256 aligned floats `[unit][output]`, in which case `y` rows hold 16
/// floats that are accumulated into. `out` and `y` must not overlap any
/// input.
#[derive(Clone, Copy)]
pub(crate) struct TileArgs {
    pub w: *const u8,
    pub half: bool,
    pub k_in: usize,
    pub bias: *const f32,
    pub x: *const f32,
    pub h: *const f32,
    pub h_stride: usize,
    pub unit0: usize,
    pub pre: *const f32,
    pub pre_stride: usize,
    pub out: *mut f32,
    pub out_stride: usize,
    pub save: *mut f32,
    pub save_stride: usize,
    pub fc: *const f32,
    pub y: *mut f32,
    pub y_stride: usize,
}

impl TileArgs {
    /// The same operands advanced by `rows` batch rows.
    #[inline]
    pub(crate) fn offset_rows(&self, rows: usize) -> TileArgs {
        // wrapping_add: pointers may be null (unused operands).
        TileArgs {
            x: self.x.wrapping_add(rows * (self.k_in + HIDDEN)),
            h: self.h.wrapping_add(rows * self.h_stride),
            pre: if self.pre.is_null() {
                self.pre
            } else {
                self.pre.wrapping_add(rows * self.pre_stride)
            },
            out: self.out.wrapping_add(rows * self.out_stride),
            save: if self.save.is_null() {
                self.save
            } else {
                self.save.wrapping_add(rows * self.save_stride)
            },
            y: if self.fc.is_null() {
                self.y
            } else {
                self.y.wrapping_add(rows * self.y_stride)
            },
            ..*self
        }
    }
}

/// Input indices per weight block of [`run_blocked`]: 64 x 48 f32 = 12 KB,
/// which leaves room in a 32 KB L1 for the streamed inputs and partial sums.
/// Divides the input width (256) so no block straddles the input and
/// recurrent parts.
pub(crate) const KC: usize = 64;

/// Floats of partial sums per row that [`run_blocked`] needs.
pub(crate) const BLOCK_ACC: usize = 4 * crate::fast::pack::LANES;

/// Floats of weight-widening buffer that [`run_blocked`] needs (f16 panels).
pub(crate) const BLOCK_WBUF: usize = KC * crate::fast::pack::ROW;

/// Smallest batch for which [`run_blocked`] beats [`run`], measured with
/// the `gru-step` benchmark on a Zen 3 AVX2 core: already at 2 rows (one
/// tile) it is faster, because its assembly inner loop keeps all 12
/// accumulators in registers where LLVM's `tile2` spills some. Batch 1 keeps
/// the plain kernel, whose 1-row tile unrolls `k` twice.
pub(crate) const BLOCKED_MIN_ROWS: usize = 2;

/// Whether [`run_blocked`] has a blocked kernel for `isa` and is worth it
/// for `rows` rows. AVX-512 tiles already hold 8 rows and its machines have
/// 2 MB of L2, so it keeps the plain kernel (and has not been measured).
pub(crate) fn use_blocked(isa: Isa, rows: usize) -> bool {
    isa == Isa::Avx2 && rows >= BLOCKED_MIN_ROWS
}

/// Largest tile (rows per weight pass) of each instruction set.
pub(crate) fn max_tile(isa: Isa) -> usize {
    match isa {
        Isa::Scalar => 4,
        Isa::Avx2 => 2,
        Isa::Avx512 => 8,
    }
}

/// Pack the inputs of `rows` rows for the kernel: for each tile of
/// `max_tile(isa)` rows (the last may be shorter), `[k][row]` with `k` over
/// the `k_in` values of `input(row)` then the 512 values of `state(row)`.
/// Interleaving the rows of a tile lets the kernel broadcast every row's
/// `x[k]` from one cache line at fixed offsets. `out` must hold
/// `rows * (k_in + 512)` floats.
pub(crate) fn pack_rows<'a>(
    isa: Isa,
    rows: usize,
    k_in: usize,
    input: impl Fn(usize) -> &'a [f32],
    state: impl Fn(usize) -> &'a [f32],
    out: &mut [f32],
) {
    let k_total = k_in + HIDDEN;
    let tile = max_tile(isa);
    assert!(out.len() >= rows * k_total);
    let mut r0 = 0;
    while r0 < rows {
        let n = tile.min(rows - r0);
        let block = &mut out[r0 * k_total..(r0 + n) * k_total];
        for b in 0..n {
            let src_in = &input(r0 + b)[..k_in];
            let src_h = &state(r0 + b)[..HIDDEN];
            for (k, &v) in src_in.iter().chain(src_h).enumerate() {
                block[k * n + b] = v;
            }
        }
        r0 += n;
    }
}

/// As [`run`], blocked over `k` (see the module docs) where [`use_blocked`]
/// says so, else exactly [`run`]. `acc` must hold `rows * BLOCK_ACC` and
/// `wbuf` `BLOCK_WBUF` floats, both 32-byte aligned; their contents on entry
/// do not matter.
///
/// # Safety
/// As [`run`]; in addition `a.k_in` must be a multiple of [`KC`].
pub(crate) unsafe fn run_blocked(
    isa: Isa,
    rows: usize,
    a: &TileArgs,
    acc: &mut [f32],
    wbuf: &mut [f32],
) {
    if !use_blocked(isa, rows) {
        run(isa, rows, a);
        return;
    }
    assert!(acc.len() >= rows * BLOCK_ACC && wbuf.len() >= BLOCK_WBUF);
    assert!(acc.as_ptr().cast::<u8>().align_offset(32) == 0);
    assert!(wbuf.as_ptr().cast::<u8>().align_offset(32) == 0);
    assert!(a.k_in.is_multiple_of(KC));
    #[cfg(target_arch = "x86_64")]
    avx2::run_blocked(rows, a, acc.as_mut_ptr(), wbuf.as_mut_ptr());
    #[cfg(not(target_arch = "x86_64"))]
    unreachable!("blocked kernel without AVX2");
}

/// Run the kernel for `rows` batch rows (any count; split into tiles).
///
/// # Safety
/// `a` must satisfy the [`TileArgs`] contract for `rows` rows, and `isa`
/// must be available on this CPU.
pub(crate) unsafe fn run(isa: Isa, rows: usize, a: &TileArgs) {
    let tile = max_tile(isa);
    let mut done = 0;
    while done < rows {
        let n = tile.min(rows - done);
        let args = a.offset_rows(done);
        match isa {
            Isa::Scalar => scalar::tile(n, &args),
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => avx2::tile(n, &args),
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => avx512::tile(n, &args),
            #[cfg(not(target_arch = "x86_64"))]
            _ => scalar::tile(n, &args),
        }
        done += n;
    }
}

/// Smallest batch the AMX unit runs on tiles; a single row runs on
/// `vdpbf16ps` (its 4-way unrolled 1-row kernel): measured with `gru-step`
/// on the Sapphire Rapids VM, batch 1 ran at 5.8-6.2k frames/s on tiles
/// against 6.8-7.0k on `vdpbf16ps` (f16: 6.6-6.9k), while from 2 rows the
/// tiles are as fast or faster (batch 4: 22.3k against 17.0k). A session
/// stepped alone therefore sums in another order than in a batch (as with
/// the f32 AVX-512 kernels, whose 1-row kernel is unrolled too).
pub(crate) const AMX_MIN_ROWS: usize = 2;

/// Run the bf16 kernel of `unit` for `rows` rows (any count): `a` as for
/// [`run`] except that `a.w` is a paired bf16 panel and `a.x` is unused;
/// row `b`'s bf16 inputs (packed by [`bf16::pack_rows`]) start at
/// `x.add(b * x_stride)`.
///
/// # Safety
/// The [`TileArgs`] contract (but for `x`) for `rows` rows; `x` holds
/// `rows` rows of `a.k_in + 512` values; `unit` is available (for AMX: its
/// `amx::permission` was granted).
pub(crate) unsafe fn run_bf16(
    unit: Bf16Unit,
    rows: usize,
    a: &TileArgs,
    x: *const u16,
    x_stride: usize,
) {
    #[cfg(target_arch = "x86_64")]
    match unit {
        Bf16Unit::Amx if rows >= AMX_MIN_ROWS => amx::run(rows, a, x, x_stride),
        _ => bf16::run(rows, a, x, x_stride),
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (unit, rows, a, x, x_stride);
        unreachable!("bf16 kernels need x86-64");
    }
}
