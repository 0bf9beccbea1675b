//! Geometric-only map (paper sec. 1 and supp. "Practical Challenges"): 3D points, the
//! database cameras and poses, and per database view the indices of the points it
//! observes. No descriptors and no images. Read in place from a byte blob (e.g. in flash)
//! without copying or allocating; view selection around a coarse prior pose.
//!
//! Blob layout (all little-endian):
//!
//! ```text
//! header  16 bytes: the blob envelope (crate::envelope): magic "GMAP", version,
//!                   payload length, CRC-32 of the payload
//! payload postcard encoding of five byte strings (varint length + bytes each):
//!   points       12 bytes per point: x, y, z as f32
//!   cameras      73 bytes per camera: COLMAP model id u8, width u32, height u32,
//!                8 parameters f64 in COLMAP order, zero-padded
//!   views        80 bytes per view: image id u32, camera index u32,
//!                pose qw qx qy qz tx ty tz f64 (COLMAP world-to-camera),
//!                first index u32 and count u32 into `view points`,
//!                first byte u32 and length u32 of its name in `names`
//!   view points  4 bytes per observation: point index u32
//!   names        the views' image names (UTF-8), one after the other
//! ```
//!
//! Version 1 had no names (72-byte views, four byte strings); it is refused with
//! [`Error::BlobVersion`]: rebuild the map with `gomatch-sim map build`.
//!
//! [`Map::from_bytes`] checks everything once (header, checksum, record sizes, every index,
//! every camera and pose), so the accessors afterwards cannot meet a bad record.

use nalgebra::UnitQuaternion;
use serde::ser::{SerializeSeq, SerializeTuple};
use serde::{Deserialize, Serialize, Serializer};

use crate::camera::{Camera, CameraModel};
use crate::envelope;
use crate::error::{BlobKind, Error, Input, MapItem, Result};
use crate::pose::Pose;
use crate::view_features::ViewFeatures;

pub use crate::envelope::{HEADER_BYTES, MAP_MAGIC, MAP_VERSION};
/// Bytes per stored 3D point.
pub const POINT_BYTES: usize = 12;
/// Bytes per stored camera.
pub const CAMERA_BYTES: usize = 1 + 4 + 4 + 8 * 8;
/// Bytes per stored view.
pub const VIEW_BYTES: usize = 4 + 4 + 7 * 8 + 4 + 4 + 4 + 4;
/// Bytes per stored observation (point index).
pub const INDEX_BYTES: usize = 4;

fn array<const N: usize>(bytes: &[u8], offset: usize) -> Option<[u8; N]> {
    bytes
        .get(offset..offset.checked_add(N)?)
        .and_then(|s| s.try_into().ok())
}

fn u32_at(bytes: &[u8], offset: usize) -> Option<u32> {
    array(bytes, offset).map(u32::from_le_bytes)
}

fn f32_at(bytes: &[u8], offset: usize) -> Option<f32> {
    array(bytes, offset).map(f32::from_le_bytes)
}

fn f64_at(bytes: &[u8], offset: usize) -> Option<f64> {
    array(bytes, offset).map(f64::from_le_bytes)
}

/// The five byte strings of the payload, borrowed from the blob.
#[derive(Deserialize)]
struct PayloadRef<'a> {
    points: &'a [u8],
    cameras: &'a [u8],
    views: &'a [u8],
    view_points: &'a [u8],
    names: &'a [u8],
}

/// An unsigned machine word the decoder's offsets are computed in: `usize`, which is
/// `u32` on a 32-bit target such as the firmware's (the tests run the same code in `u32`).
trait Word: Copy + TryFrom<usize> {
    fn checked_add(self, other: Self) -> Option<Self>;
    fn checked_mul(self, other: Self) -> Option<Self>;
}

macro_rules! word {
    ($($t:ty),*) => {$(
        impl Word for $t {
            fn checked_add(self, other: Self) -> Option<Self> {
                <$t>::checked_add(self, other)
            }
            fn checked_mul(self, other: Self) -> Option<Self> {
                <$t>::checked_mul(self, other)
            }
        }
    )*};
}
word!(u32, usize);

/// Byte range of the `count` entries of `entry_bytes` bytes each from entry `first`, every
/// step checked in the word `W`: `None` where an offset does not fit (with wrapping
/// arithmetic a crafted `first` and `count` would pass validation and read the wrong
/// entries).
fn entry_range<W: Word>(
    first: impl TryInto<W>,
    count: impl TryInto<W>,
    entry_bytes: usize,
) -> Option<core::ops::Range<W>> {
    let entry_bytes = W::try_from(entry_bytes).ok()?;
    let first = first.try_into().ok()?;
    let end = first.checked_add(count.try_into().ok()?)?;
    Some(first.checked_mul(entry_bytes)?..end.checked_mul(entry_bytes)?)
}

/// A database view as stored in the map.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapView {
    /// Image id in the source model.
    pub image_id: u32,
    /// Index of the view's camera in the map.
    pub camera_index: u32,
    /// World-to-camera pose.
    pub pose: Pose,
    /// First entry of the view's observations in the view-point list.
    first: u32,
    /// Number of observations.
    count: u32,
    /// First byte of the view's name in the name list.
    name_first: u32,
    /// Bytes of the name.
    name_len: u32,
}

/// The point indices a view observes, borrowed from the blob.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ViewPoints<'a> {
    bytes: &'a [u8],
}

impl<'a> ViewPoints<'a> {
    /// Number of observed points.
    pub fn len(&self) -> usize {
        self.bytes.len() / INDEX_BYTES
    }

    /// Whether the view observes no point.
    pub fn is_empty(&self) -> bool {
        self.bytes.is_empty()
    }

    /// The `j`-th observed point index.
    pub fn get(&self, j: usize) -> Option<u32> {
        u32_at(self.bytes, j.checked_mul(INDEX_BYTES)?)
    }

    /// The observed point indices in stored order.
    pub fn iter(&self) -> impl Iterator<Item = u32> + Clone + 'a {
        self.bytes
            .chunks_exact(INDEX_BYTES)
            .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
    }
}

/// A validated map read in place from its blob.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Map<'a> {
    points: &'a [u8],
    cameras: &'a [u8],
    views: &'a [u8],
    view_points: &'a [u8],
    names: &'a [u8],
    features: Option<ViewFeatures<'a>>,
}

impl<'a> Map<'a> {
    /// Reads and validates a map blob without copying it. Fails with
    /// an envelope error ([`crate::envelope::open`]), [`Error::MapMalformed`] (undecodable payload, record
    /// sizes, trailing bytes, a name outside the name list or not UTF-8),
    /// [`Error::MapIndexOutOfRange`], [`Error::InvalidIntrinsics`]
    /// or [`Error::NonFinite`].
    pub fn from_bytes(blob: &'a [u8]) -> Result<Self> {
        let payload = envelope::open(BlobKind::Map, blob)?;
        let (decoded, rest): (PayloadRef<'a>, &[u8]) =
            postcard::take_from_bytes(payload).map_err(|_| Error::MapMalformed)?;
        if !rest.is_empty() {
            return Err(Error::MapMalformed);
        }
        let map = Map {
            points: decoded.points,
            cameras: decoded.cameras,
            views: decoded.views,
            view_points: decoded.view_points,
            names: decoded.names,
            features: None,
        };
        map.validate()?;
        Ok(map)
    }

    /// The map with precomputed view features ([`crate::view_features`]), which the
    /// localizer uses where they fit its model and capacity. [`Error::ViewFeaturesMismatch`]
    /// when they hold another number of views, or more points for a view than it
    /// observes.
    pub fn with_view_features(self, features: ViewFeatures<'a>) -> Result<Self> {
        if features.view_count() != self.view_count() {
            return Err(Error::ViewFeaturesMismatch {
                view: self.view_count(),
            });
        }
        for view in 0..self.view_count() {
            let observed = self.view(view)?.count as usize;
            if features.view(view).is_none_or(|f| f.count > observed) {
                return Err(Error::ViewFeaturesMismatch { view });
            }
        }
        Ok(Map {
            features: Some(features),
            ..self
        })
    }

    /// The precomputed view features, if the map has them.
    pub fn view_features(&self) -> Option<&ViewFeatures<'a>> {
        self.features.as_ref()
    }

    fn validate(&self) -> Result<()> {
        let sizes = [
            (self.points, POINT_BYTES),
            (self.cameras, CAMERA_BYTES),
            (self.views, VIEW_BYTES),
            (self.view_points, INDEX_BYTES),
        ];
        if sizes.iter().any(|(bytes, size)| bytes.len() % size != 0) {
            return Err(Error::MapMalformed);
        }
        for index in 0..self.point_count() {
            if !self.point(index)?.iter().all(|v| v.is_finite()) {
                return Err(Error::NonFinite {
                    input: Input::Points3d,
                    index,
                });
            }
        }
        for index in 0..self.camera_count() {
            self.camera(index)?;
        }
        let observations = self.view_points.len() / INDEX_BYTES;
        for index in 0..self.view_count() {
            let view = self.view(index)?;
            if view.camera_index as usize >= self.camera_count() {
                return Err(Error::MapIndexOutOfRange {
                    item: MapItem::Camera,
                    index: view.camera_index as usize,
                    limit: self.camera_count(),
                });
            }
            let in_range = entry_range::<usize>(view.first, view.count, 1)
                .filter(|entries| entries.end <= observations);
            if in_range.is_none() {
                return Err(Error::MapIndexOutOfRange {
                    item: MapItem::ViewPoints,
                    index: (u64::from(view.first) + u64::from(view.count))
                        .try_into()
                        .unwrap_or(usize::MAX),
                    limit: observations,
                });
            }
            self.name_of(&view)?;
        }
        let points = self.point_count();
        let view_points = ViewPoints {
            bytes: self.view_points,
        };
        if let Some(bad) = view_points.iter().find(|&p| p as usize >= points) {
            return Err(Error::MapIndexOutOfRange {
                item: MapItem::Point,
                index: bad as usize,
                limit: points,
            });
        }
        Ok(())
    }

    /// Number of 3D points.
    pub fn point_count(&self) -> usize {
        self.points.len() / POINT_BYTES
    }

    /// Number of cameras.
    pub fn camera_count(&self) -> usize {
        self.cameras.len() / CAMERA_BYTES
    }

    /// Number of database views.
    pub fn view_count(&self) -> usize {
        self.views.len() / VIEW_BYTES
    }

    /// Total number of observations (view, point) over all views.
    pub fn observation_count(&self) -> usize {
        self.view_points.len() / INDEX_BYTES
    }

    fn out_of_range(item: MapItem, index: usize, limit: usize) -> Error {
        Error::MapIndexOutOfRange { item, index, limit }
    }

    /// World coordinates of point `index`.
    pub fn point(&self, index: usize) -> Result<[f32; 3]> {
        let limit = self.point_count();
        if index >= limit {
            return Err(Self::out_of_range(MapItem::Point, index, limit));
        }
        let read = |axis: usize| {
            let offset = index.checked_mul(POINT_BYTES)?.checked_add(4 * axis)?;
            f32_at(self.points, offset)
        };
        match (read(0), read(1), read(2)) {
            (Some(x), Some(y), Some(z)) => Ok([x, y, z]),
            _ => Err(Self::out_of_range(MapItem::Point, index, limit)),
        }
    }

    /// Camera `index`.
    pub fn camera(&self, index: usize) -> Result<Camera> {
        let limit = self.camera_count();
        if index >= limit {
            return Err(Self::out_of_range(MapItem::Camera, index, limit));
        }
        let record = entry_range::<usize>(index, 1usize, CAMERA_BYTES)
            .and_then(|range| self.cameras.get(range))
            .ok_or(Self::out_of_range(MapItem::Camera, index, limit))?;
        let model = CameraModel::from_colmap_id(i32::from(record[0]))?;
        let width = u32_at(record, 1).ok_or(Error::MapMalformed)?;
        let height = u32_at(record, 5).ok_or(Error::MapMalformed)?;
        let mut params = [0.0; 8];
        for (i, p) in params.iter_mut().enumerate() {
            *p = f64_at(record, 9 + 8 * i).ok_or(Error::MapMalformed)?;
        }
        let count = model.param_count();
        Camera::from_colmap(model, width, height, &params[..count])
    }

    /// View `index`.
    pub fn view(&self, index: usize) -> Result<MapView> {
        let limit = self.view_count();
        if index >= limit {
            return Err(Self::out_of_range(MapItem::View, index, limit));
        }
        let record = entry_range::<usize>(index, 1usize, VIEW_BYTES)
            .and_then(|range| self.views.get(range))
            .ok_or(Self::out_of_range(MapItem::View, index, limit))?;
        let value = |i: usize| f64_at(record, 8 + 8 * i).ok_or(Error::MapMalformed);
        let q = [value(0)?, value(1)?, value(2)?, value(3)?];
        let t = [value(4)?, value(5)?, value(6)?];
        Ok(MapView {
            image_id: u32_at(record, 0).ok_or(Error::MapMalformed)?,
            camera_index: u32_at(record, 4).ok_or(Error::MapMalformed)?,
            pose: Pose::from_colmap(q, t)?,
            first: u32_at(record, 64).ok_or(Error::MapMalformed)?,
            count: u32_at(record, 68).ok_or(Error::MapMalformed)?,
            name_first: u32_at(record, 72).ok_or(Error::MapMalformed)?,
            name_len: u32_at(record, 76).ok_or(Error::MapMalformed)?,
        })
    }

    /// The image name of view `index` (empty for a view stored without one).
    pub fn view_name(&self, index: usize) -> Result<&'a str> {
        self.name_of(&self.view(index)?)
    }

    fn name_of(&self, view: &MapView) -> Result<&'a str> {
        let start = view.name_first as usize;
        let bytes = start
            .checked_add(view.name_len as usize)
            .and_then(|end| self.names.get(start..end))
            .ok_or(Error::MapMalformed)?;
        core::str::from_utf8(bytes).map_err(|_| Error::MapMalformed)
    }

    /// The point indices view `index` observes.
    pub fn view_points(&self, index: usize) -> Result<ViewPoints<'a>> {
        let view = self.view(index)?;
        let out_of_range = Self::out_of_range(
            MapItem::ViewPoints,
            view.first as usize,
            self.observation_count(),
        );
        let bytes = entry_range::<usize>(view.first, view.count, INDEX_BYTES)
            .and_then(|range| self.view_points.get(range))
            .ok_or(out_of_range)?;
        Ok(ViewPoints { bytes })
    }

    /// The points view `index` observes as `(point index, position)`, in stored order: the
    /// input of [`crate::localizer::view_point_bearings`]. An index that names no point is
    /// left out (a map that passed validation has none).
    pub fn view_point_positions(
        &self,
        index: usize,
    ) -> Result<impl Iterator<Item = (u32, [f64; 3])> + Clone + '_> {
        let observed = self.view_points(index)?;
        Ok(observed.iter().filter_map(move |point| {
            let position = self.point(point as usize).ok()?;
            Some((point, position.map(f64::from)))
        }))
    }

    /// The `K` views nearest to a coarse prior pose: views whose viewing direction is
    /// within `max_angle_deg` of the prior's rank first, each group by camera-centre
    /// distance (ties by index). Returns view indices, best first; fewer than `K` when the
    /// map has fewer views.
    pub fn views_near<const K: usize>(
        &self,
        prior: &Pose,
        max_angle_deg: f64,
    ) -> Result<heapless::Vec<u32, K>> {
        let centre = prior.center();
        let direction = prior.viewing_direction();
        if !centre.iter().chain(direction.iter()).all(|v| v.is_finite()) {
            return Err(Error::NonFinite {
                input: Input::Pose,
                index: 0,
            });
        }
        let min_cos = libm::cos(max_angle_deg.to_radians());
        // (direction disagrees, distance, view index), kept sorted, best first.
        let mut best: heapless::Vec<(bool, f64, u32), K> = heapless::Vec::new();
        for index in 0..self.view_count() {
            let pose = self.view(index)?.pose;
            let disagrees = pose.viewing_direction().dot(&direction) < min_cos;
            let distance = (pose.center() - centre).norm();
            let key = (disagrees, distance, index as u32);
            let position = best
                .iter()
                .position(|b| (key.0, key.1) < (b.0, b.1))
                .unwrap_or(best.len());
            if position < K {
                if best.is_full() {
                    best.pop();
                }
                // Room was made above and `position <= len`, so this cannot fail.
                best.insert(position, key)
                    .map_err(|_| Error::CapacityExceeded {
                        capacity: K,
                        requested: K + 1,
                    })?;
            }
        }
        Ok(best.iter().map(|b| b.2).collect())
    }

    /// View indices of caller-chosen images (e.g. from image retrieval), in the given
    /// order. Fails with [`Error::MapUnknownImage`] for an id the map does not hold and
    /// [`Error::CapacityExceeded`] for more than `K` ids.
    pub fn views_by_image_id<const K: usize>(
        &self,
        image_ids: &[u32],
    ) -> Result<heapless::Vec<u32, K>> {
        if image_ids.len() > K {
            return Err(Error::CapacityExceeded {
                capacity: K,
                requested: image_ids.len(),
            });
        }
        let mut views = heapless::Vec::new();
        for &image_id in image_ids {
            let mut found = None;
            for index in 0..self.view_count() {
                if self.view(index)?.image_id == image_id {
                    found = Some(index as u32);
                    break;
                }
            }
            let index = found.ok_or(Error::MapUnknownImage { image_id })?;
            views.push(index).map_err(|_| Error::CapacityExceeded {
                capacity: K,
                requested: image_ids.len(),
            })?;
        }
        Ok(views)
    }
}

/// A database view to store: its image id and name, camera index, pose and observed point
/// indices.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapViewEntry<'p> {
    /// Image id in the source model.
    pub image_id: u32,
    /// Image name in the source model (e.g. its file name; may be empty).
    pub name: &'p str,
    /// Index into the cameras given to [`encode`].
    pub camera_index: u32,
    /// World-to-camera pose.
    pub pose: Pose,
    /// Indices into the points given to [`encode`].
    pub points: &'p [u32],
}

/// Byte string written element by element: postcard encodes a sequence of `u8` exactly
/// like a byte string (varint length, then the bytes), so it reads back borrowed.
struct ByteString<F: Fn(&mut dyn FnMut(u8))> {
    len: usize,
    write: F,
}

impl<F: Fn(&mut dyn FnMut(u8))> Serialize for ByteString<F> {
    fn serialize<S: Serializer>(&self, serializer: S) -> core::result::Result<S::Ok, S::Error> {
        let mut seq = serializer.serialize_seq(Some(self.len))?;
        let mut result = Ok(());
        (self.write)(&mut |byte| {
            if result.is_ok() {
                result = seq.serialize_element(&byte);
            }
        });
        result?;
        seq.end()
    }
}

/// Size of a postcard varint encoding of `value`.
fn varint_len(mut value: usize) -> usize {
    let mut len = 1;
    while value >= 0x80 {
        value >>= 7;
        len += 1;
    }
    len
}

/// Total bytes of the views' names.
fn name_bytes(views: &[MapViewEntry<'_>]) -> usize {
    views.iter().map(|v| v.name.len()).sum()
}

/// Size of the blob [`encode`] writes for these inputs.
pub fn encoded_len(point_count: usize, camera_count: usize, views: &[MapViewEntry<'_>]) -> usize {
    let observations: usize = views.iter().map(|v| v.points.len()).sum();
    [
        point_count * POINT_BYTES,
        camera_count * CAMERA_BYTES,
        views.len() * VIEW_BYTES,
        observations * INDEX_BYTES,
        name_bytes(views),
    ]
    .iter()
    .map(|&n| varint_len(n) + n)
    .sum::<usize>()
        + HEADER_BYTES
}

fn check_inputs(points: &[[f32; 3]], cameras: &[Camera], views: &[MapViewEntry<'_>]) -> Result<()> {
    let too_many = |n: usize| Error::CapacityExceeded {
        capacity: u32::MAX as usize,
        requested: n,
    };
    let observations: usize = views.iter().map(|v| v.points.len()).sum();
    for n in [
        points.len(),
        cameras.len(),
        views.len(),
        observations,
        name_bytes(views),
    ] {
        if n > u32::MAX as usize {
            return Err(too_many(n));
        }
    }
    if let Some(index) = points.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(Error::NonFinite {
            input: Input::Points3d,
            index,
        });
    }
    for view in views {
        if view.camera_index as usize >= cameras.len() {
            return Err(Error::MapIndexOutOfRange {
                item: MapItem::Camera,
                index: view.camera_index as usize,
                limit: cameras.len(),
            });
        }
        if let Some(&bad) = view.points.iter().find(|&&p| p as usize >= points.len()) {
            return Err(Error::MapIndexOutOfRange {
                item: MapItem::Point,
                index: bad as usize,
                limit: points.len(),
            });
        }
        let pose_values = view
            .pose
            .rotation
            .matrix()
            .iter()
            .chain(view.pose.translation.iter());
        if !pose_values.copied().all(f64::is_finite) {
            return Err(Error::NonFinite {
                input: Input::Pose,
                index: view.image_id as usize,
            });
        }
    }
    Ok(())
}

/// Writes a map blob into `out` and returns its length (see the module documentation for
/// the layout). Fails on out-of-range indices, non-finite values, or an `out` shorter than
/// [`encoded_len`] ([`Error::CapacityExceeded`]).
pub fn encode(
    points: &[[f32; 3]],
    cameras: &[Camera],
    views: &[MapViewEntry<'_>],
    out: &mut [u8],
) -> Result<usize> {
    check_inputs(points, cameras, views)?;
    let needed = encoded_len(points.len(), cameras.len(), views);
    if needed - HEADER_BYTES > u32::MAX as usize {
        return Err(Error::CapacityExceeded {
            capacity: u32::MAX as usize,
            requested: needed - HEADER_BYTES,
        });
    }
    if out.len() < needed {
        return Err(Error::CapacityExceeded {
            capacity: out.len(),
            requested: needed,
        });
    }
    let point_bytes = ByteString {
        len: points.len() * POINT_BYTES,
        write: |emit: &mut dyn FnMut(u8)| {
            for value in points.iter().flatten() {
                value.to_le_bytes().into_iter().for_each(&mut *emit);
            }
        },
    };
    let camera_bytes = ByteString {
        len: cameras.len() * CAMERA_BYTES,
        write: |emit: &mut dyn FnMut(u8)| {
            for camera in cameras {
                let (params, _) = camera.colmap_params();
                // COLMAP model ids of the supported models are 0..=4.
                emit(camera.model.colmap_id() as u8);
                camera.width.to_le_bytes().into_iter().for_each(&mut *emit);
                camera.height.to_le_bytes().into_iter().for_each(&mut *emit);
                for p in params {
                    p.to_le_bytes().into_iter().for_each(&mut *emit);
                }
            }
        },
    };
    let view_bytes = ByteString {
        len: views.len() * VIEW_BYTES,
        write: |emit: &mut dyn FnMut(u8)| {
            let (mut first, mut name_first) = (0u32, 0u32);
            for view in views {
                let q = UnitQuaternion::from_rotation_matrix(&view.pose.rotation);
                let t = view.pose.translation;
                view.image_id.to_le_bytes().into_iter().for_each(&mut *emit);
                view.camera_index
                    .to_le_bytes()
                    .into_iter()
                    .for_each(&mut *emit);
                for v in [q.w, q.i, q.j, q.k, t.x, t.y, t.z] {
                    v.to_le_bytes().into_iter().for_each(&mut *emit);
                }
                // Counts were checked to fit in u32 above.
                let count = view.points.len() as u32;
                first.to_le_bytes().into_iter().for_each(&mut *emit);
                count.to_le_bytes().into_iter().for_each(&mut *emit);
                first += count;
                // Name bytes were checked to fit in u32 above.
                let name_len = view.name.len() as u32;
                name_first.to_le_bytes().into_iter().for_each(&mut *emit);
                name_len.to_le_bytes().into_iter().for_each(&mut *emit);
                name_first += name_len;
            }
        },
    };
    let observation_bytes = ByteString {
        len: views.iter().map(|v| v.points.len()).sum::<usize>() * INDEX_BYTES,
        write: |emit: &mut dyn FnMut(u8)| {
            for index in views.iter().flat_map(|v| v.points) {
                index.to_le_bytes().into_iter().for_each(&mut *emit);
            }
        },
    };
    let names = ByteString {
        len: name_bytes(views),
        write: |emit: &mut dyn FnMut(u8)| {
            for byte in views.iter().flat_map(|v| v.name.bytes()) {
                emit(byte);
            }
        },
    };
    let payload = out.get_mut(HEADER_BYTES..).unwrap_or(&mut []);
    let capacity = payload.len();
    let payload_len = {
        let tuple = Payload(
            &point_bytes,
            &camera_bytes,
            &view_bytes,
            &observation_bytes,
            &names,
        );
        postcard::to_slice(&tuple, payload)
            .map_err(|_| Error::CapacityExceeded {
                capacity,
                requested: needed - HEADER_BYTES,
            })?
            .len()
    };
    envelope::seal(BlobKind::Map, out, payload_len)
}

/// The payload's five byte strings in order.
struct Payload<'x, A, B, C, D, E>(&'x A, &'x B, &'x C, &'x D, &'x E);

impl<A: Serialize, B: Serialize, C: Serialize, D: Serialize, E: Serialize> Serialize
    for Payload<'_, A, B, C, D, E>
{
    fn serialize<S: Serializer>(&self, serializer: S) -> core::result::Result<S::Ok, S::Error> {
        let mut tuple = serializer.serialize_tuple(5)?;
        tuple.serialize_element(self.0)?;
        tuple.serialize_element(self.1)?;
        tuple.serialize_element(self.2)?;
        tuple.serialize_element(self.3)?;
        tuple.serialize_element(self.4)?;
        tuple.end()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};

    const POINTS: [[f32; 3]; 4] = [
        [0.0, 0.0, 5.0],
        [1.0, 0.0, 5.0],
        [0.0, 1.0, 6.0],
        [-1.0, -1.0, 7.0],
    ];

    fn cameras() -> [Camera; 2] {
        [
            Camera::from_colmap(
                CameraModel::SimpleRadial,
                640,
                480,
                &[500.0, 320.0, 240.0, -0.1],
            )
            .unwrap(),
            Camera::from_colmap(
                CameraModel::OpenCv,
                1920,
                1080,
                &[1500.0, 1490.0, 960.0, 540.0, -0.1, 0.02, 0.001, -0.0005],
            )
            .unwrap(),
        ]
    }

    fn pose(x: f64, yaw: f64) -> Pose {
        Pose::new(
            Rotation3::from_euler_angles(0.0, yaw, 0.0),
            Vector3::new(x, 0.0, 0.0),
        )
    }

    const FIRST: [u32; 3] = [0, 1, 2];
    const SECOND: [u32; 2] = [3, 1];

    fn views() -> [MapViewEntry<'static>; 3] {
        [
            MapViewEntry {
                image_id: 10,
                name: "a.jpg",
                camera_index: 0,
                pose: pose(0.0, 0.0),
                points: &FIRST,
            },
            MapViewEntry {
                image_id: 20,
                name: "dir/b.jpg",
                camera_index: 1,
                pose: pose(-3.0, 0.1),
                points: &SECOND,
            },
            MapViewEntry {
                image_id: 30,
                name: "",
                camera_index: 0,
                pose: pose(1.0, 3.0),
                points: &[],
            },
        ]
    }

    fn encode_sample(buffer: &mut [u8]) -> usize {
        encode(&POINTS, &cameras(), &views(), buffer).unwrap()
    }

    #[test]
    fn map_round_trips_in_place() {
        let mut buffer = [0u8; 1024];
        let len = encode_sample(&mut buffer);
        assert_eq!(len, encoded_len(POINTS.len(), 2, &views()));
        let map = Map::from_bytes(&buffer[..len]).unwrap();
        assert_eq!(
            (
                map.point_count(),
                map.camera_count(),
                map.view_count(),
                map.observation_count()
            ),
            (4, 2, 3, 5)
        );
        for (i, p) in POINTS.iter().enumerate() {
            assert_eq!(map.point(i).unwrap(), *p);
        }
        assert_eq!(map.camera(0).unwrap(), cameras()[0]);
        assert_eq!(map.camera(1).unwrap(), cameras()[1]);
        for (i, entry) in views().iter().enumerate() {
            let view = map.view(i).unwrap();
            assert_eq!(
                (view.image_id, view.camera_index),
                (entry.image_id, entry.camera_index)
            );
            assert!((view.pose.rotation.matrix() - entry.pose.rotation.matrix()).amax() < 1e-12);
            assert_eq!(view.pose.translation, entry.pose.translation);
            let points = map.view_points(i).unwrap();
            assert_eq!(points.len(), entry.points.len());
            assert!(points.iter().eq(entry.points.iter().copied()));
            assert_eq!(map.view_name(i), Ok(entry.name));
        }
        assert_eq!(map.view_points(1).unwrap().get(1), Some(1));
        assert_eq!(map.view_points(1).unwrap().get(2), None);
    }

    #[test]
    fn accessors_report_out_of_range_indices() {
        let mut buffer = [0u8; 1024];
        let len = encode_sample(&mut buffer);
        let map = Map::from_bytes(&buffer[..len]).unwrap();
        assert_eq!(
            map.point(4),
            Err(Error::MapIndexOutOfRange {
                item: MapItem::Point,
                index: 4,
                limit: 4
            })
        );
        assert!(map.point(usize::MAX).is_err());
        assert!(map.camera(2).is_err());
        assert!(map.view(usize::MAX).is_err());
        assert!(map.view_points(3).is_err());
    }

    #[test]
    fn bad_blobs_are_typed_errors() {
        let mut buffer = [0u8; 1024];
        let len = encode_sample(&mut buffer);
        let blob = &buffer[..len];
        assert_eq!(
            Map::from_bytes(&blob[..10]),
            Err(Error::BlobTruncated {
                blob: BlobKind::Map,
                needed: 16,
                found: 10
            })
        );
        assert_eq!(
            Map::from_bytes(&blob[..len - 1]),
            Err(Error::BlobTruncated {
                blob: BlobKind::Map,
                needed: len,
                found: len - 1
            })
        );
        let mut copy = [0u8; 1024];
        copy[..len].copy_from_slice(blob);
        copy[0] = b'X';
        assert_eq!(
            Map::from_bytes(&copy[..len]),
            Err(Error::BlobMagic {
                blob: BlobKind::Map,
                found: *b"XMAP"
            })
        );
        copy[..len].copy_from_slice(blob);
        // A version-1 map (no names) is refused by its version.
        copy[4] = 1;
        assert_eq!(
            Map::from_bytes(&copy[..len]),
            Err(Error::BlobVersion {
                blob: BlobKind::Map,
                expected: 2,
                found: 1
            })
        );
        copy[..len].copy_from_slice(blob);
        copy[len - 3] ^= 0x40;
        assert!(matches!(
            Map::from_bytes(&copy[..len]),
            Err(Error::BlobChecksum {
                blob: BlobKind::Map,
                ..
            })
        ));
        copy[..len].copy_from_slice(blob);
        assert_eq!(
            Map::from_bytes(&copy[..len + 1]),
            Err(Error::BlobHeader {
                blob: BlobKind::Map
            })
        );
    }

    /// Rewrites the checksum so that a deliberately corrupted payload gets past it.
    fn reseal(blob: &mut [u8]) {
        let payload = blob.len() - HEADER_BYTES;
        envelope::seal(BlobKind::Map, blob, payload).expect("fits");
    }

    #[test]
    fn sealed_but_inconsistent_payloads_are_refused() {
        let mut buffer = [0u8; 1024];
        let len = encode_sample(&mut buffer);
        // The last observation index (point 1 of the second view, before the names and
        // their length byte) becomes 9.
        let names = "a.jpgdir/b.jpg".len() + 1;
        buffer[len - names - 4..len - names].copy_from_slice(&9u32.to_le_bytes());
        reseal(&mut buffer[..len]);
        assert_eq!(
            Map::from_bytes(&buffer[..len]),
            Err(Error::MapIndexOutOfRange {
                item: MapItem::Point,
                index: 9,
                limit: 4
            })
        );
        let mut buffer = [0u8; 1024];
        let len = encode_sample(&mut buffer);
        // First byte of the payload: the points' length varint (48) claims one more byte.
        assert_eq!(buffer[HEADER_BYTES], 48);
        buffer[HEADER_BYTES] = 49;
        reseal(&mut buffer[..len]);
        assert_eq!(Map::from_bytes(&buffer[..len]), Err(Error::MapMalformed));
        // A name that is not UTF-8, and a name range past the name list.
        let mut buffer = [0u8; 1024];
        let len = encode_sample(&mut buffer);
        buffer[len - 1] = 0xFF;
        reseal(&mut buffer[..len]);
        assert_eq!(Map::from_bytes(&buffer[..len]), Err(Error::MapMalformed));
        let mut buffer = [0u8; 1024];
        let len = encode_sample(&mut buffer);
        let views_start = len - (14 + 1) - (5 * INDEX_BYTES + 1) - 3 * VIEW_BYTES;
        let second_name_len = views_start + VIEW_BYTES + 76;
        assert_eq!(buffer[second_name_len], 9);
        buffer[second_name_len] = 10;
        reseal(&mut buffer[..len]);
        assert_eq!(Map::from_bytes(&buffer[..len]), Err(Error::MapMalformed));
    }

    #[test]
    fn offsets_that_overflow_a_32_bit_word_are_refused() {
        // The offsets as the firmware's 32-bit target computes them: the crafted view of
        // issue 23 (first 0x4000_0000, count 0xC000_0005) wraps to entries 0x4000_0000..5.
        assert_eq!(entry_range::<u32>(0x4000_0000u32, 0xC000_0005u32, 1), None);
        assert_eq!(entry_range::<u32>(0x4000_0000u32, 1u32, INDEX_BYTES), None);
        assert_eq!(
            entry_range::<u32>(u32::MAX, 0u32, 1),
            Some(u32::MAX..u32::MAX)
        );
        assert_eq!(entry_range::<u32>(3u32, 2u32, INDEX_BYTES), Some(12..20));
        assert_eq!(entry_range::<usize>(3u32, 2u32, INDEX_BYTES), Some(12..20));
        // The same view in a sealed blob is refused here too.
        let mut buffer = [0u8; 1024];
        let len = encode_sample(&mut buffer);
        let (views_at, observations) = {
            let map = Map::from_bytes(&buffer[..len]).expect("valid");
            let at = map.views.as_ptr() as usize - buffer.as_ptr() as usize;
            (at, map.observation_count())
        };
        buffer[views_at + 64..views_at + 68].copy_from_slice(&0x4000_0000u32.to_le_bytes());
        buffer[views_at + 68..views_at + 72].copy_from_slice(&0xC000_0005u32.to_le_bytes());
        reseal(&mut buffer[..len]);
        assert_eq!(
            Map::from_bytes(&buffer[..len]),
            Err(Error::MapIndexOutOfRange {
                item: MapItem::ViewPoints,
                index: usize::try_from(0x1_0000_0005u64).unwrap_or(usize::MAX),
                limit: observations,
            })
        );
    }

    #[test]
    fn encode_refuses_bad_inputs_and_small_buffers() {
        let mut buffer = [0u8; 1024];
        let bad_point = [MapViewEntry {
            points: &[7],
            ..views()[0]
        }];
        assert_eq!(
            encode(&POINTS, &cameras(), &bad_point, &mut buffer),
            Err(Error::MapIndexOutOfRange {
                item: MapItem::Point,
                index: 7,
                limit: 4
            })
        );
        let bad_camera = [MapViewEntry {
            camera_index: 2,
            ..views()[0]
        }];
        assert!(encode(&POINTS, &cameras(), &bad_camera, &mut buffer).is_err());
        let nan = [[f32::NAN, 0.0, 0.0]];
        assert_eq!(
            encode(&nan, &cameras(), &[], &mut buffer),
            Err(Error::NonFinite {
                input: Input::Points3d,
                index: 0
            })
        );
        let needed = encoded_len(POINTS.len(), 2, &views());
        assert_eq!(
            encode(&POINTS, &cameras(), &views(), &mut buffer[..needed - 1]),
            Err(Error::CapacityExceeded {
                capacity: needed - 1,
                requested: needed
            })
        );
    }

    #[test]
    fn views_near_rank_by_direction_then_distance() {
        let mut buffer = [0u8; 1024];
        let len = encode_sample(&mut buffer);
        let map = Map::from_bytes(&buffer[..len]).unwrap();
        // A prior at the first view's pose: view 0 (distance 0), then view 1 (looks 0.1 rad
        // away, centre 3 units off); view 2 looks backwards and comes last.
        let best: heapless::Vec<u32, 3> = map.views_near(&pose(0.0, 0.0), 30.0).unwrap();
        assert_eq!(best.as_slice(), &[0, 1, 2]);
        let two: heapless::Vec<u32, 2> = map.views_near(&pose(0.0, 0.0), 30.0).unwrap();
        assert_eq!(two.as_slice(), &[0, 1]);
        // With a 1-degree cone only view 0 agrees; the others follow by distance.
        let strict: heapless::Vec<u32, 3> = map.views_near(&pose(0.0, 0.0), 1.0).unwrap();
        assert_eq!(strict.as_slice(), &[0, 2, 1]);
        let bad = Pose::new(Rotation3::identity(), Vector3::new(f64::NAN, 0.0, 0.0));
        assert!(map.views_near::<3>(&bad, 30.0).is_err());
    }

    #[test]
    fn views_by_image_id_maps_ids_to_indices() {
        let mut buffer = [0u8; 1024];
        let len = encode_sample(&mut buffer);
        let map = Map::from_bytes(&buffer[..len]).unwrap();
        let views: heapless::Vec<u32, 4> = map.views_by_image_id(&[30, 10]).unwrap();
        assert_eq!(views.as_slice(), &[2, 0]);
        assert_eq!(
            map.views_by_image_id::<4>(&[10, 11]),
            Err(Error::MapUnknownImage { image_id: 11 })
        );
        assert_eq!(
            map.views_by_image_id::<1>(&[10, 20]),
            Err(Error::CapacityExceeded {
                capacity: 1,
                requested: 2
            })
        );
    }
}
