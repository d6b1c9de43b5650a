//! The offline way: a whole replay file adjusted by one `AdjustSequence`
//! call, optionally through the server's offline motion stage. Apart from
//! [`crate::replay`] (streams) because nothing of a stream's machinery
//! (pacing, windows, resumption) applies to one call.

use std::time::Instant;

use blapose_core::ModelKind;
use blapose_data::replay::Sequence;

use crate::client::{Client, SequenceInput};
use crate::error::ClientError;
use crate::replay::Adjusted;

/// Adjust `seq` with one `AdjustSequence` call (with `seq.camera` and
/// `seq.subject`, if any).
pub async fn adjust_offline(
    client: &Client,
    seq: &Sequence,
    model: ModelKind,
) -> Result<Adjusted, ClientError> {
    adjust_offline_with_motion(client, seq, model, None).await
}

/// [`adjust_offline`] with the server's offline motion stage at `motion`
/// frames per second (`Some(0.0)`: 50; `None`: no motion stage): the poses
/// smoothed and their feet held, and [`Adjusted::placement`] set.
pub async fn adjust_offline_with_motion(
    client: &Client,
    seq: &Sequence,
    model: ModelKind,
    motion: Option<f32>,
) -> Result<Adjusted, ClientError> {
    let started = Instant::now();
    let input = SequenceInput {
        motion,
        ..SequenceInput::from_sequence(seq)
    };
    let result = client.adjust_sequence(input, model).await?;
    Ok(Adjusted {
        model: result.model,
        first_frame: 0,
        adjusted: result.adjusted,
        bone_lengths: result.bone_lengths,
        lifter: None,
        lifted: Vec::new(),
        elapsed: started.elapsed(),
        session: None,
        resumes: 0,
        camera: seq.camera,
        placement: result.placement,
    })
}
