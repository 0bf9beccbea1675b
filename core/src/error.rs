//! The one error type of the core. Every variant names the exact failure and carries the
//! numbers that help the caller act on it.

use core::fmt;

use serde::{Deserialize, Serialize};

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

/// Which kind of blob an envelope error refers to (`crate::envelope`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BlobKind {
    /// A model blob (`crate::weights`).
    Model,
    /// A map blob (`crate::map`).
    Map,
    /// A view-features blob (`crate::view_features`).
    ViewFeatures,
}

impl fmt::Display for BlobKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            BlobKind::Model => "model",
            BlobKind::Map => "map",
            BlobKind::ViewFeatures => "view-features",
        })
    }
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
    /// Iterative undistortion of a keypoint did not converge within its iteration cap.
    UndistortionDidNotConverge {
        /// Index of the keypoint.
        index: usize,
    },
    /// A keypoint lies beyond the radius up to which the camera's distortion is
    /// invertible ([`crate::Camera::invertible_radius`]): its bearing would be arbitrary.
    DistortionNotInvertible {
        /// Index of the keypoint.
        index: usize,
    },
    /// A rotation that is not one: not orthonormal with determinant +1 within
    /// [`crate::pose::ROTATION_TOLERANCE`] (e.g. all zeros).
    InvalidRotation {
        /// Which input holds it.
        input: Input,
    },
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
    /// A blob shorter than its header or its declared payload.
    BlobTruncated {
        /// Which blob.
        blob: BlobKind,
        /// Bytes the blob must have.
        needed: usize,
        /// Bytes it has.
        found: usize,
    },
    /// A blob that does not start with its kind's magic bytes.
    BlobMagic {
        /// Which blob was expected.
        blob: BlobKind,
        /// The first four bytes found.
        found: [u8; 4],
    },
    /// A blob of another format version.
    BlobVersion {
        /// Which blob.
        blob: BlobKind,
        /// The version this build reads.
        expected: u16,
        /// The version in the blob.
        found: u16,
    },
    /// A header whose reserved bytes are set or that is followed by more bytes than its
    /// declared payload.
    BlobHeader {
        /// Which blob.
        blob: BlobKind,
    },
    /// A blob whose payload does not match its checksum (corrupted).
    BlobChecksum {
        /// Which blob.
        blob: BlobKind,
        /// CRC-32 stored in the header.
        stored: u32,
        /// CRC-32 of the payload as found.
        computed: u32,
    },
    /// A map payload that does not decode: bad encoding, record sizes, trailing bytes, a
    /// name outside the name list or not UTF-8.
    MapMalformed,
    /// A view-features payload that does not decode (`crate::view_features`): dimension,
    /// table or value ranges, a count above its capacity, a non-finite value, trailing
    /// bytes.
    ViewFeaturesMalformed,
    /// View features that do not belong to the map: another view count, or more points
    /// for a view than it observes.
    ViewFeaturesMismatch {
        /// The first view that does not match (the map's view count for a count mismatch).
        view: usize,
    },
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
    /// A model payload that cannot be decoded.
    ModelMalformed {
        /// Byte offset of the record that failed.
        offset: usize,
    },
    /// A model blob with another number of tensors than its configuration implies.
    TensorCount {
        /// Tensors the configuration implies.
        expected: usize,
        /// Tensors in the blob.
        found: usize,
    },
    /// A tensor of the wrong shape (rows x cols).
    TensorShape {
        /// The tensor.
        tensor: TensorName,
        /// Expected rows and columns.
        expected: [usize; 2],
        /// Rows and columns in the blob.
        found: [usize; 2],
    },
    /// A tensor byte array of the wrong length.
    TensorBytes {
        /// The tensor.
        tensor: TensorName,
        /// Which array.
        part: TensorPart,
        /// Expected bytes.
        expected: usize,
        /// Bytes in the blob.
        found: usize,
    },
    /// A configuration value outside what this build was compiled for.
    UnsupportedConfig {
        /// The field.
        field: ConfigField,
        /// Its value.
        value: u32,
        /// The largest value supported (for `heads`: the feature width it must divide).
        max: u32,
    },
    /// A non-finite or out-of-range real configuration value.
    InvalidConfigValue {
        /// The field.
        field: ConfigField,
    },
    /// A view was matched before any query was encoded.
    QueryNotEncoded,
    /// A valid query that the localizer could not localize.
    LocalizationFailed {
        /// Why.
        reason: Failure,
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
            Error::UndistortionDidNotConverge { index } => {
                write!(f, "undistortion of keypoint {index} did not converge")
            }
            Error::DistortionNotInvertible { index } => write!(
                f,
                "keypoint {index} lies beyond the radius where the camera's distortion is invertible"
            ),
            Error::InvalidRotation { input } => {
                write!(f, "{input:?}: rotation is not orthonormal")
            }
            Error::PointBehindCamera { index } => {
                write!(f, "point {index} is at or behind the camera")
            }
            Error::AllPointsBehindCamera => write!(f, "all points are at or behind the camera"),
            Error::DegenerateConfiguration => write!(f, "degenerate point configuration"),
            Error::NoPoseFound => write!(f, "no pose hypothesis found"),
            Error::BlobTruncated {
                blob,
                needed,
                found,
            } => write!(
                f,
                "{blob} blob truncated: {needed} bytes needed, {found} found"
            ),
            Error::BlobMagic { blob, found } => {
                write!(f, "not a {blob} blob: magic {found:02x?}")
            }
            Error::BlobVersion {
                blob,
                expected,
                found,
            } => write!(
                f,
                "{blob} blob format version {found}, this build reads version {expected}"
            ),
            Error::BlobHeader { blob } => write!(
                f,
                "{blob} blob header invalid (reserved bytes set or bytes after the payload)"
            ),
            Error::BlobChecksum {
                blob,
                stored,
                computed,
            } => write!(
                f,
                "{blob} blob corrupted: checksum {computed:#010x}, stored {stored:#010x}"
            ),
            Error::MapMalformed => write!(f, "malformed map payload"),
            Error::ViewFeaturesMalformed => write!(f, "malformed view-features payload"),
            Error::ViewFeaturesMismatch { view } => write!(
                f,
                "view features do not belong to this map (view {view}): build them from this map"
            ),
            Error::MapIndexOutOfRange { item, index, limit } => {
                write!(f, "map {item:?} index {index} out of range ({limit} items)")
            }
            Error::MapUnknownImage { image_id } => {
                write!(f, "the map holds no view of image {image_id}")
            }
            Error::InvalidConfig { parameter } => {
                write!(f, "invalid configuration value: {parameter}")
            }
            Error::ModelMalformed { offset } => {
                write!(f, "model blob malformed at byte {offset}")
            }
            Error::TensorCount { expected, found } => {
                write!(
                    f,
                    "model blob holds {found} tensors, configuration implies {expected}"
                )
            }
            Error::TensorShape {
                tensor,
                expected,
                found,
            } => write!(
                f,
                "tensor {tensor}: shape {}x{}, expected {}x{}",
                found[0], found[1], expected[0], expected[1]
            ),
            Error::TensorBytes {
                tensor,
                part,
                expected,
                found,
            } => write!(
                f,
                "tensor {tensor}: {part:?} has {found} bytes, expected {expected}"
            ),
            Error::UnsupportedConfig { field, value, max } => write!(
                f,
                "model configuration {field:?} = {value} not supported by this build (limit {max})"
            ),
            Error::InvalidConfigValue { field } => {
                write!(f, "model configuration {field:?} is not a valid value")
            }
            Error::QueryNotEncoded => write!(f, "no query encoded before matching a view"),
            Error::LocalizationFailed { reason } => write!(f, "localization failed: {reason}"),
        }
    }
}

impl core::error::Error for Error {}

/// Why a valid query could not be localized.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Failure {
    /// Fewer query keypoints than the matcher needs.
    TooFewKeypoints {
        /// The matcher's minimum.
        needed: usize,
        /// Keypoints given.
        found: usize,
    },
    /// No view was selected, or none had enough points in front of it to be matched.
    NoViews {
        /// Selected views skipped for having too few points.
        skipped: usize,
    },
    /// Fewer merged matches than `min_matches`.
    TooFewMatches {
        /// The configured minimum.
        needed: usize,
        /// Merged matches found.
        found: usize,
    },
    /// The best pose has fewer inliers than `min_inliers`.
    TooFewInliers {
        /// The configured minimum.
        needed: usize,
        /// Inliers of the best pose.
        found: usize,
    },
    /// The matched 3D points or keypoints are coincident or collinear.
    DegenerateMatches,
    /// RANSAC found no pose hypothesis.
    NoPoseFound,
    /// The best pose is not trusted: its confidence is below the acceptance rule's
    /// threshold ([`crate::localizer::LocalizerConfig::acceptance`]).
    LowConfidence {
        /// The pose's confidence.
        confidence: f32,
        /// The threshold.
        needed: f32,
        /// Inliers of the pose.
        inliers: usize,
    },
}

impl fmt::Display for Failure {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Failure::TooFewKeypoints { needed, found } => {
                write!(f, "too few keypoints: {found}, the matcher needs {needed}")
            }
            Failure::NoViews { skipped } => {
                write!(f, "no view to match ({skipped} skipped for too few points)")
            }
            Failure::TooFewMatches { needed, found } => {
                write!(f, "too few matches: {found}, at least {needed} needed")
            }
            Failure::TooFewInliers { needed, found } => {
                write!(f, "too few inliers: {found}, at least {needed} needed")
            }
            Failure::DegenerateMatches => write!(f, "degenerate matches (collinear points)"),
            Failure::NoPoseFound => write!(f, "RANSAC found no pose"),
            Failure::LowConfidence {
                confidence,
                needed,
                inliers,
            } => write!(
                f,
                "low confidence: {confidence:.3} < {needed:.3} ({inliers} inliers)"
            ),
        }
    }
}

/// A field of the model configuration ([`crate::weights::ModelConfig`]), named in errors.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConfigField {
    /// `feature_dim`
    FeatureDim,
    /// `encoder_blocks`
    EncoderBlocks,
    /// `classifier_dim`
    ClassifierDim,
    /// `classifier_blocks`
    ClassifierBlocks,
    /// `heads`
    Heads,
    /// `knn`
    Knn,
    /// `sinkhorn_iters`
    SinkhornIters,
    /// `sinkhorn_eps`
    SinkhornEps,
    /// `sinkhorn_stop`
    SinkhornStop,
    /// `match_threshold`
    MatchThreshold,
    /// `bin_score`
    BinScore,
}

/// Name of a tensor in errors and reports: its role and, for repeated blocks, the index.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TensorName {
    /// Role, e.g. `encoder.block.conv2`.
    pub role: &'static str,
    /// Block or layer index for repeated roles, 0 otherwise.
    pub index: u8,
}

impl fmt::Display for TensorName {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}[{}]", self.role, self.index)
    }
}

/// Which byte array of a tensor record an error refers to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TensorPart {
    /// The weight matrix.
    Weights,
    /// The int8 scales.
    Scales,
    /// The bias.
    Bias,
}
