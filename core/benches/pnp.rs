//! Criterion benchmarks of the pose solver: P3P alone, and the full LO-RANSAC-PnP on a
//! 200-correspondence set with 50% outliers (noise sigma 1e-3 on the normalised plane).

use criterion::{criterion_group, criterion_main, Criterion};
use gomatch::rng::SplitMix64;
use gomatch::{estimate_pose, p3p, PnpWorkspace, Pose, RansacConfig};
use nalgebra::{Rotation3, Vector3};
use std::hint::black_box;

/// Gaussian sample by Box-Muller.
fn gaussian(rng: &mut SplitMix64) -> f64 {
    let u = 1.0 - rng.unit_f64();
    let v = rng.unit_f64();
    (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
}

/// A camera looking at points 4 to 12 units ahead within a 60 degree field of view; the
/// first `count * (1 - outlier_ratio)` bearings are exact projections plus noise, the rest
/// random.
fn scene(
    count: usize,
    outlier_ratio: f64,
    sigma: f64,
    seed: u64,
) -> (Pose, Vec<[f64; 2]>, Vec<[f64; 3]>) {
    let mut rng = SplitMix64::new(seed);
    let pose = Pose::new(
        Rotation3::from_euler_angles(
            rng.unit_f64() * 6.0,
            rng.unit_f64() * 6.0,
            rng.unit_f64() * 6.0,
        ),
        Vector3::new(
            rng.unit_f64() * 4.0 - 2.0,
            rng.unit_f64() * 4.0 - 2.0,
            rng.unit_f64() * 4.0 - 2.0,
        ),
    );
    let camera_to_world = pose.inverse();
    let inliers = ((1.0 - outlier_ratio) * count as f64).round() as usize;
    let mut bearings = Vec::with_capacity(count);
    let mut points = Vec::with_capacity(count);
    for i in 0..count {
        let depth = 4.0 + 8.0 * rng.unit_f64();
        let b = [rng.unit_f64() * 1.2 - 0.6, rng.unit_f64() * 1.2 - 0.6];
        let x = camera_to_world.transform(&(Vector3::new(b[0], b[1], 1.0) * depth));
        points.push([x.x, x.y, x.z]);
        bearings.push(if i < inliers {
            [
                b[0] + sigma * gaussian(&mut rng),
                b[1] + sigma * gaussian(&mut rng),
            ]
        } else {
            [rng.unit_f64() * 1.2 - 0.6, rng.unit_f64() * 1.2 - 0.6]
        });
    }
    (pose, bearings, points)
}

/// Bearings and world points of one P3P problem.
type Triple = ([[f64; 2]; 3], [[f64; 3]; 3]);

fn bench_p3p(c: &mut Criterion) {
    // 64 triples of random correspondences of a 50%-outlier scene: the mix RANSAC solves.
    let (_, bearings, points) = scene(192, 0.5, 1e-3, 1);
    let triples: Vec<Triple> = (0..64)
        .map(|k| {
            let i = [k, 64 + k, 128 + (k * 7) % 64];
            (i.map(|j| bearings[j]), i.map(|j| points[j]))
        })
        .collect();
    let mut next = 0;
    c.bench_function("p3p", |b| {
        b.iter(|| {
            let (bearing, point) = &triples[next % triples.len()];
            next += 1;
            p3p::solve(black_box(bearing), black_box(point)).map(|s| s.len())
        })
    });
}

fn bench_ransac(c: &mut Criterion) {
    let (_, bearings, points) = scene(200, 0.5, 1e-3, 2);
    let mut workspace = Box::new(PnpWorkspace::<1024>::new());
    let config = RansacConfig::new();
    c.bench_function("ransac_pnp_200_points_50pct_outliers", |b| {
        b.iter(|| {
            let estimate = estimate_pose(
                black_box(&bearings),
                black_box(&points),
                &config,
                &mut workspace,
            )
            .unwrap();
            estimate.inlier_count
        })
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(30).measurement_time(std::time::Duration::from_secs(3));
    targets = bench_p3p, bench_ransac
}
criterion_main!(benches);
