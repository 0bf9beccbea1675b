//! The matcher against the reference implementation's fixtures
//! (`shared/reference/fixtures`): every stage, the Sinkhorn iteration count and the match
//! set, for f32, f16 and int8 weights. Skips with a message when `shared/` is absent.
//!
//! Tolerances. f32 follows the reference's arithmetic (unfolded residual blocks, dot
//! products accumulated in order with fused multiply-add, or bias first with separate
//! multiply and add on sets of fewer than [`SMALL_SET`] points as its BLAS does there,
//! instance norm as its CPU kernel computes it), so every encoder output is bit-identical
//! and every stage is within 1e-4 of the reference, with identical matches. f16 weights:
//! agreement (`|A ∩ R| / |A ∪ R|`) >= 0.98; int8 with the converter's defaults
//! (error-correcting GPTQ calibrated on synthetic pairs, encoder input layer in f32)
//! >= 0.95 (see docs/evaluation.md, "Conformance with the reference").

use std::path::{Path, PathBuf};

use gomatch::nn::SMALL_SET;
use gomatch::Precision;
use gomatch_sim::eval::conform::{conform, conform_blob, PlanArg, Report};

fn fixtures() -> Option<Vec<PathBuf>> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/reference/fixtures");
    let Ok(entries) = std::fs::read_dir(&root) else {
        println!("SKIP: {} not found", root.display());
        return None;
    };
    let mut dirs: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("index.json").exists())
        .collect();
    dirs.sort();
    assert!(!dirs.is_empty(), "no fixture folders in {}", root.display());
    Some(dirs)
}

fn run(fixture: &Path, precision: Precision, plan: PlanArg) -> Report {
    let report = conform(fixture, None, precision, plan)
        .unwrap_or_else(|e| panic!("{}: {e:#}", fixture.display()));
    print_report(&report, precision, plan);
    report
}

fn print_report(report: &Report, precision: Precision, plan: PlanArg) {
    println!(
        "{} {:?} plan {:?}: agreement {:.3} ({} vs {} matches), iterations {} vs {}",
        report.fixture,
        precision,
        plan,
        report.match_agreement,
        report.matches,
        report.reference_matches,
        report.sinkhorn_iterations,
        report.reference_iterations
    );
}

#[test]
fn f32_weights_reproduce_every_stage() {
    let Some(fixtures) = fixtures() else { return };
    for fixture in &fixtures {
        let report = run(fixture, Precision::F32, PlanArg::F32);
        assert_eq!(
            report.sinkhorn_iterations, report.reference_iterations,
            "{}: Sinkhorn early stop",
            report.fixture
        );
        assert_eq!(report.match_agreement, 1.0, "{report:#?}");
        for (stage, &diff) in &report.stages {
            assert!(
                diff <= 1e-4,
                "{} stage {stage}: max |diff| {diff:e} > 1e-4",
                report.fixture
            );
        }
        for stage in ["enc2d", "enc3d"] {
            assert_eq!(report.stages[stage], 0.0, "{report:#?}");
        }
    }
}

/// Points in one of the fixture's sets.
fn set_size(fixture: &Path, points: &str) -> usize {
    npy_f32(&fixture.join(format!("{points}.npy"))).len() / 2
}

/// The fixtures cover both summation paths of the reference's BLAS.
#[test]
fn fixtures_include_a_set_below_the_small_set_size() {
    let Some(fixtures) = fixtures() else { return };
    let smallest = fixtures
        .iter()
        .flat_map(|f| ["pts2d", "pts3d_bvs"].map(|p| set_size(f, p)))
        .min();
    assert!(smallest.is_some_and(|n| n < SMALL_SET), "{smallest:?}");
}

#[test]
fn f16_cost_storage_keeps_the_matches() {
    let Some(fixtures) = fixtures() else { return };
    for fixture in &fixtures {
        let report = run(fixture, Precision::F32, PlanArg::F16);
        assert!(report.match_agreement >= 0.98, "{report:#?}");
        assert!(report.stages["scores"] <= 1e-4, "{report:#?}");
    }
}

#[test]
fn f16_weights_keep_the_matches() {
    let Some(fixtures) = fixtures() else { return };
    for fixture in &fixtures {
        let report = run(fixture, Precision::F16, PlanArg::F32);
        assert!(report.match_agreement >= 0.98, "{report:#?}");
    }
}

/// One conversion (the calibration runs once) for every fixture.
#[test]
fn int8_weights_keep_the_matches() {
    let Some(fixtures) = fixtures() else { return };
    let root = fixtures[0].parent().expect("fixture root");
    let checkpoint = std::fs::read(root.join("weights.safetensors")).expect("weights");
    let (blob, _) =
        gomatch_blobs::convert::convert(&checkpoint, Precision::Int8).expect("int8 conversion");
    for fixture in &fixtures {
        let report = conform_blob(fixture, &blob, PlanArg::F32)
            .unwrap_or_else(|e| panic!("{}: {e:#}", fixture.display()));
        print_report(&report, Precision::Int8, PlanArg::F32);
        assert!(report.match_agreement >= 0.95, "{report:#?}");
    }
}

fn npy_f32(path: &Path) -> Vec<f32> {
    let bytes = std::fs::read(path).expect("fixture file");
    npyz::NpyFile::new(&bytes[..])
        .expect("npy")
        .into_vec()
        .expect("f32 values")
}
