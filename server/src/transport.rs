//! The transport under tonic: accepting TCP connections within limits,
//! the TLS handshake and the HTTP/2 preface within a deadline.
//!
//! tonic's own `TcpIncoming` accepts every connection and waits for a TLS
//! handshake or an HTTP/2 preface for ever, so a peer that opens thousands
//! of sockets and says nothing holds them until the file-descriptor limit.
//! Here an accept loop refuses a connection beyond `--max-connections` (all
//! peers) or `--max-connections-per-peer` (one IP address) at once, and
//! gives every admitted one `--handshake-timeout` to finish its TLS
//! handshake (when TLS is on) and send the 24-byte HTTP/2 client preface;
//! only then is it handed to tonic, with the preface put back in front of
//! its bytes. Each handshake runs in its own task, so a slow peer never
//! delays another's accept.
//!
//! TLS is terminated here rather than by tonic's `tls_config` for the same
//! reason (the deadline covers it) and so that a client speaking the wrong
//! protocol learns why: a plaintext HTTP/2 client on the TLS port gets an
//! HTTP/2 GOAWAY whose debug text says the server speaks TLS (h2 clients
//! print it); a TLS ClientHello on a plaintext port is closed with a log
//! line, and blapose's clients then diagnose the port themselves.
//!
//! Peers are told apart by their IP address in its canonical form
//! ([`canonical_peer`]): on a dual-stack listener (`[::]`) an IPv4 client
//! arrives as an IPv4-mapped IPv6 address (`::ffff:127.0.0.1`), which would
//! otherwise be a different client from the same address on an IPv4
//! listener and never match an IPv4 `--trusted-proxies` entry.
//!
//! Every refusal or early close is a log line and a count in
//! `blapose_connections_refused_total{limit}` or
//! `blapose_connections_closed_total{reason}`.

use std::collections::HashMap;
use std::io;
use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio_rustls::rustls;
use tokio_rustls::TlsAcceptor;
use tokio_stream::wrappers::ReceiverStream;
use tokio_util::sync::CancellationToken;
use tonic::transport::server::{Connected, TcpConnectInfo};

use crate::activity::Activity;
use crate::budget::{Budget, BudgetConnection};
use crate::frames::{FrameMeter, Refusals};
use crate::metrics;

/// TLS certificate chain and private key, both PEM files.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TlsFiles {
    /// Certificate chain (PEM).
    pub cert: PathBuf,
    /// Private key (PEM).
    pub key: PathBuf,
}

/// The HTTP/2 client connection preface (RFC 9113, section 3.4).
pub const PREFACE: &[u8; 24] = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n";

/// `peer` with an IPv4-mapped IPv6 address (`::ffff:a.b.c.d`) written as
/// the IPv4 address it maps; every other address as it is. Every
/// per-address rule (connection counts, client identity, trusted proxies)
/// sees addresses through this.
pub fn canonical_peer(peer: SocketAddr) -> SocketAddr {
    SocketAddr::new(peer.ip().to_canonical(), peer.port())
}

/// Connection limits enforced before tonic sees a connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ConnectionLimits {
    /// Connections held at once, all peers together (`--max-connections`).
    pub max_connections: usize,
    /// Connections held at once from one IP address
    /// (`--max-connections-per-peer`).
    pub max_connections_per_peer: usize,
    /// Time a new connection has to finish its TLS handshake and send the
    /// HTTP/2 preface (`--handshake-timeout`).
    pub handshake_timeout: Duration,
}

/// Which limit refused a connection; [`Refusal::flag`] names its flag.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refusal {
    /// `--max-connections`.
    Total,
    /// `--max-connections-per-peer`.
    PerPeer,
    /// `--memory-budget`.
    MemoryBudget,
}

impl Refusal {
    /// The flag that sets the limit (also the metric's `limit` label).
    pub fn flag(self) -> &'static str {
        match self {
            Refusal::Total => "max_connections",
            Refusal::PerPeer => "max_connections_per_peer",
            Refusal::MemoryBudget => "memory_budget",
        }
    }
}

#[derive(Debug, Default)]
struct Counts {
    total: usize,
    per_peer: HashMap<IpAddr, usize>,
}

/// The connections held, all and by peer; admits or refuses new ones.
#[derive(Debug, Clone)]
pub struct ConnectionTable {
    limits: ConnectionLimits,
    counts: Arc<Mutex<Counts>>,
}

/// One admitted connection's place in its [`ConnectionTable`]; freed when
/// dropped (the connection closed).
#[derive(Debug)]
pub struct Permit {
    peer: IpAddr,
    counts: Arc<Mutex<Counts>>,
    _budget: Option<BudgetConnection>,
}

impl ConnectionTable {
    /// An empty table with `limits`.
    pub fn new(limits: ConnectionLimits) -> Self {
        Self {
            limits,
            counts: Arc::default(),
        }
    }

    /// Admit a connection from `peer` that may hold `bytes` of memory
    /// ([`crate::budget::http2_connection_bytes`]): within `budget` and
    /// this table's limits, or say which refuses it. The bytes count in the
    /// budget as long as the permit lives.
    pub fn admit_within(
        &self,
        peer: IpAddr,
        budget: &Arc<Budget>,
        bytes: usize,
    ) -> Result<Permit, Refusal> {
        let held = budget
            .connection(bytes)
            .map_err(|_| Refusal::MemoryBudget)?;
        let mut permit = self.admit(peer)?;
        permit._budget = Some(held);
        Ok(permit)
    }

    /// Admit a connection from `peer`, or say which limit refuses it.
    pub fn admit(&self, peer: IpAddr) -> Result<Permit, Refusal> {
        let mut counts = lock(&self.counts);
        if counts.total >= self.limits.max_connections {
            return Err(Refusal::Total);
        }
        let holders = counts.per_peer.len();
        let held = counts.per_peer.get(&peer).copied().unwrap_or(0);
        // Per peer, and no more than a fair share of all connections, with
        // a share kept for an address that holds none.
        let admitted = crate::quota::admit(
            self.limits.max_connections_per_peer,
            self.limits.max_connections,
            counts.total,
            holders,
            held,
        );
        if admitted.is_err() {
            return Err(Refusal::PerPeer);
        }
        let from_peer = counts.per_peer.entry(peer).or_default();
        *from_peer += 1;
        counts.total += 1;
        metrics::connections(counts.total);
        Ok(Permit {
            peer,
            counts: self.counts.clone(),
            _budget: None,
        })
    }

    /// Connections held now.
    pub fn held(&self) -> usize {
        lock(&self.counts).total
    }
}

fn lock(counts: &Mutex<Counts>) -> std::sync::MutexGuard<'_, Counts> {
    counts
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl Drop for Permit {
    fn drop(&mut self) {
        let mut counts = lock(&self.counts);
        counts.total = counts.total.saturating_sub(1);
        if let Some(n) = counts.per_peer.get_mut(&self.peer) {
            *n = n.saturating_sub(1);
            if *n == 0 {
                counts.per_peer.remove(&self.peer);
            }
        }
        metrics::connections(counts.total);
    }
}

/// Why a connection was closed before it reached tonic.
#[derive(Debug, thiserror::Error)]
pub enum HandshakeError {
    /// Nothing (or not all of the handshake) within the deadline.
    #[error("no TLS handshake and HTTP/2 preface within {0:?} (--handshake-timeout)")]
    Timeout(Duration),
    /// A plaintext client on the TLS port.
    #[error("the client sent plaintext to the TLS port (it was told: the server speaks TLS)")]
    PlaintextOnTls,
    /// A TLS client on the plaintext port.
    #[error("the client started a TLS handshake on a plaintext port")]
    TlsOnPlaintext,
    /// The bytes were not the HTTP/2 preface (HTTP/1, a port scan, ...).
    #[error("the client did not send the HTTP/2 preface")]
    NotHttp2,
    /// The TLS handshake failed.
    #[error("TLS handshake failed: {0}")]
    Tls(io::Error),
    /// The socket failed or closed.
    #[error("connection closed during the handshake: {0}")]
    Io(#[from] io::Error),
}

impl HandshakeError {
    /// The metric's `reason` label.
    pub fn reason(&self) -> &'static str {
        match self {
            HandshakeError::Timeout(_) => "handshake_timeout",
            HandshakeError::PlaintextOnTls => "plaintext_on_tls_port",
            HandshakeError::TlsOnPlaintext => "tls_on_plaintext_port",
            HandshakeError::NotHttp2 => "not_http2",
            HandshakeError::Tls(_) => "tls_handshake_failed",
            HandshakeError::Io(_) => "closed_during_handshake",
        }
    }
}

/// The rustls acceptor for `files` (PEM chain and key), offering HTTP/2
/// by ALPN.
pub fn tls_acceptor(files: &TlsFiles) -> Result<TlsAcceptor, String> {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer};
    let certs = CertificateDer::pem_file_iter(&files.cert)
        .and_then(|certs| certs.collect::<Result<Vec<_>, _>>())
        .map_err(|e| {
            format!(
                "cannot read certificates from {}: {e}",
                files.cert.display()
            )
        })?;
    if certs.is_empty() {
        return Err(format!("no certificate in {}", files.cert.display()));
    }
    let key = PrivateKeyDer::from_pem_file(&files.key).map_err(|e| {
        format!(
            "cannot read a private key from {}: {e}",
            files.key.display()
        )
    })?;
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let mut config = rustls::ServerConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .map_err(|e| e.to_string())?
        .with_no_client_auth()
        .with_single_cert(certs, key)
        .map_err(|e| format!("{} and {}: {e}", files.cert.display(), files.key.display()))?;
    config.alpn_protocols = vec![b"h2".to_vec()];
    Ok(TlsAcceptor::from(Arc::new(config)))
}

/// A connection that passed the handshake: what tonic serves.
pub struct Conn {
    io: Io,
    /// The preface, read to check it, given back to HTTP/2 first.
    replay: usize,
    info: TcpConnectInfo,
    activity: Arc<Activity>,
    meter: FrameMeter,
    refusals: Refusals,
    _permit: Permit,
}

impl Conn {
    /// The connection's activity (open streams, a control-frame flood).
    pub fn activity(&self) -> Arc<Activity> {
        self.activity.clone()
    }
}

enum Io {
    Plain(TcpStream),
    Tls(Box<tokio_rustls::server::TlsStream<TcpStream>>),
}

impl std::fmt::Debug for Conn {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Conn")
            .field("peer", &self.info.remote_addr)
            .field("tls", &matches!(self.io, Io::Tls(_)))
            .finish()
    }
}

impl Connected for Conn {
    type ConnectInfo = TcpConnectInfo;

    fn connect_info(&self) -> Self::ConnectInfo {
        self.info.clone()
    }
}

impl AsyncRead for Conn {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        if self.replay < PREFACE.len() {
            let rest = &PREFACE[self.replay..];
            let n = rest.len().min(buf.remaining());
            buf.put_slice(&rest[..n]);
            self.replay += n;
            return Poll::Ready(Ok(()));
        }
        if self.activity.flooding() {
            // Read nothing more from a flooding connection: it is being
            // closed (GOAWAY, then dropped), and h2 does no more work on it.
            return Poll::Pending;
        }
        let before = buf.filled().len();
        let this = &mut *self;
        let read = match &mut this.io {
            Io::Plain(s) => Pin::new(s).poll_read(cx, buf),
            Io::Tls(s) => Pin::new(s.as_mut()).poll_read(cx, buf),
        };
        if this.meter.observe(&buf.filled()[before..]) {
            this.activity.raise_flood();
        }
        read
    }
}

impl AsyncWrite for Conn {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = &mut *self;
        let written = match &mut this.io {
            Io::Plain(s) => Pin::new(s).poll_write(cx, buf),
            Io::Tls(s) => Pin::new(s.as_mut()).poll_write(cx, buf),
        };
        if let Poll::Ready(Ok(n)) = written {
            this.refusals.count(std::iter::once(&buf[..n]));
        }
        written
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let this = &mut *self;
        let written = match &mut this.io {
            Io::Plain(s) => Pin::new(s).poll_write_vectored(cx, bufs),
            Io::Tls(s) => Pin::new(s.as_mut()).poll_write_vectored(cx, bufs),
        };
        if let Poll::Ready(Ok(mut n)) = written {
            let slices = bufs.iter().map(|b| {
                let take = n.min(b.len());
                n -= take;
                &b[..take]
            });
            this.refusals.count(slices);
        }
        written
    }

    fn is_write_vectored(&self) -> bool {
        match &self.io {
            Io::Plain(s) => s.is_write_vectored(),
            Io::Tls(s) => s.is_write_vectored(),
        }
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match &mut self.io {
            Io::Plain(s) => Pin::new(s).poll_flush(cx),
            Io::Tls(s) => Pin::new(s.as_mut()).poll_flush(cx),
        }
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match &mut self.io {
            Io::Plain(s) => Pin::new(s).poll_shutdown(cx),
            Io::Tls(s) => Pin::new(s.as_mut()).poll_shutdown(cx),
        }
    }
}

/// The memory budget a listener's connections count in, and the bytes
/// each may hold ([`crate::budget::http2_connection_bytes`]).
#[derive(Debug, Clone)]
pub struct ConnectionCost {
    /// The server's budget.
    pub budget: Arc<Budget>,
    /// What one connection counts in it.
    pub bytes: usize,
}

/// The stream of handshaken connections on `listener` that tonic serves.
/// Accepting stops when `shutdown` is cancelled or the stream is dropped
/// (the listener closes with it, so new connections are refused).
/// Each connection's control frames are counted, at most
/// `control_frames_per_second` ([`crate::frames`]).
pub fn incoming(
    listener: TcpListener,
    table: ConnectionTable,
    tls: Option<TlsAcceptor>,
    shutdown: CancellationToken,
    control_frames_per_second: u32,
    cost: ConnectionCost,
) -> ReceiverStream<io::Result<Conn>> {
    let (tx, rx) = mpsc::channel(64);
    tokio::spawn(accept_loop(
        listener,
        table,
        tls,
        shutdown,
        tx,
        control_frames_per_second,
        cost,
    ));
    ReceiverStream::new(rx)
}

async fn accept_loop(
    listener: TcpListener,
    table: ConnectionTable,
    tls: Option<TlsAcceptor>,
    shutdown: CancellationToken,
    tx: mpsc::Sender<io::Result<Conn>>,
    control_frames_per_second: u32,
    cost: ConnectionCost,
) {
    let deadline = table.limits.handshake_timeout;
    loop {
        let accepted = tokio::select! {
            accepted = listener.accept() => accepted,
            _ = shutdown.cancelled() => return,
            _ = tx.closed() => return,
        };
        let (tcp, peer) = match accepted {
            Ok((tcp, peer)) => (tcp, canonical_peer(peer)),
            Err(e) => {
                // Out of file descriptors or a connection reset before it
                // was accepted: neither ends serving. Pause briefly so an
                // fd shortage does not spin.
                tracing::warn!(error = %e, "accept failed");
                tokio::time::sleep(Duration::from_millis(20)).await;
                continue;
            }
        };
        let permit = match table.admit_within(peer.ip(), &cost.budget, cost.bytes) {
            Ok(permit) => permit,
            Err(refusal) => {
                metrics::connection_refused(refusal.flag());
                tracing::warn!(%peer, limit = refusal.flag(), "connection refused: --{} reached", refusal.flag().replace('_', "-"));
                drop(tcp);
                continue;
            }
        };
        let tls = tls.clone();
        let tx = tx.clone();
        tokio::spawn(async move {
            let info = TcpConnectInfo {
                local_addr: tcp.local_addr().ok(),
                remote_addr: Some(peer),
            };
            let _ = tcp.set_nodelay(true);
            let handshake = tokio::time::timeout(deadline, handshake(tcp, tls)).await;
            match handshake.unwrap_or(Err(HandshakeError::Timeout(deadline))) {
                Ok(io) => {
                    let conn = Conn {
                        io,
                        replay: 0,
                        info,
                        activity: Arc::new(Activity::new()),
                        meter: FrameMeter::new(control_frames_per_second),
                        refusals: Refusals::default(),
                        _permit: permit,
                    };
                    let _ = tx.send(Ok(conn)).await;
                }
                Err(e) => {
                    metrics::connection_closed(e.reason());
                    log_closed(peer, &e);
                }
            }
        });
    }
}

fn log_closed(peer: SocketAddr, e: &HandshakeError) {
    match e {
        // A client that connected and went away is ordinary.
        HandshakeError::Io(_) => tracing::debug!(%peer, error = %e, "connection closed"),
        _ => tracing::info!(%peer, reason = e.reason(), error = %e, "connection closed"),
    }
}

/// A plaintext HTTP/2 client on the TLS port: an empty SETTINGS frame (the
/// server preface it waits for) and a GOAWAY (PROTOCOL_ERROR) whose debug
/// data says what to do; h2 clients print that text.
fn goaway_speaks_tls() -> Vec<u8> {
    const DEBUG: &[u8] = b"this server speaks TLS: connect with TLS (https://, --tls-ca)";
    let mut out = vec![0, 0, 0, 0x4, 0, 0, 0, 0, 0];
    let len = 8 + DEBUG.len();
    out.extend_from_slice(&[(len >> 16) as u8, (len >> 8) as u8, len as u8, 0x7, 0]);
    out.extend_from_slice(&[0, 0, 0, 0]); // stream 0
    out.extend_from_slice(&[0, 0, 0, 0]); // last stream id
    out.extend_from_slice(&[0, 0, 0, 1]); // PROTOCOL_ERROR
    out.extend_from_slice(DEBUG);
    out
}

/// Send [`goaway_speaks_tls`] and close gracefully: half-close, then read
/// (and drop) what the client still sends for a moment, because closing a
/// socket with unread data resets it and the client would lose the GOAWAY.
async fn tell_speaks_tls(mut tcp: TcpStream) {
    if tcp.write_all(&goaway_speaks_tls()).await.is_err() || tcp.shutdown().await.is_err() {
        return;
    }
    let mut sink = [0u8; 1024];
    let _ = tokio::time::timeout(Duration::from_secs(1), async {
        while matches!(tcp.read(&mut sink).await, Ok(n) if n > 0) {}
    })
    .await;
}

/// Peek the first byte to tell TLS from plaintext, run the TLS handshake
/// when the port speaks TLS, and read and check the HTTP/2 preface.
async fn handshake(tcp: TcpStream, tls: Option<TlsAcceptor>) -> Result<Io, HandshakeError> {
    let mut first = [0u8; 1];
    if tcp.peek(&mut first).await? == 0 {
        return Err(io::Error::from(io::ErrorKind::UnexpectedEof).into());
    }
    // A TLS record starts with its content type: 0x16, handshake.
    let client_tls = first[0] == 0x16;
    let mut io = match (tls, client_tls) {
        (Some(acceptor), true) => Io::Tls(Box::new(
            acceptor.accept(tcp).await.map_err(HandshakeError::Tls)?,
        )),
        (Some(_), false) => {
            if first[0] == PREFACE[0] {
                tell_speaks_tls(tcp).await;
            }
            return Err(HandshakeError::PlaintextOnTls);
        }
        (None, true) => return Err(HandshakeError::TlsOnPlaintext),
        (None, false) => Io::Plain(tcp),
    };
    let mut preface = [0u8; 24];
    match &mut io {
        Io::Plain(s) => s.read_exact(&mut preface).await?,
        Io::Tls(s) => s.read_exact(&mut preface).await?,
    };
    if &preface != PREFACE {
        return Err(HandshakeError::NotHttp2);
    }
    Ok(io)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits(total: usize, per_peer: usize) -> ConnectionLimits {
        ConnectionLimits {
            max_connections: total,
            max_connections_per_peer: per_peer,
            handshake_timeout: Duration::from_secs(1),
        }
    }

    #[test]
    fn table_refuses_beyond_each_limit_and_frees_on_drop() {
        let table = ConnectionTable::new(limits(3, 2));
        let a: IpAddr = "10.0.0.1".parse().unwrap();
        let b: IpAddr = "10.0.0.2".parse().unwrap();
        let a1 = table.admit(a).unwrap();
        let _a2 = table.admit(a).unwrap();
        assert_eq!(table.admit(a).unwrap_err(), Refusal::PerPeer);
        let _b1 = table.admit(b).unwrap();
        assert_eq!(table.admit(b).unwrap_err(), Refusal::Total);
        drop(a1);
        assert_eq!(table.held(), 2);
        let _a3 = table.admit(a).unwrap();
        assert_eq!(Refusal::PerPeer.flag(), "max_connections_per_peer");
    }

    #[test]
    fn addresses_at_their_fair_shares_leave_room_for_another() {
        let table = ConnectionTable::new(limits(64, 64));
        let fill = |ip: &str| {
            let ip: IpAddr = ip.parse().unwrap();
            let mut held = Vec::new();
            while let Ok(p) = table.admit(ip) {
                held.push(p);
            }
            held
        };
        let a = fill("10.0.0.1");
        let b = fill("10.0.0.2");
        // 64/2, then what leaves 64/4 free; the third leaves 64/5.
        assert_eq!((a.len(), b.len()), (32, 16));
        let c = fill("10.0.0.3");
        assert_eq!(c.len(), 4, "the third still connects");
        let d = fill("10.0.0.4");
        assert!(!d.is_empty(), "and the fourth");
    }

    #[test]
    fn mapped_ipv6_peers_are_their_ipv4_address() {
        let mapped: SocketAddr = "[::ffff:127.0.0.1]:5000".parse().unwrap();
        assert_eq!(canonical_peer(mapped), "127.0.0.1:5000".parse().unwrap());
        let v6: SocketAddr = "[::1]:5000".parse().unwrap();
        assert_eq!(canonical_peer(v6), v6);
        let table = ConnectionTable::new(limits(8, 1));
        let _v4 = table.admit("10.0.0.1".parse().unwrap()).unwrap();
        let same = canonical_peer("[::ffff:10.0.0.1]:1".parse().unwrap()).ip();
        assert_eq!(table.admit(same).unwrap_err(), Refusal::PerPeer);
    }

    #[test]
    fn goaway_is_a_well_formed_frame() {
        let bytes = goaway_speaks_tls();
        let goaway = &bytes[9..];
        let len =
            (usize::from(goaway[0]) << 16) | (usize::from(goaway[1]) << 8) | usize::from(goaway[2]);
        assert_eq!(goaway[3], 0x7);
        assert_eq!(goaway.len(), 9 + len);
    }
}
