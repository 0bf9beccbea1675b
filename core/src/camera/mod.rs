//! Cameras of the COLMAP models in [`MODELS`] (one table entry per model), and the mapping
//! between pixels and bearing vectors (paper sec. 3, "Keypoint Representation":
//! `[b 1]^T ∝ K^-1 [u v 1]^T`, after removing the model's [`Lens`] distortion).
//!
//! A bearing vector here is the point `(x/z, y/z)` on the normalised image plane.

mod lens;
mod models;

use serde::{Deserialize, Serialize};

pub use lens::{Coefficients, Distort, Lens, LENS_COEFFICIENTS, RADIAL_TANGENTIAL};
pub use models::{CameraModel, ModelSpec, Param, MAX_PARAMS, MODELS};

use crate::error::{Error, Input, Result};

/// A calibrated camera: pinhole intrinsics plus its model's lens distortion.
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
    /// Coefficients of the model's [`Lens`]: `k1, k2, p1, p2` of [`RADIAL_TANGENTIAL`]
    /// for every model so far (zero where the model has none).
    pub distortion: Coefficients,
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
        let (mut focal, mut principal) = ([0.0; 2], [0.0; 2]);
        let mut distortion = [0.0; LENS_COEFFICIENTS];
        for (&param, &value) in model.spec().params.iter().zip(params) {
            match param {
                Param::Focal => focal = [value, value],
                Param::FocalX => focal[0] = value,
                Param::FocalY => focal[1] = value,
                Param::PrincipalX => principal[0] = value,
                Param::PrincipalY => principal[1] = value,
                Param::Coefficient(i) => {
                    if let Some(slot) = distortion.get_mut(i) {
                        *slot = value;
                    }
                }
            }
        }
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
    pub fn colmap_params(&self) -> ([f64; MAX_PARAMS], usize) {
        let spec = self.model.spec();
        let mut all = [0.0; MAX_PARAMS];
        for (value, &param) in all.iter_mut().zip(spec.params) {
            *value = match param {
                Param::Focal | Param::FocalX => self.focal[0],
                Param::FocalY => self.focal[1],
                Param::PrincipalX => self.principal[0],
                Param::PrincipalY => self.principal[1],
                Param::Coefficient(i) => self.distortion.get(i).copied().unwrap_or(0.0),
            };
        }
        (all, spec.params.len())
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

    /// Distorted radius on the normalised plane up to which the lens distortion is
    /// increasing, hence invertible (infinite when everywhere). A distorted point farther
    /// out either has no undistorted point or several (the lens model folds back), so any
    /// bearing found for it is arbitrary; an OPENCV camera with `k1 = -1e6, k2 = 1e6`
    /// folds at 3.9e-4, squeezing a whole image into a tiny cone.
    pub fn invertible_radius(&self) -> f64 {
        (self.lens().invertible_radius)(&self.distortion)
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

    fn lens(&self) -> Lens {
        self.model.spec().lens
    }

    fn distort(&self, point: [f64; 2]) -> [f64; 2] {
        (self.lens().distort)(&self.distortion, point).0
    }

    fn undistort(&self, distorted: [f64; 2]) -> Result<[f64; 2]> {
        (self.lens().undistort)(&self.distortion, distorted)
    }
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
        assert!(CameraModel::from_colmap_name("FISHEYE").is_err());
    }

    #[test]
    fn every_model_is_found_by_id_and_name_and_keeps_its_parameters() {
        let params: [f64; MAX_PARAMS] = core::array::from_fn(|i| 100.0 + i as f64);
        for (index, spec) in MODELS.iter().enumerate() {
            assert_eq!(spec.model.spec().id, spec.id);
            assert_eq!(spec.model as usize, index);
            assert_eq!(CameraModel::from_colmap_id(spec.id), Ok(spec.model));
            assert_eq!(CameraModel::from_colmap_name(spec.name), Ok(spec.model));
            let count = spec.model.param_count();
            let camera = Camera::from_colmap(spec.model, 640, 480, &params[..count]).unwrap();
            let (written, written_count) = camera.colmap_params();
            assert_eq!(written_count, count);
            assert_eq!(written[..count], params[..count]);
            assert!(written[count..].iter().all(|&p| p == 0.0));
        }
    }
}
