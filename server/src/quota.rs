//! Per-client limits: who a request comes from, and how much of the
//! server's shared capacity (the session table, the frame queue) one client
//! may hold, so that one client's overload is refused to that client and
//! the others are served as before.
//!
//! A client is its *identity*: the peer's IP address, or, behind a load
//! balancer, a header the balancer sets (`--client-header`), read only on
//! connections from the peers named by `--trusted-proxies` (anyone else
//! could set it to whatever escapes their limit). The bearer token is not
//! an identity: the server has one shared `--auth-token`, so it would put
//! every authenticated client in one bucket. Addresses, the peer's and the
//! trusted proxies', are compared in canonical form (an IPv4-mapped IPv6
//! address as its IPv4 address), so a dual-stack listener (`[::]`) sees
//! the balancer at the address it was configured with. The identity is hashed
//! (SHA-256, 16 bytes) so the store never holds an address or header value.
//!
//! The limits: sessions per client (a fraction of `--max-sessions` by
//! default, so that one client opening sessions as fast as it can fills its
//! own share and no more), frames one session may have waiting in the
//! batcher queue, and frames one client may have waiting (a share of
//! `--queue-capacity`). Each refusal is RESOURCE_EXHAUSTED naming its limit.
//!
//! On top of the configured shares, a *fair share* that shrinks as more
//! clients hold something ([`fair_share`]): with k clients holding part of
//! a pool, each may hold at most `total / (k + 1)`, so together they leave
//! at least one share free for a client that holds nothing. Measured
//! before it: two clients holding half the session table each (2,048 +
//! 2,047) locked every other client out for as long as they streamed. As
//! shares never take back what is held, clients that arrive one after
//! another could still fill a pool (each took a larger share than the
//! next), so a [`reserve`] of one more share is kept from every client
//! that holds some ([`admit`]). The same rules hold the frame queue and
//! connections (per address).

use std::net::IpAddr;
use std::time::Duration;

use sha2::{Digest, Sha256};

/// Who a session or frame belongs to, for the per-client limits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct ClientId([u8; 16]);

impl ClientId {
    /// The id of an identity string (hashed; never stored as given).
    pub fn of(identity: &str) -> Self {
        let digest = Sha256::digest(identity.as_bytes());
        let mut id = [0u8; 16];
        id.copy_from_slice(&digest[..16]);
        Self(id)
    }

    /// The id as 16 bytes (what a session token records of its owner).
    pub fn as_bytes(&self) -> &[u8; 16] {
        &self.0
    }

    /// An id from its bytes.
    pub fn from_bytes(bytes: [u8; 16]) -> Self {
        Self(bytes)
    }
}

/// The per-client limits and how a request's client is told.
#[derive(Debug, Clone)]
pub struct Limits {
    /// Sessions one client may hold (attached or detached).
    pub sessions_per_client: usize,
    /// Frames one session may have waiting in the batcher queue.
    pub frames_per_session: usize,
    /// Frames one client may have waiting in the batcher queue.
    pub queued_per_client: usize,
    /// How long a session token is accepted after it was issued.
    pub token_ttl: Duration,
    /// Header naming the client, set by a trusted balancer (lowercase).
    client_header: Option<String>,
    /// Peers allowed to set `client_header`.
    trusted_proxies: Vec<IpAddr>,
}

/// A pool this small (or a share this small of a larger one) is not split
/// further by [`fair_share`]: tests' and single-user deployments' small
/// tables keep working, and the guarantee holds up to `total / 16 - 1`
/// clients at once.
pub const FAIR_FLOOR: usize = 16;

/// The most of a pool of `total` one client may hold while `active`
/// clients (it included) hold some: `total / (active + 1)`, so k clients
/// at their shares leave `total / (k + 1)` for the next; never below
/// [`FAIR_FLOOR`] (all of a pool that small).
pub fn fair_share(total: usize, active: usize) -> usize {
    (total / (active.max(1) + 1)).max(total.min(FAIR_FLOOR))
}

/// The limit for a client holding `held` of a pool of `total` in which
/// `holders` clients hold some: the configured `share`, or the fair share
/// when that is smaller. A `share` of `usize::MAX` means no per-client
/// limit at all (library callers that do not tell clients apart).
pub fn effective_share(share: usize, total: usize, holders: usize, held: usize) -> usize {
    if share == usize::MAX {
        return share;
    }
    let active = holders + usize::from(held == 0);
    share.min(fair_share(total, active))
}

/// What a client that already holds part of a pool of `total` may not
/// take, with `holders` clients holding some: the fair share of one more
/// client (`total / (holders + 2)`). Shares alone do not leave it: each
/// client took its share when fewer held some (alone half, then a third,
/// a quarter, ...) and a share never takes back what is held, so three
/// clients arriving one after another could fill the pool (1/2 + 1/3 +
/// 1/4 > 1). With the reserve a client holding nothing always finds its
/// share free. Nothing is reserved in a pool of [`FAIR_FLOOR`] or fewer.
pub fn reserve(total: usize, holders: usize) -> usize {
    if total <= FAIR_FLOOR {
        0
    } else {
        total / (holders + 2)
    }
}

/// Whether a client holding `held` of a pool of `total`, of which `used`
/// are taken by `holders` clients, may take one more under its configured
/// `share`: [`effective_share`], and the [`reserve`] left for a client that
/// holds nothing. `Err` carries the limit the client is held to now.
pub fn admit(
    share: usize,
    total: usize,
    used: usize,
    holders: usize,
    held: usize,
) -> Result<(), usize> {
    let limit = effective_share(share, total, holders, held);
    if held >= limit {
        return Err(limit);
    }
    if share != usize::MAX && held > 0 && used + reserve(total, holders) >= total {
        return Err(held);
    }
    Ok(())
}

/// Smallest default share: a small table or queue (a test's, a
/// single-user deployment's) is not split, and the load tests' 1,024
/// streams from one loopback client always fit.
pub const MIN_DEFAULT_SHARE: usize = 1024;

/// The default share of `total` (sessions, or queued frames) one client
/// may take: half, so one client can never fill it, but at least
/// [`MIN_DEFAULT_SHARE`] (all of it when smaller).
pub fn default_share(total: usize) -> usize {
    (total / 2).max(total.min(MIN_DEFAULT_SHARE))
}

impl Limits {
    /// Limits with these values (each at least 1). A client is its peer's
    /// address, or the value of `client_header` on a connection from one
    /// of `trusted_proxies`.
    pub fn new(
        sessions_per_client: usize,
        frames_per_session: usize,
        queued_per_client: usize,
        token_ttl: Duration,
        client_header: Option<&str>,
        trusted_proxies: Vec<IpAddr>,
    ) -> Self {
        Self {
            sessions_per_client: sessions_per_client.max(1),
            frames_per_session: frames_per_session.max(1),
            queued_per_client: queued_per_client.max(1),
            token_ttl,
            client_header: client_header
                .map(|h| h.trim().to_ascii_lowercase())
                .filter(|h| !h.is_empty()),
            trusted_proxies: trusted_proxies
                .into_iter()
                .map(|ip| ip.to_canonical())
                .collect(),
        }
    }

    /// The client a request comes from.
    pub fn client<T>(&self, request: &tonic::Request<T>) -> ClientId {
        let peer = request.remote_addr().map(|a| a.ip());
        ClientId::of(&self.identity(peer, |name| {
            request
                .metadata()
                .get(name)
                .and_then(|v| v.to_str().ok())
                .map(str::to_string)
        }))
    }

    /// The client of a request that is not a gRPC call (the browser
    /// transport's WebSocket upgrade): `peer`, or `header` on a connection
    /// from a trusted proxy, as for [`Limits::client`].
    pub fn client_of(
        &self,
        peer: Option<IpAddr>,
        header: impl Fn(&str) -> Option<String>,
    ) -> ClientId {
        ClientId::of(&self.identity(peer, header))
    }

    /// The identity string of a peer (and its headers, read by `header`).
    fn identity(&self, peer: Option<IpAddr>, header: impl Fn(&str) -> Option<String>) -> String {
        let peer = peer.map(|ip| ip.to_canonical());
        if let (Some(name), Some(ip)) = (&self.client_header, peer) {
            if self.trusted_proxies.contains(&ip) {
                if let Some(value) = header(name).filter(|v| !v.is_empty()) {
                    return format!("header:{value}");
                }
            }
        }
        match peer {
            Some(ip) => format!("peer:{ip}"),
            None => "peer:unknown".into(),
        }
    }
}

/// Why a per-client limit refused something.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum QuotaError {
    /// The client holds its share of the session table.
    #[error("this client already holds {limit} sessions, its share of the session table (--max-sessions-per-client, or less while other clients hold sessions: the share shrinks as more clients are served); close unused sessions or retry later")]
    Sessions {
        /// The limit.
        limit: usize,
    },
    /// The session has its limit of frames waiting.
    #[error("this session already has {limit} frames waiting (--max-frames-per-session); wait for earlier answers")]
    SessionFrames {
        /// The limit.
        limit: usize,
    },
    /// The client has its share of the frame queue.
    #[error("this client already has {limit} frames waiting, its share of the queue (--max-queued-frames-per-client, or less while other clients have frames waiting); wait for earlier answers")]
    ClientFrames {
        /// The limit.
        limit: usize,
    },
}

impl QuotaError {
    /// The limit's name in metrics.
    pub fn name(&self) -> &'static str {
        match self {
            Self::Sessions { .. } => "sessions_per_client",
            Self::SessionFrames { .. } => "frames_per_session",
            Self::ClientFrames { .. } => "queued_frames_per_client",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits(header: Option<&str>, trusted: &[&str]) -> Limits {
        let trusted = trusted.iter().map(|t| t.parse().unwrap()).collect();
        Limits::new(8, 8, 8, Duration::from_secs(60), header, trusted)
    }

    #[test]
    fn the_header_counts_only_from_trusted_peers() {
        let l = limits(Some("X-Blapose-Client"), &["10.0.0.5"]);
        let header = |_: &str| Some("203.0.113.9".to_string());
        let lb: IpAddr = "10.0.0.5".parse().unwrap();
        let other: IpAddr = "10.0.0.6".parse().unwrap();
        assert_eq!(l.identity(Some(lb), header), "header:203.0.113.9");
        assert_eq!(l.identity(Some(other), header), "peer:10.0.0.6");
        assert_eq!(l.identity(Some(lb), |_| None), "peer:10.0.0.5");
        let untrusting = limits(None, &["10.0.0.5"]);
        assert_eq!(untrusting.identity(Some(lb), header), "peer:10.0.0.5");
        assert_ne!(ClientId::of("peer:a"), ClientId::of("peer:b"));
    }

    #[test]
    fn clients_arriving_one_after_another_leave_room_for_the_next() {
        // Each client takes all it is admitted before the next arrives:
        // shares alone let the third fill the pool.
        for total in [17, 64, 256, 4096, 8192] {
            let mut held: Vec<usize> = Vec::new();
            for k in 0..(total / FAIR_FLOOR).min(40) {
                let used: usize = held.iter().sum();
                assert!(used < total, "client {k} of {total}: pool full {held:?}");
                let mut mine = 0;
                while admit(total, total, used + mine, k + usize::from(mine > 0), mine).is_ok() {
                    mine += 1;
                }
                assert!(mine > 0, "client {k} of {total} admitted nothing: {held:?}");
                held.push(mine);
            }
        }
        let mut taken = 0;
        for (k, expected) in [2048, 1024, 205].into_iter().enumerate() {
            let mut mine = 0;
            while admit(2048, 4096, taken + mine, k + usize::from(mine > 0), mine).is_ok() {
                mine += 1;
            }
            assert_eq!(mine, expected, "client {k}");
            taken += mine;
        }
        assert_eq!(
            admit(3, 16, 15, 3, 2),
            Ok(()),
            "a small pool keeps no reserve"
        );
        assert_eq!(admit(usize::MAX, 64, 63, 1, 63), Ok(()), "unlimited");
    }

    #[test]
    fn k_clients_at_their_fair_shares_leave_room_for_another() {
        for total in [64, 4096, 8192] {
            for k in 1..=(total / FAIR_FLOOR - 1).min(300) {
                let share = fair_share(total, k);
                assert!(k * share < total, "{k} clients x {share} of {total}");
            }
        }
        assert_eq!(fair_share(4096, 1), 2048, "alone: half, as before");
        assert_eq!(fair_share(3, 5), 3, "a small pool is not split");
        // A client already holding counts itself; a new one is counted.
        assert_eq!(effective_share(2048, 4096, 2, 1), 1365);
        assert_eq!(effective_share(2048, 4096, 2, 0), 1024);
        assert_eq!(effective_share(100, 4096, 2, 0), 100);
        assert_eq!(
            effective_share(usize::MAX, 4096, 1, 3000),
            usize::MAX,
            "unlimited"
        );
    }

    #[test]
    fn mapped_ipv6_peers_are_their_ipv4_address_everywhere() {
        let header = |_: &str| Some("203.0.113.9".to_string());
        let mapped: IpAddr = "::ffff:10.0.0.5".parse().unwrap();
        // An IPv4 trusted proxy arriving on a dual-stack listener ...
        let l = limits(Some("x-blapose-client"), &["10.0.0.5"]);
        assert_eq!(l.identity(Some(mapped), header), "header:203.0.113.9");
        // ... and a mapped entry in the list matching an IPv4 peer.
        let l = limits(Some("x-blapose-client"), &["::ffff:10.0.0.5"]);
        let v4: IpAddr = "10.0.0.5".parse().unwrap();
        assert_eq!(l.identity(Some(v4), header), "header:203.0.113.9");
        // Without the header, the same client whichever way it arrives.
        let plain = limits(None, &[]);
        assert_eq!(plain.identity(Some(mapped), header), "peer:10.0.0.5");
        assert_eq!(plain.identity(Some(v4), header), "peer:10.0.0.5");
    }
}
