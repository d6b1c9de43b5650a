//! `blapose-client`: command-line client for the blapose server.
//!
//! A thin shell over the library: parse flags, connect, run one command,
//! print a table (and optionally JSON). All protocol and metric logic lives
//! in the library so tests exercise exactly what the CLI runs; what only
//! the command line needs (its flags, and the HTML report of `--html` in
//! [`html`]) lives here, beside it, so the library carries neither clap
//! nor the report page.

mod export;
mod html;

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context, Result};
use blapose_client::{
    adjust_offline_with_motion, evaluate, replay_across, Adjusted, Client, ClientConfig,
    KeypointLayout, ModelKind, ReplayOptions, Sequence, Sex, Subject, TlsOptions, DEFAULT_SERVER,
};
use clap::builder::{PossibleValue, PossibleValuesParser, TypedValueParser};
use clap::{Args, Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};

use html::ReportData;

/// Client for the blapose bone-length adjustment service.
///
/// Streams 2D keypoints and a lifter's 3D poses to a blapose server and gets
/// back the poses rebuilt with the person's predicted bone lengths.
#[derive(Debug, Parser)]
#[command(version, about, long_about)]
struct Cli {
    #[command(flatten)]
    connection: ConnectionArgs,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Args)]
struct ConnectionArgs {
    /// Server URL (http:// or https://). Several, comma-separated, are
    /// replicas sharing a --session-key: `replay` opens the session on the
    /// first and, when a server fails mid-stream, resumes it on the next
    /// one from the latest session token; other commands use the first.
    #[arg(long, global = true, env = "BLAPOSE_SERVER", default_value = DEFAULT_SERVER)]
    server: String,
    /// Bearer token, if the server requires one.
    #[arg(long, global = true, env = "BLAPOSE_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// PEM file of the CA that signed the server's certificate (enables
    /// TLS; without it https:// uses the system trust store).
    #[arg(long, global = true, env = "BLAPOSE_TLS_CA")]
    tls_ca: Option<PathBuf>,
    /// Name to check the server certificate against (default: URL host).
    #[arg(long, global = true, env = "BLAPOSE_TLS_DOMAIN")]
    tls_domain: Option<String>,
    /// Seconds to wait for each connection attempt.
    #[arg(
        long,
        global = true,
        env = "BLAPOSE_CONNECT_TIMEOUT",
        default_value_t = 5.0
    )]
    connect_timeout: f64,
    /// Connection attempts before giving up (exponential backoff between).
    #[arg(
        long,
        global = true,
        env = "BLAPOSE_CONNECT_ATTEMPTS",
        default_value_t = 5
    )]
    connect_attempts: u32,
    /// Deadline in seconds for unary calls and for opening a session.
    #[arg(long, global = true, env = "BLAPOSE_TIMEOUT", default_value_t = 60.0)]
    timeout: f64,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Stream a replay file frame by frame through an online session.
    ///
    /// Frames are pipelined (sent while answers arrive). With --out the
    /// adjusted poses (adjusted_3d, T x 17 x 3) and the bone lengths applied
    /// to each frame (bone_lengths, T x 16) are written as an npz. When the
    /// file has gt_3d, MPJPE, P-MPJPE and bone-length error are printed
    /// before and after the adjustment. With --server-lifter only the 2D
    /// keypoints are sent and the server's lifter produces the poses (--out
    /// then also holds them before adjustment: lifted_3d, T x 17 x 3). With
    /// --camera the file's camera calibration (camera_up, camera_focal,
    /// camera_principal) is sent and the camera-aware model serves it. With
    /// --html a self-contained HTML report (3D before/after views, bone
    /// lengths, symmetry, errors) is written.
    Replay {
        #[command(flatten)]
        io: IoArgs,
        /// Send at most this many frames per second (default: as fast as
        /// the server answers).
        #[arg(long)]
        fps: Option<f64>,
        /// Frames in flight at most (sent, not yet answered).
        #[arg(long, default_value_t = 64)]
        window: usize,
        /// Label for the server's logs.
        #[arg(long)]
        label: Option<String>,
        /// Send the 2D keypoints only and let the server's lifter produce
        /// the 3D poses (the server must run one: --lifter-weights); the
        /// file's pose_3d is not sent, and "before" is the server lifter's
        /// poses.
        #[arg(long)]
        server_lifter: bool,
        /// Open the session with the causal motion stage: each answer's
        /// bone directions smoothed from the frames so far, the pelvis
        /// placed in camera space. The exports then move through space,
        /// and --out gains root_3d (T x 3).
        #[arg(long)]
        motion: bool,
    },
    /// Adjust a replay file with one offline call (Bi-GRU by default).
    ///
    /// With --camera the file's camera calibration is sent and the
    /// camera-aware model of the chosen kind serves it. With --html a
    /// self-contained HTML report (3D before/after views, bone lengths,
    /// symmetry, errors) is written.
    Adjust {
        #[command(flatten)]
        io: IoArgs,
        /// Bone-length model: bigru (offline, whole sequence) or gru (the
        /// online model run causally, as a stream would).
        #[arg(long, default_value = "bigru", value_parser = parse_model)]
        model: ModelKind,
        /// Run the server's offline motion stage: bone directions smoothed
        /// zero-phase, the pelvis placed in camera space from the keypoints
        /// (through the file's calibration with --camera, else an assumed
        /// focal length), planted feet held. The exports then move through
        /// space, and --out gains root_3d (T x 3).
        #[arg(long)]
        motion: bool,
    },
    /// Print what the server runs: models, parameters, weights, limits.
    Info {
        /// Print JSON-like debug output instead of the summary.
        #[arg(long)]
        raw: bool,
    },
}

#[derive(Debug, Args)]
struct IoArgs {
    /// Replay file (npz): keypoints_2d (T,J,2) pixels, pose_3d (T,17,3)
    /// metres, image_size [w,h]; optional layout code (1 h36m17, 2 sh16,
    /// 3 coco17), gt_3d (T,17,3), confidence (T,J), fps, and a camera
    /// calibration: camera_up (3,) world up in camera axes, camera_focal
    /// [fx,fy] and camera_principal [cx,cy] in pixels (all three or none),
    /// plus optionally camera_height, metres above the floor (0.3 to 10).
    file: PathBuf,
    /// Write adjusted_3d and bone_lengths (and, with --server-lifter,
    /// lifted_3d) to this npz.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Write {"frames":T,"before":{..},"after":{..}} (needs gt_3d).
    #[arg(long)]
    json: Option<PathBuf>,
    /// Write a self-contained HTML report that works offline: the input
    /// and adjusted skeletons side by side in 3D (play/pause, frame slider,
    /// drag to orbit), the 16 bone lengths over time, the left/right
    /// asymmetry and, with gt_3d, the per-frame MPJPE and the before/after
    /// table.
    #[arg(long)]
    html: Option<PathBuf>,
    /// Write the adjusted motion as a BVH for Blender and animation tools:
    /// the 17 joints by name (plus 4 helpers) with the person's bone
    /// lengths in a T-pose, metres, Y up, every frame re-posed with the
    /// final lengths (client/README.md: Motion export).
    #[arg(long, value_name = "PATH")]
    bvh: Option<PathBuf>,
    /// Write the adjusted joints as a C3D (17 markers named as the joints,
    /// millimetres, Z up), for biomechanics tools.
    #[arg(long, value_name = "PATH")]
    c3d: Option<PathBuf>,
    /// Write the adjusted joints as OpenSim's TRC (17 markers, millimetres,
    /// Z up).
    #[arg(long, value_name = "PATH")]
    trc: Option<PathBuf>,
    /// Keypoint layout, overriding the file's (h36m17, sh16, coco17).
    #[arg(long)]
    layout: Option<KeypointLayout>,
    /// Refuse a file with more frames than this, before reading its
    /// arrays (the file's members are never inflated past what that many
    /// frames need).
    #[arg(long, value_name = "N", default_value_t = blapose_client::sequence::DEFAULT_MAX_FRAMES)]
    max_file_frames: usize,
    /// Send the file's camera calibration, so the server's camera-aware
    /// models serve the sequence. They need the camera's height above the
    /// floor (camera_height) and were trained for cameras 0.5-3 m high,
    /// -35 to +15 degrees from level, 40-100 degrees across; other
    /// calibrations are refused, naming the value. They read people's
    /// sizes better than the default models on such cameras (on the
    /// shipped CMU examples: 5.8 mm streamed against 7.6) but worse on
    /// Human3.6M's own (models/README.md).
    #[arg(long)]
    camera: bool,
    /// The person's stature in metres (1.0 to 2.3), overriding the file's
    /// subject_height: the server then answers with the stature
    /// regression's lengths for it, which read people better than any
    /// model without it (models/README.md).
    #[arg(long, value_name = "METRES")]
    height: Option<f32>,
    /// The person's sex, with --height (or the file's subject_height).
    #[arg(long, value_parser = sex_parser())]
    sex: Option<Sex>,
}

/// `--model`: `gru` or `bigru`, also `online`/`offline`, `online-gru`/
/// `offline-bigru`, in any case, with `-` and `_` ignored.
fn parse_model(s: &str) -> Result<ModelKind, String> {
    match s
        .trim()
        .to_ascii_lowercase()
        .replace(['-', '_'], "")
        .as_str()
    {
        "gru" | "online" | "onlinegru" => Ok(ModelKind::Gru),
        "bigru" | "offline" | "offlinebigru" => Ok(ModelKind::BiGru),
        _ => Err(format!("unknown model {s:?} (expected gru or bigru)")),
    }
}

/// `--sex`: exactly `female` or `male`, each listed in the help.
fn sex_parser() -> impl TypedValueParser<Value = Sex> {
    PossibleValuesParser::new([
        PossibleValue::new("female").help("Female"),
        PossibleValue::new("male").help("Male"),
    ])
    .try_map(|s| s.parse::<Sex>())
}

impl IoArgs {
    /// The replay file, with its camera only when --camera is given, and
    /// the file's world up direction in camera axes (`camera_up`), if any,
    /// for the HTML report's floor.
    fn load(&self) -> Result<(Sequence, Option<[f32; 3]>)> {
        let mut seq =
            Sequence::load_with_max_frames(&self.file, self.layout, self.max_file_frames)?;
        let up = seq.camera.map(|c| c.up);
        if !self.camera {
            seq.camera = None;
        }
        if let Some(height_m) = self.height {
            seq.subject = Some(Subject {
                height_m,
                sex: self.sex,
            });
        } else if let Some(sex) = self.sex {
            let subject = seq.subject.as_mut().context(
                "--sex needs the person's stature: --height, or subject_height in the file",
            )?;
            subject.sex = Some(sex);
        }
        Ok((seq, up))
    }

    /// Write the --html report, if asked for.
    async fn write_html(
        &self,
        client: &Client,
        server: &str,
        (seq, up): &(Sequence, Option<[f32; 3]>),
        result: &Adjusted,
    ) -> Result<()> {
        let Some(path) = &self.html else {
            return Ok(());
        };
        let title = self.file.file_name().map_or_else(
            || self.file.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        );
        let mut data = ReportData::from_adjusted(&title, seq, result, *up)?;
        // Header lines only: a server that cannot say what it runs still
        // gets its report.
        if let Ok(info) = client.model_info().await {
            data.add_server_info(server, &info, result);
        }
        data.write(path)?;
        println!("wrote {}", path.display());
        Ok(())
    }
}

fn seconds(v: f64, what: &str) -> Result<Duration> {
    anyhow::ensure!(
        v.is_finite() && v > 0.0,
        "{what} must be a positive number of seconds, got {v}"
    );
    Ok(Duration::from_secs_f64(v))
}

impl ConnectionArgs {
    /// The --server URLs, in order.
    fn servers(&self) -> Vec<&str> {
        self.server
            .split(',')
            .map(str::trim)
            .filter(|s| !s.is_empty())
            .collect()
    }

    /// The first --server URL.
    fn first_server(&self) -> Result<&str> {
        self.servers()
            .first()
            .copied()
            .context("--server names no server")
    }
}

/// Connect to the first --server.
async fn connect(args: &ConnectionArgs) -> Result<Client> {
    Ok(Client::connect(client_config(args, args.first_server()?)?).await?)
}

/// Connect to the first --server, and lazily (at first use) to the others,
/// which may be down for now: they are only needed to fail over.
async fn connect_all(args: &ConnectionArgs) -> Result<Vec<Client>> {
    let mut clients = vec![connect(args).await?];
    for server in args.servers().into_iter().skip(1) {
        clients.push(Client::connect_lazy(client_config(args, server)?)?);
    }
    Ok(clients)
}

fn client_config(args: &ConnectionArgs, server: &str) -> Result<ClientConfig> {
    let mut config = ClientConfig::new(server);
    config.token = args.token.clone();
    config.connect_timeout = seconds(args.connect_timeout, "--connect-timeout")?;
    config.request_timeout = seconds(args.timeout, "--timeout")?;
    config.connect_attempts = args.connect_attempts.max(1);
    config.tls = TlsOptions {
        ca_cert_pem: args
            .tls_ca
            .as_ref()
            .map(|p| std::fs::read(p).with_context(|| format!("reading {}", p.display())))
            .transpose()?,
        domain: args.tls_domain.clone(),
    };
    Ok(config)
}

fn progress_bar(total: usize) -> ProgressBar {
    let bar = ProgressBar::new(total as u64);
    if let Ok(style) = ProgressStyle::with_template(
        "{spinner} [{elapsed_precise}] {bar:40} {pos}/{len} frames ({per_sec})",
    ) {
        bar.set_style(style);
    }
    bar
}

fn finish(io: &IoArgs, seq: &Sequence, result: &Adjusted) -> Result<()> {
    println!(
        "{} frames adjusted by the {} model in {:.3} s ({:.0} frames/s)",
        result.adjusted.len(),
        result.model,
        result.elapsed.as_secs_f64(),
        result.frames_per_second()
    );
    if let Some(subject) = &seq.subject {
        println!("subject {subject}: answered with the stature regression's lengths");
    }
    match &result.camera {
        Some(camera) => println!("served by the camera-aware model (camera calibration: {camera})"),
        None if io.camera => {
            println!("served by the default model (no camera calibration in the file)")
        }
        None => println!("served by the default model (--camera sends the file's calibration, if any, to the camera-aware model)"),
    }
    // The poses the adjustment started from: the server lifter's, or the
    // file's own.
    let before = match &result.lifter {
        Some(name) => {
            println!(
                "input poses lifted by the server's {name} lifter from the 2D keypoints (the file's pose_3d was not sent)"
            );
            &result.lifted
        }
        None => &seq.pose_3d,
    };
    if let Some(last) = result.bone_lengths.last() {
        let mm: Vec<String> = last.iter().map(|l| format!("{:.0}", l * 1000.0)).collect();
        println!("final bone lengths (mm): {}", mm.join(" "));
    }
    if let Some(p) = &result.placement {
        let (first, last) = (p.roots[0], p.roots[p.roots.len() - 1]);
        let travel: f32 = p
            .roots
            .windows(2)
            .map(|w| {
                (0..3)
                    .map(|i| (w[1][i] - w[0][i]).powi(2))
                    .sum::<f32>()
                    .sqrt()
            })
            .sum();
        println!(
            "motion: pelvis placed from ({:.2}, {:.2}, {:.2}) m to ({:.2}, {:.2}, {:.2}) m in camera space, {travel:.2} m travelled{}",
            first[0], first[1], first[2], last[0], last[1], last[2],
            if p.focal_assumed { " (focal length assumed: no calibration sent)" } else { "" }
        );
    }
    if let Some(out) = &io.out {
        result.write_npz(out)?;
        println!("wrote {}", out.display());
    }
    match &seq.gt_3d {
        Some(gt) => {
            let evaluation = evaluate(before, &result.adjusted, gt)?;
            print!("{evaluation}");
            if let Some(path) = &io.json {
                write_json(path, &evaluation)?;
            }
        }
        None => {
            println!("no gt_3d in {}: accuracy not computed", io.file.display());
            if let Some(path) = &io.json {
                write_json(
                    path,
                    &serde_json::json!({ "frames": result.adjusted.len() }),
                )?;
            }
        }
    }
    Ok(())
}

fn write_json(path: &Path, value: &impl serde::Serialize) -> Result<()> {
    let text = serde_json::to_string_pretty(value)?;
    std::fs::write(path, text + "\n").with_context(|| format!("writing {}", path.display()))?;
    println!("wrote {}", path.display());
    Ok(())
}

async fn run(cli: Cli) -> Result<()> {
    match cli.command {
        Command::Replay {
            io,
            fps,
            window,
            label,
            server_lifter,
            motion,
        } => {
            let loaded = io.load()?;
            io.check_exports(loaded.0.len())?;
            let seq = &loaded.0;
            let clients = connect_all(&cli.connection).await?;
            let bar = progress_bar(seq.len());
            let options = ReplayOptions {
                fps,
                window,
                label,
                server_lifter,
                motion: motion.then(|| seq.fps.unwrap_or(0.0)),
            };
            let result =
                replay_across(&clients, seq, &options, |n| bar.set_position(n as u64)).await;
            bar.finish_and_clear();
            let result = result?;
            if let Some(s) = &result.session {
                println!(
                    "session {} closed after {} frames",
                    s.session_id, s.frames_seen
                );
            }
            if result.resumes > 0 {
                println!(
                    "the stream failed and the session was resumed {} time(s); every frame was answered once",
                    result.resumes
                );
            }
            finish(&io, seq, &result)?;
            io.write_exports(&result, seq.fps, loaded.1)?;
            io.write_html(
                &clients[0],
                cli.connection.first_server()?,
                &loaded,
                &result,
            )
            .await?;
            io.refused_exports(seq.len())
        }
        Command::Adjust { io, model, motion } => {
            let loaded = io.load()?;
            io.check_exports(loaded.0.len())?;
            let client = connect(&cli.connection).await?;
            let rate = motion.then(|| loaded.0.fps.unwrap_or(0.0));
            let result = adjust_offline_with_motion(&client, &loaded.0, model, rate).await?;
            finish(&io, &loaded.0, &result)?;
            io.write_exports(&result, loaded.0.fps, loaded.1)?;
            io.write_html(&client, cli.connection.first_server()?, &loaded, &result)
                .await?;
            io.refused_exports(loaded.0.len())
        }
        Command::Info { raw } => {
            let client = connect(&cli.connection).await?;
            let info = client.model_info().await?;
            if raw {
                println!("{info:#?}");
            } else {
                print!("{info}");
            }
            Ok(())
        }
    }
}

#[tokio::main]
async fn main() {
    let cli = Cli::parse();
    if let Err(e) = run(cli).await {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    #[test]
    fn cli_definition_is_consistent() {
        Cli::command().debug_assert();
    }

    #[test]
    fn replay_flags_parse() {
        let cli = Cli::try_parse_from([
            "blapose-client",
            "replay",
            "x.npz",
            "--server",
            "http://h:1",
            "--fps",
            "50",
            "--out",
            "o.npz",
            "--json",
            "m.json",
            "--html",
            "r.html",
        ])
        .unwrap();
        assert_eq!(cli.connection.servers(), ["http://h:1"]);
        let replicas = Cli::try_parse_from([
            "blapose-client",
            "replay",
            "x.npz",
            "--server",
            "http://a:1, http://b:2,",
        ])
        .unwrap();
        assert_eq!(replicas.connection.servers(), ["http://a:1", "http://b:2"]);
        assert_eq!(replicas.connection.first_server().unwrap(), "http://a:1");
        match cli.command {
            Command::Replay {
                io,
                fps,
                server_lifter,
                ..
            } => {
                assert_eq!(fps, Some(50.0));
                assert!(!server_lifter, "client poses by default");
                assert_eq!(io.out, Some(PathBuf::from("o.npz")));
                assert_eq!(io.json, Some(PathBuf::from("m.json")));
                assert_eq!(io.html, Some(PathBuf::from("r.html")));
            }
            other => panic!("{other:?}"),
        }
        let cli = Cli::try_parse_from([
            "blapose-client",
            "adjust",
            "x.npz",
            "--model",
            "gru",
            "--layout",
            "sh16",
        ])
        .unwrap();
        assert!(matches!(
            cli.command,
            Command::Adjust {
                model: ModelKind::Gru,
                io: IoArgs {
                    layout: Some(KeypointLayout::Sh16),
                    ..
                },
                motion: false,
            }
        ));
        let cli = Cli::try_parse_from(["blapose-client", "adjust", "x.npz", "--motion"]).unwrap();
        assert!(matches!(cli.command, Command::Adjust { motion: true, .. }));
        let cli = Cli::try_parse_from(["blapose-client", "replay", "x.npz", "--motion"]).unwrap();
        assert!(matches!(cli.command, Command::Replay { motion: true, .. }));
        assert!(
            Cli::try_parse_from(["blapose-client", "adjust", "x.npz", "--model", "lstm"]).is_err()
        );
        let cli =
            Cli::try_parse_from(["blapose-client", "replay", "x.npz", "--server-lifter"]).unwrap();
        assert!(matches!(
            cli.command,
            Command::Replay {
                server_lifter: true,
                ..
            }
        ));
        assert!(
            Cli::try_parse_from(["blapose-client", "adjust", "x.npz", "--server-lifter"]).is_err(),
            "the offline call has no server lifter"
        );
    }

    #[test]
    fn max_file_frames_defaults_to_the_library_bound() {
        let io = |args: &[&str]| match Cli::try_parse_from(args).unwrap().command {
            Command::Adjust { io, .. } | Command::Replay { io, .. } => io,
            other => panic!("{other:?}"),
        };
        assert_eq!(
            io(&["blapose-client", "adjust", "x.npz"]).max_file_frames,
            blapose_client::sequence::DEFAULT_MAX_FRAMES
        );
        let small = io(&[
            "blapose-client",
            "replay",
            "x.npz",
            "--max-file-frames",
            "10",
        ]);
        assert_eq!(small.max_file_frames, 10);
    }

    #[test]
    fn model_and_sex_accept_the_same_spellings_as_before() {
        let model = |name: &str| match Cli::try_parse_from([
            "blapose-client",
            "adjust",
            "x.npz",
            "--model",
            name,
        ]) {
            Ok(Cli {
                command: Command::Adjust { model, .. },
                ..
            }) => Some(model),
            _ => None,
        };
        for (names, kind) in [
            (
                ["gru", "GRU", "online", "Online-GRU", "online_gru"],
                ModelKind::Gru,
            ),
            (
                ["bigru", "BiGRU", "offline", "bi-gru", "offline_bigru"],
                ModelKind::BiGru,
            ),
        ] {
            for name in names {
                assert_eq!(model(name), Some(kind), "{name}");
            }
        }
        assert_eq!(model("lstm"), None);
        let cli = Cli::try_parse_from(["blapose-client", "adjust", "x.npz"]).unwrap();
        assert!(matches!(
            cli.command,
            Command::Adjust {
                model: ModelKind::BiGru,
                ..
            }
        ));
        let sex = |name: &str| {
            Cli::try_parse_from(["blapose-client", "adjust", "x.npz", "--sex", name])
                .ok()
                .and_then(|cli| match cli.command {
                    Command::Adjust { io, .. } => io.sex,
                    _ => None,
                })
        };
        assert_eq!(sex("female"), Some(Sex::Female));
        assert_eq!(sex("male"), Some(Sex::Male));
        for refused in ["f", "m", "Female", "MALE", "x"] {
            assert_eq!(sex(refused), None, "{refused}");
        }
    }

    #[test]
    fn json_has_the_documented_shape() {
        let pose: blapose_core::Pose = std::array::from_fn(|j| {
            let j = j as f32;
            [(0.1 * j).sin(), 0.07 * j, (0.3 * j).cos()]
        });
        let big = pose.map(|p| p.map(|v| 1.1 * v));
        let gt = vec![pose; 2];
        let e = evaluate(&[big, big], &gt, &gt).unwrap();
        let v: serde_json::Value = serde_json::to_value(e).unwrap();
        assert_eq!(v["frames"], 2);
        for side in ["before", "after"] {
            let keys: Vec<&String> = v[side].as_object().unwrap().keys().collect();
            assert_eq!(keys, ["bone_error_mm", "mpjpe_mm", "p_mpjpe_mm"], "{v}");
        }
        // The key order as written: mpjpe, p_mpjpe, bone error (no mpjve).
        let text = serde_json::to_string(&e.before).unwrap();
        let at = |k: &str| text.find(k).unwrap();
        assert!(at("\"mpjpe_mm\"") < at("p_mpjpe_mm") && at("p_mpjpe_mm") < at("bone_error_mm"));
        assert!(!text.contains("mpjve"), "{text}");
        assert!(e.to_string().contains("bone error (mm)"));
    }

    /// The shipped walk example's path.
    fn example() -> String {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/cmu_02_02_walk.npz");
        path.to_str().unwrap().to_string()
    }

    /// The file arguments of a `replay` or `adjust` command line.
    fn io(args: &[&str]) -> IoArgs {
        match Cli::try_parse_from(args).unwrap().command {
            Command::Replay { io, .. } | Command::Adjust { io, .. } => io,
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn height_and_sex_become_the_subject() {
        let file = &example();
        let (seq, _) = io(&["blapose-client", "adjust", file]).load().unwrap();
        assert_eq!(seq.subject, None);
        let (seq, _) = io(&[
            "blapose-client",
            "replay",
            file,
            "--height",
            "1.68",
            "--sex",
            "female",
        ])
        .load()
        .unwrap();
        assert_eq!(
            seq.subject,
            Some(Subject {
                height_m: 1.68,
                sex: Some(Sex::Female)
            })
        );
        assert!(
            io(&["blapose-client", "adjust", file, "--sex", "male"])
                .load()
                .is_err(),
            "--sex without a stature"
        );
        assert!(Cli::try_parse_from(["blapose-client", "adjust", file, "--sex", "x"]).is_err());
    }

    #[test]
    fn camera_flag_parses_for_replay_and_adjust() {
        for command in ["replay", "adjust"] {
            let io = |cli: Cli| match cli.command {
                Command::Replay { io, .. } | Command::Adjust { io, .. } => io,
                other => panic!("{other:?}"),
            };
            let default = Cli::try_parse_from(["blapose-client", command, "x.npz"]).unwrap();
            assert!(
                !io(default).camera,
                "{command}: the camera is not sent by default"
            );
            let cli =
                Cli::try_parse_from(["blapose-client", command, "x.npz", "--camera"]).unwrap();
            assert!(io(cli).camera, "{command}");
        }
        assert!(Cli::try_parse_from(["blapose-client", "info", "--camera"]).is_err());
    }

    #[test]
    fn only_camera_sends_the_files_calibration() {
        let file = &example();
        let (with, up) = io(&["blapose-client", "replay", file, "--camera"])
            .load()
            .unwrap();
        assert_eq!(up, with.camera.map(|c| c.up));
        assert!(with.camera.is_some(), "the example carries a calibration");
        let (without, up) = io(&["blapose-client", "adjust", file]).load().unwrap();
        assert!(
            up.is_some(),
            "the report's up direction does not need --camera"
        );
        assert_eq!(without.camera, None);
        assert_eq!(
            Sequence {
                camera: None,
                ..with
            },
            without,
            "only the camera is dropped"
        );
    }
}
