//! Session lifecycle: detach and resume with state intact, TTL eviction,
//! takeover, explicit close, unguessable ids and the session limit.
//!
//! The TTL is real time (sub-second): tokio's paused clock does not reach
//! across a gRPC connection to the server's purge task.

use std::time::Duration;

use blapose_client::{ClientError, KeypointLayout, Sequence};
use blapose_tests::{
    lengths_diff, pose_diff, synthetic_sequence, test_config, Reference, TestServer, TOLERANCE,
};
use tonic::Code;

const TTL: Duration = Duration::from_millis(400);
const DRAIN: Duration = Duration::from_secs(5);

fn code(result: Result<impl std::fmt::Debug, ClientError>) -> Code {
    match result {
        Err(e) => e.code().unwrap_or_else(|| panic!("no status code in {e}")),
        Ok(v) => panic!("expected an error status, got {v:?}"),
    }
}

fn short_ttl_config() -> blapose_server::ServerConfig {
    blapose_server::ServerConfig {
        session_ttl: TTL,
        ..test_config()
    }
}

/// Send frames `range` of `seq` one by one on `session`, checking each
/// against the library path over the whole sequence.
async fn send_checked(
    session: &mut blapose_client::Session,
    seq: &Sequence,
    range: std::ops::Range<usize>,
    want: &(Vec<blapose_core::Pose>, Vec<blapose_core::BoneLengths>),
) {
    for t in range {
        let got = session.adjust(&seq.frame(t)).await.expect("frame answered");
        assert_eq!(got.frames_seen, t as u64 + 1);
        assert!(pose_diff(&got.pose, &want.0[t]) < TOLERANCE, "frame {t}");
        assert!(
            lengths_diff(&got.bone_lengths, &want.1[t]) < TOLERANCE,
            "frame {t}"
        );
    }
}

#[tokio::test]
async fn detached_session_resumes_with_state_intact_until_its_ttl() {
    let server = TestServer::start(short_ttl_config()).await;
    let client = server.client().await;
    let reference = Reference::new();
    let seq = synthetic_sequence(21, 12, KeypointLayout::Sh16);
    let want = reference.online(&seq);

    let mut session = client
        .open_session(seq.input_format, Some("resume-test"))
        .await
        .expect("open");
    assert_eq!(session.info().ttl, TTL);
    send_checked(&mut session, &seq, 0..6, &want).await;
    let id = session.detach(DRAIN).await;

    // Resume on a new connection: same state, as if never interrupted.
    let other = server.client().await;
    let mut resumed = other.resume_session(&id).await.expect("resume within TTL");
    let info = resumed.info().clone();
    assert!(info.resumed);
    assert_eq!(info.session_id, id);
    assert_eq!(info.frames_seen, 6);
    assert_eq!(info.input_format, seq.input_format);
    assert!(lengths_diff(&info.bone_lengths.expect("estimate"), &want.1[5]) < TOLERANCE);
    send_checked(&mut resumed, &seq, 6..12, &want).await;
    let id = resumed.detach(DRAIN).await;

    // Past the TTL the session is gone.
    tokio::time::sleep(TTL * 2 + Duration::from_millis(200)).await;
    assert_eq!(code(client.resume_session(&id).await), Code::NotFound);
    assert_eq!(code(client.close_session(&id).await), Code::NotFound);
    server.shutdown().await;
}

#[tokio::test]
async fn attached_sessions_are_not_evicted() {
    let server = TestServer::start(short_ttl_config()).await;
    let client = server.client().await;
    let reference = Reference::new();
    let seq = synthetic_sequence(22, 3, KeypointLayout::H36m17);
    let want = reference.online(&seq);
    let mut session = client
        .open_session(seq.input_format, None)
        .await
        .expect("open");
    send_checked(&mut session, &seq, 0..1, &want).await;
    // Idle but attached for longer than the TTL.
    tokio::time::sleep(TTL * 2).await;
    send_checked(&mut session, &seq, 1..3, &want).await;
    let summary = session.close().await.expect("close");
    assert_eq!(summary.frames_seen, 3);
    server.shutdown().await;
}

#[tokio::test]
async fn resume_takes_over_an_attached_stream() {
    let server = TestServer::start(test_config()).await;
    let client = server.client().await;
    let seq = synthetic_sequence(23, 4, KeypointLayout::H36m17);
    let mut first = client
        .open_session(seq.input_format, None)
        .await
        .expect("open");
    first.adjust(&seq.frame(0)).await.expect("frame");
    let id = first.id().to_string();

    let mut second = client.resume_session(&id).await.expect("takeover");
    assert_eq!(second.info().frames_seen, 1);
    // The old stream ends with ABORTED; the new one carries on.
    let ended = match first.next_event().await {
        Ok(Some(event)) => panic!("unexpected event on the old stream: {event:?}"),
        Ok(None) => panic!("old stream ended with OK"),
        Err(e) => e,
    };
    assert_eq!(ended.code(), Some(Code::Aborted), "{ended}");
    let got = second
        .adjust(&seq.frame(1))
        .await
        .expect("frame on new stream");
    assert_eq!(got.frames_seen, 2);
    server.shutdown().await;
}

#[tokio::test]
async fn close_rpc_deletes_a_detached_session() {
    let server = TestServer::start(test_config()).await;
    let client = server.client().await;
    let seq = synthetic_sequence(24, 3, KeypointLayout::H36m17);
    let mut session = client
        .open_session(seq.input_format, None)
        .await
        .expect("open");
    for t in 0..3 {
        session.adjust(&seq.frame(t)).await.expect("frame");
    }
    let id = session.detach(DRAIN).await;
    let summary = client.close_session(&id).await.expect("close by id");
    assert_eq!(summary.frames_seen, 3);
    assert!(summary.bone_lengths.is_some());
    assert_eq!(code(client.resume_session(&id).await), Code::NotFound);
    assert_eq!(code(client.close_session(&id).await), Code::NotFound);

    // A stream-closed session cannot be resumed either.
    let session = client
        .open_session(seq.input_format, None)
        .await
        .expect("open");
    let id = session.id().to_string();
    session.close().await.expect("close");
    assert_eq!(code(client.resume_session(&id).await), Code::NotFound);
    server.shutdown().await;
}

/// Knowing the id is the credential, so ids must not be guessable and a
/// session exists only on the server that issued it.
#[tokio::test]
async fn guessed_and_foreign_session_ids_are_refused() {
    let server = TestServer::start(test_config()).await;
    let foreign_server = TestServer::start(test_config()).await;
    let client = server.client().await;
    let foreign_client = foreign_server.client().await;
    let seq = synthetic_sequence(25, 1, KeypointLayout::H36m17);

    let session = client
        .open_session(seq.input_format, None)
        .await
        .expect("open");
    let id = session.detach(DRAIN).await;
    let foreign = foreign_client
        .open_session(seq.input_format, None)
        .await
        .expect("open");
    let foreign_id = foreign.detach(DRAIN).await;
    assert_ne!(id, foreign_id);

    // A neighbour of a real id (one hex digit changed).
    let mut neighbour: Vec<char> = id.chars().collect();
    neighbour[31] = if neighbour[31] == '0' { '1' } else { '0' };
    let neighbour: String = neighbour.into_iter().collect();
    let guesses = [
        foreign_id.clone(),
        neighbour,
        "0".repeat(32),
        "f".repeat(32),
        format!("{id}00"),
        id[..31].to_string(),
        "not-a-session".to_string(),
        String::new(),
        "../../etc/passwd".to_string(),
    ];
    for guess in &guesses {
        assert_eq!(
            code(client.resume_session(guess).await),
            Code::NotFound,
            "resume {guess:?}"
        );
        assert_eq!(
            code(client.close_session(guess).await),
            Code::NotFound,
            "close {guess:?}"
        );
    }
    // The real ids still work on their own servers.
    client.resume_session(&id).await.expect("own id resumes");
    foreign_client
        .resume_session(&foreign_id)
        .await
        .expect("own id resumes");
    server.shutdown().await;
    foreign_server.shutdown().await;
}

#[tokio::test]
async fn session_limit_is_resource_exhausted_until_one_closes() {
    let config = blapose_server::ServerConfig {
        max_sessions: 3,
        ..test_config()
    };
    let server = TestServer::start(config).await;
    let client = server.client().await;
    let format = synthetic_sequence(26, 1, KeypointLayout::H36m17).input_format;
    let mut open = Vec::new();
    for _ in 0..3 {
        open.push(
            client
                .open_session(format, None)
                .await
                .expect("within limit"),
        );
    }
    assert_eq!(
        code(client.open_session(format, None).await),
        Code::ResourceExhausted
    );
    // Detached sessions still count against the limit.
    let detached = open.pop().expect("session").detach(DRAIN).await;
    assert_eq!(
        code(client.open_session(format, None).await),
        Code::ResourceExhausted
    );
    client.close_session(&detached).await.expect("close");
    client
        .open_session(format, None)
        .await
        .expect("room again after close");
    server.shutdown().await;
}
