//! Helpers the per-client limit tests share ([`super::quota`],
//! [`super::haproxy`], [`super::web`]): a plain normalized-keypoint session,
//! its frames, and one stream run with request headers.

use blapose_proto::v1 as pb;
use blapose_server::{ServerConfig, ServerHandle};
use pb::pose_adjustment_client::PoseAdjustmentClient;
use pb::stream_request::Kind as Req;
use pb::stream_response::Kind as Resp;
use tokio_stream::StreamExt;
use tonic::transport::Channel;

/// An in-process server on loopback and a client of it.
pub async fn start(config: ServerConfig) -> (ServerHandle, PoseAdjustmentClient<Channel>) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let server = blapose_server::spawn(config, listener).await.unwrap();
    let client = PoseAdjustmentClient::connect(format!("http://{}", server.local_addr()))
        .await
        .unwrap();
    (server, client)
}

/// Open a session of normalized Human3.6M-17 keypoints that asks for tokens.
pub fn open() -> pb::StreamRequest {
    pb::StreamRequest {
        kind: Some(Req::Open(pb::OpenSession {
            input_format: Some(pb::InputFormat {
                layout: pb::KeypointLayout::H36m17 as i32,
                coordinates: Some(pb::input_format::Coordinates::Normalized(true)),
            }),
            session_tokens: true,
            ..Default::default()
        })),
    }
}

/// Frame `t`: a pose 4 m away and its projection.
pub fn frame(t: u64) -> pb::StreamRequest {
    let pose: Vec<f32> = (0..17)
        .flat_map(|j| {
            let j = j as f32;
            [0.1 * j.sin(), 0.1 * j.cos() + 0.01 * t as f32, 4.0]
        })
        .collect();
    let keypoints = pose
        .chunks(3)
        .flat_map(|p| [p[0] / p[2], p[1] / p[2]])
        .collect();
    pb::StreamRequest {
        kind: Some(Req::Frame(pb::Frame {
            frame_index: t,
            keypoints_2d: keypoints,
            pose_3d: pose,
            confidence: vec![],
        })),
    }
}

/// Run `requests` on one stream with these request headers; the
/// responses, or the status it ended with.
pub async fn exchange(
    client: &mut PoseAdjustmentClient<Channel>,
    headers: &[(&'static str, &str)],
    requests: Vec<pb::StreamRequest>,
) -> Result<Vec<Resp>, tonic::Status> {
    let mut request = tonic::Request::new(tokio_stream::iter(requests));
    for (name, value) in headers {
        request.metadata_mut().insert(*name, value.parse().unwrap());
    }
    let mut inbound = client.stream(request).await?.into_inner();
    let mut out = Vec::new();
    while let Some(m) = inbound.next().await {
        out.extend(m?.kind);
    }
    Ok(out)
}

/// How many frames `answers` holds.
pub fn frames(answers: &[Resp]) -> usize {
    answers
        .iter()
        .filter(|r| matches!(r, Resp::Frame(_)))
        .count()
}
