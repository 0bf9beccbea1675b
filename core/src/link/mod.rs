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

mod device;
mod framing;
mod messages;
mod service;
#[cfg(test)]
mod tests_support;
mod wire;

pub use device::{Device, LinkIoError};
pub use framing::{decode_frame, encode_frame, rx_frame_len, TX_FRAME_LEN};
pub use messages::{
    decode_keypoints, encode_keypoints, DeviceInfo, LinkError, LocalizeReply, LocalizeRequest,
    MapInfo, ModelInfo, Rejection, Request, RequestBody, Response, ResponseBody, Views, WirePose,
};
pub use service::{NoPin, Served, Service};
pub use wire::{
    max_request_len, CHECKSUM_BYTES, KEYPOINT_BYTES, MAX_RESPONSE_LEN, PROTOCOL_VERSION,
    REASON_LEN, REQUEST_OVERHEAD,
};
