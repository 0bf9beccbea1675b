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
    /// Fails on non-finite values.
    pub fn from_matrix(r: &[[f64; 3]; 3], t: &[f64; 3]) -> Result<Self> {
        let finite = r.iter().flatten().chain(t.iter()).all(|v| v.is_finite());
        if !finite {
            return Err(Error::NonFinite {
                input: Input::Pose,
                index: 0,
            });
        }
        let m = Matrix3::from_fn(|i, j| r[i][j]);
        Ok(Self::new(
            Rotation3::from_matrix(&m),
            Vector3::new(t[0], t[1], t[2]),
        ))
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
    pub fn bearing(&self, x_world: &Vector3<f64>, index: usize) -> Result<[f64; 2]> {
        let p = self.transform(x_world);
        if p.z <= 0.0 || !p.z.is_finite() || !p.x.is_finite() || !p.y.is_finite() {
            return Err(Error::PointBehindCamera { index });
        }
        Ok([p.x / p.z, p.y / p.z])
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
    fn colmap_quaternion_matches_rotation() {
        // 90 degrees about z: q = (cos 45, 0, 0, sin 45).
        let h = core::f64::consts::FRAC_1_SQRT_2;
        let pose = Pose::from_colmap([h, 0.0, 0.0, h], [0.0; 3]).unwrap();
        let x = pose.transform(&Vector3::x());
        assert!((x - Vector3::y()).norm() < 1e-12);
        assert!(Pose::from_colmap([0.0; 4], [0.0; 3]).is_err());
    }
}
