//! Scene readers on the real models of `shared/data` (skipped with a message when absent):
//! every model loads, validates, and reprojects its observations with the stored poses as
//! accurately as `shared/data/README.md` states.

use std::path::PathBuf;

use gomatch_sim::scene::{median, SceneSource};

/// `shared/data`, located from this crate's manifest (`<repo>/tests`), or `None` with a
/// printed reason.
fn shared_data() -> Option<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    if dir.is_dir() {
        Some(dir)
    } else {
        println!("SKIPPED: {} is absent", dir.display());
        None
    }
}

/// Points sampled for the reprojection sanity check, as in the data README.
const SANITY_POINTS: usize = 200;

/// Loads a scene and checks its median reprojection error over all observations against
/// the README's figure, which was measured on 200 random points: relative `tolerance`
/// covers that sampling (for the BAL "-pre" files three 200-point samples already spread
/// over 1.15-1.53 px). The 200-point figure is printed next to it.
fn check_reprojection(source: SceneSource, readme_median_px: f64, tolerance: f64) {
    let scene = source.load().unwrap();
    let mut sampled: Vec<f64> = (0..5)
        .map(|seed| {
            scene
                .median_reprojection_error(Some(SANITY_POINTS), seed)
                .unwrap()
        })
        .collect();
    let sampled = median(&mut sampled).unwrap();
    let all = scene.median_reprojection_error(None, 0).unwrap();
    println!(
        "{}: {} images, {} points, {} observations, median reprojection error {all:.3} px \
         (all points), {sampled:.3} px (median of five 200-point samples); README {readme_median_px} px",
        scene.name,
        scene.images.len(),
        scene.points.len(),
        scene.observation_count()
    );
    assert!(
        (all - readme_median_px).abs() <= tolerance * readme_median_px,
        "{}: median {all} px vs README {readme_median_px} px",
        scene.name
    );
}

#[test]
fn colmap_binary_models_reproject_as_documented() {
    let Some(data) = shared_data() else { return };
    check_reprojection(SceneSource::Colmap(data.join("colmap/mouse")), 0.53, 0.15);
    check_reprojection(
        SceneSource::Colmap(data.join("colmap/wmv_video0")),
        1.17,
        0.15,
    );
    check_reprojection(
        SceneSource::Colmap(data.join("colmap/wmv_video3")),
        1.02,
        0.15,
    );
}

#[test]
fn colmap_text_model_reprojects_as_documented() {
    let Some(data) = shared_data() else { return };
    check_reprojection(SceneSource::Colmap(data.join("colmap/sceaux")), 0.50, 0.15);
}

#[test]
fn bundler_model_reprojects_as_documented() {
    let Some(data) = shared_data() else { return };
    let source = SceneSource::Bundler(data.join("bundler/kermit/bundle.out"));
    let scene = source.load().unwrap();
    assert_eq!(scene.images.len(), 9, "cameras 4 and 6 are unplaced");
    assert!(!scene.images.contains_key(&4) && !scene.images.contains_key(&6));
    assert_eq!(scene.points.len(), 634);
    check_reprojection(source, 0.18, 0.15);
}

#[test]
fn bal_pre_models_reproject_as_documented() {
    let Some(data) = shared_data() else { return };
    check_reprojection(
        SceneSource::Bal(data.join("bal/problem-49-7776-pre.txt")),
        1.8,
        0.25,
    );
    check_reprojection(
        SceneSource::Bal(data.join("bal/problem-21-11315-pre.txt")),
        3.4,
        0.25,
    );
}

#[test]
fn model_counts_match_the_data_readme() {
    let Some(data) = shared_data() else { return };
    let expected = [
        (SceneSource::Colmap(data.join("colmap/mouse")), 56, 4443),
        (SceneSource::Colmap(data.join("colmap/sceaux")), 11, 7862),
        (
            SceneSource::Colmap(data.join("colmap/wmv_video0")),
            137,
            3091,
        ),
        (
            SceneSource::Colmap(data.join("colmap/wmv_video3")),
            77,
            1839,
        ),
        (
            SceneSource::Bal(data.join("bal/problem-49-7776-pre.txt")),
            49,
            7776,
        ),
        (
            SceneSource::Bal(data.join("bal/problem-21-11315-pre.txt")),
            21,
            11315,
        ),
    ];
    for (source, images, points) in expected {
        let scene = source.load().unwrap();
        assert_eq!(
            (scene.images.len(), scene.points.len()),
            (images, points),
            "{}",
            scene.name
        );
    }
}

#[test]
fn colmap_text_export_round_trips_a_binary_model() {
    let Some(data) = shared_data() else { return };
    let scene = SceneSource::Colmap(data.join("colmap/mouse"))
        .load()
        .unwrap();
    let dir = std::env::temp_dir().join(format!("gomatch-colmap-roundtrip-{}", std::process::id()));
    gomatch_sim::colmap::write_model_txt(&scene, &dir).unwrap();
    let back = SceneSource::Colmap(dir.clone()).load().unwrap();
    std::fs::remove_dir_all(&dir).unwrap();
    assert_eq!(back.cameras, scene.cameras);
    assert_eq!(back.points, scene.points);
    assert_eq!(back.images.len(), scene.images.len());
    for (image, other) in scene.images.values().zip(back.images.values()) {
        assert_eq!(
            (image.id, &image.name, image.camera_id, &image.keypoints),
            (other.id, &other.name, other.camera_id, &other.keypoints)
        );
        assert!((image.pose.rotation.matrix() - other.pose.rotation.matrix()).amax() < 1e-12);
        assert!(image.pose.translation_error(&other.pose) < 1e-12);
    }
}
