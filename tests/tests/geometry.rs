//! Camera and pose geometry across crates.

use gomatch::camera::{Camera, CameraModel};
use gomatch::Pose;
use nalgebra::{Rotation3, Vector3};

#[test]
fn projected_point_round_trips_through_pixels() {
    let camera = Camera::from_colmap(
        CameraModel::SimpleRadial,
        800,
        600,
        &[700.0, 400.0, 300.0, -0.12],
    )
    .unwrap();
    let pose = Pose::new(
        Rotation3::from_euler_angles(0.2, 0.1, -0.3),
        Vector3::new(0.1, 0.2, 3.0),
    );
    let point = Vector3::new(0.4, -0.3, 1.0);
    let bearing = pose.bearing(&point, 0).unwrap();
    let pixel = camera.bearing_to_pixel(bearing).unwrap();
    let back = camera.pixel_to_bearing(pixel).unwrap();
    assert!((back[0] - bearing[0]).abs() < 1e-12 && (back[1] - bearing[1]).abs() < 1e-12);
}
