//! `gomatch-sim fit-acceptance`: fits the core's [`AcceptanceRule`] on `eval` reports of
//! training scenes. Each query with a candidate pose (RANSAC found one with 4 inliers) is
//! one example: its [`Evidence::features`] and whether the pose is right
//! ([`QueryResult::candidate_right`]). The logistic weights maximise the L2-regularised
//! likelihood on standardised features (Newton's method, deterministic), and are then
//! expressed on the raw features; `min_confidence` is the lowest confidence at which the
//! accepted training poses are at most `--max-wrong` wrong. Reports of other scenes given
//! with `--check` are scored with the fitted rule (the core's own
//! [`AcceptanceRule::confidence`] on their stored evidence, so the figures are those a
//! new `eval` run with the rule gives).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use clap::Parser;
use gomatch::acceptance::{AcceptanceRule, Evidence, OperatingPoint, FEATURES, OPERATING_SHARES};
use nalgebra::{SMatrix, SVector};
use serde::{Deserialize, Serialize};

use crate::eval::{QueryResult, Report};

/// Fit the acceptance rule's weights and threshold on `eval` reports.
#[derive(Debug, Clone, Parser)]
pub struct Args {
    /// `eval` JSON reports of the training scenes.
    #[arg(long, num_args = 1.., required = true)]
    pub reports: Vec<PathBuf>,
    /// Reports scored with the fitted rule, not used in the fit (e.g. validation scenes).
    #[arg(long, num_args = 1..)]
    pub check: Vec<PathBuf>,
    /// Threshold: the lowest that keeps the share of wrong poses among the accepted
    /// training poses at most this.
    #[arg(long, conflicts_with = "min_recall")]
    pub max_wrong: Option<f64>,
    /// Threshold: the highest that keeps at least this share of the right training poses
    /// (the default, 0.97, is issue 19's recall goal).
    #[arg(long)]
    pub min_recall: Option<f64>,
    /// L2 penalty on the standardised weights.
    #[arg(long, default_value_t = 1e-2)]
    pub l2: f64,
    /// The localizer capacity the reports were evaluated at (`eval --capacity`); a report of
    /// another capacity is an error. Default: the capacity of the first report.
    #[arg(long)]
    pub capacity: Option<usize>,
    /// Where to write the rule (JSON, read by `eval --acceptance`).
    #[arg(long)]
    pub out: PathBuf,
}

/// One training example.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Example {
    /// The pose's evidence.
    pub evidence: Evidence,
    /// Whether the pose is right.
    pub right: bool,
}

/// Precision and recall of a rule on a set of examples (see [`crate::eval::AcceptanceSummary`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Scores {
    /// Examples (candidate poses).
    pub candidates: usize,
    /// Right ones.
    pub right: usize,
    /// Accepted.
    pub accepted: usize,
    /// Accepted and wrong.
    pub accepted_wrong: usize,
}

impl Scores {
    /// Scores `rule` on `examples`.
    pub fn of(rule: &AcceptanceRule, examples: &[Example]) -> Self {
        let accepted: Vec<&Example> = examples
            .iter()
            .filter(|e| rule.accepts(rule.confidence(&e.evidence)))
            .collect();
        Self {
            candidates: examples.len(),
            right: examples.iter().filter(|e| e.right).count(),
            accepted: accepted.len(),
            accepted_wrong: accepted.iter().filter(|e| !e.right).count(),
        }
    }

    /// Right poses accepted.
    fn kept(&self) -> usize {
        self.accepted - self.accepted_wrong
    }

    /// `accepted, wrong (share), recall` for a table cell (0.0 % of nothing).
    fn brief(&self) -> String {
        let share = |a, b| percent(a, b).unwrap_or(0.0);
        format!(
            "{}, {} ({:.1} %), {:.1} %",
            self.accepted,
            self.accepted_wrong,
            share(self.accepted_wrong, self.accepted),
            share(self.kept(), self.right)
        )
    }

    fn describe(&self) -> String {
        let kept = self.kept();
        let share = |a, b| percent(a, b).map_or("-".to_string(), |p| format!("{p:.1} %"));
        format!(
            "{} candidates ({} right): {} accepted, {} wrong (precision {}), recall {} ({kept} of {})",
            self.candidates,
            self.right,
            self.accepted,
            self.accepted_wrong,
            share(kept, self.accepted),
            share(kept, self.right),
            self.right
        )
    }
}

/// `100 a / b`, `None` when `b` is 0.
fn percent(a: usize, b: usize) -> Option<f64> {
    (b > 0).then(|| 100.0 * a as f64 / b as f64)
}

/// The written file: the rule (read by `eval --acceptance`) and how it was obtained.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FitOutput {
    /// Constant term.
    pub bias: f32,
    /// Feature weights.
    pub weights: [f32; FEATURES],
    /// Threshold.
    pub min_confidence: f32,
    /// The capacity the reports were evaluated at.
    pub capacity: usize,
    /// The training reports' scenes.
    pub training_scenes: Vec<String>,
    /// The rule on the training examples.
    pub training: Scores,
    /// The rule on the checked examples (none: no `--check` reports).
    pub checked: Option<Scores>,
    /// The thresholds at each share of [`OPERATING_SHARES`] of wrong training poses.
    pub operating_points: Vec<OperatingPoint>,
}

impl FitOutput {
    /// The rule alone.
    pub fn rule(&self) -> AcceptanceRule {
        AcceptanceRule {
            bias: self.bias,
            weights: self.weights,
            min_confidence: self.min_confidence,
        }
    }
}

/// The examples of a report: its queries with a candidate pose.
pub fn examples(report: &Report) -> Vec<Example> {
    report.per_query.iter().filter_map(example).collect()
}

fn example(q: &QueryResult) -> Option<Example> {
    Some(Example {
        evidence: q.evidence?,
        right: q.candidate_right?,
    })
}

fn read_report(path: &Path) -> anyhow::Result<Report> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))
}

/// Parameters of the logistic model: the bias and one weight per feature.
const DIM: usize = FEATURES + 1;

/// Logistic regression weights `(bias, weights)` on raw features, fitted on standardised
/// ones with an L2 penalty `l2` (not on the bias) by Newton's method.
pub fn logistic_fit(examples: &[Example], l2: f64) -> anyhow::Result<(f64, [f64; FEATURES])> {
    let n = examples.len();
    if n == 0 {
        bail!("no example with a candidate pose");
    }
    let raw: Vec<[f64; FEATURES]> = examples
        .iter()
        .map(|e| e.evidence.features().map(f64::from))
        .collect();
    let mut mean = [0.0; FEATURES];
    let mut scale = [0.0; FEATURES];
    for j in 0..FEATURES {
        mean[j] = raw.iter().map(|f| f[j]).sum::<f64>() / n as f64;
        let var = raw.iter().map(|f| (f[j] - mean[j]).powi(2)).sum::<f64>() / n as f64;
        scale[j] = if var > 1e-12 { var.sqrt() } else { 1.0 };
    }
    let rows: Vec<(SVector<f64, DIM>, f64)> = raw
        .iter()
        .zip(examples)
        .map(|(f, e)| {
            let x = SVector::<f64, DIM>::from_fn(|j, _| match j {
                0 => 1.0,
                _ => (f[j - 1] - mean[j - 1]) / scale[j - 1],
            });
            (x, f64::from(u8::from(e.right)))
        })
        .collect();
    let mut penalty = SMatrix::<f64, DIM, DIM>::identity() * (l2 * n as f64);
    penalty[(0, 0)] = 0.0;
    let mut beta = SVector::<f64, DIM>::zeros();
    for _ in 0..100 {
        let mut gradient = -(penalty * beta);
        let mut hessian = penalty;
        for (x, y) in &rows {
            let p = 1.0 / (1.0 + (-x.dot(&beta)).exp());
            gradient += x * (y - p);
            hessian += x * x.transpose() * (p * (1.0 - p)).max(1e-9);
        }
        let step = hessian
            .cholesky()
            .context("singular Hessian (too few or identical examples)")?
            .solve(&gradient);
        beta += step;
        if step.amax() < 1e-10 {
            break;
        }
    }
    let mut weights = [0.0; FEATURES];
    let mut bias = beta[0];
    for j in 0..FEATURES {
        weights[j] = beta[j + 1] / scale[j];
        bias -= weights[j] * mean[j];
    }
    Ok((bias, weights))
}

/// The lowest threshold at which at most `max_wrong` of the accepted examples are wrong
/// (1.0, accepting nothing below certainty, when no threshold achieves it).
pub fn threshold_for(rule: &AcceptanceRule, examples: &[Example], max_wrong: f64) -> f32 {
    let mut scored: Vec<(f32, bool)> = examples
        .iter()
        .map(|e| (rule.confidence(&e.evidence), e.right))
        .collect();
    scored.sort_by(|a, b| b.0.total_cmp(&a.0));
    let mut best = 1.0;
    let (mut accepted, mut wrong) = (0usize, 0usize);
    for (i, &(confidence, right)) in scored.iter().enumerate() {
        accepted += 1;
        wrong += usize::from(!right);
        let tied_with_next = scored.get(i + 1).is_some_and(|n| n.0 == confidence);
        if !tied_with_next && wrong as f64 <= max_wrong * accepted as f64 {
            best = confidence;
        }
    }
    best
}

/// The highest threshold that accepts at least `min_recall` of the right examples (0.0
/// when there are none).
pub fn threshold_keeping(rule: &AcceptanceRule, examples: &[Example], min_recall: f64) -> f32 {
    let mut right: Vec<f32> = examples
        .iter()
        .filter(|e| e.right)
        .map(|e| rule.confidence(&e.evidence))
        .collect();
    right.sort_by(|a, b| b.total_cmp(a));
    let kept = (min_recall.clamp(0.0, 1.0) * right.len() as f64).ceil() as usize;
    kept.checked_sub(1)
        .and_then(|i| right.get(i))
        .copied()
        .unwrap_or(0.0)
}

/// How the threshold of a fitted rule is chosen on the training examples.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Operating {
    /// [`threshold_for`]: at most this share of the accepted poses wrong.
    MaxWrong(f64),
    /// [`threshold_keeping`]: at least this share of the right poses accepted.
    MinRecall(f64),
}

impl Operating {
    /// The default: keep 97 % of the right poses.
    pub const DEFAULT: Self = Self::MinRecall(0.97);

    fn threshold(self, rule: &AcceptanceRule, examples: &[Example]) -> f32 {
        match self {
            Self::MaxWrong(share) => threshold_for(rule, examples, share),
            Self::MinRecall(share) => threshold_keeping(rule, examples, share),
        }
    }
}

/// Fits the rule on the examples: the logistic model on those past the chance gate
/// ([`gomatch::acceptance::Evidence::beyond_chance`]; the others have confidence 0), the
/// threshold on all.
pub fn fit(examples: &[Example], l2: f64, operating: Operating) -> anyhow::Result<AcceptanceRule> {
    let gated: Vec<Example> = examples
        .iter()
        .filter(|e| e.evidence.beyond_chance())
        .copied()
        .collect();
    let (bias, weights) = logistic_fit(&gated, l2)?;
    let mut rule = AcceptanceRule {
        bias: bias as f32,
        weights: weights.map(|w| w as f32),
        min_confidence: 0.0,
    };
    rule.min_confidence = operating.threshold(&rule, examples);
    Ok(rule)
}

/// The rule's thresholds at each share of [`OPERATING_SHARES`] of wrong training poses, and
/// the share of right training poses each keeps.
pub fn operating_points(rule: &AcceptanceRule, training: &[Example]) -> Vec<OperatingPoint> {
    OPERATING_SHARES
        .iter()
        .map(|&share| {
            let min_confidence = threshold_for(rule, training, f64::from(share));
            let at = AcceptanceRule {
                min_confidence,
                ..*rule
            };
            let scores = Scores::of(&at, training);
            let kept = scores.accepted - scores.accepted_wrong;
            OperatingPoint {
                max_wrong: share,
                min_confidence,
                recall: kept as f32 / scores.right.max(1) as f32,
            }
        })
        .collect()
}

/// The capacity all reports share: `expected` when given, else the first report's.
fn common_capacity(reports: &[Report], expected: Option<usize>) -> anyhow::Result<usize> {
    let capacity = expected
        .or_else(|| reports.first().map(|r| r.capacity))
        .context("no reports")?;
    if let Some(other) = reports.iter().find(|r| r.capacity != capacity) {
        anyhow::bail!(
            "{} was evaluated at capacity {}, not {capacity}",
            other.scene,
            other.capacity
        );
    }
    Ok(capacity)
}

/// Precision and recall of the rule at other thresholds, on the training and the checked
/// examples: the operating points a user can pick with `min_confidence`.
fn print_operating_points(rule: &AcceptanceRule, training: &[Example], check: &[Example]) {
    println!(
        "| min_confidence | training: accepted, wrong, recall | checked: accepted, wrong, recall |"
    );
    println!("|---|---|---|");
    for threshold in [0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.95] {
        let at = AcceptanceRule {
            min_confidence: threshold,
            ..*rule
        };
        let cell = |examples: &[Example]| Scores::of(&at, examples).brief();
        println!("| {threshold} | {} | {} |", cell(training), cell(check));
    }
}

/// Runs `gomatch-sim fit-acceptance`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let read_all = |paths: &[PathBuf]| {
        paths
            .iter()
            .map(|p| read_report(p))
            .collect::<anyhow::Result<Vec<_>>>()
    };
    let (reports, checks) = (read_all(&args.reports)?, read_all(&args.check)?);
    let capacity = common_capacity(&reports, args.capacity)?;
    common_capacity(&checks, Some(capacity))?;
    let mut training = Vec::new();
    for report in &reports {
        let examples = examples(report);
        println!("{}: {} examples", report.scene, examples.len());
        training.extend(examples);
    }
    let operating = match (args.max_wrong, args.min_recall) {
        (Some(share), _) => Operating::MaxWrong(share),
        (None, Some(share)) => Operating::MinRecall(share),
        (None, None) => Operating::DEFAULT,
    };
    let rule = fit(&training, args.l2, operating)?;
    let scores = Scores::of(&rule, &training);
    println!("capacity {capacity}");
    println!("training: {}", scores.describe());
    println!("rule: {rule:?}");
    let mut checked = Vec::new();
    for report in &checks {
        let examples = examples(report);
        println!(
            "check {}: {}",
            report.scene,
            Scores::of(&rule, &examples).describe()
        );
        checked.extend(examples);
    }
    let checked_scores = (!checked.is_empty()).then(|| Scores::of(&rule, &checked));
    if let Some(all) = &checked_scores {
        println!("check, all: {}", all.describe());
    }
    print_operating_points(&rule, &training, &checked);
    let operating_points = operating_points(&rule, &training);
    for p in &operating_points {
        println!(
            "operating point: at most {} % wrong on training: min_confidence {}, recall {:.1} %",
            p.max_wrong * 100.0,
            p.min_confidence,
            p.recall * 100.0
        );
    }
    let output = FitOutput {
        bias: rule.bias,
        weights: rule.weights,
        min_confidence: rule.min_confidence,
        capacity,
        training_scenes: reports.into_iter().map(|r| r.scene).collect(),
        training: scores,
        checked: checked_scores,
        operating_points,
    };
    std::fs::write(&args.out, serde_json::to_string_pretty(&output)? + "\n")
        .with_context(|| format!("writing {}", args.out.display()))?;
    println!("wrote {}", args.out.display());
    Ok(())
}
