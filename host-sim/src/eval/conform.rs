//! `gomatch-sim conform`: runs the matcher on a reference fixture and compares every stage
//! with the reference's tensors (`shared/reference/fixtures/<input>/`).
//!
//! The weights are converted from the fixture's `weights.safetensors` by the same code as
//! `gomatch-tools convert`. Per stage the report gives the largest absolute difference
//! from the reference. Matches are compared as sets of `(i3d, i2d)` pairs `A` (ours) and
//! `R` (the reference's mutual assignment): `match_agreement = |A ∩ R| / |A ∪ R|`, so it
//! is 1 only for identical sets and both a missed and an extra match lower it;
//! `match_recall = |A ∩ R| / |R|` is reported beside it.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use anyhow::{bail, ensure, Context, Result};
use gomatch::nn::LayerTap;
use gomatch::sinkhorn::{PlanScalar, Transport};
use gomatch::{Matcher, Model, Observer, Precision, Stage};
use gomatch_blobs::convert::PrecisionArg;
use half::f16;
use serde::Serialize;

/// Capacity of the conformance workspaces (the fixtures hold at most 500 points).
pub const CAPACITY: usize = 1024;

static MATCHER_F32: Mutex<Matcher<CAPACITY, f32>> = Mutex::new(Matcher::new());
static MATCHER_F16: Mutex<Matcher<CAPACITY, f16>> = Mutex::new(Matcher::new());

/// Command-line arguments of `conform`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Fixture folder (holds index.json and the .npy stages).
    #[arg(long)]
    pub fixture: PathBuf,
    /// Weight precision to convert the checkpoint to.
    #[arg(long, value_enum, default_value = "f32")]
    pub precision: PrecisionArg,
    /// Storage of the Sinkhorn cost matrix.
    #[arg(long, value_enum, default_value = "f32")]
    pub plan: PlanArg,
    /// Checkpoint (default: weights.safetensors beside the fixture folder).
    #[arg(long)]
    pub weights: Option<PathBuf>,
    /// A model blob (`gomatch-tools convert`) to run instead of converting the
    /// checkpoint; `--precision` and `--weights` are then ignored.
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Where to write the JSON report (printed to stdout as well).
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// Storage type of the Sinkhorn cost matrix.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum PlanArg {
    /// 32-bit float.
    F32,
    /// 16-bit float.
    F16,
}

/// The comparison of one run with the reference.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// Fixture folder name.
    pub fixture: String,
    /// Weight precision.
    pub precision: String,
    /// Cost matrix storage.
    pub plan: PlanArg,
    /// Stage name -> largest absolute difference from the reference.
    pub stages: BTreeMap<String, f64>,
    /// Stage name -> largest absolute value of the reference (the scale of the stage).
    pub reference_max: BTreeMap<String, f64>,
    /// Sinkhorn iterations we ran.
    pub sinkhorn_iterations: usize,
    /// Sinkhorn iterations the reference ran (index.json).
    pub reference_iterations: usize,
    /// `|A ∩ R| / |A ∪ R|` of the match sets.
    pub match_agreement: f64,
    /// `|A ∩ R| / |R|`.
    pub match_recall: f64,
    /// Our matches.
    pub matches: usize,
    /// The reference's matches.
    pub reference_matches: usize,
    /// Our matches `(i3d, i2d)` that the reference does not have.
    pub extra_matches: Vec<(i64, i64)>,
    /// Reference matches `(i3d, i2d)` we do not have.
    pub missing_matches: Vec<(i64, i64)>,
}

/// Runs the command.
pub fn run(args: &Args) -> Result<()> {
    let report = match &args.model {
        Some(path) => {
            let blob =
                std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
            conform_blob(&args.fixture, &blob, args.plan)?
        }
        None => conform(
            &args.fixture,
            args.weights.as_deref(),
            args.precision.into(),
            args.plan,
        )?,
    };
    let json = serde_json::to_string_pretty(&report)?;
    println!("{json}");
    if let Some(path) = &args.json {
        std::fs::write(path, &json).with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

/// Converts the checkpoint, runs the matcher on the fixture and compares every stage.
pub fn conform(
    fixture: &Path,
    weights: Option<&Path>,
    precision: Precision,
    plan: PlanArg,
) -> Result<Report> {
    let weights = match weights {
        Some(w) => w.to_path_buf(),
        None => fixture
            .parent()
            .context("fixture folder has no parent")?
            .join("weights.safetensors"),
    };
    let checkpoint =
        std::fs::read(&weights).with_context(|| format!("reading {}", weights.display()))?;
    let (blob, _) = gomatch_blobs::convert::convert(&checkpoint, precision)?;
    conform_blob(fixture, &blob, plan)
}

/// Runs the matcher with the model blob `blob` on the fixture and compares every stage.
pub fn conform_blob(fixture: &Path, blob: &[u8], plan: PlanArg) -> Result<Report> {
    let model = Model::from_bytes(blob).map_err(|e| anyhow::anyhow!("loading blob: {e}"))?;
    let precision = model.precision();
    let pts2d = points(&fixture.join("pts2d.npy"))?;
    let pts3d = points(&fixture.join("pts3d_bvs.npy"))?;
    let mut observer = Comparison {
        fixture: fixture.to_path_buf(),
        stages: BTreeMap::new(),
        reference_max: BTreeMap::new(),
        error: None,
    };
    let ours: Vec<(u16, u16, f32)> = match plan {
        PlanArg::F32 => run_matcher(&MATCHER_F32, &model, &pts2d, &pts3d, &mut observer)?,
        PlanArg::F16 => run_matcher(&MATCHER_F16, &model, &pts2d, &pts3d, &mut observer)?,
    };
    if let Some(e) = observer.error.take() {
        return Err(e);
    }
    let iterations = observer.stages.remove("sinkhorn_iterations").unwrap_or(0.0) as usize;

    let index: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(fixture.join("index.json")).context("reading index.json")?,
    )?;
    let reference_iterations = index["sinkhorn"]["iterations_run"]
        .as_u64()
        .context("index.json: sinkhorn.iterations_run")? as usize;
    let ref_i3d = read_npy::<i64>(&fixture.join("match_i3d.npy"))?.1;
    let ref_i2d = read_npy::<i64>(&fixture.join("match_i2d.npy"))?.1;
    let ref_probs = read_npy::<f32>(&fixture.join("match_probs.npy"))?.1;
    let reference: BTreeMap<(i64, i64), f32> = ref_i3d
        .iter()
        .zip(&ref_i2d)
        .zip(&ref_probs)
        .map(|((&a, &b), &p)| ((a, b), p))
        .collect();
    let ours_set: BTreeSet<(i64, i64)> = ours
        .iter()
        .map(|&(i3, i2, _)| (i64::from(i3), i64::from(i2)))
        .collect();
    let common = ours_set
        .iter()
        .filter(|k| reference.contains_key(k))
        .count();
    let union = ours_set.len() + reference.len() - common;
    let mut prob_diff = 0.0f64;
    for &(i3, i2, p) in &ours {
        if let Some(&r) = reference.get(&(i64::from(i3), i64::from(i2))) {
            prob_diff = prob_diff.max(f64::from((p - r).abs()));
        }
    }
    let extra: Vec<(i64, i64)> = ours_set
        .iter()
        .filter(|k| !reference.contains_key(k))
        .copied()
        .collect();
    let missing: Vec<(i64, i64)> = reference
        .keys()
        .filter(|k| !ours_set.contains(k))
        .copied()
        .collect();
    let mut stages = std::mem::take(&mut observer.stages);
    stages.insert("match_probs".into(), prob_diff);
    Ok(Report {
        fixture: fixture
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
        precision: format!("{precision:?}").to_lowercase(),
        plan,
        stages,
        reference_max: observer.reference_max,
        sinkhorn_iterations: iterations,
        reference_iterations,
        match_agreement: if union == 0 {
            1.0
        } else {
            common as f64 / union as f64
        },
        match_recall: if reference.is_empty() {
            1.0
        } else {
            common as f64 / reference.len() as f64
        },
        matches: ours_set.len(),
        reference_matches: reference.len(),
        extra_matches: extra,
        missing_matches: missing,
    })
}

/// Runs one pair on a shared workspace, the minimum point count lowered to what the
/// network needs so the small fixtures run.
fn run_matcher<S: PlanScalar>(
    matcher: &Mutex<Matcher<CAPACITY, S>>,
    model: &Model<'_>,
    pts2d: &[[f32; 2]],
    pts3d: &[[f32; 2]],
    observer: &mut Comparison,
) -> Result<Vec<(u16, u16, f32)>> {
    let mut matcher = matcher
        .lock()
        .map_err(|_| anyhow::anyhow!("workspace lock poisoned"))?;
    matcher.set_min_points(gomatch::matcher::MIN_POINTS_NETWORK);
    matcher
        .encode_query_observed(model, pts2d, observer)
        .map_err(|e| anyhow::anyhow!("encoding the query: {e}"))?;
    let set = matcher
        .match_view_observed(model, pts3d, observer)
        .map_err(|e| anyhow::anyhow!("matching: {e}"))?;
    Ok(set
        .as_slice()
        .iter()
        .map(|m| (m.i3d, m.i2d, m.probability))
        .collect())
}

/// Observer comparing each stage with the fixture as it is produced.
struct Comparison {
    fixture: PathBuf,
    stages: BTreeMap<String, f64>,
    reference_max: BTreeMap<String, f64>,
    error: Option<anyhow::Error>,
}

impl Comparison {
    fn record(&mut self, name: &str, result: Result<(f64, f64)>) {
        match result {
            Ok((diff, scale)) => {
                self.stages.insert(name.to_string(), diff);
                self.reference_max.insert(name.to_string(), scale);
            }
            Err(e) => {
                if self.error.is_none() {
                    self.error = Some(e.context(format!("stage {name}")));
                }
            }
        }
    }
}

fn stage_name(stage: Stage) -> &'static str {
    match stage {
        Stage::Enc2d => "enc2d",
        Stage::Enc3d => "enc3d",
        Stage::Att0Self2d => "att0_self_2d",
        Stage::Att0Self3d => "att0_self_3d",
        Stage::Att1Cross2d => "att1_cross_2d",
        Stage::Att1Cross3d => "att1_cross_3d",
        Stage::Att2Self2d => "att2_self_2d",
        Stage::Att2Self3d => "att2_self_3d",
        Stage::Desc2dL2 => "desc2d_l2",
        Stage::Desc3dL2 => "desc3d_l2",
    }
}

/// Layer inputs are not compared (the fixtures hold the stages' outputs).
impl LayerTap for Comparison {}

impl<S: PlanScalar> Observer<S> for Comparison {
    fn features(&mut self, stage: Stage, x: &[f32], channels: usize, n: usize) {
        let name = stage_name(stage);
        let result = read_npy::<f32>(&self.fixture.join(format!("{name}.npy"))).and_then(
            |(shape, reference)| {
                ensure!(
                    shape == [n as u64, channels as u64],
                    "reference shape {shape:?}, ours [{n}, {channels}]"
                );
                let mut worst = 0.0f64;
                for i in 0..n {
                    for c in 0..channels {
                        let d = (x[c * n + i] - reference[i * channels + c]).abs();
                        worst = worst.max(f64::from(d));
                    }
                }
                Ok((worst, max_abs(&reference)))
            },
        );
        self.record(name, result);
    }

    fn transport(&mut self, t: &Transport<'_, S>) {
        for (name, value) in [
            (
                "ot_cost",
                &(|i, j| t.cost(i, j)) as &dyn Fn(usize, usize) -> f32,
            ),
            ("scores", &|i, j| t.plan(i, j)),
        ] {
            let result = read_npy::<f32>(&self.fixture.join(format!("{name}.npy"))).and_then(
                |(shape, reference)| {
                    let (rows, cols) = (t.n3 + 1, t.n2 + 1);
                    ensure!(
                        shape == [rows as u64, cols as u64],
                        "reference shape {shape:?}, ours [{rows}, {cols}]"
                    );
                    let mut worst = 0.0f64;
                    for i in 0..rows {
                        for j in 0..cols {
                            let d = (value(i, j) - reference[i * cols + j]).abs();
                            worst = worst.max(f64::from(d));
                        }
                    }
                    Ok((worst, max_abs(&reference)))
                },
            );
            self.record(name, result);
        }
        self.stages
            .insert("sinkhorn_iterations".into(), t.iterations as f64);
    }
}

fn max_abs(values: &[f32]) -> f64 {
    values
        .iter()
        .fold(0.0f64, |m, &v| m.max(f64::from(v.abs())))
}

/// A `.npy` array: shape and values in C order.
fn read_npy<T: npyz::Deserialize>(path: &Path) -> Result<(Vec<u64>, Vec<T>)> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    let npy =
        npyz::NpyFile::new(&bytes[..]).with_context(|| format!("parsing {}", path.display()))?;
    if npy.order() != npyz::Order::C {
        bail!("{}: Fortran order not supported", path.display());
    }
    let shape = npy.shape().to_vec();
    let values = npy
        .into_vec::<T>()
        .with_context(|| format!("reading values of {}", path.display()))?;
    Ok((shape, values))
}

/// An `(N, 2)` float32 array of bearing coordinates.
fn points(path: &Path) -> Result<Vec<[f32; 2]>> {
    let (shape, values) = read_npy::<f32>(path)?;
    ensure!(
        shape.len() == 2 && shape[1] == 2,
        "{}: shape {shape:?}, expected (N, 2)",
        path.display()
    );
    Ok(values.chunks_exact(2).map(|p| [p[0], p[1]]).collect())
}
