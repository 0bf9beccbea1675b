//! The plain C structures of a query and its result, and their conversions.

use gomatch::camera::{CameraModel, MAX_PARAMS};
use gomatch::localizer::MAX_VIEWS;
use gomatch::{Camera, Localization, Pose};
use nalgebra::{Quaternion, UnitQuaternion, Vector3};

use crate::error::{failure_code, gomatch_error, gomatch_failure};

/// Most views per query (image ids, or `k` nearest to a prior).
pub const GOMATCH_MAX_VIEWS: usize = 10;
/// Most parameters of a camera model (`GOMATCH_CAMERA_OPENCV`).
pub const GOMATCH_MAX_CAMERA_PARAMS: usize = 8;

const _: () = assert!(GOMATCH_MAX_VIEWS == MAX_VIEWS && GOMATCH_MAX_CAMERA_PARAMS == MAX_PARAMS);

/// Camera models (COLMAP's ids) and their parameters, in COLMAP order.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum gomatch_camera_model {
    /// `f, cx, cy`.
    GOMATCH_CAMERA_SIMPLE_PINHOLE = 0,
    /// `fx, fy, cx, cy`.
    GOMATCH_CAMERA_PINHOLE = 1,
    /// `f, cx, cy, k`.
    GOMATCH_CAMERA_SIMPLE_RADIAL = 2,
    /// `f, cx, cy, k1, k2`.
    GOMATCH_CAMERA_RADIAL = 3,
    /// `fx, fy, cx, cy, k1, k2, p1, p2`.
    GOMATCH_CAMERA_OPENCV = 4,
}

/// A calibrated camera: a COLMAP model and its parameters (pixels).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct gomatch_camera {
    /// A `gomatch_camera_model`.
    pub model: u32,
    /// Image width in pixels (0 when unknown).
    pub width: u32,
    /// Image height in pixels (0 when unknown).
    pub height: u32,
    /// The model's parameters in COLMAP order; the entries after them are ignored.
    pub params: [f64; GOMATCH_MAX_CAMERA_PARAMS],
}

/// A rigid pose, world to camera (COLMAP's convention: `x_cam = R x_world + t`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct gomatch_pose {
    /// The rotation `R` as a unit quaternion `w, x, y, z` (`w >= 0` in results).
    pub rotation: [f64; 4],
    /// The translation `t`.
    pub translation: [f64; 3],
}

/// How `gomatch_views` selects the map's views.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum gomatch_view_selection {
    /// The views of `image_ids` (e.g. from image retrieval), in that order.
    GOMATCH_VIEWS_IMAGE_IDS = 0,
    /// The `k` views nearest to the prior pose: those looking within `max_angle_deg` of
    /// it first, each group by camera-centre distance.
    GOMATCH_VIEWS_NEAR_PRIOR = 1,
}

/// The map views a query is matched against.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct gomatch_views {
    /// A `gomatch_view_selection`.
    pub selection: u32,
    /// `GOMATCH_VIEWS_IMAGE_IDS`: how many of `image_ids` to use.
    pub image_id_count: u32,
    /// `GOMATCH_VIEWS_IMAGE_IDS`: the views' image ids.
    pub image_ids: [u32; GOMATCH_MAX_VIEWS],
    /// `GOMATCH_VIEWS_NEAR_PRIOR`: the coarse prior pose (any non-zero quaternion).
    pub prior: gomatch_pose,
    /// `GOMATCH_VIEWS_NEAR_PRIOR`: how many views, at most `GOMATCH_MAX_VIEWS`.
    pub k: u32,
    /// `GOMATCH_VIEWS_NEAR_PRIOR`: the viewing-direction cone of the first group, degrees.
    pub max_angle_deg: f64,
}

/// One query: keypoints in pixels, the camera that took them, the views to match.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct gomatch_query {
    /// Keypoint positions `x, y` in pixels (origin top-left, y down), at most the
    /// workspace's capacity (a detector's best; the caller caps).
    pub keypoints: *const [f32; 2],
    /// How many keypoints.
    pub keypoint_count: usize,
    /// The query camera.
    pub camera: gomatch_camera,
    /// The views to match against.
    pub views: gomatch_views,
}

/// The outcome of `gomatch_localize`.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct gomatch_result {
    /// Whether there is a pose.
    pub localized: bool,
    /// Why not (`GOMATCH_FAILURE_NONE` when localized).
    pub failure: gomatch_failure,
    /// The failure's threshold (see `gomatch_failure`), else 0.
    pub needed: u32,
    /// The failure's count (see `gomatch_failure`), else 0.
    pub found: u32,
    /// World to camera, when localized (else the identity).
    pub pose: gomatch_pose,
    /// The acceptance rule's confidence in the best pose, in [0, 1], also when it was
    /// refused (`GOMATCH_FAILURE_LOW_CONFIDENCE`); -1 when no pose was scored.
    pub confidence: f32,
    /// The confidence a pose needs to be accepted.
    pub min_confidence: f32,
    /// RANSAC inliers of the best pose (`gomatch_inliers` lists those of an accepted one).
    pub inliers: u32,
    /// Matches of the mutual assignment, summed over the views.
    pub matches_mutual: u32,
    /// Of them, those the classifier accepts.
    pub matches_classified: u32,
    /// After merging the views (each keypoint and each map point once).
    pub matches_merged: u32,
    /// Views matched.
    pub views_used: u32,
    /// Selected views skipped for having too few points in front of them.
    pub views_skipped: u32,
    /// RANSAC minimal samples drawn.
    pub ransac_iterations: u32,
}

/// One inlier of an accepted pose.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct gomatch_inlier {
    /// Index of the query keypoint.
    pub keypoint: u32,
    /// Index of the map's 3D point.
    pub point: u32,
    /// The classifier's match probability.
    pub probability: f32,
}

/// A `u32` count or index, saturated.
pub(crate) fn narrow(v: usize) -> u32 {
    u32::try_from(v).unwrap_or(u32::MAX)
}

impl gomatch_pose {
    /// The identity pose.
    pub(crate) const IDENTITY: Self = gomatch_pose {
        rotation: [1.0, 0.0, 0.0, 0.0],
        translation: [0.0; 3],
    };

    /// The pose of a core `Pose` (its quaternion with `w >= 0`).
    pub(crate) fn from_pose(pose: &Pose) -> Self {
        let q = UnitQuaternion::from_rotation_matrix(&pose.rotation);
        let sign = if q.w < 0.0 { -1.0 } else { 1.0 };
        let t = pose.translation;
        gomatch_pose {
            rotation: [sign * q.w, sign * q.i, sign * q.j, sign * q.k],
            translation: [t.x, t.y, t.z],
        }
    }

    /// The core `Pose` of a prior: finite values and a non-zero quaternion, else
    /// `GOMATCH_ERROR_INVALID_PRIOR`.
    pub(crate) fn to_prior(self) -> Result<Pose, gomatch_error> {
        let [w, x, y, z] = self.rotation;
        let norm2 = w * w + x * x + y * y + z * z;
        let finite = self
            .rotation
            .iter()
            .chain(&self.translation)
            .all(|v| v.is_finite());
        if !finite || norm2 <= 1e-24 || !norm2.is_finite() {
            return Err(gomatch_error::GOMATCH_ERROR_INVALID_PRIOR);
        }
        let rotation = UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z));
        let [tx, ty, tz] = self.translation;
        Ok(Pose::new(
            rotation.to_rotation_matrix(),
            Vector3::new(tx, ty, tz),
        ))
    }
}

impl gomatch_camera {
    /// The core camera, or `GOMATCH_ERROR_INVALID_CAMERA`.
    pub(crate) fn to_camera(self) -> Result<Camera, gomatch_error> {
        let invalid = gomatch_error::GOMATCH_ERROR_INVALID_CAMERA;
        let id = i32::try_from(self.model).map_err(|_| invalid)?;
        let model = CameraModel::from_colmap_id(id).map_err(|_| invalid)?;
        let params = self.params.get(..model.param_count()).ok_or(invalid)?;
        Camera::from_colmap(model, self.width, self.height, params).map_err(|_| invalid)
    }
}

impl gomatch_result {
    /// A result without a pose or counts (what an error leaves).
    pub(crate) const EMPTY: Self = gomatch_result {
        localized: false,
        failure: gomatch_failure::GOMATCH_FAILURE_NONE,
        needed: 0,
        found: 0,
        pose: gomatch_pose::IDENTITY,
        confidence: -1.0,
        min_confidence: 0.0,
        inliers: 0,
        matches_mutual: 0,
        matches_classified: 0,
        matches_merged: 0,
        views_used: 0,
        views_skipped: 0,
        ransac_iterations: 0,
    };

    /// The result of a localization with the acceptance threshold `min_confidence`.
    pub(crate) fn from_localization(l: &Localization, min_confidence: f32) -> Self {
        let (localized, failure, needed, found, pose) = match &l.outcome {
            Ok(pose) => (
                true,
                gomatch_failure::GOMATCH_FAILURE_NONE,
                0,
                0,
                gomatch_pose::from_pose(pose),
            ),
            Err(reason) => {
                let (code, needed, found) = failure_code(reason);
                (false, code, needed, found, gomatch_pose::IDENTITY)
            }
        };
        gomatch_result {
            localized,
            failure,
            needed: narrow(needed),
            found: narrow(found),
            pose,
            confidence: l.confidence.unwrap_or(-1.0),
            min_confidence,
            inliers: narrow(l.counts.inliers),
            matches_mutual: narrow(l.counts.mutual),
            matches_classified: narrow(l.counts.classified),
            matches_merged: narrow(l.counts.merged),
            views_used: narrow(l.views_used),
            views_skipped: narrow(l.views_skipped),
            ransac_iterations: l.ransac_iterations,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pose_round_trips_through_its_quaternion() {
        let prior = gomatch_pose {
            rotation: [0.3, -0.5, 0.1, 0.8],
            translation: [1.0, -2.0, 3.5],
        };
        let pose = prior.to_prior().expect("valid");
        let back = gomatch_pose::from_pose(&pose);
        let norm = (0.09f64 + 0.25 + 0.01 + 0.64).sqrt();
        for (a, b) in back.rotation.iter().zip(prior.rotation) {
            assert!((a - b / norm).abs() < 1e-12, "{back:?}");
        }
        assert_eq!(back.translation, prior.translation);
        // The quaternion of a result has w >= 0: -q is the same rotation.
        let negated = gomatch_pose {
            rotation: prior.rotation.map(|v| -v),
            ..prior
        };
        let same = gomatch_pose::from_pose(&negated.to_prior().expect("valid"));
        assert!(same.rotation[0] > 0.0);
        for (a, b) in same.rotation.iter().zip(back.rotation) {
            assert!((a - b).abs() < 1e-12);
        }
    }

    #[test]
    fn invalid_priors_and_cameras_are_refused() {
        let bad = [
            [0.0, 0.0, 0.0, 0.0],
            [f64::NAN, 0.0, 0.0, 1.0],
            [1e300, 1e300, 0.0, 0.0],
        ];
        for rotation in bad {
            let prior = gomatch_pose {
                rotation,
                translation: [0.0; 3],
            };
            assert_eq!(
                prior.to_prior().map(|_| ()),
                Err(gomatch_error::GOMATCH_ERROR_INVALID_PRIOR)
            );
        }
        let camera = |model, f| gomatch_camera {
            model,
            width: 640,
            height: 480,
            params: [f, 320.0, 240.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        };
        assert!(camera(0, 500.0).to_camera().is_ok());
        for (model, f) in [(5, 500.0), (u32::MAX, 500.0), (0, -1.0), (2, f64::INFINITY)] {
            assert_eq!(
                camera(model, f).to_camera(),
                Err(gomatch_error::GOMATCH_ERROR_INVALID_CAMERA)
            );
        }
    }
}
