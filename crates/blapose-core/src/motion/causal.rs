//! A stream's causal motion stage ([`CausalMotion`]): the bone directions
//! through a per-channel filter, rebuilt with the session's lengths; the
//! pelvis solved from the rays and filtered. Its state is plain numbers
//! ([`MotionState`]) so a session token carries it and a continuation is
//! bit-exact.

use super::root::{solve_root, Rays};
use super::{
    directions_as_values, normalized, values_as_directions, CausalMotionConfig, ChannelFilter,
    Placed,
};
use crate::bones::{decompose, rebuild, BoneError};
use crate::pose::{BoneLengths, Pose};
use crate::skeleton::{NUM_JOINTS, ROOT};

/// A stream's causal motion stage: its settings and its filters' state.
#[derive(Debug, Clone, PartialEq)]
pub struct CausalMotion {
    config: CausalMotionConfig,
    directions: Option<ChannelFilter>,
    root: Option<ChannelFilter>,
}

/// A [`CausalMotion`]'s state as numbers, for session tokens.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct MotionState {
    /// The direction filter's state (empty when off or before a frame).
    pub directions: Vec<f64>,
    /// The root filter's state.
    pub root: Vec<f64>,
}

impl CausalMotion {
    /// A stage with fresh filters.
    pub fn new(config: CausalMotionConfig) -> Self {
        Self {
            config,
            directions: config
                .directions
                .map(|s| ChannelFilter::new(s, config.rate_hz)),
            root: config.root.map(|s| ChannelFilter::new(s, config.rate_hz)),
        }
    }

    /// Its settings.
    pub fn config(&self) -> &CausalMotionConfig {
        &self.config
    }

    /// The next frame's pose: `adjusted`'s bone directions smoothed, then
    /// rebuilt with `lengths` from `adjusted`'s root. Errors (a zero-length
    /// bone, a non-finite joint) leave the state as it was.
    pub fn smooth_pose(
        &mut self,
        adjusted: &Pose,
        lengths: &BoneLengths,
    ) -> Result<Pose, BoneError> {
        let Some(bank) = &mut self.directions else {
            return Ok(*adjusted);
        };
        let (_, dirs) = decompose(adjusted)?;
        let mut values = directions_as_values(&dirs);
        bank.step(&mut values);
        let smoothed = normalized(values_as_directions(&values));
        Ok(rebuild(adjusted[ROOT], &smoothed, lengths))
    }

    /// The next frame's root position: `solved` (camera space, metres)
    /// through the root filter.
    pub fn smooth_root(&mut self, solved: [f64; 3]) -> [f64; 3] {
        let mut v = solved;
        if let Some(bank) = &mut self.root {
            bank.step(&mut v);
        }
        v
    }

    /// One frame through the stage: `adjusted` (root-relative, lengths
    /// applied) smoothed ([`Self::smooth_pose`]), and where the pelvis is
    /// when `rays` (the frame's viewing rays and per-joint weights) are
    /// given: solved for the smoothed pose ([`root::solve_root`]), then
    /// filtered ([`Self::smooth_root`]). A frame whose root cannot be
    /// solved gets none and leaves the root filter as it was.
    pub fn step(
        &mut self,
        adjusted: &Pose,
        lengths: &BoneLengths,
        rays: Option<(&Rays, &[f64; NUM_JOINTS])>,
    ) -> Result<Placed, BoneError> {
        let pose = self.smooth_pose(adjusted, lengths)?;
        let root = rays
            .and_then(|(r, w)| solve_root(r, &pose, w))
            .map(|solved| self.smooth_root(solved));
        Ok(Placed { pose, root })
    }

    /// The filters' state.
    pub fn state(&self) -> MotionState {
        MotionState {
            directions: self
                .directions
                .as_ref()
                .map(ChannelFilter::state)
                .unwrap_or_default(),
            root: self
                .root
                .as_ref()
                .map(ChannelFilter::state)
                .unwrap_or_default(),
        }
    }

    /// A stage with `config` continuing from `state`; `None` when the state
    /// does not fit the settings.
    pub fn restore(config: CausalMotionConfig, state: &MotionState) -> Option<Self> {
        let fresh = Self::new(config);
        let restore = |bank: Option<ChannelFilter>, s: &[f64]| -> Option<Option<ChannelFilter>> {
            match bank {
                Some(b) => Some(Some(b.with_state(s)?)),
                None if s.is_empty() => Some(None),
                None => None,
            }
        };
        Some(Self {
            config,
            directions: restore(fresh.directions, &state.directions)?,
            root: restore(fresh.root, &state.root)?,
        })
    }
}
