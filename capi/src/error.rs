//! Status codes and failure reasons, and their texts.

use core::ffi::c_char;

use gomatch::error::{Error, Input};
use gomatch::Failure;

/// What a function did: `GOMATCH_OK`, or why it refused (nothing was changed then, apart
/// from the outputs the function documents).
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum gomatch_error {
    /// Success.
    GOMATCH_OK = 0,
    /// A required pointer is NULL.
    GOMATCH_ERROR_NULL_POINTER = 1,
    /// A pointer is not aligned for its type (the workspace: `GOMATCH_LOCALIZER_ALIGN`).
    GOMATCH_ERROR_MISALIGNED = 2,
    /// An enumeration argument out of range, or a length above `PTRDIFF_MAX`.
    GOMATCH_ERROR_INVALID_ARGUMENT = 3,
    /// A workspace capacity this library was not built for (see
    /// `gomatch_localizer_bytes`).
    GOMATCH_ERROR_UNSUPPORTED_CAPACITY = 4,
    /// The workspace is smaller than `gomatch_localizer_bytes(capacity)`.
    GOMATCH_ERROR_WORKSPACE_TOO_SMALL = 5,
    /// A model, map or workspace that was never opened or initialised.
    GOMATCH_ERROR_NOT_INITIALIZED = 6,
    /// An output buffer too small for what is to be written (the size needed is reported).
    GOMATCH_ERROR_BUFFER_TOO_SMALL = 7,
    /// No localization to report: the workspace has not localized since it was initialised,
    /// or its last call was refused before the query was read.
    GOMATCH_ERROR_NO_RESULT = 8,
    /// A blob shorter than its header or its declared payload.
    GOMATCH_ERROR_BLOB_TRUNCATED = 10,
    /// A blob of another kind (its magic bytes are not the model's or the map's).
    GOMATCH_ERROR_BLOB_MAGIC = 11,
    /// A blob of another format version than this library reads.
    GOMATCH_ERROR_BLOB_VERSION = 12,
    /// A blob header with reserved bytes set, or bytes after the declared payload.
    GOMATCH_ERROR_BLOB_HEADER = 13,
    /// A blob whose payload does not match its checksum (corrupted).
    GOMATCH_ERROR_BLOB_CHECKSUM = 14,
    /// A blob payload that does not decode, or whose content is invalid.
    GOMATCH_ERROR_BLOB_MALFORMED = 15,
    /// A model whose configuration exceeds what this library was compiled for.
    GOMATCH_ERROR_MODEL_UNSUPPORTED = 16,
    /// More keypoints than the workspace's capacity.
    GOMATCH_ERROR_TOO_MANY_KEYPOINTS = 20,
    /// A keypoint with a NaN or infinite coordinate.
    GOMATCH_ERROR_NON_FINITE_KEYPOINT = 21,
    /// An unknown camera model, non-finite parameters or a non-positive focal length.
    GOMATCH_ERROR_INVALID_CAMERA = 22,
    /// A keypoint beyond the radius where the camera's distortion can be inverted.
    GOMATCH_ERROR_DISTORTION_NOT_INVERTIBLE = 23,
    /// The undistortion of a keypoint did not converge.
    GOMATCH_ERROR_UNDISTORTION_FAILED = 24,
    /// More than `GOMATCH_MAX_VIEWS` views (image ids, or `k`).
    GOMATCH_ERROR_TOO_MANY_VIEWS = 25,
    /// An image id the map holds no view of.
    GOMATCH_ERROR_UNKNOWN_IMAGE = 26,
    /// A prior pose with a non-finite value or a zero quaternion, or a non-finite or
    /// negative `max_angle_deg`.
    GOMATCH_ERROR_INVALID_PRIOR = 27,
    /// An error the API does not expect from the core (a bug: please report it).
    GOMATCH_ERROR_INTERNAL = 99,
}

use gomatch_error::*;

/// Why a valid query was not localized (`gomatch_result.failure`).
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum gomatch_failure {
    /// Localized: there is a pose.
    GOMATCH_FAILURE_NONE = 0,
    /// Fewer keypoints than the matcher needs (`needed`, `found`).
    GOMATCH_FAILURE_TOO_FEW_KEYPOINTS = 1,
    /// No view to match: none selected, or all had too few points in front of them
    /// (`found`: views skipped).
    GOMATCH_FAILURE_NO_VIEWS = 2,
    /// Fewer merged matches than the pose solver needs (`needed`, `found`).
    GOMATCH_FAILURE_TOO_FEW_MATCHES = 3,
    /// The best pose has too few inliers (`needed`, `found`).
    GOMATCH_FAILURE_TOO_FEW_INLIERS = 4,
    /// The matched points or keypoints are coincident or collinear.
    GOMATCH_FAILURE_DEGENERATE_MATCHES = 5,
    /// RANSAC found no pose.
    GOMATCH_FAILURE_NO_POSE_FOUND = 6,
    /// A pose was found but its confidence is below the acceptance threshold
    /// (`confidence` < `min_confidence`; `found`: its inliers).
    GOMATCH_FAILURE_LOW_CONFIDENCE = 7,
}

/// A failure as its code and its two counts (`needed`, `found`).
pub(crate) fn failure_code(failure: &Failure) -> (gomatch_failure, usize, usize) {
    use gomatch_failure::*;
    match *failure {
        Failure::TooFewKeypoints { needed, found } => {
            (GOMATCH_FAILURE_TOO_FEW_KEYPOINTS, needed, found)
        }
        Failure::NoViews { skipped } => (GOMATCH_FAILURE_NO_VIEWS, 0, skipped),
        Failure::TooFewMatches { needed, found } => {
            (GOMATCH_FAILURE_TOO_FEW_MATCHES, needed, found)
        }
        Failure::TooFewInliers { needed, found } => {
            (GOMATCH_FAILURE_TOO_FEW_INLIERS, needed, found)
        }
        Failure::DegenerateMatches => (GOMATCH_FAILURE_DEGENERATE_MATCHES, 0, 0),
        Failure::NoPoseFound => (GOMATCH_FAILURE_NO_POSE_FOUND, 0, 0),
        Failure::LowConfidence { inliers, .. } => (GOMATCH_FAILURE_LOW_CONFIDENCE, 0, inliers),
    }
}

/// The code of an error of `gomatch::Model::from_bytes` or `gomatch::Map::from_bytes`.
pub(crate) fn blob_error(error: &Error) -> gomatch_error {
    match error {
        Error::BlobTruncated { .. } => GOMATCH_ERROR_BLOB_TRUNCATED,
        Error::BlobMagic { .. } => GOMATCH_ERROR_BLOB_MAGIC,
        Error::BlobVersion { .. } => GOMATCH_ERROR_BLOB_VERSION,
        Error::BlobHeader { .. } => GOMATCH_ERROR_BLOB_HEADER,
        Error::BlobChecksum { .. } => GOMATCH_ERROR_BLOB_CHECKSUM,
        Error::UnsupportedConfig { .. } => GOMATCH_ERROR_MODEL_UNSUPPORTED,
        // The payload's content: undecodable records, shapes, indices, cameras, values.
        _ => GOMATCH_ERROR_BLOB_MALFORMED,
    }
}

/// The code of an error of `gomatch::Localizer::localize` on a query the API has checked
/// (keypoint and view counts, camera model, prior).
pub(crate) fn query_error(error: &Error) -> gomatch_error {
    match error {
        Error::NonFinite {
            input: Input::Keypoints,
            ..
        } => GOMATCH_ERROR_NON_FINITE_KEYPOINT,
        Error::InvalidIntrinsics => GOMATCH_ERROR_INVALID_CAMERA,
        Error::DistortionNotInvertible { .. } => GOMATCH_ERROR_DISTORTION_NOT_INVERTIBLE,
        Error::UndistortionDidNotConverge { .. } => GOMATCH_ERROR_UNDISTORTION_FAILED,
        Error::MapUnknownImage { .. } => GOMATCH_ERROR_UNKNOWN_IMAGE,
        Error::NonFinite {
            input: Input::Pose, ..
        }
        | Error::InvalidRotation { .. } => GOMATCH_ERROR_INVALID_PRIOR,
        _ => GOMATCH_ERROR_INTERNAL,
    }
}

/// The text of a `gomatch_error` (a static, zero-terminated string; "unknown error" for a
/// value that is none).
#[no_mangle]
pub extern "C" fn gomatch_error_str(error: u32) -> *const c_char {
    let text = match error {
        0 => c"success",
        1 => c"a required pointer is NULL",
        2 => c"a pointer is not aligned for its type",
        3 => c"an enumeration argument out of range, or a length above PTRDIFF_MAX",
        4 => c"this library was not built for that workspace capacity",
        5 => c"the workspace is smaller than gomatch_localizer_bytes(capacity)",
        6 => c"model, map or workspace not opened or initialised",
        7 => c"output buffer too small",
        8 => c"no localization to report",
        10 => c"blob truncated",
        11 => c"not a blob of this kind (magic bytes)",
        12 => c"blob of another format version",
        13 => c"blob header invalid (reserved bytes set or bytes after the payload)",
        14 => c"blob corrupted (checksum)",
        15 => c"blob payload malformed",
        16 => c"model configuration not supported by this build",
        20 => c"more keypoints than the workspace's capacity",
        21 => c"non-finite keypoint",
        22 => c"invalid camera (model, parameters or focal length)",
        23 => c"keypoint beyond the radius where the camera's distortion is invertible",
        24 => c"undistortion of a keypoint did not converge",
        25 => c"more views than GOMATCH_MAX_VIEWS",
        26 => c"the map holds no view of that image id",
        27 => c"invalid prior pose or viewing angle",
        99 => c"internal error (a bug: please report it)",
        _ => c"unknown error",
    };
    text.as_ptr()
}

/// The text of a `gomatch_failure` (a static, zero-terminated string; "unknown failure"
/// for a value that is none).
#[no_mangle]
pub extern "C" fn gomatch_failure_str(failure: u32) -> *const c_char {
    let text = match failure {
        0 => c"localized",
        1 => c"too few keypoints",
        2 => c"no view to match",
        3 => c"too few matches",
        4 => c"too few inliers",
        5 => c"degenerate matches (collinear points)",
        6 => c"RANSAC found no pose",
        7 => c"low confidence",
        _ => c"unknown failure",
    };
    text.as_ptr()
}

/// `pointer` when it is non-null and aligned for `T`.
pub(crate) fn checked<T>(pointer: *const T) -> Result<core::ptr::NonNull<T>, gomatch_error> {
    let Some(pointer) = core::ptr::NonNull::new(pointer.cast_mut()) else {
        return Err(gomatch_error::GOMATCH_ERROR_NULL_POINTER);
    };
    if !pointer.is_aligned() {
        return Err(gomatch_error::GOMATCH_ERROR_MISALIGNED);
    }
    Ok(pointer)
}

#[cfg(test)]
mod tests {
    use super::*;
    use core::ffi::CStr;
    use gomatch::error::BlobKind;

    fn text(p: *const c_char) -> &'static str {
        // SAFETY: the functions return pointers to static C string literals.
        unsafe { CStr::from_ptr(p) }.to_str().expect("ASCII")
    }

    #[test]
    fn every_code_has_its_own_text() {
        let codes = [
            0u32, 1, 2, 3, 4, 5, 6, 7, 8, 10, 11, 12, 13, 14, 15, 16, 20, 21, 22, 23, 24, 25, 26,
            27, 99,
        ];
        let texts: std::collections::BTreeSet<_> =
            codes.iter().map(|&c| text(gomatch_error_str(c))).collect();
        assert_eq!(texts.len(), codes.len());
        assert!(!texts.contains("unknown error"));
        assert_eq!(text(gomatch_error_str(9)), "unknown error");
        assert_eq!(text(gomatch_error_str(u32::MAX)), "unknown error");
        let failures: std::collections::BTreeSet<_> =
            (0..8).map(|c| text(gomatch_failure_str(c))).collect();
        assert_eq!(failures.len(), 8);
        assert_eq!(text(gomatch_failure_str(8)), "unknown failure");
        assert_eq!(
            gomatch_error_str(GOMATCH_ERROR_INTERNAL as u32),
            gomatch_error_str(99)
        );
    }

    /// The errors the API cannot meet through its own checks map to `INTERNAL`; a C test
    /// cannot reach them, so they are checked here.
    #[test]
    fn errors_the_checks_exclude_are_internal() {
        let unexpected = [
            Error::QueryNotEncoded,
            Error::CapacityExceeded {
                capacity: 10,
                requested: 11,
            },
            Error::LengthMismatch { left: 1, right: 2 },
            Error::InvalidConfig {
                parameter: "threshold",
            },
        ];
        for e in unexpected {
            assert_eq!(query_error(&e), GOMATCH_ERROR_INTERNAL, "{e:?}");
        }
        assert_eq!(
            blob_error(&Error::BlobHeader {
                blob: BlobKind::Map
            }),
            GOMATCH_ERROR_BLOB_HEADER
        );
        assert_eq!(
            blob_error(&Error::MapMalformed),
            GOMATCH_ERROR_BLOB_MALFORMED
        );
    }
}
