//! The device link: a request/response protocol between a host (phone, SoC) and the
//! localizer device over any byte stream ([`embedded_io::Read`] + [`embedded_io::Write`]:
//! a UART, a USB CDC endpoint, SPI behind a driver, a pipe in a simulation).
//!
//! ```text
//! host                                          device (no_std, no allocation)
//!  [0] cobs(postcard(Request) crc32) [0]   -->  receive buffer (static) -> decode in place
//!                                               -> Localizer::localize (busy pin high)
//!      cobs(postcard(Response) crc32) [0]  <--  reply buffer (static)
//! ```
//!
//! Messages are [postcard](https://docs.rs/postcard) encodings of [`Request`] and
//! [`Response`], each followed by the CRC-32 (IEEE) of its bytes, little-endian, and
//! framed with COBS (consistent overhead byte stuffing): a frame holds no zero byte and
//! ends with one, so a receiver that lost track finds the next frame at the next zero.
//! The device ignores empty frames; a host sends a zero before each request to close
//! whatever a broken earlier frame left behind.
//!
//! Every request carries an `id` that the reply echoes. A frame that is not valid COBS,
//! fails its checksum, whose message does not decode, ends early, carries trailing bytes
//! or exceeds the receive buffer gets a [`Response`] with `id: None` and a [`LinkError`],
//! and the device goes on with the next frame. Both sides check the checksum, so a
//! dropped, flipped, duplicated or truncated byte is detected (CRC-32 catches every burst
//! of up to 32 bits and all but 2^-32 of other corruptions); a host matches replies to
//! requests by id and retries on a timeout (`gomatch-sim`'s `device::HostLink`).
//!
//! The largest request is a localization with `N` keypoints (8 bytes each, `f32` pixel
//! coordinates) plus at most [`REQUEST_OVERHEAD`] bytes; [`rx_frame_len`] gives the
//! receive buffer a [`Device`] needs, a function of the capacity only.

use core::convert::Infallible;
use core::fmt::Write as _;

use embedded_hal::digital::{ErrorType, OutputPin};
use embedded_io::{Read, Write};
use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::error::{Error, Input};
use crate::localizer::{
    Clock, Failure, Localization, Localizer, LocalizerConfig, MatchCounts, Query, StageTimings,
    ViewSelection, MAX_VIEWS,
};
use crate::map::{Map, MAP_VERSION};
use crate::pose::Pose;
use crate::sinkhorn::PlanScalar;
use crate::weights::{Model, ModelConfig, Precision, MODEL_VERSION};

/// Version of the messages below; a host compares it with [`DeviceInfo::protocol_version`].
pub const PROTOCOL_VERSION: u16 = 2;
/// Bytes of one keypoint on the wire: `x` then `y`, `f32` little-endian pixels.
pub const KEYPOINT_BYTES: usize = 8;
/// Upper bound of a request's encoding besides its keypoint bytes: the id, the message
/// tags, the camera, the keypoint count, and the view selection at its largest (checked
/// by a test against the worst case).
pub const REQUEST_OVERHEAD: usize = 256;
/// Upper bound of a response's encoding (checked by a test against the worst case).
pub const MAX_RESPONSE_LEN: usize = 400;
/// Bytes of the CRC-32 after each message.
pub const CHECKSUM_BYTES: usize = 4;
/// Bytes of the longest reply frame, delimiter included.
pub const TX_FRAME_LEN: usize = cobs_len(MAX_RESPONSE_LEN + CHECKSUM_BYTES) + 1;
/// Most bytes of the message of [`Rejection::Other`].
pub const REASON_LEN: usize = 96;
/// Bytes read from the stream at once.
const READ_CHUNK: usize = 64;

/// Longest request message for `capacity` keypoints, before COBS.
pub const fn max_request_len(capacity: usize) -> usize {
    REQUEST_OVERHEAD + KEYPOINT_BYTES * capacity
}

/// Receive buffer of a device with `capacity` keypoints: the longest request frame
/// (message and checksum COBS-encoded, delimiter not stored). For capacity 1024: 8,486
/// bytes.
pub const fn rx_frame_len(capacity: usize) -> usize {
    cobs_len(max_request_len(capacity) + CHECKSUM_BYTES)
}

/// Longest COBS encoding of `len` bytes: one code byte per run of at most 254 bytes.
const fn cobs_len(len: usize) -> usize {
    len + len / 254 + 1
}

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

/// The view selection on the wire ([`ViewSelection`]).
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
        let narrow = |v: usize| u32::try_from(v).unwrap_or(u32::MAX);
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
    /// [`PROTOCOL_VERSION`] of the device.
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
        let narrow = |v: usize| u32::try_from(v).unwrap_or(u32::MAX);
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
    if bytes.len() % KEYPOINT_BYTES != 0 || bytes.len() / KEYPOINT_BYTES > out.len() {
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

/// Encodes a message and its CRC-32 as one COBS frame ending with its zero delimiter;
/// `None` when `out` is too small.
pub fn encode_frame<'o, T: Serialize>(message: &T, out: &'o mut [u8]) -> Option<&'o [u8]> {
    let cobs = postcard::ser_flavors::Cobs::try_new(postcard::ser_flavors::Slice::new(out)).ok()?;
    let flavor = Checksummed {
        inner: cobs,
        crc: crc32fast::Hasher::new(),
    };
    postcard::serialize_with_flavor(message, flavor)
        .ok()
        .map(|f: &mut [u8]| &*f)
}

/// A postcard flavor that appends the CRC-32 of the serialised bytes before `inner`
/// finishes the frame.
struct Checksummed<B> {
    inner: B,
    crc: crc32fast::Hasher,
}

impl<B: postcard::ser_flavors::Flavor> postcard::ser_flavors::Flavor for Checksummed<B> {
    type Output = B::Output;

    fn try_push(&mut self, data: u8) -> postcard::Result<()> {
        self.crc.update(&[data]);
        self.inner.try_push(data)
    }

    fn try_extend(&mut self, data: &[u8]) -> postcard::Result<()> {
        self.crc.update(data);
        self.inner.try_extend(data)
    }

    fn finalize(mut self) -> postcard::Result<B::Output> {
        self.inner.try_extend(&self.crc.finalize().to_le_bytes())?;
        self.inner.finalize()
    }
}

/// Decodes one COBS frame, in place, into a message: the bytes up to the frame's zero
/// delimiter (or all of them when it has none) must be exactly one message followed by
/// its CRC-32. The errors are those the device replies with.
pub fn decode_frame<'f, T: Deserialize<'f>>(frame: &'f mut [u8]) -> Result<T, LinkError> {
    let end = frame.iter().position(|&b| b == 0).unwrap_or(frame.len());
    let frame = frame.get_mut(..end).unwrap_or(&mut []);
    let len = cobs::decode_in_place(frame).map_err(|_| LinkError::Truncated)?;
    let body_len = len
        .checked_sub(CHECKSUM_BYTES)
        .ok_or(LinkError::Truncated)?;
    let (bytes, checksum) = frame.get(..len).unwrap_or(&[]).split_at(body_len);
    let stored = checksum
        .try_into()
        .map(u32::from_le_bytes)
        .map_err(|_| LinkError::Truncated)?;
    if crc32fast::hash(bytes) != stored {
        return Err(LinkError::Checksum);
    }
    match postcard::take_from_bytes::<T>(bytes) {
        Ok((message, [])) => Ok(message),
        Ok(_) => Err(LinkError::Malformed),
        Err(postcard::Error::DeserializeUnexpectedEnd) => Err(LinkError::Truncated),
        Err(_) => Err(LinkError::Malformed),
    }
}

/// A busy pin for devices without one.
#[derive(Debug, Clone, Copy, Default)]
pub struct NoPin;

impl ErrorType for NoPin {
    type Error = Infallible;
}

impl OutputPin for NoPin {
    fn set_low(&mut self) -> Result<(), Infallible> {
        Ok(())
    }

    fn set_high(&mut self) -> Result<(), Infallible> {
        Ok(())
    }
}

/// What the device serves: the localizer workspace, the model and map read in place, the
/// settings, a busy pin (high while a localization runs) and an optional clock.
pub struct Service<'a, const N: usize, S: PlanScalar, P: OutputPin> {
    localizer: &'a mut Localizer<N, S>,
    model: Model<'a>,
    map: Map<'a>,
    model_bytes: usize,
    map_bytes: usize,
    /// Settings of every localization.
    pub config: LocalizerConfig,
    busy: P,
    clock: Option<&'a dyn Clock>,
}

impl<'a, const N: usize, S: PlanScalar, P: OutputPin> Service<'a, N, S, P> {
    /// Validates the model and map blobs once ([`Model::from_bytes`],
    /// [`Map::from_bytes`]) and sets the busy pin low.
    pub fn new(
        localizer: &'a mut Localizer<N, S>,
        model_blob: &'a [u8],
        map_blob: &'a [u8],
        mut busy: P,
    ) -> crate::error::Result<Self> {
        let model = Model::from_bytes(model_blob)?;
        let map = Map::from_bytes(map_blob)?;
        // A pin that cannot be driven is no reason not to serve.
        let _ = busy.set_low();
        Ok(Service {
            localizer,
            model,
            map,
            model_bytes: model_blob.len(),
            map_bytes: map_blob.len(),
            config: LocalizerConfig::new(),
            busy,
            clock: None,
        })
    }

    /// Stage timings from this clock go into every [`LocalizeReply`].
    pub fn with_clock(mut self, clock: &'a dyn Clock) -> Self {
        self.clock = Some(clock);
        self
    }

    /// The answer to [`RequestBody::Info`] for a receive buffer of `rx_frame_bytes`.
    pub fn info(&self, rx_frame_bytes: usize) -> DeviceInfo {
        let narrow = |v: usize| u32::try_from(v).unwrap_or(u32::MAX);
        DeviceInfo {
            protocol_version: PROTOCOL_VERSION,
            capacity: narrow(N),
            max_views: MAX_VIEWS as u8,
            sinkhorn_bytes: core::mem::size_of::<S>() as u8,
            workspace_bytes: narrow(Localizer::<N, S>::BYTES),
            rx_frame_bytes: narrow(rx_frame_bytes),
            model: ModelInfo {
                format_version: MODEL_VERSION,
                precision: self.model.precision(),
                config: *self.model.config(),
                bytes: narrow(self.model_bytes),
            },
            map: MapInfo {
                format_version: MAP_VERSION,
                points: narrow(self.map.point_count()),
                views: narrow(self.map.view_count()),
                cameras: narrow(self.map.camera_count()),
                observations: narrow(self.map.observation_count()),
                bytes: narrow(self.map_bytes),
            },
        }
    }

    /// Runs one localization request with its keypoints decoded into `keypoints`.
    pub fn localize(
        &mut self,
        request: &LocalizeRequest<'_>,
        keypoints: &mut [[f32; 2]; N],
    ) -> ResponseBody {
        let narrow = |v: usize| u32::try_from(v).unwrap_or(u32::MAX);
        let count = request.keypoints.len() / KEYPOINT_BYTES;
        if request.keypoints.len() % KEYPOINT_BYTES != 0 {
            return ResponseBody::Error(LinkError::KeypointBytes {
                len: narrow(request.keypoints.len()),
            });
        }
        let Some(n) = decode_keypoints(request.keypoints, keypoints) else {
            return rejected(Rejection::TooManyKeypoints {
                capacity: narrow(N),
                requested: narrow(count),
            });
        };
        let views = match &request.views {
            Views::ImageIds(ids) => ViewSelection::ImageIds(ids.as_slice()),
            Views::NearPrior {
                prior,
                k,
                max_angle_deg,
            } => {
                if usize::from(*k) > MAX_VIEWS {
                    return rejected(Rejection::TooManyViews {
                        capacity: MAX_VIEWS as u32,
                        requested: u32::from(*k),
                    });
                }
                match prior.to_pose() {
                    Ok(prior) => ViewSelection::NearPrior {
                        prior,
                        k: usize::from(*k),
                        max_angle_deg: *max_angle_deg,
                    },
                    Err(e) => return rejected(Rejection::from(&e)),
                }
            }
        };
        let query = Query {
            keypoints: keypoints.get(..n).unwrap_or(&[]),
            camera: request.camera,
        };
        let _ = self.busy.set_high();
        let result = self.localizer.localize(
            &self.model,
            &self.map,
            &query,
            views,
            &self.config,
            self.clock,
        );
        let _ = self.busy.set_low();
        match result {
            Ok(localization) => ResponseBody::Localized(LocalizeReply::from(&localization)),
            Err(e) => rejected(Rejection::from(&e)),
        }
    }
}

fn rejected(rejection: Rejection) -> ResponseBody {
    ResponseBody::Error(LinkError::Rejected(rejection))
}

/// What one [`Device::serve`] call did.
#[derive(Debug, Clone, PartialEq)]
pub enum Served {
    /// A request with this id was answered.
    Answered {
        /// The request's id.
        id: u32,
    },
    /// A frame was refused with this error (and the error was sent).
    Refused(LinkError),
    /// The stream ended (a partial frame is dropped).
    Closed,
}

/// An error of the stream under the link.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkIoError<E> {
    /// Reading or writing the stream failed.
    Io(E),
    /// A reply did not fit [`TX_FRAME_LEN`] (a bug: the bound is tested).
    ReplyTooLong,
}

/// The device end of the link: receive buffer, keypoint buffer and reply buffer, for up
/// to `N` keypoints; `RX` is the receive buffer, at least [`rx_frame_len`]`(N)`. Built by
/// a `const fn`, all zero, so a `static` lands in `.bss`; [`Device::BYTES`] is its size.
pub struct Device<const N: usize, const RX: usize> {
    rx: [u8; RX],
    rx_len: usize,
    /// The current frame outgrew `rx`; its bytes are skipped up to the delimiter.
    overflowed: bool,
    chunk: [u8; READ_CHUNK],
    chunk_start: usize,
    chunk_end: usize,
    keypoints: [[f32; 2]; N],
    tx: [u8; TX_FRAME_LEN],
}

impl<const N: usize, const RX: usize> Default for Device<N, RX> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize, const RX: usize> Device<N, RX> {
    /// Size of the device's buffers in bytes.
    pub const BYTES: usize = core::mem::size_of::<Self>();

    /// An idle device with empty buffers.
    pub const fn new() -> Self {
        const { assert!(RX >= rx_frame_len(N), "RX must hold rx_frame_len(N) bytes") };
        Device {
            rx: [0; RX],
            rx_len: 0,
            overflowed: false,
            chunk: [0; READ_CHUNK],
            chunk_start: 0,
            chunk_end: 0,
            keypoints: [[0.0; 2]; N],
            tx: [0; TX_FRAME_LEN],
        }
    }

    /// Reads from `io` until one frame is complete, answers it and returns; empty frames
    /// are skipped. Bytes after the frame stay buffered for the next call.
    pub fn serve<IO, S, P>(
        &mut self,
        io: &mut IO,
        service: &mut Service<'_, N, S, P>,
    ) -> Result<Served, LinkIoError<IO::Error>>
    where
        IO: Read + Write,
        S: PlanScalar,
        P: OutputPin,
    {
        loop {
            while self.chunk_start < self.chunk_end {
                let byte = self.chunk.get(self.chunk_start).copied().unwrap_or(0);
                self.chunk_start += 1;
                if byte != 0 {
                    self.push(byte);
                    continue;
                }
                let (len, overflowed) = (self.rx_len, self.overflowed);
                (self.rx_len, self.overflowed) = (0, false);
                if overflowed {
                    let error = LinkError::Oversized {
                        limit: u32::try_from(RX).unwrap_or(u32::MAX),
                    };
                    return self.refuse(io, error);
                }
                if len == 0 {
                    continue;
                }
                return self.answer(io, service, len);
            }
            let read = io.read(&mut self.chunk).map_err(LinkIoError::Io)?;
            if read == 0 {
                (self.rx_len, self.overflowed) = (0, false);
                return Ok(Served::Closed);
            }
            (self.chunk_start, self.chunk_end) = (0, read.min(READ_CHUNK));
        }
    }

    /// Serves frames until the stream ends.
    pub fn serve_until_closed<IO, S, P>(
        &mut self,
        io: &mut IO,
        service: &mut Service<'_, N, S, P>,
    ) -> Result<(), LinkIoError<IO::Error>>
    where
        IO: Read + Write,
        S: PlanScalar,
        P: OutputPin,
    {
        while self.serve(io, service)? != Served::Closed {}
        Ok(())
    }

    /// Appends a byte of the current frame, or marks the frame oversized.
    fn push(&mut self, byte: u8) {
        match self.rx.get_mut(self.rx_len) {
            Some(slot) if !self.overflowed => {
                *slot = byte;
                self.rx_len += 1;
            }
            _ => self.overflowed = true,
        }
    }

    /// Decodes the frame in `rx[..len]` and sends the answer.
    fn answer<IO, S, P>(
        &mut self,
        io: &mut IO,
        service: &mut Service<'_, N, S, P>,
        len: usize,
    ) -> Result<Served, LinkIoError<IO::Error>>
    where
        IO: Read + Write,
        S: PlanScalar,
        P: OutputPin,
    {
        let frame = self.rx.get_mut(..len).unwrap_or(&mut []);
        let request: Request<'_> = match decode_frame(frame) {
            Ok(request) => request,
            Err(error) => return self.refuse(io, error),
        };
        let body = match &request.body {
            RequestBody::Info => ResponseBody::Info(service.info(RX)),
            RequestBody::Localize(localize) => service.localize(localize, &mut self.keypoints),
        };
        let id = request.id;
        send(io, &mut self.tx, &Response { id: Some(id), body })?;
        Ok(Served::Answered { id })
    }

    /// Sends the error reply of a frame that did not decode.
    fn refuse<IO: Write>(
        &mut self,
        io: &mut IO,
        error: LinkError,
    ) -> Result<Served, LinkIoError<IO::Error>> {
        let response = Response {
            id: None,
            body: ResponseBody::Error(error.clone()),
        };
        send(io, &mut self.tx, &response)?;
        Ok(Served::Refused(error))
    }
}

/// Encodes `response` into `tx` and writes the frame.
fn send<IO: Write>(
    io: &mut IO,
    tx: &mut [u8],
    response: &Response,
) -> Result<(), LinkIoError<IO::Error>> {
    let frame = encode_frame(response, tx).ok_or(LinkIoError::ReplyTooLong)?;
    io.write_all(frame).map_err(LinkIoError::Io)?;
    io.flush().map_err(LinkIoError::Io)
}

#[cfg(test)]
mod tests {
    extern crate std;

    use std::sync::Mutex;
    use std::vec::Vec;

    use nalgebra::{Rotation3, Vector3};
    use proptest::prelude::*;

    use super::*;
    use crate::camera::CameraModel;
    use crate::map::{encode, encoded_len, MapViewEntry};
    use crate::weights::tests_support::{blob, TINY};

    const CAP: usize = 64;
    const RX: usize = rx_frame_len(CAP);
    static LOCALIZER: Mutex<Localizer<CAP>> = Mutex::new(Localizer::new());
    static DEVICE: Mutex<Device<CAP, RX>> = Mutex::new(Device::new());

    /// A byte stream: reads `input`, collects what is written.
    struct Pipe {
        input: Vec<u8>,
        at: usize,
        output: Vec<u8>,
    }

    impl embedded_io::ErrorType for Pipe {
        type Error = Infallible;
    }

    impl Read for Pipe {
        fn read(&mut self, buf: &mut [u8]) -> Result<usize, Infallible> {
            // Odd read sizes exercise frames split over reads.
            let n = buf.len().min(self.input.len() - self.at).min(37);
            buf[..n].copy_from_slice(&self.input[self.at..self.at + n]);
            self.at += n;
            Ok(n)
        }
    }

    impl Write for Pipe {
        fn write(&mut self, buf: &[u8]) -> Result<usize, Infallible> {
            self.output.extend_from_slice(buf);
            Ok(buf.len())
        }

        fn flush(&mut self) -> Result<(), Infallible> {
            Ok(())
        }
    }

    fn camera() -> Camera {
        Camera::from_colmap(CameraModel::SimplePinhole, 640, 480, &[500.0, 320.0, 240.0])
            .expect("valid")
    }

    fn pose(x: f64) -> Pose {
        Pose::new(
            Rotation3::from_euler_angles(0.0, 0.05 * x, 0.0),
            Vector3::new(x, 0.0, 0.0),
        )
    }

    /// Model blob, map blob (80 points seen by views 10 and 20) and the query pixels of
    /// those points from `pose(0.1)`.
    fn fixture() -> (Vec<u8>, Vec<u8>, Vec<[f32; 2]>) {
        let mut model = std::vec![0u8; 64 * 1024];
        let len = blob(&TINY, 5, &mut model);
        model.truncate(len);
        let points: Vec<[f32; 3]> = (0..80)
            .map(|i| {
                let (u, v) = ((i % 10) as f32 * 0.3 - 1.35, (i / 10) as f32 * 0.3 - 1.05);
                [u, v, 5.0 + 0.3 * libm::sinf(3.0 * u + 2.0 * v)]
            })
            .collect();
        let all: Vec<u32> = (0..80).collect();
        let views = [(10, -0.3), (20, 0.3)].map(|(image_id, x)| MapViewEntry {
            image_id,
            name: "",
            camera_index: 0,
            pose: pose(x),
            points: &all,
        });
        let mut map = std::vec![0u8; encoded_len(points.len(), 1, &views)];
        let len = encode(&points, &[camera()], &views, &mut map).expect("encodes");
        map.truncate(len);
        let truth = pose(0.1);
        let pixels = points
            .iter()
            .take(CAP)
            .map(|p| {
                let x = Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
                let b = truth.bearing(&x, 0).expect("in front");
                let px = camera().bearing_to_pixel(b).expect("projects");
                [px[0] as f32, px[1] as f32]
            })
            .collect();
        (model, map, pixels)
    }

    fn localize_request(id: u32, keypoints: &[u8], ids: &[u32]) -> Request<'static> {
        let keypoints: &'static [u8] = std::vec::Vec::leak(keypoints.to_vec());
        Request {
            id,
            body: RequestBody::Localize(LocalizeRequest {
                camera: camera(),
                keypoints,
                views: Views::ImageIds(heapless::Vec::from_slice(ids).expect("<= 10")),
            }),
        }
    }

    /// `[0]` then the request's frame, as a host sends it.
    fn frame(request: &Request<'_>) -> Vec<u8> {
        let mut out = std::vec![0u8; rx_frame_len(CAP) + 2];
        let len = encode_frame(request, &mut out[1..]).expect("fits").len();
        out.truncate(len + 1);
        out
    }

    /// The frame of raw message bytes: COBS of the bytes and their CRC-32, then `[0]`.
    fn checked(message: &[u8]) -> Vec<u8> {
        let mut body = message.to_vec();
        body.extend(crc32fast::hash(message).to_le_bytes());
        cobs_frame(&body)
    }

    /// COBS of `body`, then `[0]`.
    fn cobs_frame(body: &[u8]) -> Vec<u8> {
        let mut out = std::vec![0u8; cobs_len(body.len()) + 1];
        let len = cobs::encode(body, &mut out);
        out.truncate(len + 1);
        out
    }

    /// Runs the device until the input ends; returns the decoded replies.
    fn serve(input: Vec<u8>, model: &[u8], map: &[u8]) -> (Vec<Served>, Vec<Response>) {
        let mut localizer = LOCALIZER.lock().expect("lock");
        let mut device = DEVICE.lock().expect("lock");
        let mut service = Service::new(&mut localizer, model, map, NoPin).expect("valid blobs");
        let mut pipe = Pipe {
            input,
            at: 0,
            output: Vec::new(),
        };
        let mut served = Vec::new();
        loop {
            let s = device.serve(&mut pipe, &mut service).expect("infallible");
            if s == Served::Closed {
                break;
            }
            served.push(s);
        }
        let replies = pipe
            .output
            .split_mut(|&b| b == 0)
            .filter(|f| !f.is_empty())
            .map(|f| decode_frame::<Response>(f).expect("device replies decode"))
            .collect();
        (served, replies)
    }

    #[test]
    fn frame_sizes_are_derived_from_the_capacity() {
        assert_eq!(max_request_len(1024), 256 + 8 * 1024);
        assert_eq!(rx_frame_len(1024), 8448 + 4 + 33 + 1);
        assert!(
            Device::<1024, { rx_frame_len(1024) }>::BYTES
                < rx_frame_len(1024) + 8 * 1024 + TX_FRAME_LEN + 128
        );
    }

    /// The largest request of each kind fits [`max_request_len`], its frame
    /// [`rx_frame_len`].
    #[test]
    fn largest_requests_fit_the_receive_buffer() {
        let params = [1e300; 8];
        let camera = Camera {
            width: u32::MAX,
            height: u32::MAX,
            ..Camera::from_colmap(CameraModel::OpenCv, 1, 1, &params).expect("valid")
        };
        // No zero byte anywhere: the longest COBS encoding.
        let keypoints = std::vec![0xA5u8; KEYPOINT_BYTES * CAP];
        let prior = WirePose {
            rotation: [[1e300; 3]; 3],
            translation: [1e300; 3],
        };
        let selections = [
            Views::ImageIds(heapless::Vec::from_slice(&[u32::MAX; MAX_VIEWS]).expect("10")),
            Views::NearPrior {
                prior,
                k: u8::MAX,
                max_angle_deg: 1e300,
            },
        ];
        for views in selections {
            let request = Request {
                id: u32::MAX,
                body: RequestBody::Localize(LocalizeRequest {
                    camera,
                    keypoints: &keypoints,
                    views,
                }),
            };
            let mut buf = std::vec![0u8; 2 * max_request_len(CAP)];
            let len = postcard::to_slice(&request, &mut buf)
                .expect("encodes")
                .len();
            assert!(len <= max_request_len(CAP), "{len}");
            let mut out = std::vec![0u8; 2 * rx_frame_len(CAP)];
            let frame = encode_frame(&request, &mut out).expect("encodes");
            assert!(frame.len() - 1 <= rx_frame_len(CAP), "{}", frame.len());
        }
    }

    /// The largest response of each kind fits [`MAX_RESPONSE_LEN`] and [`TX_FRAME_LEN`].
    #[test]
    fn largest_responses_fit_the_reply_buffer() {
        let config = ModelConfig {
            feature_dim: u16::MAX,
            classifier_dim: u16::MAX,
            ..ModelConfig::REFERENCE
        };
        let info = DeviceInfo {
            protocol_version: u16::MAX,
            capacity: u32::MAX,
            max_views: u8::MAX,
            sinkhorn_bytes: u8::MAX,
            workspace_bytes: u32::MAX,
            rx_frame_bytes: u32::MAX,
            model: ModelInfo {
                format_version: u16::MAX,
                precision: Precision::Int8,
                config,
                bytes: u32::MAX,
            },
            map: MapInfo {
                format_version: u16::MAX,
                points: u32::MAX,
                views: u32::MAX,
                cameras: u32::MAX,
                observations: u32::MAX,
                bytes: u32::MAX,
            },
        };
        let counts = MatchCounts {
            mutual: usize::MAX,
            classified: usize::MAX,
            merged: usize::MAX,
            inliers: usize::MAX,
        };
        let timings = StageTimings {
            prepare_us: u64::MAX,
            encode_us: u64::MAX,
            match_us: u64::MAX,
            merge_us: u64::MAX,
            pose_us: u64::MAX,
            total_us: u64::MAX,
        };
        let reply = |outcome| LocalizeReply {
            outcome,
            counts,
            views_used: u32::MAX,
            views_skipped: u32::MAX,
            ransac_iterations: u32::MAX,
            timings: Some(timings),
            confidence: Some(f32::MAX),
        };
        let failure = Failure::TooFewInliers {
            needed: usize::MAX,
            found: usize::MAX,
        };
        let mut message = heapless::String::new();
        while message.push('\u{10FFFF}').is_ok() {}
        let bodies = [
            ResponseBody::Info(info),
            ResponseBody::Localized(reply(Ok(WirePose {
                rotation: [[f64::MAX; 3]; 3],
                translation: [f64::MAX; 3],
            }))),
            ResponseBody::Localized(reply(Err(failure))),
            ResponseBody::Error(LinkError::Rejected(Rejection::Other { message })),
            ResponseBody::Error(LinkError::Rejected(Rejection::TooManyKeypoints {
                capacity: u32::MAX,
                requested: u32::MAX,
            })),
        ];
        for body in bodies {
            let response = Response {
                id: Some(u32::MAX),
                body,
            };
            let mut buf = [0u8; 2 * MAX_RESPONSE_LEN];
            let len = postcard::to_slice(&response, &mut buf)
                .expect("encodes")
                .len();
            assert!(len <= MAX_RESPONSE_LEN, "{len}");
            let mut tx = [0u8; TX_FRAME_LEN];
            assert!(encode_frame(&response, &mut tx).is_some());
        }
    }

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
    fn device_answers_requests_and_refuses_bad_frames() {
        let (model, map, pixels) = fixture();
        let mut bytes = std::vec![0u8; KEYPOINT_BYTES * pixels.len()];
        let keypoints = encode_keypoints(&pixels, &mut bytes)
            .expect("fits")
            .to_vec();
        let info = Request {
            id: 1,
            body: RequestBody::Info,
        };
        let good = localize_request(2, &keypoints, &[10, 20]);
        let unknown = localize_request(3, &keypoints, &[10, 99]);
        let ragged = localize_request(4, &keypoints[..13], &[10]);
        let mut truncated = frame(&good);
        truncated.truncate(truncated.len() - 40);
        let mut input = frame(&info);
        input.extend(&truncated);
        input.extend(frame(&good));
        input.extend(checked(&[0x01, 0x09])); // id 1, unknown message tag 9
        input.extend(std::vec![0x11; RX + 5]); // oversized
        input.extend(frame(&unknown));
        input.extend(frame(&ragged));
        input.extend(&frame(&good)[..30]); // cut off by the end of the stream
        let (served, replies) = serve(input, &model, &map);
        let ids: Vec<Option<u32>> = replies.iter().map(|r| r.id).collect();
        assert_eq!(
            ids,
            [Some(1), None, Some(2), None, None, Some(3), Some(4)],
            "{served:?}"
        );

        let ResponseBody::Info(info) = &replies[0].body else {
            panic!("{:?}", replies[0]);
        };
        assert_eq!(info.capacity as usize, CAP);
        assert_eq!(info.rx_frame_bytes as usize, RX);
        assert_eq!(info.workspace_bytes as usize, Localizer::<CAP>::BYTES);
        assert_eq!(info.model.bytes as usize, model.len());
        assert_eq!(info.model.config, TINY);
        assert_eq!(
            (info.map.points, info.map.views, info.map.cameras),
            (80, 2, 1)
        );
        assert_eq!(info.map.bytes as usize, map.len());

        assert_eq!(replies[1].body, ResponseBody::Error(LinkError::Truncated));
        let ResponseBody::Localized(reply) = &replies[2].body else {
            panic!("{:?}", replies[2]);
        };
        let direct = {
            let model = Model::from_bytes(&model).expect("valid");
            let map = Map::from_bytes(&map).expect("valid");
            let query = Query {
                keypoints: &pixels,
                camera: camera(),
            };
            let mut l = LOCALIZER.lock().expect("lock");
            l.localize(
                &model,
                &map,
                &query,
                ViewSelection::ImageIds(&[10, 20]),
                &LocalizerConfig::new(),
                None,
            )
            .expect("valid")
        };
        assert_eq!(*reply, LocalizeReply::from(&direct));
        assert_eq!(replies[3].body, ResponseBody::Error(LinkError::Malformed));
        // Info with id 1 is [0x01, 0x00]; with a byte after it, malformed.
        assert_eq!(
            decode_frame::<Request<'_>>(&mut checked(&[0x01, 0x00])),
            Ok(Request {
                id: 1,
                body: RequestBody::Info
            })
        );
        assert_eq!(
            decode_frame::<Request<'_>>(&mut checked(&[0x01, 0x00, 0x05])),
            Err(LinkError::Malformed)
        );
        assert_eq!(
            decode_frame::<Request<'_>>(&mut [0x07, 0x01, 0x02]),
            Err(LinkError::Truncated)
        );
        // Shorter than a checksum; a changed, a lost and an added byte.
        assert_eq!(
            decode_frame::<Request<'_>>(&mut [0x04, 0x01, 0x02, 0x03]),
            Err(LinkError::Truncated)
        );
        let mut info = std::vec![0x01, 0x00];
        info.extend(crc32fast::hash(&info).to_le_bytes());
        let mut flipped = info.clone();
        flipped[0] ^= 0x40;
        let mut lost = info.clone();
        lost.remove(3);
        let mut added = info.clone();
        added.insert(3, 0x77);
        for body in [flipped, lost, added] {
            assert_eq!(
                decode_frame::<Request<'_>>(&mut cobs_frame(&body)),
                Err(LinkError::Checksum)
            );
        }
        assert_eq!(
            replies[4].body,
            ResponseBody::Error(LinkError::Oversized { limit: RX as u32 })
        );
        assert_eq!(
            replies[5].body,
            rejected(Rejection::UnknownImage { image_id: 99 })
        );
        assert_eq!(
            replies[6].body,
            ResponseBody::Error(LinkError::KeypointBytes { len: 13 })
        );
        assert_eq!(served.len(), replies.len());
    }

    #[test]
    fn refused_inputs_name_the_reason() {
        let (model, map, pixels) = fixture();
        let mut too_many = pixels.clone();
        too_many.push([1.0, 1.0]);
        let mut nan = pixels.clone();
        nan[7][0] = f32::NAN;
        let wire = |p: &[[f32; 2]]| {
            let mut bytes = std::vec![0u8; KEYPOINT_BYTES * p.len()];
            encode_keypoints(p, &mut bytes).expect("fits");
            bytes
        };
        let mut near = localize_request(3, &wire(&pixels), &[]);
        if let RequestBody::Localize(r) = &mut near.body {
            r.views = Views::NearPrior {
                prior: WirePose::from(&pose(0.0)),
                k: 11,
                max_angle_deg: 30.0,
            };
        }
        let mut input = frame(&localize_request(1, &wire(&too_many), &[10]));
        input.extend(frame(&localize_request(2, &wire(&nan), &[10])));
        input.extend(frame(&near));
        let (_, replies) = serve(input, &model, &map);
        let bodies: Vec<ResponseBody> = replies.into_iter().map(|r| r.body).collect();
        assert_eq!(
            bodies,
            [
                rejected(Rejection::TooManyKeypoints {
                    capacity: CAP as u32,
                    requested: CAP as u32 + 1
                }),
                rejected(Rejection::NonFiniteKeypoint { index: 7 }),
                rejected(Rejection::TooManyViews {
                    capacity: 10,
                    requested: 11
                }),
            ]
        );
    }

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

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(512))]

        /// Arbitrary frames never panic the decoder.
        #[test]
        fn arbitrary_frames_decode_or_fail_cleanly(mut bytes in proptest::collection::vec(any::<u8>(), 0..600)) {
            let _ = decode_frame::<Request<'_>>(&mut bytes.clone());
            let _ = decode_frame::<Response>(&mut bytes);
        }

        /// A valid request with one byte changed is refused: the checksum (or the COBS
        /// framing) detects the change, so it never decodes to another request.
        #[test]
        fn mutated_requests_are_refused(at in 0usize..400, value in any::<u8>()) {
            let keypoints = std::vec![0x3Fu8; 8 * 40];
            let mut bytes = frame(&localize_request(7, &keypoints, &[1, 2, 3]))[1..].to_vec();
            let i = at % (bytes.len() - 1);
            let unchanged = bytes[i] == value;
            bytes[i] = value;
            let decoded = decode_frame::<Request<'_>>(&mut bytes);
            prop_assert!(unchanged || decoded.is_err(), "{:?}", decoded);
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]

        /// Random bytes, then a valid request: the device answers the request as if the
        /// noise had not been there.
        #[test]
        fn device_recovers_from_noise(noise in proptest::collection::vec(any::<u8>(), 0..3 * RX)) {
            let (model, map, pixels) = fixture();
            let mut bytes = std::vec![0u8; KEYPOINT_BYTES * pixels.len()];
            let keypoints = encode_keypoints(&pixels, &mut bytes).expect("fits").to_vec();
            let request = localize_request(0xC0FFEE, &keypoints, &[20, 10]);
            let mut input = noise;
            input.extend(frame(&request));
            let (_, replies) = serve(input.clone(), &model, &map);
            let clean = serve(frame(&request), &model, &map).1;
            let answer = replies.iter().rev().find(|r| r.id == Some(0xC0FFEE));
            prop_assert_eq!(answer, clean.first());
            prop_assert!(matches!(clean[0].body, ResponseBody::Localized(_)));
        }
    }
}
