//! A tiny deterministic scene, map, model and query, built through the public API, for
//! tests that run many localizations (the link soak, the fuzz targets): points on a grid
//! ([`TINY_POINTS`], or fewer) seen by two views of one pinhole camera, a model with `d = 8` and random weights.

use gomatch::weights::{tensor_spec, ModelConfig, Precision};
use gomatch::Camera;
use gomatch_blobs::convert::{write_blob, Options};
use gomatch_blobs::float_linear::FloatLinear;

use crate::map::build_map;
use crate::readers::colmap::{parse_cameras_txt, parse_images_txt, parse_points_txt};
use crate::scene::Scene;

/// Image ids of the two views.
pub const TINY_VIEWS: [u32; 2] = [10, 20];
/// Focal length and principal point of the camera (640 x 480 pixels).
const FOCAL: f64 = 500.0;
const CENTRE: [f64; 2] = [320.0, 240.0];
/// Points of the scene the link soak and the tests use (the fuzz targets use fewer).
pub const TINY_POINTS: usize = 80;

/// A [`ModelConfig::TINY`] blob in f32 with weights in [-0.5, 0.5) drawn from `seed`.
pub fn tiny_model_blob(seed: u32) -> anyhow::Result<Vec<u8>> {
    random_model_blob(&ModelConfig::TINY, seed)
}

/// A `config` blob in f32 with weights in [-0.5, 0.5) drawn from `seed`.
pub fn random_model_blob(config: &ModelConfig, seed: u32) -> anyhow::Result<Vec<u8>> {
    let mut state = seed;
    let mut next = move || {
        state = state.wrapping_mul(747_796_405).wrapping_add(2_891_336_453);
        (state >> 8) as f32 / (1u32 << 24) as f32 - 0.5
    };
    let tensors: Vec<FloatLinear> = (0..)
        .map_while(|i| tensor_spec(config, i))
        .map(|spec| FloatLinear {
            rows: spec.rows,
            cols: spec.cols,
            weights: (0..spec.rows * spec.cols).map(|_| next()).collect(),
            bias: (0..if spec.bias { spec.rows } else { 0 })
                .map(|_| next())
                .collect(),
        })
        .collect();
    write_blob(config, &Options::new(Precision::F32), &tensors)
}

/// The first `count` 3D points of a wavy grid 10 points wide about 5 units in front of
/// the views.
fn points(count: usize) -> Vec<[f64; 3]> {
    (0..count)
        .map(|i| {
            let (u, v) = ((i % 10) as f64 * 0.3 - 1.35, (i / 10) as f64 * 0.3 - 1.05);
            [u, v, 5.0 + 0.3 * (3.0 * u + 2.0 * v).sin()]
        })
        .collect()
}

/// The pixel of `p` seen by an unrotated camera at `x` on the x axis.
fn project(p: &[f64; 3], x: f64) -> [f64; 2] {
    [
        FOCAL * (p[0] - x) / p[2] + CENTRE[0],
        FOCAL * p[1] / p[2] + CENTRE[1],
    ]
}

/// The scene of `points` points as COLMAP text files: `cameras.txt`, `images.txt`,
/// `points3D.txt`.
pub fn tiny_scene_txt(points: usize) -> [String; 3] {
    let [cx, cy] = CENTRE;
    let cameras = format!("1 SIMPLE_PINHOLE 640 480 {FOCAL} {cx} {cy}\n");
    let points = self::points(points);
    let mut images = String::new();
    for (image_id, x) in TINY_VIEWS.iter().zip([-0.3, 0.3]) {
        // World-to-camera translation of a camera centred at (x, 0, 0).
        images += &format!("{image_id} 1 0 0 0 {} 0 0 1 view{image_id}.jpg\n", -x);
        for (id, p) in points.iter().enumerate() {
            let [u, v] = project(p, x);
            images += &format!("{u} {v} {id} ");
        }
        images += "\n";
    }
    let mut points3d = String::new();
    for (id, [x, y, z]) in points.iter().enumerate() {
        points3d += &format!(
            "{id} {x} {y} {z} 128 128 128 0.5 {} {id} {} {id}\n",
            TINY_VIEWS[0], TINY_VIEWS[1]
        );
    }
    [cameras, images, points3d]
}

/// The scene of [`tiny_scene_txt`] as OpenSfM files: `reconstruction.json` and
/// `tracks.csv` (`crate::readers::opensfm`; shots `view10.jpg`, `view20.jpg`, one track per point,
/// feature id = point id).
pub fn tiny_scene_opensfm(points: usize) -> [String; 2] {
    let size = CENTRE[0].max(CENTRE[1]) * 2.0;
    let points = self::points(points);
    let mut shots = Vec::new();
    let mut tracks = String::from("OPENSFM_TRACKS_VERSION_v2\n");
    for (image_id, x) in TINY_VIEWS.iter().zip([-0.3, 0.3]) {
        let name = format!("view{image_id}.jpg");
        shots.push(format!(
            r#""{name}": {{"rotation": [0, 0, 0], "translation": [{}, 0, 0], "camera": "c"}}"#,
            -x
        ));
        for (id, p) in points.iter().enumerate() {
            let [u, v] = project(p, x);
            let (nx, ny) = ((u - CENTRE[0]) / size, (v - CENTRE[1]) / size);
            tracks += &format!("{name}\t{id}\t{id}\t{nx}\t{ny}\t0.01\t128\t128\t128\n");
        }
    }
    let points_json: Vec<String> = points
        .iter()
        .enumerate()
        .map(|(id, [x, y, z])| format!(r#""{id}": {{"coordinates": [{x}, {y}, {z}]}}"#))
        .collect();
    let reconstruction = format!(
        r#"[{{"cameras": {{"c": {{"projection_type": "perspective", "width": {}, "height": {}, "focal": {}, "k1": 0, "k2": 0}}}}, "shots": {{{}}}, "points": {{{}}}}}]"#,
        (CENTRE[0] * 2.0) as u32,
        (CENTRE[1] * 2.0) as u32,
        FOCAL / size,
        shots.join(", "),
        points_json.join(", ")
    );
    [reconstruction, tracks]
}

/// The scene of [`tiny_scene_txt`], read by the COLMAP text readers.
pub fn tiny_scene(points: usize) -> anyhow::Result<Scene> {
    let [cameras, images, points] = tiny_scene_txt(points);
    Ok(Scene {
        name: "tiny".into(),
        cameras: parse_cameras_txt(&cameras)?,
        images: parse_images_txt(&images)?,
        points: parse_points_txt(&points)?,
    })
}

/// The map blob of [`tiny_scene`].
pub fn tiny_map_blob(points: usize) -> anyhow::Result<Vec<u8>> {
    build_map(&tiny_scene(points)?)
}

/// The camera of the scene.
pub fn tiny_camera() -> anyhow::Result<Camera> {
    let [cx, cy] = CENTRE;
    Camera::from_colmap(
        gomatch::camera::CameraModel::SimplePinhole,
        640,
        480,
        &[FOCAL, cx, cy],
    )
    .map_err(|e| anyhow::anyhow!("tiny camera: {e}"))
}

/// Pixels of the first `count` points (of any scene size) seen from `x` on the x axis (between the views
/// for `x` in `-0.3..0.3`).
pub fn tiny_query(x: f64, count: usize) -> Vec<[f32; 2]> {
    points(count)
        .iter()
        .map(|p| project(p, x).map(|c| c as f32))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::readers::opensfm::parse_opensfm;

    /// The OpenSfM files hold the COLMAP text's scene: the same points, poses and pixels
    /// (image ids are the shots' positions there).
    #[test]
    fn opensfm_files_hold_the_tiny_scene() {
        let colmap = tiny_scene(12).unwrap();
        let [json, csv] = tiny_scene_opensfm(12);
        let opensfm = parse_opensfm(&json, &csv, "tiny".into()).unwrap();
        opensfm.validate().unwrap();
        assert_eq!(opensfm.points.len(), colmap.points.len());
        for (id, point) in &colmap.points {
            assert!((opensfm.points[id].xyz - point.xyz).norm() < 1e-12);
        }
        for (index, image) in colmap.images.values().enumerate() {
            let other = &opensfm.images[&u32::try_from(index).unwrap()];
            assert!(other.pose.translation_error(&image.pose) < 1e-12);
            assert!(other.pose.rotation_error_deg(&image.pose) < 1e-9);
            assert_eq!(other.keypoints.len(), image.keypoints.len());
            for (a, b) in other.keypoints.iter().zip(&image.keypoints) {
                assert_eq!(a.point3d, b.point3d);
                assert!((a.pixel[0] - b.pixel[0]).abs() < 1e-9);
                assert!((a.pixel[1] - b.pixel[1]).abs() < 1e-9);
            }
        }
    }
}
