//! Criterion benchmark of one full localization (paper sec. 4.1): a `colmap/mouse` query
//! (protocol seed 0, keypoints capped at N = 1024) against its k = 10 co-visible views
//! with the shipped int8 model and an f16 Sinkhorn cost (the device configuration), one
//! thread: encode the query once, match every view, merge, RANSAC-PnP; and the same with
//! the map's precomputed view features (`gomatch-sim map features`). Run:
//! `cargo bench -p gomatch-sim --bench localize`.

use std::sync::Mutex;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion};
use gomatch::{Localizer, Map, Model};
use gomatch_blobs::view_features::{attach, build_view_features};
use half::f16;

mod workload;

static LOCALIZER: Mutex<Localizer<{ workload::CAPACITY }, f16>> = Mutex::new(Localizer::new());

fn bench(c: &mut Criterion) {
    let Ok(blob) = std::fs::read(workload::repo("models/gomatch-int8.bin")) else {
        println!("SKIP localize bench: models/gomatch-int8.bin not found");
        return;
    };
    let Some(problem) = workload::mouse_query() else {
        println!("SKIP localize bench: ../shared/data/colmap/mouse not found");
        return;
    };
    let model = Model::from_bytes(&blob).expect("shipped model reads");
    let map = Map::from_bytes(&problem.map).expect("map reads back");
    let features = build_view_features(&model, &map, workload::CAPACITY).expect("features");
    let with_features = attach(map, &features).expect("features fit the map");
    let mut localizer = LOCALIZER.lock().expect("lock");
    let first = workload::localize(&mut localizer, &model, &map, &problem);
    println!(
        "mouse query: {} keypoints, {} views used, {} merged correspondences, pose found: {}",
        problem.pixels.len(),
        first.views_used,
        first.counts.merged,
        first.outcome.is_ok()
    );
    let mut group = c.benchmark_group("localize");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(20));
    group.bench_function("mouse_k10_n1024_int8_f16", |b| {
        b.iter(|| workload::localize(&mut localizer, &model, &map, &problem).views_used)
    });
    group.bench_function("mouse_k10_n1024_int8_f16_view_features", |b| {
        b.iter(|| workload::localize(&mut localizer, &model, &with_features, &problem).views_used)
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
