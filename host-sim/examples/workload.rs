//! One unit of work for instruction counting (`tools/callgrind.sh`): `match N WEIGHTS`
//! runs the matcher once on a query-view pair of N points (reference fixture weights,
//! f16 Sinkhorn cost for int8 and f16, f32 otherwise); `localize` runs one full k = 10
//! localization of a `colmap/mouse` query at N = 1024 with the shipped int8 model and an
//! f16 cost (the device configuration); `localize features` the same with the map's
//! precomputed view features. Preparation (conversion, map and features build) is outside
//! the functions callgrind is told to count.
//!
//! `time N WEIGHTS RUNS` times the same match (`tools/bench_reference.sh` runs it beside
//! the reference): two warm-up runs, then RUNS timed ones on this thread, and prints
//! `RESULT {"n", "precision", "folded", "runs", "median_ms", "min_ms", "max_ms", "matches"}`.
//! WEIGHTS is a precision (int8 with the converter's folded residual blocks) or
//! `int8-unfolded` (the reference's blocks, `gomatch-tools convert --fold-blocks=false`).
//!
//! `GOMATCH_KERNELS=portable|avx2|avx512` caps the kernel set the core picks at run time
//! (`gomatch::nn::dispatch::limit_kernels`; default: the widest this CPU has), to time or
//! count each set on one machine (the results are the same bits).

use std::sync::Mutex;
use std::time::Instant;

use gomatch::nn::dispatch::{limit_kernels, KernelSet};
use gomatch::{Localizer, Map, Matcher, Model, Precision};
use gomatch_blobs::convert::{convert_with, Options};
use gomatch_blobs::quantize::Rounding;
use gomatch_blobs::view_features::{attach, build_view_features};
use half::f16;

#[path = "../benches/workload/mod.rs"]
mod workload;

const CAPACITY: usize = workload::CAPACITY;
static MATCHER_F32: Mutex<Matcher<CAPACITY, f32>> = Mutex::new(Matcher::new());
static MATCHER_F16: Mutex<Matcher<CAPACITY, f16>> = Mutex::new(Matcher::new());
static LOCALIZER: Mutex<Localizer<CAPACITY, f16>> = Mutex::new(Localizer::new());

/// Warm-up runs before the timed ones.
const WARMUP: usize = 2;

fn main() -> anyhow::Result<()> {
    if let Ok(kernels) = std::env::var("GOMATCH_KERNELS") {
        limit_kernels(match kernels.as_str() {
            "portable" => KernelSet::Portable,
            "avx2" => KernelSet::Avx2,
            "avx512" => KernelSet::Avx512,
            other => anyhow::bail!("GOMATCH_KERNELS={other}: expected portable, avx2 or avx512"),
        });
    }
    let args: Vec<String> = std::env::args().skip(1).collect();
    match args.iter().map(String::as_str).collect::<Vec<_>>()[..] {
        ["match", n, weights] => match_once(n.parse()?, parse_weights(weights)?),
        ["time", n, weights, runs] => time_matches(n.parse()?, parse_weights(weights)?, runs.parse()?),
        ["localize"] => localize_once(false),
        ["localize", "features"] => localize_once(true),
        _ => anyhow::bail!(
            "usage: workload match N WEIGHTS | workload time N WEIGHTS RUNS | workload localize [features] (WEIGHTS: f32, f16, int8 or int8-unfolded)"
        ),
    }
}

/// How the fixture weights are converted: a precision, and for int8 the converter's
/// default of folded residual blocks or (`int8-unfolded`) the reference's layers
/// (`gomatch-tools convert --fold-blocks=false`).
#[derive(Clone, Copy)]
struct Weights {
    precision: Precision,
    folded: bool,
}

fn parse_weights(name: &str) -> anyhow::Result<Weights> {
    let precision = match name {
        "f32" => Precision::F32,
        "f16" => Precision::F16,
        "int8" | "int8-unfolded" => Precision::Int8,
        other => anyhow::bail!("unknown weights {other}"),
    };
    Ok(Weights {
        precision,
        folded: Options::new(precision).fold_blocks && !name.ends_with("-unfolded"),
    })
}

/// The reference fixture weights converted as `weights` asks (nearest rounding).
fn fixture_blob(weights: Weights) -> anyhow::Result<Vec<u8>> {
    let checkpoint = std::fs::read(workload::shared("reference/fixtures/weights.safetensors"))?;
    let options = Options {
        rounding: Rounding::Nearest,
        fold_blocks: weights.folded,
        ..Options::new(weights.precision)
    };
    Ok(convert_with(&checkpoint, &options)?.0)
}

/// One match of a query-view pair; the number of matches. Never inlined: callgrind counts
/// inside this function (`tools/callgrind.sh`), whatever the compiler inlines below it.
#[inline(never)]
fn run_match(
    model: &Model<'_>,
    precision: Precision,
    query: &[[f32; 2]],
    db: &[[f32; 2]],
) -> anyhow::Result<usize> {
    Ok(if precision == Precision::F32 {
        let mut m = MATCHER_F32.lock().expect("lock");
        m.match_pair(model, query, db)?.len()
    } else {
        let mut m = MATCHER_F16.lock().expect("lock");
        m.match_pair(model, query, db)?.len()
    })
}

fn match_once(n: usize, weights: Weights) -> anyhow::Result<()> {
    let precision = weights.precision;
    let blob = fixture_blob(weights)?;
    let model = Model::from_bytes(&blob)?;
    let (query, db) = workload::pair(n);
    let matches = run_match(&model, precision, &query, &db)?;
    println!("match N={n} {precision:?}: {matches} matches");
    Ok(())
}

fn time_matches(n: usize, weights: Weights, runs: usize) -> anyhow::Result<()> {
    anyhow::ensure!(runs > 0, "RUNS must be at least 1");
    let precision = weights.precision;
    let blob = fixture_blob(weights)?;
    let model = Model::from_bytes(&blob)?;
    let (query, db) = workload::pair(n);
    let mut matches = 0;
    for _ in 0..WARMUP {
        matches = run_match(&model, precision, &query, &db)?;
    }
    let mut ms: Vec<f64> = (0..runs)
        .map(|_| {
            let start = Instant::now();
            run_match(&model, precision, &query, &db).map(|_| start.elapsed().as_secs_f64() * 1e3)
        })
        .collect::<anyhow::Result<_>>()?;
    ms.sort_by(f64::total_cmp);
    let result = serde_json::json!({
        "n": n,
        "precision": format!("{precision:?}").to_lowercase(),
        "folded": weights.folded,
        "runs": runs,
        "median_ms": ms[runs / 2],
        "min_ms": ms[0],
        "max_ms": ms[runs - 1],
        "matches": matches,
    });
    println!("RESULT {result}");
    Ok(())
}

/// One full localization; with `features`, on the map with its precomputed view features
/// (built first, outside the counted call).
fn localize_once(features: bool) -> anyhow::Result<()> {
    let blob = std::fs::read(workload::repo("models/gomatch-int8.bin"))?;
    let model = Model::from_bytes(&blob)?;
    let problem = workload::mouse_query()
        .ok_or_else(|| anyhow::anyhow!("colmap/mouse is absent under ../shared/data"))?;
    let map = Map::from_bytes(&problem.map)?;
    let features_blob = if features {
        build_view_features(&model, &map, CAPACITY)?
    } else {
        Vec::new()
    };
    let map = if features {
        attach(map, &features_blob)?
    } else {
        map
    };
    let mut localizer = LOCALIZER.lock().expect("lock");
    let result = workload::localize(&mut localizer, &model, &map, &problem);
    println!(
        "localize: {} keypoints, {} views used, {} merged, outcome {:?}",
        problem.pixels.len(),
        result.views_used,
        result.counts.merged,
        result.outcome.is_ok()
    );
    Ok(())
}
