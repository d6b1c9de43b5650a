//! A model's estimate combined with a known stature: does the 2D stream
//! add anything to what the person's height already says?
//!
//! Why: given the height, the stature regression
//! ([`blapose_train::stature`])
//! already knows most of a person's absolute size; what video can add is
//! the *proportions* for that height (and, with a calibration, a second
//! reading of the size). The simplest honest way to find out is to let
//! data decide how much to trust each: per bone, ordinary least squares
//!
//! `length_b = a_b + s_b * stature + g_b * estimate_b`
//!
//! where `estimate_b` is the model's reading. If the model carries no
//! information beyond the height, `g_b` comes out near 0 and the answer is
//! the stature regression; if it does, the fit uses it.
//!
//! **Fitted on training data only.** The many-bodies benchmark
//! ([`crate::bodies`]) fits it on a *fit set* built like the benchmark but
//! from the ANSUR training split's people on the *training* subjects'
//! motion ([`crate::bodies::FitSet`]), then applies it to the held-out
//! individuals: rows `input: "height"` (the calibration-free model) and
//! `"calibration+height"` (the camera-aware model).

use blapose_core::skeleton::NUM_BONES;
use blapose_core::BoneLengths;

use blapose_train::TrainError;

/// One least-squares plane per bone over (stature, the model's estimate).
#[derive(Debug, Clone, PartialEq)]
pub struct HeightFusion {
    /// Per bone, metres.
    pub intercept: [f64; NUM_BONES],
    /// Per bone, metres of bone per metre of stature.
    pub stature_slope: [f64; NUM_BONES],
    /// Per bone, weight of the model's estimate of that bone.
    pub estimate_weight: [f64; NUM_BONES],
    /// People the planes were fitted on.
    pub people: usize,
}

/// One person of a fit: stature (m), the model's estimate, the truth.
pub type FitSample = (f64, BoneLengths, BoneLengths);

impl HeightFusion {
    /// Fit on `samples`. Fewer than three people, a non-finite value, no
    /// spread in stature, or a model estimate that is (nearly) a linear
    /// function of stature for some bone is a [`TrainError`].
    pub fn fit(samples: &[FitSample]) -> Result<Self, TrainError> {
        let n = samples.len();
        if n < 3 {
            return Err(TrainError::InvalidArgument(format!(
                "height fusion: {n} people; at least 3 are needed"
            )));
        }
        if samples
            .iter()
            .any(|(h, e, t)| !h.is_finite() || e.iter().chain(t).any(|v| !v.is_finite()))
        {
            return Err(TrainError::InvalidArgument(
                "height fusion: a non-finite stature, estimate or length".into(),
            ));
        }
        let nf = n as f64;
        let mean = |f: &dyn Fn(&FitSample) -> f64| samples.iter().map(f).sum::<f64>() / nf;
        let mh = mean(&|s| s.0);
        let mut fit = Self {
            intercept: [0.0; NUM_BONES],
            stature_slope: [0.0; NUM_BONES],
            estimate_weight: [0.0; NUM_BONES],
            people: n,
        };
        for b in 0..NUM_BONES {
            let me = mean(&|s| f64::from(s.1[b]));
            let mt = mean(&|s| f64::from(s.2[b]));
            let (mut shh, mut see, mut she, mut sht, mut set) = (0.0, 0.0, 0.0, 0.0, 0.0);
            for (h, e, t) in samples {
                let (h, e, t) = (h - mh, f64::from(e[b]) - me, f64::from(t[b]) - mt);
                shh += h * h;
                see += e * e;
                she += h * e;
                sht += h * t;
                set += e * t;
            }
            let det = shh * see - she * she;
            // The normal equations are degenerate when stature or the
            // estimate has no spread, or one is a linear function of the
            // other.
            if !(det > 1e-12 * shh * see && shh > 0.0 && see > 0.0) {
                return Err(TrainError::InvalidArgument(format!(
                    "height fusion: bone {b}: the model's estimate and the stature are (nearly) \
                     collinear or constant over the fit set"
                )));
            }
            let s = (see * sht - she * set) / det;
            let g = (shh * set - she * sht) / det;
            fit.stature_slope[b] = s;
            fit.estimate_weight[b] = g;
            fit.intercept[b] = mt - s * mh - g * me;
        }
        Ok(fit)
    }

    /// The lengths of someone `stature_m` tall whom the model read as
    /// `estimate`.
    pub fn predict(&self, stature_m: f64, estimate: &BoneLengths) -> BoneLengths {
        std::array::from_fn(|b| {
            (self.intercept[b]
                + self.stature_slope[b] * stature_m
                + self.estimate_weight[b] * f64::from(estimate[b])) as f32
        })
    }

    /// The mean weight given to the model's estimates (0: the model adds
    /// nothing to the height).
    pub fn mean_estimate_weight(&self) -> f64 {
        self.estimate_weight.iter().sum::<f64>() / NUM_BONES as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Truth = 0.01 b + 0.2 h + 0.5 e_b (+ nothing else): recovered.
    #[test]
    fn a_known_plane_is_recovered() {
        let samples: Vec<FitSample> = (0..50)
            .map(|i| {
                let h = 1.5 + 0.01 * i as f64;
                let e: BoneLengths =
                    std::array::from_fn(|b| 0.3 + 0.05 * ((i * 7 + b * 3) % 11) as f32);
                let t = std::array::from_fn(|b| {
                    (0.01 * b as f64 + 0.2 * h + 0.5 * f64::from(e[b])) as f32
                });
                (h, e, t)
            })
            .collect();
        let fit = HeightFusion::fit(&samples).unwrap();
        for b in 0..NUM_BONES {
            assert!((fit.stature_slope[b] - 0.2).abs() < 1e-4, "{fit:?}");
            assert!((fit.estimate_weight[b] - 0.5).abs() < 1e-4, "{fit:?}");
            assert!((fit.intercept[b] - 0.01 * b as f64).abs() < 1e-4, "{fit:?}");
        }
        let p = fit.predict(1.8, &[0.4; NUM_BONES]);
        assert!((f64::from(p[3]) - (0.03 + 0.36 + 0.2)).abs() < 1e-4);
        assert!((fit.mean_estimate_weight() - 0.5).abs() < 1e-4);
    }

    #[test]
    fn degenerate_fits_are_errors_not_panics() {
        let one: FitSample = (1.7, [0.4; NUM_BONES], [0.4; NUM_BONES]);
        assert!(HeightFusion::fit(&[one, one]).is_err(), "too few");
        // A constant estimate carries nothing to weigh.
        let constant: Vec<FitSample> = (0..10)
            .map(|i| (1.5 + 0.05 * i as f64, [0.4; NUM_BONES], [0.4; NUM_BONES]))
            .collect();
        assert!(HeightFusion::fit(&constant).is_err());
        let mut bad = constant.clone();
        bad[0].0 = f64::NAN;
        assert!(HeightFusion::fit(&bad).is_err());
    }
}
