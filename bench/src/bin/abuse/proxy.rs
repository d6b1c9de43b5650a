//! The `proxy6` case: a balancer's client header behind a dual-stack
//! listener. The server listens on `[::]`, so an IPv4 peer arrives as
//! `::ffff:a.b.c.d`; `--trusted-proxies 127.0.0.1` must still match the
//! balancer (127.0.0.1), whose header then names each client, and must not
//! match anyone else (127.0.0.2), whose header is ignored.

use anyhow::{ensure, Result};

use crate::client::{abuser, connect, connect_from, hold_sessions, Victim, MAX_RSS_GROWTH};

/// Sessions per header value (the server's `--max-sessions-per-client`
/// is `limit`) from the trusted balancer and from an untrusted address,
/// beside the healthy client (from the balancer, a client of its own).
pub(crate) async fn proxy6(url: &str, pid: u32, header: &str, limit: usize) -> Result<()> {
    println!(
        "case proxy6: --client-header {header} from the trusted 127.0.0.1 on a [::] listener (limit {limit} per client)"
    );
    let victim = Victim::before(url, Some(header), pid).await?;
    // Behind the balancer: "a" and "b" are two clients, `limit` each.
    let mut balancer = connect(url).await?;
    let (a, _) = hold_sessions(&mut balancer, Some((header, "a")), limit + 1, 1).await?;
    let (b, _) = hold_sessions(&mut balancer, Some((header, "b")), limit + 1, 1).await?;
    // From an untrusted address: "c" and "d" are one client, the address.
    let mut stranger = connect_from(url, abuser(0)).await?;
    let (c, _) = hold_sessions(&mut stranger, Some((header, "c")), limit + 1, 1).await?;
    let (d, _) = hold_sessions(&mut stranger, Some((header, "d")), limit + 1, 1).await?;
    println!(
        "  from the balancer: \"a\" holds {}, \"b\" {}; from {}: \"c\" {}, \"d\" {}",
        a.len(),
        b.len(),
        abuser(0),
        c.len(),
        d.len()
    );
    let latency = victim.during().await;
    let honoured = a.len() == limit && b.len() == limit;
    let ignored = c.len() + d.len() == limit;
    drop((a, b, c, d));
    victim.check(latency, MAX_RSS_GROWTH)?;
    ensure!(
        honoured,
        "not enforced: the trusted balancer's header did not name its clients on a [::] listener"
    );
    ensure!(
        ignored,
        "not enforced: an untrusted address's header was believed"
    );
    Ok(())
}
