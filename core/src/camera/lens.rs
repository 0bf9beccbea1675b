//! Lens distortions on the normalised image plane, each a [`Lens`]: the functions a camera
//! model's table entry ([`super::models::MODELS`]) points to.

use crate::error::{Error, Result};

/// Lens coefficients a camera stores ([`crate::Camera::distortion`]).
pub const LENS_COEFFICIENTS: usize = 4;
/// Lens coefficients as [`crate::Camera::distortion`] stores them.
pub type Coefficients = [f64; LENS_COEFFICIENTS];

/// A distortion of a normalised point: the distorted point and its 2x2 Jacobian
/// (row-major).
pub type Distort = fn(&Coefficients, [f64; 2]) -> ([f64; 2], [f64; 4]);

/// A lens distortion as the three functions a camera needs of it.
#[derive(Debug, Clone, Copy)]
pub struct Lens {
    /// Distorted point of an undistorted one, with its Jacobian.
    pub distort: Distort,
    /// Undistorted point of a distorted one (inverse of `distort` inside
    /// `invertible_radius`).
    pub undistort: fn(&Coefficients, [f64; 2]) -> Result<[f64; 2]>,
    /// Distorted radius up to which `distort` is invertible (infinite when everywhere).
    pub invertible_radius: fn(&Coefficients) -> f64,
}

/// COLMAP's `OPENCV` lens, radial `k1, k2` and tangential `p1, p2` (Brown-Conrady); the
/// simpler COLMAP models are this lens with some coefficients zero.
pub const RADIAL_TANGENTIAL: Lens = Lens {
    distort: radial_tangential,
    undistort: undistort_radial_tangential,
    invertible_radius: radial_invertible_radius,
};

/// Iteration cap of the Newton undistortion.
const UNDISTORT_MAX_ITERATIONS: usize = 100;
/// Squared step length under which the Newton undistortion has converged.
const UNDISTORT_STEP_TOLERANCE2: f64 = 1e-24;

/// COLMAP's `OPENCV` distortion of a normalised point, with its 2x2 Jacobian (row-major).
fn radial_tangential(&[k1, k2, p1, p2]: &Coefficients, [u, v]: [f64; 2]) -> ([f64; 2], [f64; 4]) {
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

/// Inverts [`radial_tangential`]: the identity without distortion, else Newton's method.
fn undistort_radial_tangential(
    coefficients: &Coefficients,
    distorted: [f64; 2],
) -> Result<[f64; 2]> {
    if coefficients.iter().all(|&d| d == 0.0) {
        return Ok(distorted);
    }
    newton_undistort(radial_tangential, coefficients, distorted)
}

/// Inverts `distort` by Newton's method, starting at the distorted point.
fn newton_undistort(
    distort: Distort,
    coefficients: &Coefficients,
    distorted: [f64; 2],
) -> Result<[f64; 2]> {
    let mut x = distorted;
    for _ in 0..UNDISTORT_MAX_ITERATIONS {
        let (f, [a, b, c, d]) = distort(coefficients, x);
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

/// Distorted radius up to which the radial distortion `r (1 + k1 r^2 + k2 r^4)` is
/// increasing, hence invertible: its value at the first zero of its derivative
/// `1 + 3 k1 r^2 + 5 k2 r^4`, infinite when there is none.
fn radial_invertible_radius(&[k1, k2, _, _]: &Coefficients) -> f64 {
    let Some(s) = smallest_positive_root(5.0 * k2, 3.0 * k1, 1.0) else {
        return f64::INFINITY;
    };
    let r = libm::sqrt(s);
    r * (1.0 + k1 * s + k2 * s * s)
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
