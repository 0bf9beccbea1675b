//! Scene readers on the real models of `shared/data` (skipped with a message when absent):
//! every model loads, validates, and reprojects its observations with the stored poses as
//! accurately as `shared/data/README.md` states.

use std::path::PathBuf;

use gomatch_sim::readers::SceneSource;
use gomatch_sim::scene::median;

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

/// The 45 scenes of `shared/data/README.md`'s section "45 more real scenes": path, format, images and 3D
/// points as the README lists them, and the observations (track elements) this project's
/// readers find, every link checked both ways by `Scene::validate`.
const ADDED_SCENES: [(&str, &str, usize, usize, usize); 45] = [
    ("colmap/mamechun", "colmap", 128, 5751, 26268),
    ("colmap/softmurata", "colmap", 177, 4217, 129186),
    ("colmap/wesley_cup1", "colmap", 362, 8649, 89054),
    ("colmap/tensorf_myr", "colmap", 184, 6271, 53859),
    ("colmap/pratikk_1", "colmap", 92, 2505, 39489),
    ("colmap/pratikk_2", "colmap", 48, 2009, 18253),
    ("colmap/pratikk_4", "colmap", 47, 1626, 21094),
    ("colmap/pratikk_5", "colmap", 38, 1362, 10069),
    ("colmap/pratikk_6", "colmap", 26, 836, 7869),
    ("colmap/pratikk_7", "colmap", 14, 769, 6791),
    ("colmap/pratikk_8", "colmap", 19, 647, 7407),
    ("colmap/pratikk_9", "colmap", 10, 620, 4557),
    ("colmap/yowsitian", "colmap", 118, 852, 31139),
    ("colmap/binbin", "colmap", 101, 6885, 49127),
    ("colmap/slamdrone_output2_1", "colmap", 72, 2944, 23612),
    ("colmap/slamdrone_output2_2", "colmap", 90, 3316, 22641),
    ("colmap/slamdrone_output2_3", "colmap", 20, 602, 2945),
    ("colmap/slamdrone_output_4", "colmap", 65, 2238, 19668),
    ("colmap/kwrous", "colmap", 77, 9262, 57847),
    ("colmap/yhuoyuh", "colmap", 71, 4414, 30839),
    ("colmap/splatam_up", "colmap", 50, 5255, 55090),
    ("colmap/considering_d1", "colmap", 44, 2358, 14186),
    ("colmap/xuzhy", "colmap", 29, 7562, 50334),
    ("colmap/lofi_a", "colmap", 28, 1404, 5568),
    ("colmap/carlygp", "colmap", 26, 5561, 25103),
    ("colmap/bjr_a", "colmap", 25, 1409, 5970),
    ("colmap/bjr_b", "colmap", 20, 1613, 6131),
    ("colmap/bjr_c", "colmap", 8, 1483, 5241),
    ("colmap/bartoszek", "colmap", 23, 1443, 5931),
    ("colmap/ranjith", "colmap", 13, 3550, 13785),
    ("colmap/flopau", "colmap", 13, 1609, 10225),
    ("colmap/bgopen3d", "colmap", 10, 2312, 8025),
    ("colmap/vijay_final_try", "colmap", 14, 3036, 15987),
    ("colmap/vijay_ft1", "colmap", 10, 2167, 10461),
    ("colmap/vijay_boxes1", "colmap", 6, 3154, 11596),
    ("colmap/avishai", "colmap", 8, 10160, 46434),
    ("colmap/yding", "colmap", 7, 699, 2616),
    ("colmap/halogen", "colmap", 5, 2013, 6760),
    ("colmap/kyumin", "colmap", 5, 2137, 6890),
    ("colmap/marychris", "colmap", 5, 3592, 12042),
    ("opensfm/projcv_cc9d27", "opensfm", 26, 3173, 8540),
    ("opensfm/applebanana", "opensfm", 103, 6570, 23231),
    ("opensfm/bathtub", "opensfm", 19, 1191, 2980),
    ("bundler/obscurs_a", "bundler", 150, 3169, 17493),
    ("bundler/obscurs_b", "bundler", 104, 3133, 14988),
];

fn added_scene_source(data: &std::path::Path, path: &str, format: &str) -> SceneSource {
    match format {
        "colmap" => SceneSource::Colmap(data.join(path)),
        "opensfm" => SceneSource::OpenSfm(data.join(path)),
        _ => SceneSource::Bundler(data.join(path).join("bundle.out")),
    }
}

/// Loads every added scene of one format: counts as listed, and the stored poses reproject
/// the observations with a median error under 2 px (the README's figures are 0.27-1.50 px).
fn check_added_scenes(format: &str) {
    let Some(data) = shared_data() else { return };
    let mut mismatches = Vec::new();
    for (path, _, images, points, observations) in ADDED_SCENES.iter().filter(|s| s.1 == format) {
        let scene = added_scene_source(&data, path, format).load().unwrap();
        assert_eq!(scene.name, *path);
        let error = scene.median_reprojection_error(None, 0).unwrap();
        let found = (
            scene.images.len(),
            scene.points.len(),
            scene.observation_count(),
        );
        println!(
            "{path}: {} images, {} points, {} observations, median reprojection error {error:.3} px",
            found.0, found.1, found.2
        );
        assert!(error < 2.0, "{path}: median reprojection error {error} px");
        if found != (*images, *points, *observations) {
            mismatches.push(format!("{path}: {found:?}"));
        }
    }
    assert!(mismatches.is_empty(), "{mismatches:#?}");
}

#[test]
fn added_colmap_scenes_load_with_their_counts() {
    check_added_scenes("colmap");
}

#[test]
fn opensfm_scenes_load_with_their_counts() {
    check_added_scenes("opensfm");
}

#[test]
fn bundler_scenes_with_name_lists_load_with_their_counts() {
    check_added_scenes("bundler");
    let Some(data) = shared_data() else { return };
    let scene = SceneSource::Bundler(data.join("bundler/obscurs_b/bundle.out"))
        .load()
        .unwrap();
    assert_eq!(scene.images[&0].name, "Scan_01-back.png");
}

#[test]
fn colmap_text_export_round_trips_a_binary_model() {
    let Some(data) = shared_data() else { return };
    let scene = SceneSource::Colmap(data.join("colmap/mouse"))
        .load()
        .unwrap();
    let dir = std::env::temp_dir().join(format!("gomatch-colmap-roundtrip-{}", std::process::id()));
    gomatch_sim::readers::colmap::write_model_txt(&scene, &dir).unwrap();
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

/// Runs the protocol on a real scene and checks the ground truth against the model's own
/// triangulation. Real models hold near-duplicate 3D points (tracks that were never
/// merged), so a ground-truth pair "agrees" when its keypoint triangulates the matched
/// point or a point within 2 % of its depth from it; and most pairs must join a keypoint
/// that the model triangulated.
fn check_protocol(source: SceneSource) {
    use gomatch_sim::protocol::{scene_samples, ProtocolParams};
    let scene = source.load().unwrap();
    let params = ProtocolParams {
        queries_per_scene: 40,
        ..ProtocolParams::default()
    };
    let samples = scene_samples(&scene, &params);
    assert!(!samples.is_empty(), "{}: no query", scene.name);
    let (mut pairs, mut triangulated, mut agreeing) = (0usize, 0usize, 0usize);
    let (mut keypoints, mut views) = (0usize, 0usize);
    let mut inlier_rates = Vec::new();
    for sample in &samples {
        assert!(sample.views.len() >= params.min_views && sample.views.len() <= params.k);
        assert!(sample.keypoints.len() <= params.max_keypoints);
        assert!(sample.views.iter().all(|v| v.image_id != sample.image_id));
        keypoints += sample.keypoints.len();
        for view in &sample.views {
            assert!(view.point_ids.len() <= params.max_points);
            views += 1;
            pairs += view.gt_pairs.len();
            for &(k, p) in &view.gt_pairs {
                let Some(model_point) = sample.keypoints.point3d[k] else {
                    continue;
                };
                triangulated += 1;
                let matched = view.xyz[p];
                let depth = sample.pose.transform(&matched).z;
                let gap = (scene.points[&model_point].xyz - matched).norm();
                if model_point == view.point_ids[p] || gap < 0.02 * depth {
                    agreeing += 1;
                }
            }
            inlier_rates.push(view.gt_pairs.len() as f64 / sample.keypoints.len() as f64);
        }
    }
    let triangulated_share = triangulated as f64 / pairs as f64;
    let agreement = agreeing as f64 / triangulated as f64;
    println!(
        "{}: {} queries, {:.0} keypoints/query, {:.1} views/query, {:.0} GT matches/view, \
         median inlier rate {:.3}, {:.1} % of GT pairs on triangulated keypoints, {:.1} % of \
         those agree with the model",
        scene.name,
        samples.len(),
        keypoints as f64 / samples.len() as f64,
        views as f64 / samples.len() as f64,
        pairs as f64 / views as f64,
        median(&mut inlier_rates).unwrap(),
        100.0 * triangulated_share,
        100.0 * agreement
    );
    assert!(
        triangulated_share > 0.85,
        "{}: {triangulated_share}",
        scene.name
    );
    assert!(agreement > 0.95, "{}: agreement {agreement}", scene.name);
}

#[test]
fn protocol_ground_truth_agrees_with_the_models_triangulation() {
    let Some(data) = shared_data() else { return };
    for scene in ["mouse", "sceaux", "wmv_video0", "wmv_video3"] {
        check_protocol(SceneSource::Colmap(data.join("colmap").join(scene)));
    }
}

/// On synthetic scenes, whose 3D points are exact and whose keypoints carry only pixel
/// noise, the ground truth must find a triangulated query keypoint's own point in a view
/// whenever its noise is below the threshold (mutual nearest neighbours lose a few to
/// closer neighbours) and mostly pair keypoints with their own points. With a wrong query
/// pose no keypoint meets its own point; what remains are chance coincidences of dense
/// keypoints and projections, which the real models show as well (turning the query by
/// 2 degrees leaves 4.6 % of the pairs on colmap/mouse and 10.4 % on colmap/sceaux).
#[test]
fn protocol_ground_truth_on_synthetic_scenes_follows_the_triangulation() {
    use gomatch::Pose;
    use gomatch_sim::protocol::synthetic::synthetic_scene;
    use gomatch_sim::protocol::{query_sample, select_queries, ProtocolParams};
    use nalgebra::{Rotation3, Vector3};

    let params = ProtocolParams {
        queries_per_scene: 10,
        ..ProtocolParams::default()
    };
    for index in 0..3 {
        let scene = synthetic_scene(5, index);
        let queries = select_queries(&scene, &params);
        assert!(!queries.is_empty(), "{}: no query", scene.name);
        let (mut candidates, mut found, mut pairs, mut own_pairs) = (0usize, 0, 0, 0);
        let (mut wrong_pairs, mut wrong_own_pairs) = (0usize, 0);
        for &query in &queries {
            let sample = query_sample(&scene, query, &params).unwrap();
            for view in &sample.views {
                for (k, point3d) in sample.keypoints.point3d.iter().enumerate() {
                    let Some(p) =
                        point3d.and_then(|id| view.point_ids.iter().position(|&v| v == id))
                    else {
                        continue;
                    };
                    let projected = sample.pose.bearing(&view.xyz[p], 0).unwrap();
                    let keypoint = sample.keypoints.bearings[k];
                    let distance = (projected[0] - keypoint[0]).hypot(projected[1] - keypoint[1]);
                    if distance < params.gt_threshold {
                        candidates += 1;
                        found += usize::from(view.gt_pairs.contains(&(k, p)));
                    }
                }
                pairs += view.gt_pairs.len();
                own_pairs += view
                    .gt_pairs
                    .iter()
                    .filter(|&&(k, p)| sample.keypoints.point3d[k] == Some(view.point_ids[p]))
                    .count();
            }
            // Turn the query camera by 2 degrees about its centre: its projections move
            // by ~35 thresholds.
            let turn = Pose::new(
                Rotation3::from_axis_angle(&Vector3::y_axis(), 2f64.to_radians()),
                Vector3::zeros(),
            );
            let mut moved = scene.clone();
            let image = moved.images.get_mut(&query).unwrap();
            image.pose = turn.compose(&image.pose);
            let wrong = query_sample(&moved, query, &params).unwrap();
            for view in &wrong.views {
                wrong_pairs += view.gt_pairs.len();
                wrong_own_pairs += view
                    .gt_pairs
                    .iter()
                    .filter(|&&(k, p)| wrong.keypoints.point3d[k] == Some(view.point_ids[p]))
                    .count();
            }
        }
        let recall = found as f64 / candidates as f64;
        let precision = own_pairs as f64 / pairs as f64;
        println!(
            "{}: {} queries, {pairs} GT pairs, {:.1} % found of the keypoints within the \
             threshold of their own point, {:.1} % of pairs on the keypoint's own point, \
             {wrong_pairs} pairs with a 2-degree pose error",
            scene.name,
            queries.len(),
            100.0 * recall,
            100.0 * precision
        );
        assert!(recall > 0.95, "{}: recall {recall}", scene.name);
        assert!(precision > 0.9, "{}: precision {precision}", scene.name);
        assert_eq!(wrong_own_pairs, 0, "{}", scene.name);
        assert!(
            wrong_pairs * 5 < pairs,
            "{}: {wrong_pairs} of {pairs}",
            scene.name
        );
    }
}

/// `map rank`'s shares: per block of stored keypoints, and on sceaux the evidence behind the
/// protocol's ranked caps (keypoints stored last are triangulated more often).
#[test]
fn sceaux_keypoints_stored_last_are_triangulated_more_often() {
    use gomatch_sim::map::{block_shares, first_and_last_shares};
    use gomatch_sim::scene::Keypoint;

    let keypoints: Vec<Keypoint> = [None, Some(3), Some(4), None, Some(7)]
        .map(|point3d| Keypoint {
            pixel: [0.0, 0.0],
            point3d,
        })
        .to_vec();
    assert_eq!(block_shares(&keypoints, 2), vec![0.5, 0.5, 1.0]);

    let Some(data) = shared_data() else { return };
    let sceaux = SceneSource::Colmap(data.join("colmap/sceaux"))
        .load()
        .unwrap();
    let shares = first_and_last_shares(&sceaux, 1024);
    assert_eq!(shares.len(), 11);
    let mean = |f: fn(&(u32, f64, f64)) -> f64| shares.iter().map(f).sum::<f64>() / 11.0;
    let (first, last) = (mean(|s| s.1), mean(|s| s.2));
    assert!(last > first + 0.15, "first {first}, last {last}");
}
