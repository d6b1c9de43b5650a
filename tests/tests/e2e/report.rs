//! The HTML report of `blapose-client replay --html`, end to end: an
//! example replayed through a server with the shipped (embedded) weights,
//! the report built and written by the library calls the CLI makes
//! (`ReportData::from_adjusted`, `add_server_info`, `write`), then read
//! back: the page carries the file's poses, the server's answers, the
//! ground truth and the client's before/after table, and nothing remote.
//! Without embedded weights the test says so and passes vacuously.

use blapose_client::html::{embedded_data, FORMAT, TEMPLATE};
use blapose_client::{evaluate, replay, ReplayOptions, ReportData, Sequence};
use blapose_core::Pose;
use blapose_server::{ServerConfig, WeightsSource};
use blapose_tests::{workspace_root, TestServer};

/// `flat` (the page's metres, rounded to 0.1 mm) equals `poses`.
fn assert_poses(what: &str, flat: &blapose_client::html::JsonValue, poses: &[Pose]) {
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
        ..blapose_tests::test_config()
    };
    let server = TestServer::start(config).await;
    let client = server.client().await;
    let file = workspace_root().join("examples/cmu_02_02_walk.npz");
    let mut seq = Sequence::load(&file, None).expect("example loads");
    let up = seq.camera.map(|c| c.up);
    seq.camera = None; // as the CLI without --camera
    let result = replay(&client, &seq, &ReplayOptions::default(), |_| {})
        .await
        .expect("replay");

    let mut data =
        ReportData::from_adjusted("cmu_02_02_walk.npz", &seq, &result, up).expect("report data");
    let info = client.model_info().await.expect("model info");
    data.add_server_info(&server.url(), &info, &result);
    let path = std::env::temp_dir().join(format!("blapose-e2e-report-{}.html", std::process::id()));
    data.write(&path).expect("report written");
    let html = std::fs::read_to_string(&path).expect("report readable");
    std::fs::remove_file(&path).ok();

    // The template around the data is unchanged.
    let v = embedded_data(&html).expect("the page embeds its data");
    assert!(html.starts_with(&TEMPLATE[..TEMPLATE.find("__BLAPOSE").unwrap()]));
    assert_eq!(v["format"], FORMAT);
    assert_eq!(v["title"], "cmu_02_02_walk.npz");
    assert_eq!(v["frames"], seq.len());
    assert_eq!(v["fps"], 50.0);
    assert_eq!(v["skeleton"]["bone_names"][1], "r_thigh");
    assert_poses("before", &v["before"], &seq.pose_3d);
    assert_poses("after", &v["after"], &result.adjusted);
    assert_poses("gt", &v["gt"], seq.gt_3d.as_deref().expect("gt"));
    let up_json: Vec<f64> = (0..3).map(|i| v["up"][i].as_f64().unwrap()).collect();
    assert_eq!(up_json, up.unwrap().map(f64::from).to_vec());
    // The client's table, as `replay` prints it.
    let evaluation = evaluate(
        &seq.pose_3d,
        &result.adjusted,
        seq.gt_3d.as_deref().unwrap(),
    )
    .expect("metrics");
    for (side, m) in [("before", evaluation.before), ("after", evaluation.after)] {
        assert_eq!(v["metrics"][side]["mpjpe_mm"].as_f64(), Some(m.mpjpe_mm));
        assert_eq!(
            v["metrics"][side]["p_mpjpe_mm"].as_f64(),
            Some(m.p_mpjpe_mm)
        );
        assert_eq!(
            v["metrics"][side]["bone_error_mm"].as_f64(),
            Some(m.bone_error_mm)
        );
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
            .any(|h| h.starts_with("server=http://127.0.0.1:")),
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
    server.shutdown().await;
}
