//! Zero-phase smoothing of whole recordings: a Butterworth low-pass run
//! forwards and backwards (as SciPy's `sosfiltfilt`, FreeMoCap's choice),
//! and the Savitzky-Golay filter (a sliding least-squares polynomial, as
//! SciPy's `savgol_filter` with `mode="interp"`); both match SciPy to 1e-7
//! (tested).
//!
//! Offline only: each output reads samples after it. Both keep a straight
//! line (the polynomial exactly, the Butterworth away from the ends, where
//! its odd-extension padding leaves a transient of a few thousandths of
//! the slope), so a steadily moving limb is not pulled back. Hand-written rather than a DSP crate because each is a few dozen
//! lines over the slices the motion stage already holds.

use std::f64::consts::PI;

use nalgebra::{DMatrix, DVector};

/// One second-order section `b0 + b1 z^-1 + b2 z^-2 / 1 + a1 z^-1 + a2 z^-2`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Section {
    b: [f64; 3],
    a: [f64; 2],
}

impl Section {
    /// Run over `x` in place (transposed direct form II), starting from the
    /// steady state of a constant input equal to `x[0]`.
    fn run(&self, x: &mut [f64]) {
        let Some(&x0) = x.first() else { return };
        let [b0, b1, b2] = self.b;
        let [a1, a2] = self.a;
        let mut z2 = (b2 - a2) * x0;
        let mut z1 = (b1 - a1) * x0 + z2;
        for v in x.iter_mut() {
            let input = *v;
            let y = b0 * input + z1;
            z1 = b1 * input - a1 * y + z2;
            z2 = b2 * input - a2 * y;
            *v = y;
        }
    }
}

/// The sections of an even-order Butterworth low-pass (bilinear transform
/// with the cutoff pre-warped), unit gain at rest.
fn butterworth_sections(order: usize, cutoff_hz: f64, rate_hz: f64) -> Vec<Section> {
    let k = (PI * cutoff_hz / rate_hz).tan();
    (1..=order / 2)
        .map(|i| {
            let q = 1.0 / (2.0 * ((2 * i - 1) as f64 * PI / (2 * order) as f64).cos());
            let norm = 1.0 / (1.0 + k / q + k * k);
            let b0 = k * k * norm;
            Section {
                b: [b0, 2.0 * b0, b0],
                a: [2.0 * (k * k - 1.0) * norm, (1.0 - k / q + k * k) * norm],
            }
        })
        .collect()
}

/// A zero-phase Butterworth low-pass of even `order` (2, 4, ...; the
/// effective order doubles, run twice) on one series in place. Short
/// series (under 2 samples) and cutoffs at or above Nyquist are left as
/// they are.
pub fn butterworth_filtfilt(x: &mut [f64], order: usize, cutoff_hz: f64, rate_hz: f64) {
    if x.len() < 2 || order < 2 || cutoff_hz <= 0.0 || cutoff_hz >= rate_hz / 2.0 {
        return;
    }
    let sections = butterworth_sections(order - order % 2, cutoff_hz, rate_hz);
    // Pad both ends with the odd extension (a reflection about the end
    // value) so the transient settles outside the recording.
    let pad = (3 * (2 * sections.len() + 1)).min(x.len() - 1);
    let (first, last) = (x[0], x[x.len() - 1]);
    let mut ext: Vec<f64> = (1..=pad).rev().map(|i| 2.0 * first - x[i]).collect();
    ext.extend_from_slice(x);
    ext.extend((1..=pad).map(|i| 2.0 * last - x[x.len() - 1 - i]));
    for s in &sections {
        s.run(&mut ext);
    }
    ext.reverse();
    for s in &sections {
        s.run(&mut ext);
    }
    ext.reverse();
    x.copy_from_slice(&ext[pad..pad + x.len()]);
}

/// Weights that give the least-squares polynomial of degree `degree`
/// through `window` equally spaced samples, evaluated at sample `at`.
fn savgol_weights(window: usize, degree: usize, at: usize) -> Option<Vec<f64>> {
    let centre = (window - 1) as f64 / 2.0;
    let powers = |i: usize| -> Vec<f64> {
        let u = (i as f64 - centre) / centre.max(1.0);
        (0..=degree).map(|p| u.powi(p as i32)).collect()
    };
    let rows: Vec<Vec<f64>> = (0..window).map(powers).collect();
    let a = DMatrix::from_fn(window, degree + 1, |i, p| rows[i][p]);
    // Weights w_i = powers(at)^T (A^T A)^-1 powers(i).
    let coeffs = (a.transpose() * &a)
        .lu()
        .solve(&DVector::from_vec(powers(at)))?;
    Some(
        rows.iter()
            .map(|r| r.iter().zip(&coeffs).map(|(a, b)| a * b).sum())
            .collect(),
    )
}

/// The Savitzky-Golay filter (odd `window`, polynomial `degree` below it)
/// on one series in place. Interior samples take the polynomial fitted to
/// the window centred on them; the first and last `window / 2` take the
/// one fitted to the first or last full window. Series shorter than the
/// window are fitted as one window when longer than `degree`, else left.
pub fn savitzky_golay(x: &mut [f64], window: usize, degree: usize) {
    let window = window.min(x.len() - x.len().is_multiple_of(2) as usize);
    if window <= degree || window < 3 {
        return;
    }
    let half = window / 2;
    let src = x.to_vec();
    let apply = |w: &[f64], start: usize| -> f64 {
        w.iter()
            .zip(&src[start..start + window])
            .map(|(a, b)| a * b)
            .sum()
    };
    let Some(centre) = savgol_weights(window, degree, half) else {
        return;
    };
    for (t, v) in x.iter_mut().enumerate().take(src.len() - half).skip(half) {
        *v = apply(&centre, t - half);
    }
    for k in 0..half {
        if let Some(w) = savgol_weights(window, degree, k) {
            x[k] = apply(&w, 0);
        }
        if let Some(w) = savgol_weights(window, degree, window - 1 - k) {
            x[src.len() - 1 - k] = apply(&w, src.len() - window);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn butterworth_sections_match_scipy() {
        // scipy.signal.butter(4, 3, fs=50, output="sos"): the product of
        // the sections has the same numerator and denominator.
        let s = butterworth_sections(4, 3.0, 50.0);
        let gain: f64 = s.iter().map(|s| s.b.iter().sum::<f64>()).product();
        let den: f64 = s.iter().map(|s| 1.0 + s.a[0] + s.a[1]).product();
        assert!((gain / den - 1.0).abs() < 1e-12, "unit gain at rest");
        let b0: f64 = s.iter().map(|s| s.b[0]).product();
        assert!((b0 - 8.063598650371017e-4).abs() < 1e-15, "b0 = {b0}");
    }

    /// `sin(0.3 t) + 0.1 cos(2.1 t)`, t = 0..40.
    fn wave() -> Vec<f64> {
        (0..40)
            .map(|t| (t as f64 * 0.3).sin() + 0.1 * (t as f64 * 2.1).cos())
            .collect()
    }

    #[test]
    fn both_match_scipy_on_a_short_series() {
        // scipy.signal.sosfiltfilt(butter(4, 3, fs=50, output="sos"), x) and
        // savgol_filter(x, 11, 3, mode="interp") at t = 0, 3, 20, 39.
        let mut b = wave();
        butterworth_filtfilt(&mut b, 4, 3.0, 50.0);
        let mut s = wave();
        savitzky_golay(&mut s, 11, 3);
        for (i, t) in [0, 3, 20, 39].into_iter().enumerate() {
            let want_b = [0.11368837, 0.701169, -0.2317281, -0.77284568][i];
            let want_s = [0.04140516, 0.76913784, -0.27785025, -0.68171941][i];
            assert!((b[t] - want_b).abs() < 1e-7, "butterworth t={t}: {}", b[t]);
            assert!((s[t] - want_s).abs() < 1e-7, "savgol t={t}: {}", s[t]);
        }
    }

    #[test]
    fn lines_pass_and_noise_is_removed() {
        let line: Vec<f64> = (0..100).map(|t| 0.3 + 0.01 * t as f64).collect();
        let mut b = line.clone();
        butterworth_filtfilt(&mut b, 4, 3.0, 50.0);
        let mut s = line.clone();
        savitzky_golay(&mut s, 31, 3);
        for t in 0..100 {
            // The Butterworth's start-up transient outlasts its padding by
            // a little (as SciPy's does): exact inside, close at the ends.
            let tol = if (35..65).contains(&t) { 1e-4 } else { 3e-3 };
            assert!(
                (b[t] - line[t]).abs() < tol,
                "butterworth {t}: {}",
                b[t] - line[t]
            );
            assert!((s[t] - line[t]).abs() < 1e-9, "savgol {t}");
        }
        let noise: Vec<f64> = (0..200)
            .map(|t| if t % 2 == 0 { 1.0 } else { -1.0 })
            .collect();
        let mut b = noise.clone();
        butterworth_filtfilt(&mut b, 4, 3.0, 50.0);
        assert!(
            b[40..160].iter().all(|v| v.abs() < 1e-3),
            "{:?}",
            &b[40..45]
        );
    }

    #[test]
    fn savgol_weights_match_the_textbook() {
        // Savitzky and Golay's 5-point quadratic smoothing: (-3, 12, 17, 12, -3) / 35.
        let w = savgol_weights(5, 2, 2).unwrap();
        for (got, want) in w.iter().zip([-3.0, 12.0, 17.0, 12.0, -3.0]) {
            assert!((got - want / 35.0).abs() < 1e-12);
        }
    }
}
