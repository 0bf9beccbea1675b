//! The map option that precomputes, per database view, what the matcher computes for the
//! view alone (the encoder and the first self-attention layer, [`gomatch::view_features`]),
//! for one model and capacity: built here for `gomatch-sim map features` and measured by
//! `mem-report`.

use std::sync::Mutex;

use anyhow::{ensure, Context};
use gomatch::localizer::view_point_bearings;
use gomatch::view_features::{blob_len, write_blob, ViewFeatures};
use gomatch::{Map, Matcher, Model};
use half::f16;

/// Largest capacity the features can be computed for.
pub const MAX_CAPACITY: usize = 1024;

/// The matcher that computes them (its Sinkhorn storage is not used).
static MATCHER: Mutex<Matcher<MAX_CAPACITY, f16>> = Mutex::new(Matcher::new());

/// The network input of `view` as the localizer picks it at `capacity`: bearing
/// coordinates of the view's first `capacity` points that have one.
pub fn view_bearings(map: &Map<'_>, view: usize, capacity: usize) -> anyhow::Result<Vec<[f32; 2]>> {
    let pose = map.view(view)?.pose;
    let points = map.view_point_positions(view)?;
    let mut depths = vec![0.0; capacity];
    Ok(view_point_bearings(pose, points, capacity, &mut depths)
        .map(|(_, b)| [b[0] as f32, b[1] as f32])
        .collect())
}

/// The view-features blob of `map` for `model` at `capacity` points per view. A view with
/// fewer points than the matcher needs stores none (the localizer skips it).
pub fn build_view_features(
    model: &Model<'_>,
    map: &Map<'_>,
    capacity: usize,
) -> anyhow::Result<Vec<u8>> {
    ensure!(
        (1..=MAX_CAPACITY).contains(&capacity),
        "capacity {capacity}: view features are computed for 1 to {MAX_CAPACITY} points per view"
    );
    let mut matcher = MATCHER.lock().unwrap_or_else(|e| e.into_inner());
    let mut views = Vec::with_capacity(map.view_count());
    for view in 0..map.view_count() {
        let db = view_bearings(map, view, capacity)?;
        let features = if db.len() < matcher.min_points() {
            Vec::new()
        } else {
            matcher
                .encode_view(model, &db)
                .with_context(|| format!("view {view}"))?
                .to_vec()
        };
        views.push(features);
    }
    let dim = usize::from(model.config().feature_dim);
    let counts: Vec<usize> = views.iter().map(|v| v.len() / dim).collect();
    let slices: Vec<&[f32]> = views.iter().map(Vec::as_slice).collect();
    let mut blob = vec![0u8; blob_len(dim, &counts)];
    let len = write_blob(model.checksum(), dim, capacity, &slices, &mut blob)?;
    blob.truncate(len);
    Ok(blob)
}

/// Reads a view-features blob and attaches it to `map` (both checked).
pub fn attach<'a>(map: Map<'a>, blob: &'a [u8]) -> anyhow::Result<Map<'a>> {
    let features = ViewFeatures::from_bytes(blob).context("reading the view features")?;
    Ok(map.with_view_features(features)?)
}
