//! One unit of work for instruction counting (`tools/callgrind.sh`): `match N PRECISION`
//! runs the matcher once on a query-view pair of N points (reference fixture weights,
//! f16 Sinkhorn cost for int8 and f16, f32 otherwise); `localize` runs one full k = 10
//! localization of a `colmap/mouse` query at N = 1024 with the shipped int8 model and an
//! f16 cost (the device configuration). Preparation (conversion, map build) is outside
//! the functions callgrind is told to count.

use std::sync::Mutex;

use gomatch::{Localizer, Matcher, Model, Precision};
use gomatch_tools::convert::{convert_with, Options};
use gomatch_tools::quantize::Rounding;
use half::f16;

#[path = "../benches/workload/mod.rs"]
mod workload;

const CAPACITY: usize = workload::CAPACITY;
static MATCHER_F32: Mutex<Matcher<CAPACITY, f32>> = Mutex::new(Matcher::new());
static MATCHER_F16: Mutex<Matcher<CAPACITY, f16>> = Mutex::new(Matcher::new());
static LOCALIZER: Mutex<Localizer<CAPACITY, f16>> = Mutex::new(Localizer::new());

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match args.iter().map(String::as_str).collect::<Vec<_>>()[..] {
        ["match", n, precision] => match_once(n.parse()?, precision),
        ["localize"] => localize_once(),
        _ => anyhow::bail!("usage: workload match N f32|f16|int8 | workload localize"),
    }
}

fn match_once(n: usize, precision: &str) -> anyhow::Result<()> {
    let precision = match precision {
        "f32" => Precision::F32,
        "f16" => Precision::F16,
        "int8" => Precision::Int8,
        other => anyhow::bail!("unknown precision {other}"),
    };
    let checkpoint = std::fs::read(workload::shared("reference/fixtures/weights.safetensors"))?;
    let options = Options {
        rounding: Rounding::Nearest,
        ..Options::new(precision)
    };
    let (blob, _) = convert_with(&checkpoint, &options)?;
    let model = Model::from_bytes(&blob)?;
    let (query, db) = workload::pair(n);
    let matches = if precision == Precision::F32 {
        let mut m = MATCHER_F32.lock().expect("lock");
        m.match_pair(&model, &query, &db)?.len()
    } else {
        let mut m = MATCHER_F16.lock().expect("lock");
        m.match_pair(&model, &query, &db)?.len()
    };
    println!("match N={n} {precision:?}: {matches} matches");
    Ok(())
}

fn localize_once() -> anyhow::Result<()> {
    let blob = std::fs::read(workload::repo("models/gomatch-int8.bin"))?;
    let model = Model::from_bytes(&blob)?;
    let problem = workload::mouse_query()
        .ok_or_else(|| anyhow::anyhow!("colmap/mouse is absent under ../shared/data"))?;
    let mut localizer = LOCALIZER.lock().expect("lock");
    let result = workload::localize(&mut localizer, &model, &problem);
    println!(
        "localize: {} keypoints, {} views used, {} merged, outcome {:?}",
        problem.pixels.len(),
        result.views_used,
        result.counts.merged,
        result.outcome.is_ok()
    );
    Ok(())
}
