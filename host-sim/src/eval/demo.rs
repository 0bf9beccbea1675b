//! `gomatch-sim demo`: the whole localizer on a built-in synthetic scene, no files
//! needed. Builds the scene ([`crate::protocol::synthetic`]) and its map blob, localizes a few
//! protocol queries with the shipped model (or, without one, with ground-truth matches)
//! and prints per query the pose and reprojection errors, match counts and stage
//! timings, then the memory the device would need.

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use gomatch::{Localizer, LocalizerConfig, Model, PnpWorkspace};
use half::f16;

use crate::eval::{evaluate, EvalOptions, Matching, QueryResult, Report, SinkhornPrecision};
use crate::host::{default_model_path, CAPACITY};

use crate::protocol::synthetic::SyntheticQueries;

/// Localize a few queries of a built-in synthetic scene and print what happened.
#[derive(Debug, Clone, Parser)]
pub struct Args {
    /// Model blob (default: `models/gomatch-int8.bin`, searched upwards).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Use ground-truth matches even when a model is available.
    #[arg(long)]
    pub oracle: bool,
    /// The scene and its queries.
    #[command(flatten)]
    pub synthetic: SyntheticQueries,
    /// Storage of the Sinkhorn cost matrix.
    #[arg(long, value_enum, default_value_t = SinkhornPrecision::F16)]
    pub precision_sinkhorn: SinkhornPrecision,
    /// Print the core's log (per-view match counts, stage timings) to stderr.
    #[arg(long)]
    pub verbose: bool,
}

/// Writes the core's `log` records to stderr.
struct StderrLogger;

impl log::Log for StderrLogger {
    fn enabled(&self, _: &log::Metadata<'_>) -> bool {
        true
    }

    fn log(&self, record: &log::Record<'_>) {
        eprintln!("[{} {}] {}", record.level(), record.target(), record.args());
    }

    fn flush(&self) {}
}

fn kib(bytes: usize) -> String {
    if bytes >= 1 << 20 {
        format!("{:.2} MiB", bytes as f64 / f64::from(1 << 20))
    } else {
        format!("{:.1} KiB", bytes as f64 / 1024.0)
    }
}

fn print_query(q: &QueryResult) {
    println!(
        "query image {}: {} keypoints, {} views ({} matched), {} ground-truth matches",
        q.image_id, q.keypoints, q.views, q.views_used, q.gt_matches
    );
    let c = &q.counts;
    println!(
        "  matches: {} mutual, {} classified, {} merged, {} inliers; {} RANSAC iterations",
        c.mutual, c.classified, c.merged, c.inliers, q.ransac_iterations
    );
    match (&q.failure, q.rotation_deg, q.translation) {
        (None, Some(r), Some(t)) => println!(
            "  localized{}; errors: rotation {r:.4} deg, translation {t:.5}, reprojection {}",
            q.confidence
                .map_or(String::new(), |c| format!(" with confidence {c:.3}")),
            q.reprojection_px
                .map_or("infinite".to_string(), |e| format!("{e:.3} px"))
        ),
        (failure, _, _) => println!(
            "  not localized: {}",
            failure.as_deref().unwrap_or("unknown")
        ),
    }
    let t = &q.timings_ms;
    println!(
        "  time (ms): prepare {:.2}, encode {:.1}, match {:.1}, merge {:.2}, pose {:.2}, total {:.1}",
        t.prepare, t.encode, t.matching, t.merge, t.pose, t.total
    );
}

fn print_memory(report: &Report) {
    println!("memory:");
    let (f16_bytes, f32_bytes) = (
        Localizer::<CAPACITY, f16>::BYTES,
        Localizer::<CAPACITY, f32>::BYTES,
    );
    println!(
        "  Localizer<{CAPACITY}, f16>::BYTES {} ({f16_bytes} B), Localizer<{CAPACITY}, f32>::BYTES {} ({f32_bytes} B), RAM, static",
        kib(f16_bytes),
        kib(f32_bytes)
    );
    println!(
        "  of which PnpWorkspace<{CAPACITY}>::BYTES {}",
        kib(PnpWorkspace::<CAPACITY>::BYTES)
    );
    if report.model_bytes > 0 {
        println!(
            "  model blob {} (flash, read in place)",
            kib(report.model_bytes)
        );
    }
    println!(
        "  map blob {} (flash, read in place) for this scene",
        kib(report.map_bytes)
    );
}

/// Runs `gomatch-sim demo`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let started = std::time::Instant::now();
    if args.verbose {
        static LOGGER: StderrLogger = StderrLogger;
        log::set_logger(&LOGGER)
            .map(|()| log::set_max_level(log::LevelFilter::Debug))
            .map_err(|e| anyhow::anyhow!("installing the logger: {e}"))?;
    }
    let scene = args.synthetic.scene();
    println!(
        "synthetic scene {}: {} images, {} cameras, {} 3D points",
        scene.name,
        scene.images.len(),
        scene.cameras.len(),
        scene.points.len()
    );
    let model_path = args.model.clone().unwrap_or_else(default_model_path);
    let blob = if args.oracle {
        None
    } else if model_path.is_file() {
        Some(gomatch_blobs::files::read_model_blob(&model_path)?)
    } else {
        println!(
            "NOTE: no trained model at {}; falling back to ground-truth matches (oracle) to show the pose solver. Pass --model PATH to use another blob.",
            model_path.display()
        );
        None
    };
    let model = blob
        .as_deref()
        .map(Model::from_bytes)
        .transpose()
        .with_context(|| format!("decoding {}", model_path.display()))?;
    let matching = match (&model, &blob) {
        (Some(model), Some(blob)) => {
            println!(
                "model {} ({}, {:?} weights), Sinkhorn cost in {:?}",
                model_path.display(),
                kib(blob.len()),
                model.precision(),
                args.precision_sinkhorn
            );
            Matching::Model {
                model,
                blob_bytes: blob.len(),
                precision: args.precision_sinkhorn,
            }
        }
        _ => {
            println!("matches: ground truth (oracle)");
            Matching::Oracle
        }
    };
    let options = EvalOptions {
        protocol: args.synthetic.protocol(CAPACITY),
        localizer: LocalizerConfig::new(),
        threads: 1,
        view_features: false,
    };
    let report = evaluate(&scene, matching, &options, false)?;
    for q in &report.per_query {
        print_query(q);
    }
    let refused = report
        .per_query
        .iter()
        .filter(|q| q.failure.is_some() && q.confidence.is_some())
        .count();
    println!(
        "{} of {} queries localized ({refused} refused for low confidence); reprojection AUC @1/5/10 px {:.1} / {:.1} / {:.1} %",
        report.queries - report.failures,
        report.queries,
        report.auc_1px,
        report.auc_5px,
        report.auc_10px
    );
    print_memory(&report);
    println!("demo took {:.2} s", started.elapsed().as_secs_f64());
    Ok(())
}
