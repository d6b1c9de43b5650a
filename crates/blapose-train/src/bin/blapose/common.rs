//! What several commands share: the model-kind flag, subject and camera
//! lists (from the library, [`blapose_train::cli`], which `blapose-lab`
//! shares too), the progress bar. Kept here so each command reads them the
//! same way.

pub use blapose_train::cli::{camera_list, known_subjects, ModelArg};
use indicatif::{ProgressBar, ProgressStyle};

/// The progress bar of a training run (`steps` optimizer steps).
pub fn step_bar(steps: u64) -> ProgressBar {
    let pb = ProgressBar::new(steps);
    pb.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {pos}/{len} eta {eta} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    pb
}
