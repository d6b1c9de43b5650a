//! The session key: the secret replicas share to authenticate session
//! tokens, how `--session-key` spells it, and the HMAC-SHA256 it keys
//! (from the `hmac` crate over `sha2`; MACs verified in constant time).

use hmac::Mac;
use sha2::{Digest, Sha256};

/// Shortest session key accepted, in bytes.
pub const MIN_KEY_BYTES: usize = 16;

/// Why a session key was not accepted.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum KeyError {
    /// A key shorter than [`MIN_KEY_BYTES`].
    #[error("the session key has {0} bytes; at least {MIN_KEY_BYTES} are required")]
    TooShort(usize),
    /// A key that does not decode.
    #[error("the session key does not decode: {0}")]
    Encoding(String),
}

/// The secret replicas share to authenticate tokens (never printed).
#[derive(Clone, PartialEq, Eq)]
pub struct SessionKey(Box<[u8]>);

impl std::fmt::Debug for SessionKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "SessionKey({} bytes, redacted)", self.0.len())
    }
}

impl SessionKey {
    /// A key of these bytes (at least [`MIN_KEY_BYTES`]).
    pub fn new(bytes: &[u8]) -> Result<Self, KeyError> {
        if bytes.len() < MIN_KEY_BYTES {
            return Err(KeyError::TooShort(bytes.len()));
        }
        Ok(Self(bytes.into()))
    }

    /// Parse `--session-key`: `hex:<hex digits>`, `base64:<standard or
    /// URL-safe base64, padding optional>`, or else the string's own UTF-8
    /// bytes. At least 16 bytes after decoding.
    pub fn parse(text: &str) -> Result<Self, KeyError> {
        let bytes = if let Some(hex) = text.strip_prefix("hex:") {
            decode_hex(hex.trim())?
        } else if let Some(b64) = text.strip_prefix("base64:") {
            decode_base64(b64.trim())?
        } else {
            text.as_bytes().to_vec()
        };
        Self::new(&bytes)
    }

    pub(crate) fn mac(&self, message: &[u8]) -> [u8; 32] {
        hmac_sha256(&self.0, message)
    }

    /// Whether `mac` authenticates `message` (compared in constant time).
    pub(crate) fn verifies(&self, message: &[u8], mac: &[u8]) -> bool {
        let Ok(mut check) = HmacSha256::new_from_slice(&self.0) else {
            return false;
        };
        check.update(message);
        check.verify_slice(mac).is_ok()
    }
}

fn decode_hex(text: &str) -> Result<Vec<u8>, KeyError> {
    if !text.len().is_multiple_of(2) {
        return Err(KeyError::Encoding("hex: an odd number of digits".into()));
    }
    text.as_bytes()
        .chunks_exact(2)
        .map(|pair| {
            let digit = |c: u8| (c as char).to_digit(16);
            match (digit(pair[0]), digit(pair[1])) {
                (Some(hi), Some(lo)) => Ok((hi * 16 + lo) as u8),
                _ => Err(KeyError::Encoding(format!(
                    "hex: {:?} is not a hex byte",
                    String::from_utf8_lossy(pair)
                ))),
            }
        })
        .collect()
}

fn decode_base64(text: &str) -> Result<Vec<u8>, KeyError> {
    use base64::engine::{DecodePaddingMode, GeneralPurpose, GeneralPurposeConfig};
    use base64::{alphabet, Engine};
    let config =
        GeneralPurposeConfig::new().with_decode_padding_mode(DecodePaddingMode::Indifferent);
    let alphabet = if text.contains(['-', '_']) {
        &alphabet::URL_SAFE
    } else {
        &alphabet::STANDARD
    };
    GeneralPurpose::new(alphabet, config)
        .decode(text)
        .map_err(|e| KeyError::Encoding(format!("base64: {e}")))
}

/// HMAC-SHA256 (RFC 2104) of `message` under `key`.
pub fn hmac_sha256(key: &[u8], message: &[u8]) -> [u8; 32] {
    let mut mac = HmacSha256::new_from_slice(key).expect("HMAC takes keys of any length");
    mac.update(message);
    mac.finalize().into_bytes().into()
}

type HmacSha256 = hmac::Hmac<Sha256>;

/// A 32-byte weights id from a weights hash as the server reports it
/// (lowercase hex SHA-256); any other string (a test provider's) is hashed.
pub fn weights_id(sha256_hex: &str) -> [u8; 32] {
    match decode_hex(sha256_hex) {
        Ok(bytes) if bytes.len() == 32 => {
            let mut id = [0u8; 32];
            id.copy_from_slice(&bytes);
            id
        }
        _ => Sha256::digest(sha256_hex.as_bytes()).into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_parse_from_hex_base64_or_raw_and_must_be_16_bytes() {
        let raw = SessionKey::parse("0123456789abcdef").unwrap();
        assert_eq!(&*raw.0, b"0123456789abcdef");
        let hex = SessionKey::parse("hex:000102030405060708090a0b0c0d0e0f").unwrap();
        assert_eq!(&*hex.0, &(0u8..16).collect::<Vec<_>>()[..]);
        let b64 = SessionKey::parse("base64:AAECAwQFBgcICQoLDA0ODw==").unwrap();
        assert_eq!(b64, hex);
        let b64 = SessionKey::parse("base64:AAECAwQFBgcICQoLDA0ODw").unwrap();
        assert_eq!(b64, hex);
        assert_eq!(SessionKey::parse("short"), Err(KeyError::TooShort(5)));
        assert_eq!(
            SessionKey::parse("hex:00010203"),
            Err(KeyError::TooShort(4))
        );
        assert!(matches!(
            SessionKey::parse("hex:zz"),
            Err(KeyError::Encoding(_))
        ));
        assert!(matches!(
            SessionKey::parse("base64:!!!!"),
            Err(KeyError::Encoding(_))
        ));
        assert!(!format!("{raw:?}").contains("0123"), "keys are not printed");
    }

    #[test]
    fn hmac_matches_rfc_4231() {
        let hex = |b: &[u8]| b.iter().map(|x| format!("{x:02x}")).collect::<String>();
        // Test case 1.
        assert_eq!(
            hex(&hmac_sha256(&[0x0b; 20], b"Hi There")),
            "b0344c61d8db38535ca8afceaf0bf12b881dc200c9833da726e9376c2e32cff7"
        );
        // Test case 2.
        assert_eq!(
            hex(&hmac_sha256(b"Jefe", b"what do ya want for nothing?")),
            "5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"
        );
        // Test case 6: a key longer than the block.
        assert_eq!(
            hex(&hmac_sha256(
                &[0xaa; 131],
                b"Test Using Larger Than Block-Size Key - Hash Key First"
            )),
            "60e431591ee0b67f0d8a26aacbf5b77f8e0bc6213728c5140546040f0ee37f54"
        );
    }
}
