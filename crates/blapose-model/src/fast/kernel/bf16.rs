//! The panel kernel on the CPU's bfloat16 units: `vdpbf16ps` (AVX512-BF16)
//! here, AMX tiles in [`super::amx`].
//!
//! Why: with f32 (or f16-stored) weights the batched step is bound by f32
//! FMAs (one multiply per lane per instruction). bf16 dot-product
//! instructions multiply two bf16 pairs per f32 lane (`vdpbf16ps`) or a
//! whole 16 x 32 by 32 x 16 block (AMX `tdpbf16ps`) and accumulate in f32,
//! so the matrix products cost a half (AVX512-BF16) to a small fraction
//! (AMX) of the FMA version, and the weights take half the bytes of f32.
//!
//! What is rounded: the weights (once, when packed) and the products'
//! inputs, i.e. the frame embedding and the previous state, each step, to
//! bf16 (8 significant bits, round to nearest even). Sums, biases, gates,
//! the state update `h' = n + z (h - n)` and the output layer stay f32, so
//! the state itself is never rounded; the accuracy this costs is measured in
//! `crates/blapose-model/README.md` (well inside 0.02 mm of mean bone-length
//! error on Human3.6M, and within 0.1 mm of f32 over 10,000 frames).
//!
//! Inputs are packed row-major in bf16 ([`pack_rows`]): row `b` holds the
//! `k_in` embedding values then the 512 state values at `x + b * k_total`.
//! A pair `(x[2j], x[2j+1])` is one 32-bit word, which `vdpbf16ps` takes
//! broadcast and an AMX `A` tile takes as 16 rows of 64 bytes. The panel
//! is the paired layout of [`crate::fast::pack`].
//!
//! The `vdpbf16ps` kernels mirror the AVX-512 f32 ones (up to 8 rows per
//! weight pass, one row unrolled four ways) and share their epilogue.

use std::arch::x86_64::*;

use super::avx512::epilogue;
use super::TileArgs;
use crate::fast::pack::{LANES, ROW};
use crate::HIDDEN;

/// Rows per `vdpbf16ps` weight pass.
pub(crate) const MAX_TILE: usize = 8;

/// u16 values per input pair step inside a paired panel.
const PAIR: usize = 2 * ROW;

/// Pack the bf16 inputs of `rows` rows: row `b` gets `input(b)[..k_in]`
/// then `state(b)[..512]`, rounded to bf16, at `out[b * (k_in + 512)..]`.
/// Rows at and past `rows` are left as they are.
///
/// # Safety
/// AVX512-BF16 (and AVX-512F/BW) must be available.
#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
pub(crate) unsafe fn pack_rows<'a>(
    rows: usize,
    k_in: usize,
    input: impl Fn(usize) -> &'a [f32],
    state: impl Fn(usize) -> &'a [f32],
    out: &mut [u16],
) {
    let k_total = k_in + HIDDEN;
    assert!(out.len() >= rows * k_total);
    assert!(k_in.is_multiple_of(32));
    for b in 0..rows {
        let dst = &mut out[b * k_total..(b + 1) * k_total];
        let src_in = &input(b)[..k_in];
        let src_h = &state(b)[..HIDDEN];
        let (d_in, d_h) = dst.split_at_mut(k_in);
        convert(src_in, d_in);
        convert(src_h, d_h);
    }
}

/// `dst = bf16(src)` (round to nearest even), lengths multiples of 32.
#[inline]
#[target_feature(enable = "avx512f,avx512bw,avx512bf16")]
fn convert(src: &[f32], dst: &mut [u16]) {
    assert_eq!(src.len(), dst.len());
    for (s, d) in src.chunks_exact(32).zip(dst.chunks_exact_mut(32)) {
        // SAFETY: each chunk holds 32 values; unaligned loads and stores.
        unsafe {
            let lo = _mm512_loadu_ps(s.as_ptr());
            let hi = _mm512_loadu_ps(s.as_ptr().add(16));
            let v: __m512i = std::mem::transmute(_mm512_cvtne2ps_pbh(hi, lo));
            _mm512_storeu_si512(d.as_mut_ptr().cast(), v);
        }
    }
}

/// 32 bf16 weights (one gate row of a pair step).
macro_rules! ld_w {
    ($p:expr) => {
        std::mem::transmute::<__m512i, __m512bh>(_mm512_load_si512($p as *const __m512i))
    };
}

/// A broadcast input pair.
macro_rules! ld_x {
    ($p:expr) => {
        std::mem::transmute::<__m512i, __m512bh>(_mm512_set1_epi32(
            ($p as *const i32).read_unaligned(),
        ))
    };
}

/// Kernel for `rows <= 8` rows with `vdpbf16ps`: `a` as for the f32
/// kernels except that `a.w` is a paired bf16 panel and `a.x` is unused;
/// row `b`'s bf16 inputs are at `x.add(b * x_stride)`.
///
/// # Safety
/// The [`TileArgs`] contract (but for `x`) for `rows` rows, `x` rows of
/// `a.k_in + 512` values, AVX512-BF16 available.
pub(crate) unsafe fn tile(rows: usize, a: &TileArgs, x: *const u16, x_stride: usize) {
    match rows {
        1 => tile1(a, x),
        2 => tile2(a, x, x_stride),
        3 => tile3(a, x, x_stride),
        4 => tile4(a, x, x_stride),
        5 => tile5(a, x, x_stride),
        6 => tile6(a, x, x_stride),
        7 => tile7(a, x, x_stride),
        8 => tile8(a, x, x_stride),
        _ => unreachable!("bf16 tile of {rows} rows"),
    }
}

/// All rows, tile by tile.
///
/// # Safety
/// As [`tile`] for `rows` rows.
pub(crate) unsafe fn run(rows: usize, a: &TileArgs, x: *const u16, x_stride: usize) {
    let mut done = 0;
    while done < rows {
        let n = MAX_TILE.min(rows - done);
        tile(n, &a.offset_rows(done), x.add(done * x_stride), x_stride);
        done += n;
    }
}

/// A kernel for a fixed number of rows; each `(r, z, n, b)` names row `b`'s
/// accumulators.
macro_rules! tile_fn {
    ($name:ident, $(($r:ident, $z:ident, $n:ident, $b:expr)),+) => {
        #[target_feature(enable = "avx512f,avx512bw,avx512bf16,avx2,fma")]
        unsafe fn $name(a: &TileArgs, x: *const u16, xs: usize) {
            let zero = _mm512_setzero_ps();
            $(let mut $r = zero; let mut $z = zero; let mut $n = zero;)+
            let mut w = a.w as *const u16;
            let mut xp = x;
            for _ in 0..a.k_in / 2 {
                let wr = ld_w!(w);
                let wz = ld_w!(w.add(2 * LANES));
                let wn = ld_w!(w.add(4 * LANES));
                $(
                    let xv = ld_x!(xp.add($b * xs));
                    $r = _mm512_dpbf16_ps($r, wr, xv);
                    $z = _mm512_dpbf16_ps($z, wz, xv);
                    $n = _mm512_dpbf16_ps($n, wn, xv);
                )+
                w = w.add(PAIR);
                xp = xp.add(2);
            }
            let ni = [$($n),+];
            $($n = zero;)+
            for _ in 0..HIDDEN / 2 {
                let wr = ld_w!(w);
                let wz = ld_w!(w.add(2 * LANES));
                let wn = ld_w!(w.add(4 * LANES));
                $(
                    let xv = ld_x!(xp.add($b * xs));
                    $r = _mm512_dpbf16_ps($r, wr, xv);
                    $z = _mm512_dpbf16_ps($z, wz, xv);
                    $n = _mm512_dpbf16_ps($n, wn, xv);
                )+
                w = w.add(PAIR);
                xp = xp.add(2);
            }
            epilogue(a, &[$([$r, $z, $n]),+], &ni);
        }
    };
}

tile_fn!(tile2, (r0, z0, n0, 0), (r1, z1, n1, 1));
tile_fn!(tile3, (r0, z0, n0, 0), (r1, z1, n1, 1), (r2, z2, n2, 2));
tile_fn!(
    tile4,
    (r0, z0, n0, 0),
    (r1, z1, n1, 1),
    (r2, z2, n2, 2),
    (r3, z3, n3, 3)
);
tile_fn!(
    tile5,
    (r0, z0, n0, 0),
    (r1, z1, n1, 1),
    (r2, z2, n2, 2),
    (r3, z3, n3, 3),
    (r4, z4, n4, 4)
);
tile_fn!(
    tile6,
    (r0, z0, n0, 0),
    (r1, z1, n1, 1),
    (r2, z2, n2, 2),
    (r3, z3, n3, 3),
    (r4, z4, n4, 4),
    (r5, z5, n5, 5)
);
tile_fn!(
    tile7,
    (r0, z0, n0, 0),
    (r1, z1, n1, 1),
    (r2, z2, n2, 2),
    (r3, z3, n3, 3),
    (r4, z4, n4, 4),
    (r5, z5, n5, 5),
    (r6, z6, n6, 6)
);
tile_fn!(
    tile8,
    (r0, z0, n0, 0),
    (r1, z1, n1, 1),
    (r2, z2, n2, 2),
    (r3, z3, n3, 3),
    (r4, z4, n4, 4),
    (r5, z5, n5, 5),
    (r6, z6, n6, 6),
    (r7, z7, n7, 7)
);

/// One row, pair steps unrolled four ways (12 independent accumulators, so
/// the `vdpbf16ps` latency does not serialize the loop).
#[target_feature(enable = "avx512f,avx512bw,avx512bf16,avx2,fma")]
unsafe fn tile1(a: &TileArgs, x: *const u16) {
    let zero = _mm512_setzero_ps();
    let mut acc = [[zero; 3]; 4];
    let mut w = a.w as *const u16;
    let mut xp = x;
    let mut ni = zero;
    for (phase, len) in [a.k_in, HIDDEN].into_iter().enumerate() {
        let (mut r0, mut z0, mut n0) = (acc[0][0], acc[0][1], acc[0][2]);
        let (mut r1, mut z1, mut n1) = (acc[1][0], acc[1][1], acc[1][2]);
        let (mut r2, mut z2, mut n2) = (acc[2][0], acc[2][1], acc[2][2]);
        let (mut r3, mut z3, mut n3) = (acc[3][0], acc[3][1], acc[3][2]);
        macro_rules! step {
            ($r:ident, $z:ident, $n:ident, $u:expr) => {
                let xv = ld_x!(xp.add(2 * $u));
                let wu = w.add($u * PAIR);
                $r = _mm512_dpbf16_ps($r, ld_w!(wu), xv);
                $z = _mm512_dpbf16_ps($z, ld_w!(wu.add(2 * LANES)), xv);
                $n = _mm512_dpbf16_ps($n, ld_w!(wu.add(4 * LANES)), xv);
            };
        }
        // k_in and HIDDEN are multiples of 8: len / 8 groups of 4 pairs
        for _ in 0..len / 8 {
            step!(r0, z0, n0, 0);
            step!(r1, z1, n1, 1);
            step!(r2, z2, n2, 2);
            step!(r3, z3, n3, 3);
            w = w.add(4 * PAIR);
            xp = xp.add(8);
        }
        acc = [[r0, z0, n0], [r1, z1, n1], [r2, z2, n2], [r3, z3, n3]];
        if phase == 0 {
            for part in &mut acc {
                ni = _mm512_add_ps(ni, part[2]);
                part[2] = zero;
            }
        }
    }
    let mut g = acc[0];
    for part in &acc[1..] {
        for (gi, pi) in g.iter_mut().zip(part) {
            *gi = _mm512_add_ps(*gi, *pi);
        }
    }
    epilogue(a, &[g], &[ni]);
}
