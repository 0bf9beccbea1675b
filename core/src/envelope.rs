//! The one envelope of every blob the core reads (model and map): a 16-byte header, then
//! the payload. All integers little-endian:
//!
//! ```text
//! [0..4)    magic: b"GMWB" (model) or b"GMAP" (map)
//! [4..6)    format version u16 of that kind
//! [6..8)    reserved u16 = 0
//! [8..12)   payload length u32
//! [12..16)  CRC-32 (IEEE 802.3, as zlib's crc32) of the payload
//! [16..)    payload, exactly `payload length` bytes
//! ```
//!
//! [`open`] checks it and returns the payload; [`seal`] writes it in front of a payload.

use crate::error::{BlobKind, Error, Result};

/// Size of the header.
pub const HEADER_BYTES: usize = 16;
/// Magic bytes of a model blob.
pub const MODEL_MAGIC: [u8; 4] = *b"GMWB";
/// Layout version of the model blob this build reads and writes (3: this envelope; 2 had
/// a 6-byte preamble and a trailing checksum).
pub const MODEL_VERSION: u16 = 3;
/// Magic bytes of a map blob.
pub const MAP_MAGIC: [u8; 4] = *b"GMAP";
/// Layout version of the map blob this build reads and writes (2: views carry names).
pub const MAP_VERSION: u16 = 2;
/// Magic of a view-features blob (`crate::view_features`).
pub const VIEW_FEATURES_MAGIC: [u8; 4] = *b"GVFT";
/// Format version of a view-features blob.
pub const VIEW_FEATURES_VERSION: u16 = 1;

/// Magic bytes of a kind of blob.
pub const fn magic(kind: BlobKind) -> [u8; 4] {
    match kind {
        BlobKind::Model => MODEL_MAGIC,
        BlobKind::Map => MAP_MAGIC,
        BlobKind::ViewFeatures => VIEW_FEATURES_MAGIC,
    }
}

/// Format version of a kind of blob this build reads and writes.
pub const fn version(kind: BlobKind) -> u16 {
    match kind {
        BlobKind::Model => MODEL_VERSION,
        BlobKind::Map => MAP_VERSION,
        BlobKind::ViewFeatures => VIEW_FEATURES_VERSION,
    }
}

/// CRC-32 (IEEE) of `bytes`.
pub fn crc32(bytes: &[u8]) -> u32 {
    crc32fast::hash(bytes)
}

/// Checks the envelope of a `kind` blob (length, magic, version, reserved bytes, exact
/// payload length, checksum, in that order) and returns its payload.
pub fn open(kind: BlobKind, blob: &[u8]) -> Result<&[u8]> {
    let Some((header, payload)) = blob.split_first_chunk::<HEADER_BYTES>() else {
        return Err(Error::BlobTruncated {
            blob: kind,
            needed: HEADER_BYTES,
            found: blob.len(),
        });
    };
    let field = |at: usize| [header[at], header[at + 1], header[at + 2], header[at + 3]];
    let found = field(0);
    if found != magic(kind) {
        return Err(Error::BlobMagic { blob: kind, found });
    }
    let found = u16::from_le_bytes([header[4], header[5]]);
    if found != version(kind) {
        return Err(Error::BlobVersion {
            blob: kind,
            expected: version(kind),
            found,
        });
    }
    let declared = u32::from_le_bytes(field(8)) as usize;
    if payload.len() < declared {
        return Err(Error::BlobTruncated {
            blob: kind,
            needed: HEADER_BYTES.saturating_add(declared),
            found: blob.len(),
        });
    }
    if payload.len() > declared || header[6..8] != [0, 0] {
        return Err(Error::BlobHeader { blob: kind });
    }
    let stored = u32::from_le_bytes(field(12));
    let computed = crc32(payload);
    if stored != computed {
        return Err(Error::BlobChecksum {
            blob: kind,
            stored,
            computed,
        });
    }
    Ok(payload)
}

/// Seals a `kind` blob in place: `blob[HEADER_BYTES..HEADER_BYTES + payload_len]` holds
/// the payload, the header is written in front of it; returns the blob's length.
/// [`Error::CapacityExceeded`] when `blob` cannot hold that payload or it is longer than
/// `u32::MAX` bytes.
pub fn seal(kind: BlobKind, blob: &mut [u8], payload_len: usize) -> Result<usize> {
    let too_long = Error::CapacityExceeded {
        capacity: blob
            .len()
            .saturating_sub(HEADER_BYTES)
            .min(u32::MAX as usize),
        requested: payload_len,
    };
    let length = u32::try_from(payload_len).map_err(|_| too_long)?;
    let end = HEADER_BYTES.checked_add(payload_len).ok_or(too_long)?;
    let Some((header, payload)) = blob
        .get_mut(..end)
        .and_then(|b| b.split_first_chunk_mut::<HEADER_BYTES>())
    else {
        return Err(too_long);
    };
    header[..4].copy_from_slice(&magic(kind));
    header[4..6].copy_from_slice(&version(kind).to_le_bytes());
    header[6..8].copy_from_slice(&[0, 0]);
    header[8..12].copy_from_slice(&length.to_le_bytes());
    header[12..16].copy_from_slice(&crc32(payload).to_le_bytes());
    Ok(end)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sealed(kind: BlobKind, payload: &[u8], out: &mut [u8]) -> usize {
        out[HEADER_BYTES..HEADER_BYTES + payload.len()].copy_from_slice(payload);
        seal(kind, out, payload.len()).expect("room for the payload")
    }

    #[test]
    fn crc32_matches_the_standard_check_value() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
        assert_eq!(crc32(b""), 0);
    }

    #[test]
    fn a_sealed_payload_opens_as_itself() {
        let mut buf = [0u8; 64];
        for kind in [BlobKind::Model, BlobKind::Map] {
            let len = sealed(kind, b"payload", &mut buf);
            assert_eq!(open(kind, &buf[..len]), Ok(&b"payload"[..]));
            assert_eq!(&buf[..4], &magic(kind));
        }
        let len = sealed(BlobKind::Map, b"", &mut buf);
        assert_eq!(open(BlobKind::Map, &buf[..len]), Ok(&b""[..]));
    }

    #[test]
    fn every_fault_of_the_envelope_is_its_own_error() {
        let kind = BlobKind::Model;
        let mut buf = [0u8; 64];
        let len = sealed(kind, b"payload", &mut buf);
        let blob = &buf[..len];
        let truncated = |needed, found| Error::BlobTruncated {
            blob: kind,
            needed,
            found,
        };
        assert_eq!(open(kind, &blob[..15]), Err(truncated(16, 15)));
        assert_eq!(open(kind, &blob[..len - 1]), Err(truncated(len, len - 1)));
        assert_eq!(
            open(BlobKind::Map, blob),
            Err(Error::BlobMagic {
                blob: BlobKind::Map,
                found: MODEL_MAGIC
            })
        );
        let mut edited = buf;
        edited[4] ^= 1;
        assert_eq!(
            open(kind, &edited[..len]),
            Err(Error::BlobVersion {
                blob: kind,
                expected: MODEL_VERSION,
                found: MODEL_VERSION ^ 1
            })
        );
        let mut edited = buf;
        edited[6] = 1;
        assert_eq!(
            open(kind, &edited[..len]),
            Err(Error::BlobHeader { blob: kind })
        );
        assert_eq!(
            open(kind, &buf[..len + 1]),
            Err(Error::BlobHeader { blob: kind })
        );
        let mut edited = buf;
        edited[HEADER_BYTES] ^= 0x20;
        let Err(Error::BlobChecksum {
            stored, computed, ..
        }) = open(kind, &edited[..len]).map(|_| ())
        else {
            panic!("a flipped payload bit is a checksum error");
        };
        assert_eq!(stored, crc32(b"payload"));
        assert_eq!(computed, crc32(b"Payload"));
    }

    #[test]
    fn sealing_more_than_the_buffer_holds_is_refused() {
        let mut buf = [0u8; 20];
        assert_eq!(
            seal(BlobKind::Map, &mut buf, 5),
            Err(Error::CapacityExceeded {
                capacity: 4,
                requested: 5
            })
        );
        assert_eq!(seal(BlobKind::Map, &mut buf, 4), Ok(20));
    }

    #[test]
    fn a_declared_length_near_u32_max_is_truncation_not_overflow() {
        let mut buf = [0u8; 32];
        let len = sealed(BlobKind::Map, b"x", &mut buf);
        buf[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
        assert_eq!(
            open(BlobKind::Map, &buf[..len]),
            Err(Error::BlobTruncated {
                blob: BlobKind::Map,
                needed: HEADER_BYTES.saturating_add(u32::MAX as usize),
                found: len
            })
        );
    }
}
