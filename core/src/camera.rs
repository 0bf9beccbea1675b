//! Camera models with COLMAP's parameter order, and the mapping between pixels and bearing
//! vectors (paper sec. 3, "Keypoint Representation": `[b 1]^T ∝ K^-1 [u v 1]^T`, after
//! removing lens distortion).
//!
//! A bearing vector here is the point `(x/z, y/z)` on the normalised image plane.

use serde::{Deserialize, Serialize};

use crate::error::{Error, Input, Result};

/// Iteration cap of the Newton undistortion.
const UNDISTORT_MAX_ITERATIONS: usize = 100;
/// Squared step length under which the Newton undistortion has converged.
const UNDISTORT_STEP_TOLERANCE2: f64 = 1e-24;

/// The COLMAP camera models supported, with their COLMAP model ids.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum CameraModel {
    /// `f, cx, cy` (COLMAP id 0).
    SimplePinhole,
    /// `fx, fy, cx, cy` (COLMAP id 1).
    Pinhole,
    /// `f, cx, cy, k` (COLMAP id 2).
    SimpleRadial,
    /// `f, cx, cy, k1, k2` (COLMAP id 3).
    Radial,
    /// `fx, fy, cx, cy, k1, k2, p1, p2` (COLMAP id 4).
    OpenCv,
}

impl CameraModel {
    /// Model from its COLMAP id.
    pub fn from_colmap_id(id: i32) -> Result<Self> {
        match id {
            0 => Ok(Self::SimplePinhole),
            1 => Ok(Self::Pinhole),
            2 => Ok(Self::SimpleRadial),
            3 => Ok(Self::Radial),
            4 => Ok(Self::OpenCv),
            _ => Err(Error::InvalidIntrinsics),
        }
    }

    /// Model from its COLMAP name (`SIMPLE_PINHOLE`, `PINHOLE`, ...).
    pub fn from_colmap_name(name: &str) -> Result<Self> {
        match name {
            "SIMPLE_PINHOLE" => Ok(Self::SimplePinhole),
            "PINHOLE" => Ok(Self::Pinhole),
            "SIMPLE_RADIAL" => Ok(Self::SimpleRadial),
            "RADIAL" => Ok(Self::Radial),
            "OPENCV" => Ok(Self::OpenCv),
            _ => Err(Error::InvalidIntrinsics),
        }
    }

    /// COLMAP id of the model.
    pub fn colmap_id(self) -> i32 {
        match self {
            Self::SimplePinhole => 0,
            Self::Pinhole => 1,
            Self::SimpleRadial => 2,
            Self::Radial => 3,
            Self::OpenCv => 4,
        }
    }

    /// Number of COLMAP parameters of the model.
    pub fn param_count(self) -> usize {
        match self {
            Self::SimplePinhole => 3,
            Self::Pinhole => 4,
            Self::SimpleRadial => 4,
            Self::Radial => 5,
            Self::OpenCv => 8,
        }
    }
}

/// A calibrated camera: pinhole intrinsics plus radial/tangential distortion.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    /// Which COLMAP model the parameters came from.
    pub model: CameraModel,
    /// Image width in pixels (0 when unknown).
    pub width: u32,
    /// Image height in pixels (0 when unknown).
    pub height: u32,
    /// Focal lengths in pixels.
    pub focal: [f64; 2],
    /// Principal point in pixels.
    pub principal: [f64; 2],
    /// Distortion `k1, k2, p1, p2` (zero where the model has none).
    pub distortion: [f64; 4],
}

impl Camera {
    /// Camera from a COLMAP model and its parameters in COLMAP order. Fails with
    /// [`Error::InvalidIntrinsics`] on a wrong parameter count, non-finite values or a
    /// non-positive focal length.
    pub fn from_colmap(
        model: CameraModel,
        width: u32,
        height: u32,
        params: &[f64],
    ) -> Result<Self> {
        if params.len() != model.param_count() || params.iter().any(|p| !p.is_finite()) {
            return Err(Error::InvalidIntrinsics);
        }
        let p = params;
        let (focal, principal, distortion) = match model {
            CameraModel::SimplePinhole => ([p[0], p[0]], [p[1], p[2]], [0.0; 4]),
            CameraModel::Pinhole => ([p[0], p[1]], [p[2], p[3]], [0.0; 4]),
            CameraModel::SimpleRadial => ([p[0], p[0]], [p[1], p[2]], [p[3], 0.0, 0.0, 0.0]),
            CameraModel::Radial => ([p[0], p[0]], [p[1], p[2]], [p[3], p[4], 0.0, 0.0]),
            CameraModel::OpenCv => ([p[0], p[1]], [p[2], p[3]], [p[4], p[5], p[6], p[7]]),
        };
        if focal[0] <= 0.0 || focal[1] <= 0.0 {
            return Err(Error::InvalidIntrinsics);
        }
        Ok(Self {
            model,
            width,
            height,
            focal,
            principal,
            distortion,
        })
    }

    /// A distortion-free camera with focal length `f` and principal point `(cx, cy)`.
    pub fn simple_pinhole(width: u32, height: u32, f: f64, cx: f64, cy: f64) -> Result<Self> {
        Self::from_colmap(CameraModel::SimplePinhole, width, height, &[f, cx, cy])
    }

    /// The parameters in COLMAP order; the count is `model.param_count()`.
    pub fn colmap_params(&self) -> ([f64; 8], usize) {
        let [fx, fy] = self.focal;
        let [cx, cy] = self.principal;
        let [k1, k2, p1, p2] = self.distortion;
        let all = match self.model {
            CameraModel::SimplePinhole => [fx, cx, cy, 0.0, 0.0, 0.0, 0.0, 0.0],
            CameraModel::Pinhole => [fx, fy, cx, cy, 0.0, 0.0, 0.0, 0.0],
            CameraModel::SimpleRadial => [fx, cx, cy, k1, 0.0, 0.0, 0.0, 0.0],
            CameraModel::Radial => [fx, cx, cy, k1, k2, 0.0, 0.0, 0.0],
            CameraModel::OpenCv => [fx, fy, cx, cy, k1, k2, p1, p2],
        };
        (all, self.model.param_count())
    }

    /// Checks a camera built field by field: finite parameters and positive focal
    /// lengths, else [`Error::InvalidIntrinsics`].
    pub fn check(&self) -> Result<()> {
        let finite = self
            .focal
            .iter()
            .chain(&self.principal)
            .chain(&self.distortion)
            .all(|v| v.is_finite());
        if finite && self.focal[0] > 0.0 && self.focal[1] > 0.0 {
            Ok(())
        } else {
            Err(Error::InvalidIntrinsics)
        }
    }

    /// Mean focal length in pixels (to express normalised-plane errors in pixels).
    pub fn mean_focal(&self) -> f64 {
        0.5 * (self.focal[0] + self.focal[1])
    }

    /// Bearing vector `(x/z, y/z)` of a pixel: `K^-1` followed by iterative undistortion.
    /// A pixel beyond the distortion's fold ([`Self::invertible_radius`]) has no unique
    /// bearing: [`Error::DistortionNotInvertible`]. Errors name keypoint 0; callers
    /// converting a list put in the index.
    pub fn pixel_to_bearing(&self, pixel: [f64; 2]) -> Result<[f64; 2]> {
        if !pixel[0].is_finite() || !pixel[1].is_finite() {
            return Err(Error::NonFinite {
                input: Input::Keypoints,
                index: 0,
            });
        }
        let distorted = [
            (pixel[0] - self.principal[0]) / self.focal[0],
            (pixel[1] - self.principal[1]) / self.focal[1],
        ];
        let radius = libm::hypot(distorted[0], distorted[1]);
        if radius >= self.invertible_radius() {
            return Err(Error::DistortionNotInvertible { index: 0 });
        }
        self.undistort(distorted)
    }

    /// Distorted radius on the normalised plane up to which the radial distortion
    /// `r (1 + k1 r^2 + k2 r^4)` is increasing, hence invertible: its value at the first
    /// zero of its derivative `1 + 3 k1 r^2 + 5 k2 r^4`, infinite when there is none. A
    /// distorted point farther out either has no undistorted point or several (the lens
    /// model folds back), so any bearing found for it is arbitrary; an OPENCV camera with
    /// `k1 = -1e6, k2 = 1e6` folds at 3.9e-4, squeezing a whole image into a tiny cone.
    pub fn invertible_radius(&self) -> f64 {
        let [k1, k2, _, _] = self.distortion;
        let Some(s) = smallest_positive_root(5.0 * k2, 3.0 * k1, 1.0) else {
            return f64::INFINITY;
        };
        let r = libm::sqrt(s);
        r * (1.0 + k1 * s + k2 * s * s)
    }

    /// Pixel of a bearing vector `(x/z, y/z)`: distortion followed by `K`.
    pub fn bearing_to_pixel(&self, bearing: [f64; 2]) -> Result<[f64; 2]> {
        let [u, v] = self.distort(bearing);
        let pixel = [
            self.focal[0] * u + self.principal[0],
            self.focal[1] * v + self.principal[1],
        ];
        if pixel[0].is_finite() && pixel[1].is_finite() {
            Ok(pixel)
        } else {
            Err(Error::NonFinite {
                input: Input::Keypoints,
                index: 0,
            })
        }
    }

    fn has_distortion(&self) -> bool {
        self.distortion.iter().any(|&d| d != 0.0)
    }

    /// COLMAP's distortion of a normalised point, with its 2x2 Jacobian (row-major).
    fn distort_with_jacobian(&self, [u, v]: [f64; 2]) -> ([f64; 2], [f64; 4]) {
        let [k1, k2, p1, p2] = self.distortion;
        let (u2, v2, uv) = (u * u, v * v, u * v);
        let r2 = u2 + v2;
        let radial = k1 * r2 + k2 * r2 * r2;
        let d_radial = k1 + 2.0 * k2 * r2; // d radial / d r2
        let du = u * radial + 2.0 * p1 * uv + p2 * (r2 + 2.0 * u2);
        let dv = v * radial + 2.0 * p2 * uv + p1 * (r2 + 2.0 * v2);
        let j00 = 1.0 + radial + 2.0 * u2 * d_radial + 2.0 * p1 * v + 6.0 * p2 * u;
        let j01 = 2.0 * uv * d_radial + 2.0 * p1 * u + 2.0 * p2 * v;
        let j10 = 2.0 * uv * d_radial + 2.0 * p2 * v + 2.0 * p1 * u;
        let j11 = 1.0 + radial + 2.0 * v2 * d_radial + 2.0 * p2 * u + 6.0 * p1 * v;
        ([u + du, v + dv], [j00, j01, j10, j11])
    }

    fn distort(&self, point: [f64; 2]) -> [f64; 2] {
        self.distort_with_jacobian(point).0
    }

    /// Inverts [`Self::distort`] by Newton's method, starting at the distorted point.
    fn undistort(&self, distorted: [f64; 2]) -> Result<[f64; 2]> {
        if !self.has_distortion() {
            return Ok(distorted);
        }
        let mut x = distorted;
        for _ in 0..UNDISTORT_MAX_ITERATIONS {
            let (f, [a, b, c, d]) = self.distort_with_jacobian(x);
            let r = [f[0] - distorted[0], f[1] - distorted[1]];
            let det = a * d - b * c;
            if !det.is_finite() || det.abs() < 1e-12 {
                return Err(Error::UndistortionDidNotConverge { index: 0 });
            }
            let step = [(d * r[0] - b * r[1]) / det, (a * r[1] - c * r[0]) / det];
            x = [x[0] - step[0], x[1] - step[1]];
            if step[0] * step[0] + step[1] * step[1] < UNDISTORT_STEP_TOLERANCE2 {
                return Ok(x);
            }
        }
        Err(Error::UndistortionDidNotConverge { index: 0 })
    }
}

/// Smallest positive root of `a s^2 + b s + c` (`c = 1` here, so 0 is never a root).
fn smallest_positive_root(a: f64, b: f64, c: f64) -> Option<f64> {
    if a == 0.0 {
        let s = -c / b;
        return (s > 0.0 && s.is_finite()).then_some(s);
    }
    let discriminant = b * b - 4.0 * a * c;
    if discriminant < 0.0 {
        return None;
    }
    let root = libm::sqrt(discriminant);
    // Both roots without cancellation: q = -(b + sign(b) root) / 2, s = q / a and c / q.
    let q = -0.5 * (b + libm::copysign(root, b));
    [q / a, c / q]
        .into_iter()
        .filter(|s| *s > 0.0 && s.is_finite())
        .min_by(f64::total_cmp)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pinhole_inverts_k() {
        let cam = Camera::from_colmap(
            CameraModel::Pinhole,
            640,
            480,
            &[500.0, 400.0, 320.0, 240.0],
        )
        .unwrap();
        assert_eq!(cam.pixel_to_bearing([820.0, 640.0]), Ok([1.0, 1.0]));
        assert_eq!(cam.bearing_to_pixel([1.0, 1.0]), Ok([820.0, 640.0]));
    }

    #[test]
    fn opencv_round_trip() {
        let cam = Camera::from_colmap(
            CameraModel::OpenCv,
            1920,
            1080,
            &[1500.0, 1490.0, 960.0, 540.0, -0.1, 0.02, 0.001, -0.0005],
        )
        .unwrap();
        let pixel = [100.0, 1000.0];
        let bearing = cam.pixel_to_bearing(pixel).unwrap();
        let back = cam.bearing_to_pixel(bearing).unwrap();
        assert!((back[0] - pixel[0]).abs() < 1e-8 && (back[1] - pixel[1]).abs() < 1e-8);
    }

    #[test]
    fn distortion_is_inverted_only_up_to_its_fold() {
        let opencv = |k1: f64, k2: f64| {
            Camera::from_colmap(
                CameraModel::OpenCv,
                640,
                480,
                &[500.0, 500.0, 320.0, 240.0, k1, k2, 0.0, 0.0],
            )
            .unwrap()
        };
        // Issue 23's camera: the profile's derivative 1 - 3e6 s + 5e6 s^2 (s = r^2) first
        // vanishes at s = 3.3e-7, where the profile peaks at 3.85e-4 (0.19 px).
        let squeezed = opencv(-1e6, 1e6);
        let fold = squeezed.invertible_radius();
        let s: f64 = (3e6 - (9e12f64 - 20e6).sqrt()) / 10e6;
        assert!((fold - s.sqrt() * (1.0 - 1e6 * s + 1e6 * s * s)).abs() < 1e-14);
        assert!(fold < 4e-4);
        assert_eq!(
            squeezed.pixel_to_bearing([600.0, 400.0]),
            Err(Error::DistortionNotInvertible { index: 0 })
        );
        assert!(squeezed.pixel_to_bearing([320.1, 240.0]).is_ok());
        // Barrel distortion with k2 = 0 folds at r^2 = -1 / (3 k1).
        let barrel = opencv(-0.3, 0.0);
        let r: f64 = (1.0f64 / 0.9).sqrt();
        assert!((barrel.invertible_radius() - r * (1.0 - 0.3 * r * r)).abs() < 1e-12);
        // Monotonic profiles never fold.
        assert_eq!(opencv(0.1, 0.01).invertible_radius(), f64::INFINITY);
        assert_eq!(opencv(0.0, 0.0).invertible_radius(), f64::INFINITY);
    }

    #[test]
    fn rejects_bad_intrinsics() {
        assert_eq!(
            Camera::from_colmap(CameraModel::Pinhole, 1, 1, &[0.0, 1.0, 0.0, 0.0]),
            Err(Error::InvalidIntrinsics)
        );
        assert_eq!(
            Camera::from_colmap(CameraModel::Pinhole, 1, 1, &[1.0, 1.0, 0.0]),
            Err(Error::InvalidIntrinsics)
        );
        assert_eq!(
            Camera::from_colmap(CameraModel::SimplePinhole, 1, 1, &[f64::NAN, 1.0, 0.0]),
            Err(Error::InvalidIntrinsics)
        );
        assert!(CameraModel::from_colmap_id(7).is_err());
    }
}
