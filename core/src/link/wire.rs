//! The wire format's version and sizes, and the saturating narrowing of its count fields.

/// Version of the link's messages; a host compares it with
/// [`DeviceInfo::protocol_version`](super::DeviceInfo::protocol_version).
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
/// Most bytes of the message of [`Rejection::Other`](super::Rejection::Other).
pub const REASON_LEN: usize = 96;

/// Longest request message for `capacity` keypoints, before COBS.
pub const fn max_request_len(capacity: usize) -> usize {
    REQUEST_OVERHEAD + KEYPOINT_BYTES * capacity
}

/// A count or size as a `u32` message field, saturated at `u32::MAX`.
pub(super) fn narrow(v: usize) -> u32 {
    u32::try_from(v).unwrap_or(u32::MAX)
}
