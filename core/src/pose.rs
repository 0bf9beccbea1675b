//! Rigid camera pose in the COLMAP convention: world to camera, `x_cam = R x_world + t`.

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};

use crate::error::{Error, Input, Result};

/// A world-to-camera rigid transform, `x_cam = R x_world + t` (COLMAP convention).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    /// Rotation from world to camera axes.
    pub rotation: Rotation3<f64>,
    /// Translation: the world origin expressed in camera coordinates.
    pub translation: Vector3<f64>,
}

impl Default for Pose {
    fn default() -> Self {
        Self::identity()
    }
}

impl Pose {
    /// The identity transform.
    pub fn identity() -> Self {
        Self {
            rotation: Rotation3::identity(),
            translation: Vector3::zeros(),
        }
    }

    /// Pose from a rotation and a translation.
    pub fn new(rotation: Rotation3<f64>, translation: Vector3<f64>) -> Self {
        Self {
            rotation,
            translation,
        }
    }

    /// Pose from a row-major 3x3 rotation matrix, re-orthonormalised, and a translation.
    /// Fails on non-finite values ([`Error::NonFinite`]) and on a matrix that is no rotation
    /// up to the rounding of a stored file (`|R^T R - I| > STORED_ROTATION_TOLERANCE` per entry
    /// or a non-positive determinant: [`Error::InvalidRotation`]), and its re-orthonormalisation
    /// takes at most [`MAX_ORTHONORMALISATION_STEPS`] iterations.
    pub fn from_matrix(r: &[[f64; 3]; 3], t: &[f64; 3]) -> Result<Self> {
        let finite = r.iter().flatten().chain(t.iter()).all(|v| v.is_finite());
        if !finite {
            return Err(Error::NonFinite {
                input: Input::Pose,
                index: 0,
            });
        }
        let m = Matrix3::from_fn(|i, j| r[i][j]);
        let gram = m.transpose() * m - Matrix3::identity();
        if gram.amax() > STORED_ROTATION_TOLERANCE || m.determinant() <= 0.0 {
            return Err(Error::InvalidRotation { input: Input::Pose });
        }
        let rotation = Rotation3::from_matrix_eps(
            &m,
            f64::EPSILON,
            MAX_ORTHONORMALISATION_STEPS,
            Rotation3::identity(),
        );
        Ok(Self::new(rotation, Vector3::new(t[0], t[1], t[2])))
    }

    /// Pose from COLMAP's `QW QX QY QZ TX TY TZ`. Fails on non-finite values or a zero
    /// quaternion.
    pub fn from_colmap(q: [f64; 4], t: [f64; 3]) -> Result<Self> {
        let norm2: f64 = q.iter().map(|v| v * v).sum();
        let finite = q.iter().chain(t.iter()).all(|v| v.is_finite());
        if !finite || norm2 < 1e-24 {
            return Err(Error::NonFinite {
                input: Input::Pose,
                index: 0,
            });
        }
        let quat = nalgebra::Quaternion::new(q[0], q[1], q[2], q[3]);
        let rotation = UnitQuaternion::from_quaternion(quat).to_rotation_matrix();
        Ok(Self::new(rotation, Vector3::new(t[0], t[1], t[2])))
    }

    /// Checks a pose built field by field: finite values ([`Error::NonFinite`]) and a
    /// rotation matrix `R` with `|R^T R - I| <= ROTATION_TOLERANCE` per entry and a
    /// positive determinant ([`Error::InvalidRotation`]).
    pub fn check(&self) -> Result<()> {
        let r = self.rotation.matrix();
        if !r
            .iter()
            .chain(self.translation.iter())
            .all(|v| v.is_finite())
        {
            return Err(Error::NonFinite {
                input: Input::Pose,
                index: 0,
            });
        }
        let gram = r.transpose() * r - Matrix3::identity();
        if gram.amax() > ROTATION_TOLERANCE || r.determinant() <= 0.0 {
            return Err(Error::InvalidRotation { input: Input::Pose });
        }
        Ok(())
    }

    /// Maps a world point into camera coordinates.
    pub fn transform(&self, x_world: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * x_world + self.translation
    }

    /// Composition `self ∘ other`: first `other`, then `self`.
    pub fn compose(&self, other: &Pose) -> Pose {
        Pose::new(
            self.rotation * other.rotation,
            self.rotation * other.translation + self.translation,
        )
    }

    /// The inverse transform (camera to world).
    pub fn inverse(&self) -> Pose {
        let r_inv = self.rotation.inverse();
        Pose::new(r_inv, -(r_inv * self.translation))
    }

    /// Camera centre in world coordinates, `-R^T t`.
    pub fn center(&self) -> Vector3<f64> {
        -(self.rotation.inverse() * self.translation)
    }

    /// Viewing direction (the camera's +z axis) in world coordinates.
    pub fn viewing_direction(&self) -> Vector3<f64> {
        self.rotation.inverse() * Vector3::z()
    }

    /// Angle in degrees of the relative rotation between two poses.
    pub fn rotation_error_deg(&self, other: &Pose) -> f64 {
        let relative = self.rotation * other.rotation.inverse();
        let cos = ((relative.matrix().trace() - 1.0) * 0.5).clamp(-1.0, 1.0);
        libm::acos(cos).to_degrees()
    }

    /// Euclidean distance between the translation vectors.
    pub fn translation_error(&self, other: &Pose) -> f64 {
        (self.translation - other.translation).norm()
    }

    /// Euclidean distance between the camera centres.
    pub fn center_error(&self, other: &Pose) -> f64 {
        (self.center() - other.center()).norm()
    }

    /// Bearing vector of a world point seen from this camera (paper eq. 1):
    /// `p' = R p + t`, `[b 1] = p' / p'_z`. Points at or behind the camera plane
    /// (`p'_z <= 0`) are reported as [`Error::PointBehindCamera`] with the given index.
    /// This is the bare projection: whether a scene point's bearing is meaningful (not at
    /// the camera centre, not far off axis) is [`ProjectionRule`]'s call.
    pub fn bearing(&self, x_world: &Vector3<f64>, index: usize) -> Result<[f64; 2]> {
        camera_bearing(&self.transform(x_world)).ok_or(Error::PointBehindCamera { index })
    }
}

/// The bearing `(x / z, y / z)` of a point in camera coordinates; `None` when it is not
/// in front of the camera or not finite.
pub fn camera_bearing(p: &Vector3<f64>) -> Option<[f64; 2]> {
    if p.z <= 0.0 || !p.z.is_finite() || !p.x.is_finite() || !p.y.is_finite() {
        return None;
    }
    Some([p.x / p.z, p.y / p.z])
}

/// Largest deviation of `R^T R` from the identity, per entry, that [`Pose::check`]
/// accepts as a rotation (poses stored in `f64` deviate by about 1e-15).
pub const ROTATION_TOLERANCE: f64 = 1e-6;

/// How far from orthonormal a rotation read from a file may be ([`Pose::from_matrix`]): files
/// store rotations with a few decimals, so this is looser than [`ROTATION_TOLERANCE`].
pub const STORED_ROTATION_TOLERANCE: f64 = 1e-3;

/// Iterations of the re-orthonormalisation in [`Pose::from_matrix`] (nalgebra's
/// `Rotation3::from_matrix_eps`, from the identity): a bound, far above what a matrix within
/// [`STORED_ROTATION_TOLERANCE`] needs.
pub const MAX_ORTHONORMALISATION_STEPS: usize = 10_000;

/// Smallest depth of a usable projection, as a fraction of the camera's reference depth
/// (the median depth of the points it observes); see [`ProjectionRule`].
pub const MIN_DEPTH_RATIO: f64 = 1e-5;

/// Largest bearing coordinate, `|x/z|` and `|y/z|`, of a usable projection: 84.3 degrees
/// off the optical axis, beyond the field of view of the camera models supported.
pub const MAX_BEARING: f64 = 10.0;

/// Why a world point has no usable bearing in a camera.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Unusable {
    /// At or behind the camera plane, or a non-finite position.
    Behind,
    /// In front, but closer than the rule's minimum depth: at the camera centre, where a
    /// bearing is arbitrary and moves by any amount with a tiny change of pose.
    TooClose,
    /// Beyond [`MAX_BEARING`] off the optical axis.
    OffAxis,
}

/// The one rule that turns a world point into a bearing in a camera (paper eq. 1), shared
/// by the localizer's view bearings, the protocol's ground truth and the reprojection
/// metric: the point's depth must be at least [`MIN_DEPTH_RATIO`] times the camera's
/// reference depth (the median depth of the points it observes, so the rule holds at any
/// scene scale), and both bearing coordinates at most [`MAX_BEARING`]. A point failing it
/// is skipped, never turned into a bearing: SfM models hold points triangulated at a
/// camera's centre, whose bearing is arbitrary.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProjectionRule {
    min_depth: f64,
}

impl ProjectionRule {
    /// The rule of a camera whose reference depth is `reference_depth`; one that is not
    /// positive and finite (a camera that sees no point) accepts no point.
    pub fn with_reference_depth(reference_depth: f64) -> Self {
        let usable = reference_depth > 0.0 && reference_depth.is_finite();
        Self {
            min_depth: if usable {
                MIN_DEPTH_RATIO * reference_depth
            } else {
                f64::INFINITY
            },
        }
    }

    /// The rule of the camera at `pose` that observes `points`: its reference depth is
    /// the median (the upper middle one for an even count) of the depths of the first
    /// `depths.len()` points in front of it; `depths` is scratch space.
    pub fn of_camera(
        pose: &Pose,
        points: impl Iterator<Item = [f64; 3]>,
        depths: &mut [f64],
    ) -> Self {
        let in_front = points
            .map(|[x, y, z]| pose.transform(&Vector3::new(x, y, z)).z)
            .filter(|depth| *depth > 0.0 && depth.is_finite());
        let mut len = 0;
        for (slot, depth) in depths.iter_mut().zip(in_front) {
            *slot = depth;
            len += 1;
        }
        let found = depths.get_mut(..len).unwrap_or(&mut []);
        if found.is_empty() {
            return Self::with_reference_depth(0.0);
        }
        let (_, median, _) = found.select_nth_unstable_by(len / 2, f64::total_cmp);
        Self::with_reference_depth(*median)
    }

    /// Smallest depth of a usable point, in world units (infinite when none is usable).
    pub fn min_depth(&self) -> f64 {
        self.min_depth
    }

    /// The bearing of `x_world` in the camera at `pose` when the rule allows it.
    pub fn bearing(
        &self,
        pose: &Pose,
        x_world: &Vector3<f64>,
    ) -> core::result::Result<[f64; 2], Unusable> {
        let p = pose.transform(x_world);
        if !(p.z > 0.0 && p.iter().all(|v| v.is_finite())) {
            return Err(Unusable::Behind);
        }
        if p.z < self.min_depth {
            return Err(Unusable::TooClose);
        }
        let bearing = [p.x / p.z, p.y / p.z];
        if bearing.iter().all(|b| b.abs() <= MAX_BEARING) {
            Ok(bearing)
        } else {
            Err(Unusable::OffAxis)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample_pose() -> Pose {
        Pose::new(
            Rotation3::from_euler_angles(0.1, -0.4, 0.7),
            Vector3::new(0.3, -1.0, 2.0),
        )
    }

    #[test]
    fn inverse_composes_to_identity() {
        let pose = sample_pose();
        let identity = pose.compose(&pose.inverse());
        assert!(identity.rotation_error_deg(&Pose::identity()) < 1e-9);
        assert!(identity.translation.norm() < 1e-12);
    }

    #[test]
    fn center_maps_to_camera_origin() {
        let pose = sample_pose();
        assert!(pose.transform(&pose.center()).norm() < 1e-12);
    }

    #[test]
    fn bearing_divides_by_depth_and_rejects_points_behind() {
        let pose = Pose::identity();
        assert_eq!(
            pose.bearing(&Vector3::new(1.0, 2.0, 4.0), 0),
            Ok([0.25, 0.5])
        );
        assert_eq!(
            pose.bearing(&Vector3::new(1.0, 2.0, 0.0), 3),
            Err(Error::PointBehindCamera { index: 3 })
        );
        assert_eq!(
            pose.bearing(&Vector3::new(1.0, 2.0, -1.0), 4),
            Err(Error::PointBehindCamera { index: 4 })
        );
    }

    #[test]
    fn projection_rule_skips_points_at_the_centre_and_far_off_axis() {
        let pose = sample_pose();
        let in_camera = |x: f64, y: f64, z: f64| pose.inverse().transform(&Vector3::new(x, y, z));
        let seen: std::vec::Vec<[f64; 3]> = [2.0, 4.0, 5.0, 7.0, 1e9]
            .iter()
            .chain(&[-3.0, 0.0])
            .map(|&z| in_camera(0.1, 0.0, z).into())
            .collect();
        let mut depths = [0.0; 8];
        let rule = ProjectionRule::of_camera(&pose, seen.into_iter(), &mut depths);
        // Median of the five depths in front: 5.
        assert!((rule.min_depth() - 5.0 * MIN_DEPTH_RATIO).abs() < 1e-12);
        let project = |x, y, z| rule.bearing(&pose, &in_camera(x, y, z));
        let b = project(1.0, -2.0, 4.0).unwrap();
        assert!((b[0] - 0.25).abs() < 1e-12 && (b[1] + 0.5).abs() < 1e-12);
        assert_eq!(project(0.0, 0.0, 2.3e-10), Err(Unusable::TooClose));
        assert_eq!(project(0.0, 0.0, -1.0), Err(Unusable::Behind));
        assert_eq!(project(10.5, 0.0, 1.0), Err(Unusable::OffAxis));
        assert!(project(0.0, 9.9, 1.0).is_ok());
        // A camera that sees nothing in front accepts nothing.
        let blind = ProjectionRule::of_camera(&pose, core::iter::empty(), &mut depths);
        assert_eq!(
            blind.bearing(&pose, &in_camera(0.0, 0.0, 5.0)),
            Err(Unusable::TooClose)
        );
    }

    #[test]
    fn check_refuses_matrices_that_are_no_rotation() {
        assert_eq!(sample_pose().check(), Ok(()));
        let with =
            |m: Matrix3<f64>| Pose::new(Rotation3::from_matrix_unchecked(m), Vector3::zeros());
        let invalid = Err(Error::InvalidRotation { input: Input::Pose });
        assert_eq!(with(Matrix3::zeros()).check(), invalid);
        assert_eq!(with(Matrix3::identity() * 1.01).check(), invalid);
        assert_eq!(with(-Matrix3::identity()).check(), invalid);
        let mut nan = sample_pose();
        nan.translation.y = f64::NAN;
        assert!(matches!(nan.check(), Err(Error::NonFinite { .. })));
    }

    #[test]
    fn colmap_quaternion_matches_rotation() {
        // 90 degrees about z: q = (cos 45, 0, 0, sin 45).
        let h = core::f64::consts::FRAC_1_SQRT_2;
        let pose = Pose::from_colmap([h, 0.0, 0.0, h], [0.0; 3]).unwrap();
        let x = pose.transform(&Vector3::x());
        assert!((x - Vector3::y()).norm() < 1e-12);
        assert!(Pose::from_colmap([0.0; 4], [0.0; 3]).is_err());
    }
}
