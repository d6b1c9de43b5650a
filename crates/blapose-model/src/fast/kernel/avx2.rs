//! AVX2 + FMA version of the panel kernel: a panel's 16 units are two `ymm`
//! per gate, so a row needs six accumulators; with 16 registers a tile holds
//! at most two rows, and a single row unrolls `k` twice to hide latency.
//! As in the AVX-512 kernel, accumulators are separate variables (an array
//! indexed in loops was kept in memory by LLVM).

use std::arch::x86_64::*;

use super::TileArgs;
use crate::fast::math::avx2::{sigmoid, tanh};
use crate::fast::pack::{LANES, ROW};
use crate::{HIDDEN, OUTPUT_DIM};

/// Kernel for `rows <= 2` rows.
///
/// # Safety
/// See the [`TileArgs`] contract; AVX2 and FMA must be available.
pub(crate) unsafe fn tile(rows: usize, a: &TileArgs) {
    match (rows, a.half) {
        (1, false) => tile1(a),
        (2, false) => tile2(a),
        (1, true) => tile1_h(a),
        (2, true) => tile2_h(a),
        _ => unreachable!("tile of {rows} rows"),
    }
}

/// 8 f32 weights.
macro_rules! ld_f32 {
    ($p:expr) => {
        _mm256_load_ps($p)
    };
}

/// 8 f16 weights, widened to f32.
macro_rules! ld_f16 {
    ($p:expr) => {
        _mm256_cvtph_ps(_mm_load_si128($p as *const __m128i))
    };
}

/// Accumulate `len` values of `k` into the named per-"slot" accumulators;
/// each slot is `(r_lo, r_hi, z_lo, z_hi, n_lo, n_hi, x offset, w offset)`.
/// `x` advances by `$xstep` and `w` by `$wstep` rows per iteration.
macro_rules! accumulate {
    ($ld:ident, $w:ident, $x:ident, $len:expr, $xstep:expr, $wstep:expr,
     $(($rl:ident, $rh:ident, $zl:ident, $zh:ident, $nl:ident, $nh:ident, $xo:expr, $wo:expr)),+) => {
        for _ in 0..$len {
            $(
                let xv = _mm256_set1_ps(*$x.add($xo));
                let wp = $w.add($wo * ROW);
                $rl = _mm256_fmadd_ps($ld!(wp), xv, $rl);
                $rh = _mm256_fmadd_ps($ld!(wp.add(8)), xv, $rh);
                $zl = _mm256_fmadd_ps($ld!(wp.add(LANES)), xv, $zl);
                $zh = _mm256_fmadd_ps($ld!(wp.add(LANES + 8)), xv, $zh);
                $nl = _mm256_fmadd_ps($ld!(wp.add(2 * LANES)), xv, $nl);
                $nh = _mm256_fmadd_ps($ld!(wp.add(2 * LANES + 8)), xv, $nh);
            )+
            $w = $w.add($wstep * ROW);
            $x = $x.add($xstep);
        }
    };
}

/// Two rows, one `k` per iteration.
macro_rules! tile2_fn {
    ($name:ident, $ld:ident, $ty:ty) => {
        #[target_feature(enable = "avx2,fma,f16c")]
        unsafe fn $name(a: &TileArgs) {
            let zero = _mm256_setzero_ps();
            let (mut ar0, mut br0, mut az0, mut bz0, mut an0, mut bn0) =
                (zero, zero, zero, zero, zero, zero);
            let (mut ar1, mut br1, mut az1, mut bz1, mut an1, mut bn1) =
                (zero, zero, zero, zero, zero, zero);
            let mut w = a.w as *const $ty;
            let mut x = a.x;
            accumulate!(
                $ld,
                w,
                x,
                a.k_in,
                2,
                1,
                (ar0, br0, az0, bz0, an0, bn0, 0, 0),
                (ar1, br1, az1, bz1, an1, bn1, 1, 0)
            );
            let ni = [[an0, bn0], [an1, bn1]];
            (an0, bn0, an1, bn1) = (zero, zero, zero, zero);
            accumulate!(
                $ld,
                w,
                x,
                HIDDEN,
                2,
                1,
                (ar0, br0, az0, bz0, an0, bn0, 0, 0),
                (ar1, br1, az1, bz1, an1, bn1, 1, 0)
            );
            let acc = [
                [[ar0, br0], [az0, bz0], [an0, bn0]],
                [[ar1, br1], [az1, bz1], [an1, bn1]],
            ];
            epilogue(a, &acc, &ni);
        }
    };
}

/// One row, `k` unrolled twice (12 independent accumulators).
macro_rules! tile1_fn {
    ($name:ident, $ld:ident, $ty:ty) => {
        #[target_feature(enable = "avx2,fma,f16c")]
        unsafe fn $name(a: &TileArgs) {
            let zero = _mm256_setzero_ps();
            let (mut ar0, mut br0, mut az0, mut bz0, mut an0, mut bn0) =
                (zero, zero, zero, zero, zero, zero);
            let (mut ar1, mut br1, mut az1, mut bz1, mut an1, mut bn1) =
                (zero, zero, zero, zero, zero, zero);
            let mut w = a.w as *const $ty;
            let mut x = a.x;
            // k_in and HIDDEN are even
            accumulate!(
                $ld,
                w,
                x,
                a.k_in / 2,
                2,
                2,
                (ar0, br0, az0, bz0, an0, bn0, 0, 0),
                (ar1, br1, az1, bz1, an1, bn1, 1, 1)
            );
            let ni = [[_mm256_add_ps(an0, an1), _mm256_add_ps(bn0, bn1)]];
            (an0, bn0, an1, bn1) = (zero, zero, zero, zero);
            accumulate!(
                $ld,
                w,
                x,
                HIDDEN / 2,
                2,
                2,
                (ar0, br0, az0, bz0, an0, bn0, 0, 0),
                (ar1, br1, az1, bz1, an1, bn1, 1, 1)
            );
            let acc = [[
                [_mm256_add_ps(ar0, ar1), _mm256_add_ps(br0, br1)],
                [_mm256_add_ps(az0, az1), _mm256_add_ps(bz0, bz1)],
                [_mm256_add_ps(an0, an1), _mm256_add_ps(bn0, bn1)],
            ]];
            epilogue(a, &acc, &ni);
        }
    };
}

tile2_fn!(tile2, ld_f32, f32);
tile2_fn!(tile2_h, ld_f16, u16);
tile1_fn!(tile1, ld_f32, f32);
tile1_fn!(tile1_h, ld_f16, u16);

/// Gates -> new states (and output contributions) for each row:
/// `acc[b][gate][half]` pre-activations without biases (`gate` 2 is the
/// recurrent part of `n`), `ni[b][half]` the input part of `n`.
#[inline]
#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn epilogue<const BT: usize>(
    a: &TileArgs,
    acc: &[[[__m256; 2]; 3]; BT],
    ni: &[[__m256; 2]; BT],
) {
    for b in 0..BT {
        let mut h_new = [_mm256_setzero_ps(); 2];
        for half in 0..2 {
            let g = [acc[b][0][half], acc[b][1][half], acc[b][2][half]];
            let lane = |gate: usize| gate * LANES + half * 8;
            let mut pr = _mm256_add_ps(g[0], _mm256_loadu_ps(a.bias.add(lane(0))));
            let mut pz = _mm256_add_ps(g[1], _mm256_loadu_ps(a.bias.add(lane(1))));
            let mut pn = _mm256_add_ps(ni[b][half], _mm256_loadu_ps(a.bias.add(lane(2))));
            let nh = _mm256_add_ps(g[2], _mm256_loadu_ps(a.bias.add(lane(3))));
            if !a.pre.is_null() {
                let pre = a.pre.add(b * a.pre_stride + a.unit0 + half * 8);
                pr = _mm256_add_ps(pr, _mm256_loadu_ps(pre));
                pz = _mm256_add_ps(pz, _mm256_loadu_ps(pre.add(HIDDEN)));
                pn = _mm256_add_ps(pn, _mm256_loadu_ps(pre.add(2 * HIDDEN)));
            }
            let r = sigmoid(pr);
            let z = sigmoid(pz);
            let n = tanh(_mm256_fmadd_ps(r, nh, pn));
            let h_old = _mm256_loadu_ps(a.h.add(b * a.h_stride + a.unit0 + half * 8));
            h_new[half] = _mm256_fmadd_ps(z, _mm256_sub_ps(h_old, n), n);
            _mm256_storeu_ps(a.out.add(b * a.out_stride + half * 8), h_new[half]);
            if !a.save.is_null() {
                let s = a.save.add(b * a.save_stride + a.unit0 + half * 8);
                _mm256_storeu_ps(s, r);
                _mm256_storeu_ps(s.add(HIDDEN), z);
                _mm256_storeu_ps(s.add(2 * HIDDEN), n);
                _mm256_storeu_ps(s.add(3 * HIDDEN), nh);
            }
        }
        if !a.fc.is_null() {
            let mut s = [0.0f32; LANES];
            _mm256_storeu_ps(s.as_mut_ptr(), sigmoid(h_new[0]));
            _mm256_storeu_ps(s.as_mut_ptr().add(8), sigmoid(h_new[1]));
            let y = a.y.add(b * a.y_stride);
            let mut y0 = _mm256_loadu_ps(y);
            let mut y1 = _mm256_loadu_ps(y.add(8));
            for (u, &su) in s.iter().enumerate() {
                let sv = _mm256_set1_ps(su);
                let row = a.fc.add(u * OUTPUT_DIM);
                y0 = _mm256_fmadd_ps(sv, _mm256_load_ps(row), y0);
                y1 = _mm256_fmadd_ps(sv, _mm256_load_ps(row.add(8)), y1);
            }
            _mm256_storeu_ps(y, y0);
            _mm256_storeu_ps(y.add(8), y1);
        }
    }
}

/// Load (or zero) the partial sums of one row of a blocked tile.
macro_rules! load_sums {
    ($r:expr, $row:expr) => {{
        let row = $r.acc.add($row * ACC);
        let (rz, n) = if $r.fresh_rz {
            (None, None)
        } else {
            (Some(row), Some(row.add($r.n_slot)))
        };
        let n = if $r.fresh_n { None } else { n };
        let ld = |p: Option<*mut f32>, off: usize| match p {
            Some(p) => _mm256_load_ps(p.add(off)),
            None => _mm256_setzero_ps(),
        };
        [
            ld(rz, 0),
            ld(rz, 8),
            ld(rz.map(|p| p.add(LANES)), 0),
            ld(rz.map(|p| p.add(LANES)), 8),
            ld(n, 0),
            ld(n, 8),
        ]
    }};
}

/// Store the partial sums of one row of a blocked tile.
#[inline]
#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn store_sums(r: &BlockRange, row: usize, s: [__m256; 6]) {
    let p = r.acc.add(row * ACC);
    _mm256_store_ps(p, s[0]);
    _mm256_store_ps(p.add(8), s[1]);
    _mm256_store_ps(p.add(LANES), s[2]);
    _mm256_store_ps(p.add(LANES + 8), s[3]);
    _mm256_store_ps(p.add(r.n_slot), s[4]);
    _mm256_store_ps(p.add(r.n_slot + 8), s[5]);
}

/// A `k` range of one row (the odd row of an odd batch).
#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn block1(r: &BlockRange) {
    let [mut ar, mut br, mut az, mut bz, mut an, mut bn] = load_sums!(r, 0);
    let mut w = r.w;
    let mut x = r.x;
    accumulate!(ld_f32, w, x, r.len, 1, 1, (ar, br, az, bz, an, bn, 0, 0));
    store_sums(r, 0, [ar, br, az, bz, an, bn]);
}

/// A `k` range of a 2-row tile: 12 accumulators, 2 broadcasts and 2 weight
/// registers use all 16 `ymm` registers. Written in assembly because LLVM
/// hoisted all six weight loads of a `k` ahead of the FMAs, ran out of
/// registers and spilled accumulators to the stack inside the loop (the
/// plain kernel's `tile2` has the same problem, but there the loop waits on
/// L2 anyway).
#[target_feature(enable = "avx2,fma,f16c")]
unsafe fn block2(r: &BlockRange) {
    let [mut a0, mut a1, mut a2, mut a3, mut a4, mut a5] = load_sums!(r, 0);
    let [mut b0, mut b1, mut b2, mut b3, mut b4, mut b5] = load_sums!(r, 1);
    // the loop handles two `k` per iteration
    assert!(r.len > 0 && r.len.is_multiple_of(2));
    // SAFETY (caller): `w` holds `len` aligned rows of 48 floats and `x`
    // `len` pairs of inputs; the loop reads nothing else and writes no memory.
    std::arch::asm!(
        "2:",
        "vbroadcastss {x0}, dword ptr [{x}]",
        "vbroadcastss {x1}, dword ptr [{x} + 4]",
        "vmovaps {w0}, ymmword ptr [{w}]",
        "vfmadd231ps {a0}, {w0}, {x0}",
        "vfmadd231ps {b0}, {w0}, {x1}",
        "vmovaps {w1}, ymmword ptr [{w} + 32]",
        "vfmadd231ps {a1}, {w1}, {x0}",
        "vfmadd231ps {b1}, {w1}, {x1}",
        "vmovaps {w0}, ymmword ptr [{w} + 64]",
        "vfmadd231ps {a2}, {w0}, {x0}",
        "vfmadd231ps {b2}, {w0}, {x1}",
        "vmovaps {w1}, ymmword ptr [{w} + 96]",
        "vfmadd231ps {a3}, {w1}, {x0}",
        "vfmadd231ps {b3}, {w1}, {x1}",
        "vmovaps {w0}, ymmword ptr [{w} + 128]",
        "vfmadd231ps {a4}, {w0}, {x0}",
        "vfmadd231ps {b4}, {w0}, {x1}",
        "vmovaps {w1}, ymmword ptr [{w} + 160]",
        "vfmadd231ps {a5}, {w1}, {x0}",
        "vfmadd231ps {b5}, {w1}, {x1}",
        "vbroadcastss {x0}, dword ptr [{x} + 8]",
        "vbroadcastss {x1}, dword ptr [{x} + 12]",
        "vmovaps {w0}, ymmword ptr [{w} + 192]",
        "vfmadd231ps {a0}, {w0}, {x0}",
        "vfmadd231ps {b0}, {w0}, {x1}",
        "vmovaps {w1}, ymmword ptr [{w} + 224]",
        "vfmadd231ps {a1}, {w1}, {x0}",
        "vfmadd231ps {b1}, {w1}, {x1}",
        "vmovaps {w0}, ymmword ptr [{w} + 256]",
        "vfmadd231ps {a2}, {w0}, {x0}",
        "vfmadd231ps {b2}, {w0}, {x1}",
        "vmovaps {w1}, ymmword ptr [{w} + 288]",
        "vfmadd231ps {a3}, {w1}, {x0}",
        "vfmadd231ps {b3}, {w1}, {x1}",
        "vmovaps {w0}, ymmword ptr [{w} + 320]",
        "vfmadd231ps {a4}, {w0}, {x0}",
        "vfmadd231ps {b4}, {w0}, {x1}",
        "vmovaps {w1}, ymmword ptr [{w} + 352]",
        "vfmadd231ps {a5}, {w1}, {x0}",
        "vfmadd231ps {b5}, {w1}, {x1}",
        "add {w}, 384",
        "add {x}, 16",
        "sub {n}, 2",
        "jnz 2b",
        w = inout(reg) r.w => _,
        x = inout(reg) r.x => _,
        n = inout(reg) r.len => _,
        a0 = inout(ymm_reg) a0,
        a1 = inout(ymm_reg) a1,
        a2 = inout(ymm_reg) a2,
        a3 = inout(ymm_reg) a3,
        a4 = inout(ymm_reg) a4,
        a5 = inout(ymm_reg) a5,
        b0 = inout(ymm_reg) b0,
        b1 = inout(ymm_reg) b1,
        b2 = inout(ymm_reg) b2,
        b3 = inout(ymm_reg) b3,
        b4 = inout(ymm_reg) b4,
        b5 = inout(ymm_reg) b5,
        x0 = out(ymm_reg) _,
        x1 = out(ymm_reg) _,
        w0 = out(ymm_reg) _,
        w1 = out(ymm_reg) _,
        options(nostack, readonly),
    );
    store_sums(r, 0, [a0, a1, a2, a3, a4, a5]);
    store_sums(r, 1, [b0, b1, b2, b3, b4, b5]);
}

/// Operands of one `k` range of one tile in the blocked kernel.
struct BlockRange {
    /// f32 weights of the range, `[k][48]`, 32-byte aligned.
    w: *const f32,
    /// The tile's packed inputs at the range's first `k`.
    x: *const f32,
    len: usize,
    /// The tile's partial sums, [`ACC`] floats per row, 32-byte aligned.
    acc: *mut f32,
    /// Offset of the `n` sums this range adds to (`N_H` or `N_I`).
    n_slot: usize,
    /// Whether this is the first range of the r/z sums (start from zero).
    fresh_rz: bool,
    /// Whether this is the first range of its `n` sums.
    fresh_n: bool,
}

/// Floats of partial sums per row in the blocked kernel:
/// `[r | z | n recurrent | n input]` x 16 lanes.
const ACC: usize = super::BLOCK_ACC;
const N_H: usize = 2 * LANES;
const N_I: usize = 3 * LANES;

/// The panel for `rows` rows with cache blocking over `k`: the panel is
/// cut into blocks of [`super::KC`] input indices (12 KB of f32), and each
/// block is applied to every tile of rows while it stays in L1, the partial
/// sums of all rows living in `acc` (`rows * ACC` floats, 32-byte aligned).
/// f16 panels are widened block by block into `wbuf` (`KC * 48` floats,
/// 32-byte aligned) first, so the inner loop is the f32 one. The epilogue is
/// the same as the unblocked kernel's.
///
/// # Safety
/// See the [`TileArgs`] contract (inputs packed by `pack_rows` for
/// [`super::Isa::Avx2`]); `k_in` must be a multiple of `KC`; `acc` and
/// `wbuf` as above; AVX2, FMA and F16C must be available.
#[target_feature(enable = "avx2,fma,f16c")]
pub(crate) unsafe fn run_blocked(rows: usize, a: &TileArgs, acc: *mut f32, wbuf: *mut f32) {
    const TILE: usize = 2;
    let kc = super::KC;
    let k_total = a.k_in + HIDDEN;
    debug_assert!(a.k_in.is_multiple_of(kc));
    let mut k0 = 0;
    while k0 < k_total {
        let len = kc.min(k_total - k0);
        let w = if a.half {
            let src = a.w.cast::<u16>().add(k0 * ROW);
            for i in (0..len * ROW).step_by(8) {
                let v = _mm256_cvtph_ps(_mm_load_si128(src.add(i).cast()));
                _mm256_store_ps(wbuf.add(i), v);
            }
            wbuf.cast_const()
        } else {
            a.w.cast::<f32>().add(k0 * ROW)
        };
        let input = k0 < a.k_in;
        let mut r0 = 0;
        while r0 < rows {
            let n = TILE.min(rows - r0);
            let range = BlockRange {
                w,
                x: a.x.add(r0 * k_total + k0 * n),
                len,
                acc: acc.add(r0 * ACC),
                n_slot: if input { N_I } else { N_H },
                fresh_rz: k0 == 0,
                fresh_n: k0 == 0 || k0 == a.k_in,
            };
            if n == TILE {
                block2(&range);
            } else {
                block1(&range);
            }
            r0 += n;
        }
        k0 += len;
    }
    // The unblocked kernel's epilogue, on the sums loaded back from `acc`.
    let zero = _mm256_setzero_ps();
    let sums = |b: usize, off: usize| -> [__m256; 2] {
        let p = acc.add(b * ACC + off);
        [_mm256_load_ps(p), _mm256_load_ps(p.add(8))]
    };
    let mut r0 = 0;
    while r0 < rows {
        let n = TILE.min(rows - r0);
        let args = a.offset_rows(r0);
        let row = |b: usize| {
            let ni = if a.k_in == 0 {
                [zero; 2]
            } else {
                sums(r0 + b, N_I)
            };
            (
                [sums(r0 + b, 0), sums(r0 + b, LANES), sums(r0 + b, N_H)],
                ni,
            )
        };
        if n == TILE {
            let ((g0, ni0), (g1, ni1)) = (row(0), row(1));
            epilogue(&args, &[g0, g1], &[ni0, ni1]);
        } else {
            let (g0, ni0) = row(0);
            epilogue(&args, &[g0], &[ni0]);
        }
        r0 += n;
    }
}
