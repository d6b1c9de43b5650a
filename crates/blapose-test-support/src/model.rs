//! A model whose answers do not matter, for the tests of what happens
//! around the model (transport, limits, metrics, TLS): a server needs one,
//! and loading real weights would only slow those tests down.

use blapose_proto::v1::ModelDescription;
use blapose_server::backend::{Backend, BackendError, SequenceBackend, OUTPUT_DIM, STATE_DIM};
use blapose_server::ModelProvider;

/// A model that answers every step and sequence with the same lengths
/// (0.25 m each): for tests of what happens around the model (transport,
/// limits, metrics), where its answers do not matter. Its steps check
/// that the server hands them whole rows of state and output.
#[derive(Debug, Default, Clone, Copy)]
pub struct ConstantModel;

impl Backend for ConstantModel {
    /// Also checks the buffers the server hands it are `batch` rows.
    fn step(
        &mut self,
        _: &[f32],
        hidden: &mut [f32],
        out: &mut [f32],
        batch: usize,
    ) -> Result<(), BackendError> {
        assert_eq!(hidden.len(), batch * STATE_DIM);
        out.fill(0.25);
        assert_eq!(out.len(), batch * OUTPUT_DIM);
        Ok(())
    }
}

impl SequenceBackend for ConstantModel {
    fn predict(&mut self, _: &[f32], _: usize) -> Result<[f32; 16], BackendError> {
        Ok([0.25; 16])
    }
}

impl ModelProvider for ConstantModel {
    fn online(&self) -> Result<Box<dyn Backend>, BackendError> {
        Ok(Box::new(ConstantModel))
    }
    fn offline(&self) -> Result<Box<dyn SequenceBackend>, BackendError> {
        Ok(Box::new(ConstantModel))
    }
    fn describe(&self) -> Vec<ModelDescription> {
        Vec::new()
    }
}

/// A server with `config` and the [`ConstantModel`], on a free loopback
/// port: what the tests of the transport and the limits start.
pub async fn spawn_constant(config: blapose_server::ServerConfig) -> blapose_server::ServerHandle {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .expect("a loopback port");
    blapose_server::spawn_with_provider(config, listener, std::sync::Arc::new(ConstantModel))
        .await
        .expect("the server starts")
}
