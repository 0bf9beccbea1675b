//! `gomatch-sim eval` and the localization protocol against the device path: the oracle
//! (ground-truth matches into the pose solver) localizes nearly every query of a
//! synthetic scene and of the real validation scenes, the device and the protocol pick
//! the same database points, results do not depend on the thread count, and the plot is
//! written. The real scenes are skipped with a message when `shared/` is absent.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use gomatch::acceptance::AcceptanceRule;
use gomatch::localizer::view_point_bearings;
use gomatch::map::Map;
use gomatch::LocalizerConfig;
use gomatch::Model;
use gomatch_sim::eval::{
    curve_label, evaluate, ground_truth_pairs, plot_curves, pose_is_right, protocol_samples,
    report_errors, AcceptanceSummary, EvalOptions, Matching, QueryResult, Report,
    SinkhornPrecision, TimingsMs,
};
use gomatch_sim::host::CAPACITY;
use gomatch_sim::map::{build_map, map_point_index};
use gomatch_sim::protocol::synthetic::synthetic_scene;
use gomatch_sim::protocol::ProtocolParams;
use gomatch_sim::readers::SceneSource;
use gomatch_sim::scene::Scene;

fn options(k: usize, queries: usize, threads: usize) -> EvalOptions {
    EvalOptions {
        protocol: ProtocolParams::for_localizer(k, queries, 0, CAPACITY),
        localizer: LocalizerConfig::new(),
        threads,
        view_features: false,
    }
}

fn print(report: &Report) {
    println!(
        "{} k={} {}: {} queries, {} failures, AUC @1/5/10 px {:.2} / {:.2} / {:.2}",
        report.scene,
        report.k,
        report.matcher,
        report.queries,
        report.failures,
        report.auc_1px,
        report.auc_5px,
        report.auc_10px
    );
}

fn data_dir() -> Option<PathBuf> {
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    if data.is_dir() {
        Some(data)
    } else {
        println!("SKIPPED: {} is absent", data.display());
        None
    }
}

#[test]
fn oracle_localizes_the_queries_of_synthetic_scenes() {
    for index in 0..2 {
        let scene = synthetic_scene(1, index);
        let report = evaluate(&scene, Matching::Oracle, &options(10, 15, 1), false).unwrap();
        print(&report);
        assert!(report.queries >= 10, "{} queries", report.queries);
        assert_eq!(report.failures, 0);
        assert!(report.auc_5px >= 90.0, "AUC@5px {}", report.auc_5px);
        let rotation = report.rot_deg_q.unwrap();
        assert!(rotation[1] < 0.5, "median rotation error {}", rotation[1]);
    }
}

/// AUC@5px floors: PoseLib on the same ground truth (shared/data/README.md, k = 10, 40
/// queries) minus one point.
#[test]
fn oracle_matches_poselib_on_the_validation_scenes() {
    let Some(data) = data_dir() else { return };
    for (scene, poselib_auc5) in [("mouse", 98.4), ("sceaux", 98.7)] {
        let source = SceneSource::Colmap(data.join("colmap").join(scene));
        let mut loaded = source.load().unwrap();
        loaded.name = source.name();
        for k in [1, 10] {
            let report = evaluate(&loaded, Matching::Oracle, &options(k, 40, 1), false).unwrap();
            print(&report);
            assert_eq!(report.failures, 0);
            let floor = if k == 10 { poselib_auc5 - 1.0 } else { 95.0 };
            assert!(
                report.auc_5px >= floor,
                "{scene} k={k}: AUC@5px {} below {floor}",
                report.auc_5px
            );
        }
    }
}

/// The protocol's view points (ground truth) are exactly the points the device's
/// localizer reads from the map blob for the same view.
#[test]
fn device_and_protocol_select_the_same_view_points() {
    let mut scenes: Vec<Scene> = vec![synthetic_scene(2, 1)];
    if let Some(data) = data_dir() {
        scenes.push(
            SceneSource::Colmap(data.join("colmap/sceaux"))
                .load()
                .unwrap(),
        );
    }
    for scene in &scenes {
        let blob = build_map(scene).unwrap();
        let map = Map::from_bytes(&blob).unwrap();
        // Map point index of every scene point id (the map keeps observed points in id
        // order).
        let index: BTreeMap<u64, u32> = scene
            .points
            .values()
            .filter(|p| !p.track.is_empty())
            .enumerate()
            .map(|(i, p)| (p.id, i as u32))
            .collect();
        let mut capped = 0;
        for sample in protocol_samples(scene, &options(10, 5, 1).protocol) {
            for view in &sample.views {
                let v = map.views_by_image_id::<1>(&[view.image_id]).unwrap()[0] as usize;
                let pose = map.view(v).unwrap().pose;
                let observed = map.view_points(v).unwrap();
                let points = (0..observed.len()).map(|j| {
                    let p = observed.get(j).unwrap();
                    (p, map.point(p as usize).unwrap().map(f64::from))
                });
                let mut depths = vec![0.0; CAPACITY];
                let device: Vec<u32> = view_point_bearings(pose, points, CAPACITY, &mut depths)
                    .map(|(p, _)| p)
                    .collect();
                let protocol: Vec<u32> = view.point_ids.iter().map(|id| index[id]).collect();
                assert_eq!(device, protocol, "view {}", view.image_id);
                capped += usize::from(observed.len() > CAPACITY);
            }
        }
        println!("{}: {capped} views over the capacity", scene.name);
    }
}

fn without_timings(results: &[QueryResult]) -> Vec<QueryResult> {
    results
        .iter()
        .map(|q| QueryResult {
            timings_ms: TimingsMs::default(),
            ..q.clone()
        })
        .collect()
}

#[test]
fn results_do_not_depend_on_the_thread_count() {
    let scene = synthetic_scene(1, 2);
    let one = evaluate(&scene, Matching::Oracle, &options(10, 7, 1), false).unwrap();
    let two = evaluate(&scene, Matching::Oracle, &options(10, 7, 2), false).unwrap();
    assert_eq!(
        without_timings(&one.per_query),
        without_timings(&two.per_query)
    );
    assert_eq!(
        (one.auc_1px, one.auc_5px, one.auc_10px),
        (two.auc_1px, two.auc_5px, two.auc_10px)
    );
}

#[test]
fn plot_writes_a_png_of_the_curves() {
    let scene = synthetic_scene(1, 0);
    let report = evaluate(&scene, Matching::Oracle, &options(10, 5, 1), false).unwrap();
    let k1 = evaluate(&scene, Matching::Oracle, &options(1, 5, 1), false).unwrap();
    let path = std::env::temp_dir().join(format!("gomatch-eval-{}.png", std::process::id()));
    let curves = [
        (curve_label(&report), report_errors(&report)),
        (curve_label(&k1), report_errors(&k1)),
    ];
    plot_curves(&report.scene, &curves, &path).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    std::fs::remove_file(&path).unwrap();
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
    assert!(bytes.len() > 1000);
}

#[test]
fn the_ransac_cap_is_applied_and_recorded_in_the_report() {
    let scene = synthetic_scene(1, 2);
    let mut capped = options(10, 4, 1);
    capped.localizer.ransac.max_iterations = 3;
    let report = evaluate(&scene, Matching::Oracle, &capped, false).unwrap();
    assert_eq!(report.ransac_max_iterations, 3);
    assert!(report.per_query.iter().all(|q| q.ransac_iterations <= 3));

    let default = evaluate(&scene, Matching::Oracle, &options(10, 4, 1), false).unwrap();
    assert_eq!(default.ransac_max_iterations, 10_000);
    let mut json = serde_json::to_value(&default).unwrap();
    json.as_object_mut()
        .unwrap()
        .remove("ransac_max_iterations");
    // Reports written before the cap was recorded ran at the default of that time, 1000.
    let older: Report = serde_json::from_value(json).unwrap();
    assert_eq!(older.ransac_max_iterations, 1000);
}

#[test]
fn ground_truth_pairs_name_the_map_points_of_the_views() {
    let scene = synthetic_scene(1, 0);
    let blob = build_map(&scene).unwrap();
    let map = Map::from_bytes(&blob).unwrap();
    let index = map_point_index(&scene).unwrap();
    let samples = protocol_samples(&scene, &options(10, 5, 1).protocol);
    assert!(!samples.is_empty());
    let bits = |x: [f32; 3]| x.map(f32::to_bits);
    for sample in &samples {
        let expected: BTreeSet<(usize, [u32; 3])> = sample
            .views
            .iter()
            .flat_map(|v| {
                v.gt_pairs.iter().map(|&(keypoint, point)| {
                    let x = v.xyz[point];
                    (keypoint, bits([x.x as f32, x.y as f32, x.z as f32]))
                })
            })
            .collect();
        let named: BTreeSet<(usize, [u32; 3])> = ground_truth_pairs(sample, &index)
            .into_iter()
            .map(|(keypoint, point)| (keypoint, bits(map.point(point as usize).unwrap())))
            .collect();
        assert!(!named.is_empty());
        assert_eq!(named, expected, "image {}", sample.image_id);
    }
}

/// The shipped int8 model as the matcher with an f16 cost (the device configuration), or
/// `None` (with a SKIPPED line) without `models/`. Its blob and model live for the rest of
/// the test process.
fn shipped_int8_matching() -> Option<Matching<'static>> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/gomatch-int8.bin");
    let Ok(blob) = std::fs::read(&path) else {
        println!("SKIPPED: no shipped model at {}", path.display());
        return None;
    };
    let blob: &'static [u8] = Box::leak(blob.into_boxed_slice());
    let model: &'static Model<'static> = Box::leak(Box::new(Model::from_bytes(blob).unwrap()));
    Some(Matching::Model {
        model,
        blob_bytes: blob.len(),
        precision: SinkhornPrecision::F16,
    })
}

#[test]
fn correct_matches_are_counted_among_the_merged_matches_and_inliers() {
    let Some(matching) = shipped_int8_matching() else {
        return;
    };
    let scene = synthetic_scene(1, 0);
    let report = evaluate(&scene, matching, &options(10, 4, 2), false).unwrap();
    print(&report);
    for query in &report.per_query {
        let correct = query.correct.expect("recorded for every query");
        assert!(correct.merged <= query.counts.merged, "{query:?}");
        assert!(
            correct.inliers <= query.counts.inliers.min(correct.merged),
            "{query:?}"
        );
        if query.rotation_deg.is_some_and(|r| r < 1.0) {
            assert!(
                correct.inliers >= 4.0,
                "an accurate pose rests on true matches: {query:?}"
            );
        }
    }
    assert!(report
        .per_query
        .iter()
        .any(|q| q.rotation_deg.is_some_and(|r| r < 1.0)));
    let mean = report.mean_correct.expect("every query recorded it");
    let n = report.per_query.len() as f64;
    let merged: f64 = report
        .per_query
        .iter()
        .map(|q| q.correct.unwrap().merged)
        .sum();
    assert_eq!(mean.merged, merged / n);

    let oracle = evaluate(&scene, Matching::Oracle, &options(10, 4, 1), false).unwrap();
    for query in &oracle.per_query {
        let correct = query.correct.unwrap();
        assert_eq!(
            (correct.merged, correct.inliers),
            (query.counts.merged, query.counts.inliers)
        );
    }
}

/// The acceptance figures agree with the per-query records: accepted poses are the
/// reported ones, a refused candidate is a failure, the evidence's features are stored,
/// and a rule that refuses everything leaves the candidates as they were.
#[test]
fn acceptance_counts_are_consistent_with_the_queries() {
    let Some(matching) = shipped_int8_matching() else {
        return;
    };
    let scene = synthetic_scene(1, 1);
    let report = evaluate(&scene, matching, &options(10, 4, 2), false).unwrap();
    print(&report);
    let a = report.acceptance.expect("recorded");
    assert_eq!(a.rule, AcceptanceRule::for_capacity(report.capacity));
    assert!(a.accepted_wrong <= a.accepted && a.accepted <= a.candidates);
    assert!(a.candidates_right <= a.candidates && a.candidates <= report.queries);
    assert_eq!(a.accepted, report.queries - report.failures);
    assert_eq!(a, AcceptanceSummary::of(a.rule, &report.per_query));
    let right_accepted = a.accepted - a.accepted_wrong;
    assert_eq!(
        a.precision,
        (a.accepted > 0).then(|| right_accepted as f64 / a.accepted as f64)
    );
    assert!(a.candidates > 0, "the model localizes synthetic queries");
    for q in &report.per_query {
        let Some(evidence) = q.evidence else {
            assert!(q.candidate_right.is_none() && q.failure.is_some(), "{q:?}");
            continue;
        };
        assert_eq!(q.features, Some(evidence.features()));
        assert_eq!(evidence.inliers as f64, q.counts.inliers);
        assert!(evidence.inliers <= evidence.loose && evidence.loose <= evidence.merged);
        let confidence = q.confidence.expect("scored with the evidence");
        assert_eq!(confidence, a.rule.confidence(&evidence));
        let rotation = q.candidate_rotation_deg.expect("a candidate");
        assert_eq!(
            q.candidate_right,
            Some(pose_is_right(q.candidate_reprojection_px, rotation))
        );
        // Every candidate was re-matched, and the rule saw the re-matched inliers and their
        // chance level (pairs of shifted keypoints, at most the keypoints).
        let guided = q.guided.expect("a candidate is re-matched");
        assert_eq!(evidence.guided_inliers, u32::from(guided.inliers));
        assert!(usize::from(guided.chance) <= q.keypoints);
        assert_eq!(
            guided.rounds == 0,
            evidence.guided_chance == 0.0 && guided.chance == 0
        );
        assert!(evidence.guided_chance <= f32::from(guided.chance));
        assert!(guided.rounds == 0 || usize::from(guided.inliers) >= gomatch::guided::MIN_INLIERS);
        assert!(guided.inliers <= guided.pairs);
        if q.failure.is_none() {
            assert!(a.rule.accepts(confidence));
            assert_eq!(q.rotation_deg, Some(rotation));
            assert_eq!(q.reprojection_px, q.candidate_reprojection_px);
        }
    }

    let refuse_all = AcceptanceRule {
        bias: -100.0,
        weights: [0.0; gomatch::acceptance::FEATURES],
        min_confidence: 0.5,
    };
    let strict = EvalOptions {
        localizer: LocalizerConfig {
            acceptance: Some(refuse_all),
            ..LocalizerConfig::new()
        },
        ..options(10, 4, 2)
    };
    let refused = evaluate(&scene, matching, &strict, false).unwrap();
    let r = refused.acceptance.unwrap();
    assert_eq!((r.accepted, r.accepted_wrong, r.precision), (0, 0, None));
    assert_eq!(
        (r.candidates, r.candidates_right),
        (a.candidates, a.candidates_right)
    );
    assert_eq!(refused.failures, refused.queries);
    assert_eq!(refused.auc_10px, 0.0);
    for (q, before) in refused.per_query.iter().zip(&report.per_query) {
        assert_eq!(q.evidence, before.evidence);
        assert_eq!(q.candidate_rotation_deg, before.candidate_rotation_deg);
        assert!(q.reprojection_px.is_none() && q.rotation_deg.is_none());
        if q.evidence.is_some() {
            let failure = q.failure.as_deref().unwrap();
            assert!(failure.starts_with("low confidence"), "{failure}");
        }
    }
}

/// Guided re-matching (`--no-guided` leaves it out) changes the judged pose and the rule's
/// last feature only: the matches and the rest of the evidence are the same, and on the
/// synthetic queries the re-matched poses are closer to the truth.
#[test]
fn guided_re_matching_refines_the_judged_poses() {
    let Some(matching) = shipped_int8_matching() else {
        return;
    };
    let scene = synthetic_scene(1, 1);
    let guided = evaluate(&scene, matching, &options(10, 4, 2), false).unwrap();
    let paper = EvalOptions {
        localizer: LocalizerConfig {
            guided: None,
            ..LocalizerConfig::new()
        },
        ..options(10, 4, 2)
    };
    let unguided = evaluate(&scene, matching, &paper, false).unwrap();
    print(&guided);
    print(&unguided);
    assert!(guided.guided && !unguided.guided);
    let mut rotations = (Vec::new(), Vec::new());
    for (g, u) in guided.per_query.iter().zip(&unguided.per_query) {
        assert_eq!(g.counts, u.counts);
        assert_eq!(u.guided, None);
        if let (Some(ge), Some(ue)) = (g.evidence, u.evidence) {
            // Without re-matching the last feature counts RANSAC-PnP's inliers.
            assert_eq!(ue.guided_inliers, ue.inliers);
            let g_counts = g.guided.expect("re-matched");
            assert_eq!(ge.guided_inliers, u32::from(g_counts.inliers));
            assert_eq!(
                gomatch::acceptance::Evidence {
                    guided_inliers: ue.inliers,
                    guided_chance: 0.0,
                    ..ge
                },
                ue
            );
        }
        if let (Some(a), Some(b)) = (g.candidate_rotation_deg, u.candidate_rotation_deg) {
            rotations.0.push(a);
            rotations.1.push(b);
        }
    }
    assert!(
        !rotations.0.is_empty(),
        "the model localizes synthetic queries"
    );
    let (with, without) = (
        rotations.0.iter().sum::<f64>(),
        rotations.1.iter().sum::<f64>(),
    );
    assert!(
        with < without,
        "rotation errors {:?} against {:?}",
        rotations.0,
        rotations.1
    );
}

/// `--capacity 128`: the protocol gives at most 128 keypoints per query, the report records
/// the capacity and the small localizer's workspace, and the shipped model still localizes
/// a synthetic query with it.
#[test]
fn a_small_capacity_caps_the_keypoints_and_runs_the_small_localizer() {
    let Some(matching) = shipped_int8_matching() else {
        return;
    };
    let scene = synthetic_scene(1, 0);
    let small = EvalOptions {
        protocol: ProtocolParams::for_localizer(3, 4, 0, 128),
        ..options(3, 4, 2)
    };
    let report = evaluate(&scene, matching, &small, false).unwrap();
    print(&report);
    assert_eq!(report.capacity, 128);
    assert_eq!(
        report.localizer_bytes,
        gomatch::Localizer::<128, half::f16>::BYTES
    );
    assert!(report.per_query.iter().all(|q| q.keypoints <= 128));
    assert!(report.mean_views_used <= 3.0);
    assert!(report
        .per_query
        .iter()
        .any(|q| q.rotation_deg.is_some_and(|r| r < 1.0)));
    let unknown = EvalOptions {
        protocol: ProtocolParams::for_localizer(3, 4, 0, 100),
        ..options(3, 4, 1)
    };
    assert!(evaluate(&scene, matching, &unknown, false).is_err());
}

/// `--view-features`: the map's precomputed view features give the same poses, errors and
/// counts as computing the views, and the report says they were used.
#[test]
fn view_features_give_the_same_evaluation() {
    let Some(matching) = shipped_int8_matching() else {
        return;
    };
    let scene = synthetic_scene(1, 0);
    let plain = evaluate(&scene, matching, &options(3, 4, 1), false).unwrap();
    let with = EvalOptions {
        view_features: true,
        ..options(3, 4, 1)
    };
    let report = evaluate(&scene, matching, &with, false).unwrap();
    assert!(report.view_features && !plain.view_features);
    let outcome = |r: &Report| {
        r.per_query
            .iter()
            .map(|q| {
                (
                    q.reprojection_px.map(f64::to_bits),
                    q.failure.clone(),
                    q.counts,
                )
            })
            .collect::<Vec<_>>()
    };
    assert_eq!(outcome(&report), outcome(&plain));
    assert_eq!(
        (report.auc_1px, report.auc_10px),
        (plain.auc_1px, plain.auc_10px)
    );
}
