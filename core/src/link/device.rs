//! The device loop: reads frames from a byte stream, answers each through a [`Service`].

use embedded_hal::digital::OutputPin;
use embedded_io::{Read, Write};

use super::framing::{decode_frame, encode_frame, rx_frame_len, TX_FRAME_LEN};
use super::messages::{LinkError, Request, RequestBody, Response, ResponseBody};
use super::service::{Served, Service};
use super::wire::narrow;
use crate::sinkhorn::PlanScalar;

/// Bytes read from the stream at once.
const READ_CHUNK: usize = 64;

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
            match self.next_frame() {
                Some(Ok(len)) => return self.answer(io, service, len),
                Some(Err(error)) => return self.refuse(io, error),
                None => {}
            }
            if !self.refill(io)? {
                (self.rx_len, self.overflowed) = (0, false);
                return Ok(Served::Closed);
            }
        }
    }

    /// Moves buffered bytes into `rx` up to the end of a non-empty frame: its length, or
    /// [`LinkError::Oversized`] when it outgrew `rx`; `None` when the buffered bytes ran out
    /// first.
    fn next_frame(&mut self) -> Option<Result<usize, LinkError>> {
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
                return Some(Err(LinkError::Oversized { limit: narrow(RX) }));
            }
            if len > 0 {
                return Some(Ok(len));
            }
        }
        None
    }

    /// Reads the next bytes of the stream into the chunk buffer; `false` when it ended.
    fn refill<IO: Read>(&mut self, io: &mut IO) -> Result<bool, LinkIoError<IO::Error>> {
        let read = io.read(&mut self.chunk).map_err(LinkIoError::Io)?;
        (self.chunk_start, self.chunk_end) = (0, read.min(READ_CHUNK));
        Ok(read > 0)
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

    use std::vec::Vec;

    use proptest::prelude::*;

    use crate::link::messages::rejected;
    use crate::link::tests_support::*;
    use crate::link::*;
    use crate::localizer::{Localizer, LocalizerConfig, Query, ViewSelection};
    use crate::map::Map;
    use crate::weights::tests_support::TINY;
    use crate::weights::Model;

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
