//! `gomatch-sim eval`: the paper's MegaDepth localization protocol (supp. "Dataset
//! Details", "Reprojection Error AUC") on any structure-from-motion model, through the
//! device path: the scene becomes a map blob ([`crate::map::build_map`]) and every query
//! runs the core's [`Localizer::localize`] with the protocol's co-visible view ids. With
//! `--oracle` the ground-truth matches go straight to the pose solver instead.
//!
//! Reported: the reprojection-error AUC at 1/5/10 px (ground-truth inlier 3D points
//! projected with the true and the estimated pose, [`query_reprojection_error`]), the
//! rotation and translation error quartiles of the localized queries, failures, mean
//! match counts per stage, how many merged matches and inliers are ground-truth pairs
//! ([`Correct`]), stage timings, and how well the acceptance rule separates right poses
//! from wrong ones ([`AcceptanceSummary`], with each query's [`Evidence`] and features).
//!
//! Beside it: [`fit`] fits the acceptance rule on its reports, [`demo`] localizes a
//! built-in synthetic scene, [`pnp`] compares RANSAC-PnP with PoseLib and OpenCV, and
//! [`conform`] compares the matcher's stages with the reference's.

pub mod conform;
pub mod demo;
pub mod fit;
pub mod pnp;

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::Instant;

use anyhow::{bail, Context};
use clap::{Parser, ValueEnum};
use gomatch::acceptance::{AcceptanceRule, Evidence, FEATURES};
use gomatch::guided::{GuidedConfig, GuidedCounts};
use gomatch::localizer::{Correspondence, MatchCounts, StageTimings};
use gomatch::map::Map;
use gomatch::sinkhorn::PlanScalar;
use gomatch::{
    estimate_pose, Localizer, LocalizerConfig, Model, PnpWorkspace, Pose, Query, RansacConfig,
    ViewSelection,
};
use half::f16;
use indicatif::{ProgressBar, ProgressStyle};
use serde::{Deserialize, Serialize};

use crate::host::{default_model_path, register_font, HostClock, ModelArgs, CAPACITY};
use crate::map::{build_map, map_point_index};
use crate::protocol::{
    error_auc, quantiles, query_reprojection_error, query_sample, select_queries, FreshDetection,
    ProtocolParams, QuerySample,
};
use crate::scene::{ImageId, PointId, Scene};
use gomatch_blobs::view_features::{attach, build_view_features};

/// Thread stack for the localizer workers: the workspace lives on it (about 7.7 MiB with
/// an f32 cost, twice that in unoptimised builds).
const WORKER_STACK: usize = 64 << 20;
/// AUC thresholds in pixels.
pub const AUC_THRESHOLDS: [f64; 3] = [1.0, 5.0, 10.0];
/// A pose is wrong when its reprojection error is above this (pixels)...
pub const WRONG_REPROJECTION_PX: f64 = 10.0;
/// ... or its rotation error above this (degrees).
pub const WRONG_ROTATION_DEG: f64 = 5.0;

/// Evaluate localization on a structure-from-motion model with the paper's protocol.
#[derive(Debug, Clone, Parser)]
pub struct Args {
    /// The scene.
    #[command(flatten)]
    pub source: ModelArgs,
    /// Co-visible views per query.
    #[arg(long, default_value_t = 10)]
    pub k: usize,
    /// Localizer capacity `N`: keypoints per query and points per view (`Localizer<N, _>`);
    /// 128 and 256 are the small-part configurations of docs/embedded.md.
    #[arg(long, default_value_t = CAPACITY, value_parser = parse_capacity)]
    pub capacity: usize,
    /// Send the ground-truth matches to the pose solver instead of the matcher's.
    #[arg(long)]
    pub oracle: bool,
    /// Model blob (default: models/gomatch-int8.bin, searched from the current folder and
    /// the executable's).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Storage of the Sinkhorn cost matrix.
    #[arg(long, value_enum, default_value_t = SinkhornPrecision::F16)]
    pub precision_sinkhorn: SinkhornPrecision,
    /// Queries sampled from the scene.
    #[arg(long, default_value_t = 500)]
    pub queries: usize,
    /// Seed of the protocol's query selection and of RANSAC's sampling (0: the device's
    /// default RANSAC seed).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Cap on RANSAC's minimal samples per query (the localizer's default; the adaptive
    /// stop usually ends earlier).
    #[arg(long, default_value_t = RansacConfig::new().max_iterations)]
    pub ransac_iterations: u32,
    /// Worker threads, each with its own localizer (results do not depend on it; timings
    /// do).
    #[arg(long, default_value_t = 1)]
    pub threads: usize,
    /// Write the JSON report here (optional).
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// PNG of the cumulative reprojection-error curve (recall vs px, 0-10 px).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Earlier JSON reports whose curves the plot shows beside this one (repeatable).
    #[arg(long, requires = "plot")]
    pub plot_with: Vec<PathBuf>,
    /// Acceptance rule to use instead of the built-in one: a JSON file as written by
    /// `gomatch-sim fit-acceptance` (`bias`, `weights`, `min_confidence`).
    #[arg(long)]
    pub acceptance: Option<PathBuf>,
    /// Precompute the map's view features for the model and capacity first (the map
    /// option of `map features`; built before the timed queries, same results).
    #[arg(long)]
    pub view_features: bool,
    /// Leave out guided re-matching: the pose is RANSAC-PnP's on the matcher's matches, as
    /// in the paper (the oracle's always is RANSAC-PnP's on the ground-truth matches); the
    /// acceptance rules are fitted with it.
    #[arg(long)]
    pub no_guided: bool,
    /// Leave out the second attempt after a refused pose (RANSAC-PnP once more on the
    /// matches its inliers left out, `docs/evaluation.md`, "Second attempt"); the acceptance
    /// rules are fitted with it.
    #[arg(long)]
    pub no_second_attempt: bool,
    /// Query keypoints as a new detector run on the photo would give them
    /// ([`FreshDetection::TYPICAL`]) instead of the reconstruction's own.
    #[arg(long)]
    pub fresh_keypoints: bool,
}

/// Storage type of the Sinkhorn cost matrix.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SinkhornPrecision {
    /// Half precision (the device configuration, 2 bytes per entry).
    F16,
    /// Single precision.
    F32,
}

/// Match counts per stage (the core's [`MatchCounts`]).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Counts {
    /// Mutual-assignment matches, summed over the views.
    pub mutual: f64,
    /// Accepted by the classifier, summed over the views.
    pub classified: f64,
    /// Merged: each keypoint and each 3D point once.
    pub merged: f64,
    /// Inliers of the final pose.
    pub inliers: f64,
}

impl From<MatchCounts> for Counts {
    fn from(c: MatchCounts) -> Self {
        Self {
            mutual: c.mutual as f64,
            classified: c.classified as f64,
            merged: c.merged as f64,
            inliers: c.inliers as f64,
        }
    }
}

/// How many of the merged matches and of the pose's inliers are ground-truth pairs (the
/// protocol's, supp. "Ground Truth Correspondences"): what separates a matching failure
/// from a pose-solver failure.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Correct {
    /// Merged matches that are ground-truth pairs.
    pub merged: f64,
    /// Inliers that are ground-truth pairs.
    pub inliers: f64,
}

/// Stage timings in milliseconds (the core's [`StageTimings`]).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct TimingsMs {
    /// Input checks, bearings, view selection.
    pub prepare: f64,
    /// Query encoder.
    pub encode: f64,
    /// Matching of all views.
    pub matching: f64,
    /// Merge.
    pub merge: f64,
    /// RANSAC-PnP.
    pub pose: f64,
    /// Whole query.
    pub total: f64,
}

impl From<StageTimings> for TimingsMs {
    fn from(t: StageTimings) -> Self {
        let ms = |us: u64| us as f64 / 1000.0;
        Self {
            prepare: ms(t.prepare_us),
            encode: ms(t.encode_us),
            matching: ms(t.match_us),
            merge: ms(t.merge_us),
            pose: ms(t.pose_us),
            total: ms(t.total_us),
        }
    }
}

/// The outcome of one query.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct QueryResult {
    /// The query image.
    pub image_id: ImageId,
    /// Keypoints given to the localizer.
    pub keypoints: usize,
    /// Views given (the protocol's co-visible views).
    pub views: usize,
    /// Views matched.
    pub views_used: usize,
    /// Ground-truth matches over all views (each keypoint once).
    pub gt_matches: usize,
    /// Match counts per stage.
    pub counts: Counts,
    /// Correct matches among them (absent in reports written before it was recorded).
    #[serde(default)]
    pub correct: Option<Correct>,
    /// RANSAC minimal samples drawn.
    pub ransac_iterations: u32,
    /// Why the query failed, if it did.
    pub failure: Option<String>,
    /// Mean reprojection error in pixels (infinite for a failure; `null` in JSON).
    pub reprojection_px: Option<f64>,
    /// The reference code's variant: mean distance between the ground-truth keypoints'
    /// pixels and their 3D points projected with the estimated pose.
    pub keypoint_reprojection_px: Option<f64>,
    /// Rotation error in degrees, when localized.
    pub rotation_deg: Option<f64>,
    /// Translation error in scene units, when localized.
    pub translation: Option<f64>,
    /// Stage timings.
    pub timings_ms: TimingsMs,
    /// Evidence about the best pose, when RANSAC found one with `min_inliers` inliers
    /// (absent in older reports and for the oracle).
    #[serde(default)]
    pub evidence: Option<Evidence>,
    /// The acceptance rule's inputs computed from `evidence` ([`Evidence::features`]).
    #[serde(default)]
    pub features: Option<[f32; FEATURES]>,
    /// The acceptance rule's confidence in that pose.
    #[serde(default)]
    pub confidence: Option<f32>,
    /// Reprojection error of that pose, accepted or not (`null`: no pose, or infinite).
    #[serde(default)]
    pub candidate_reprojection_px: Option<f64>,
    /// Rotation error of that pose, degrees.
    #[serde(default)]
    pub candidate_rotation_deg: Option<f64>,
    /// Whether that pose is right ([`pose_is_right`]); `null` without a pose.
    #[serde(default)]
    pub candidate_right: Option<bool>,
    /// What guided re-matching did to that pose (absent in older reports).
    #[serde(default)]
    pub guided: Option<GuidedCounts>,
    /// Whether the reported pose is the second attempt's
    /// ([`gomatch::localizer::Localization::second_attempt`]).
    #[serde(default)]
    pub second_attempt: bool,
}

/// A pose is right when its reprojection error is at most [`WRONG_REPROJECTION_PX`] and
/// its rotation error at most [`WRONG_ROTATION_DEG`].
pub fn pose_is_right(reprojection_px: Option<f64>, rotation_deg: f64) -> bool {
    reprojection_px.is_some_and(|e| e <= WRONG_REPROJECTION_PX)
        && rotation_deg <= WRONG_ROTATION_DEG
}

/// How the acceptance rule did on a scene. A *candidate* is a query for which RANSAC
/// found a pose with `min_inliers` (4) inliers: what the localizer accepted before the
/// rule existed.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AcceptanceSummary {
    /// The rule used.
    pub rule: AcceptanceRule,
    /// Queries with a candidate pose.
    pub candidates: usize,
    /// Candidates that are right ([`pose_is_right`]).
    pub candidates_right: usize,
    /// Queries whose pose was accepted (reported as localized).
    pub accepted: usize,
    /// Accepted poses that are wrong.
    pub accepted_wrong: usize,
    /// `1 - accepted_wrong / accepted` (`null` when none was accepted).
    pub precision: Option<f64>,
    /// Right accepted poses / right candidates: the share of the right poses the old
    /// `min_inliers` rule reported that this rule keeps (`null` without right candidates).
    pub recall: Option<f64>,
    /// Right accepted poses / all queries.
    pub right_of_all: f64,
}

impl AcceptanceSummary {
    /// Counts over the queries of a report.
    pub fn of(rule: AcceptanceRule, per_query: &[QueryResult]) -> Self {
        let candidates = per_query
            .iter()
            .filter(|q| q.candidate_right.is_some())
            .count();
        let right = |q: &QueryResult| q.candidate_right == Some(true);
        let candidates_right = per_query.iter().filter(|q| right(q)).count();
        let accepted: Vec<&QueryResult> =
            per_query.iter().filter(|q| q.failure.is_none()).collect();
        let accepted_right = accepted.iter().filter(|q| right(q)).count();
        let accepted_wrong = accepted.len() - accepted_right;
        let ratio = |a: usize, b: usize| (b > 0).then(|| a as f64 / b as f64);
        Self {
            rule,
            candidates,
            candidates_right,
            accepted: accepted.len(),
            accepted_wrong,
            precision: ratio(accepted_right, accepted.len()),
            recall: ratio(accepted_right, candidates_right),
            right_of_all: ratio(accepted_right, per_query.len()).unwrap_or(0.0),
        }
    }
}

/// The RANSAC cap of reports written before it was recorded (the localizer's default then).
fn default_ransac_iterations() -> u32 {
    1000
}

/// The capacity of reports written before it was recorded.
fn default_capacity() -> usize {
    CAPACITY
}

/// Capacities `eval --capacity` offers.
pub const CAPACITIES: [usize; 3] = [128, 256, CAPACITY];

/// A `--capacity` value: one of [`CAPACITIES`].
pub(crate) fn parse_capacity(text: &str) -> Result<usize, String> {
    let n: usize = text.parse().map_err(|e| format!("{e}"))?;
    if CAPACITIES.contains(&n) {
        Ok(n)
    } else {
        Err(format!("one of {CAPACITIES:?}"))
    }
}

/// Summary of an evaluation: the JSON report.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Report {
    /// Scene name.
    pub scene: String,
    /// `oracle` or the model blob's path.
    pub matcher: String,
    /// Sinkhorn cost storage (model runs).
    pub precision_sinkhorn: SinkhornPrecision,
    /// Co-visible views per query.
    pub k: usize,
    /// Localizer capacity (keypoints per query, points per view).
    #[serde(default = "default_capacity")]
    pub capacity: usize,
    /// Whether the map's precomputed view features were used.
    #[serde(default)]
    pub view_features: bool,
    /// Whether RANSAC-PnP's poses were re-matched by projection before the acceptance rule
    /// (`false` for the oracle, with `--no-guided`, and in reports written before it).
    #[serde(default)]
    pub guided: bool,
    /// Whether a refused pose had a second attempt (`false` for the oracle, with
    /// `--no-second-attempt`, and in reports written before it).
    #[serde(default)]
    pub second_attempt: bool,
    /// Whether the query keypoints looked like a fresh detection (`eval --fresh-keypoints`).
    #[serde(default)]
    pub fresh_keypoints: bool,
    /// Protocol seed.
    pub seed: u64,
    /// Cap on RANSAC's minimal samples per query.
    #[serde(default = "default_ransac_iterations")]
    pub ransac_max_iterations: u32,
    /// Queries evaluated.
    pub queries: usize,
    /// Queries without a pose.
    pub failures: usize,
    /// Reprojection-error AUC at 1 px, percent.
    pub auc_1px: f64,
    /// At 5 px.
    pub auc_5px: f64,
    /// At 10 px.
    pub auc_10px: f64,
    /// AUC @1/5/10 px of the reference code's variant (errors against the keypoint
    /// pixels, so keypoint noise enters).
    pub auc_keypoint_px: [f64; 3],
    /// Rotation error quartiles (25/50/75 %) of the localized queries, degrees.
    pub rot_deg_q: Option<[f64; 3]>,
    /// Translation error quartiles, scene units.
    pub trans_q: Option<[f64; 3]>,
    /// Mean keypoints per query.
    pub mean_keypoints: f64,
    /// Mean views matched per query.
    pub mean_views_used: f64,
    /// Mean ground-truth matches per query.
    pub mean_gt_matches: f64,
    /// Mean match counts per stage.
    pub mean_counts: Counts,
    /// Mean correct matches (absent in reports written before it was recorded).
    #[serde(default)]
    pub mean_correct: Option<Correct>,
    /// Mean stage timings.
    pub mean_timings_ms: TimingsMs,
    /// Worker threads used (timings are per query, measured under that load).
    pub threads: usize,
    /// Bytes of the localizer workspace.
    pub localizer_bytes: usize,
    /// Bytes of the map blob.
    pub map_bytes: usize,
    /// Bytes of the model blob (0 for the oracle).
    pub model_bytes: usize,
    /// The acceptance rule's precision and recall (absent in older reports).
    #[serde(default)]
    pub acceptance: Option<AcceptanceSummary>,
    /// Every query.
    pub per_query: Vec<QueryResult>,
}

/// What produces the 2D-3D matches.
#[derive(Clone, Copy)]
pub enum Matching<'m> {
    /// Ground-truth matches.
    Oracle,
    /// The network.
    Model {
        /// The decoded model.
        model: &'m Model<'m>,
        /// Size of its blob.
        blob_bytes: usize,
        /// Storage of the Sinkhorn cost.
        precision: SinkhornPrecision,
    },
}

/// Settings of [`evaluate`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EvalOptions {
    /// Protocol parameters (`k`, queries, seed).
    pub protocol: ProtocolParams,
    /// Localizer settings (RANSAC).
    pub localizer: LocalizerConfig,
    /// Worker threads.
    pub threads: usize,
    /// Localize on the map with its precomputed view features (the model's).
    pub view_features: bool,
}

/// The oracle's input: every ground-truth pair of every view, each keypoint once (its
/// first pair, views in the protocol's order), as (keypoint bearing, world point).
pub fn oracle_correspondences(sample: &QuerySample) -> (Vec<[f64; 2]>, Vec<[f64; 3]>) {
    let mut used = BTreeSet::new();
    let mut bearings = Vec::new();
    let mut points = Vec::new();
    for view in &sample.views {
        for &(keypoint, point) in &view.gt_pairs {
            if used.insert(keypoint) {
                bearings.push(sample.keypoints.bearings[keypoint]);
                let x = view.xyz[point];
                points.push([x.x, x.y, x.z]);
            }
        }
    }
    (bearings, points)
}

/// What one query produced, before scoring.
struct Outcome {
    estimate: Option<Pose>,
    guided: Option<GuidedCounts>,
    second_attempt: bool,
    candidate: Option<Pose>,
    evidence: Option<Evidence>,
    confidence: Option<f32>,
    failure: Option<String>,
    counts: MatchCounts,
    correct: Correct,
    views_used: usize,
    ransac_iterations: u32,
    timings: StageTimings,
}

fn oracle_outcome<const N: usize>(
    sample: &QuerySample,
    config: &RansacConfig,
    workspace: &mut PnpWorkspace<N>,
) -> Outcome {
    let start = Instant::now();
    let (bearings, points) = oracle_correspondences(sample);
    let gt_total: usize = sample.views.iter().map(|v| v.gt_pairs.len()).sum();
    let mut counts = MatchCounts {
        mutual: gt_total,
        classified: gt_total,
        merged: bearings.len(),
        inliers: 0,
    };
    let result = estimate_pose(&bearings, &points, config, workspace);
    let pose_us = u64::try_from(start.elapsed().as_micros()).unwrap_or(u64::MAX);
    let (estimate, failure, ransac_iterations) = match result {
        Ok(e) => {
            counts.inliers = e.inlier_count;
            (Some(e.pose), None, e.iterations)
        }
        Err(e) => (None, Some(e.to_string()), 0),
    };
    Outcome {
        estimate,
        guided: None,
        second_attempt: false,
        candidate: estimate,
        evidence: None,
        confidence: None,
        failure,
        counts,
        correct: Correct {
            merged: counts.merged as f64,
            inliers: counts.inliers as f64,
        },
        views_used: sample.views.len(),
        ransac_iterations,
        timings: StageTimings {
            pose_us,
            total_us: pose_us,
            ..StageTimings::default()
        },
    }
}

/// The query's keypoints as the device gets them: pixels in `f32`.
pub fn query_pixels(sample: &QuerySample) -> Vec<[f32; 2]> {
    sample
        .keypoints
        .pixels
        .iter()
        .map(|p| [p[0] as f32, p[1] as f32])
        .collect()
}

/// Runs the core localizer on one protocol sample with its co-visible view ids.
fn localizer_outcome<const N: usize, S: PlanScalar>(
    localizer: &mut Localizer<N, S>,
    model: &Model<'_>,
    map: &Map<'_>,
    point_index: &BTreeMap<PointId, u32>,
    sample: &QuerySample,
    config: &LocalizerConfig,
) -> anyhow::Result<Outcome> {
    let pixels = query_pixels(sample);
    let ids: Vec<u32> = sample.views.iter().map(|v| v.image_id).collect();
    let query = Query {
        keypoints: &pixels,
        camera: sample.camera,
    };
    let clock = HostClock::default();
    let result = localizer
        .localize(
            model,
            map,
            &query,
            ViewSelection::ImageIds(&ids),
            config,
            Some(&clock),
        )
        .with_context(|| format!("localizing image {}", sample.image_id))?;
    let truth = ground_truth_pairs(sample, point_index);
    let is_true = |c: &&Correspondence| truth.contains(&(usize::from(c.keypoint), c.point));
    let correct = Correct {
        merged: localizer.correspondences().iter().filter(is_true).count() as f64,
        inliers: localizer.inliers().filter(is_true).count() as f64,
    };
    Ok(Outcome {
        estimate: result.outcome.ok(),
        guided: config.guided.and(result.candidate).map(|_| result.guided),
        second_attempt: result.second_attempt,
        candidate: result.candidate,
        evidence: result.evidence,
        confidence: result.confidence,
        failure: result.outcome.err().map(|f| f.to_string()),
        counts: result.counts,
        correct,
        views_used: result.views_used,
        ransac_iterations: result.ransac_iterations,
        timings: result.timings.unwrap_or_default(),
    })
}

/// The ground-truth pairs of every view as (keypoint index, index of the 3D point in the
/// scene's map blob, [`map_point_index`]).
pub fn ground_truth_pairs(
    sample: &QuerySample,
    point_index: &BTreeMap<PointId, u32>,
) -> BTreeSet<(usize, u32)> {
    sample
        .views
        .iter()
        .flat_map(|view| {
            view.gt_pairs.iter().filter_map(|&(keypoint, point)| {
                let id = view.point_ids.get(point)?;
                Some((keypoint, *point_index.get(id)?))
            })
        })
        .collect()
}

/// The reference implementation's reprojection error: mean pixel distance between each
/// ground-truth keypoint (each once) and its 3D point projected with the estimated pose
/// under the query's projection rule; infinite without an estimate, ground truth, or when
/// the rule refuses a point under the estimate.
pub fn keypoint_reprojection_error(sample: &QuerySample, estimate: Option<&Pose>) -> f64 {
    let Some(estimate) = estimate else {
        return f64::INFINITY;
    };
    let mut used = BTreeSet::new();
    let (mut total, mut count) = (0.0, 0usize);
    for view in &sample.views {
        for &(keypoint, point) in &view.gt_pairs {
            if !used.insert(keypoint) {
                continue;
            }
            let projected = sample
                .projection
                .bearing(estimate, &view.xyz[point])
                .ok()
                .and_then(|b| sample.camera.bearing_to_pixel(b).ok());
            let Some(p) = projected else {
                return f64::INFINITY;
            };
            let k = sample.keypoints.pixels[keypoint];
            total += ((p[0] - k[0]).powi(2) + (p[1] - k[1]).powi(2)).sqrt();
            count += 1;
        }
    }
    if count == 0 {
        f64::INFINITY
    } else {
        total / count as f64
    }
}

/// Scores one query (supp. "Reprojection Error AUC").
fn score(sample: &QuerySample, outcome: Outcome) -> QueryResult {
    let gt_points = sample.gt_inlier_points();
    let error = query_reprojection_error(
        &sample.camera,
        &sample.projection,
        &sample.pose,
        outcome.estimate.as_ref(),
        &gt_points,
    );
    let keypoint_error = keypoint_reprojection_error(sample, outcome.estimate.as_ref());
    let candidate_error = query_reprojection_error(
        &sample.camera,
        &sample.projection,
        &sample.pose,
        outcome.candidate.as_ref(),
        &gt_points,
    );
    let candidate_error = candidate_error.is_finite().then_some(candidate_error);
    let candidate_rotation = outcome
        .candidate
        .map(|c| c.rotation_error_deg(&sample.pose));
    QueryResult {
        image_id: sample.image_id,
        keypoints: sample.keypoints.len(),
        views: sample.views.len(),
        views_used: outcome.views_used,
        gt_matches: oracle_correspondences(sample).0.len(),
        counts: outcome.counts.into(),
        correct: Some(outcome.correct),
        ransac_iterations: outcome.ransac_iterations,
        failure: outcome.failure,
        reprojection_px: error.is_finite().then_some(error),
        keypoint_reprojection_px: keypoint_error.is_finite().then_some(keypoint_error),
        rotation_deg: outcome.estimate.map(|e| e.rotation_error_deg(&sample.pose)),
        translation: outcome.estimate.map(|e| e.translation_error(&sample.pose)),
        timings_ms: outcome.timings.into(),
        evidence: outcome.evidence,
        features: outcome.evidence.map(|e| e.features()),
        confidence: outcome.confidence,
        candidate_reprojection_px: candidate_error,
        candidate_rotation_deg: candidate_rotation,
        candidate_right: candidate_rotation.map(|r| pose_is_right(candidate_error, r)),
        guided: outcome.guided,
        second_attempt: outcome.second_attempt,
    }
}

/// What the localizer workers run on.
#[derive(Clone, Copy)]
struct Work<'a, 'm> {
    samples: &'a [QuerySample],
    matching: Matching<'m>,
    map: &'a Map<'m>,
    point_index: &'a BTreeMap<PointId, u32>,
    options: &'a EvalOptions,
    progress: &'a ProgressBar,
}

/// [`run_workers`] with the localizer capacity of the protocol (`--capacity`); also the
/// workspace bytes of one worker (the localizer's, or the pose solver's for the oracle).
fn run_at_capacity<S: PlanScalar + Send>(
    work: Work<'_, '_>,
) -> anyhow::Result<(Vec<QueryResult>, usize)> {
    fn bytes<const N: usize, S: PlanScalar>(matching: Matching<'_>) -> usize {
        match matching {
            Matching::Oracle => PnpWorkspace::<N>::BYTES,
            Matching::Model { .. } => Localizer::<N, S>::BYTES,
        }
    }
    Ok(match work.options.protocol.max_keypoints {
        128 => (run_workers::<128, S>(work)?, bytes::<128, S>(work.matching)),
        256 => (run_workers::<256, S>(work)?, bytes::<256, S>(work.matching)),
        CAPACITY => (
            run_workers::<CAPACITY, S>(work)?,
            bytes::<CAPACITY, S>(work.matching),
        ),
        other => anyhow::bail!("capacity {other} is not one of {CAPACITIES:?}"),
    })
}

/// Localizes every sample in `threads` workers; query `i` goes to worker `i % threads`,
/// and each worker owns one localizer, so results do not depend on the thread count.
fn run_workers<const N: usize, S: PlanScalar + Send>(
    work: Work<'_, '_>,
) -> anyhow::Result<Vec<QueryResult>> {
    let Work {
        samples,
        matching,
        map,
        point_index,
        options,
        progress,
    } = work;
    let threads = options.threads.clamp(1, samples.len().max(1));
    let results: Mutex<Vec<Option<QueryResult>>> = Mutex::new(vec![None; samples.len()]);
    std::thread::scope(|scope| -> anyhow::Result<()> {
        let handles = (0..threads)
            .map(|worker| {
                let results = &results;
                std::thread::Builder::new()
                    .name(format!("localizer-{worker}"))
                    .stack_size(WORKER_STACK)
                    .spawn_scoped(scope, move || -> anyhow::Result<()> {
                        let mut localizer = Localizer::<N, S>::new();
                        let mut workspace = PnpWorkspace::<N>::new();
                        for (i, sample) in samples.iter().enumerate().skip(worker).step_by(threads)
                        {
                            let outcome = match matching {
                                Matching::Oracle => oracle_outcome(
                                    sample,
                                    &options.localizer.ransac_config(N),
                                    &mut workspace,
                                ),
                                Matching::Model { model, .. } => localizer_outcome(
                                    &mut localizer,
                                    model,
                                    map,
                                    point_index,
                                    sample,
                                    &options.localizer,
                                )?,
                            };
                            let result = score(sample, outcome);
                            results.lock().map_err(|_| anyhow::anyhow!("poisoned"))?[i] =
                                Some(result);
                            progress.inc(1);
                        }
                        Ok(())
                    })
                    .context("spawning a localizer thread")
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        for handle in handles {
            handle
                .join()
                .map_err(|_| anyhow::anyhow!("a localizer thread panicked"))??;
        }
        Ok(())
    })?;
    let results = results
        .into_inner()
        .map_err(|_| anyhow::anyhow!("poisoned"))?;
    Ok(results.into_iter().flatten().collect())
}

/// Mean correct matches over the queries, if every query recorded them.
fn mean_correct(per_query: &[QueryResult]) -> Option<Correct> {
    let correct: Vec<Correct> = per_query.iter().map(|q| q.correct).collect::<Option<_>>()?;
    Some(Correct {
        merged: mean(correct.iter().map(|c| c.merged)),
        inliers: mean(correct.iter().map(|c| c.inliers)),
    })
}

fn mean(values: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    if n == 0 {
        0.0
    } else {
        sum / n as f64
    }
}

/// The protocol's samples with `k` views each, for the queries the paper's protocol
/// selects with its default `k` (10), so that every `k` evaluates the same queries.
pub fn protocol_samples(scene: &Scene, params: &ProtocolParams) -> Vec<QuerySample> {
    let selection = ProtocolParams {
        k: params.k.max(ProtocolParams::default().k),
        ..*params
    };
    select_queries(scene, &selection)
        .into_iter()
        .filter_map(|id| query_sample(scene, id, params))
        .collect()
}

/// Evaluates the scene's protocol queries with the given matching.
pub fn evaluate(
    scene: &Scene,
    matching: Matching<'_>,
    options: &EvalOptions,
    show_progress: bool,
) -> anyhow::Result<Report> {
    let samples = protocol_samples(scene, &options.protocol);
    let blob = build_map(scene)?;
    let mut map = Map::from_bytes(&blob).context("reading back the map")?;
    let features = match matching {
        Matching::Model { model, .. } if options.view_features => {
            build_view_features(model, &map, options.protocol.max_points)?
        }
        _ => Vec::new(),
    };
    if !features.is_empty() {
        map = attach(map, &features)?;
    }
    let point_index = map_point_index(scene)?;
    let progress = if show_progress {
        ProgressBar::new(samples.len() as u64).with_style(
            ProgressStyle::with_template("{bar:40} {pos}/{len} queries {elapsed} (eta {eta})")
                .context("progress bar template")?,
        )
    } else {
        ProgressBar::hidden()
    };
    let work = Work {
        samples: &samples,
        matching,
        map: &map,
        point_index: &point_index,
        options,
        progress: &progress,
    };
    let ((per_query, localizer_bytes), model_bytes, precision) = match matching {
        Matching::Oracle => (run_at_capacity::<f32>(work)?, 0, SinkhornPrecision::F32),
        Matching::Model {
            blob_bytes,
            precision: SinkhornPrecision::F16,
            ..
        } => (
            run_at_capacity::<f16>(work)?,
            blob_bytes,
            SinkhornPrecision::F16,
        ),
        Matching::Model {
            blob_bytes,
            precision: SinkhornPrecision::F32,
            ..
        } => (
            run_at_capacity::<f32>(work)?,
            blob_bytes,
            SinkhornPrecision::F32,
        ),
    };
    progress.finish_and_clear();
    let errors: Vec<f64> = per_query
        .iter()
        .map(|q| q.reprojection_px.unwrap_or(f64::INFINITY))
        .collect();
    let auc = error_auc(&errors, &AUC_THRESHOLDS);
    let keypoint_errors: Vec<f64> = per_query
        .iter()
        .map(|q| q.keypoint_reprojection_px.unwrap_or(f64::INFINITY))
        .collect();
    let auc_keypoint = error_auc(&keypoint_errors, &AUC_THRESHOLDS);
    let q = [0.25, 0.5, 0.75];
    let quartiles = |values: Vec<f64>| quantiles(&values, &q).map(|v| [v[0], v[1], v[2]]);
    let rot_deg_q = quartiles(per_query.iter().filter_map(|q| q.rotation_deg).collect());
    let trans_q = quartiles(per_query.iter().filter_map(|q| q.translation).collect());
    let n = per_query.len();
    let counts = |f: fn(&Counts) -> f64| mean(per_query.iter().map(|q| f(&q.counts)));
    let timing = |f: fn(&TimingsMs) -> f64| mean(per_query.iter().map(|q| f(&q.timings_ms)));
    Ok(Report {
        scene: scene.name.clone(),
        matcher: match matching {
            Matching::Oracle => "oracle".into(),
            Matching::Model { .. } => "model".into(),
        },
        precision_sinkhorn: precision,
        k: options.protocol.k,
        capacity: options.protocol.max_keypoints,
        view_features: !features.is_empty(),
        guided: options.localizer.guided.is_some() && !matches!(matching, Matching::Oracle),
        second_attempt: options.localizer.second_attempt && !matches!(matching, Matching::Oracle),
        fresh_keypoints: options.protocol.fresh.is_some(),
        seed: options.protocol.seed,
        ransac_max_iterations: options.localizer.ransac.max_iterations,
        queries: n,
        failures: per_query.iter().filter(|q| q.failure.is_some()).count(),
        auc_1px: auc[0],
        auc_5px: auc[1],
        auc_10px: auc[2],
        auc_keypoint_px: [auc_keypoint[0], auc_keypoint[1], auc_keypoint[2]],
        rot_deg_q,
        trans_q,
        mean_keypoints: mean(per_query.iter().map(|q| q.keypoints as f64)),
        mean_views_used: mean(per_query.iter().map(|q| q.views_used as f64)),
        mean_gt_matches: mean(per_query.iter().map(|q| q.gt_matches as f64)),
        mean_counts: Counts {
            mutual: counts(|c| c.mutual),
            classified: counts(|c| c.classified),
            merged: counts(|c| c.merged),
            inliers: counts(|c| c.inliers),
        },
        mean_correct: mean_correct(&per_query),
        mean_timings_ms: TimingsMs {
            prepare: timing(|t| t.prepare),
            encode: timing(|t| t.encode),
            matching: timing(|t| t.matching),
            merge: timing(|t| t.merge),
            pose: timing(|t| t.pose),
            total: timing(|t| t.total),
        },
        threads: options.threads.max(1),
        localizer_bytes,
        map_bytes: blob.len(),
        model_bytes,
        acceptance: Some(AcceptanceSummary::of(
            options
                .localizer
                .acceptance_rule(options.protocol.max_keypoints),
            &per_query,
        )),
        per_query,
    })
}

/// Draws the cumulative reprojection-error curves (recall in percent vs threshold, 0-10
/// px) of one or more reports, like the paper's AUC figure, titled after the scene.
pub fn plot_curves(scene: &str, curves: &[(String, Vec<f64>)], path: &Path) -> anyhow::Result<()> {
    use plotters::prelude::*;

    const MAX_PX: f64 = 10.0;
    const STEPS: usize = 400;
    let font = register_font();
    let root = BitMapBackend::new(path, (800, 560)).into_drawing_area();
    root.fill(&WHITE)?;
    let mut chart = ChartBuilder::on(&root);
    chart.margin(20);
    if font {
        chart
            .caption(
                format!("{scene}: cumulative reprojection error"),
                ("sans-serif", 24),
            )
            .x_label_area_size(45)
            .y_label_area_size(55);
    } else {
        chart.x_label_area_size(0).y_label_area_size(0);
    }
    let mut chart = chart.build_cartesian_2d(0.0..MAX_PX, 0.0..100.0)?;
    if font {
        chart
            .configure_mesh()
            .x_desc("reprojection error threshold (px)")
            .y_desc("queries localized (%)")
            .draw()?;
    } else {
        chart
            .configure_mesh()
            .disable_x_mesh()
            .disable_y_mesh()
            .draw()?;
    }
    for (i, (label, errors)) in curves.iter().enumerate() {
        let n = errors.len().max(1) as f64;
        let recall = |t: f64| 100.0 * errors.iter().filter(|&&e| e < t).count() as f64 / n;
        let color = Palette99::pick(i).to_rgba();
        let points = (0..=STEPS).map(|s| {
            let t = MAX_PX * s as f64 / STEPS as f64;
            (t, recall(t))
        });
        let series = chart.draw_series(LineSeries::new(points, color.stroke_width(2)))?;
        if font {
            series
                .label(label.as_str())
                .legend(move |(x, y)| PathElement::new([(x, y), (x + 20, y)], color));
        }
    }
    if font {
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::LowerRight)
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()?;
    } else {
        eprintln!("no TrueType font found: the plot has curves but no text");
    }
    root.present()?;
    Ok(())
}

/// Label of a report's curve: matcher (the model blob's file name), k and the three AUCs.
pub fn curve_label(report: &Report) -> String {
    let matcher = Path::new(&report.matcher)
        .file_name()
        .map_or(report.matcher.clone(), |n| n.to_string_lossy().into_owned());
    format!(
        "{matcher} k={} ({:.1}/{:.1}/{:.1})",
        report.k, report.auc_1px, report.auc_5px, report.auc_10px
    )
}

/// Reprojection errors of a report, failures as infinite.
pub fn report_errors(report: &Report) -> Vec<f64> {
    report
        .per_query
        .iter()
        .map(|q| q.reprojection_px.unwrap_or(f64::INFINITY))
        .collect()
}

fn print_report(report: &Report) {
    println!(
        "{} k={} N={} {}: {} queries, {} failures",
        report.scene, report.k, report.capacity, report.matcher, report.queries, report.failures
    );
    println!(
        "  reprojection AUC @1/5/10 px: {:.2} / {:.2} / {:.2} %",
        report.auc_1px, report.auc_5px, report.auc_10px
    );
    let k = &report.auc_keypoint_px;
    println!(
        "  (reference code's variant, against keypoint pixels: {:.2} / {:.2} / {:.2} %)",
        k[0], k[1], k[2]
    );
    if let (Some(r), Some(t)) = (report.rot_deg_q, report.trans_q) {
        println!(
            "  rotation error quartiles (deg): {:.4} / {:.4} / {:.4}",
            r[0], r[1], r[2]
        );
        println!(
            "  translation error quartiles:    {:.5} / {:.5} / {:.5}",
            t[0], t[1], t[2]
        );
    }
    let c = &report.mean_counts;
    println!(
        "  mean per query: {:.0} keypoints, {:.1} views, {:.1} ground-truth matches; matches {:.1} mutual / {:.1} classified / {:.1} merged / {:.1} inliers",
        report.mean_keypoints, report.mean_views_used, report.mean_gt_matches, c.mutual, c.classified, c.merged, c.inliers
    );
    if let Some(t) = &report.mean_correct {
        println!(
            "  of which ground-truth pairs: {:.1} merged, {:.1} inliers",
            t.merged, t.inliers
        );
    }
    if let Some(a) = &report.acceptance {
        let percent = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{:.1} %", 100.0 * v));
        println!(
            "  acceptance: {} accepted, {} of them wrong (precision {}); {} of {} right poses with >= 4 inliers kept (recall {})",
            a.accepted,
            a.accepted_wrong,
            percent(a.precision),
            a.accepted - a.accepted_wrong,
            a.candidates_right,
            percent(a.recall)
        );
    }
    let t = &report.mean_timings_ms;
    println!(
        "  mean time per query (ms, {} thread(s)): encode {:.1}, match {:.1}, merge {:.2}, pose {:.2}, total {:.1}",
        report.threads, t.encode, t.matching, t.merge, t.pose, t.total
    );
}

/// Reads an acceptance rule from a JSON file (`gomatch-sim fit-acceptance`'s output; fields
/// other than the rule's are ignored).
pub fn read_rule(path: &Path) -> anyhow::Result<AcceptanceRule> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| {
        format!(
            "{}: not an acceptance rule (bias, weights, min_confidence)",
            path.display()
        )
    })
}

/// Runs `gomatch-sim eval`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    if args.k == 0 || args.k > gomatch::localizer::MAX_VIEWS {
        bail!(
            "--k must be 1..={} (got {})",
            gomatch::localizer::MAX_VIEWS,
            args.k
        );
    }
    let source = args.source.source()?;
    let mut scene = source.load()?;
    scene.name = source.name();
    let options = EvalOptions {
        protocol: ProtocolParams {
            fresh: args.fresh_keypoints.then_some(FreshDetection::TYPICAL),
            ..ProtocolParams::for_localizer(args.k, args.queries, args.seed, args.capacity)
        },
        localizer: LocalizerConfig {
            ransac: RansacConfig {
                max_iterations: args.ransac_iterations,
                seed: args.seed,
                ..RansacConfig::new()
            },
            acceptance: args.acceptance.as_deref().map(read_rule).transpose()?,
            guided: (!args.no_guided).then(GuidedConfig::new),
            second_attempt: !args.no_second_attempt,
            ..LocalizerConfig::new()
        },
        threads: args.threads,
        view_features: args.view_features,
    };
    let model_path = args.model.clone().unwrap_or_else(default_model_path);
    let blob;
    let model;
    let (matching, matcher) = if args.oracle {
        (Matching::Oracle, "oracle".to_string())
    } else {
        blob = gomatch_blobs::files::read_model_blob(&model_path)
            .context("pass --model PATH, or use --oracle")?;
        model = Model::from_bytes(&blob)
            .with_context(|| format!("decoding the model {}", model_path.display()))?;
        (
            Matching::Model {
                model: &model,
                blob_bytes: blob.len(),
                precision: args.precision_sinkhorn,
            },
            model_path.display().to_string(),
        )
    };
    let mut report = evaluate(&scene, matching, &options, true)?;
    report.matcher = matcher;
    print_report(&report);
    if let Some(json) = &args.json {
        std::fs::write(json, serde_json::to_string_pretty(&report)?)
            .with_context(|| format!("writing {}", json.display()))?;
        println!("wrote {}", json.display());
    }
    if let Some(plot) = &args.plot {
        let mut curves = vec![(curve_label(&report), report_errors(&report))];
        for other in &args.plot_with {
            let text = std::fs::read_to_string(other)
                .with_context(|| format!("reading {}", other.display()))?;
            let earlier: Report = serde_json::from_str(&text)
                .with_context(|| format!("parsing {}", other.display()))?;
            curves.push((curve_label(&earlier), report_errors(&earlier)));
        }
        plot_curves(&report.scene, &curves, plot)?;
        println!("wrote {}", plot.display());
    }
    Ok(())
}
