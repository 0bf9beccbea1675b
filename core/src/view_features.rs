//! Precomputed view features: what the matcher computes for a database view before the view
//! meets the query (paper sec. 3.2, supp. "Architecture Details": the point encoder and the
//! first self-attention layer, which sees the view's own points only). A map can carry them
//! in a blob of their own, computed once when the map is built for one model and capacity;
//! the localizer then starts each pair at the cross attention. They are the f32 values the
//! matcher would compute, so matches and poses are the same bits with and without them.
//!
//! Blob layout (all little-endian):
//!
//! ```text
//! header  16 bytes: the blob envelope (crate::envelope): magic "GVFT", version,
//!                   payload length, CRC-32 of the payload
//! payload model     u32: the CRC-32 of the model blob's payload they were computed with
//!         dim       u32: feature dimension d
//!         capacity  u32: points per view N: each view's first min(points with a bearing, N)
//!                   points in stored order, as the localizer picks them
//!         views     u32: the map's view count
//!         per view  first u32 (in values), count u32 (points)
//!         values    f32, per view d x count, channel-major
//! ```
//!
//! [`ViewFeatures::from_bytes`] checks the layout once (every range with checked arithmetic,
//! so a 32-bit target reads the same), and [`crate::Map::with_view_features`] checks it
//! against the map, so the accessors afterwards cannot meet a bad record.

use crate::envelope;
use crate::error::{BlobKind, Error, Result};
use crate::limits::MAX_FEATURE_DIM;

/// Bytes of the fixed payload header (model, dim, capacity, views).
const FIXED_BYTES: usize = 16;
/// Bytes per view in the table (first, count).
const ENTRY_BYTES: usize = 8;
/// Bytes per stored value.
const VALUE_BYTES: usize = 4;

/// A validated view-features blob read in place.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ViewFeatures<'a> {
    model_checksum: u32,
    dim: usize,
    capacity: usize,
    views: usize,
    table: &'a [u8],
    values: &'a [u8],
}

/// One view's features: `dim x count` values, channel-major.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FeatureRows<'a> {
    /// Feature dimension.
    pub dim: usize,
    /// Points.
    pub count: usize,
    bytes: &'a [u8],
}

impl FeatureRows<'_> {
    /// Writes the values into `out` (`dim x count`, channel-major); `out` shorter than that
    /// takes its first values.
    pub fn copy_to(&self, out: &mut [f32]) {
        for (o, b) in out.iter_mut().zip(self.bytes.chunks_exact(VALUE_BYTES)) {
            *o = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
        }
    }
}

fn u32_at(bytes: &[u8], at: usize) -> Option<u32> {
    let b = bytes.get(at..at.checked_add(4)?)?;
    Some(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
}

impl<'a> ViewFeatures<'a> {
    /// Reads and validates a blob without copying it: an envelope error
    /// ([`crate::envelope::open`]), or [`Error::ViewFeaturesMalformed`] for a dimension
    /// above [`MAX_FEATURE_DIM`], a table or value range outside the payload, a count above
    /// the capacity, a non-finite value or trailing bytes.
    pub fn from_bytes(blob: &'a [u8]) -> Result<Self> {
        let payload = envelope::open(BlobKind::ViewFeatures, blob)?;
        let malformed = Error::ViewFeaturesMalformed;
        let field = |i: usize| u32_at(payload, 4 * i).map(|v| v as usize).ok_or(malformed);
        let (model_checksum, dim, capacity, views) = (
            u32_at(payload, 0).ok_or(malformed)?,
            field(1)?,
            field(2)?,
            field(3)?,
        );
        if dim == 0 || dim > MAX_FEATURE_DIM {
            return Err(malformed);
        }
        let table_end = views
            .checked_mul(ENTRY_BYTES)
            .and_then(|t| t.checked_add(FIXED_BYTES))
            .ok_or(malformed)?;
        let table = payload.get(FIXED_BYTES..table_end).ok_or(malformed)?;
        let values = payload.get(table_end..).ok_or(malformed)?;
        let features = ViewFeatures {
            model_checksum,
            dim,
            capacity,
            views,
            table,
            values,
        };
        let mut expected = 0usize;
        for view in 0..views {
            let (first, count) = features.entry(view).ok_or(malformed)?;
            if first != expected || count > capacity {
                return Err(malformed);
            }
            expected = count
                .checked_mul(dim)
                .and_then(|n| n.checked_add(first))
                .ok_or(malformed)?;
        }
        let finite = values
            .chunks_exact(VALUE_BYTES)
            .all(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]).is_finite());
        if expected.checked_mul(VALUE_BYTES) != Some(values.len()) || !finite {
            return Err(malformed);
        }
        Ok(features)
    }

    /// The first value and point count of `view`.
    fn entry(&self, view: usize) -> Option<(usize, usize)> {
        let at = view.checked_mul(ENTRY_BYTES)?;
        let first = u32_at(self.table, at)? as usize;
        let count = u32_at(self.table, at.checked_add(4)?)? as usize;
        Some((first, count))
    }

    /// The CRC-32 of the model blob's payload they were computed with
    /// ([`crate::Model::checksum`]).
    pub fn model_checksum(&self) -> u32 {
        self.model_checksum
    }

    /// Feature dimension.
    pub fn dim(&self) -> usize {
        self.dim
    }

    /// Points per view they were computed for.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Views.
    pub fn view_count(&self) -> usize {
        self.views
    }

    /// The features of `view` (`None` past the last view).
    pub fn view(&self, view: usize) -> Option<FeatureRows<'a>> {
        if view >= self.views {
            return None;
        }
        let (first, count) = self.entry(view)?;
        let start = first.checked_mul(VALUE_BYTES)?;
        let len = count.checked_mul(self.dim)?.checked_mul(VALUE_BYTES)?;
        let bytes = self.values.get(start..start.checked_add(len)?)?;
        Some(FeatureRows {
            dim: self.dim,
            count,
            bytes,
        })
    }
}

/// Bytes of a blob for views of `counts` points and dimension `dim`.
pub fn blob_len(dim: usize, counts: &[usize]) -> usize {
    let values: usize = counts.iter().map(|c| c * dim).sum();
    envelope::HEADER_BYTES + FIXED_BYTES + ENTRY_BYTES * counts.len() + VALUE_BYTES * values
}

/// Writes a blob into `out` (at least [`blob_len`] bytes): the features of each view, `dim x
/// count` values channel-major, for a model blob whose payload has CRC-32 `model_checksum`
/// and `capacity` points per view. Returns the blob's length; [`Error::CapacityExceeded`]
/// when `out` is too short or a count, the dimension or the total does not fit a `u32`.
pub fn write_blob(
    model_checksum: u32,
    dim: usize,
    capacity: usize,
    views: &[&[f32]],
    out: &mut [u8],
) -> Result<usize> {
    let counts = views.iter().map(|v| v.len() / dim.max(1));
    let mut at = envelope::HEADER_BYTES;
    let mut put = |out: &mut [u8], value: usize| -> Result<()> {
        let v = u32::try_from(value).map_err(|_| Error::CapacityExceeded {
            capacity: u32::MAX as usize,
            requested: value,
        })?;
        let room = out.len();
        let slot = out.get_mut(at..at + 4).ok_or(Error::CapacityExceeded {
            capacity: room,
            requested: at + 4,
        })?;
        slot.copy_from_slice(&v.to_le_bytes());
        at += 4;
        Ok(())
    };
    put(out, model_checksum as usize)?;
    put(out, dim)?;
    put(out, capacity)?;
    put(out, views.len())?;
    let mut first = 0;
    for count in counts {
        put(out, first)?;
        put(out, count)?;
        first += count * dim;
    }
    for value in views.iter().flat_map(|v| v.iter()) {
        put(out, value.to_bits() as usize)?;
    }
    envelope::seal(BlobKind::ViewFeatures, out, at - envelope::HEADER_BYTES)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A blob of two views (2 and 1 points, d = 2) and its bytes.
    fn two_views() -> std::vec::Vec<u8> {
        let (a, b) = ([1.0, 2.0, 3.0, 4.0], [5.0, -6.0]);
        let mut out = std::vec![0u8; blob_len(2, &[2, 1])];
        let len = write_blob(0xABCD, 2, 8, &[&a, &b], &mut out).expect("fits");
        assert_eq!(len, out.len());
        out
    }

    /// `blob` with payload byte `at` set to `value` and the envelope resealed.
    fn edited(blob: &[u8], at: usize, value: u8) -> std::vec::Vec<u8> {
        let mut blob = blob.to_vec();
        blob[envelope::HEADER_BYTES + at] = value;
        let payload = blob.len() - envelope::HEADER_BYTES;
        envelope::seal(BlobKind::ViewFeatures, &mut blob, payload).expect("fits");
        blob
    }

    #[test]
    fn written_features_read_back() {
        let blob = two_views();
        let f = ViewFeatures::from_bytes(&blob).expect("valid");
        assert_eq!(
            (f.model_checksum(), f.dim(), f.capacity(), f.view_count()),
            (0xABCD, 2, 8, 2)
        );
        let mut out = [0.0f32; 4];
        let rows = f.view(0).expect("view 0");
        assert_eq!((rows.dim, rows.count), (2, 2));
        rows.copy_to(&mut out);
        assert_eq!(out, [1.0, 2.0, 3.0, 4.0]);
        let rows = f.view(1).expect("view 1");
        assert_eq!(rows.count, 1);
        rows.copy_to(&mut out[..2]);
        assert_eq!(out[..2], [5.0, -6.0]);
        assert_eq!(f.view(2), None);
    }

    #[test]
    fn every_bad_payload_is_a_typed_error() {
        let blob = two_views();
        let malformed = Err(Error::ViewFeaturesMalformed);
        // Dimension 0 and above the maximum, a view count the table cannot hold (also
        // one whose table size overflows 32 bits), a count above the capacity, a gap in
        // the values, a NaN value, trailing and missing bytes.
        assert_eq!(ViewFeatures::from_bytes(&edited(&blob, 4, 0)), malformed);
        assert_eq!(ViewFeatures::from_bytes(&edited(&blob, 5, 1)), malformed);
        assert_eq!(ViewFeatures::from_bytes(&edited(&blob, 12, 3)), malformed);
        assert_eq!(
            ViewFeatures::from_bytes(&edited(&blob, 15, 0x40)),
            malformed
        );
        assert_eq!(ViewFeatures::from_bytes(&edited(&blob, 20, 9)), malformed);
        assert_eq!(ViewFeatures::from_bytes(&edited(&blob, 24, 5)), malformed);
        let values = FIXED_BYTES + 2 * ENTRY_BYTES;
        assert_eq!(
            ViewFeatures::from_bytes(&edited(&blob, values + 3, 0x7F)),
            {
                // 0x7F in the top byte of 1.0 (0x3F80_0000) gives 0x7F80_0000: infinity.
                malformed
            }
        );
        let mut longer = blob.clone();
        longer.extend_from_slice(&[0; 4]);
        let payload = longer.len() - envelope::HEADER_BYTES;
        envelope::seal(BlobKind::ViewFeatures, &mut longer, payload).expect("fits");
        assert_eq!(ViewFeatures::from_bytes(&longer), malformed);
        let shorter = &blob[..blob.len() - 4];
        let mut cut = shorter.to_vec();
        envelope::seal(BlobKind::ViewFeatures, &mut cut, shorter.len() - 16).expect("fits");
        assert_eq!(ViewFeatures::from_bytes(&cut), malformed);
        assert!(matches!(
            ViewFeatures::from_bytes(&blob[..10]),
            Err(Error::BlobTruncated {
                blob: BlobKind::ViewFeatures,
                ..
            })
        ));
    }

    #[test]
    fn a_short_buffer_is_refused() {
        let mut out = [0u8; 40];
        assert!(matches!(
            write_blob(1, 2, 8, &[&[1.0, 2.0, 3.0, 4.0]], &mut out),
            Err(Error::CapacityExceeded { .. })
        ));
    }
}
