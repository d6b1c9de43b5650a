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

use std::time::Duration;

use tokio::time::Instant;

/// Frame types that open nothing and cost the server work: PRIORITY,
/// RST_STREAM, SETTINGS, PING, WINDOW_UPDATE (RFC 9113, section 6).
const CONTROL_TYPES: [u8; 5] = [0x2, 0x3, 0x4, 0x6, 0x8];
const HEADER: usize = 9;
const WINDOW: Duration = Duration::from_secs(1);

/// Follows one connection's incoming frames and counts its control frames.
#[derive(Debug)]
pub struct FrameMeter {
    limit: u32,
    header: [u8; HEADER],
    have: usize,
    skip: usize,
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
            header: [0; HEADER],
            have: 0,
            skip: 0,
            window_start: Instant::now(),
            in_window: 0,
            tripped: false,
        }
    }

    /// Account for `bytes`, the next bytes read; `true` once the
    /// connection has passed the limit (and from then on).
    pub fn observe(&mut self, mut bytes: &[u8]) -> bool {
        while !bytes.is_empty() && !self.tripped {
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
            if CONTROL_TYPES.contains(&h[3]) {
                self.count();
            }
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
}
