//! Pixel -> bearing -> pixel round trip for every camera model with realistic distortion
//! (the bearing convention the pose solver relies on).

use gomatch::camera::{Camera, MODELS};
use proptest::prelude::*;

/// Intrinsics of a camera of the given model: focal 0.7 to 1.5 image widths, principal
/// point near the centre, distortion of real lenses (barrel or pincushion).
fn camera_strategy() -> impl Strategy<Value = Camera> {
    let models = prop::sample::select(MODELS.iter().map(|spec| spec.model).collect::<Vec<_>>());
    (
        models,
        640u32..2000,
        0.5f64..0.8,
        0.7f64..1.5,
        0.95f64..1.05,
        -0.02f64..0.02,
        -0.25f64..0.1,
        -0.05f64..0.05,
        -1e-3f64..1e-3,
        -1e-3f64..1e-3,
    )
        .prop_map(
            |(model, width, aspect, focal, fy_ratio, offset, k1, k2, p1, p2)| {
                let height = (width as f64 * aspect) as u32;
                let f = focal * width as f64;
                let (cx, cy) = (
                    width as f64 * (0.5 + offset),
                    height as f64 * (0.5 - offset),
                );
                // Every intrinsic drawn, then the model keeps its own parameters of them.
                let (params, count) = Camera {
                    model,
                    width,
                    height,
                    focal: [f, f * fy_ratio],
                    principal: [cx, cy],
                    distortion: [k1, k2, p1, p2],
                }
                .colmap_params();
                Camera::from_colmap(model, width, height, &params[..count]).unwrap()
            },
        )
        .prop_filter(
            "distortion not invertible over the image (as no calibrated lens is)",
            |camera| corner_radius(camera) < 0.95 * largest_distorted_radius(camera),
        )
}

/// Largest normalised radius of an image corner: the distorted radius to undistort.
fn corner_radius(camera: &Camera) -> f64 {
    let f = camera.focal[0].min(camera.focal[1]);
    let (w, h) = (camera.width as f64, camera.height as f64);
    [[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]]
        .iter()
        .map(|c| (c[0] - camera.principal[0]).hypot(c[1] - camera.principal[1]) / f)
        .fold(0.0, f64::max)
}

/// The radial distortion `r (1 + k1 r^2 + k2 r^4)` increases up to a turning point of
/// barrel lenses; distorted radii beyond its value there have no undistorted preimage.
fn largest_distorted_radius(camera: &Camera) -> f64 {
    let [k1, k2, ..] = camera.distortion;
    let distort = |r: f64| r * (1.0 + k1 * r * r + k2 * r.powi(4));
    let mut best = 0.0f64;
    for i in 1..=4000 {
        let value = distort(i as f64 * 1e-3);
        if value < best {
            break;
        }
        best = value;
    }
    best
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(2000))]

    #[test]
    fn pixel_bearing_pixel_round_trip_is_below_1e_4_px(
        camera in camera_strategy(),
        u in 0.0f64..1.0,
        v in 0.0f64..1.0,
    ) {
        let pixel = [u * camera.width as f64, v * camera.height as f64];
        let bearing = camera.pixel_to_bearing(pixel).unwrap();
        let back = camera.bearing_to_pixel(bearing).unwrap();
        let error = ((back[0] - pixel[0]).powi(2) + (back[1] - pixel[1]).powi(2)).sqrt();
        prop_assert!(error < 1e-4, "{camera:?} {pixel:?} -> {back:?}: {error} px");
    }
}
