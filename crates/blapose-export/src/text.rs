//! Fixed-point number formatting for the text formats, several times faster
//! than `format!("{:.6}")` (which goes through the exact float printer):
//! a 10,000-frame BVH holds 660,000 numbers.

/// Append `x` with `decimals` digits after the point (rounded half away
/// from zero). For `|x| * 10^decimals` beyond 9e15 it falls back to the
/// float printer.
pub fn push_fixed(out: &mut String, x: f64, decimals: usize) {
    const POW: [f64; 10] = [1.0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9];
    let scaled = POW.get(decimals).map_or(f64::INFINITY, |p| (x * p).round());
    if scaled.is_nan() || scaled.abs() >= 9e15 {
        use std::fmt::Write as _;
        write!(out, "{x:.decimals$}").expect("string");
        return;
    }
    let n = scaled as i64;
    if n < 0 || (n == 0 && x.is_sign_negative() && x != 0.0) {
        out.push('-');
    }
    let n = n.unsigned_abs();
    let unit = POW[decimals] as u64;
    push_u64(out, n / unit);
    if decimals > 0 {
        out.push('.');
        let frac = n % unit;
        let digits = if frac == 0 {
            1
        } else {
            frac.ilog10() as usize + 1
        };
        out.extend(std::iter::repeat_n('0', decimals - digits));
        push_u64(out, frac);
    }
}

fn push_u64(out: &mut String, mut n: u64) {
    let mut buf = [0u8; 20];
    let mut i = buf.len();
    loop {
        i -= 1;
        buf[i] = b'0' + (n % 10) as u8;
        n /= 10;
        if n == 0 {
            break;
        }
    }
    out.push_str(std::str::from_utf8(&buf[i..]).expect("digits"));
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fixed(x: f64, d: usize) -> String {
        let mut s = String::new();
        push_fixed(&mut s, x, d);
        s
    }

    #[test]
    fn matches_the_float_printer() {
        for x in [
            0.0,
            1.0,
            -1.5,
            0.000_123,
            -0.000_000_4,
            123.456_789_4,
            -720.000_000_6,
            1e-9,
            5e9,
            0.1 + 0.2,
        ] {
            for d in [0, 4, 6] {
                assert_eq!(
                    fixed(x, d).parse::<f64>().unwrap(),
                    format!("{x:.d$}").parse::<f64>().unwrap(),
                    "{x} {d}"
                );
            }
        }
        assert_eq!(fixed(-0.000_000_4, 6), "-0.000000");
        assert_eq!(fixed(12.5, 0), "13");
        assert_eq!(fixed(-3.000_05, 4), "-3.0001");
        assert_eq!(fixed(1e300, 4), format!("{:.4}", 1e300));
    }
}
