//! A tiny deterministic scene, map, model and query, built through the public API, for
//! tests that run many localizations (the link soak, the fuzz targets): points on a grid
//! ([`TINY_POINTS`], or fewer) seen by two views of one pinhole camera, a model with `d = 8` and random weights.

use gomatch::weights::{tensor_spec, ModelConfig, Precision};
use gomatch::Camera;
use gomatch_tools::convert::{write_blob, FloatLinear, Options};

use crate::colmap::{parse_cameras_txt, parse_images_txt, parse_points_txt};
use crate::map::build_map;
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
