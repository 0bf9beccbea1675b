//! The device link's reply to the last localization, for a C firmware that serves a
//! gomatch host (`gomatch-sim`'s `HostLink`) over a UART, and for comparing builds.

use gomatch::link::{
    encode_frame, LinkError, LocalizeReply, Response, ResponseBody, MAX_RESPONSE_LEN, TX_FRAME_LEN,
};

use crate::error::checked;
use crate::error::gomatch_error::{self, *};
use crate::localizer::{gomatch_localizer, last_outcome, Last};

/// Bytes of the longest reply `gomatch_link_reply` writes (a frame with its delimiter).
pub const GOMATCH_LINK_REPLY_BYTES: usize = 407;

const _: () = assert!(GOMATCH_LINK_REPLY_BYTES == TX_FRAME_LEN && MAX_RESPONSE_LEN < TX_FRAME_LEN);

/// What `gomatch_link_reply` writes.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum gomatch_reply_form {
    /// The frame a device sends on its byte stream: the postcard message and its CRC-32,
    /// COBS-encoded, then the zero delimiter (docs/formats.md, "Device link").
    GOMATCH_REPLY_FRAME = 0,
    /// The postcard message alone: the bytes `firmware/cross_isa.sh` compares between
    /// builds (no clock, so no stage timings).
    GOMATCH_REPLY_MESSAGE = 1,
}

/// Writes the device link's reply to request `request_id` for the workspace's last
/// localization (its pose or failure, counts and confidence; or the refusal of its
/// query's content) to `out`, `capacity` bytes (`GOMATCH_LINK_REPLY_BYTES` always
/// suffice), and its length to `*len`. When it does not fit:
/// `GOMATCH_ERROR_BUFFER_TOO_SMALL`, nothing written to `out`, `*len` still set.
///
/// # Safety
/// `localizer` must be NULL or a workspace not written during the call; `out` NULL or
/// writable for `capacity` bytes; `len` NULL or writable.
#[no_mangle]
pub unsafe extern "C" fn gomatch_link_reply(
    localizer: *const gomatch_localizer,
    request_id: u32,
    form: u32,
    out: *mut u8,
    capacity: usize,
    len: *mut usize,
) -> gomatch_error {
    let len = match checked(len) {
        Ok(len) => len.as_ptr(),
        Err(e) => return e,
    };
    // SAFETY: the caller's promise on `localizer`.
    let body = match unsafe { last_outcome(localizer) } {
        Ok(Last::Localized(localization)) => {
            ResponseBody::Localized(LocalizeReply::from(&localization))
        }
        Ok(Last::Refused(rejection)) => ResponseBody::Error(LinkError::Rejected(rejection)),
        Ok(Last::Nothing) => return GOMATCH_ERROR_NO_RESULT,
        Err(e) => return e,
    };
    let response = Response {
        id: Some(request_id),
        body,
    };
    let mut buffer = [0u8; TX_FRAME_LEN];
    const FRAME: u32 = gomatch_reply_form::GOMATCH_REPLY_FRAME as u32;
    const MESSAGE: u32 = gomatch_reply_form::GOMATCH_REPLY_MESSAGE as u32;
    let encoded = match form {
        FRAME => encode_frame(&response, &mut buffer).map(|b| b.len()),
        MESSAGE => postcard::to_slice(&response, &mut buffer)
            .ok()
            .map(|b| b.len()),
        _ => return GOMATCH_ERROR_INVALID_ARGUMENT,
    };
    // Every response fits (the link's tests serialise the worst case).
    let Some(n) = encoded else {
        return gomatch_error::GOMATCH_ERROR_INTERNAL;
    };
    // SAFETY: checked.
    unsafe { len.write(n) };
    if n > capacity {
        return GOMATCH_ERROR_BUFFER_TOO_SMALL;
    }
    let out = match checked(out) {
        Ok(out) => out.as_ptr(),
        Err(e) => return e,
    };
    // SAFETY: `out` is writable for `capacity >= n` bytes and is not the local buffer.
    unsafe { core::ptr::copy_nonoverlapping(buffer.as_ptr(), out, n) };
    GOMATCH_OK
}
