//! A replay file's camera keys (`camera_up`, `camera_focal`,
//! `camera_principal`, and optionally `camera_height` and
//! `camera_distortion`) read into a [`CameraCalibration`]: all or none of
//! the required ones, each of its shape. Its values are checked with the
//! rest of the sequence ([`super::Sequence::validate`]).

use super::camera::CameraCalibration;
use super::error::{npz_err, SequenceError};
use super::keys::*;
use super::source::{scalar, ArraySource};
use crate::npz::{check_declared_shape, NpzError};

/// The calibration in `npz`'s camera keys (`None` without any), for
/// keypoints in pixels of an image of `image_size`. Values are checked by
/// [`Sequence::validate`].
pub(super) fn camera_from(
    npz: &mut impl ArraySource,
    image_size: (u32, u32),
) -> Result<Option<CameraCalibration>, SequenceError> {
    let present: Vec<&str> = CAMERA_KEYS
        .into_iter()
        .chain([KEY_CAMERA_HEIGHT, KEY_CAMERA_DISTORTION])
        .filter(|k| npz.has(k))
        .collect();
    if present.is_empty() {
        return Ok(None);
    }
    if let Some(missing) = CAMERA_KEYS.into_iter().find(|k| !npz.has(k)) {
        return Err(SequenceError::PartialCamera {
            missing,
            found: present.join(", "),
        });
    }
    Ok(Some(CameraCalibration {
        up: camera_array(npz, KEY_CAMERA_UP)?,
        focal: camera_array(npz, KEY_CAMERA_FOCAL)?,
        principal: camera_array(npz, KEY_CAMERA_PRINCIPAL)?,
        image_size: Some(image_size),
        height: if npz.has(KEY_CAMERA_HEIGHT) {
            Some(scalar(npz, KEY_CAMERA_HEIGHT).map_err(npz_err)?)
        } else {
            None
        },
        distortion: if npz.has(KEY_CAMERA_DISTORTION) {
            Some(distortion_from(npz)?)
        } else {
            None
        },
    }))
}

/// [`KEY_CAMERA_DISTORTION`] as the five OpenCV coefficients (`k3 = 0` for
/// a four-value array).
fn distortion_from(npz: &mut impl ArraySource) -> Result<[f32; 5], SequenceError> {
    let shape = npz.shape_of(KEY_CAMERA_DISTORTION).map_err(npz_err)?;
    if shape != [4] && shape != [5] {
        return Err(npz_err(NpzError::Shape {
            key: KEY_CAMERA_DISTORTION.to_owned(),
            expected: "(4,) or (5,)".into(),
            actual: shape,
        }));
    }
    let array = npz.read(KEY_CAMERA_DISTORTION, &shape).map_err(npz_err)?;
    match *array.data() {
        [k1, k2, p1, p2] => Ok([k1, k2, p1, p2, 0.0]),
        [k1, k2, p1, p2, k3] => Ok([k1, k2, p1, p2, k3]),
        _ => Err(npz_err(NpzError::Shape {
            key: KEY_CAMERA_DISTORTION.to_owned(),
            expected: "(4,) or (5,)".into(),
            actual: array.shape().to_vec(),
        })),
    }
}

/// The `(N,)` array `key` as a fixed-size array.
fn camera_array<const N: usize>(
    npz: &mut impl ArraySource,
    key: &str,
) -> Result<[f32; N], SequenceError> {
    let shape = npz.shape_of(key).map_err(npz_err)?;
    check_declared_shape(key, &shape, &[Some(N)]).map_err(npz_err)?;
    let array = npz.read(key, &shape).map_err(npz_err)?;
    Ok(std::array::from_fn(|i| array.data()[i]))
}
