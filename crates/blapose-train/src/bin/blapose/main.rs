//! The `blapose` command line (see `blapose --help`): one module per
//! command, so that each command's flags sit beside the code that reads
//! them; the library (`blapose_train`) does the work.
//!
//! - `train` ([`train`]): a bone-length model on synthetic sequences;
//! - `eval` ([`eval`]): bone-length error on Human3.6M (the many-bodies
//!   benchmark and the eval diagnostics are research: `blapose-lab`);
//! - `train-lifter`, `finetune` ([`lifter`]): 2D-to-3D lifters;
//! - `eval-adjust` ([`eval_adjust`]): lifters before and after the
//!   bone-length adjustment;
//! - `fit-stature` ([`stature`]): the stature regression the server
//!   embeds;
//! - `data-report`, `bench-train` ([`report`]): data statistics and
//!   training throughput.
//!
//! Every closed set of values is a clap `ValueEnum` of the library,
//! spelled as in the runs' configuration files.

mod common;
mod eval;
mod eval_adjust;
mod lifter;
mod report;
mod stature;
mod train;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "blapose",
    version,
    about = "Train and evaluate the BLAPose bone-length models",
    // A flag given twice takes its last value, so scripts can append
    // overrides to a fixed recipe.
    args_override_self = true
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Evaluate bone-length predictions on Human3.6M (default S9 and S11,
    /// all cameras, all sequences) beside the naive baselines.
    Eval(Box<eval::EvalArgs>),
    /// Time training steps of the hand-written network on random input
    /// (prints frames_per_second=...).
    BenchTrain(report::BenchTrainArgs),
    /// Train a bone-length model on synthetic sequences built from the
    /// Human3.6M training subjects (S1 S5 S6 S7 S8).
    Train(Box<train::TrainArgs>),
    /// Train a 2D-to-3D lifter on the training subjects' real Stacked
    /// Hourglass detections (root-relative camera-space MPJPE, flip
    /// augmentation).
    TrainLifter(Box<lifter::TrainLifterArgs>),
    /// Fine-tune a lifter through the bone-length adjustment (L_direction +
    /// L_MPJPE of the pose rebuilt with the frozen Bi-GRU's lengths).
    Finetune(Box<lifter::FinetuneArgs>),
    /// Score lifters on S9/S11 before and after the bone-length adjustment
    /// (online GRU running estimate, offline Bi-GRU): the paper's Tables 2
    /// and 3.
    EvalAdjust(Box<eval_adjust::EvalAdjustArgs>),
    /// Print the training data statistics, the ANSUR calibration and the
    /// detector residuals; time the augmentation pipeline.
    DataReport(report::DataReportArgs),
    /// Fit the stature regression (bone lengths from height and sex) on
    /// the ANSUR II training split and write the file the server embeds.
    FitStature(stature::FitStatureArgs),
}

fn main() -> Result<()> {
    match Cli::parse().command {
        Command::DataReport(args) => report::data_report(args),
        Command::Train(args) => train::run(*args),
        Command::Eval(args) => eval::run(*args),
        Command::TrainLifter(args) => lifter::train_lifter(*args),
        Command::Finetune(args) => lifter::finetune(*args),
        Command::EvalAdjust(args) => eval_adjust::run(*args),
        Command::BenchTrain(args) => report::bench_train(args),
        Command::FitStature(args) => stature::run(args),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    #[test]
    fn the_command_line_is_well_formed() {
        Cli::command().debug_assert();
    }

    #[test]
    fn flags_parse_into_typed_values() {
        let cli = Cli::try_parse_from([
            "blapose",
            "train",
            "--out",
            "x",
            "--model",
            "Bi-GRU",
            "--lengths",
            "normal",
            "--shift-plane",
            "ground",
            "--noise",
            "none",
            "--lengths",
            "true",
        ])
        .unwrap();
        let Command::Train(a) = cli.command else {
            panic!("not train")
        };
        let cfg = a.config();
        assert_eq!(cfg.kind, blapose_model::ModelKind::BiGru);
        assert_eq!(
            cfg.lengths,
            blapose_train::lengths::LengthStrategy::True,
            "the last of a repeated flag wins"
        );
        assert_eq!(cfg.shift_plane, blapose_train::synth::ShiftPlane::Ground);
        assert_eq!(cfg.noise, blapose_train::noise::NoiseKind::None);
        assert!(
            Cli::try_parse_from(["blapose", "train", "--out", "x", "--noise", "wide"]).is_err()
        );
        // Removed research options are refused, not ignored.
        for gone in [
            "--detector-gain",
            "--precondition",
            "--decouple-size",
            "--camera-height-std=0.1",
            "--camera-angle-std=1",
            "--noise-scale=1.5",
            "--init-output-mean=false",
            "--height-normalized",
        ] {
            assert!(
                Cli::try_parse_from(["blapose", "train", "--out", "x", gone]).is_err(),
                "{gone}"
            );
        }
        assert!(Cli::try_parse_from([
            "blapose",
            "eval",
            "--model",
            "bigru",
            "--weights",
            "w",
            "--chunk",
            "128"
        ])
        .is_err());
    }

    #[test]
    fn defaults_are_the_documented_recipe_defaults() {
        let cli = Cli::try_parse_from(["blapose", "train", "--out", "x"]).unwrap();
        let Command::Train(a) = cli.command else {
            panic!("not train")
        };
        let cfg = a.config();
        let json = serde_json::to_value(&cfg).unwrap();
        for (field, value) in [
            ("kind", "bigru"),
            ("lengths", "ansur"),
            ("noise", "residual"),
            ("shift_plane", "camera"),
            ("ansur_people", "train"),
        ] {
            assert_eq!(json[field], value, "{field}");
        }
        assert_eq!(
            (cfg.steps, cfg.epoch_steps, cfg.batch, cfg.seq_len),
            (2000, 100, 64, 64)
        );
        assert_eq!((cfg.lr, cfg.lr_decay, cfg.clip_norm), (1e-4, 0.95, 5.0));
        assert_eq!((cfg.head_lr_scale, cfg.ema_decay), (0.01, 0.999));
        let cli = Cli::try_parse_from(["blapose", "train", "--out", "x", "--ansur-people", "all"])
            .unwrap();
        let Command::Train(a) = cli.command else {
            panic!("not train")
        };
        assert_eq!(
            a.config().ansur_people,
            blapose_train::ansur_split::AnsurPeople::All
        );
    }

    #[test]
    fn eval_takes_a_model_and_its_weights_and_no_research_diagnostics() {
        let eval = |extra: &[&str]| {
            let mut all = vec!["blapose", "eval", "--model", "gru", "--weights", "w"];
            all.extend_from_slice(extra);
            Cli::try_parse_from(all)
        };
        let cli = eval(&[
            "--calibrated",
            "--fps",
            "25",
            "--every",
            "4",
            "--flip-average",
        ])
        .unwrap();
        assert!(matches!(cli.command, Command::Eval(_)));
        // The model and its weights are required.
        assert!(Cli::try_parse_from(["blapose", "eval", "--model", "gru"]).is_err());
        assert!(Cli::try_parse_from(["blapose", "eval", "--weights", "w"]).is_err());
        // Research lives in blapose-lab; removed options are gone.
        for research in [
            &["--benchmark", "bodies"][..],
            &["--state-frames", "4"],
            &["--skip-frames", "100"],
            &["--rectify"],
            &["--drop-joints", "0.2"],
            &["--stature-proxy"],
            &["--height-correction"],
        ] {
            assert!(eval(research).is_err(), "{research:?}");
        }
    }
}
