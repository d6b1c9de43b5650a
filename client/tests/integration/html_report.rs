//! The HTML report of `blapose-client replay --html`, end to end: the
//! command line itself replays an example through a server started here
//! (with the shipped, embedded weights) and writes the report, the result
//! npz and the JSON; the page is then read back: it carries the file's
//! poses, the server's answers, the ground truth and the client's
//! before/after table, and nothing remote. The report is the binary's (it
//! sits beside the library), so it is tested through the binary. Without
//! embedded weights the test says so and passes vacuously.

use std::path::{Path, PathBuf};
use std::process::Command;

use blapose_client::sequence::read_adjusted;
use blapose_client::{evaluate, Sequence};
use blapose_core::Pose;
use blapose_server::{ServerConfig, WeightsSource};

/// The page the binary fills (the Python package ships the same file).
const TEMPLATE: &str = include_str!("../../../python/src/blapose/report_template.html");
/// The data's `format` field.
const FORMAT: &str = "blapose-report/1";

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The JSON data embedded in a report page.
fn embedded_data(html: &str) -> Option<serde_json::Value> {
    const START: &str = r#"<script id="blapose-data" type="application/json">"#;
    let start = html.find(START)? + START.len();
    let end = start + html[start..].find("</script>")?;
    serde_json::from_str(&html[start..end]).ok()
}

/// `flat` (the page's metres, rounded to 0.1 mm) equals `poses`.
fn assert_poses(what: &str, flat: &serde_json::Value, poses: &[Pose]) {
    let flat = flat
        .as_array()
        .unwrap_or_else(|| panic!("{what} is an array"));
    assert_eq!(flat.len(), poses.len() * 17 * 3, "{what}");
    for (i, v) in flat.iter().enumerate() {
        let want = f64::from(poses[i / 51][(i % 51) / 3][i % 3]);
        let got = v
            .as_f64()
            .unwrap_or_else(|| panic!("{what}[{i}] is a number"));
        assert!(
            (got - want).abs() <= 0.5e-4 + 1e-9,
            "{what}[{i}]: {got} vs {want}"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replay_writes_a_self_contained_html_report() {
    if blapose_server::embedded_gru().is_none() {
        println!("skipping the HTML report test: the server was built without embedded weights (models/ is empty)");
        return;
    }
    let config = ServerConfig {
        weights: WeightsSource::Embedded,
        bigru_weights: WeightsSource::Embedded,
        camera_aware: None,
        metrics_addr: None,
        ..ServerConfig::default()
    };
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("bind loopback");
    let addr = listener.local_addr().expect("local addr");
    let server = blapose_server::spawn(config, listener)
        .await
        .expect("server starts");
    let url = format!("http://{addr}");

    let file = workspace_root().join("examples/cmu_02_02_walk.npz");
    let dir = std::env::temp_dir().join(format!("blapose-cli-report-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let (html_path, out_path, json_path) = (
        dir.join("report.html"),
        dir.join("out.npz"),
        dir.join("metrics.json"),
    );
    let args: Vec<String> = vec![
        "--server".into(),
        url.clone(),
        "replay".into(),
        file.display().to_string(),
        "--html".into(),
        html_path.display().to_string(),
        "--out".into(),
        out_path.display().to_string(),
        "--json".into(),
        json_path.display().to_string(),
    ];
    let output = tokio::task::spawn_blocking(move || {
        Command::new(env!("CARGO_BIN_EXE_blapose-client"))
            .args(&args)
            .output()
            .expect("the CLI runs")
    })
    .await
    .expect("join");
    assert!(
        output.status.success(),
        "blapose-client replay failed:\n{}\n{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        stdout.contains(&format!("wrote {}", html_path.display())),
        "{stdout}"
    );
    let html = std::fs::read_to_string(&html_path).expect("report readable");
    let (adjusted, _) = read_adjusted(&out_path).expect("the --out file");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json_path).expect("the --json file"))
            .expect("JSON");
    std::fs::remove_dir_all(&dir).ok();
    // As the CLI reads it: the file's calibration (not sent without
    // --camera) still gives the report its up direction.
    let seq = Sequence::load(&file, None).expect("example loads");
    let up = seq.camera.map(|c| c.up);
    assert_eq!(adjusted.len(), seq.len());

    // The template around the data is unchanged.
    let v = embedded_data(&html).expect("the page embeds its data");
    assert!(html.starts_with(&TEMPLATE[..TEMPLATE.find("__BLAPOSE").unwrap()]));
    assert_eq!(v["format"], FORMAT);
    assert_eq!(v["title"], "cmu_02_02_walk.npz");
    assert_eq!(v["frames"], seq.len());
    assert_eq!(v["fps"], 50.0);
    assert_eq!(v["skeleton"]["bone_names"][1], "r_thigh");
    assert_poses("before", &v["before"], &seq.pose_3d);
    assert_poses("after", &v["after"], &adjusted);
    assert_poses("gt", &v["gt"], seq.gt_3d.as_deref().expect("gt"));
    let up_json: Vec<f64> = (0..3).map(|i| v["up"][i].as_f64().unwrap()).collect();
    assert_eq!(up_json, up.unwrap().map(f64::from).to_vec());
    // The client's table, as `replay` prints it and writes it to --json.
    let evaluation =
        evaluate(&seq.pose_3d, &adjusted, seq.gt_3d.as_deref().unwrap()).expect("metrics");
    assert_eq!(json["frames"], seq.len());
    for (side, m) in [("before", evaluation.before), ("after", evaluation.after)] {
        for (key, value) in [
            ("mpjpe_mm", m.mpjpe_mm),
            ("p_mpjpe_mm", m.p_mpjpe_mm),
            ("bone_error_mm", m.bone_error_mm),
        ] {
            assert_eq!(
                v["metrics"][side][key].as_f64(),
                Some(value),
                "{side}.{key}"
            );
            assert_eq!(json[side][key].as_f64(), Some(value), "--json {side}.{key}");
        }
    }
    let header: Vec<String> = v["info"]
        .as_array()
        .unwrap()
        .iter()
        .map(|kv| format!("{}={}", kv[0].as_str().unwrap(), kv[1].as_str().unwrap()))
        .collect();
    assert!(
        header
            .iter()
            .any(|h| h.starts_with("model=gru (default, stream)")),
        "{header:?}"
    );
    assert!(
        header
            .iter()
            .any(|h| h.starts_with(&format!("server={url} (blapose-server "))),
        "{header:?}"
    );
    assert!(
        header.iter().any(|h| h.starts_with("weights=")),
        "{header:?}"
    );

    // Offline: no remote script, style sheet or image.
    let lower = html.to_ascii_lowercase();
    for remote in [
        "src=\"http",
        "href=\"http",
        "<link",
        "<img",
        "url(http",
        "<script src",
    ] {
        assert!(!lower.contains(remote), "the report references {remote}");
    }
    // 0.1 mm rounding keeps it small: ~1.3 kB a frame for three pose sets.
    assert!(
        html.len() < 60_000 + 1_500 * seq.len(),
        "{} bytes",
        html.len()
    );
    server.shutdown().await.expect("clean shutdown");
}
