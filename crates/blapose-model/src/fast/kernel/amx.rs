//! The panel kernel on AMX tiles (`tdpbf16ps`), for CPUs that have them.
//!
//! Why: one `tdpbf16ps` multiplies a 16 x 32 bf16 block of inputs (16
//! batch rows, 32 input indices) by a 32 x 16 block of weights (16 units)
//! into a 16 x 16 f32 tile: 8,192 multiply-adds, against 32 for a
//! `vdpbf16ps`. The GRU step's products then cost a small part of the
//! step, which becomes bound by the epilogue (gates, state update, output
//! layer), shared with the other kernels.
//!
//! A call handles one panel (16 units) for all rows, 16 rows (one *block*)
//! at a time. Tiles: `tmm0..3` accumulate the r, z, input-n and
//! recurrent-n pre-activations of the block, `tmm4` holds the inputs of 32
//! indices (row-major bf16 rows, see [`super::bf16`]) and `tmm5..7` the
//! r, z, n weights of the same 32 indices: in the paired panel layout, a
//! gate's 16 pair rows are 64 bytes each at a stride of 192 bytes, exactly a
//! `B` tile. Finished accumulators go to a 4 KB buffer on the stack and the
//! shared AVX-512 epilogue turns each row into new states and outputs. Each
//! row's sums depend only on that row's inputs, so a session gets the same
//! bits whatever batch it shares.
//!
//! Rust has no stable AMX intrinsics, so the tile instructions are inline
//! assembly. The tile registers are not part of Rust's register model: no
//! compiler-generated code touches them, the asm blocks that use them are
//! volatile (kept in order), and every call configures the tiles itself
//! (`ldtilecfg`) and releases them (`tilerelease`) before returning, so no
//! tile state outlives a call.
//!
//! Linux enables AMX's 8 KB of tile data per process only on request
//! (`arch_prctl(ARCH_REQ_XCOMP_PERM, XFEATURE_XTILEDATA)`); [`permission`]
//! asks once and callers fall back to `vdpbf16ps` when it is refused.

use std::arch::asm;
use std::arch::x86_64::*;
use std::sync::OnceLock;

use super::avx512::epilogue;
use super::TileArgs;
use crate::fast::pack::LANES;
use crate::HIDDEN;

/// Rows per tile block.
pub(crate) const BLOCK: usize = 16;

/// Bytes between the pair rows of one gate in a paired panel (3 gates x 16
/// lanes x 2 bf16).
const W_STRIDE: usize = 192;

/// Bytes of panel per 32 input indices (16 pair rows).
const W_STEP: usize = 16 * W_STRIDE;

/// `arch_prctl` codes (linux/arch/x86/include/uapi/asm/prctl.h) and the
/// XSAVE feature number of the AMX tile data.
#[cfg(target_os = "linux")]
const ARCH_REQ_XCOMP_PERM: libc::c_ulong = 0x1023;
#[cfg(target_os = "linux")]
const XFEATURE_XTILEDATA: libc::c_ulong = 18;

/// Whether this process may use AMX tiles: the CPU has them
/// ([`crate::fast::Bf16Unit::Amx`]) and the OS granted the tile data (asked
/// once per process). `Err` names what is missing.
pub(crate) fn permission() -> Result<(), String> {
    static GRANTED: OnceLock<Result<(), String>> = OnceLock::new();
    GRANTED
        .get_or_init(|| {
            if let Some(missing) = crate::fast::Bf16Unit::Amx.missing_feature() {
                return Err(format!("the CPU lacks {missing}"));
            }
            request_tile_data()
        })
        .clone()
}

#[cfg(target_os = "linux")]
fn request_tile_data() -> Result<(), String> {
    // SAFETY: arch_prctl with ARCH_REQ_XCOMP_PERM only reads its two integer
    // arguments; it changes which XSAVE features this process may use.
    let rc = unsafe {
        libc::syscall(
            libc::SYS_arch_prctl,
            ARCH_REQ_XCOMP_PERM,
            XFEATURE_XTILEDATA,
        )
    };
    if rc == 0 {
        Ok(())
    } else {
        Err(format!(
            "the kernel refused AMX tile data (arch_prctl: {})",
            std::io::Error::last_os_error()
        ))
    }
}

#[cfg(not(target_os = "linux"))]
fn request_tile_data() -> Result<(), String> {
    Err("AMX is only enabled on Linux".into())
}

/// The `ldtilecfg` operand: palette 1, eight tiles of 64 bytes per row;
/// the accumulators (`tmm0..3`) and inputs (`tmm4`) have one row per batch
/// row of the block (a partial last block multiplies only its own rows),
/// the weights (`tmm5..7`) 16 pair rows.
#[repr(C, align(64))]
struct TileConfig([u8; 64]);

impl TileConfig {
    fn new(rows: usize) -> Self {
        let mut c = [0u8; 64];
        c[0] = 1; // palette
        for t in 0..8 {
            c[16 + 2 * t] = 64; // bytes per row (u16, little-endian)
            c[48 + t] = if t < 5 { rows as u8 } else { 16 };
        }
        TileConfig(c)
    }
}

/// Accumulators of one block as stored: `[r | z | n_in | n_h][row][lane]`.
#[repr(C, align(64))]
struct Acc([f32; 4 * BLOCK * LANES]);

macro_rules! tile_load {
    ($t:literal, $ptr:expr, $stride:expr) => {
        asm!(
            concat!("tileloadd tmm", $t, ", [{p} + {s}*1]"),
            p = in(reg) $ptr,
            s = in(reg) $stride,
            options(nostack, readonly, preserves_flags)
        )
    };
}

macro_rules! tile_store {
    ($t:literal, $ptr:expr, $stride:expr) => {
        asm!(
            concat!("tilestored [{p} + {s}*1], tmm", $t),
            p = in(reg) $ptr,
            s = in(reg) $stride,
            options(nostack, preserves_flags)
        )
    };
}

macro_rules! tile_dp {
    ($c:literal, $a:literal, $b:literal) => {
        asm!(
            concat!("tdpbf16ps tmm", $c, ", tmm", $a, ", tmm", $b),
            options(nostack, nomem, preserves_flags)
        )
    };
}

/// Run one panel for `rows` rows: `a` as for the f32 kernels except that
/// `a.w` is a paired bf16 panel and `a.x` is unused; row `b`'s bf16 inputs
/// are at `x.add(b * x_stride)`.
///
/// # Safety
/// The [`TileArgs`] contract (but for `x`) for `rows` rows; `x` as above
/// with `a.k_in + 512` values per row, `a.k_in` a multiple of 32;
/// [`permission`] returned `Ok`.
#[target_feature(enable = "avx512f,avx512bw,avx512bf16,avx2,fma")]
pub(crate) unsafe fn run(rows: usize, a: &TileArgs, x: *const u16, x_stride: usize) {
    let steps_in = a.k_in / 32;
    let steps = (a.k_in + HIDDEN) / 32;
    let xs = x_stride * 2;
    let ws = W_STRIDE;
    let mut acc = Acc([0.0; 4 * BLOCK * LANES]);
    let acc_p = acc.0.as_mut_ptr();
    let cs = LANES * 4; // bytes per accumulator row
    let mut configured = 0;
    let mut r0 = 0;
    while r0 < rows {
        let n = BLOCK.min(rows - r0);
        if n != configured {
            let config = TileConfig::new(n);
            asm!("ldtilecfg [{}]", in(reg) config.0.as_ptr(), options(nostack, readonly, preserves_flags));
            configured = n;
        }
        asm!(
            "tilezero tmm0",
            "tilezero tmm1",
            "tilezero tmm2",
            "tilezero tmm3",
            options(nostack, nomem, preserves_flags)
        );
        let xb = x.add(r0 * x_stride).cast::<u8>();
        let w = a.w;
        for s in 0..steps_in {
            tile_load!(4, xb.add(s * 64), xs);
            let wp = w.add(s * W_STEP);
            tile_load!(5, wp, ws);
            tile_dp!(0, 4, 5);
            tile_load!(6, wp.add(64), ws);
            tile_dp!(1, 4, 6);
            tile_load!(7, wp.add(128), ws);
            tile_dp!(2, 4, 7);
        }
        for s in steps_in..steps {
            tile_load!(4, xb.add(s * 64), xs);
            let wp = w.add(s * W_STEP);
            tile_load!(5, wp, ws);
            tile_dp!(0, 4, 5);
            tile_load!(6, wp.add(64), ws);
            tile_dp!(1, 4, 6);
            tile_load!(7, wp.add(128), ws);
            tile_dp!(3, 4, 7);
        }
        tile_store!(0, acc_p, cs);
        tile_store!(1, acc_p.add(BLOCK * LANES), cs);
        tile_store!(2, acc_p.add(2 * BLOCK * LANES), cs);
        tile_store!(3, acc_p.add(3 * BLOCK * LANES), cs);
        for b in 0..n {
            let row = |g: usize| _mm512_load_ps(acc_p.add((g * BLOCK + b) * LANES));
            let args = a.offset_rows(r0 + b);
            epilogue(&args, &[[row(0), row(1), row(3)]], &[row(2)]);
        }
        r0 += BLOCK;
    }
    asm!("tilerelease", options(nostack, nomem, preserves_flags));
}
