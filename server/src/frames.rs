//! Control-frame floods, seen in the bytes a connection reads.
//!
//! h2 answers every PING and SETTINGS and applies every WINDOW_UPDATE,
//! RST_STREAM and PRIORITY it reads; none of them opens a stream, so none
//! is held by `--max-concurrent-streams`. Measured before this: one
//! connection sending 44.6 M WINDOW_UPDATE frames in 15 s took 85 % of a
//! core. [`FrameMeter`] follows the HTTP/2 framing of the bytes read (each
//! frame is a 9-byte header whose first three bytes give the payload's
//! length) without decoding anything else, counts the control frames per
//! one-second window, and says when a connection passes
//! `--max-control-frames-per-second`; the connection is then sent GOAWAY
//! and closed ([`crate::connection`]). Frames are never changed or held:
//! h2 still reads and checks every byte.
//!
//! The same walk over the bytes a connection *writes* finds the streams h2
//! refuses by itself, past `--max-concurrent-streams`, with RST_STREAM
//! REFUSED_STREAM ([`Refusals`]): no handler sees those, so this is where
//! they are counted.

use std::time::Duration;

use tokio::time::Instant;

/// Frame types that open nothing and cost the server work: PRIORITY,
/// RST_STREAM, SETTINGS, PING, WINDOW_UPDATE (RFC 9113, section 6).
const CONTROL_TYPES: [u8; 5] = [0x2, 0x3, 0x4, 0x6, 0x8];
const HEADER: usize = 9;
const WINDOW: Duration = Duration::from_secs(1);
const RST_STREAM: u8 = 0x3;
/// RST_STREAM's error code for a stream refused before any processing
/// (RFC 9113, section 7).
const REFUSED_STREAM: u32 = 0x7;

/// Follows the frames of one direction of a connection without decoding
/// them: each frame's type, and an RST_STREAM's error code.
#[derive(Debug, Default)]
struct Frames {
    header: [u8; HEADER],
    have: usize,
    skip: usize,
    code: [u8; 4],
    /// Bytes of an RST_STREAM's error code read so far, while reading it.
    reading_code: Option<usize>,
}

impl Frames {
    /// Walk `bytes`, the next of the direction: `on_frame(type, code)` for
    /// each frame once its header is read (an RST_STREAM's once its error
    /// code is read too, with the code).
    fn feed(&mut self, mut bytes: &[u8], mut on_frame: impl FnMut(u8, Option<u32>)) {
        while !bytes.is_empty() {
            if let Some(have) = self.reading_code {
                let n = (4 - have).min(bytes.len());
                self.code[have..have + n].copy_from_slice(&bytes[..n]);
                self.skip -= n;
                bytes = &bytes[n..];
                if have + n == 4 {
                    self.reading_code = None;
                    on_frame(RST_STREAM, Some(u32::from_be_bytes(self.code)));
                } else {
                    self.reading_code = Some(have + n);
                }
                continue;
            }
            if self.skip > 0 {
                let n = self.skip.min(bytes.len());
                self.skip -= n;
                bytes = &bytes[n..];
                continue;
            }
            let n = (HEADER - self.have).min(bytes.len());
            self.header[self.have..self.have + n].copy_from_slice(&bytes[..n]);
            self.have += n;
            bytes = &bytes[n..];
            if self.have < HEADER {
                break;
            }
            self.have = 0;
            let h = self.header;
            self.skip = usize::from(h[0]) << 16 | usize::from(h[1]) << 8 | usize::from(h[2]);
            if h[3] == RST_STREAM && self.skip == 4 {
                self.reading_code = Some(0);
            } else {
                on_frame(h[3], None);
            }
        }
    }
}

/// Follows one connection's outgoing frames and counts the streams h2
/// refused with RST_STREAM REFUSED_STREAM (past `--max-concurrent-streams`;
/// also streams opened after its GOAWAY).
#[derive(Debug, Default)]
pub struct Refusals {
    frames: Frames,
}

impl Refusals {
    /// Account for `bytes`, the next bytes written; the streams refused in
    /// them.
    pub fn observe(&mut self, bytes: &[u8]) -> usize {
        let mut refused = 0;
        self.frames.feed(bytes, |kind, code| {
            if kind == RST_STREAM && code == Some(REFUSED_STREAM) {
                refused += 1;
            }
        });
        refused
    }

    /// Count the streams refused in `written`, the bytes just written, in
    /// `blapose_limited_total{limit="max_concurrent_streams"}`.
    pub fn count<'a>(&mut self, written: impl Iterator<Item = &'a [u8]>) {
        for bytes in written {
            for _ in 0..self.observe(bytes) {
                crate::metrics::limited("max_concurrent_streams");
            }
        }
    }
}

/// Follows one connection's incoming frames and counts its control frames.
#[derive(Debug)]
pub struct FrameMeter {
    limit: u32,
    frames: Frames,
    window_start: Instant,
    in_window: u32,
    tripped: bool,
}

impl FrameMeter {
    /// A meter allowing `limit` control frames per second; it starts at
    /// the first frame header (after the connection preface).
    pub fn new(limit: u32) -> Self {
        Self {
            limit,
            frames: Frames::default(),
            window_start: Instant::now(),
            in_window: 0,
            tripped: false,
        }
    }

    /// Account for `bytes`, the next bytes read; `true` once the
    /// connection has passed the limit (and from then on).
    pub fn observe(&mut self, bytes: &[u8]) -> bool {
        if self.tripped {
            return true;
        }
        let mut control = 0;
        self.frames.feed(bytes, |kind, _| {
            if CONTROL_TYPES.contains(&kind) {
                control += 1;
            }
        });
        for _ in 0..control {
            self.count();
        }
        self.tripped
    }

    fn count(&mut self) {
        let now = Instant::now();
        if now.duration_since(self.window_start) >= WINDOW {
            self.window_start = now;
            self.in_window = 0;
        }
        self.in_window += 1;
        if self.in_window > self.limit {
            self.tripped = true;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(kind: u8, payload: usize) -> Vec<u8> {
        let mut f = vec![
            (payload >> 16) as u8,
            (payload >> 8) as u8,
            payload as u8,
            kind,
            0,
        ];
        f.extend_from_slice(&[0, 0, 0, 1]);
        f.extend(std::iter::repeat_n(0xAB, payload));
        f
    }

    #[tokio::test(start_paused = true)]
    async fn counts_control_frames_across_reads_and_skips_payloads() {
        let mut m = FrameMeter::new(3);
        // DATA whose payload is full of bytes that look like headers.
        let mut bytes = frame(0x0, 300);
        for _ in 0..3 {
            bytes.extend(frame(0x8, 4)); // WINDOW_UPDATE
        }
        bytes.extend(frame(0x1, 20)); // HEADERS: not control
                                      // Fed one byte at a time: headers split across reads.
        for b in &bytes {
            assert!(!m.observe(std::slice::from_ref(b)));
        }
        tokio::time::advance(Duration::from_millis(1100)).await;
        for _ in 0..3 {
            assert!(!m.observe(&frame(0x6, 8)), "a new window");
        }
        assert!(m.observe(&frame(0x4, 0)), "the fourth in one second");
        assert!(m.observe(&frame(0x0, 1)), "stays tripped");
    }

    #[test]
    fn counts_refused_streams_in_the_bytes_written() {
        let rst = |code: u32| {
            let mut f = frame(RST_STREAM, 0);
            f[2] = 4;
            f.extend(code.to_be_bytes());
            f
        };
        let mut bytes = frame(0x4, 6); // SETTINGS
        bytes.extend(rst(REFUSED_STREAM));
        bytes.extend(frame(0x0, 40)); // DATA
        bytes.extend(rst(0x8)); // CANCEL: not a refusal
        bytes.extend(rst(REFUSED_STREAM));
        let mut r = Refusals::default();
        let refused: usize = bytes
            .iter()
            .map(|b| r.observe(std::slice::from_ref(b)))
            .sum();
        assert_eq!(refused, 2, "fed one byte at a time");
        assert_eq!(Refusals::default().observe(&bytes), 2, "in one write");
    }
}
