//! Minimal absolute pose from three 2D-3D correspondences (P3P), the hypothesis generator of
//! the RANSAC-PnP stage (paper supp. "Pose Estimation").
//!
//! Formulation after Ding, Yang, Larsson, Kukelova, "Revisiting the P3P Problem" (CVPR 2023),
//! which shares its structure with Lambda Twist (Persson & Nordberg, ECCV 2018). With unit
//! rays `y_i`, unknown depths `d_i > 0`, `m_ij = y_i . y_j` and squared world distances
//! `a_ij = |X_i - X_j|^2`, the law of cosines gives
//!
//! ```text
//! Q_ij(d) = d_i^2 + d_j^2 - 2 m_ij d_i d_j = a_ij      (ij = 01, 02, 12)
//! ```
//!
//! Ordering the points so that `a_12` is the largest distance and eliminating the right-hand
//! sides gives two homogeneous conics in `d = (d0, d1, d2)`:
//!
//! ```text
//! F1 = Q_01 - (a_01 / a_12) Q_12 = 0,   F2 = Q_02 - (a_02 / a_12) Q_12 = 0.
//! ```
//!
//! A real root `s` of the cubic `det(F1 + s F2) = 0` gives a degenerate member of the
//! pencil: a pair of lines through which every common point of the two conics passes. Each
//! line is intersected with one conic (a quadratic), the depths are scaled by `Q_12 = a_12`,
//! polished by Gauss-Newton on the three distance equations, and the pose is the rigid map
//! of the world triangle onto the camera triangle. Every real solution with positive depths
//! is returned (at most four).

use nalgebra::{Matrix3, Rotation3, Vector3};

use crate::error::{Error, Input, Result};
use crate::pose::Pose;

/// Largest number of real solutions of P3P.
pub const MAX_SOLUTIONS: usize = 4;

/// Gauss-Newton steps polishing the depths of one solution.
const DEPTH_POLISH_STEPS: usize = 3;
/// Relative squared sine below which three world points count as collinear.
const COLLINEAR_SIN2: f64 = 1e-16;

/// The real solutions of one P3P problem, poses world to camera.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct P3pSolutions {
    poses: [Pose; MAX_SOLUTIONS],
    len: usize,
}

impl Default for P3pSolutions {
    fn default() -> Self {
        Self::new()
    }
}

impl P3pSolutions {
    /// No solution.
    pub fn new() -> Self {
        Self {
            poses: [Pose::identity(); MAX_SOLUTIONS],
            len: 0,
        }
    }

    /// The solutions found, in no particular order.
    pub fn as_slice(&self) -> &[Pose] {
        self.poses.get(..self.len).unwrap_or(&[])
    }

    /// Number of solutions.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether no solution was found.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    fn push(&mut self, pose: Pose) {
        if let Some(slot) = self.poses.get_mut(self.len) {
            *slot = pose;
            self.len += 1;
        }
    }
}

/// Solves P3P for bearing vectors `(x/z, y/z)` on the normalised image plane and their world
/// points; returns every real solution with all three points in front of the camera.
///
/// Fails on non-finite input ([`Error::NonFinite`] with the index of the first bad item) and
/// on degenerate configurations: coincident or collinear world points, or coincident
/// bearings ([`Error::DegenerateConfiguration`]).
pub fn solve(bearings: &[[f64; 2]; 3], points: &[[f64; 3]; 3]) -> Result<P3pSolutions> {
    for (index, b) in bearings.iter().enumerate() {
        if !b.iter().all(|v| v.is_finite()) {
            return Err(Error::NonFinite {
                input: Input::Keypoints,
                index,
            });
        }
    }
    for (index, p) in points.iter().enumerate() {
        if !p.iter().all(|v| v.is_finite()) {
            return Err(Error::NonFinite {
                input: Input::Points3d,
                index,
            });
        }
    }
    let rays = bearings.map(|b| unit_ray(&b));
    let world = points.map(|p| Vector3::new(p[0], p[1], p[2]));
    let distinct_rays = (0..3).all(|i| rays[i].dot(&rays[(i + 1) % 3]) < 1.0 - 1e-15);
    if !distinct_rays || world_triangle_is_degenerate(&world) {
        return Err(Error::DegenerateConfiguration);
    }
    let mut solutions = P3pSolutions::new();
    solve_rays(&rays, &world, &mut solutions);
    Ok(solutions)
}

/// Unit ray of a bearing vector `(x/z, y/z)`.
pub fn unit_ray(bearing: &[f64; 2]) -> Vector3<f64> {
    let ray = Vector3::new(bearing[0], bearing[1], 1.0);
    ray * (1.0 / ray.norm())
}

fn world_triangle_is_degenerate(world: &[Vector3<f64>; 3]) -> bool {
    let e1 = world[1] - world[0];
    let e2 = world[2] - world[0];
    let scale = e1.norm_squared() * e2.norm_squared();
    let area2 = e1.cross(&e2).norm_squared();
    area2.is_nan() || area2 <= COLLINEAR_SIN2 * scale
}

/// P3P on unit rays, without input checks: writes every real solution with positive depths
/// into `out` (cleared first). Degenerate or non-finite input yields no solution.
pub fn solve_rays(rays: &[Vector3<f64>; 3], world: &[Vector3<f64>; 3], out: &mut P3pSolutions) {
    out.len = 0;
    let (y, x) = order_longest_side_last(rays, world);
    let Some(world_inverse) = world_frame_inverse(&x) else {
        return;
    };
    let a01 = (x[0] - x[1]).norm_squared();
    let a02 = (x[0] - x[2]).norm_squared();
    let a12 = (x[1] - x[2]).norm_squared();
    let problem = DepthProblem {
        a: [a01, a02, a12],
        m: [y[0].dot(&y[1]), y[0].dot(&y[2]), y[1].dot(&y[2])],
    };
    let (first, second) = problem.conics();
    // Write the pencil as `P + s Q` with the better-conditioned leading coefficient.
    let (p, q) = if determinant(&second).abs() >= determinant(&first).abs() {
        (first, second)
    } else {
        (second, first)
    };
    let [c0, c1, c2, c3] = pencil_determinant(&p, &q);
    if !c3.is_finite() {
        return;
    }
    // c3 = det Q = 0 means det P = 0 as well: P itself is the degenerate member.
    let (roots, root_count) = if c3 == 0.0 {
        ([0.0; 3], 1)
    } else {
        let inverse_c3 = 1.0 / c3;
        real_cubic_roots(c2 * inverse_c3, c1 * inverse_c3, c0 * inverse_c3)
    };
    for &s in roots.iter().take(root_count) {
        let degenerate = p + q * s;
        let Some(lines) = split_line_pair(&degenerate) else {
            continue;
        };
        // On both lines `P = -s Q`: intersect with whichever of the two is larger there.
        let conic = if s.abs() > 1.0 { p } else { q };
        for line in lines {
            for direction in line_conic_intersections(&line, &conic)
                .into_iter()
                .flatten()
            {
                if let Some(depths) = problem.scaled_depths(&direction) {
                    let pose = pose_from_depths(&problem.polish(depths), &y, &x, &world_inverse);
                    if let Some(pose) = pose {
                        out.push(pose);
                    }
                }
            }
        }
        return;
    }
}

/// Reorders the correspondences so that the pair (1, 2) has the largest world distance.
fn order_longest_side_last(
    rays: &[Vector3<f64>; 3],
    world: &[Vector3<f64>; 3],
) -> ([Vector3<f64>; 3], [Vector3<f64>; 3]) {
    let d01 = (world[0] - world[1]).norm_squared();
    let d02 = (world[0] - world[2]).norm_squared();
    let d12 = (world[1] - world[2]).norm_squared();
    let order = if d01 >= d02 && d01 >= d12 {
        [2, 0, 1]
    } else if d02 >= d12 {
        [1, 0, 2]
    } else {
        [0, 1, 2]
    };
    (order.map(|i| rays[i]), order.map(|i| world[i]))
}

/// Inverse of `[X1 - X0, X2 - X0, (X1 - X0) x (X2 - X0)]`, or `None` for a collinear triangle.
fn world_frame_inverse(x: &[Vector3<f64>; 3]) -> Option<Matrix3<f64>> {
    if world_triangle_is_degenerate(x) {
        return None;
    }
    let e1 = x[1] - x[0];
    let e2 = x[2] - x[0];
    Matrix3::from_columns(&[e1, e2, e1.cross(&e2)]).try_inverse()
}

/// The three law-of-cosines equations `Q_ij(d) = a_ij` for pairs 01, 02, 12.
struct DepthProblem {
    a: [f64; 3],
    m: [f64; 3],
}

impl DepthProblem {
    /// Matrices of the homogeneous conics `F1` and `F2` (module doc) in `(d0, d1, d2)`.
    fn conics(&self) -> (Matrix3<f64>, Matrix3<f64>) {
        let [a01, a02, a12] = self.a;
        let [m01, m02, m12] = self.m;
        let a = a01 / a12;
        let b = a02 / a12;
        let f1 = Matrix3::new(1.0, -m01, 0.0, -m01, 1.0 - a, a * m12, 0.0, a * m12, -a);
        let f2 = Matrix3::new(1.0, 0.0, -m02, 0.0, -b, b * m12, -m02, b * m12, 1.0 - b);
        (f1, f2)
    }

    /// Depths along a direction of the conics' common points, scaled so that
    /// `Q_12 = a_12`; `None` unless all three are positive.
    fn scaled_depths(&self, direction: &Vector3<f64>) -> Option<Vector3<f64>> {
        let sign = if direction.sum() < 0.0 { -1.0 } else { 1.0 };
        let e = direction * sign;
        if !(e.x > 0.0 && e.y > 0.0 && e.z > 0.0) {
            return None;
        }
        let q12 = e.y * e.y + e.z * e.z - 2.0 * self.m[2] * e.y * e.z;
        let scale2 = self.a[2] / q12;
        (scale2 > 0.0 && scale2.is_finite()).then(|| e * libm::sqrt(scale2))
    }

    /// Residuals `Q_ij(d) - a_ij`.
    fn residuals(&self, d: &Vector3<f64>) -> Vector3<f64> {
        let [m01, m02, m12] = self.m;
        Vector3::new(
            d.x * d.x + d.y * d.y - 2.0 * m01 * d.x * d.y - self.a[0],
            d.x * d.x + d.z * d.z - 2.0 * m02 * d.x * d.z - self.a[1],
            d.y * d.y + d.z * d.z - 2.0 * m12 * d.y * d.z - self.a[2],
        )
    }

    /// A few Gauss-Newton steps on the three distance equations.
    fn polish(&self, mut d: Vector3<f64>) -> Vector3<f64> {
        let [m01, m02, m12] = self.m;
        for _ in 0..DEPTH_POLISH_STEPS {
            let r = self.residuals(&d);
            if r.abs().sum() < 1e-13 * self.a[2] {
                break;
            }
            let jacobian = Matrix3::new(
                d.x - m01 * d.y,
                d.y - m01 * d.x,
                0.0,
                d.x - m02 * d.z,
                0.0,
                d.z - m02 * d.x,
                0.0,
                d.y - m12 * d.z,
                d.z - m12 * d.y,
            ) * 2.0;
            match jacobian.try_inverse() {
                Some(inverse) => {
                    let next = d - inverse * r;
                    if next.iter().all(|v| v.is_finite() && *v > 0.0) {
                        d = next;
                    } else {
                        break;
                    }
                }
                None => break,
            }
        }
        d
    }
}

/// Determinant of a 3x3 matrix.
fn determinant(m: &Matrix3<f64>) -> f64 {
    m.m11 * (m.m22 * m.m33 - m.m23 * m.m32) - m.m12 * (m.m21 * m.m33 - m.m23 * m.m31)
        + m.m13 * (m.m21 * m.m32 - m.m22 * m.m31)
}

/// Adjugate (transposed cofactor matrix) of a 3x3 matrix.
fn adjugate(m: &Matrix3<f64>) -> Matrix3<f64> {
    Matrix3::new(
        m.m22 * m.m33 - m.m23 * m.m32,
        m.m13 * m.m32 - m.m12 * m.m33,
        m.m12 * m.m23 - m.m13 * m.m22,
        m.m23 * m.m31 - m.m21 * m.m33,
        m.m11 * m.m33 - m.m13 * m.m31,
        m.m13 * m.m21 - m.m11 * m.m23,
        m.m21 * m.m32 - m.m22 * m.m31,
        m.m12 * m.m31 - m.m11 * m.m32,
        m.m11 * m.m22 - m.m12 * m.m21,
    )
}

/// Coefficients `[c0, c1, c2, c3]` of `det(P + s Q) = c0 + c1 s + c2 s^2 + c3 s^3`, from
/// `det(P + sQ) = det P + s tr(adj(P) Q) + s^2 tr(P adj(Q)) + s^3 det Q`.
fn pencil_determinant(p: &Matrix3<f64>, q: &Matrix3<f64>) -> [f64; 4] {
    let trace_of_product =
        |a: &Matrix3<f64>, b: &Matrix3<f64>| a.component_mul(&b.transpose()).sum();
    [
        determinant(p),
        trace_of_product(&adjugate(p), q),
        trace_of_product(p, &adjugate(q)),
        determinant(q),
    ]
}

/// Real roots of the monic cubic `s^3 + c2 s^2 + c1 s + c0`, largest first, each polished by
/// a Newton step. Returns the roots and how many are valid (1 or 3).
fn real_cubic_roots(c2: f64, c1: f64, c0: f64) -> ([f64; 3], usize) {
    let shift = c2 / 3.0;
    // Depressed cubic t^3 + p t + q with s = t - c2/3.
    let p = c1 - c2 * shift;
    let q = c0 - c1 * shift + 2.0 * shift * shift * shift;
    let half_q = 0.5 * q;
    let discriminant = half_q * half_q + p * p * p / 27.0;
    let (mut roots, count) = if discriminant > 0.0 || p >= 0.0 {
        let root_discriminant = libm::sqrt(discriminant.max(0.0));
        let u = -libm::cbrt(half_q + libm::copysign(root_discriminant, half_q));
        let t = if u != 0.0 { u - p / (3.0 * u) } else { 0.0 };
        ([t - shift, 0.0, 0.0], 1)
    } else {
        let radius = 2.0 * libm::sqrt(-p / 3.0);
        let cos3 = (3.0 * q / (p * radius)).clamp(-1.0, 1.0);
        let angle = libm::acos(cos3) / 3.0;
        let third = 2.0 * core::f64::consts::FRAC_PI_3;
        (
            [
                radius * libm::cos(angle) - shift,
                radius * libm::cos(angle - third) - shift,
                radius * libm::cos(angle - 2.0 * third) - shift,
            ],
            3,
        )
    };
    for s in roots.iter_mut().take(count) {
        let value = ((*s + c2) * *s + c1) * *s + c0;
        let slope = (3.0 * *s + 2.0 * c2) * *s + c1;
        if slope != 0.0 {
            let step = value / slope;
            if step.is_finite() {
                *s -= step;
            }
        }
    }
    (roots, count)
}

/// Splits a rank-2 symmetric matrix `C = l m^T + m l^T` into its two real lines `l`, `m`;
/// `None` when the lines are complex conjugates or the matrix has rank below 2.
fn split_line_pair(c: &Matrix3<f64>) -> Option<[Vector3<f64>; 2]> {
    // For real lines -adj(C) = p p^T with p = l x m, the lines' common point.
    let b = -adjugate(c);
    let diagonal = [b.m11, b.m22, b.m33];
    let k = if diagonal[0] >= diagonal[1] && diagonal[0] >= diagonal[2] {
        0
    } else if diagonal[1] >= diagonal[2] {
        1
    } else {
        2
    };
    let pivot = diagonal[k];
    if pivot.is_nan() || pivot <= 0.0 {
        return None;
    }
    let p = b.column(k) * (1.0 / libm::sqrt(pivot));
    // C + [p]x = 2 l m^T (up to which line is l): rank one.
    let rank_one = c + p.cross_matrix();
    let (row, col) = rank_one.iamax_full();
    let largest = rank_one[(row, col)].abs();
    if largest.is_nan() || largest == 0.0 {
        return None;
    }
    Some([
        rank_one.column(col).into_owned(),
        rank_one.row(row).transpose(),
    ])
}

/// The (up to two) intersections of a line with a conic, as homogeneous directions.
fn line_conic_intersections(
    line: &Vector3<f64>,
    conic: &Matrix3<f64>,
) -> [Option<Vector3<f64>>; 2] {
    // Orthogonal basis (u, v) of the plane `line . x = 0`, both of length
    // sqrt(1 - l_k^2) >= sqrt(2/3) for the unit line and its smallest component k.
    let line = line * (1.0 / line.norm());
    let smallest = line.iamin();
    let mut axis = Vector3::zeros();
    axis[smallest] = 1.0;
    let u = line.cross(&axis);
    let v = line.cross(&u);
    // (alpha u + beta v)^T C (alpha u + beta v) = A alpha^2 + B alpha beta + C beta^2.
    let cu = conic * u;
    let qa = u.dot(&cu);
    let qb = 2.0 * v.dot(&cu);
    let qc = v.dot(&(conic * v));
    let mut discriminant = qb * qb - 4.0 * qa * qc;
    let tolerance = 1e-12 * (qb * qb + (4.0 * qa * qc).abs());
    if discriminant < 0.0 && discriminant > -tolerance {
        discriminant = 0.0;
    }
    if discriminant.is_nan() || discriminant < 0.0 {
        return [None, None];
    }
    let h = -0.5 * (qb + libm::copysign(libm::sqrt(discriminant), qb));
    let first = u * h + v * qa;
    let second = u * qc + v * h;
    let valid = |d: Vector3<f64>| (d.norm_squared() > 0.0).then_some(d);
    [valid(first), valid(second)]
}

/// The rigid motion taking the world triangle `x` to the camera points `d_i y_i`.
fn pose_from_depths(
    depths: &Vector3<f64>,
    y: &[Vector3<f64>; 3],
    x: &[Vector3<f64>; 3],
    world_inverse: &Matrix3<f64>,
) -> Option<Pose> {
    let p0 = y[0] * depths.x;
    let e1 = y[1] * depths.y - p0;
    let e2 = y[2] * depths.z - p0;
    let camera_frame = Matrix3::from_columns(&[e1, e2, e1.cross(&e2)]);
    let rotation = camera_frame * world_inverse;
    let translation = p0 - rotation * x[0];
    let finite = rotation
        .iter()
        .chain(translation.iter())
        .all(|v| v.is_finite());
    finite.then(|| Pose::new(Rotation3::from_matrix_unchecked(rotation), translation))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn project(pose: &Pose, points: &[[f64; 3]; 3]) -> [[f64; 2]; 3] {
        points.map(|p| pose.bearing(&Vector3::new(p[0], p[1], p[2]), 0).unwrap())
    }

    /// Frobenius distance of the rotations and distance of the translations of the solution
    /// closest to `truth`.
    fn closest_error(solutions: &P3pSolutions, truth: &Pose) -> (f64, f64) {
        solutions
            .as_slice()
            .iter()
            .map(|s| {
                let rotation = (s.rotation.matrix() - truth.rotation.matrix()).norm();
                (rotation, s.translation_error(truth))
            })
            .fold((f64::INFINITY, f64::INFINITY), |best, e| {
                if e.0 + e.1 < best.0 + best.1 {
                    e
                } else {
                    best
                }
            })
    }

    #[test]
    fn cubic_roots_of_known_polynomials() {
        // (s - 1)(s - 2)(s - 3) = s^3 - 6 s^2 + 11 s - 6.
        let (roots, count) = real_cubic_roots(-6.0, 11.0, -6.0);
        assert_eq!(count, 3);
        let mut sorted = roots;
        sorted.sort_by(|a, b| a.partial_cmp(b).unwrap());
        for (r, e) in sorted.iter().zip([1.0, 2.0, 3.0]) {
            assert!((r - e).abs() < 1e-12, "{sorted:?}");
        }
        // (s - 2)(s^2 + 1) = s^3 - 2 s^2 + s - 2: one real root.
        let (roots, count) = real_cubic_roots(-2.0, 1.0, -2.0);
        assert_eq!(count, 1);
        assert!((roots[0] - 2.0).abs() < 1e-12);
    }

    #[test]
    fn pencil_determinant_matches_direct_expansion() {
        let p = Matrix3::new(1.0, 2.0, 0.5, 2.0, -1.0, 0.3, 0.5, 0.3, 2.0);
        let q = Matrix3::new(0.2, -1.0, 0.0, -1.0, 3.0, 1.0, 0.0, 1.0, -0.5);
        let c = pencil_determinant(&p, &q);
        for s in [-2.0, -0.5, 0.0, 0.7, 3.0] {
            let direct = determinant(&(p + q * s));
            let poly = c[0] + s * (c[1] + s * (c[2] + s * c[3]));
            assert!((direct - poly).abs() < 1e-10 * (1.0 + direct.abs()));
        }
    }

    #[test]
    fn line_pair_splits_back_into_its_lines() {
        let l = Vector3::new(1.0, -2.0, 0.5);
        let m = Vector3::new(0.3, 1.0, 2.0);
        let c = l * m.transpose() + m * l.transpose();
        let [a, b] = split_line_pair(&c).unwrap();
        let parallel =
            |u: &Vector3<f64>, v: &Vector3<f64>| u.cross(v).norm() < 1e-9 * u.norm() * v.norm();
        assert!((parallel(&a, &l) && parallel(&b, &m)) || (parallel(&a, &m) && parallel(&b, &l)));
        // x^2 + y^2 = (x + iy)(x - iy): complex lines.
        assert!(
            split_line_pair(&Matrix3::new(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0)).is_none()
        );
    }

    #[test]
    fn identity_pose_fixture() {
        let points = [[0.0, 0.0, 5.0], [1.0, 0.0, 5.0], [0.0, 1.0, 6.0]];
        let bearings = [[0.0, 0.0], [0.2, 0.0], [0.0, 1.0 / 6.0]];
        let solutions = solve(&bearings, &points).unwrap();
        let (rotation, translation) = closest_error(&solutions, &Pose::identity());
        assert!(
            rotation < 1e-12 && translation < 1e-12,
            "{rotation} {translation}"
        );
        for pose in solutions.as_slice() {
            for (p, b) in points.iter().zip(&bearings) {
                let back = pose.bearing(&Vector3::new(p[0], p[1], p[2]), 0).unwrap();
                assert!((back[0] - b[0]).abs() < 1e-9 && (back[1] - b[1]).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn general_pose_fixture() {
        let truth = Pose::new(
            Rotation3::from_euler_angles(0.3, -0.2, 1.1),
            Vector3::new(0.5, -0.3, 6.0),
        );
        let points = [[1.0, 0.5, -0.2], [-0.7, 1.2, 0.4], [0.3, -1.1, 0.9]];
        let solutions = solve(&project(&truth, &points), &points).unwrap();
        assert!(!solutions.is_empty() && solutions.len() <= MAX_SOLUTIONS);
        let (rotation, translation) = closest_error(&solutions, &truth);
        assert!(
            rotation < 1e-9 && translation < 1e-9,
            "{rotation} {translation}"
        );
    }

    #[test]
    fn rejects_bad_input() {
        let points = [[0.0, 0.0, 5.0], [1.0, 0.0, 5.0], [0.0, 1.0, 6.0]];
        let bearings = [[0.0, 0.0], [0.2, 0.0], [0.0, 1.0 / 6.0]];
        let mut nan_points = points;
        nan_points[2][1] = f64::NAN;
        assert_eq!(
            solve(&bearings, &nan_points),
            Err(Error::NonFinite {
                input: Input::Points3d,
                index: 2
            })
        );
        let mut inf_bearings = bearings;
        inf_bearings[1][0] = f64::INFINITY;
        assert_eq!(
            solve(&inf_bearings, &points),
            Err(Error::NonFinite {
                input: Input::Keypoints,
                index: 1
            })
        );
        let collinear = [[0.0, 0.0, 5.0], [1.0, 0.0, 5.0], [2.0, 0.0, 5.0]];
        assert_eq!(
            solve(&bearings, &collinear),
            Err(Error::DegenerateConfiguration)
        );
        let coincident = [[0.0, 0.0, 5.0], [0.0, 0.0, 5.0], [0.0, 1.0, 6.0]];
        assert_eq!(
            solve(&bearings, &coincident),
            Err(Error::DegenerateConfiguration)
        );
        let same_rays = [[0.1, 0.0], [0.1, 0.0], [0.0, 0.2]];
        assert_eq!(
            solve(&same_rays, &points),
            Err(Error::DegenerateConfiguration)
        );
    }

    /// Number of positive-depth solutions found by scanning the depth of the first point:
    /// for each sign choice, the depths of the other two follow from the 01 and 02 equations
    /// and a sign change of the 12 residual marks a solution.
    fn scanned_solution_count(bearings: &[[f64; 2]; 3], points: &[[f64; 3]; 3]) -> usize {
        let y = bearings.map(|b| unit_ray(&b));
        let x = points.map(|p| Vector3::new(p[0], p[1], p[2]));
        let (m01, m02, m12) = (y[0].dot(&y[1]), y[0].dot(&y[2]), y[1].dot(&y[2]));
        let a01 = (x[0] - x[1]).norm_squared();
        let a02 = (x[0] - x[2]).norm_squared();
        let a12 = (x[1] - x[2]).norm_squared();
        let d_max = libm::sqrt((a01 / (1.0 - m01 * m01)).min(a02 / (1.0 - m02 * m02)));
        let steps = 40_000;
        let mut count = 0;
        for (s1, s2) in [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] {
            let mut previous: Option<f64> = None;
            for i in 1..steps {
                let d0 = d_max * i as f64 / steps as f64;
                let r1 = a01 - d0 * d0 * (1.0 - m01 * m01);
                let r2 = a02 - d0 * d0 * (1.0 - m02 * m02);
                let (d1, d2) = (
                    m01 * d0 + s1 * libm::sqrt(r1),
                    m02 * d0 + s2 * libm::sqrt(r2),
                );
                if r1 < 0.0 || r2 < 0.0 || d1 <= 0.0 || d2 <= 0.0 {
                    previous = None;
                    continue;
                }
                let f = d1 * d1 + d2 * d2 - 2.0 * m12 * d1 * d2 - a12;
                if previous.is_some_and(|p| (p > 0.0) != (f > 0.0)) {
                    count += 1;
                }
                previous = Some(f);
            }
        }
        count
    }

    #[test]
    fn finds_every_solution_a_depth_scan_finds_and_only_true_ones() {
        // Random (mostly outlier) triples have zero to four solutions.
        let scene = crate::test_scene::Scene::new(17, 600, 0, 0.0);
        let mut histogram = [0usize; MAX_SOLUTIONS + 1];
        for k in 0..120 {
            let index = [k, 200 + k, 400 + k];
            let bearings = index.map(|i| scene.bearings[i]);
            let points = index.map(|i| scene.points[i]);
            let Ok(solutions) = solve(&bearings, &points) else {
                continue;
            };
            // The scan can miss a root next to a fold of its parametrisation, never invent one.
            let scanned = scanned_solution_count(&bearings, &points);
            assert!(
                solutions.len() >= scanned,
                "triple {k}: {} < {scanned}",
                solutions.len()
            );
            for pose in solutions.as_slice() {
                for (p, b) in points.iter().zip(&bearings) {
                    let back = pose.bearing(&Vector3::new(p[0], p[1], p[2]), 0).unwrap();
                    assert!((back[0] - b[0]).abs() < 1e-9 && (back[1] - b[1]).abs() < 1e-9);
                }
            }
            histogram[solutions.len()] += 1;
        }
        // The check is not vacuous: several solution counts occur.
        assert!(
            histogram.iter().filter(|&&c| c > 0).count() >= 3,
            "{histogram:?}"
        );
    }

    mod properties {
        use super::*;
        use crate::rng::SplitMix64;
        use crate::test_scene::{random_pose, rotation_distance, transform_points, Scene};
        use proptest::prelude::*;

        fn triple(scene: &Scene) -> ([[f64; 2]; 3], [[f64; 3]; 3]) {
            (
                [scene.bearings[0], scene.bearings[1], scene.bearings[2]],
                [scene.points[0], scene.points[1], scene.points[2]],
            )
        }

        /// A triangle with sides of at least 1 and angles of at least 5 degrees.
        fn well_conditioned(points: &[[f64; 3]; 3]) -> bool {
            let world = points.map(|p| Vector3::new(p[0], p[1], p[2]));
            (0..3).all(|i| {
                let a = world[(i + 1) % 3] - world[i];
                let b = world[(i + 2) % 3] - world[i];
                a.norm() > 1.0 && a.cross(&b).norm() > 0.087 * a.norm() * b.norm()
            })
        }

        fn same_pose(a: &Pose, b: &Pose, tolerance: f64) -> bool {
            rotation_distance(a, b) < tolerance
                && a.translation_error(b) < tolerance * (1.0 + b.translation.norm())
        }

        fn contains(solutions: &P3pSolutions, pose: &Pose, tolerance: f64) -> bool {
            solutions
                .as_slice()
                .iter()
                .any(|s| same_pose(s, pose, tolerance))
        }

        proptest! {
            #![proptest_config(ProptestConfig::with_cases(256))]

            #[test]
            fn noise_free_scenes_recover_the_pose(seed in any::<u64>()) {
                let scene = Scene::new(seed, 3, 3, 0.0);
                let (bearings, points) = triple(&scene);
                prop_assume!(well_conditioned(&points));
                let solutions = solve(&bearings, &points).unwrap();
                prop_assert!(contains(&solutions, &scene.pose, 1e-6));
                for pose in solutions.as_slice() {
                    for (p, b) in points.iter().zip(&bearings) {
                        let back = pose.bearing(&Vector3::new(p[0], p[1], p[2]), 0).unwrap();
                        prop_assert!((back[0] - b[0]).abs() < 1e-8 && (back[1] - b[1]).abs() < 1e-8);
                    }
                }
            }

            #[test]
            fn permuting_the_correspondences_keeps_the_solutions(
                seed in any::<u64>(),
                order in Just([0usize, 1, 2]).prop_shuffle(),
            ) {
                let scene = Scene::new(seed, 3, 3, 0.0);
                let (bearings, points) = triple(&scene);
                prop_assume!(well_conditioned(&points));
                let solutions = solve(&bearings, &points).unwrap();
                let permuted = solve(&order.map(|i| bearings[i]), &order.map(|i| points[i])).unwrap();
                for pose in permuted.as_slice() {
                    prop_assert!(contains(&solutions, pose, 1e-7));
                }
                for pose in solutions.as_slice() {
                    prop_assert!(contains(&permuted, pose, 1e-7));
                }
            }

            #[test]
            fn rigid_change_of_world_frame_moves_the_solutions_with_it(
                seed in any::<u64>(),
                frame_seed in any::<u64>(),
            ) {
                let scene = Scene::new(seed, 3, 3, 0.0);
                let (bearings, points) = triple(&scene);
                prop_assume!(well_conditioned(&points));
                let frame = random_pose(&mut SplitMix64::new(frame_seed));
                let moved = transform_points(&frame, &points);
                let moved: [[f64; 3]; 3] = [moved[0], moved[1], moved[2]];
                let solutions = solve(&bearings, &points).unwrap();
                let in_new_frame = solve(&bearings, &moved).unwrap();
                let back_to_world = frame.inverse();
                for pose in solutions.as_slice() {
                    prop_assert!(contains(&in_new_frame, &pose.compose(&back_to_world), 1e-7));
                }
                prop_assert_eq!(solutions.len(), in_new_frame.len());
            }
        }
    }
}
