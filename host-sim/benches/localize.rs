//! Criterion benchmark of one full localization (paper sec. 4.1): a `colmap/mouse` query
//! (protocol seed 0, keypoints capped at N = 1024) against its k = 10 co-visible views
//! with the shipped int8 model and an f16 Sinkhorn cost (the device configuration), one
//! thread: encode the query once, match every view, merge, RANSAC-PnP. Run:
//! `cargo bench -p gomatch-sim --bench localize`.

use std::sync::Mutex;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion};
use gomatch::{Localizer, Model};
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
    let mut localizer = LOCALIZER.lock().expect("lock");
    let first = workload::localize(&mut localizer, &model, &problem);
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
        b.iter(|| workload::localize(&mut localizer, &model, &problem).views_used)
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
