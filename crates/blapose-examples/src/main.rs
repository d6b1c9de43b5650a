//! `make-example`: build the licence-clean replay examples under `examples/`
//! from the CMU motion clips (see the `blapose_examples` library for the recipe).
//!
//! ```text
//! cargo run --release -p blapose-examples --bin make-example -- \
//!     --cmu ../shared/data/cmu/cmu_h36m17.npz --out examples/
//! ```

use std::path::PathBuf;

use anyhow::{Context, Result};
use blapose_core::bones::adjust_sequence;
use blapose_core::metrics::pose_metrics;
use blapose_data::npz::{read_npz, write_npz};
use blapose_examples::{clip_name_and_stature, make_example, ExampleConfig};
use clap::Parser;

/// Build replay examples (2D keypoints from a synthetic camera, a plausibly
/// wrong lifted pose and the ground truth) from CMU motion capture clips.
#[derive(Debug, Parser)]
#[command(version, about, long_about = None)]
struct Args {
    /// The CMU clips mapped to the Human3.6M 17-joint order (T, 17, 3),
    /// metres, +Z up.
    #[arg(
        long,
        env = "BLAPOSE_CMU",
        default_value = "../shared/data/cmu/cmu_h36m17.npz"
    )]
    cmu: PathBuf,
    /// Directory to write the examples into.
    #[arg(long, default_value = "examples")]
    out: PathBuf,
    /// Base random seed (each clip mixes in its name).
    #[arg(long, default_value_t = ExampleConfig::default().seed)]
    seed: u64,
    /// Only these clips (npz keys, e.g. subject02/02_02); default: all.
    #[arg(long = "clip")]
    clips: Vec<String>,
}

fn main() -> Result<()> {
    let args = Args::parse();
    let npz = read_npz(&args.cmu).with_context(|| format!("reading {}", args.cmu.display()))?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let keys: Vec<String> = npz
        .keys()
        .filter(|k| args.clips.is_empty() || args.clips.iter().any(|c| c == k))
        .map(str::to_string)
        .collect();
    anyhow::ensure!(
        !keys.is_empty(),
        "no matching clips in {}",
        args.cmu.display()
    );
    println!(
        "{:<22} {:>6} {:>8} {:>11} {:>13}",
        "example", "frames", "depth (m)", "MPJPE (mm)", "bone err (mm)"
    );
    for key in keys {
        let (name, stature) = clip_name_and_stature(&key);
        let world = npz.poses(&key)?;
        let config = ExampleConfig {
            seed: args.seed,
            stature,
            ..ExampleConfig::default()
        };
        let example = make_example(&key, &world, &config).with_context(|| format!("clip {key}"))?;
        let path = args.out.join(format!("{name}.npz"));
        write_npz(&path, &example.to_npz()?)
            .with_context(|| format!("writing {}", path.display()))?;
        let seq = &example.sequence;
        let gt = seq.gt_3d.as_deref().unwrap_or_default();
        let m = pose_metrics(&seq.pose_3d, gt)?;
        // The ceiling: the adjustment with the true lengths.
        let oracle = adjust_sequence(&seq.pose_3d, &example.gt_lengths)?;
        let oracle = pose_metrics(&oracle, gt)?;
        // Mean camera-to-pelvis depth over the clip.
        let dist = world
            .iter()
            .map(|p| example.camera.world_to_camera(p[0].map(f64::from))[2])
            .sum::<f64>()
            / world.len() as f64;
        println!(
            "{:<22} {:>6} {:>9.2} {:>11.1} {:>13.1} {:>18.1}",
            name,
            seq.len(),
            dist,
            m.mpjpe_mm,
            m.bone_error_mm,
            oracle.mpjpe_mm
        );
    }
    Ok(())
}
