//! The fuzz targets on stable: every committed seed (`fuzz/seeds/<target>/`) and
//! regression (`fuzz/regressions/<target>/`) runs through the same bodies as the libFuzzer
//! targets (`fuzz/bodies/mod.rs`, included here). The seeds are written by
//! `write_seeds` (ignored; run it to regenerate them:
//! `cargo test --release -p gomatch-integration --test fuzz_replay -- --ignored write_seeds`).

#[allow(dead_code)]
#[path = "../../fuzz/bodies/mod.rs"]
mod bodies;

use std::path::{Path, PathBuf};

use gomatch::link::{self, encode_frame, LocalizeRequest, Request, RequestBody, Views};
use gomatch::{Map, Model};
use gomatch_blobs::view_features::build_view_features;
use gomatch_sim::device::tiny::{tiny_query, tiny_scene, tiny_scene_opensfm, tiny_scene_txt};
use gomatch_sim::scene::Scene;
use nalgebra::UnitQuaternion;

/// Largest seed file.
const MAX_SEED_BYTES: usize = 16 * 1024;

fn fuzz_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../fuzz")
}

/// The files of `fuzz/<kind>/<target>/`, sorted (none when the folder is absent).
fn files(kind: &str, target: &str) -> Vec<PathBuf> {
    let Ok(entries) = std::fs::read_dir(fuzz_dir().join(kind).join(target)) else {
        return Vec::new();
    };
    let mut paths: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file())
        .collect();
    paths.sort();
    paths
}

/// Every seed and regression of every target runs through its body without a panic;
/// every target has seeds, each under 16 KiB.
#[test]
fn seeds_and_regressions_replay_cleanly() {
    let mut failures = Vec::new();
    let mut runs = 0;
    for (target, body) in bodies::TARGETS {
        let seeds = files("seeds", target);
        assert!(!seeds.is_empty(), "no seeds for {target}");
        for seed in &seeds {
            let len = std::fs::metadata(seed).expect("seed").len() as usize;
            assert!(len < MAX_SEED_BYTES, "{}: {len} B", seed.display());
        }
        for path in seeds.iter().chain(&files("regressions", target)) {
            let data = std::fs::read(path).expect("readable");
            runs += 1;
            if std::panic::catch_unwind(|| body(&data)).is_err() {
                failures.push(path.display().to_string());
            }
        }
    }
    println!("replayed {runs} inputs");
    assert!(failures.is_empty(), "panicked: {failures:?}");
}

/// The first bytes of each target's inputs: a mode byte for the blobs, the two file
/// lengths for the COLMAP readers.
fn three_files(files: [&[u8]; 3]) -> Vec<u8> {
    let len = |f: &[u8]| u16::try_from(f.len()).expect("small file").to_le_bytes();
    let mut out = Vec::new();
    out.extend(len(files[0]));
    out.extend(len(files[1]));
    for f in files {
        out.extend_from_slice(f);
    }
    out
}

/// The `opensfm` target's layout: a `u16` length, then `reconstruction.json` and
/// `tracks.csv`.
fn two_files(files: [&[u8]; 2]) -> Vec<u8> {
    let mut out = u16::try_from(files[0].len())
        .expect("small file")
        .to_le_bytes()
        .to_vec();
    out.extend_from_slice(files[0]);
    out.extend_from_slice(files[1]);
    out
}

fn with_mode(mode: u8, blob: &[u8]) -> Vec<u8> {
    let mut out = vec![mode];
    out.extend_from_slice(blob);
    out
}

/// The tiny scene in COLMAP's binary format: `cameras.bin`, `images.bin`, `points3D.bin`.
fn colmap_bin(scene: &Scene) -> [Vec<u8>; 3] {
    let mut cameras = (scene.cameras.len() as u64).to_le_bytes().to_vec();
    for (id, camera) in &scene.cameras {
        cameras.extend(id.to_le_bytes());
        cameras.extend(0i32.to_le_bytes()); // SIMPLE_PINHOLE
        cameras.extend(u64::from(camera.width).to_le_bytes());
        cameras.extend(u64::from(camera.height).to_le_bytes());
        for p in [camera.focal[0], camera.principal[0], camera.principal[1]] {
            cameras.extend(p.to_le_bytes());
        }
    }
    let mut images = (scene.images.len() as u64).to_le_bytes().to_vec();
    for (id, image) in &scene.images {
        images.extend(id.to_le_bytes());
        let q = UnitQuaternion::from_rotation_matrix(&image.pose.rotation);
        for v in [q.w, q.i, q.j, q.k] {
            images.extend(v.to_le_bytes());
        }
        for v in image.pose.translation.iter() {
            images.extend(v.to_le_bytes());
        }
        images.extend(image.camera_id.to_le_bytes());
        images.extend(image.name.as_bytes());
        images.push(0);
        images.extend((image.keypoints.len() as u64).to_le_bytes());
        for k in &image.keypoints {
            images.extend(k.pixel[0].to_le_bytes());
            images.extend(k.pixel[1].to_le_bytes());
            images.extend(k.point3d.unwrap_or(u64::MAX).to_le_bytes());
        }
    }
    let mut points = (scene.points.len() as u64).to_le_bytes().to_vec();
    for (id, point) in &scene.points {
        points.extend(id.to_le_bytes());
        for v in point.xyz.iter() {
            points.extend(v.to_le_bytes());
        }
        points.extend([128, 128, 128]);
        points.extend(0.5f64.to_le_bytes());
        points.extend((point.track.len() as u64).to_le_bytes());
        for t in &point.track {
            points.extend(t.image_id.to_le_bytes());
            points.extend(t.keypoint_index.to_le_bytes());
        }
    }
    [cameras, images, points]
}

/// A BAL problem and a Bundler file of two cameras looking down -z at four points.
fn bal_and_bundler() -> (String, String) {
    let points = [
        [0.0, 0.0, -5.0],
        [1.0, 0.0, -5.0],
        [0.0, 1.0, -6.0],
        [1.0, 1.0, -4.0],
    ];
    let mut bal = format!("2 {} {}\n", points.len(), 2 * points.len());
    let mut bundler = format!("# Bundle file v0.3\n2 {}\n", points.len());
    let shifts = [-0.2, 0.2];
    let project = |p: &[f64; 3], shift: f64| {
        let (x, y, z) = (p[0] + shift, p[1], p[2]);
        [-500.0 * x / z, -500.0 * y / z]
    };
    for (point, p) in points.iter().enumerate() {
        for (camera, &shift) in shifts.iter().enumerate() {
            let [u, v] = project(p, shift);
            bal += &format!("{camera} {point} {u} {v}\n");
        }
    }
    for shift in shifts {
        bal += &format!("0\n0\n0\n{shift}\n0\n0\n500\n0\n0\n");
        bundler += &format!("500 0 0\n1 0 0\n0 1 0\n0 0 1\n{shift} 0 0\n");
    }
    for (point, p) in points.iter().enumerate() {
        bal += &format!("{}\n{}\n{}\n", p[0], p[1], p[2]);
        bundler += &format!("{} {} {}\n255 255 255\n2", p[0], p[1], p[2]);
        for (camera, &shift) in shifts.iter().enumerate() {
            let [u, v] = project(p, shift);
            bundler += &format!(" {camera} {point} {u} {v}");
        }
        bundler += "\n";
    }
    (bal, bundler)
}

/// The `localize` target's layout (see `bodies::localize`): camera, configuration, view
/// selection, prior, keypoints.
fn localize_input(model: u8, params: &[f64], selector: u8, pixels: &[[f32; 2]]) -> Vec<u8> {
    let mut out = vec![model];
    out.extend(640u16.to_le_bytes());
    out.extend(480u16.to_le_bytes());
    for p in params {
        out.extend(p.to_le_bytes());
    }
    out.extend(1000u16.to_le_bytes());
    out.extend(1e-3f64.to_le_bytes());
    out.extend(0.999f64.to_le_bytes());
    out.extend(7u64.to_le_bytes());
    out.push(3);
    out.extend([4, 4]);
    out.push(selector);
    out.extend(std::iter::repeat_n(0u8, usize::from(selector % 13)));
    for v in [
        1.0f64, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.05, 0.0, 0.0,
    ] {
        out.extend(v.to_le_bytes());
    }
    if selector & 0x80 != 0 {
        out.extend(30.0f64.to_le_bytes());
    }
    for [x, y] in pixels {
        out.extend(x.to_le_bytes());
        out.extend(y.to_le_bytes());
    }
    out
}

/// `[0]` + the frame of a request.
fn request_frame(id: u32, body: RequestBody<'_>) -> Vec<u8> {
    let mut out = vec![0u8; link::rx_frame_len(bodies::CAPACITY) + 2];
    let len = encode_frame(&Request { id, body }, &mut out[1..])
        .expect("fits")
        .len();
    out.truncate(1 + len);
    out
}

/// Every seed, by target and file name.
fn seeds() -> Vec<(&'static str, &'static str, Vec<u8>)> {
    let fixture = bodies::fixture();
    let (model, map) = (&fixture.model, &fixture.map);
    let features = build_view_features(
        &Model::from_bytes(model).expect("model"),
        &Map::from_bytes(map).expect("map"),
        bodies::CAPACITY,
    )
    .expect("features");
    let scene = tiny_scene(bodies::FIXTURE_POINTS).expect("scene");
    let [cameras_txt, images_txt, points_txt] = tiny_scene_txt(bodies::FIXTURE_POINTS);
    let [cameras_bin, images_bin, points_bin] = colmap_bin(&scene);
    let [opensfm_json, opensfm_csv] = tiny_scene_opensfm(bodies::FIXTURE_POINTS);
    let (bal, bundler) = bal_and_bundler();
    let pixels = &tiny_query(0.05, bodies::CAPACITY);
    let info = request_frame(1, RequestBody::Info);
    let mut cut = request_frame(2, RequestBody::Info);
    cut.truncate(cut.len() - 2);
    let fixture_pixels = &fixture.pixels;
    let mut keypoints = vec![0u8; link::KEYPOINT_BYTES * fixture_pixels.len()];
    link::encode_keypoints(fixture_pixels, &mut keypoints).expect("fits");
    let by_image_ids = request_frame(
        3,
        RequestBody::Localize(LocalizeRequest {
            camera: fixture.camera,
            keypoints: &keypoints,
            views: Views::ImageIds(heapless::Vec::from_slice(&[10, 20]).expect("2 ids")),
        }),
    );
    let pinhole = [500.0, 320.0, 240.0];
    let opencv = [500.0, 510.0, 320.0, 240.0, -0.1, 0.01, 1e-3, -1e-3];
    vec![
        ("model_blob", "tiny-f32", with_mode(0, model)),
        ("model_blob", "tiny-f32-fixed-header", with_mode(7, model)),
        (
            "model_blob",
            "tiny-f32-cut",
            with_mode(6, &model[..model.len() / 2]),
        ),
        ("map_blob", "tiny", with_mode(0, map)),
        ("map_blob", "tiny-fixed-header", with_mode(7, map)),
        ("map_blob", "tiny-cut", with_mode(6, &map[..map.len() / 2])),
        ("view_features", "tiny", with_mode(0, &features)),
        (
            "view_features",
            "tiny-fixed-header",
            with_mode(7, &features),
        ),
        ("device_link", "no-noise", Vec::new()),
        ("device_link", "info-frame", info.clone()),
        ("device_link", "cut-frame", cut),
        ("device_link", "every-byte", (0..=255u8).collect()),
        ("device_link", "localize-image-ids", by_image_ids),
        (
            "colmap_bin",
            "tiny",
            three_files([&cameras_bin, &images_bin, &points_bin]),
        ),
        (
            "colmap_txt",
            "tiny",
            three_files([
                cameras_txt.as_bytes(),
                images_txt.as_bytes(),
                points_txt.as_bytes(),
            ]),
        ),
        ("bal", "two-cameras", bal.into_bytes()),
        ("bundler", "two-cameras", bundler.into_bytes()),
        (
            "opensfm",
            "tiny",
            two_files([opensfm_json.as_bytes(), opensfm_csv.as_bytes()]),
        ),
        (
            "localize",
            "pinhole-image-ids",
            localize_input(0, &pinhole, 2, pixels),
        ),
        (
            "localize",
            "opencv-near-prior",
            localize_input(4, &opencv, 0x82, &pixels[..bodies::CAPACITY - 4]),
        ),
        (
            "localize",
            "too-many-keypoints",
            localize_input(0, &pinhole, 2, &[pixels.as_slice(), &pixels[..2]].concat()),
        ),
    ]
}

/// Writes the seeds into `fuzz/seeds/<target>/<name>` (deterministic: the same bytes
/// each run).
#[test]
#[ignore = "writes the committed seed files"]
fn write_seeds() {
    for (target, name, bytes) in seeds() {
        let dir = fuzz_dir().join("seeds").join(target);
        std::fs::create_dir_all(&dir).expect("seed folder");
        std::fs::write(dir.join(name), &bytes).expect("written");
        println!("{target}/{name}: {} B", bytes.len());
    }
}
