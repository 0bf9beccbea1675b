//! Frames: a postcard message and its CRC-32, COBS-encoded, ended by a zero byte.

use serde::{Deserialize, Serialize};

use super::messages::LinkError;
use super::wire::{max_request_len, CHECKSUM_BYTES, MAX_RESPONSE_LEN};

/// Bytes of the longest reply frame, delimiter included.
pub const TX_FRAME_LEN: usize = cobs_len(MAX_RESPONSE_LEN + CHECKSUM_BYTES) + 1;

/// Receive buffer of a device with `capacity` keypoints: the longest request frame
/// (message and checksum COBS-encoded, delimiter not stored). For capacity 1024: 8,486
/// bytes.
pub const fn rx_frame_len(capacity: usize) -> usize {
    cobs_len(max_request_len(capacity) + CHECKSUM_BYTES)
}

/// Longest COBS encoding of `len` bytes: one code byte per run of at most 254 bytes.
pub(super) const fn cobs_len(len: usize) -> usize {
    len + len / 254 + 1
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

#[cfg(test)]
mod tests {
    extern crate std;

    use proptest::prelude::*;

    use crate::camera::{Camera, CameraModel};
    use crate::link::tests_support::{checked, cobs_frame, frame, localize_request, CAP};
    use crate::link::*;
    use crate::localizer::{Failure, MatchCounts, StageTimings, MAX_VIEWS};
    use crate::weights::{ModelConfig, Precision};

    #[test]
    fn frame_sizes_are_derived_from_the_capacity() {
        assert_eq!(max_request_len(1024), 256 + 8 * 1024);
        assert_eq!(rx_frame_len(1024), 8448 + 4 + 33 + 1);
        assert!(
            Device::<1024, { rx_frame_len(1024) }>::BYTES
                < rx_frame_len(1024) + 8 * 1024 + TX_FRAME_LEN + 128
        );
    }

    /// A frame decodes to its message only when it is whole, its checksum matches and the
    /// message uses every byte.
    #[test]
    fn frames_decode_only_when_whole_and_checked() {
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
}
