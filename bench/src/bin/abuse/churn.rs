//! The `churn` case: one client within every quota opening and closing
//! sessions as fast as it can. With `--session-key` the server remembers
//! each closed session (so its tokens cannot revive it) until its tokens
//! expire; `--max-ended-sessions` bounds that memory, which this case
//! checks as the server's resident memory, beside the healthy client.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{ensure, Context, Result};
use blapose_proto::v1 as pb;
use pb::stream_request::Kind as Req;
use pb::stream_response::Kind as Resp;

use crate::client::{abuser, connect_from, frames, open, opened, start, Victim};

/// `sessions` sessions opened and closed from one address over `parallel`
/// connections (one session at a time on each, so the client is always
/// within its session share); the server's peak memory growth within
/// `bound` bytes, the healthy client's latency while it runs.
pub(crate) async fn churn(
    url: &str,
    pid: u32,
    sessions: u64,
    parallel: usize,
    bound: u64,
) -> Result<()> {
    println!(
        "case churn: {sessions} sessions opened and closed by one client ({parallel} at a time)"
    );
    let (format, _) = frames()?;
    let victim = Victim::before(url, None, pid).await?;
    let next = Arc::new(AtomicU64::new(0));
    let done = Arc::new(AtomicU64::new(0));
    let started = Instant::now();
    let mut workers = Vec::new();
    for _ in 0..parallel {
        let (url, next, done) = (url.to_owned(), next.clone(), done.clone());
        workers.push(tokio::spawn(async move {
            let mut client = connect_from(&url, abuser(0)).await?;
            while next.fetch_add(1, Ordering::Relaxed) < sessions {
                let mut stream = start(&mut client, open(&format, true), None).await?;
                opened(&mut stream).await?;
                stream
                    .tx
                    .send(pb::StreamRequest {
                        kind: Some(Req::Close(pb::CloseSession {})),
                    })
                    .await?;
                loop {
                    match stream.rx.message().await?.and_then(|r| r.kind) {
                        Some(Resp::Closed(_)) => break,
                        Some(_) => continue,
                        None => anyhow::bail!("the stream ended before its session closed"),
                    }
                }
                done.fetch_add(1, Ordering::Relaxed);
            }
            anyhow::Ok(())
        }));
    }
    // The healthy client once the churn has run a while (a tenth of it,
    // or two seconds), then the rest of the churn.
    while done.load(Ordering::Relaxed) < sessions / 10
        && started.elapsed() < Duration::from_secs(2)
        && !workers.iter().all(|w| w.is_finished())
    {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let latency = victim.during().await;
    let mut progress = Instant::now();
    while !workers.iter().all(|w| w.is_finished()) {
        tokio::time::sleep(Duration::from_millis(50)).await;
        if progress.elapsed() > Duration::from_secs(10) {
            let n = done.load(Ordering::Relaxed);
            println!(
                "  ... {n} churned ({:.0}/s)",
                n as f64 / started.elapsed().as_secs_f64()
            );
            progress = Instant::now();
        }
    }
    let mut failed = None;
    for w in workers {
        if let Err(e) = w.await.context("churn worker")? {
            failed.get_or_insert(e);
        }
    }
    let n = done.load(Ordering::Relaxed);
    let secs = started.elapsed().as_secs_f64();
    println!(
        "  {n} sessions opened and closed in {secs:.1} s ({:.0}/s)",
        n as f64 / secs
    );
    victim.check(latency, bound)?;
    if let Some(e) = failed {
        return Err(e.context("a session of the churning client was refused"));
    }
    ensure!(n == sessions, "only {n} of {sessions} sessions churned");
    Ok(())
}
