//! The one error type of the core. Every variant names the exact failure and carries the
//! numbers that help the caller act on it.

use core::fmt;

/// Which input an error refers to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Input {
    /// Query keypoints (pixels or bearing vectors).
    Keypoints,
    /// 3D points.
    Points3d,
    /// Camera intrinsics or distortion parameters.
    Intrinsics,
    /// A pose (rotation or translation).
    Pose,
}

/// Which part of a map an index refers to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MapItem {
    /// A 3D point.
    Point,
    /// A camera (intrinsics).
    Camera,
    /// A database view.
    View,
    /// The list of observed point indices of the views.
    ViewPoints,
}

/// Every way the core can refuse its input.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub enum Error {
    /// Fewer items than the algorithm needs.
    TooFewPoints {
        /// Minimum the algorithm needs.
        needed: usize,
        /// What the caller passed.
        found: usize,
    },
    /// More items than the compiled capacity holds.
    CapacityExceeded {
        /// The compiled capacity.
        capacity: usize,
        /// What the caller asked for.
        requested: usize,
    },
    /// Two inputs that must have the same length do not.
    LengthMismatch {
        /// Length of the first input.
        left: usize,
        /// Length of the second input.
        right: usize,
    },
    /// A NaN or infinite value.
    NonFinite {
        /// Which input holds it.
        input: Input,
        /// Index of the offending item.
        index: usize,
    },
    /// Intrinsics that cannot describe a camera (non-positive focal length, unknown model,
    /// wrong parameter count).
    InvalidIntrinsics,
    /// Iterative undistortion did not converge within its iteration cap.
    UndistortionDidNotConverge,
    /// A 3D point lies at or behind the camera plane (z <= 0).
    PointBehindCamera {
        /// Index of the point.
        index: usize,
    },
    /// Every 3D point lies at or behind the camera.
    AllPointsBehindCamera,
    /// The points are in a degenerate configuration (coincident or collinear).
    DegenerateConfiguration,
    /// No pose hypothesis was supported by enough inliers.
    NoPoseFound,
    /// A map blob shorter than its header or its declared payload.
    MapTruncated {
        /// Bytes the blob must have.
        needed: usize,
        /// Bytes it has.
        found: usize,
    },
    /// A blob that does not start with the map magic bytes.
    MapBadMagic,
    /// A map blob of another format version.
    MapVersionMismatch {
        /// The version this code reads.
        expected: u16,
        /// The version in the blob.
        found: u16,
    },
    /// A map blob whose payload does not match its checksum.
    MapChecksumMismatch {
        /// Checksum stored in the header.
        stored: u32,
        /// Checksum of the payload as found.
        computed: u32,
    },
    /// A map payload that does not decode: bad encoding, record sizes, trailing bytes.
    MapCorrupt,
    /// An index into a map (or a reference inside it) beyond the end of what it indexes.
    MapIndexOutOfRange {
        /// What the index refers to.
        item: MapItem,
        /// The index.
        index: usize,
        /// The number of items.
        limit: usize,
    },
    /// An image id the map holds no view for.
    MapUnknownImage {
        /// The unknown id.
        image_id: u32,
    },
    /// A configuration value is out of its valid range.
    InvalidConfig {
        /// Name of the offending parameter.
        parameter: &'static str,
    },
}

/// Result with the core's [`Error`].
pub type Result<T> = core::result::Result<T, Error>;

impl fmt::Display for Error {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Error::TooFewPoints { needed, found } => {
                write!(f, "too few points: need at least {needed}, got {found}")
            }
            Error::CapacityExceeded {
                capacity,
                requested,
            } => write!(
                f,
                "capacity exceeded: {requested} requested, compiled capacity {capacity} ({} over)",
                requested.saturating_sub(capacity)
            ),
            Error::LengthMismatch { left, right } => {
                write!(f, "inputs of different lengths: {left} vs {right}")
            }
            Error::NonFinite { input, index } => {
                write!(f, "non-finite value in {input:?} at index {index}")
            }
            Error::InvalidIntrinsics => write!(f, "invalid camera intrinsics"),
            Error::UndistortionDidNotConverge => write!(f, "undistortion did not converge"),
            Error::PointBehindCamera { index } => {
                write!(f, "point {index} is at or behind the camera")
            }
            Error::AllPointsBehindCamera => write!(f, "all points are at or behind the camera"),
            Error::DegenerateConfiguration => write!(f, "degenerate point configuration"),
            Error::NoPoseFound => write!(f, "no pose hypothesis found"),
            Error::MapTruncated { needed, found } => {
                write!(
                    f,
                    "map blob truncated: {needed} bytes needed, {found} found"
                )
            }
            Error::MapBadMagic => write!(f, "not a map blob (bad magic bytes)"),
            Error::MapVersionMismatch { expected, found } => {
                write!(f, "map format version {found}, expected {expected}")
            }
            Error::MapChecksumMismatch { stored, computed } => write!(
                f,
                "map checksum mismatch: stored {stored:#010x}, computed {computed:#010x}"
            ),
            Error::MapCorrupt => write!(f, "corrupt map payload"),
            Error::MapIndexOutOfRange { item, index, limit } => {
                write!(f, "map {item:?} index {index} out of range ({limit} items)")
            }
            Error::MapUnknownImage { image_id } => {
                write!(f, "the map holds no view of image {image_id}")
            }
            Error::InvalidConfig { parameter } => {
                write!(f, "invalid configuration value: {parameter}")
            }
        }
    }
}

impl core::error::Error for Error {}
