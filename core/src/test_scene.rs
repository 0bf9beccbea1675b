//! Synthetic scenes for the unit tests and proptests of the pose solver.

use std::vec::Vec;

use nalgebra::{Rotation3, Vector3};

use crate::pose::Pose;
use crate::rng::SplitMix64;

/// A camera, world points 4 to 12 units in front of it within a 66 degree field of view,
/// and their bearing vectors: exact (plus optional noise) for the first `inliers`, random
/// for the rest.
pub struct Scene {
    pub pose: Pose,
    pub bearings: Vec<[f64; 2]>,
    pub points: Vec<[f64; 3]>,
}

fn uniform(rng: &mut SplitMix64, low: f64, high: f64) -> f64 {
    low + (high - low) * rng.unit_f64()
}

fn gaussian(rng: &mut SplitMix64) -> f64 {
    let u = 1.0 - rng.unit_f64();
    let v = rng.unit_f64();
    libm::sqrt(-2.0 * libm::log(u)) * libm::cos(2.0 * core::f64::consts::PI * v)
}

/// A random pose: any rotation, translation within 3 units of the origin.
pub fn random_pose(rng: &mut SplitMix64) -> Pose {
    let axis_angle = Vector3::new(
        uniform(rng, -3.0, 3.0),
        uniform(rng, -3.0, 3.0),
        uniform(rng, -3.0, 3.0),
    );
    let translation = Vector3::new(
        uniform(rng, -3.0, 3.0),
        uniform(rng, -3.0, 3.0),
        uniform(rng, -3.0, 3.0),
    );
    Pose::new(Rotation3::new(axis_angle), translation)
}

impl Scene {
    pub fn new(seed: u64, count: usize, inliers: usize, noise_sigma: f64) -> Self {
        let mut rng = SplitMix64::new(seed);
        let pose = random_pose(&mut rng);
        let camera_to_world = pose.inverse();
        let mut bearings = Vec::with_capacity(count);
        let mut points = Vec::with_capacity(count);
        for i in 0..count {
            let b = [
                uniform(&mut rng, -0.65, 0.65),
                uniform(&mut rng, -0.65, 0.65),
            ];
            let depth = uniform(&mut rng, 4.0, 12.0);
            let x = camera_to_world.transform(&(Vector3::new(b[0], b[1], 1.0) * depth));
            points.push([x.x, x.y, x.z]);
            bearings.push(if i < inliers {
                [
                    b[0] + noise_sigma * gaussian(&mut rng),
                    b[1] + noise_sigma * gaussian(&mut rng),
                ]
            } else {
                [
                    uniform(&mut rng, -0.65, 0.65),
                    uniform(&mut rng, -0.65, 0.65),
                ]
            });
        }
        Self {
            pose,
            bearings,
            points,
        }
    }
}

/// Frobenius distance between two rotations.
pub fn rotation_distance(a: &Pose, b: &Pose) -> f64 {
    (a.rotation.matrix() - b.rotation.matrix()).norm()
}

/// The rigid map `X -> R X + t` applied to world points, as a pose.
pub fn transform_points(transform: &Pose, points: &[[f64; 3]]) -> Vec<[f64; 3]> {
    points
        .iter()
        .map(|p| {
            let q = transform.transform(&Vector3::new(p[0], p[1], p[2]));
            [q.x, q.y, q.z]
        })
        .collect()
}

/// 80 points on a wavy surface about 5 units in front of the origin, a 10 x 8 grid: the
/// map of the localizer's and the link's unit tests.
pub fn wavy_surface() -> Vec<[f32; 3]> {
    (0..80)
        .map(|i| {
            let (u, v) = ((i % 10) as f32 * 0.3 - 1.35, (i / 10) as f32 * 0.3 - 1.05);
            [u, v, 5.0 + 0.3 * libm::sinf(3.0 * u + 2.0 * v)]
        })
        .collect()
}
