//! The protobuf codec of the generated stubs, with small per-RPC buffers.
//!
//! tonic's default prost codec allocates an 8 KiB encode and an 8 KiB decode
//! buffer for every RPC up front. A blapose stream lives as long as a camera
//! session and carries ~0.5 KiB frames, so with thousands of mostly idle
//! sessions those two buffers were most of the server's memory per session.
//! This codec starts them at [`BUFFER_SIZE`]; they still grow in steps of
//! that size for larger messages (an offline `AdjustSequence` request of
//! thousands of frames), so nothing is refused that the default accepts.

use std::marker::PhantomData;

use prost::Message;
use tonic::codec::{BufferSettings, Codec};
use tonic_prost::ProstCodec;

/// Initial (and growth-step) size of each encode/decode buffer, bytes:
/// two frames of 17 joints.
pub const BUFFER_SIZE: usize = 1024;

/// Encoded bytes after which a streaming encoder yields (tonic's default).
const YIELD_THRESHOLD: usize = 32 * 1024;

/// [`ProstCodec`] with [`BUFFER_SIZE`] buffers (named by `build.rs` as the
/// codec of every generated method).
#[derive(Debug, Clone)]
pub struct SmallBufferCodec<T, U>(PhantomData<(T, U)>);

impl<T, U> Default for SmallBufferCodec<T, U> {
    fn default() -> Self {
        Self(PhantomData)
    }
}

fn settings() -> BufferSettings {
    BufferSettings::new(BUFFER_SIZE, YIELD_THRESHOLD)
}

impl<T, U> Codec for SmallBufferCodec<T, U>
where
    T: Message + Send + 'static,
    U: Message + Default + Send + 'static,
{
    type Encode = T;
    type Decode = U;
    type Encoder = <ProstCodec<T, U> as Codec>::Encoder;
    type Decoder = <ProstCodec<T, U> as Codec>::Decoder;

    fn encoder(&mut self) -> Self::Encoder {
        ProstCodec::<T, U>::raw_encoder(settings())
    }

    fn decoder(&mut self) -> Self::Decoder {
        ProstCodec::<T, U>::raw_decoder(settings())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tonic::codec::Encoder;

    #[test]
    fn buffers_start_small() {
        let mut codec =
            SmallBufferCodec::<crate::v1::StreamRequest, crate::v1::StreamResponse>::default();
        let settings = format!("{:?}", codec.encoder().buffer_settings());
        assert!(
            settings.contains(&format!("buffer_size: {BUFFER_SIZE}")),
            "{settings}"
        );
    }
}
