//! Levenberg-Marquardt refinement of a pose on the reprojection error (paper supp. "Pose
//! Estimation": the RANSAC-PnP pose is refined on its inliers).
//!
//! The residual of a correspondence is the difference on the normalised image plane between
//! the projection `(p_x/p_z, p_y/p_z)` of `p = R X + t` and the observed bearing vector. The
//! pose is updated as `R <- exp([w]x) R`, `t <- t + dt` with the 6-vector `(w, dt)` from the
//! damped normal equations `(H + lambda diag(H)) delta = -g`, `H`, `g` accumulated with the
//! iteratively reweighted robust loss. All linear algebra is fixed-size (6x6).

use nalgebra::{Matrix6, Rotation3, Vector3, Vector6};

use crate::error::{Error, Input, Result};
use crate::pose::Pose;

/// Depth under which a point counts as at or behind the camera.
const MIN_DEPTH: f64 = 1e-12;
/// Squared residual charged to a point at or behind the camera (a 45 degree error budget
/// squared many times over): the loss caps it (truncated) or makes it dominant (others).
const BEHIND_CAMERA_RESIDUAL2: f64 = 1e4;
/// Initial, smallest and largest Levenberg-Marquardt damping.
const LAMBDA_INITIAL: f64 = 1e-4;
const LAMBDA_MIN: f64 = 1e-12;
const LAMBDA_MAX: f64 = 1e8;

/// Robust loss `rho(r^2)` of one squared residual.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Loss {
    /// Plain least squares, `rho = r^2`.
    Squared,
    /// `rho = min(r^2, threshold^2)`: residuals above the threshold have no influence.
    Truncated {
        /// Residual (normalised plane) above which a point is ignored.
        threshold: f64,
    },
    /// Cauchy, `rho = c^2 log(1 + r^2 / c^2)`.
    Cauchy {
        /// Residual scale `c` (normalised plane).
        scale: f64,
    },
}

impl Loss {
    /// `(rho(r2), rho'(r2))`: the cost and the IRLS weight of a squared residual.
    fn cost_and_weight(&self, r2: f64) -> (f64, f64) {
        match *self {
            Loss::Squared => (r2, 1.0),
            Loss::Truncated { threshold } => {
                let t2 = threshold * threshold;
                if r2 < t2 {
                    (r2, 1.0)
                } else {
                    (t2, 0.0)
                }
            }
            Loss::Cauchy { scale } => {
                let c2 = scale * scale;
                let ratio = r2 / c2;
                (c2 * libm::log1p(ratio), 1.0 / (1.0 + ratio))
            }
        }
    }

    fn is_valid(&self) -> bool {
        match *self {
            Loss::Squared => true,
            Loss::Truncated { threshold: s } | Loss::Cauchy { scale: s } => {
                s > 0.0 && s.is_finite()
            }
        }
    }
}

/// Settings of the refinement.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RefineConfig {
    /// Robust loss.
    pub loss: Loss,
    /// Most Levenberg-Marquardt iterations (accepted or rejected steps).
    pub max_iterations: u32,
    /// Stop when the update is shorter than this (radians / world units).
    pub step_tolerance: f64,
    /// Stop when the gradient's largest component is below this.
    pub gradient_tolerance: f64,
    /// Stop when an accepted step lowers the cost by less than this fraction.
    pub cost_tolerance: f64,
}

impl Default for RefineConfig {
    fn default() -> Self {
        Self::new()
    }
}

impl RefineConfig {
    /// Least squares, 100 iterations, tolerances `1e-10` (step), `1e-16` (gradient) and
    /// `1e-12` (relative cost decrease).
    pub const fn new() -> Self {
        Self {
            loss: Loss::Squared,
            max_iterations: 100,
            step_tolerance: 1e-10,
            gradient_tolerance: 1e-16,
            cost_tolerance: 1e-12,
        }
    }
}

/// A refined pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Refinement {
    /// The refined pose, world to camera.
    pub pose: Pose,
    /// Final robust cost `sum rho(r^2)`.
    pub cost: f64,
    /// Iterations run.
    pub iterations: u32,
}

/// Refines `initial` on all correspondences (bearing vectors `(x/z, y/z)` and world points).
///
/// Fails on a length mismatch, fewer than 3 correspondences, non-finite values (index of the
/// first), a loss scale that is not positive and finite, or when every point is at or behind
/// the initial camera ([`Error::AllPointsBehindCamera`]).
pub fn refine(
    bearings: &[[f64; 2]],
    points: &[[f64; 3]],
    initial: &Pose,
    config: &RefineConfig,
) -> Result<Refinement> {
    if bearings.len() != points.len() {
        return Err(Error::LengthMismatch {
            left: bearings.len(),
            right: points.len(),
        });
    }
    if bearings.len() < 3 {
        return Err(Error::TooFewPoints {
            needed: 3,
            found: bearings.len(),
        });
    }
    check_finite(bearings, points)?;
    let pose_finite = initial
        .rotation
        .matrix()
        .iter()
        .chain(initial.translation.iter())
        .all(|v| v.is_finite());
    if !pose_finite {
        return Err(Error::NonFinite {
            input: Input::Pose,
            index: 0,
        });
    }
    if !config.loss.is_valid() {
        return Err(Error::InvalidConfig {
            parameter: "loss scale",
        });
    }
    let in_front = points
        .iter()
        .any(|p| initial.transform(&Vector3::new(p[0], p[1], p[2])).z > MIN_DEPTH);
    if !in_front {
        return Err(Error::AllPointsBehindCamera);
    }
    Ok(refine_on(
        &AllCorrespondences { bearings, points },
        initial,
        config,
    ))
}

/// First non-finite bearing or point, as an error.
pub(crate) fn check_finite(bearings: &[[f64; 2]], points: &[[f64; 3]]) -> Result<()> {
    if let Some(index) = bearings
        .iter()
        .position(|b| !b.iter().all(|v| v.is_finite()))
    {
        return Err(Error::NonFinite {
            input: Input::Keypoints,
            index,
        });
    }
    if let Some(index) = points.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(Error::NonFinite {
            input: Input::Points3d,
            index,
        });
    }
    Ok(())
}

/// A set of correspondences the refinement iterates over.
pub(crate) trait Correspondences {
    /// Calls `f(bearing, point)` for every correspondence, in a fixed order.
    fn for_each(&self, f: impl FnMut(&[f64; 2], &[f64; 3]));
}

/// Every correspondence of two equally long slices.
pub(crate) struct AllCorrespondences<'a> {
    pub bearings: &'a [[f64; 2]],
    pub points: &'a [[f64; 3]],
}

impl Correspondences for AllCorrespondences<'_> {
    fn for_each(&self, mut f: impl FnMut(&[f64; 2], &[f64; 3])) {
        for (b, p) in self.bearings.iter().zip(self.points) {
            f(b, p);
        }
    }
}

/// The correspondences at the given indices (indices out of range are skipped).
pub(crate) struct SelectedCorrespondences<'a> {
    pub bearings: &'a [[f64; 2]],
    pub points: &'a [[f64; 3]],
    pub indices: &'a [u32],
}

impl Correspondences for SelectedCorrespondences<'_> {
    fn for_each(&self, mut f: impl FnMut(&[f64; 2], &[f64; 3])) {
        for &i in self.indices {
            if let (Some(b), Some(p)) = (self.bearings.get(i as usize), self.points.get(i as usize))
            {
                f(b, p);
            }
        }
    }
}

/// Cost, gradient and Gauss-Newton Hessian of the robust reprojection error at a pose.
struct NormalEquations {
    cost: f64,
    hessian: Matrix6<f64>,
    gradient: Vector6<f64>,
}

fn normal_equations<C: Correspondences>(set: &C, pose: &Pose, loss: &Loss) -> NormalEquations {
    let rotation = pose.rotation.matrix();
    let mut cost = 0.0;
    // Upper triangle of H, row by row, and g.
    let mut upper = [0.0f64; 21];
    let mut gradient = [0.0f64; 6];
    set.for_each(|b, x| {
        let q = rotation * Vector3::new(x[0], x[1], x[2]);
        let p = q + pose.translation;
        if p.z.is_nan() || p.z <= MIN_DEPTH {
            cost += loss.cost_and_weight(BEHIND_CAMERA_RESIDUAL2).0;
            return;
        }
        let inv_z = 1.0 / p.z;
        let u = p.x * inv_z;
        let v = p.y * inv_z;
        let (ru, rv) = (u - b[0], v - b[1]);
        let (rho, weight) = loss.cost_and_weight(ru * ru + rv * rv);
        cost += rho;
        if weight == 0.0 {
            return;
        }
        // Rows of d(u, v)/d(w, dt) for p = exp([w]x) q + t + dt: (q x du, du), (q x dv, dv)
        // with du = (1, 0, -u) / z and dv = (0, 1, -v) / z.
        let ju = [-u * q.y, q.z + u * q.x, -q.y, 1.0, 0.0, -u].map(|j| j * inv_z);
        let jv = [-v * q.y - q.z, v * q.x, q.x, 0.0, 1.0, -v].map(|j| j * inv_z);
        let mut k = 0;
        for r in 0..6 {
            let (wu, wv) = (weight * ju[r], weight * jv[r]);
            for c in r..6 {
                upper[k] += wu * ju[c] + wv * jv[c];
                k += 1;
            }
            gradient[r] += wu * ru + wv * rv;
        }
    });
    let mut hessian = Matrix6::zeros();
    let mut k = 0;
    for r in 0..6 {
        for c in r..6 {
            hessian[(r, c)] = upper[k];
            hessian[(c, r)] = upper[k];
            k += 1;
        }
    }
    NormalEquations {
        cost,
        hessian,
        gradient: Vector6::from(gradient),
    }
}

/// The pose moved by the update `(w, dt)`.
fn apply_update(pose: &Pose, delta: &Vector6<f64>) -> Pose {
    let w = Vector3::new(delta[0], delta[1], delta[2]);
    let dt = Vector3::new(delta[3], delta[4], delta[5]);
    let rotation = Rotation3::new(w) * pose.rotation;
    Pose::new(rotation, pose.translation + dt)
}

/// Levenberg-Marquardt from `initial` on a set of correspondences.
pub(crate) fn refine_on<C: Correspondences>(
    set: &C,
    initial: &Pose,
    config: &RefineConfig,
) -> Refinement {
    let mut pose = *initial;
    let mut current = normal_equations(set, &pose, &config.loss);
    let mut lambda = LAMBDA_INITIAL;
    let mut iterations = 0;
    while iterations < config.max_iterations {
        if current.gradient.amax() < config.gradient_tolerance {
            break;
        }
        iterations += 1;
        let mut damped = current.hessian;
        for i in 0..6 {
            damped[(i, i)] += lambda * current.hessian[(i, i)].max(1e-12);
        }
        let Some(step) = damped.cholesky().map(|c| -c.solve(&current.gradient)) else {
            lambda *= 10.0;
            if lambda > LAMBDA_MAX {
                break;
            }
            continue;
        };
        let candidate = apply_update(&pose, &step);
        let next = normal_equations(set, &candidate, &config.loss);
        if next.cost < current.cost {
            let small_decrease = current.cost - next.cost <= config.cost_tolerance * current.cost;
            pose = candidate;
            current = next;
            lambda = (lambda * 0.1).max(LAMBDA_MIN);
            if small_decrease || step.amax() < config.step_tolerance {
                break;
            }
        } else {
            lambda *= 10.0;
            if lambda > LAMBDA_MAX || step.amax() < config.step_tolerance {
                break;
            }
        }
    }
    Refinement {
        pose,
        cost: current.cost,
        iterations,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene() -> (Pose, [[f64; 3]; 8]) {
        let pose = Pose::new(
            Rotation3::from_euler_angles(0.2, -0.3, 0.5),
            Vector3::new(0.4, -0.2, 5.0),
        );
        let points = [
            [0.5, 0.3, 0.1],
            [-0.8, 0.2, 0.6],
            [0.1, -0.9, -0.4],
            [1.0, 1.0, 1.0],
            [-1.0, -0.5, 0.2],
            [0.3, 0.7, -0.8],
            [0.9, -0.4, 0.5],
            [-0.2, 0.1, -1.0],
        ];
        (pose, points)
    }

    fn project_all(pose: &Pose, points: &[[f64; 3]]) -> [[f64; 2]; 8] {
        let mut out = [[0.0; 2]; 8];
        for (o, p) in out.iter_mut().zip(points) {
            *o = pose.bearing(&Vector3::new(p[0], p[1], p[2]), 0).unwrap();
        }
        out
    }

    fn perturbed(pose: &Pose) -> Pose {
        Pose::new(
            Rotation3::from_euler_angles(0.02, -0.01, 0.03) * pose.rotation,
            pose.translation + Vector3::new(0.05, -0.04, 0.1),
        )
    }

    #[test]
    fn converges_to_the_exact_pose_from_a_perturbed_start() {
        let (truth, points) = scene();
        let bearings = project_all(&truth, &points);
        let result = refine(&bearings, &points, &perturbed(&truth), &RefineConfig::new()).unwrap();
        let rotation = (result.pose.rotation.matrix() - truth.rotation.matrix()).norm();
        assert!(rotation < 1e-12 && result.pose.translation_error(&truth) < 1e-11);
        assert!(result.cost < 1e-20);
    }

    #[test]
    fn truncated_loss_ignores_a_gross_outlier() {
        let (truth, points) = scene();
        let mut bearings = project_all(&truth, &points);
        bearings[3] = [0.5, -0.5];
        let config = RefineConfig {
            loss: Loss::Truncated { threshold: 0.01 },
            ..RefineConfig::new()
        };
        let result = refine(&bearings, &points, &perturbed(&truth), &config).unwrap();
        let rotation = (result.pose.rotation.matrix() - truth.rotation.matrix()).norm();
        // The capped outlier's constant cost hides improvements below ~1e-20 of the total.
        assert!(rotation < 1e-10 && result.pose.translation_error(&truth) < 1e-10);
        assert!((result.cost - 1e-4).abs() < 1e-12);
    }

    #[test]
    fn loss_values_and_weights() {
        assert_eq!(Loss::Squared.cost_and_weight(4.0), (4.0, 1.0));
        let truncated = Loss::Truncated { threshold: 1.0 };
        assert_eq!(truncated.cost_and_weight(0.25), (0.25, 1.0));
        assert_eq!(truncated.cost_and_weight(4.0), (1.0, 0.0));
        let (cost, weight) = Loss::Cauchy { scale: 1.0 }.cost_and_weight(1.0);
        assert!((cost - core::f64::consts::LN_2).abs() < 1e-15 && weight == 0.5);
    }

    #[test]
    fn rejects_bad_input() {
        let (truth, points) = scene();
        let bearings = project_all(&truth, &points);
        let config = RefineConfig::new();
        assert_eq!(
            refine(&bearings[..5], &points, &truth, &config).unwrap_err(),
            Error::LengthMismatch { left: 5, right: 8 }
        );
        assert_eq!(
            refine(&bearings[..2], &points[..2], &truth, &config).unwrap_err(),
            Error::TooFewPoints {
                needed: 3,
                found: 2
            }
        );
        let mut bad = points;
        bad[6][2] = f64::NAN;
        assert_eq!(
            refine(&bearings, &bad, &truth, &config).unwrap_err(),
            Error::NonFinite {
                input: Input::Points3d,
                index: 6
            }
        );
        let behind = Pose::new(
            truth.rotation,
            truth.translation - Vector3::new(0.0, 0.0, 20.0),
        );
        assert_eq!(
            refine(&bearings, &points, &behind, &config).unwrap_err(),
            Error::AllPointsBehindCamera
        );
        let bad_loss = RefineConfig {
            loss: Loss::Cauchy { scale: 0.0 },
            ..config
        };
        assert!(matches!(
            refine(&bearings, &points, &truth, &bad_loss),
            Err(Error::InvalidConfig { .. })
        ));
    }
}
