//! Portable session state: a session exported as an opaque, versioned,
//! authenticated *session token* that any replica sharing the session key
//! can restore exactly.
//!
//! A session lives in one server's memory; a token lets it outlive that
//! server. It holds everything the answers after it depend on: the GRU
//! hidden state (f32, bit for bit), the running mean's f64 sums and count
//! (so the estimate continues bit for bit, not from a rounded mean), the
//! input format, the camera calibration as the client sent it (the camera
//! the models read through is rebuilt from it by the same validation and
//! preparation an open runs), the client label, the server lifter's window
//! of normalized keypoints for a lifting session, and the SHA-256 of the
//! weights the state belongs to (the online GRU of the session's family,
//! and the lifter's) so that a replica with other weights refuses it
//! instead of continuing a state its model never produced.
//!
//! # Layout (version 3)
//!
//! A simple explicit binary layout, all integers and floats little-endian,
//! rather than a private protobuf message: the token is dominated by 1,024
//! raw f32 (4 KiB) that protobuf would store the same way, every field is
//! fixed or length-prefixed, and an explicit layout makes the exact bytes
//! that are authenticated and the version check obvious (a decoder that
//! rejects any trailing or missing byte is a few lines, with no
//! "unknown fields" leniency to reason about).
//!
//! ```text
//! offset size  field
//! 0      4     magic "BLPT"
//! 4      1     version (3)
//! 5      1     flags: bit 0 camera calibration present, bit 1 lifter window
//!              present, bit 2 subject present, bit 3 motion stage present,
//!              bit 4 chain origin present, bit 5 owner present
//! 6      16    session id
//! 22     32    SHA-256 of the session family's online GRU weights
//! 54     8     issued at (u64, milliseconds since the Unix epoch)
//! 62     8     frames the model read (u64) = the running mean's count
//! 70     1     keypoint layout (1 H36M-17, 2 SH-16, 3 COCO-17)
//! 71     1     coordinates (0 normalized, 1 pixels)
//! 72     4+4   image width, height (u32; 0 when normalized)
//! 80     1+n   client label (length byte, UTF-8)
//! ..     128   running sums of the 16 bone-length predictions (f64)
//! ..     4+4h  hidden-state length h (u32) and the hidden state (f32)
//! ..     8     frames answered without a detected joint (u64); frames seen
//!              = this + the running mean's count
//! ..     4+136 joints seen so far (u32, bit j = joint j), then each joint's
//!              last detected position (17 x 2 f32; 0 for joints not seen)
//! [camera] 2+c length (u16) and the prost encoding of the CameraCalibration
//! [subject] 4+1 stature (f32, metres) and sex (u8: 0 unspecified, 1 female,
//!          2 male)
//! [motion] 8   frame rate (f64), then the direction filter's and the root
//!          4+8n filter's state, each a count (u32) and f64 values
//! [origin] 8   for a session restored from a token: the issue time (u64 ms)
//!              of the first token of the chain it came from; the token
//!              expires `--token-ttl` after this instead of its own issue
//!              time, so no chain of restores outlives its first token
//! [owner]  16  the client that held the session (its hashed identity,
//!              `crate::quota::ClientId`): the floor of ended sessions it
//!              pushed out of this server's memory applies to the token
//! [lifter] 32  SHA-256 of the lifter weights
//!          2+2 receptive field, frames held w (u16 each)
//!          136w the window's frames, oldest first (17 x 2 f32 each)
//! end-32 32    HMAC-SHA256(session key, every byte before it)
//! ```
//!
//! A session without a camera or lifter gives a 4,489-byte token (plus its
//! label); the hidden state is 4,096 of them. Version 1 (before missing
//! joints were held) lacked the two missing-joint fields, version 2 the
//! issue time. The magic and the version are
//! read before the MAC is checked (a later version may authenticate
//! differently); everything else is read only from authenticated bytes.
//! A token expires `--token-ttl` after it was issued: every replica refuses
//! it then, which bounds what a replica that never saw the session close
//! can be made to restore. An authentic token is still checked like input
//! before it is restored ([`crate::restore_check`]): a signature says which
//! replica wrote it, not that its state is one a session can be in.
//!
//! The key and its HMAC-SHA256 are [`key`]'s (checked there against RFC
//! 4231's test vectors; MACs verified in constant time).

use blapose_core::layouts::{Coordinates, KeypointLayout};
use blapose_core::missing::HeldJoints;
use blapose_core::motion::MotionState;
use blapose_core::{Keypoints2d, NUM_BONES, NUM_JOINTS};
use blapose_proto::v1 as pb;
use prost::Message;

pub mod key;

pub use key::{hmac_sha256, weights_id, KeyError, SessionKey, MIN_KEY_BYTES};

use crate::session::{InputFormat, RunningMean, SessionId, StateCopy, STATE_DIM};

/// The token format this server writes and reads.
pub const TOKEN_VERSION: u8 = 3;
/// First bytes of every token.
pub const MAGIC: [u8; 4] = *b"BLPT";
/// Bytes of the MAC at the end of a token.
pub const MAC_BYTES: usize = 32;

const FLAG_CAMERA: u8 = 1;
const FLAG_LIFTER: u8 = 2;
const FLAG_SUBJECT: u8 = 4;
const FLAG_MOTION: u8 = 8;
const FLAG_ORIGIN: u8 = 16;
const FLAG_OWNER: u8 = 32;

/// Most filter values a token's motion section may hold per filter (the
/// served filters hold 99 and 9).
const MAX_MOTION_VALUES: usize = 4096;

/// A motion session's stage in a token: its frame rate and its filters'
/// state.
#[derive(Debug, Clone, PartialEq)]
pub struct PortableMotion {
    /// Frames per second the stage runs at.
    pub rate_hz: f64,
    /// The filters' state.
    pub state: MotionState,
}
const FRAME_FLOATS: usize = NUM_JOINTS * 2;

/// Why a token was refused or a key not accepted.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TokenError {
    /// Not a session token at all (too short, wrong magic).
    #[error("the session token is not a blapose session token ({0})")]
    NotAToken(String),
    /// Another token format version.
    #[error("the session token has format version {found}; this server reads version {TOKEN_VERSION} (a replica of another release made it)")]
    Version {
        /// The token's version.
        found: u8,
    },
    /// The MAC does not match: altered, truncated or another key.
    #[error("the session token failed authentication: it was altered or truncated, or made under another session key")]
    Unauthenticated,
    /// Authentic but undecodable (only a server bug could make one).
    #[error("the session token is malformed: {0}")]
    Malformed(String),
}

impl TokenError {
    /// The gRPC status a resume with such a token ends with.
    pub fn to_status(&self) -> tonic::Status {
        match self {
            Self::NotAToken(_) | Self::Malformed(_) => {
                tonic::Status::invalid_argument(self.to_string())
            }
            Self::Version { .. } => tonic::Status::failed_precondition(self.to_string()),
            Self::Unauthenticated => tonic::Status::unauthenticated(self.to_string()),
        }
    }
}

/// The lifter part of a lifting session's state.
#[derive(Debug, Clone, PartialEq)]
pub struct PortableWindow {
    /// The lifter weights it belongs to.
    pub lifter_id: [u8; 32],
    /// The lifter's receptive field (the window's size).
    pub receptive_field: usize,
    /// The frames held, oldest first.
    pub frames: Vec<Keypoints2d>,
}

/// Everything a token carries, decoded.
#[derive(Debug, Clone, PartialEq)]
pub struct PortableState {
    /// The session's id.
    pub session_id: SessionId,
    /// The online GRU weights of the session's family.
    pub weights_id: [u8; 32],
    /// Input format.
    pub input: InputFormat,
    /// Client label.
    pub label: String,
    /// The camera calibration as opened.
    pub camera: Option<pb::CameraCalibration>,
    /// The GRU state and running mean.
    pub hidden: Vec<f32>,
    /// The running mean.
    pub lengths: RunningMean,
    /// The lifter's window, for a lifting session.
    pub window: Option<PortableWindow>,
    /// Each joint's last detected position.
    pub held: HeldJoints,
    /// Frames answered without a detected joint.
    pub skipped: u64,
    /// The subject as opened.
    pub subject: Option<pb::Subject>,
    /// The motion stage, for a session opened with motion.
    pub motion: Option<PortableMotion>,
    /// When the token was issued (milliseconds since the Unix epoch).
    pub issued_at_ms: u64,
    /// For a session restored from a token: the issue time of the first
    /// token of its chain, which this token expires from.
    pub origin_ms: Option<u64>,
    /// The client that held the session (hashed identity).
    pub owner: Option<[u8; 16]>,
}

/// Milliseconds since the Unix epoch now (0 for a clock before it).
pub fn now_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
}

impl PortableState {
    /// Frames processed in this state.
    pub fn frames_seen(&self) -> u64 {
        self.lengths.count() + self.skipped
    }

    /// The time the token's TTL runs from: its chain's origin, or its own
    /// issue time for a session that was never restored.
    pub fn expiry_origin_ms(&self) -> u64 {
        self.origin_ms.unwrap_or(self.issued_at_ms)
    }

    /// Assemble from a session's parts and a copy of its state.
    pub fn new(
        session_id: SessionId,
        weights_id: [u8; 32],
        input: InputFormat,
        label: &str,
        camera: Option<&pb::CameraCalibration>,
        lifter: Option<([u8; 32], usize)>,
        state: StateCopy,
    ) -> Self {
        let origin_ms = state.origin_ms;
        let window = match (lifter, state.window) {
            (Some((lifter_id, receptive_field)), Some(frames)) => Some(PortableWindow {
                lifter_id,
                receptive_field,
                frames,
            }),
            _ => None,
        };
        Self {
            session_id,
            weights_id,
            input,
            label: label.to_string(),
            camera: camera.cloned(),
            hidden: state.hidden.into_vec(),
            lengths: state.lengths,
            window,
            held: state.held,
            skipped: state.skipped,
            subject: None,
            motion: None,
            issued_at_ms: now_ms(),
            origin_ms,
            owner: None,
        }
    }

    /// Encode and authenticate under `key`.
    pub fn seal(&self, key: &SessionKey) -> Vec<u8> {
        let camera = self.camera.as_ref().map(|c| c.encode_to_vec());
        let mut out = Vec::with_capacity(
            4550 + camera.as_ref().map_or(0, Vec::len)
                + self
                    .window
                    .as_ref()
                    .map_or(0, |w| 36 + w.frames.len() * FRAME_FLOATS * 4),
        );
        out.extend_from_slice(&MAGIC);
        out.push(TOKEN_VERSION);
        let mut flags = 0;
        if camera.is_some() {
            flags |= FLAG_CAMERA;
        }
        if self.window.is_some() {
            flags |= FLAG_LIFTER;
        }
        if self.subject.is_some() {
            flags |= FLAG_SUBJECT;
        }
        if self.motion.is_some() {
            flags |= FLAG_MOTION;
        }
        if self.origin_ms.is_some() {
            flags |= FLAG_ORIGIN;
        }
        if self.owner.is_some() {
            flags |= FLAG_OWNER;
        }
        out.push(flags);
        out.extend_from_slice(self.session_id.as_bytes());
        out.extend_from_slice(&self.weights_id);
        out.extend_from_slice(&self.issued_at_ms.to_le_bytes());
        out.extend_from_slice(&self.lengths.count().to_le_bytes());
        out.push(match self.input.layout {
            KeypointLayout::H36m17 => 1,
            KeypointLayout::Sh16 => 2,
            KeypointLayout::Coco17 => 3,
        });
        let (tag, w, h) = match self.input.coordinates {
            Coordinates::Normalized => (0u8, 0u32, 0u32),
            Coordinates::Pixels { width, height } => (1, width, height),
        };
        out.push(tag);
        out.extend_from_slice(&w.to_le_bytes());
        out.extend_from_slice(&h.to_le_bytes());
        // Labels are at most 128 bytes (MAX_LABEL_BYTES); cut at a char
        // boundary all the same.
        let mut end = self.label.len().min(255);
        while !self.label.is_char_boundary(end) {
            end -= 1;
        }
        out.push(end as u8);
        out.extend_from_slice(&self.label.as_bytes()[..end]);
        for s in self.lengths.sum() {
            out.extend_from_slice(&s.to_le_bytes());
        }
        out.extend_from_slice(&(self.hidden.len() as u32).to_le_bytes());
        for v in &self.hidden {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&self.skipped.to_le_bytes());
        let seen = self
            .held
            .last()
            .iter()
            .enumerate()
            .filter(|(_, p)| p.is_some())
            .fold(0u32, |m, (j, _)| m | 1 << j);
        out.extend_from_slice(&seen.to_le_bytes());
        for p in self.held.last() {
            for v in p.unwrap_or([0.0; 2]) {
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
        if let Some(camera) = &camera {
            out.extend_from_slice(&(camera.len().min(u16::MAX as usize) as u16).to_le_bytes());
            out.extend_from_slice(camera);
        }
        if let Some(subject) = &self.subject {
            out.extend_from_slice(&subject.height_m.to_le_bytes());
            out.push(u8::try_from(subject.sex).unwrap_or(u8::MAX));
        }
        if let Some(m) = &self.motion {
            out.extend_from_slice(&m.rate_hz.to_le_bytes());
            for values in [&m.state.directions, &m.state.root] {
                out.extend_from_slice(&(values.len() as u32).to_le_bytes());
                for v in values.iter() {
                    out.extend_from_slice(&v.to_le_bytes());
                }
            }
        }
        if let Some(origin) = self.origin_ms {
            out.extend_from_slice(&origin.to_le_bytes());
        }
        if let Some(owner) = &self.owner {
            out.extend_from_slice(owner);
        }
        if let Some(w) = &self.window {
            out.extend_from_slice(&w.lifter_id);
            out.extend_from_slice(&(w.receptive_field as u16).to_le_bytes());
            out.extend_from_slice(&(w.frames.len() as u16).to_le_bytes());
            for frame in &w.frames {
                for v in frame.iter().flatten() {
                    out.extend_from_slice(&v.to_le_bytes());
                }
            }
        }
        let mac = key.mac(&out);
        out.extend_from_slice(&mac);
        out
    }

    /// Check and decode a token made under `key`.
    pub fn open(token: &[u8], key: &SessionKey) -> Result<Self, TokenError> {
        if token.len() < MAGIC.len() + 1 {
            return Err(TokenError::NotAToken(format!(
                "{} bytes, too short",
                token.len()
            )));
        }
        if token[..4] != MAGIC {
            return Err(TokenError::NotAToken("wrong leading bytes".into()));
        }
        if token[4] != TOKEN_VERSION {
            return Err(TokenError::Version { found: token[4] });
        }
        if token.len() < 6 + MAC_BYTES {
            return Err(TokenError::Unauthenticated);
        }
        let (body, mac) = token.split_at(token.len() - MAC_BYTES);
        if !key.verifies(body, mac) {
            return Err(TokenError::Unauthenticated);
        }
        decode_body(body)
    }
}

/// A cursor over authenticated bytes.
struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], TokenError> {
        let end = self
            .at
            .checked_add(n)
            .filter(|&e| e <= self.bytes.len())
            .ok_or_else(|| TokenError::Malformed(format!("ends inside {what}")))?;
        let s = &self.bytes[self.at..end];
        self.at = end;
        Ok(s)
    }
    fn array<const N: usize>(&mut self, what: &str) -> Result<[u8; N], TokenError> {
        let mut a = [0u8; N];
        a.copy_from_slice(self.take(N, what)?);
        Ok(a)
    }
    fn u8(&mut self, what: &str) -> Result<u8, TokenError> {
        Ok(self.array::<1>(what)?[0])
    }
    fn u16(&mut self, what: &str) -> Result<u16, TokenError> {
        Ok(u16::from_le_bytes(self.array(what)?))
    }
    fn u32(&mut self, what: &str) -> Result<u32, TokenError> {
        Ok(u32::from_le_bytes(self.array(what)?))
    }
    fn u64(&mut self, what: &str) -> Result<u64, TokenError> {
        Ok(u64::from_le_bytes(self.array(what)?))
    }
    fn f32s(&mut self, n: usize, what: &str) -> Result<Vec<f32>, TokenError> {
        let bytes = self.take(
            n.checked_mul(4)
                .ok_or_else(|| TokenError::Malformed(format!("{what}: too long")))?,
            what,
        )?;
        Ok(bytes
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect())
    }
}

fn decode_body(body: &[u8]) -> Result<PortableState, TokenError> {
    let bad = |what: String| TokenError::Malformed(what);
    let mut r = Reader { bytes: body, at: 6 };
    let flags = body[5];
    let known = FLAG_CAMERA | FLAG_LIFTER | FLAG_SUBJECT | FLAG_MOTION | FLAG_ORIGIN | FLAG_OWNER;
    if flags & !known != 0 {
        return Err(bad(format!("unknown flags {flags:#x}")));
    }
    let session_id = SessionId::from_bytes(r.array("the session id")?);
    let weights_id = r.array("the weights hash")?;
    let issued_at_ms = r.u64("the issue time")?;
    let count = r.u64("frames seen")?;
    let layout = match r.u8("the layout")? {
        1 => KeypointLayout::H36m17,
        2 => KeypointLayout::Sh16,
        3 => KeypointLayout::Coco17,
        other => return Err(bad(format!("unknown layout {other}"))),
    };
    let tag = r.u8("the coordinates")?;
    let (width, height) = (r.u32("the image width")?, r.u32("the image height")?);
    let coordinates = match tag {
        0 => Coordinates::Normalized,
        1 => Coordinates::Pixels { width, height },
        other => return Err(bad(format!("unknown coordinates {other}"))),
    };
    let label_len = usize::from(r.u8("the label length")?);
    let label = std::str::from_utf8(r.take(label_len, "the label")?)
        .map_err(|_| bad("the label is not UTF-8".into()))?
        .to_string();
    let mut sum = [0f64; NUM_BONES];
    for s in &mut sum {
        *s = f64::from_le_bytes(r.array("the running sums")?);
    }
    let hidden_len = r.u32("the hidden-state length")? as usize;
    if hidden_len != STATE_DIM {
        return Err(bad(format!(
            "a hidden state of {hidden_len} floats; this server's model has {STATE_DIM}"
        )));
    }
    let hidden = r.f32s(hidden_len, "the hidden state")?;
    let skipped = r.u64("the frames without a detected joint")?;
    let seen = r.u32("the joints seen")?;
    if seen >> NUM_JOINTS != 0 {
        return Err(bad(format!(
            "joints seen {seen:#x} beyond joint {NUM_JOINTS}"
        )));
    }
    let positions = r.f32s(FRAME_FLOATS, "the held joints")?;
    let held = HeldJoints::from_last(std::array::from_fn(|j| {
        (seen >> j & 1 == 1).then(|| [positions[2 * j], positions[2 * j + 1]])
    }));
    let camera = if flags & FLAG_CAMERA != 0 {
        let n = usize::from(r.u16("the camera length")?);
        let bytes = r.take(n, "the camera")?;
        Some(
            pb::CameraCalibration::decode(bytes)
                .map_err(|e| bad(format!("the camera does not decode: {e}")))?,
        )
    } else {
        None
    };
    let subject = if flags & FLAG_SUBJECT != 0 {
        let height_m = f32::from_le_bytes(r.array("the subject's stature")?);
        let sex = i32::from(r.u8("the subject's sex")?);
        Some(pb::Subject { height_m, sex })
    } else {
        None
    };
    let motion = if flags & FLAG_MOTION != 0 {
        let rate_hz = f64::from_le_bytes(r.array("the motion frame rate")?);
        let mut filter = |what: &str| -> Result<Vec<f64>, TokenError> {
            let n = r.u32(what)? as usize;
            if n > MAX_MOTION_VALUES {
                return Err(bad(format!(
                    "{what}: {n} values, at most {MAX_MOTION_VALUES}"
                )));
            }
            Ok(r.take(n * 8, what)?
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
                .collect())
        };
        let directions = filter("the motion direction filter")?;
        let root = filter("the motion root filter")?;
        Some(PortableMotion {
            rate_hz,
            state: MotionState { directions, root },
        })
    } else {
        None
    };
    let origin_ms = if flags & FLAG_ORIGIN != 0 {
        Some(r.u64("the chain origin")?)
    } else {
        None
    };
    let owner = if flags & FLAG_OWNER != 0 {
        Some(r.array("the owner")?)
    } else {
        None
    };
    let window = if flags & FLAG_LIFTER != 0 {
        let lifter_id = r.array("the lifter hash")?;
        let receptive_field = usize::from(r.u16("the receptive field")?);
        let held = usize::from(r.u16("the window length")?);
        if held > receptive_field {
            return Err(bad(format!(
                "a window of {held} frames for a receptive field of {receptive_field}"
            )));
        }
        let flat = r.f32s(held * FRAME_FLOATS, "the lifter window")?;
        let frames = flat
            .chunks_exact(FRAME_FLOATS)
            .map(|f| std::array::from_fn(|j| [f[2 * j], f[2 * j + 1]]))
            .collect();
        Some(PortableWindow {
            lifter_id,
            receptive_field,
            frames,
        })
    } else {
        None
    };
    if r.at != body.len() {
        return Err(bad(format!("{} bytes left over", body.len() - r.at)));
    }
    Ok(PortableState {
        session_id,
        weights_id,
        input: InputFormat {
            layout,
            coordinates,
        },
        label,
        camera,
        hidden,
        lengths: RunningMean::from_parts(sum, count),
        window,
        held,
        skipped,
        subject,
        motion,
        issued_at_ms,
        origin_ms,
        owner,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn key(byte: u8) -> SessionKey {
        SessionKey::new(&[byte; 32]).unwrap()
    }

    fn state(camera: bool, lifter: bool) -> PortableState {
        let mut lengths = RunningMean::new();
        for k in 0..7 {
            lengths.push(&std::array::from_fn(|b| 0.1 + 0.013 * (b + k) as f32));
        }
        PortableState {
            session_id: SessionId::from_bytes([7; 16]),
            weights_id: weights_id("ab"),
            input: InputFormat {
                layout: KeypointLayout::Coco17,
                coordinates: Coordinates::Pixels {
                    width: 1920,
                    height: 1080,
                },
            },
            label: "cam é".into(),
            camera: camera.then(|| pb::CameraCalibration {
                up: vec![0.0, -1.0, 0.1],
                focal_x: 1000.0,
                focal_y: 1000.0,
                principal_x: 960.0,
                principal_y: 540.0,
                image_size: None,
                height: 1.7,
                distortion: vec![-0.12, 0.03, 0.0005, -0.0002, 0.0],
            }),
            hidden: (0..STATE_DIM).map(|i| (i as f32 * 0.37).sin()).collect(),
            lengths,
            window: lifter.then(|| PortableWindow {
                lifter_id: weights_id("lifter"),
                receptive_field: 27,
                frames: (0..5)
                    .map(|f| [[f as f32 * 0.1, -0.5]; NUM_JOINTS])
                    .collect(),
            }),
            held: HeldJoints::from_last(std::array::from_fn(|j| {
                (j % 3 != 1).then_some([j as f32 * 0.05, -0.25 - j as f32 * 0.01])
            })),
            skipped: 2,
            subject: camera.then_some(pb::Subject {
                height_m: 1.72,
                sex: 1,
            }),
            issued_at_ms: 1_780_000_000_000,
            motion: None,
            origin_ms: lifter.then_some(1_779_999_000_000),
            owner: camera.then_some([9; 16]),
        }
    }

    #[test]
    fn tokens_round_trip_exactly() {
        for (camera, lifter) in [(false, false), (true, false), (false, true), (true, true)] {
            let s = state(camera, lifter);
            let token = s.seal(&key(1));
            let back = PortableState::open(&token, &key(1)).unwrap();
            assert_eq!(back, s);
            assert_eq!(back.frames_seen(), 7 + 2, "read and skipped frames");
            assert_eq!(back.held, s.held, "joints seen and not seen");
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&back.hidden), bits(&s.hidden));
            assert_eq!(back.lengths.sum(), s.lengths.sum());
        }
        let plain = state(false, false).seal(&key(1));
        // 4,489 bytes + the label's 6.
        assert_eq!(plain.len(), 4489 + 6, "token size");
    }

    #[test]
    fn altered_truncated_and_foreign_tokens_are_typed_errors() {
        let good = state(true, true).seal(&key(1));
        assert_eq!(
            PortableState::open(&good, &key(2)),
            Err(TokenError::Unauthenticated)
        );
        for cut in [0, 1, 4, 5, 6, 37, 38, 100, good.len() - 1] {
            let err = PortableState::open(&good[..cut], &key(1)).unwrap_err();
            assert!(
                matches!(err, TokenError::NotAToken(_) | TokenError::Unauthenticated),
                "cut {cut}: {err:?}"
            );
        }
        // Every single bit flip is refused.
        for byte in 0..good.len() {
            for bit in 0..8 {
                let mut t = good.clone();
                t[byte] ^= 1 << bit;
                let err = PortableState::open(&t, &key(1)).unwrap_err();
                if byte == 4 {
                    assert!(matches!(err, TokenError::Version { .. }), "{err:?}");
                } else if byte < 4 {
                    assert!(matches!(err, TokenError::NotAToken(_)), "{err:?}");
                } else {
                    assert_eq!(err, TokenError::Unauthenticated, "byte {byte} bit {bit}");
                }
            }
        }
        // A version-2 token (before tokens expired) is refused.
        let mut v2 = good.clone();
        v2[4] = 2;
        assert_eq!(
            PortableState::open(&v2, &key(1)),
            Err(TokenError::Version { found: 2 })
        );
        assert_eq!(
            TokenError::Version { found: 1 }.to_status().code(),
            tonic::Code::FailedPrecondition
        );
        assert_eq!(
            TokenError::Unauthenticated.to_status().code(),
            tonic::Code::Unauthenticated
        );
    }

    #[test]
    fn random_bytes_never_panic() {
        let mut rng = rand::rngs::StdRng::seed_from_u64(23);
        let good = state(false, true).seal(&key(1));
        for i in 0..20_000 {
            let len = rng.random_range(0..6000);
            let mut t: Vec<u8> = (0..len).map(|_| rng.random()).collect();
            if i % 2 == 0 && t.len() > 5 {
                t[..5].copy_from_slice(&good[..5]);
            }
            assert!(PortableState::open(&t, &key(1)).is_err());
        }
        // Authentic but malformed bodies (a server bug or a leaked key) are
        // refused without a panic too.
        for cut in 6..200 {
            let mut body = good[..cut].to_vec();
            let mac = key(1).mac(&body);
            body.extend_from_slice(&mac);
            assert!(matches!(
                PortableState::open(&body, &key(1)),
                Err(TokenError::Malformed(_))
            ));
        }
    }
}
