// TEMPORARY local load check (not to be committed).
use blapose_proto::v1 as pb;
use pb::pose_adjustment_client::PoseAdjustmentClient;
use pb::stream_request::Kind as Req;
use pb::stream_response::Kind as Resp;
use std::time::{Duration, Instant};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;

fn open() -> pb::StreamRequest {
    pb::StreamRequest {
        kind: Some(Req::Open(pb::OpenSession {
            input_format: Some(pb::InputFormat {
                layout: 1,
                coordinates: Some(pb::input_format::Coordinates::ImageSize(pb::ImageSize {
                    width: 1000,
                    height: 1000,
                })),
            }),
            model: 0,
            client_label: String::new(),
        })),
    }
}
fn frame(i: u64) -> pb::StreamRequest {
    let mut p = Vec::new();
    for j in 0..17 {
        p.extend([
            0.1 * j as f32,
            0.05 * (j * j) as f32 % 0.7,
            4.0 + 0.01 * j as f32,
        ]);
    }
    pb::StreamRequest {
        kind: Some(Req::Frame(pb::Frame {
            frame_index: i,
            keypoints_2d: (0..34)
                .map(|k| 400.0 + (k as f32 * 7.0 + i as f32) % 200.0)
                .collect(),
            confidence: vec![],
            pose_3d: p,
        })),
    }
}

async fn run_stream(addr: String, frames: u64, window: usize) -> Vec<Duration> {
    let mut c = PoseAdjustmentClient::connect(addr).await.unwrap();
    let (tx, rx) = mpsc::channel(1024);
    let mut resp = c
        .stream(ReceiverStream::new(rx))
        .await
        .unwrap()
        .into_inner();
    tx.send(open()).await.unwrap();
    resp.message().await.unwrap();
    let mut sent_at = std::collections::VecDeque::new();
    let mut lat = Vec::new();
    let mut sent = 0u64;
    while (lat.len() as u64) < frames {
        while sent < frames && sent_at.len() < window {
            tx.send(frame(sent)).await.unwrap();
            sent_at.push_back(Instant::now());
            sent += 1;
        }
        match resp.message().await.unwrap().and_then(|r| r.kind) {
            Some(Resp::Frame(_)) => {}
            other => panic!("{other:?}"),
        }
        lat.push(sent_at.pop_front().unwrap().elapsed());
    }
    lat
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore]
async fn load() {
    let streams: usize = std::env::var("STREAMS").unwrap().parse().unwrap();
    let window: usize = std::env::var("WINDOW").unwrap().parse().unwrap();
    let frames: u64 = std::env::var("FRAMES").unwrap().parse().unwrap();
    let addr = std::env::var("ADDR").unwrap();
    let t = Instant::now();
    let hs: Vec<_> = (0..streams)
        .map(|_| tokio::spawn(run_stream(addr.clone(), frames, window)))
        .collect();
    let mut all = Vec::new();
    for h in hs {
        all.extend(h.await.unwrap());
    }
    let el = t.elapsed();
    all.sort();
    let p = |q: f64| all[((all.len() as f64 - 1.0) * q) as usize];
    println!(
        "streams {streams} window {window}: {} frames in {:?} = {:.0} fps; p50 {:?} p99 {:?}",
        all.len(),
        el,
        all.len() as f64 / el.as_secs_f64(),
        p(0.5),
        p(0.99)
    );
}
