//! The core localizer end to end with a real network: the reference fixture weights
//! (random, from `shared/reference/fixtures`, converted to int8 with the converter's code)
//! on a synthetic scene's map. The weights are untrained, so these tests check that the
//! whole device path runs, is bit-identical from call to call, respects its capacity and
//! reports every failure as a typed value; the oracle tests (`eval.rs`) check accuracy.
//! Skips with a message when `shared/` is absent.

use std::path::Path;
use std::sync::{Mutex, OnceLock};

use gomatch::localizer::{Failure, MAX_VIEWS};
use gomatch::map::Map;
use gomatch::weights::Precision;
use gomatch::{
    Camera, Correspondence, Error, Localization, Localizer, LocalizerConfig, Model, Query,
    ViewSelection,
};
use gomatch_blobs::convert::{convert_with, Options};
use gomatch_sim::eval::{protocol_samples, query_pixels};
use gomatch_sim::map::build_map;
use gomatch_sim::protocol::synthetic::synthetic_scene;
use gomatch_sim::protocol::{ProtocolParams, QuerySample};
use half::f16;

/// Small capacity, so that the synthetic views (a few hundred to ~1500 points) overflow it.
const CAP: usize = 256;
static LOCALIZER: Mutex<Localizer<CAP, f16>> = Mutex::new(Localizer::new());

/// The fixture checkpoint as an int8 model blob, or `None` (with a message) without
/// `shared/`.
fn model_blob() -> Option<&'static [u8]> {
    static BLOB: OnceLock<Option<Vec<u8>>> = OnceLock::new();
    BLOB.get_or_init(|| {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/reference/fixtures/weights.safetensors");
        let Ok(checkpoint) = std::fs::read(&path) else {
            println!("SKIPPED: {} is absent", path.display());
            return None;
        };
        // Rounded to nearest: these tests need an int8 model, not a calibrated one
        // (`conformance.rs` checks the calibrated conversion).
        let options = Options::rounded_to_nearest(Precision::Int8);
        Some(convert_with(&checkpoint, &options).expect("converts").0)
    })
    .as_deref()
}

struct Fixture {
    map_blob: Vec<u8>,
    samples: Vec<QuerySample>,
}

fn fixture() -> &'static Fixture {
    static FIXTURE: OnceLock<Fixture> = OnceLock::new();
    FIXTURE.get_or_init(|| {
        let scene = synthetic_scene(0, 0);
        let params = ProtocolParams {
            k: 3,
            queries_per_scene: 2,
            max_keypoints: CAP,
            max_points: CAP,
            ..ProtocolParams::default()
        };
        Fixture {
            map_blob: build_map(&scene).expect("map"),
            samples: protocol_samples(&scene, &params),
        }
    })
}

fn view_ids(sample: &QuerySample) -> Vec<u32> {
    sample.views.iter().map(|v| v.image_id).collect()
}

fn localize(
    model: &Model<'_>,
    map: &Map<'_>,
    keypoints: &[[f32; 2]],
    camera: Camera,
    views: ViewSelection<'_>,
) -> Result<(Localization, Vec<Correspondence>), Error> {
    let mut localizer = LOCALIZER.lock().expect("lock");
    let query = Query { keypoints, camera };
    let result = localizer.localize(model, map, &query, views, &LocalizerConfig::new(), None)?;
    Ok((result, localizer.correspondences().to_vec()))
}

#[test]
fn localize_runs_end_to_end_deterministically_within_capacity() {
    let Some(blob) = model_blob() else { return };
    let model = Model::from_bytes(blob).expect("model");
    let f = fixture();
    let map = Map::from_bytes(&f.map_blob).expect("map");
    assert!(!f.samples.is_empty());
    for sample in &f.samples {
        let ids = view_ids(sample);
        let pixels = query_pixels(sample);
        assert!(pixels.len() <= CAP);
        let views = ViewSelection::ImageIds(&ids);
        let first = localize(&model, &map, &pixels, sample.camera, views).expect("valid input");
        let again = localize(&model, &map, &pixels, sample.camera, views).expect("valid input");
        assert_eq!(first, again, "bit-identical twice");
        let (result, matches) = first;
        println!(
            "query {}: {} keypoints, {} views, counts {:?}, outcome {:?}",
            sample.image_id,
            pixels.len(),
            result.views_used,
            result.counts,
            result.outcome.map(|_| "pose")
        );
        // Views with more points in front than the capacity were matched on CAP of them.
        let overflowing = ids
            .iter()
            .map(|&id| map.views_by_image_id::<1>(&[id]).expect("known")[0])
            .filter(|&v| map.view_points(v as usize).expect("view").len() > CAP)
            .count();
        assert!(overflowing > 0, "the scene must exercise the capacity");
        assert_eq!(result.views_used + result.views_skipped, ids.len());
        let c = result.counts;
        assert!(c.mutual <= result.views_used * 2 * CAP);
        assert!(c.classified <= c.mutual && c.merged <= c.classified.min(CAP));
        assert!(c.inliers <= c.merged);
        assert_eq!(matches.len(), c.merged);
        assert!(matches
            .iter()
            .all(|m| usize::from(m.keypoint) < pixels.len()
                && (m.point as usize) < map.point_count()
                && m.probability > model.config().match_threshold));
        match result.outcome {
            Ok(pose) => {
                assert!(c.inliers >= 4);
                assert!(pose.rotation.matrix().iter().all(|v| v.is_finite()));
                assert_eq!(matches.iter().filter(|m| m.inlier).count(), c.inliers);
            }
            Err(reason) => {
                assert!(matches.iter().all(|m| !m.inlier));
                assert_eq!(result.pose(), Err(Error::LocalizationFailed { reason }));
            }
        }
    }
}

#[test]
fn bad_queries_and_view_selections_are_typed_errors() {
    let Some(blob) = model_blob() else { return };
    let model = Model::from_bytes(blob).expect("model");
    let f = fixture();
    let map = Map::from_bytes(&f.map_blob).expect("map");
    let sample = &f.samples[0];
    let ids = view_ids(sample);
    let pixels = query_pixels(sample);
    let views = ViewSelection::ImageIds(&ids);
    let run = |keypoints: &[[f32; 2]], camera: Camera, views: ViewSelection<'_>| {
        localize(&model, &map, keypoints, camera, views).map(|(l, _)| l)
    };

    let mut nan = pixels.clone();
    nan[3][0] = f32::NAN;
    assert_eq!(
        run(&nan, sample.camera, views),
        Err(Error::NonFinite {
            input: gomatch::error::Input::Keypoints,
            index: 3
        })
    );
    let too_many = vec![[10.0f32, 10.0]; CAP + 1];
    assert_eq!(
        run(&too_many, sample.camera, views),
        Err(Error::CapacityExceeded {
            capacity: CAP,
            requested: CAP + 1
        })
    );
    let degenerate = Camera {
        focal: [f64::NAN, 1.0],
        ..sample.camera
    };
    assert_eq!(
        run(&pixels, degenerate, views),
        Err(Error::InvalidIntrinsics)
    );
    assert_eq!(
        run(
            &pixels,
            sample.camera,
            ViewSelection::ImageIds(&[ids[0], 999_999])
        ),
        Err(Error::MapUnknownImage { image_id: 999_999 })
    );
    let eleven: Vec<u32> = vec![ids[0]; MAX_VIEWS + 1];
    assert_eq!(
        run(&pixels, sample.camera, ViewSelection::ImageIds(&eleven)),
        Err(Error::CapacityExceeded {
            capacity: MAX_VIEWS,
            requested: MAX_VIEWS + 1
        })
    );
    let zero = run(&pixels, sample.camera, ViewSelection::ImageIds(&[])).expect("valid");
    assert_eq!(zero.outcome, Err(Failure::NoViews { skipped: 0 }));
    let few = run(&pixels[..5], sample.camera, views).expect("valid");
    assert_eq!(
        few.outcome,
        Err(Failure::TooFewKeypoints {
            needed: 10,
            found: 5
        })
    );
    // Keypoints piled on one pixel: the network runs, whatever it matches cannot give a
    // pose, and the reason is a typed failure.
    let piled = vec![[100.0f32, 100.0]; 40];
    let result = run(&piled, sample.camera, views).expect("valid input");
    assert!(result.outcome.is_err(), "{:?}", result.outcome);
    // Near a prior pose instead of image ids: the k nearest views of the map.
    let near = ViewSelection::NearPrior {
        prior: sample.pose,
        k: 2,
        max_angle_deg: 30.0,
    };
    let result = run(&pixels, sample.camera, near).expect("valid input");
    assert_eq!(result.views_used + result.views_skipped, 2);
}
