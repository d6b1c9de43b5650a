//! The browser transport (`--web-addr`) from a WebSocket client: the same
//! answers, bit for bit, as the gRPC stream for the same frames, the same
//! typed errors, auth through the subprotocol, query or header, and the
//! bounds that keep a browser from holding the server (a vanished client,
//! an idle socket, an oversize message, too many sockets from one
//! address). Also the page at `/`, built or not.

use crate::support;

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use blapose_proto::v1 as pb;
use blapose_server::{ServerConfig, ServerHandle, WebConfig};
use futures_util::{SinkExt, StreamExt};
use pb::stream_request::Kind as Req;
use pb::stream_response::Kind as Resp;
use prost::Message as _;
use support::{exchange, frame, open, start};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::tungstenite::{self, Message};

type Ws =
    tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>;

/// A server with the browser transport on a free port (the default
/// models, no camera-aware pair: faster to start).
fn config(edit: impl FnOnce(&mut ServerConfig)) -> ServerConfig {
    let mut config = ServerConfig {
        camera_aware: None,
        web: Some(WebConfig::new("127.0.0.1:0".parse().unwrap())),
        ..Default::default()
    };
    edit(&mut config);
    config
}

fn web_addr(server: &ServerHandle) -> SocketAddr {
    server.web_addr().expect("the browser transport is on")
}

/// Connect to the WebSocket offering blapose.v1 (and `protocols`), at
/// `query` (e.g. `?token=x`), with these headers.
async fn connect(
    addr: SocketAddr,
    query: &str,
    protocols: &[&str],
    headers: &[(&'static str, &str)],
) -> Result<Ws, tungstenite::Error> {
    let mut request = format!("ws://{addr}/v1/stream{query}")
        .into_client_request()
        .unwrap();
    let offered = std::iter::once("blapose.v1")
        .chain(protocols.iter().copied())
        .collect::<Vec<_>>()
        .join(", ");
    request
        .headers_mut()
        .insert("sec-websocket-protocol", offered.parse().unwrap());
    for (name, value) in headers {
        request.headers_mut().insert(*name, value.parse().unwrap());
    }
    let (ws, response) = tokio_tungstenite::connect_async(request).await?;
    assert_eq!(
        response.headers()["sec-websocket-protocol"],
        "blapose.v1",
        "the server selects blapose.v1 (browsers require a selected protocol)"
    );
    Ok(ws)
}

/// How a socket ended: the final status (code, message) from the text
/// message and the close code.
#[derive(Debug, Default, PartialEq)]
struct Ending {
    status: Option<(i32, String)>,
    close: Option<u16>,
}

/// Send `requests` (one binary message each), then read answers until
/// the socket closes (sending stops early if the server closed first).
async fn exchange_ws(ws: &mut Ws, requests: &[pb::StreamRequest]) -> (Vec<Resp>, Ending) {
    for r in requests {
        if ws.send(Message::binary(r.encode_to_vec())).await.is_err() {
            break;
        }
    }
    read_all(ws).await
}

async fn read_all(ws: &mut Ws) -> (Vec<Resp>, Ending) {
    let mut answers = Vec::new();
    let mut ending = Ending::default();
    while let Some(message) = tokio::time::timeout(Duration::from_secs(10), ws.next())
        .await
        .expect("the server answers or closes within 10 s")
    {
        match message {
            Ok(Message::Binary(b)) => answers.extend(pb::StreamResponse::decode(b).unwrap().kind),
            Ok(Message::Text(t)) => {
                let v: serde_json::Value = serde_json::from_str(t.as_str()).unwrap();
                let code = v["code"].as_i64().unwrap() as i32;
                assert!(v["status"].as_str().is_some_and(|s| !s.is_empty()), "{v}");
                ending.status = Some((code, v["message"].as_str().unwrap().to_string()));
            }
            Ok(Message::Close(frame)) => {
                ending.close = frame.map(|f| u16::from(f.code));
                break;
            }
            Ok(_) => {}
            Err(e) => {
                eprintln!("read: {e}");
                break;
            }
        }
    }
    (answers, ending)
}

/// Session ids differ between two sessions; everything else must not.
fn without_ids(answers: Vec<Resp>) -> Vec<Vec<u8>> {
    answers
        .into_iter()
        .map(|mut r| {
            match &mut r {
                Resp::Opened(o) => o.session_id.clear(),
                Resp::Closed(c) => c.session_id.clear(),
                _ => {}
            }
            pb::StreamResponse { kind: Some(r) }.encode_to_vec()
        })
        .collect()
}

fn bad_frames(t: u64) -> Vec<pb::StreamRequest> {
    let mut short = frame(t);
    let mut nan = frame(t + 1);
    if let Some(Req::Frame(f)) = &mut short.kind {
        f.keypoints_2d.truncate(10);
    }
    if let Some(Req::Frame(f)) = &mut nan.kind {
        f.pose_3d[4] = f32::NAN;
    }
    vec![short, nan]
}

fn close() -> pb::StreamRequest {
    pb::StreamRequest {
        kind: Some(Req::Close(pb::CloseSession {})),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_same_frames_get_bit_identical_answers_and_errors_on_both_transports() {
    let (server, mut grpc) = start(config(|_| {})).await;
    let mut requests = vec![open()];
    requests.extend((0..12).map(frame));
    requests.extend(bad_frames(12));
    requests.extend((14..24).map(frame));
    requests.push(close());

    let over_grpc = exchange(&mut grpc, &[], requests.clone()).await.unwrap();
    let mut ws = connect(web_addr(&server), "", &[], &[]).await.unwrap();
    let (over_ws, ending) = exchange_ws(&mut ws, &requests).await;
    assert_eq!(
        ending,
        Ending {
            status: None,
            close: Some(1000)
        }
    );
    assert_eq!(support::frames(&over_ws), 22, "{over_ws:?}");
    let errors: Vec<_> = over_ws
        .iter()
        .filter_map(|r| match r {
            Resp::Error(e) => Some((e.frame_index, e.code)),
            _ => None,
        })
        .collect();
    assert_eq!(
        errors,
        vec![
            (12, tonic::Code::InvalidArgument as i32),
            (13, tonic::Code::InvalidArgument as i32)
        ]
    );
    assert!(matches!(over_ws.last(), Some(Resp::Closed(_))));
    assert_eq!(without_ids(over_ws), without_ids(over_grpc));

    // A stream-ending error: the same code and message as gRPC's status.
    let first_a_frame = vec![frame(0)];
    let status = exchange(&mut grpc, &[], first_a_frame.clone())
        .await
        .unwrap_err();
    let mut ws = connect(web_addr(&server), "", &[], &[]).await.unwrap();
    let (answers, ending) = exchange_ws(&mut ws, &first_a_frame).await;
    assert!(answers.is_empty());
    assert_eq!(
        ending,
        Ending {
            status: Some((status.code() as i32, status.message().to_string())),
            close: Some(4000 + status.code() as u16),
        }
    );

    // What only a socket can send wrong: text, or bytes that are no
    // StreamRequest.
    for wrong in [
        Message::text("hello"),
        Message::binary(vec![0xff, 0xff, 0xff]),
    ] {
        let mut ws = connect(web_addr(&server), "", &[], &[]).await.unwrap();
        ws.send(Message::binary(open().encode_to_vec()))
            .await
            .unwrap();
        ws.send(wrong).await.unwrap();
        let (answers, ending) = read_all(&mut ws).await;
        assert!(matches!(answers[..], [Resp::Opened(_)]), "{answers:?}");
        assert_eq!(ending.close, Some(4003), "INVALID_ARGUMENT: {ending:?}");
    }
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_bearer_token_is_required_as_subprotocol_query_or_header() {
    let (server, _) = start(config(|c| c.auth_token = Some("s3cret".into()))).await;
    let addr = web_addr(&server);
    let refused = |r: Result<Ws, tungstenite::Error>| match r {
        Err(tungstenite::Error::Http(response)) => response.status().as_u16(),
        Err(e) => panic!("expected an HTTP refusal, got {e}"),
        Ok(_) => panic!("expected a refusal, the socket opened"),
    };
    assert_eq!(refused(connect(addr, "", &[], &[]).await), 401, "missing");
    assert_eq!(refused(connect(addr, "?token=wrong", &[], &[]).await), 401);
    assert_eq!(
        refused(connect(addr, "", &["bearer.s3cre"], &[]).await),
        401
    );
    let header = [("authorization", "Bearer nope")];
    assert_eq!(
        refused(connect(addr, "?token=s3cret", &[], &header).await),
        401
    );
    for (query, protocols, headers) in [
        ("", &["bearer.s3cret"][..], &[][..]),
        ("?token=s3cret", &[][..], &[][..]),
        ("", &[][..], &[("authorization", "Bearer s3cret")][..]),
    ] {
        let mut ws = connect(addr, query, protocols, headers).await.unwrap();
        let (answers, ending) = exchange_ws(&mut ws, &[open(), frame(0), close()]).await;
        assert_eq!(support::frames(&answers), 1, "{query} {protocols:?}");
        assert_eq!(ending.close, Some(1000));
    }
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_vanishes_frees_its_session_and_a_silent_one_is_closed() {
    let (server, _) = start(config(|c| {
        c.max_sessions = 1;
        c.session_ttl = Duration::from_millis(200);
        if let Some(web) = &mut c.web {
            web.idle_timeout = Duration::from_millis(300);
        }
    }))
    .await;
    let addr = web_addr(&server);
    let mut ws = connect(addr, "", &[], &[]).await.unwrap();
    for r in [open(), frame(0), frame(1)] {
        ws.send(Message::binary(r.encode_to_vec())).await.unwrap();
    }
    // Gone mid-stream, without a close: the TCP connection just drops.
    drop(ws);
    // The one session slot is free again once its session is detached
    // and its TTL passed (a stream still attached would hold it).
    let started = Instant::now();
    let answers = loop {
        let mut ws = connect(addr, "", &[], &[]).await.unwrap();
        let (answers, _) = exchange_ws(&mut ws, &[open(), frame(0), close()]).await;
        if support::frames(&answers) == 1 || started.elapsed() > Duration::from_secs(5) {
            break answers;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    assert_eq!(support::frames(&answers), 1, "{answers:?}");

    // A socket that sends nothing, not even pongs (this client answers
    // pings only while it reads), is closed after the idle timeout.
    let mut ws = connect(addr, "", &[], &[]).await.unwrap();
    ws.send(Message::binary(open().encode_to_vec()))
        .await
        .unwrap();
    tokio::time::sleep(Duration::from_millis(650)).await;
    let (answers, ending) = read_all(&mut ws).await;
    assert!(matches!(answers[..], [Resp::Opened(_)]), "{answers:?}");
    assert_eq!(ending.close, Some(4004), "DEADLINE_EXCEEDED: {ending:?}");
    server.shutdown().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversize_messages_and_too_many_sockets_are_refused() {
    let (server, _) = start(config(|c| {
        c.max_message_bytes = 4096;
        c.connection_limits.max_connections_per_peer = 2;
    }))
    .await;
    let addr = web_addr(&server);
    let mut ws = connect(addr, "", &[], &[]).await.unwrap();
    let mut big = frame(0);
    if let Some(Req::Frame(f)) = &mut big.kind {
        f.confidence = vec![1.0; 2000];
    }
    let (answers, ending) = exchange_ws(&mut ws, &[open(), big]).await;
    assert!(matches!(answers[..], [Resp::Opened(_)]), "{answers:?}");
    let (code, message) = ending.status.clone().expect("a final status");
    assert_eq!(code, tonic::Code::OutOfRange as i32, "{message}");
    assert!(message.contains("--max-message-bytes"), "{message}");
    assert_eq!(ending.close, Some(4011));
    drop(ws);

    // Two sockets from this address are held; the third is refused at
    // accept, and admitted again once one closes.
    let wait_admitted = || async {
        let started = Instant::now();
        loop {
            match connect(addr, "", &[], &[]).await {
                Ok(ws) => return ws,
                Err(e) if started.elapsed() > Duration::from_secs(5) => panic!("{e}"),
                Err(_) => tokio::time::sleep(Duration::from_millis(20)).await,
            }
        }
    };
    let first = wait_admitted().await;
    let _second = wait_admitted().await;
    assert!(connect(addr, "", &[], &[]).await.is_err(), "a third socket");
    drop(first);
    let _third = wait_admitted().await;
    server.shutdown().await.unwrap();
}

/// `GET path` over plain HTTP/1.1: the status code and body.
async fn get(addr: SocketAddr, path: &str) -> (u16, String) {
    let mut tcp = tokio::net::TcpStream::connect(addr).await.unwrap();
    let request = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n");
    tcp.write_all(request.as_bytes()).await.unwrap();
    let mut response = String::new();
    tcp.read_to_string(&mut response).await.unwrap();
    let status = response[9..12].parse().unwrap();
    let body = response.split_once("\r\n\r\n").unwrap().1.to_string();
    (status, body)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_is_served_or_the_server_says_how_to_build_it() {
    let dir = std::env::temp_dir().join(format!("blapose-web-test-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let (server, _) = start(config(|c| {
        if let Some(web) = &mut c.web {
            web.dir = dir.join("missing");
        }
    }))
    .await;
    let (status, body) = get(web_addr(&server), "/").await;
    assert_eq!(status, 503);
    assert!(body.contains("cd web && npm ci"), "{body}");
    // The socket works without the page.
    let mut ws = connect(web_addr(&server), "", &[], &[]).await.unwrap();
    let (answers, _) = exchange_ws(&mut ws, &[open(), frame(0), close()]).await;
    assert_eq!(support::frames(&answers), 1);
    server.shutdown().await.unwrap();

    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("index.html"), "<p>live</p>").unwrap();
    let (server, _) = start(config(|c| {
        if let Some(web) = &mut c.web {
            web.dir = dir.clone();
        }
    }))
    .await;
    assert_eq!(
        get(web_addr(&server), "/").await,
        (200, "<p>live</p>".into())
    );
    assert_eq!(get(web_addr(&server), "/nothing.js").await.0, 404);
    assert_eq!(get(web_addr(&server), "/../Cargo.toml").await.0 / 100, 4);
    server.shutdown().await.unwrap();
    let _ = std::fs::remove_dir_all(&dir);
}

/// `POST path` with a JSON `body` over plain HTTP/1.1: the status code,
/// the response's head and its body.
async fn post(addr: SocketAddr, path: &str, body: &[u8]) -> (u16, String, Vec<u8>) {
    let mut tcp = tokio::net::TcpStream::connect(addr).await.unwrap();
    let head = format!(
        "POST {path} HTTP/1.1\r\nHost: {addr}\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    tcp.write_all(head.as_bytes()).await.unwrap();
    // A refusal may come before the body is read and close the connection.
    let _ = tcp.write_all(body).await;
    let mut response = Vec::new();
    let _ = tcp.read_to_end(&mut response).await;
    let split = response
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("a response head");
    let head = String::from_utf8_lossy(&response[..split]).to_string();
    let status = head[9..12].parse().unwrap();
    (status, head, response[split + 4..].to_vec())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_take_is_downloaded_as_bvh_c3d_trc_or_a_replay_file() {
    let (server, _) = start(config(|c| c.auth_token = Some("s3cret".into()))).await;
    let addr = web_addr(&server);
    let pose: Vec<f32> = (0..17)
        .flat_map(|j| {
            [
                0.05 * j as f32,
                -0.1 * j as f32,
                3.0 + 0.02 * (j % 3) as f32,
            ]
        })
        .collect();
    let mut pose0 = [[0.0f32; 3]; 17];
    for (j, p) in pose0.iter_mut().enumerate() {
        *p = [pose[3 * j], pose[3 * j + 1], pose[3 * j + 2]];
    }
    // Over 2 MB of JSON (axum's default body limit), under the take's 32 MB.
    let frames = 3000;
    let take = serde_json::json!({
        "fps": 30.0,
        "layout": "coco17",
        "image_size": [640, 480],
        "keypoints_2d": vec![200.0f32; frames * 34],
        "confidence": vec![0.8f32; frames * 17],
        "pose_3d": pose.repeat(frames),
        "adjusted": pose.repeat(frames),
        "bone_lengths": blapose_core::bones::bone_lengths(&pose0).to_vec(),
    });
    let body = serde_json::to_vec(&take).unwrap();
    assert!(body.len() > 2 << 20, "{} bytes", body.len());
    let (status, _, text) = post(addr, "/v1/export/bvh", &body).await;
    assert_eq!(status, 401, "{}", String::from_utf8_lossy(&text));
    let (status, head, bvh) = post(addr, "/v1/export/bvh?token=s3cret", &body).await;
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&bvh));
    assert!(head.contains("blapose-take.bvh"), "{head}");
    let bvh = String::from_utf8(bvh).unwrap();
    assert!(
        bvh.starts_with("HIERARCHY") && bvh.contains("Frames: 3000"),
        "{bvh}"
    );
    let (status, _, npz) = post(addr, "/v1/export/npz?token=s3cret", &body).await;
    assert_eq!(status, 200);
    let back = blapose_data::replay::sequence::Sequence::read_from(
        std::io::Cursor::new(npz),
        "take.npz",
        None,
        10_000,
    )
    .expect("the replay file reads back");
    assert_eq!(back.pose_3d.len(), frames);
    // Bad takes are named; an oversized one is refused before it is read.
    let (status, _, text) = post(addr, "/v1/export/bvh?token=s3cret", b"{\"fps\": 30}").await;
    assert_eq!(status, 400);
    assert!(String::from_utf8_lossy(&text).contains("not valid JSON"));
    let (status, _, text) = post(addr, "/v1/export/gif?token=s3cret", &body).await;
    assert_eq!(status, 400);
    assert!(String::from_utf8_lossy(&text).contains("unknown export format"));
    let huge = vec![b' '; blapose_server::web::export::MAX_TAKE_BYTES + 1];
    assert_eq!(
        post(addr, "/v1/export/bvh?token=s3cret", &huge).await.0,
        413
    );
    // The server still streams.
    let mut ws = connect(addr, "?token=s3cret", &[], &[]).await.unwrap();
    let (answers, _) = exchange_ws(&mut ws, &[open(), frame(0), close()]).await;
    assert_eq!(support::frames(&answers), 1);
    server.shutdown().await.unwrap();
}

/// Read until `n` answers arrived (the socket stays open).
async fn read_n(ws: &mut Ws, n: usize) -> Vec<Resp> {
    let mut answers = Vec::new();
    while answers.len() < n {
        let message = tokio::time::timeout(Duration::from_secs(10), ws.next())
            .await
            .expect("answers within 10 s")
            .expect("the socket is open")
            .unwrap();
        if let Message::Binary(b) = message {
            answers.extend(pb::StreamResponse::decode(b).unwrap().kind);
        }
    }
    answers
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sessions_and_tokens_are_shared_with_grpc_and_shutdown_drains_sockets() {
    let key =
        blapose_server::token::SessionKey::parse("hex:000102030405060708090a0b0c0d0e0f").unwrap();
    let (server, mut grpc) = start(config(|c| c.session_key = Some(key))).await;
    // Opened over the socket (with a session token), resumed over gRPC.
    let mut ws = connect(web_addr(&server), "", &[], &[]).await.unwrap();
    for r in [open(), frame(0), frame(1)] {
        ws.send(Message::binary(r.encode_to_vec())).await.unwrap();
    }
    let answers = read_n(&mut ws, 3).await;
    let Resp::Opened(opened) = &answers[0] else {
        panic!("{answers:?}")
    };
    assert!(!opened.session_token.is_empty(), "a token, as on gRPC");
    drop(ws);
    let resume = pb::StreamRequest {
        kind: Some(Req::Resume(pb::ResumeSession {
            session_id: opened.session_id.clone(),
            ..Default::default()
        })),
    };
    let answers = exchange(&mut grpc, &[], vec![resume, frame(2), close()])
        .await
        .unwrap();
    let Resp::Opened(resumed) = &answers[0] else {
        panic!("{answers:?}")
    };
    assert!(resumed.resumed);
    assert_eq!(resumed.frames_seen, 2);

    // Shutdown: the socket's frames are answered, a last token sent (the
    // stream asked for tokens), then UNAVAILABLE.
    let mut ws = connect(web_addr(&server), "", &[], &[]).await.unwrap();
    for r in [open(), frame(0)] {
        ws.send(Message::binary(r.encode_to_vec())).await.unwrap();
    }
    read_n(&mut ws, 2).await;
    let stopped = tokio::spawn(server.shutdown());
    let (answers, ending) = read_all(&mut ws).await;
    assert!(matches!(answers[..], [Resp::Token(_)]), "{answers:?}");
    assert_eq!(ending.close, Some(4014), "{ending:?}");
    assert_eq!(
        ending.status.map(|s| s.0),
        Some(tonic::Code::Unavailable as i32)
    );
    stopped.await.unwrap().unwrap();
}
