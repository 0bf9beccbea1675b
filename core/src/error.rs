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
            Error::InvalidConfig { parameter } => {
                write!(f, "invalid configuration value: {parameter}")
            }
        }
    }
}

impl core::error::Error for Error {}
