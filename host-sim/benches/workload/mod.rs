//! Inputs shared by the benches and the `workload` example (instruction counts): a
//! deterministic query-view pair of `n` bearings, and one `colmap/mouse` query with its
//! k = 10 co-visible views for a full localization with the shipped model.

#![allow(dead_code)] // each includer uses a part

use std::path::PathBuf;

use gomatch::map::Map;
use gomatch::{Camera, Localization, Localizer, LocalizerConfig, Model, Query, ViewSelection};
use gomatch_sim::eval::{protocol_samples, query_pixels};
use gomatch_sim::map::build_map;
use gomatch_sim::protocol::ProtocolParams;
use gomatch_sim::readers::SceneSource;
use half::f16;

/// Keypoints per query and points per view of the localization workload.
pub const CAPACITY: usize = 1024;

/// A file of the repository.
pub fn repo(path: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join(path)
}

/// A file of the shared data folder (`../shared` beside the checkout).
pub fn shared(path: &str) -> PathBuf {
    repo("../shared").join(path)
}

/// `n` bearings in [-0.6, 0.6]^2 from a linear congruential generator.
pub fn bearings(n: usize, seed: u64) -> Vec<[f32; 2]> {
    let mut state = seed
        .wrapping_mul(6364136223846793005)
        .wrapping_add(1442695040888963407);
    let mut next = move || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((state >> 40) as f32 / (1u64 << 24) as f32) * 1.2 - 0.6
    };
    (0..n).map(|_| [next(), next()]).collect()
}

/// Query and database: 70 % of the database are the query points with noise.
pub fn pair(n: usize) -> (Vec<[f32; 2]>, Vec<[f32; 2]>) {
    let query = bearings(n, 1);
    let noise = bearings(n, 2);
    let outliers = bearings(n, 3);
    let db = (0..n)
        .map(|i| {
            if i * 10 < n * 7 {
                let q = query[(i * 7919) % n];
                [q[0] + noise[i][0] * 1e-3, q[1] + noise[i][1] * 1e-3]
            } else {
                outliers[i]
            }
        })
        .collect();
    (query, db)
}

/// One localization problem: the map blob, a query's pixels, camera and view ids.
pub struct Problem {
    pub map: Vec<u8>,
    pub pixels: Vec<[f32; 2]>,
    pub camera: Camera,
    pub views: Vec<u32>,
}

/// The first protocol query (seed 0) of `colmap/mouse` with its k = 10 co-visible views,
/// keypoints and view points capped at [`CAPACITY`]; `None` without the data.
pub fn mouse_query() -> Option<Problem> {
    let scene = SceneSource::Colmap(shared("data/colmap/mouse"))
        .load()
        .ok()?;
    let params = ProtocolParams::for_localizer(10, 1, 0, CAPACITY);
    let sample = protocol_samples(&scene, &params).into_iter().next()?;
    Some(Problem {
        map: build_map(&scene).ok()?,
        pixels: query_pixels(&sample),
        camera: sample.camera,
        views: sample.views.iter().map(|v| v.image_id).collect(),
    })
}

/// Runs the full localization (encode once, match each view, merge, RANSAC-PnP) on `map`
/// (the problem's, read with or without view features).
pub fn localize(
    localizer: &mut Localizer<CAPACITY, f16>,
    model: &Model<'_>,
    map: &Map<'_>,
    problem: &Problem,
) -> Localization {
    let query = Query {
        keypoints: &problem.pixels,
        camera: problem.camera,
    };
    localizer
        .localize(
            model,
            map,
            &query,
            ViewSelection::ImageIds(&problem.views),
            &LocalizerConfig::default(),
            None,
        )
        .expect("valid query")
}
