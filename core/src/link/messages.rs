//! The link's messages: what a host asks, what a device answers, and the keypoint wire layout.

use core::fmt::Write as _;

use serde::{Deserialize, Serialize};

use super::wire::{narrow, KEYPOINT_BYTES, REASON_LEN};
use crate::camera::Camera;
use crate::error::{Error, Input};
use crate::localizer::{Failure, Localization, MatchCounts, StageTimings, MAX_VIEWS};
use crate::pose::Pose;
use crate::weights::{ModelConfig, Precision};

/// A message from the host.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Request<'a> {
    /// Echoed in the reply.
    pub id: u32,
    /// What is asked.
    #[serde(borrow)]
    pub body: RequestBody<'a>,
}

/// What the host asks.
// One message lives at a time, on the stack, and there is no heap to box into.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum RequestBody<'a> {
    /// The device's model, map and capacity ([`DeviceInfo`]).
    Info,
    /// Localize a query ([`LocalizeReply`]).
    #[serde(borrow)]
    Localize(LocalizeRequest<'a>),
}

/// "Localize these keypoints (pixels + camera) against these views / near this prior."
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LocalizeRequest<'a> {
    /// The query camera.
    pub camera: Camera,
    /// Keypoint pixels, [`KEYPOINT_BYTES`] each: `x`, `y` as `f32` little-endian
    /// (read in place from the receive buffer; see [`encode_keypoints`]).
    #[serde(borrow)]
    pub keypoints: &'a [u8],
    /// Which map views to match against.
    pub views: Views,
}

/// The view selection on the wire ([`ViewSelection`](crate::ViewSelection)).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Views {
    /// Views by image id, e.g. from image retrieval (at most [`MAX_VIEWS`]).
    ImageIds(heapless::Vec<u32, MAX_VIEWS>),
    /// The `k` views nearest to a coarse prior pose.
    NearPrior {
        /// The prior pose of the query.
        prior: WirePose,
        /// Number of views (at most [`MAX_VIEWS`]).
        k: u8,
        /// Viewing-direction cone of the preferred views, in degrees.
        max_angle_deg: f64,
    },
}

/// A [`Pose`] on the wire: row-major rotation matrix and translation, exactly the bits
/// of the pose.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct WirePose {
    /// World-to-camera rotation, row-major.
    pub rotation: [[f64; 3]; 3],
    /// Translation.
    pub translation: [f64; 3],
}

impl From<&Pose> for WirePose {
    fn from(pose: &Pose) -> Self {
        let m = pose.rotation.matrix();
        WirePose {
            rotation: core::array::from_fn(|i| core::array::from_fn(|j| m[(i, j)])),
            translation: [pose.translation.x, pose.translation.y, pose.translation.z],
        }
    }
}

impl WirePose {
    /// The pose with exactly these values (no re-orthonormalisation, so a pose survives
    /// the round trip bit for bit); [`Error::NonFinite`] on a NaN or infinity.
    pub fn to_pose(&self) -> crate::error::Result<Pose> {
        let values = self.rotation.iter().flatten().chain(&self.translation);
        if let Some(index) = values.clone().position(|v| !v.is_finite()) {
            return Err(Error::NonFinite {
                input: Input::Pose,
                index,
            });
        }
        let r = &self.rotation;
        let m = nalgebra::Matrix3::new(
            r[0][0], r[0][1], r[0][2], r[1][0], r[1][1], r[1][2], r[2][0], r[2][1], r[2][2],
        );
        let [x, y, z] = self.translation;
        Ok(Pose::new(
            nalgebra::Rotation3::from_matrix_unchecked(m),
            nalgebra::Vector3::new(x, y, z),
        ))
    }
}

/// A message from the device.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Response {
    /// The request's id; `None` when the frame did not decode.
    pub id: Option<u32>,
    /// The answer.
    pub body: ResponseBody,
}

/// The device's answer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum ResponseBody {
    /// Answer to [`RequestBody::Info`].
    Info(DeviceInfo),
    /// Answer to [`RequestBody::Localize`] when the input was valid.
    Localized(LocalizeReply),
    /// The frame or the request was refused.
    Error(LinkError),
}

/// "Pose or failure reason, with counts."
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LocalizeReply {
    /// The world-to-camera pose, or why there is none.
    pub outcome: core::result::Result<WirePose, Failure>,
    /// Match counts per stage.
    pub counts: MatchCounts,
    /// Views matched.
    pub views_used: u32,
    /// Selected views skipped for having too few points in front of them.
    pub views_skipped: u32,
    /// RANSAC minimal samples drawn.
    pub ransac_iterations: u32,
    /// Stage timings, when the device has a clock.
    pub timings: Option<StageTimings>,
    /// The acceptance rule's confidence in the best pose, when RANSAC found one (also
    /// when it was refused: [`Failure::LowConfidence`]).
    pub confidence: Option<f32>,
}

impl From<&Localization> for LocalizeReply {
    fn from(l: &Localization) -> Self {
        LocalizeReply {
            outcome: l.outcome.as_ref().map(WirePose::from).map_err(|f| *f),
            counts: l.counts,
            views_used: narrow(l.views_used),
            views_skipped: narrow(l.views_skipped),
            ransac_iterations: l.ransac_iterations,
            timings: l.timings,
            confidence: l.confidence,
        }
    }
}

/// "Model and map info": what the device runs, for the host to check before sending.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DeviceInfo {
    /// [`PROTOCOL_VERSION`](super::PROTOCOL_VERSION) of the device.
    pub protocol_version: u16,
    /// Most keypoints per query (and points per view): the localizer's `N`.
    pub capacity: u32,
    /// Most views per query.
    pub max_views: u8,
    /// Bytes per value of the Sinkhorn cost storage (4: `f32`, 2: `f16`).
    pub sinkhorn_bytes: u8,
    /// Bytes of the localizer workspace.
    pub workspace_bytes: u32,
    /// Bytes of the receive buffer: the longest request frame accepted.
    pub rx_frame_bytes: u32,
    /// The model blob.
    pub model: ModelInfo,
    /// The map blob.
    pub map: MapInfo,
}

/// The model blob a device runs.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ModelInfo {
    /// Blob format version.
    pub format_version: u16,
    /// Weight precision.
    pub precision: Precision,
    /// Architecture and inference settings.
    pub config: ModelConfig,
    /// Blob size in bytes.
    pub bytes: u32,
}

/// The map blob a device runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct MapInfo {
    /// Map format version.
    pub format_version: u16,
    /// 3D points.
    pub points: u32,
    /// Database views.
    pub views: u32,
    /// Cameras.
    pub cameras: u32,
    /// View-point observations.
    pub observations: u32,
    /// Blob size in bytes.
    pub bytes: u32,
}

/// Why a frame or request got no regular answer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum LinkError {
    /// The frame's bytes are not one request message (unknown message tag, bad varint,
    /// bytes left after the message, ...).
    Malformed,
    /// The frame ended inside a COBS block (a code byte announces more bytes than
    /// follow), is shorter than a checksum, or the message ended before its last field.
    Truncated,
    /// The frame's CRC-32 does not match its bytes (a byte was lost, changed or added on
    /// the way).
    Checksum,
    /// The frame is longer than the receive buffer (`limit` bytes); it was skipped up to
    /// its delimiter.
    Oversized {
        /// Receive buffer size.
        limit: u32,
    },
    /// The keypoint bytes are not a whole number of keypoints.
    KeypointBytes {
        /// Bytes received.
        len: u32,
    },
    /// The request decoded but its content was refused.
    Rejected(Rejection),
}

/// A request refused for its content (the localizer's input checks).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Rejection {
    /// More keypoints than the device's capacity.
    TooManyKeypoints {
        /// The capacity `N`.
        capacity: u32,
        /// Keypoints sent.
        requested: u32,
    },
    /// More views than [`MAX_VIEWS`].
    TooManyViews {
        /// [`MAX_VIEWS`].
        capacity: u32,
        /// Views asked for.
        requested: u32,
    },
    /// A keypoint is NaN or infinite, or has no finite bearing.
    NonFiniteKeypoint {
        /// Its index.
        index: u32,
    },
    /// The camera has invalid intrinsics or a keypoint cannot be undistorted.
    InvalidCamera,
    /// An image id the map has no view of.
    UnknownImage {
        /// The id.
        image_id: u32,
    },
    /// Any other input error, as the core describes it.
    Other {
        /// The core error's message (truncated to [`REASON_LEN`] bytes).
        message: heapless::String<REASON_LEN>,
    },
}

impl From<&Error> for Rejection {
    fn from(error: &Error) -> Self {
        match *error {
            Error::NonFinite {
                input: Input::Keypoints,
                index,
            } => Rejection::NonFiniteKeypoint {
                index: narrow(index),
            },
            Error::InvalidIntrinsics
            | Error::UndistortionDidNotConverge { .. }
            | Error::DistortionNotInvertible { .. } => Rejection::InvalidCamera,
            Error::MapUnknownImage { image_id } => Rejection::UnknownImage { image_id },
            ref other => {
                let mut message = heapless::String::new();
                let mut sink = Truncating(&mut message);
                // A full buffer ends the message; what fits is kept.
                let _ = write!(sink, "{other}");
                Rejection::Other { message }
            }
        }
    }
}

/// Writes what fits into a fixed string, character by character.
struct Truncating<'s>(&'s mut heapless::String<REASON_LEN>);

impl core::fmt::Write for Truncating<'_> {
    fn write_str(&mut self, s: &str) -> core::fmt::Result {
        for c in s.chars() {
            self.0.push(c).map_err(|_| core::fmt::Error)?;
        }
        Ok(())
    }
}

/// Writes keypoint pixels in the wire layout of [`LocalizeRequest::keypoints`]; `None`
/// when `out` is shorter than [`KEYPOINT_BYTES`] per keypoint.
pub fn encode_keypoints<'o>(keypoints: &[[f32; 2]], out: &'o mut [u8]) -> Option<&'o [u8]> {
    let len = keypoints.len().checked_mul(KEYPOINT_BYTES)?;
    let out = out.get_mut(..len)?;
    for (chunk, [x, y]) in out.chunks_exact_mut(KEYPOINT_BYTES).zip(keypoints) {
        let (a, b) = chunk.split_at_mut(4);
        a.copy_from_slice(&x.to_le_bytes());
        b.copy_from_slice(&y.to_le_bytes());
    }
    Some(out)
}

/// Reads keypoint pixels from the wire layout into `out`; the number read, or `None`
/// when the bytes are not whole keypoints or more than `out` holds.
pub fn decode_keypoints(bytes: &[u8], out: &mut [[f32; 2]]) -> Option<usize> {
    if !bytes.len().is_multiple_of(KEYPOINT_BYTES) || bytes.len() / KEYPOINT_BYTES > out.len() {
        return None;
    }
    let f32_at = |c: &[u8], at: usize| {
        let word: [u8; 4] = c.get(at..at + 4)?.try_into().ok()?;
        Some(f32::from_le_bytes(word))
    };
    let mut count = 0;
    for (slot, chunk) in out.iter_mut().zip(bytes.chunks_exact(KEYPOINT_BYTES)) {
        *slot = [f32_at(chunk, 0)?, f32_at(chunk, 4)?];
        count += 1;
    }
    Some(count)
}

/// A [`ResponseBody`] refusing a request for its content.
pub(super) fn rejected(rejection: Rejection) -> ResponseBody {
    ResponseBody::Error(LinkError::Rejected(rejection))
}

#[cfg(test)]
mod tests {
    use nalgebra::{Rotation3, Vector3};

    use super::*;

    #[test]
    fn keypoints_round_trip_through_the_wire_layout() {
        let keypoints = [[1.5f32, -2.25], [f32::MAX, 0.0], [3.0, 4.0]];
        let mut bytes = [0u8; 24];
        let wire = encode_keypoints(&keypoints, &mut bytes).expect("fits");
        let mut back = [[0.0f32; 2]; 4];
        assert_eq!(decode_keypoints(wire, &mut back), Some(3));
        assert_eq!(&back[..3], &keypoints);
        assert_eq!(decode_keypoints(&bytes[..23], &mut back), None);
        assert_eq!(decode_keypoints(&bytes, &mut back[..2]), None);
        assert_eq!(encode_keypoints(&keypoints, &mut [0u8; 23]), None);
    }

    #[test]
    fn poses_cross_the_wire_bit_for_bit() {
        let p = Pose::new(
            Rotation3::from_euler_angles(0.3, -1.1, 2.9),
            Vector3::new(1.0 / 3.0, -7.25, 1e-9),
        );
        assert_eq!(WirePose::from(&p).to_pose(), Ok(p));
        let mut bad = WirePose::from(&p);
        bad.translation[2] = f64::INFINITY;
        assert_eq!(
            bad.to_pose(),
            Err(Error::NonFinite {
                input: Input::Pose,
                index: 11
            })
        );
    }

    /// The device answers info and localization requests exactly as a direct call, and
    /// turns bad frames and bad requests into error replies without stopping.
    #[test]
    fn other_errors_carry_the_core_message_truncated() {
        let error = Error::InvalidConfig {
            parameter: "min_inliers",
        };
        let Rejection::Other { message } = Rejection::from(&error) else {
            panic!("not Other");
        };
        assert_eq!(message.as_str(), "invalid configuration value: min_inliers");
        let long = Error::BlobChecksum {
            blob: crate::error::BlobKind::Model,
            stored: 0,
            computed: 0,
        };
        let Rejection::Other { message } = Rejection::from(&long) else {
            panic!("not Other");
        };
        assert!(message.len() <= REASON_LEN && message.starts_with("model blob"));
    }
}
