//! The memory an idle session costs, measured from the resident set of
//! this test binary (its only test, so nothing else allocates meanwhile).
//! Target: at most 16 KiB per idle session.

use std::time::Duration;

use blapose_core::layouts::KeypointLayout;
use blapose_server::session::{Coordinates, InputFormat, SessionConfig, SessionStore};

fn resident_bytes() -> Option<usize> {
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: usize = statm.split_whitespace().nth(1)?.parse().ok()?;
    Some(pages * 4096)
}

#[tokio::test]
async fn an_idle_session_costs_well_under_16_kib() {
    let Some(start) = resident_bytes() else {
        println!("skipping: /proc/self/statm not available");
        return;
    };
    let n = 20_000;
    let (store, _guard) = SessionStore::new(n, Duration::from_secs(600));
    let config = SessionConfig {
        input: InputFormat {
            layout: KeypointLayout::Coco17,
            coordinates: Coordinates::Pixels {
                width: 1920,
                height: 1080,
            },
        },
        label: "camera-01".into(),
        lifter_frames: None,
        camera: None,
        subject: None,
        motion: None,
    };
    let mut attachments = Vec::with_capacity(n);
    for _ in 0..n {
        let a = store.open(config.clone()).unwrap();
        // Touch the state as a served session would (pages really resident).
        a.session.lock().hidden.fill(0.5);
        store.detach(&a.session, a.epoch);
        attachments.push(a.session.id());
    }
    let end = resident_bytes().unwrap();
    let per_session = end.saturating_sub(start) / n;
    println!("resident memory per idle session: {per_session} bytes");
    assert_eq!(store.len(), n);
    assert!(per_session < 8 * 1024, "{per_session} bytes per session");
    assert!(
        per_session >= 4 * 1024,
        "{per_session} bytes: the 4 KiB state cannot be missing"
    );
}
