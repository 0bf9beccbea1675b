//! `gomatch-sim pnp`: runs the core's RANSAC-PnP on the shared synthetic PnP sets and
//! compares it with the PoseLib and OpenCV anchors measured on the very same sets.
//!
//! Per configuration (`n50_out00`, ...) it reports the success rate (rotation error below
//! 1 degree and camera-centre error below 1% of the scene distance), the median rotation
//! error in degrees, the median relative camera-centre error and the median time per call
//! on one thread, with the same keys as `anchors.json`, and the ratios to PoseLib.
//!
//! Scene distance: distance from the true camera centre to the centroid of the set's 3D
//! points. A call that finds no pose counts as a failure with infinite errors (written as
//! `null` in JSON, like the anchors).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use clap::Parser;
use cpu_time::ThreadTime;
use gomatch::{estimate_pose, PnpWorkspace, Pose, RansacConfig};
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

/// Capacity of the workspace used here (the sets hold at most 1000 correspondences).
pub const CAPACITY: usize = 1024;
/// Rotation error under which a pose counts as a success, degrees.
pub const SUCCESS_ROTATION_DEG: f64 = 1.0;
/// Camera-centre error, relative to the scene distance, under which a pose counts as a
/// success.
pub const SUCCESS_CENTER_RELATIVE: f64 = 0.01;

/// Arguments of `gomatch-sim pnp`.
#[derive(Parser, Debug)]
pub struct Args {
    /// Folder of `nCOUNT_outRATIO.json` sets.
    #[arg(long, default_value = "../shared/pnp/sets")]
    pub sets: PathBuf,
    /// Anchors (PoseLib, OpenCV) to compare with; default: `anchors.json` beside the folder.
    #[arg(long)]
    pub anchors: Option<PathBuf>,
    /// Write the results as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Timed calls per set (the median over all calls of a configuration is reported).
    #[arg(long, default_value_t = 5)]
    pub repeat: usize,
    /// Seed of the RANSAC sampler.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Inlier threshold on the normalised image plane.
    #[arg(long, default_value_t = 1e-3)]
    pub threshold: f64,
    /// Disable the local optimisation (LO) of RANSAC.
    #[arg(long)]
    pub no_lo: bool,
    /// Disable the final Levenberg-Marquardt refinement.
    #[arg(long)]
    pub no_refine: bool,
    /// Cap on RANSAC's minimal samples per set (default: the anchors' cap, not the
    /// localizer's).
    #[arg(long, default_value_t = ANCHOR_MAX_ITERATIONS)]
    pub max_iterations: u32,
}

/// RANSAC cap under which the anchors (PoseLib, OpenCV) were measured
/// (`shared/pnp/README.md`), so that comparisons with them are like for like.
pub const ANCHOR_MAX_ITERATIONS: u32 = 1000;

/// One file of synthetic sets (format: `shared/pnp/README.md`).
#[derive(Debug, Deserialize)]
pub struct SetFile {
    /// Correspondences per set.
    pub count: usize,
    /// Fraction of outliers.
    pub outlier_ratio: f64,
    /// The sets.
    pub sets: Vec<PnpSet>,
}

/// One 2D-3D correspondence set with its true pose.
#[derive(Debug, Deserialize)]
pub struct PnpSet {
    /// World points.
    pub points3d: Vec<[f64; 3]>,
    /// Bearing vectors `(x/z, y/z)`, noisy, outliers random.
    pub bearing: Vec<[f64; 2]>,
    /// True world-to-camera rotation, row-major.
    #[serde(rename = "R")]
    pub rotation: [f64; 9],
    /// True translation.
    pub t: [f64; 3],
}

impl PnpSet {
    /// The true pose.
    pub fn true_pose(&self) -> anyhow::Result<Pose> {
        let r = &self.rotation;
        let rows = [[r[0], r[1], r[2]], [r[3], r[4], r[5]], [r[6], r[7], r[8]]];
        Pose::from_matrix(&rows, &self.t).map_err(|e| anyhow::anyhow!("true pose: {e}"))
    }

    /// Distance from the true camera centre to the centroid of the 3D points.
    pub fn scene_distance(&self, truth: &Pose) -> f64 {
        let sum = self.points3d.iter().fold(Vector3::zeros(), |acc, p| {
            acc + Vector3::new(p[0], p[1], p[2])
        });
        let centroid = sum / self.points3d.len().max(1) as f64;
        (truth.center() - centroid).norm()
    }
}

/// Metrics of one configuration, with the keys of `anchors.json`.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct Metrics {
    /// Fraction of sets solved (rotation < 1 deg and centre error < 1% of scene distance).
    pub success_rate: f64,
    /// Median rotation error, degrees (`None`: infinite, no pose).
    pub rot_med_deg: Option<f64>,
    /// Median camera-centre error relative to the scene distance.
    pub trans_rel_med: Option<f64>,
    /// Median microseconds per call, one thread (thread CPU time).
    pub us_per_call: f64,
}

/// Errors of one solved set.
#[derive(Debug, Clone, Copy)]
pub struct SetOutcome {
    /// Rotation error in degrees (infinite when no pose was found).
    pub rotation_deg: f64,
    /// Camera-centre error relative to the scene distance (infinite when no pose).
    pub center_relative: f64,
}

impl SetOutcome {
    /// Whether the pose meets both success bounds.
    pub fn success(&self) -> bool {
        self.rotation_deg < SUCCESS_ROTATION_DEG && self.center_relative < SUCCESS_CENTER_RELATIVE
    }
}

/// The RANSAC settings of the command line.
pub fn ransac_config(args: &Args) -> RansacConfig {
    RansacConfig {
        seed: args.seed,
        threshold: args.threshold,
        local_optimization: !args.no_lo,
        refine: !args.no_refine,
        max_iterations: args.max_iterations,
        ..RansacConfig::new()
    }
}

/// Reads one set file.
pub fn load_set_file(path: &Path) -> anyhow::Result<SetFile> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))
}

/// The set files of a folder, keyed by configuration name and ordered by point count, then
/// outlier ratio.
pub fn list_set_files(folder: &Path) -> anyhow::Result<Vec<(String, PathBuf)>> {
    let mut files = Vec::new();
    for entry in
        std::fs::read_dir(folder).with_context(|| format!("listing {}", folder.display()))?
    {
        let path = entry?.path();
        let Some(name) = path.file_stem().and_then(|s| s.to_str()) else {
            continue;
        };
        if let Some(key) = configuration_key(name) {
            files.push((key, name.to_string(), path));
        }
    }
    files.sort();
    Ok(files
        .into_iter()
        .map(|(_, name, path)| (name, path))
        .collect())
}

/// Sort key `(count, outlier percent)` of a name `nCOUNT_outRATIO`.
fn configuration_key(name: &str) -> Option<(usize, usize)> {
    let (count, outliers) = name.strip_prefix('n')?.split_once("_out")?;
    Some((count.parse().ok()?, outliers.parse().ok()?))
}

/// Runs the solver once on a set and measures its errors.
pub fn solve_set(
    set: &PnpSet,
    config: &RansacConfig,
    workspace: &mut PnpWorkspace<CAPACITY>,
) -> anyhow::Result<SetOutcome> {
    let truth = set.true_pose()?;
    let outcome = match estimate_pose(&set.bearing, &set.points3d, config, workspace) {
        Ok(estimate) => SetOutcome {
            rotation_deg: estimate.pose.rotation_error_deg(&truth),
            center_relative: estimate.pose.center_error(&truth) / set.scene_distance(&truth),
        },
        Err(gomatch::Error::NoPoseFound) => SetOutcome {
            rotation_deg: f64::INFINITY,
            center_relative: f64::INFINITY,
        },
        Err(e) => bail!("solver refused a set: {e}"),
    };
    Ok(outcome)
}

/// Median like NumPy's (mean of the two middle values for an even count); `None` when empty
/// or infinite.
pub fn median(values: &[f64]) -> Option<f64> {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    let n = sorted.len();
    let m = match n {
        0 => return None,
        _ if n % 2 == 1 => sorted[n / 2],
        _ => 0.5 * (sorted[n / 2 - 1] + sorted[n / 2]),
    };
    m.is_finite().then_some(m)
}

/// Accuracy metrics of all sets of a file and the median time per call over `repeat` timed
/// calls per set (`repeat = 0` skips timing and reports 0). Time is the calling thread's CPU
/// time, so other processes on a busy machine do not inflate it.
pub fn evaluate_file(
    file: &SetFile,
    config: &RansacConfig,
    repeat: usize,
) -> anyhow::Result<Metrics> {
    let mut workspace = Box::new(PnpWorkspace::<CAPACITY>::new());
    let mut outcomes = Vec::with_capacity(file.sets.len());
    let mut times_us = Vec::with_capacity(file.sets.len() * repeat);
    for set in &file.sets {
        outcomes.push(solve_set(set, config, &mut workspace)?);
        for _ in 0..repeat {
            let start = ThreadTime::now();
            let result = estimate_pose(&set.bearing, &set.points3d, config, &mut workspace);
            let elapsed = start.elapsed();
            std::hint::black_box(&result);
            times_us.push(elapsed.as_secs_f64() * 1e6);
        }
    }
    let successes = outcomes.iter().filter(|o| o.success()).count();
    let rotations: Vec<f64> = outcomes.iter().map(|o| o.rotation_deg).collect();
    let centers: Vec<f64> = outcomes.iter().map(|o| o.center_relative).collect();
    Ok(Metrics {
        success_rate: successes as f64 / outcomes.len().max(1) as f64,
        rot_med_deg: median(&rotations),
        trans_rel_med: median(&centers),
        us_per_call: median(&times_us).unwrap_or(0.0),
    })
}

/// Anchors file: per method, per configuration, the metrics.
pub fn load_anchors(path: &Path) -> anyhow::Result<BTreeMap<String, BTreeMap<String, Metrics>>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let value: serde_json::Value = serde_json::from_str(&text)?;
    let mut methods = BTreeMap::new();
    for (method, per_config) in value.as_object().into_iter().flatten() {
        if let Ok(parsed) = serde_json::from_value::<BTreeMap<String, Metrics>>(per_config.clone())
        {
            methods.insert(method.clone(), parsed);
        }
    }
    Ok(methods)
}

/// Ratio `ours / theirs` (`None` when either is missing or the divisor is zero).
fn ratio(ours: Option<f64>, theirs: Option<f64>) -> Option<f64> {
    match (ours, theirs) {
        (Some(a), Some(b)) if b != 0.0 => Some(a / b),
        _ => None,
    }
}

/// Ratios of our metrics to another method's, same keys.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct Ratios {
    /// Success rate ratio.
    pub success_rate: Option<f64>,
    /// Median rotation error ratio.
    pub rot_med_deg: Option<f64>,
    /// Median relative centre error ratio.
    pub trans_rel_med: Option<f64>,
    /// Time per call ratio.
    pub us_per_call: Option<f64>,
}

fn ratios(ours: &Metrics, theirs: &Metrics) -> Ratios {
    Ratios {
        success_rate: ratio(Some(ours.success_rate), Some(theirs.success_rate)),
        rot_med_deg: ratio(ours.rot_med_deg, theirs.rot_med_deg),
        trans_rel_med: ratio(ours.trans_rel_med, theirs.trans_rel_med),
        us_per_call: ratio(Some(ours.us_per_call), Some(theirs.us_per_call)),
    }
}

#[derive(Serialize)]
struct Report<'a> {
    what: &'a str,
    settings: Settings,
    gomatch: &'a BTreeMap<String, Metrics>,
    ratio_to_poselib: BTreeMap<String, Ratios>,
}

#[derive(Serialize)]
struct Settings {
    max_iterations: u32,
    threshold: f64,
    confidence: f64,
    seed: u64,
    local_optimization: bool,
    refine: bool,
    timed_calls_per_set: usize,
}

fn show(value: Option<f64>, digits: usize) -> String {
    value.map_or("inf".into(), |v| format!("{v:.digits$}"))
}

/// Runs the command.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let config = ransac_config(args);
    let anchors_path = args
        .anchors
        .clone()
        .unwrap_or_else(|| args.sets.join("..").join("anchors.json"));
    let anchors = load_anchors(&anchors_path).unwrap_or_else(|e| {
        eprintln!("no anchors ({e:#}); reporting without ratios");
        BTreeMap::new()
    });
    let poselib = anchors.get("poselib");
    let files = list_set_files(&args.sets)?;
    if files.is_empty() {
        bail!("no nCOUNT_outRATIO.json sets in {}", args.sets.display());
    }
    let mut ours = BTreeMap::new();
    let mut to_poselib = BTreeMap::new();
    println!(
        "{:<12} {:>13} {:>17} {:>19} {:>17} | ratio to PoseLib: success rot trans time",
        "config", "success", "rot med deg", "trans rel med", "us/call"
    );
    for (name, path) in &files {
        let file = load_set_file(path)?;
        let metrics = evaluate_file(&file, &config, args.repeat)?;
        let theirs = poselib.and_then(|p| p.get(name));
        let r = theirs.map(|t| ratios(&metrics, t));
        let pair = |a: String, b: Option<String>| format!("{a} / {}", b.unwrap_or("-".into()));
        println!(
            "{:<12} {:>13} {:>17} {:>19} {:>17} | {} {} {} {}",
            name,
            pair(
                format!("{:.2}", metrics.success_rate),
                theirs.map(|t| format!("{:.2}", t.success_rate))
            ),
            pair(
                show(metrics.rot_med_deg, 3),
                theirs.map(|t| show(t.rot_med_deg, 3))
            ),
            pair(
                show(metrics.trans_rel_med, 5),
                theirs.map(|t| show(t.trans_rel_med, 5))
            ),
            pair(
                format!("{:.1}", metrics.us_per_call),
                theirs.map(|t| format!("{:.1}", t.us_per_call))
            ),
            show(r.and_then(|r| r.success_rate), 2),
            show(r.and_then(|r| r.rot_med_deg), 2),
            show(r.and_then(|r| r.trans_rel_med), 2),
            show(r.and_then(|r| r.us_per_call), 3),
        );
        if let Some(r) = r {
            to_poselib.insert(name.clone(), r);
        }
        ours.insert(name.clone(), metrics);
    }
    println!(
        "(ours / PoseLib; PoseLib figures from {})",
        anchors_path.display()
    );
    if let Some(out) = &args.json {
        let report = Report {
            what: "gomatch-rs RANSAC-PnP on the shared sets: median over the sets of each configuration; \
                   success = rotation < 1 deg and camera-centre error < 1% of the distance from the true \
                   centre to the centroid of the 3D points; us_per_call = median thread CPU time over all \
                   timed calls, one thread; ratio_to_poselib = ours / poselib",
            settings: Settings {
                max_iterations: config.max_iterations,
                threshold: config.threshold,
                confidence: config.confidence,
                seed: config.seed,
                local_optimization: config.local_optimization,
                refine: config.refine,
                timed_calls_per_set: args.repeat,
            },
            gomatch: &ours,
            ratio_to_poselib: to_poselib,
        };
        std::fs::write(out, serde_json::to_string_pretty(&report)?)
            .with_context(|| format!("writing {}", out.display()))?;
        println!("wrote {}", out.display());
    }
    Ok(())
}
