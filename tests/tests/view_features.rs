//! The map option of precomputed view features (`gomatch::view_features`, `gomatch-sim map
//! features`): a localization reads them instead of computing each view's encoder and first
//! self-attention layer and gives the same bits; features of another model or capacity are
//! left unused; features of another map are refused.

use std::sync::Mutex;

use gomatch::localizer::Localization;
use gomatch::view_features::ViewFeatures;
use gomatch::{Error, Localizer, LocalizerConfig, Map, Model, Query, ViewSelection};
use gomatch_blobs::view_features::{attach, build_view_features};
use gomatch_tools::mem_report::{map_query, BUILTIN_MAP};
use half::f16;

const CAPACITY: usize = 256;
static LOCALIZER: Mutex<Localizer<CAPACITY, f16>> = Mutex::new(Localizer::new());

fn shipped(name: &str) -> Vec<u8> {
    let path = format!("{}/../models/{name}", env!("CARGO_MANIFEST_DIR"));
    std::fs::read(&path).unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// The built-in map's most observed view as a query against its 10 nearest views.
fn localize(model: &Model<'_>, map: &Map<'_>) -> Localization {
    let query = map_query(map, CAPACITY).expect("query");
    let views = ViewSelection::NearPrior {
        prior: query.pose,
        k: 10,
        max_angle_deg: 30.0,
    };
    let q = Query {
        keypoints: &query.pixels,
        camera: query.camera,
    };
    let mut localizer = LOCALIZER.lock().unwrap_or_else(|e| e.into_inner());
    localizer
        .localize(model, map, &q, views, &LocalizerConfig::new(), None)
        .expect("localizes")
}

/// `blob` with one stored value changed and the envelope resealed.
fn with_one_value_changed(blob: &[u8]) -> Vec<u8> {
    let mut blob = blob.to_vec();
    let last = blob.len() - 4;
    let value = f32::from_le_bytes(blob[last..].try_into().expect("4 bytes")) + 1.0;
    blob[last..].copy_from_slice(&value.to_le_bytes());
    let payload = blob.len() - gomatch::envelope::HEADER_BYTES;
    gomatch::envelope::seal(gomatch::error::BlobKind::ViewFeatures, &mut blob, payload)
        .expect("fits");
    blob
}

#[test]
fn precomputed_features_give_the_same_localization() {
    let model_blob = shipped("gomatch-int8.bin");
    let model = Model::from_bytes(&model_blob).expect("model");
    let map = Map::from_bytes(BUILTIN_MAP).expect("map");
    let want = localize(&model, &map);
    assert!(want.views_used > 1, "{want:?}");

    let features = build_view_features(&model, &map, CAPACITY).expect("features");
    let with = attach(map, &features).expect("attaches");
    assert_eq!(localize(&model, &with), want);

    // They are read: a changed value changes the result.
    let changed = with_one_value_changed(&features);
    let with_changed = attach(map, &changed).expect("attaches");
    assert_ne!(localize(&model, &with_changed), want);
}

#[test]
fn features_of_another_model_or_capacity_are_not_used() {
    let model_blob = shipped("gomatch-int8.bin");
    let model = Model::from_bytes(&model_blob).expect("model");
    let map = Map::from_bytes(BUILTIN_MAP).expect("map");
    let want = localize(&model, &map);
    let other_blob = shipped("gomatch-f32.bin");
    let other = Model::from_bytes(&other_blob).expect("model");
    let foreign = with_one_value_changed(&build_view_features(&other, &map, CAPACITY).expect("f"));
    assert_eq!(
        localize(&model, &attach(map, &foreign).expect("attaches")),
        want
    );
    // At N = 16 a view's first 16 points are not the 256 the localizer takes.
    let small = with_one_value_changed(&build_view_features(&model, &map, 16).expect("f"));
    assert_eq!(
        localize(&model, &attach(map, &small).expect("attaches")),
        want
    );
    // At N = 1024 the counts are the same (no view has 256 points) but the projection rule's
    // reference depth may differ with the capacity: another capacity is never used.
    let wider = with_one_value_changed(&build_view_features(&model, &map, 1024).expect("f"));
    assert_eq!(
        localize(&model, &attach(map, &wider).expect("attaches")),
        want
    );
}

#[test]
fn features_of_another_map_are_refused() {
    let model_blob = shipped("gomatch-int8.bin");
    let model = Model::from_bytes(&model_blob).expect("model");
    let map = Map::from_bytes(BUILTIN_MAP).expect("map");
    let tiny_blob =
        gomatch_sim::device::tiny::tiny_map_blob(gomatch_sim::device::tiny::TINY_POINTS)
            .expect("tiny");
    let tiny = Map::from_bytes(&tiny_blob).expect("tiny map");
    let features = build_view_features(&model, &tiny, CAPACITY).expect("features");
    let parsed = ViewFeatures::from_bytes(&features).expect("valid");
    assert_eq!(
        map.with_view_features(parsed),
        Err(Error::ViewFeaturesMismatch {
            view: map.view_count()
        })
    );
}
