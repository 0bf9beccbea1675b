//! Criterion benchmark of the full matcher (encoder, attention, Sinkhorn, mutual
//! assignment, classifier) on one query-view pair of N keypoints and N points, one thread,
//! for each weight precision, plus a per-stage time breakdown printed before the runs.
//!
//! Weights: the reference fixture checkpoint (`shared/reference/fixtures`), converted like
//! `gomatch-tools convert`. Inputs: deterministic pseudo-random bearings; the database is
//! the query with noise plus outliers. Run: `cargo bench -p gomatch-sim --bench matcher`.

use std::sync::Mutex;
use std::time::{Duration, Instant};

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use gomatch::nn::LayerTap;
use gomatch::sinkhorn::{PlanScalar, Transport};
use gomatch::{Matcher, Model, Observer, Precision, Stage};
use gomatch_blobs::convert::{convert_with, Options};
use gomatch_blobs::quantize::Rounding;
use half::f16;
use workload::pair;

mod workload;

const CAPACITY: usize = 1024;
static MATCHER_F32: Mutex<Matcher<CAPACITY, f32>> = Mutex::new(Matcher::new());
static MATCHER_F16: Mutex<Matcher<CAPACITY, f16>> = Mutex::new(Matcher::new());

fn checkpoint() -> Option<Vec<u8>> {
    let path = workload::shared("reference/fixtures/weights.safetensors");
    match std::fs::read(&path) {
        Ok(bytes) => Some(bytes),
        Err(_) => {
            println!("SKIP matcher bench: {} not found", path.display());
            None
        }
    }
}

/// Times between consecutive stage reports.
struct StageClock {
    last: Instant,
    spent: Vec<(&'static str, Duration)>,
}

impl StageClock {
    fn lap(&mut self, name: &'static str) {
        let now = Instant::now();
        self.spent.push((name, now - self.last));
        self.last = now;
    }
}

impl LayerTap for StageClock {}

impl<S: PlanScalar> Observer<S> for StageClock {
    fn features(&mut self, stage: Stage, _x: &[f32], _c: usize, _n: usize) {
        match stage {
            Stage::Enc2d => self.lap("encoder (query)"),
            Stage::Att0Self2d => self.lap("self attention 0 (query)"),
            Stage::Enc3d => self.lap("encoder (view)"),
            Stage::Att0Self3d => self.lap("self attention 0 (view)"),
            Stage::Att1Cross3d => self.lap("cross attention (pair)"),
            Stage::Att2Self3d => self.lap("self attention 2 (pair)"),
            Stage::Desc3dL2 => self.lap("L2 normalise"),
            _ => {}
        }
    }
    fn transport(&mut self, _t: &Transport<'_, S>) {
        self.lap("cost + Sinkhorn");
    }
}

/// Runs of the stage breakdown; the median per stage is printed.
const BREAKDOWN_RUNS: usize = 5;

fn breakdown<S: PlanScalar>(
    matcher: &Mutex<Matcher<CAPACITY, S>>,
    model: &Model<'_>,
    label: &str,
    n: usize,
) {
    let (query, db) = pair(n);
    let mut m = matcher.lock().unwrap();
    let mut runs: Vec<Vec<(&'static str, Duration)>> = Vec::new();
    let (mut matches, mut iterations) = (0, 0);
    for _ in 0..BREAKDOWN_RUNS {
        let mut clock = StageClock {
            last: Instant::now(),
            spent: Vec::new(),
        };
        m.encode_query_observed(model, &query, &mut clock).unwrap();
        let set = m.match_view_observed(model, &db, &mut clock).unwrap();
        (matches, iterations) = (set.len(), set.sinkhorn_iterations());
        clock.lap("mutual assignment + classifier (pair)");
        runs.push(clock.spent);
    }
    let median = |values: &mut Vec<Duration>| {
        values.sort();
        values[values.len() / 2]
    };
    let mut totals: Vec<Duration> = runs
        .iter()
        .map(|r| r.iter().map(|(_, d)| *d).sum())
        .collect();
    println!(
        "stage breakdown {label} N={n}: total {:.1} ms (median of {BREAKDOWN_RUNS}), {matches} matches, {iterations} Sinkhorn iterations",
        median(&mut totals).as_secs_f64() * 1e3
    );
    for (stage, (name, _)) in runs[0].iter().enumerate() {
        let mut times: Vec<Duration> = runs.iter().map(|r| r[stage].1).collect();
        println!(
            "  {name:32} {:8.2} ms",
            median(&mut times).as_secs_f64() * 1e3
        );
    }
}

fn bench(c: &mut Criterion) {
    let Some(checkpoint) = checkpoint() else {
        return;
    };
    println!(
        "workspace bytes: Matcher<256, f32> {}, Matcher<256, f16> {}, Matcher<1024, f32> {}, Matcher<1024, f16> {}",
        Matcher::<256, f32>::BYTES,
        Matcher::<256, f16>::BYTES,
        Matcher::<1024, f32>::BYTES,
        Matcher::<1024, f16>::BYTES
    );
    let mut group = c.benchmark_group("matcher");
    group.sample_size(10).warm_up_time(Duration::from_secs(1));
    for precision in [Precision::F32, Precision::F16, Precision::Int8] {
        // The rounding of int8 levels does not change the speed: round to nearest (no
        // calibration run).
        let options = Options {
            rounding: Rounding::Nearest,
            ..Options::new(precision)
        };
        let (blob, _) = convert_with(&checkpoint, &options).unwrap();
        let model = Model::from_bytes(&blob).unwrap();
        let name = format!("{precision:?}").to_lowercase();
        for n in [256, 1024] {
            breakdown(&MATCHER_F32, &model, &format!("{name}/plan f32"), n);
            let (query, db) = pair(n);
            group.bench_with_input(
                BenchmarkId::new(format!("{name}/plan_f32"), n),
                &n,
                |b, _| {
                    let mut m = MATCHER_F32.lock().unwrap();
                    b.iter(|| m.match_pair(&model, &query, &db).unwrap().len());
                },
            );
            group.bench_with_input(
                BenchmarkId::new(format!("{name}/plan_f16"), n),
                &n,
                |b, _| {
                    let mut m = MATCHER_F16.lock().unwrap();
                    b.iter(|| m.match_pair(&model, &query, &db).unwrap().len());
                },
            );
        }
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
