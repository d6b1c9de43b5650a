//! Generated Rust types for the blapose gRPC contract,
//! `proto/blapose/v1/blapose.proto` — the only interface between the server
//! and its clients.
//!
//! Generated at build time (protox + tonic-prost-build, no system `protoc`),
//! so the proto file stays the single source of truth. Both the server stub
//! ([`v1::pose_adjustment_server`]) and the client stub
//! ([`v1::pose_adjustment_client`]) live here; read the proto for the meaning
//! of every field. [`convert`] maps the generated layout and input-format
//! types to blapose-core's, once for both ends.

pub mod codec;
pub mod convert;

/// Package `blapose.v1`.
pub mod v1 {
    #![allow(clippy::all, missing_docs)]
    tonic::include_proto!("blapose.v1");
}

/// Encoded `google.protobuf.FileDescriptorSet` of `blapose/v1/blapose.proto`
/// (with source info), for gRPC server reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] =
    include_bytes!(concat!(env!("OUT_DIR"), "/blapose_descriptor.bin"));

/// Fully-qualified name of the gRPC service, as health checks name it.
pub const SERVICE_NAME: &str = "blapose.v1.PoseAdjustment";

#[cfg(test)]
mod tests {
    use super::v1;
    use prost::Message;

    #[test]
    fn descriptor_set_names_the_service() {
        // The descriptor must contain the service so reflection can show it.
        let text = String::from_utf8_lossy(super::FILE_DESCRIPTOR_SET);
        assert!(text.contains("PoseAdjustment"));
        assert!(text.contains("blapose.v1"));
    }

    #[test]
    fn oneof_round_trip() {
        let req = v1::StreamRequest {
            kind: Some(v1::stream_request::Kind::Frame(v1::Frame {
                frame_index: 7,
                keypoints_2d: vec![0.5; 34],
                confidence: vec![],
                pose_3d: vec![0.1; 51],
            })),
        };
        let bytes = req.encode_to_vec();
        let back = v1::StreamRequest::decode(bytes.as_slice()).expect("decodes");
        assert_eq!(back, req);
        assert_eq!(
            <v1::pose_adjustment_server::PoseAdjustmentServer<Dummy> as tonic::server::NamedService>::NAME,
            super::SERVICE_NAME
        );
    }

    struct Dummy;
    #[tonic::async_trait]
    impl v1::pose_adjustment_server::PoseAdjustment for Dummy {
        type StreamStream = tokio_stream::Empty<Result<v1::StreamResponse, tonic::Status>>;
        async fn stream(
            &self,
            _r: tonic::Request<tonic::Streaming<v1::StreamRequest>>,
        ) -> Result<tonic::Response<Self::StreamStream>, tonic::Status> {
            Err(tonic::Status::unimplemented("test"))
        }
        async fn close_session(
            &self,
            _r: tonic::Request<v1::CloseSessionRequest>,
        ) -> Result<tonic::Response<v1::CloseSessionResponse>, tonic::Status> {
            Err(tonic::Status::unimplemented("test"))
        }
        async fn adjust_sequence(
            &self,
            _r: tonic::Request<v1::AdjustSequenceRequest>,
        ) -> Result<tonic::Response<v1::AdjustSequenceResponse>, tonic::Status> {
            Err(tonic::Status::unimplemented("test"))
        }
        async fn model_info(
            &self,
            _r: tonic::Request<v1::ModelInfoRequest>,
        ) -> Result<tonic::Response<v1::ModelInfoResponse>, tonic::Status> {
            Err(tonic::Status::unimplemented("test"))
        }
    }
}
