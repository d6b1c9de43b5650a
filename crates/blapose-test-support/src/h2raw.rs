//! Raw HTTP/2 for tests that must do what a well-behaved client never does:
//! open streams beyond SETTINGS_MAX_CONCURRENT_STREAMS, send an oversized
//! header list, send an undecodable gRPC message, stall mid-preface. h2 and
//! tonic clients refuse to (they queue streams and check sizes), so these
//! tests write the frames themselves (RFC 9113, HPACK literals of RFC 7541).

use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

pub const PREFACE: &[u8; 24] = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n";
pub const DATA: u8 = 0x0;
pub const HEADERS: u8 = 0x1;
pub const RST_STREAM: u8 = 0x3;
pub const SETTINGS: u8 = 0x4;
pub const GOAWAY: u8 = 0x7;
pub const END_STREAM: u8 = 0x1;
pub const END_HEADERS: u8 = 0x4;
pub const SETTINGS_MAX_CONCURRENT_STREAMS: u16 = 0x3;
pub const SETTINGS_MAX_HEADER_LIST_SIZE: u16 = 0x6;
pub const REFUSED_STREAM: u32 = 0x7;

/// One frame.
#[derive(Debug, Clone)]
pub struct Frame {
    pub kind: u8,
    pub flags: u8,
    pub stream: u32,
    pub payload: Vec<u8>,
}

impl Frame {
    /// The error code of a RST_STREAM or GOAWAY.
    pub fn error_code(&self) -> Option<u32> {
        let at = match self.kind {
            RST_STREAM => 0,
            GOAWAY => 4,
            _ => return None,
        };
        let b = self.payload.get(at..at + 4)?;
        Some(u32::from_be_bytes([b[0], b[1], b[2], b[3]]))
    }

    /// The parameters of a SETTINGS frame.
    pub fn settings(&self) -> Vec<(u16, u32)> {
        self.payload
            .chunks_exact(6)
            .map(|c| {
                (
                    u16::from_be_bytes([c[0], c[1]]),
                    u32::from_be_bytes([c[2], c[3], c[4], c[5]]),
                )
            })
            .collect()
    }
}

/// A frame's bytes.
pub fn frame(kind: u8, flags: u8, stream: u32, payload: &[u8]) -> Vec<u8> {
    let len = payload.len();
    let mut out = vec![(len >> 16) as u8, (len >> 8) as u8, len as u8, kind, flags];
    out.extend_from_slice(&stream.to_be_bytes());
    out.extend_from_slice(payload);
    out
}

/// Connect and send the client preface and an empty SETTINGS frame.
pub async fn connect(addr: std::net::SocketAddr) -> TcpStream {
    let mut s = TcpStream::connect(addr).await.expect("connect");
    s.set_nodelay(true).unwrap();
    let mut hello = PREFACE.to_vec();
    hello.extend(frame(SETTINGS, 0, 0, &[]));
    s.write_all(&hello).await.expect("send the preface");
    s
}

/// The next frame, or `None` at EOF, a reset connection or after `wait`.
pub async fn read_frame(s: &mut TcpStream, wait: Duration) -> Option<Frame> {
    tokio::time::timeout(wait, async {
        let mut head = [0u8; 9];
        s.read_exact(&mut head).await.ok()?;
        let len = (usize::from(head[0]) << 16) | (usize::from(head[1]) << 8) | usize::from(head[2]);
        let mut payload = vec![0u8; len];
        s.read_exact(&mut payload).await.ok()?;
        Some(Frame {
            kind: head[3],
            flags: head[4],
            stream: u32::from_be_bytes([head[5], head[6], head[7], head[8]]) & 0x7fff_ffff,
            payload,
        })
    })
    .await
    .ok()
    .flatten()
}

/// Read frames until one matches `want`; `None` if the connection ends or
/// `wait` passes first.
pub async fn wait_for(
    s: &mut TcpStream,
    wait: Duration,
    want: impl Fn(&Frame) -> bool,
) -> Option<Frame> {
    let deadline = tokio::time::Instant::now() + wait;
    loop {
        let left = deadline.saturating_duration_since(tokio::time::Instant::now());
        let f = read_frame(s, left).await?;
        if want(&f) {
            return Some(f);
        }
    }
}

/// HPACK integer with an `n`-bit prefix whose high bits are `first`.
fn hpack_int(out: &mut Vec<u8>, first: u8, n: u32, mut value: usize) {
    let max = (1usize << n) - 1;
    if value < max {
        out.push(first | value as u8);
        return;
    }
    out.push(first | max as u8);
    value -= max;
    while value >= 128 {
        out.push((value % 128 + 128) as u8);
        value /= 128;
    }
    out.push(value as u8);
}

fn hpack_string(out: &mut Vec<u8>, s: &[u8]) {
    hpack_int(out, 0, 7, s.len());
    out.extend_from_slice(s);
}

/// A header block for a gRPC POST to `path` (`/package.Service/Method`),
/// with `extra` headers, all as literals without indexing.
pub fn grpc_headers(path: &str, extra: &[(&str, &[u8])]) -> Vec<u8> {
    let mut block = vec![0x83, 0x86]; // :method POST, :scheme http
    hpack_int(&mut block, 0x00, 4, 4); // :path, indexed name
    hpack_string(&mut block, path.as_bytes());
    hpack_int(&mut block, 0x00, 4, 1); // :authority
    hpack_string(&mut block, b"localhost");
    hpack_int(&mut block, 0x00, 4, 31); // content-type
    hpack_string(&mut block, b"application/grpc");
    for (name, value) in [("te", b"trailers".as_slice())].iter().chain(extra) {
        block.push(0x00);
        hpack_string(&mut block, name.as_bytes());
        hpack_string(&mut block, value);
    }
    block
}

/// A gRPC message (uncompressed) framed as DATA payload.
pub fn grpc_message(message: &[u8]) -> Vec<u8> {
    let mut out = vec![0u8];
    out.extend_from_slice(&(message.len() as u32).to_be_bytes());
    out.extend_from_slice(message);
    out
}

/// The path of the bidirectional stream.
pub const STREAM_PATH: &str = "/blapose.v1.PoseAdjustment/Stream";
/// The path of the offline call.
pub const ADJUST_SEQUENCE_PATH: &str = "/blapose.v1.PoseAdjustment/AdjustSequence";
