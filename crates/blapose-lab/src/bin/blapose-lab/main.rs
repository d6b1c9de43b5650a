//! The `blapose-lab` command line (see `blapose-lab --help`): the research
//! commands around the shipped models, apart from the product's `blapose`
//! so that its commands carry only what a user needs. One module per
//! command; the library (`blapose_lab`, over `blapose_train`) does the
//! work.
//!
//! - `bodies` ([`bodies`]): the many-bodies cross-camera benchmark;
//! - `diagnose` ([`diagnose`]): `blapose eval`'s run with the research
//!   diagnostics around it;
//! - `motion` ([`motion`]): the candidate motion filters on training
//!   subjects.

mod bodies;
mod diagnose;
mod motion;
mod root_scale;

use anyhow::Result;
use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "blapose-lab",
    version,
    about = "Research around the BLAPose bone-length models: the many-bodies benchmark, eval diagnostics",
    // A flag given twice takes its last value, as in `blapose`.
    args_override_self = true
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// The many-bodies cross-camera benchmark: held-out ANSUR II people on
    /// S9/S11 motion through wide cameras, the four shipped models in
    /// --models-dir beside the prior, the stature regression and the size
    /// oracles.
    Bodies(Box<bodies::BodiesArgs>),
    /// `blapose eval` with research diagnostics: trials joined mid-way,
    /// rectified without the weights' contract, the online state restarted,
    /// joints lost, or the stature regression on each subject's stature
    /// proxy.
    Diagnose(Box<diagnose::DiagnoseArgs>),
    /// Every candidate motion filter (causal and offline, directions, root,
    /// feet, 2D before lifting) on held-out training trials, beside the
    /// baselines: how the served motion stages were chosen.
    Motion(Box<motion::MotionArgs>),
}

fn main() -> Result<()> {
    match Cli::parse().command {
        Command::Bodies(args) => bodies::run(*args),
        Command::Diagnose(args) => diagnose::run(*args),
        Command::Motion(args) => motion::run(*args),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use blapose_lab::stature_proxy::StatureSource;
    use clap::CommandFactory;

    #[test]
    fn the_command_line_is_well_formed() {
        Cli::command().debug_assert();
    }

    #[test]
    fn the_benchmark_needs_no_model_flags_and_refuses_them() {
        let cli = Cli::try_parse_from([
            "blapose-lab",
            "bodies",
            "--json",
            "b.json",
            "--bench-individuals",
            "5",
        ])
        .unwrap();
        assert!(matches!(cli.command, Command::Bodies(_)));
        assert!(Cli::try_parse_from(["blapose-lab", "bodies", "--model", "gru"]).is_err());
        assert!(Cli::try_parse_from(["blapose-lab", "bodies", "--weights", "w"]).is_err());
    }

    #[test]
    fn diagnose_takes_eval_flags_and_the_diagnostics() {
        let parse = |extra: &[&str]| {
            let mut all = vec!["blapose-lab", "diagnose"];
            all.extend_from_slice(extra);
            Cli::try_parse_from(all)
        };
        let model = ["--model", "gru", "--weights", "w"];
        for diagnostic in [
            &["--state-frames", "4"][..],
            &["--skip-frames", "100", "--fps", "25"],
            &["--rectify"],
            &["--drop-joints", "0.2", "--drop-seed", "3", "--calibrated"],
            &["--every", "4", "--subjects", "S9", "--cameras", "54138969"],
        ] {
            assert!(
                parse(&[&model[..], diagnostic].concat()).is_ok(),
                "{diagnostic:?}"
            );
        }
        // Without --stature-proxy the model and its weights are required.
        assert!(parse(&["--model", "gru"]).is_err());
        assert!(parse(&["--weights", "w"]).is_err());
        assert!(parse(&[&model[..], &["--rectify", "--calibrated"]].concat()).is_err());
        assert!(parse(&["--drop-seed", "3"]).is_err());
    }

    #[test]
    fn motion_refuses_the_test_subjects_before_loading_anything() {
        let cli = Cli::try_parse_from(["blapose-lab", "motion", "--subjects", "S1,S9"]).unwrap();
        let Command::Motion(args) = cli.command else {
            panic!("not motion")
        };
        let err = motion::run(*args).unwrap_err().to_string();
        assert!(
            err.contains("S9: choose on training subjects only"),
            "{err}"
        );
    }

    #[test]
    fn the_stature_proxy_takes_its_source_and_defaults_to_the_calibrated_proxy() {
        let source = |args: &[&str]| {
            let mut all = vec!["blapose-lab", "diagnose", "--stature-proxy"];
            all.extend_from_slice(args);
            let cli = Cli::try_parse_from(all).ok()?;
            match cli.command {
                Command::Diagnose(a) => Some(a.stature_source),
                Command::Bodies(_) | Command::Motion(_) => None,
            }
        };
        assert_eq!(source(&[]), Some(StatureSource::CalibratedProxy));
        assert_eq!(
            source(&["--stature-source", "matched"]),
            Some(StatureSource::Matched)
        );
        assert_eq!(
            source(&["--stature-source", "proxy"]),
            Some(StatureSource::Proxy)
        );
        assert_eq!(source(&["--stature-source", "tape"]), None);
        // Not with a model, nor with lost joints.
        assert_eq!(source(&["--model", "gru", "--weights", "w"]), None);
        assert_eq!(source(&["--drop-joints", "0.2"]), None);
    }
}
