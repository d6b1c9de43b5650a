//! The `token` case: one session token resumed on two replicas sharing a
//! key, and the tokens the copies issue, held to server/README.md's token
//! rules.

use std::time::{Duration, Instant};

use anyhow::{ensure, Context, Result};
use blapose_proto::v1 as pb;
use pb::pose_adjustment_client::PoseAdjustmentClient;
use pb::stream_request::Kind as Req;
use pb::stream_response::Kind as Resp;
use tonic::transport::Channel;
use tonic::Code;

use crate::client::{connect, frames, open, opened, round_trip, start, Stream};

/// A fresh token for the session of `stream` (a `TokenRequest`'s answer).
async fn token_of(stream: &mut Stream) -> Result<Vec<u8>> {
    stream
        .tx
        .send(pb::StreamRequest {
            kind: Some(Req::TokenRequest(pb::TokenRequest {})),
        })
        .await?;
    while let Some(r) = stream.rx.message().await? {
        if let Some(Resp::Token(t)) = r.kind {
            return Ok(t.token);
        }
    }
    Ok(Vec::new())
}

/// Resume `id` with `token` on `client`; the stream and its opening.
async fn resume(
    client: &mut PoseAdjustmentClient<Channel>,
    id: &str,
    token: &[u8],
) -> Result<(Stream, pb::SessionOpened), tonic::Status> {
    let first = Req::Resume(pb::ResumeSession {
        session_id: id.to_owned(),
        session_token: token.to_vec(),
        session_tokens: true,
    });
    let mut stream = start(client, first, None).await?;
    let o = opened(&mut stream).await?;
    Ok((stream, o))
}

/// Resume `id` with `token` on a new connection to `url`, which the token
/// rules say must be refused with FAILED_PRECONDITION (printed); anything
/// else is a failure, described.
async fn refused(url: &str, id: &str, token: &[u8], what: &str) -> Result<Option<String>> {
    let mut c = connect(url).await?;
    Ok(match resume(&mut c, id, token).await {
        Err(s) if s.code() == Code::FailedPrecondition => {
            println!("  {what}: refused: {}", s.message());
            None
        }
        Err(s) => Some(format!(
            "{what}: {} (expected FAILED_PRECONDITION): {}",
            s.code(),
            s.message()
        )),
        Ok(_) => Some(format!("not enforced: {what} restored the closed session")),
    })
}

/// Whether `stream` still answers a frame; the status it ended with if not.
async fn answers(stream: &mut Stream, frame: &pb::Frame) -> Result<(), tonic::Status> {
    round_trip(stream, frame)
        .await
        .map(|_| ())
        .map_err(|e| match e.downcast::<tonic::Status>() {
            Ok(status) => status,
            Err(e) => tonic::Status::unknown(e.to_string()),
        })
}

/// The token rules of server/README.md under abuse: one live copy per
/// replica (a second resume of the same token takes the session over, the
/// first stream ends ABORTED), a closed session's token refused where it
/// was closed, and after the TTL of the first token neither it nor a token
/// the replica's copy issued restores the closed session on any replica.
/// Two replicas may each restore one copy (documented, bounded by
/// --token-ttl).
pub(crate) async fn token(url: &str, replica: &str, ttl: Duration) -> Result<()> {
    println!("case token: one session token resumed on two replicas (token TTL {ttl:?})");
    let (format, frames) = frames()?;
    let mut a = connect(url).await?;
    let mut stream = start(&mut a, open(&format, true), None).await?;
    let session = opened(&mut stream).await?;
    let issued = Instant::now();
    let id = session.session_id.clone();
    for frame in &frames[..10] {
        round_trip(&mut stream, frame).await?;
    }
    let token = token_of(&mut stream).await?;
    ensure!(
        !token.is_empty(),
        "no session token: start the replicas with --session-key"
    );
    drop(stream);
    tokio::time::sleep(Duration::from_millis(100)).await;

    // The token on both replicas at once, then again on the origin.
    let mut b = connect(replica).await?;
    let mut a1 = connect(url).await?;
    let mut a2 = connect(url).await?;
    let (on_b, on_a) = tokio::join!(resume(&mut b, &id, &token), resume(&mut a1, &id, &token));
    let (mut on_b, _) = on_b.context("resume on the replica")?;
    let (mut first_a, _) = on_a.context("resume on the origin")?;
    answers(&mut on_b, &frames[10]).await?;
    answers(&mut first_a, &frames[10]).await?;
    println!("  resumed on both replicas (one copy each, as documented: bounded by the token TTL)");
    // The replica's copy issues tokens of its own: the chain the copy
    // started. They must expire with the first token, not TTL after they
    // were issued.
    let chained = token_of(&mut on_b).await?;
    ensure!(
        chained != token,
        "the replica's copy issued no token of its own"
    );
    let (mut second_a, _) = resume(&mut a2, &id, &token)
        .await
        .context("second resume on the origin")?;
    answers(&mut second_a, &frames[10]).await?;
    let mut failures = Vec::new();
    match answers(&mut first_a, &frames[11]).await {
        Err(s) if s.code() == Code::Aborted => {
            println!("  a second resume on the origin took the session over: the first stream ended ABORTED")
        }
        other => failures.push(format!(
            "not enforced: two live copies on one replica (the first stream: {other:?})"
        )),
    }

    // Close it on the origin: its token is refused there afterwards.
    second_a
        .tx
        .send(pb::StreamRequest {
            kind: Some(Req::Close(pb::CloseSession {})),
        })
        .await?;
    while let Ok(Some(r)) = second_a.rx.message().await {
        if matches!(r.kind, Some(Resp::Closed(_))) {
            break;
        }
    }
    failures.extend(refused(url, &id, &token, "after close, the token on the origin").await?);

    // Expired: refused on every replica.
    tokio::time::sleep(
        (issued + ttl + Duration::from_millis(500)).saturating_duration_since(Instant::now()),
    )
    .await;
    drop(on_b);
    let tokens = [("first", &token), ("replica copy's", &chained)];
    for ((name, url), (which, token)) in [("replica", replica), ("origin", url)]
        .into_iter()
        .flat_map(|r| tokens.map(|t| (r, t)))
    {
        let what = format!("the {which} token, expired, on the {name}");
        failures.extend(refused(url, &id, token, &what).await?);
    }
    for f in &failures {
        println!("  FAIL: {f}");
    }
    ensure!(
        failures.is_empty(),
        "{} token rule(s) do not hold",
        failures.len()
    );
    Ok(())
}
