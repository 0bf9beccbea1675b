//! Real SfM models hold 3D points at a camera's centre (issue 24). The core's projection
//! rule ([`gomatch::pose::ProjectionRule`]) skips them everywhere: injected into
//! `colmap/mouse`, such a point changes no oracle score, never enters a view's bearings on
//! the device, and a query whose camera coincides with a map point still localizes.

use std::path::Path;

use gomatch::localizer::view_point_bearings;
use gomatch::map::Map;
use gomatch::{Localizer, LocalizerConfig, Model, Query, ViewSelection};
use gomatch_sim::eval::{
    evaluate, protocol_samples, query_pixels, EvalOptions, Matching, QueryResult,
};
use gomatch_sim::host::{default_model_path, CAPACITY};
use gomatch_sim::map::{build_map, map_point_index};
use gomatch_sim::protocol::{
    query_reprojection_error, query_sample, ProtocolParams, QuerySample, ViewSample,
};
use gomatch_sim::readers::SceneSource;
use gomatch_sim::scene::{ImageId, Keypoint, Point3d, PointId, Scene, TrackElement};

/// Depth of the injected points in the camera they sit at: the 2.3e-10.
const CENTRE_DEPTH: f64 = 2.3e-10;

fn mouse() -> Option<Scene> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/colmap/mouse");
    if !dir.is_dir() {
        println!("SKIPPED: {} is absent", dir.display());
        return None;
    }
    Some(SceneSource::Colmap(dir).load().expect("mouse loads"))
}

fn options() -> EvalOptions {
    EvalOptions {
        protocol: ProtocolParams::for_localizer(10, 40, 0, CAPACITY),
        localizer: LocalizerConfig::new(),
        threads: 1,
        view_features: false,
    }
}

/// The point `CENTRE_DEPTH` in front of `at`'s camera centre, observed by image `by` as
/// its best-ranked keypoint (the last stored one), at the pixel where `by` sees it.
fn inject(scene: &mut Scene, at: ImageId, by: ImageId) -> PointId {
    let pose = scene.images[&at].pose;
    let xyz = pose.center() + CENTRE_DEPTH * pose.viewing_direction();
    let id = scene.points.keys().max().map_or(0, |m| m + 1);
    let observer = &scene.images[&by];
    let camera = scene.cameras[&observer.camera_id];
    let pixel = observer
        .pose
        .bearing(&xyz, 0)
        .and_then(|b| camera.bearing_to_pixel(b))
        .expect("the observer sees the point");
    let image = scene.images.get_mut(&by).expect("observer exists");
    let keypoint_index = image.keypoints.len() as u32;
    image.keypoints.push(Keypoint {
        pixel,
        point3d: Some(id),
    });
    let track = vec![TrackElement {
        image_id: by,
        keypoint_index,
    }];
    scene.points.insert(id, Point3d { id, xyz, track });
    id
}

/// Oracle scores by query, except `excluded`'s (its own keypoints changed).
fn oracle_scores(scene: &Scene, excluded: ImageId) -> Vec<(ImageId, Option<f64>)> {
    let report = evaluate(scene, Matching::Oracle, &options(), false).expect("evaluates");
    report
        .per_query
        .iter()
        .filter(|q: &&QueryResult| q.image_id != excluded)
        .map(|q| (q.image_id, q.reprojection_px))
        .collect()
}

/// The image that is a co-visible view of the most protocol queries.
fn busiest_view(samples: &[QuerySample]) -> ImageId {
    let mut uses = std::collections::BTreeMap::<ImageId, usize>::new();
    for view in samples.iter().flat_map(|s| &s.views) {
        *uses.entry(view.image_id).or_default() += 1;
    }
    uses.into_iter()
        .max_by_key(|&(id, n)| (n, std::cmp::Reverse(id)))
        .expect("views")
        .0
}

#[test]
fn a_point_at_a_database_camera_changes_nothing() {
    let Some(scene) = mouse() else { return };
    let samples = protocol_samples(&scene, &options().protocol);
    let view = busiest_view(&samples);
    let mut injected = scene.clone();
    let point = inject(&mut injected, view, view);

    // The bare projection would give it a bearing; the rule refuses it.
    let pose = injected.images[&view].pose;
    assert!(pose.bearing(&injected.points[&point].xyz, 0).is_ok());
    let after = protocol_samples(&injected, &options().protocol);
    let mut affected = 0;
    for (old, new) in samples
        .iter()
        .zip(&after)
        .filter(|(s, _)| s.image_id != view)
    {
        assert_eq!(old.image_id, new.image_id);
        for (a, b) in old.views.iter().zip(&new.views) {
            assert!(!b.point_ids.contains(&point));
            assert_eq!((&a.point_ids, &a.gt_pairs), (&b.point_ids, &b.gt_pairs));
            if b.image_id == view {
                affected += 1;
                assert_eq!(b.refused_points, 1);
            }
        }
    }
    assert!(affected >= 5, "{affected} queries see view {view}");
    assert_eq!(oracle_scores(&scene, view), oracle_scores(&injected, view));

    // On the device: the map stores the point first in the view's list, and the view's
    // bearings skip it.
    let blob = build_map(&injected).expect("builds");
    let map = Map::from_bytes(&blob).expect("valid");
    let index = map_point_index(&injected).expect("indexed")[&point];
    let v = map.views_by_image_id::<1>(&[view]).expect("view")[0] as usize;
    let observed = map.view_points(v).expect("points");
    assert_eq!(observed.get(0), Some(index));
    let points = (0..observed.len()).filter_map(|j| {
        let p = observed.get(j)?;
        Some((p, map.point(p as usize).ok()?.map(f64::from)))
    });
    let mut depths = vec![0.0; CAPACITY];
    let mut chosen = view_point_bearings(
        map.view(v).expect("view").pose,
        points,
        CAPACITY,
        &mut depths,
    );
    assert!(chosen.by_ref().all(|(p, _)| p != index));
    assert_eq!(chosen.skipped(), 1);
}

#[test]
fn a_query_whose_camera_holds_a_map_point_still_localizes() {
    let Some(scene) = mouse() else { return };
    let samples = protocol_samples(&scene, &options().protocol);
    // The query with the most ground-truth matches whose camera centre one of its views
    // sees, and that view's index.
    let sees = |s: &QuerySample, v: usize| {
        let image = &scene.images[&s.views[v].image_id];
        let camera = scene.cameras[&image.camera_id];
        let centre = image.pose.transform(&s.pose.center());
        image
            .pose
            .bearing(&s.pose.center(), 0)
            .and_then(|b| camera.bearing_to_pixel(b))
            .is_ok_and(|[x, y]| {
                centre.z > 0.0
                    && (0.0..f64::from(camera.width)).contains(&x)
                    && (0.0..f64::from(camera.height)).contains(&y)
            })
    };
    let (query, v) = samples
        .iter()
        .filter_map(|s| Some((s, (0..s.views.len()).find(|&v| sees(s, v))?)))
        .max_by_key(|(s, _)| s.views.iter().map(|v| v.gt_pairs.len()).sum::<usize>())
        .expect("a query whose centre a view sees");
    let mut injected = scene.clone();
    let point = inject(&mut injected, query.image_id, query.views[v].image_id);
    let sample = query_sample(&injected, query.image_id, &options().protocol).expect("sample");
    // Usable in the view (ranked first), refused as ground truth in the query: the
    // ground truth by point id and the oracle score are unchanged.
    assert_eq!(sample.views[v].point_ids[0], point);
    let by_id = |view: &ViewSample| -> Vec<(usize, PointId)> {
        view.gt_pairs
            .iter()
            .map(|&(k, p)| (k, view.point_ids[p]))
            .collect()
    };
    for (a, b) in query.views.iter().zip(&sample.views) {
        assert_eq!(by_id(a), by_id(b));
    }
    let oracle = |scene: &Scene| {
        oracle_scores(scene, u32::MAX)
            .into_iter()
            .find(|&(id, _)| id == query.image_id)
    };
    assert!(oracle(&scene).is_some());
    assert_eq!(oracle(&scene), oracle(&injected));

    let blob = std::fs::read(default_model_path()).expect("the shipped model");
    let model = Model::from_bytes(&blob).expect("decodes");
    let map_blob = build_map(&injected).expect("builds");
    let map = Map::from_bytes(&map_blob).expect("valid");
    let error = network_error(&model, &map, &sample);
    println!(
        "query {}: {error:.3} px with a map point at its camera",
        sample.image_id
    );
    assert!(error < 5.0, "{error} px");
}

/// Localizes `sample` with the network (on a thread whose stack holds the workspace) and
/// returns its reprojection error in pixels.
fn network_error(model: &Model<'_>, map: &Map<'_>, sample: &QuerySample) -> f64 {
    std::thread::scope(|scope| {
        std::thread::Builder::new()
            .stack_size(64 << 20)
            .spawn_scoped(scope, || {
                let mut localizer = Localizer::<CAPACITY>::new();
                let pixels = query_pixels(sample);
                let ids: Vec<u32> = sample.views.iter().map(|v| v.image_id).collect();
                let query = Query {
                    keypoints: &pixels,
                    camera: sample.camera,
                };
                let result = localizer
                    .localize(
                        model,
                        map,
                        &query,
                        ViewSelection::ImageIds(&ids),
                        &LocalizerConfig::new(),
                        None,
                    )
                    .expect("valid input");
                query_reprojection_error(
                    &sample.camera,
                    &sample.projection,
                    &sample.pose,
                    result.outcome.ok().as_ref(),
                    &sample.gt_inlier_points(),
                )
            })
            .expect("spawns")
            .join()
            .expect("no panic")
    })
}
