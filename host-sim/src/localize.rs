//! `gomatch-sim localize`: localizes new photos against a map blob (paper sec. 4.1, the
//! device path: the core's [`Localizer::localize`]). A query is its keypoints (a text
//! file, a `.npy` array or COLMAP's `database.db`, [`crate::readers::keypoints`]), its camera (a
//! COLMAP camera line, a camera of the map, or the database's) and the database views to
//! match it against (names, an hloc pairs file, or a prior pose). Many queries come as an
//! hloc query list (`name MODEL WIDTH HEIGHT PARAMS...` per line).
//!
//! Output: per query a line on the terminal, hloc's results format
//! (`name qw qx qy qz tx ty tz`, world to camera, localized queries only) and a JSON report
//! with the pose, the inliers, the counts and timings, or why the query was not localized.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context};
use clap::{Args as ClapArgs, Parser};
use gomatch::acceptance::{AcceptanceRule, Evidence, OperatingPoint};
use gomatch::guided::GuidedCounts;
use gomatch::localizer::{Failure, MAX_VIEWS};
use gomatch::map::Map;
use gomatch::{Camera, Localizer, LocalizerConfig, Model, Pose, Query, ViewSelection};
use half::f16;
use nalgebra::UnitQuaternion;
use serde::{Deserialize, Serialize};

use crate::eval::{Counts, TimingsMs};
use crate::host::{HostClock, CAPACITY};
use crate::readers::colmap::parse_camera_line;
use crate::readers::keypoints::{read_keypoint_file, ColmapDatabase, KeypointFile};

/// Thread stack for the localizer (its workspace lives on it; see `eval`).
const WORKER_STACK: usize = 64 << 20;
/// Viewing-direction cone of `--prior` (views looking within it rank first).
const PRIOR_MAX_ANGLE_DEG: f64 = 45.0;

/// Localize photos against a map blob.
#[derive(Debug, Clone, Parser)]
pub struct Args {
    /// Map blob (`gomatch-sim map build`).
    #[arg(long)]
    pub map: PathBuf,
    /// Model blob (default: models/gomatch-int8.bin, searched from the current folder and
    /// the executable's).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// The map's view-features blob (`map features`, for this model): the views' encoder
    /// and first self-attention layer are read instead of computed, with the same results.
    #[arg(long)]
    pub view_features: Option<PathBuf>,
    /// The queries.
    #[command(flatten)]
    pub queries: QueryArgs,
    /// Where the keypoints come from.
    #[command(flatten)]
    pub keypoints: KeypointArgs,
    /// The query camera as a COLMAP line `MODEL WIDTH HEIGHT PARAMS...` (e.g.
    /// "SIMPLE_RADIAL 1600 1200 1400 800 600 0.01"); default: the query list's, else the
    /// database's.
    #[arg(long, conflicts_with = "camera_index")]
    pub camera: Option<String>,
    /// The query camera as a camera index of the map (`map list`).
    #[arg(long)]
    pub camera_index: Option<usize>,
    /// Which database views to match.
    #[command(flatten)]
    pub views: ViewArgs,
    /// Number of views nearest to `--prior`.
    #[arg(long, default_value_t = MAX_VIEWS)]
    pub k: usize,
    /// Accept a pose from this confidence on instead of the threshold of the capacity's
    /// acceptance rule: a stricter operating point (`docs/evaluation.md`), or 0 to report every
    /// pose RANSAC-PnP found, with its confidence (`docs/acceptance.md`).
    #[arg(long)]
    pub min_confidence: Option<f32>,
    /// Write hloc's results format: `name qw qx qy qz tx ty tz` per localized query.
    #[arg(long)]
    pub results: Option<PathBuf>,
    /// Write the JSON report (every query: pose or failure, inliers, counts, timings).
    #[arg(long)]
    pub json: Option<PathBuf>,
}

/// One query by name, or an hloc query list.
#[derive(Debug, Clone, ClapArgs)]
#[group(required = true, multiple = false)]
pub struct QueryArgs {
    /// Name of the one query image (as in the database, the pairs file and the results).
    #[arg(long)]
    pub query: Option<String>,
    /// hloc query list: `name MODEL WIDTH HEIGHT PARAMS...` per line.
    #[arg(long)]
    pub query_list: Option<PathBuf>,
}

/// Exactly one keypoint source.
#[derive(Debug, Clone, ClapArgs)]
#[group(required = true, multiple = false)]
pub struct KeypointArgs {
    /// Keypoints of the one query: text (`x y [score]` per line) or `.npy` (N x 2 or 3).
    #[arg(long, requires = "query")]
    pub keypoints: Option<PathBuf>,
    /// COLMAP `database.db`: the `keypoints` of each query by image name.
    #[arg(long)]
    pub database: Option<PathBuf>,
    /// Folder with a keypoint file per query: `NAME.txt` or `NAME.npy`.
    #[arg(long)]
    pub keypoint_dir: Option<PathBuf>,
}

/// Exactly one way to pick the database views.
#[derive(Debug, Clone, ClapArgs)]
#[group(required = true, multiple = false)]
pub struct ViewArgs {
    /// Names of the database images to match (at most 10), for every query.
    #[arg(long, num_args = 1..)]
    pub views: Vec<String>,
    /// hloc pairs file: `query_name database_name` per line; a query's first 10 are used.
    #[arg(long)]
    pub pairs: Option<PathBuf>,
    /// A coarse prior pose "qw qx qy qz tx ty tz" (world to camera): the `--k` views
    /// nearest to it, those looking within 45 degrees of it first.
    #[arg(long, allow_hyphen_values = true)]
    pub prior: Option<String>,
}

/// One query to localize.
#[derive(Debug, Clone, PartialEq)]
pub struct QuerySpec {
    /// Image name.
    pub name: String,
    /// Camera from the query list, if given there.
    pub camera: Option<Camera>,
}

/// A pose in COLMAP's convention (world to camera), quaternion with `qw >= 0`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ColmapPose {
    /// Rotation quaternion `qw qx qy qz`.
    pub qvec: [f64; 4],
    /// Translation `tx ty tz`.
    pub tvec: [f64; 3],
}

impl From<&Pose> for ColmapPose {
    fn from(pose: &Pose) -> Self {
        let q = UnitQuaternion::from_rotation_matrix(&pose.rotation);
        let sign = if q.w < 0.0 { -1.0 } else { 1.0 };
        let t = pose.translation;
        Self {
            qvec: [q.w, q.i, q.j, q.k].map(|v| sign * v),
            tvec: [t.x, t.y, t.z],
        }
    }
}

/// One inlier 2D-3D match of a localized query.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Inlier {
    /// Index of the keypoint in the query's keypoint file (or database row).
    pub keypoint: usize,
    /// Index of the 3D point in the map (`map build` stores points in model id order).
    pub point: u32,
    /// The point's world coordinates.
    pub xyz: [f32; 3],
    /// The classifier's probability of the match.
    pub probability: f32,
}

/// The outcome of one query: the JSON report's entry.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct QueryOutcome {
    /// Image name.
    pub name: String,
    /// Keypoints in its file.
    pub keypoints_total: usize,
    /// Keypoints given to the localizer (the best `CAPACITY`).
    pub keypoints_used: usize,
    /// Names of the views selected.
    pub views: Vec<String>,
    /// Views matched.
    pub views_used: usize,
    /// The pose, when localized.
    pub pose: Option<ColmapPose>,
    /// The acceptance rule's confidence in the best pose (`None` when RANSAC found none).
    pub confidence: Option<f32>,
    /// The strictest operating point of the capacity's rule that confidence passes
    /// ([`OperatingPoint::for_capacity`]: its share of wrong poses among the accepted
    /// training poses, its threshold and recall); `None` when it passes none.
    pub operating_point: Option<OperatingPoint>,
    /// The acceptance rule's inputs for the best pose ([`Evidence`]; `None` when RANSAC
    /// found none).
    pub evidence: Option<Evidence>,
    /// What guided re-matching did to the best pose: rounds kept, pairs and inliers of the
    /// last round, pairs by chance.
    pub guided: GuidedCounts,
    /// Whether the pose is the second attempt's, RANSAC-PnP on the matches a refused pose's
    /// inliers left out (`docs/evaluation.md`, "Second attempt"; a refusal is the first's).
    #[serde(default)]
    pub second_attempt: bool,
    /// Why not, when not localized.
    pub failure: Option<String>,
    /// The typed reason (the core's `Failure`).
    pub failure_detail: Option<Failure>,
    /// Match counts per stage.
    pub counts: Counts,
    /// The pose's inliers.
    pub inliers: Vec<Inlier>,
    /// RANSAC minimal samples drawn.
    pub ransac_iterations: u32,
    /// Stage timings.
    pub timings_ms: TimingsMs,
}

/// The JSON report of a run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LocalizeReport {
    /// The map blob.
    pub map: String,
    /// The model blob.
    pub model: String,
    /// Queries given.
    pub queries: usize,
    /// Queries localized.
    pub localized: usize,
    /// Every query, in input order.
    pub per_query: Vec<QueryOutcome>,
}

/// Parses an hloc query list: `name MODEL WIDTH HEIGHT PARAMS...` per line (blank lines
/// and `#` comments skipped).
pub fn parse_query_list(text: &str) -> anyhow::Result<Vec<QuerySpec>> {
    text.lines()
        .enumerate()
        .map(|(i, line)| (i + 1, line.trim()))
        .filter(|(_, line)| !line.is_empty() && !line.starts_with('#'))
        .map(|(number, line)| {
            let (name, camera) = line.split_once(char::is_whitespace).unwrap_or((line, ""));
            let camera = parse_camera_line(camera)
                .with_context(|| format!("query list line {number} ({name})"))?;
            Ok(QuerySpec {
                name: name.to_string(),
                camera: Some(camera),
            })
        })
        .collect()
}

/// Parses an hloc pairs file into each query's database names, in file order.
pub fn parse_pairs(text: &str) -> anyhow::Result<BTreeMap<String, Vec<String>>> {
    let mut pairs: BTreeMap<String, Vec<String>> = BTreeMap::new();
    for (number, line) in text.lines().enumerate().map(|(i, l)| (i + 1, l.trim())) {
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let fields: Vec<&str> = line.split_whitespace().collect();
        let [query, database] = fields[..] else {
            bail!("pairs line {number}: expected `query_name database_name`, found {line:?}");
        };
        pairs.entry(query.into()).or_default().push(database.into());
    }
    Ok(pairs)
}

/// Parses a pose `qw qx qy qz tx ty tz` (world to camera).
pub fn parse_pose(text: &str) -> anyhow::Result<Pose> {
    let values = text
        .split_whitespace()
        .map(str::parse::<f64>)
        .collect::<Result<Vec<f64>, _>>()
        .with_context(|| format!("--prior {text:?}: expected 7 numbers"))?;
    let [qw, qx, qy, qz, tx, ty, tz] = values[..] else {
        bail!("--prior {text:?}: expected 7 numbers qw qx qy qz tx ty tz");
    };
    Pose::from_colmap([qw, qx, qy, qz], [tx, ty, tz])
        .map_err(|e| anyhow::anyhow!("--prior {text:?}: {e}"))
}

/// Image ids of the map views named `names` (the first view of each name).
fn image_ids_by_name(map: &Map<'_>, names: &[String]) -> anyhow::Result<Vec<u32>> {
    let mut by_name = BTreeMap::new();
    for index in (0..map.view_count()).rev() {
        by_name.insert(map.view_name(index)?, map.view(index)?.image_id);
    }
    names
        .iter()
        .map(|name| {
            by_name.get(name.as_str()).copied().with_context(|| {
                format!("the map has no view named {name:?} (see `gomatch-sim map list`)")
            })
        })
        .collect()
}

/// Name of the map view with image id `image_id`.
fn view_name_of(map: &Map<'_>, image_id: u32) -> anyhow::Result<String> {
    for index in 0..map.view_count() {
        if map.view(index)?.image_id == image_id {
            return Ok(map.view_name(index)?.to_string());
        }
    }
    bail!("the map has no view of image {image_id}")
}

/// Where the keypoints and cameras of the queries come from.
enum KeypointSource {
    File(PathBuf),
    Database(ColmapDatabase),
    Folder(PathBuf),
}

impl KeypointSource {
    fn open(args: &KeypointArgs) -> anyhow::Result<Self> {
        match (&args.keypoints, &args.database, &args.keypoint_dir) {
            (Some(file), None, None) => Ok(Self::File(file.clone())),
            (None, Some(db), None) => Ok(Self::Database(ColmapDatabase::open(db)?)),
            (None, None, Some(dir)) => Ok(Self::Folder(dir.clone())),
            _ => bail!("give exactly one of --keypoints, --database, --keypoint-dir"),
        }
    }

    fn keypoints(&self, name: &str) -> anyhow::Result<KeypointFile> {
        match self {
            Self::File(path) => read_keypoint_file(path),
            Self::Database(db) => db.keypoints(name),
            Self::Folder(dir) => {
                let npy = dir.join(format!("{name}.npy"));
                let txt = dir.join(format!("{name}.txt"));
                let path = if npy.is_file() { npy } else { txt };
                read_keypoint_file(&path)
            }
        }
    }

    fn camera(&self, name: &str) -> Option<anyhow::Result<Camera>> {
        match self {
            Self::Database(db) => Some(db.camera(name)),
            _ => None,
        }
    }
}

/// Everything fixed across the queries of a run.
struct Session<'a> {
    model: Model<'a>,
    map: Map<'a>,
    keypoints: KeypointSource,
    camera: Option<Camera>,
    views: ViewChoice,
    config: LocalizerConfig,
}

/// The resolved view selection.
enum ViewChoice {
    Names(Vec<String>),
    Pairs(BTreeMap<String, Vec<String>>),
    Prior { prior: Pose, k: usize },
}

impl Session<'_> {
    fn camera_of(&self, query: &QuerySpec) -> anyhow::Result<Camera> {
        if let Some(camera) = self.camera.or(query.camera) {
            return Ok(camera);
        }
        self.keypoints.camera(&query.name).unwrap_or_else(|| {
            bail!(
                "no camera for {}: pass --camera \"MODEL WIDTH HEIGHT PARAMS...\", --camera-index, a query list or a database",
                query.name
            )
        })
    }

    /// Image ids of the views to match query `name` against, best first.
    fn view_ids(&self, name: &str) -> anyhow::Result<Vec<u32>> {
        let names = match &self.views {
            ViewChoice::Names(names) => names.as_slice(),
            ViewChoice::Pairs(pairs) => pairs.get(name).map_or(&[][..], |v| v.as_slice()),
            ViewChoice::Prior { prior, k } => {
                let near: heapless::Vec<u32, MAX_VIEWS> =
                    self.map.views_near(prior, PRIOR_MAX_ANGLE_DEG)?;
                return near
                    .iter()
                    .take(*k)
                    .map(|&v| Ok(self.map.view(v as usize)?.image_id))
                    .collect();
            }
        };
        image_ids_by_name(&self.map, &names[..names.len().min(MAX_VIEWS)])
    }

    fn localize(
        &self,
        localizer: &mut Localizer<CAPACITY, f16>,
        query: &QuerySpec,
    ) -> anyhow::Result<QueryOutcome> {
        let file = self.keypoints.keypoints(&query.name)?;
        let kept = file.keep_best(CAPACITY);
        let camera = self.camera_of(query)?;
        let ids = self.view_ids(&query.name)?;
        let clock = HostClock::default();
        let result = localizer
            .localize(
                &self.model,
                &self.map,
                &Query {
                    keypoints: &kept.pixels,
                    camera,
                },
                ViewSelection::ImageIds(&ids),
                &self.config,
                Some(&clock),
            )
            .with_context(|| format!("localizing {}", query.name))?;
        let inliers = localizer
            .inliers()
            .map(|c| {
                Ok(Inlier {
                    keypoint: kept.file_index[usize::from(c.keypoint)],
                    point: c.point,
                    xyz: self.map.point(c.point as usize)?,
                    probability: c.probability,
                })
            })
            .collect::<anyhow::Result<Vec<_>>>()?;
        Ok(QueryOutcome {
            name: query.name.clone(),
            keypoints_total: kept.total,
            keypoints_used: kept.pixels.len(),
            views: ids
                .iter()
                .map(|&id| view_name_of(&self.map, id))
                .collect::<anyhow::Result<_>>()?,
            views_used: result.views_used,
            pose: result.outcome.as_ref().ok().map(ColmapPose::from),
            confidence: result.confidence,
            operating_point: result.confidence.and_then(|c| {
                OperatingPoint::strictest_passed(OperatingPoint::for_capacity(CAPACITY), c)
            }),
            evidence: result.evidence,
            guided: result.guided,
            second_attempt: result.second_attempt,
            failure: result.outcome.err().map(|f| f.to_string()),
            failure_detail: result.outcome.err(),
            counts: result.counts.into(),
            inliers,
            ransac_iterations: result.ransac_iterations,
            timings_ms: result.timings.unwrap_or_default().into(),
        })
    }
}

/// hloc's results line of a localized query.
pub fn results_line(outcome: &QueryOutcome) -> Option<String> {
    let pose = outcome.pose?;
    let values: Vec<String> = pose
        .qvec
        .iter()
        .chain(&pose.tvec)
        .map(f64::to_string)
        .collect();
    Some(format!("{} {}", outcome.name, values.join(" ")))
}

fn print_outcome(outcome: &QueryOutcome) {
    let c = &outcome.counts;
    let summary = format!(
        "{} keypoints of {}, {} of {} views, matches {:.0} mutual / {:.0} classified / {:.0} merged, {:.0} inliers, {:.0} ms",
        outcome.keypoints_used,
        outcome.keypoints_total,
        outcome.views_used,
        outcome.views.len(),
        c.mutual,
        c.classified,
        c.merged,
        c.inliers,
        outcome.timings_ms.total
    );
    match &outcome.failure {
        None => println!(
            "{}: localized, confidence {:.3}{} ({summary})",
            outcome.name,
            outcome.confidence.unwrap_or(f32::NAN),
            outcome.operating_point.map_or(String::new(), |p| format!(
                " (passes the {} % operating point)",
                p.max_wrong * 100.0
            ))
        ),
        Some(reason) => println!("{}: NOT localized: {reason} ({summary})", outcome.name),
    }
}

/// The queries of a run: the query list's, or the one named.
fn queries(args: &QueryArgs) -> anyhow::Result<Vec<QuerySpec>> {
    match (&args.query, &args.query_list) {
        (Some(name), None) => Ok(vec![QuerySpec {
            name: name.clone(),
            camera: None,
        }]),
        (None, Some(path)) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?;
            parse_query_list(&text).with_context(|| format!("parsing {}", path.display()))
        }
        _ => bail!("give exactly one of --query, --query-list"),
    }
}

fn view_choice(args: &ViewArgs, k: usize) -> anyhow::Result<ViewChoice> {
    if let Some(path) = &args.pairs {
        let text =
            std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        return Ok(ViewChoice::Pairs(
            parse_pairs(&text).with_context(|| format!("parsing {}", path.display()))?,
        ));
    }
    if let Some(prior) = &args.prior {
        ensure!(
            (1..=MAX_VIEWS).contains(&k),
            "--k must be 1..={MAX_VIEWS} (got {k})"
        );
        return Ok(ViewChoice::Prior {
            prior: parse_pose(prior)?,
            k,
        });
    }
    ensure!(
        args.views.len() <= MAX_VIEWS,
        "--views takes at most {MAX_VIEWS} names (got {})",
        args.views.len()
    );
    Ok(ViewChoice::Names(args.views.clone()))
}

/// The localizer's settings: the defaults, with the capacity's acceptance rule at
/// `min_confidence` when given.
fn localizer_config(min_confidence: Option<f32>) -> anyhow::Result<LocalizerConfig> {
    let mut config = LocalizerConfig::new();
    if let Some(threshold) = min_confidence {
        ensure!(
            (0.0..=1.0).contains(&threshold),
            "--min-confidence must be in 0..=1 (got {threshold})"
        );
        config.acceptance = Some(AcceptanceRule {
            min_confidence: threshold,
            ..AcceptanceRule::for_capacity(CAPACITY)
        });
    }
    Ok(config)
}

/// Localizes every query; runs on a thread with room for the localizer's workspace (the
/// session moves there: a database connection is not shared between threads).
fn localize_all(session: Session<'_>, queries: &[QuerySpec]) -> anyhow::Result<Vec<QueryOutcome>> {
    std::thread::scope(|scope| {
        std::thread::Builder::new()
            .stack_size(WORKER_STACK)
            .spawn_scoped(scope, move || {
                let mut localizer = Localizer::<CAPACITY, f16>::new();
                queries
                    .iter()
                    .map(|query| {
                        let outcome = session.localize(&mut localizer, query)?;
                        print_outcome(&outcome);
                        Ok(outcome)
                    })
                    .collect::<anyhow::Result<Vec<_>>>()
            })
            .context("spawning the localizer thread")?
            .join()
            .map_err(|_| anyhow::anyhow!("the localizer thread panicked"))?
    })
}

/// Runs `gomatch-sim localize` and returns its report.
pub fn run(args: &Args) -> anyhow::Result<LocalizeReport> {
    let map_blob = gomatch_blobs::files::read_map_blob(&args.map)?;
    let features_blob = match &args.view_features {
        Some(path) => std::fs::read(path).with_context(|| format!("reading {}", path.display()))?,
        None => Vec::new(),
    };
    let mut map = Map::from_bytes(&map_blob)?;
    if args.view_features.is_some() {
        map = gomatch_blobs::view_features::attach(map, &features_blob)?;
    }
    let model_path = args
        .model
        .clone()
        .unwrap_or_else(gomatch_blobs::files::shipped_model_path);
    let model_blob = gomatch_blobs::files::read_model_blob(&model_path)?;
    let camera = match (&args.camera, args.camera_index) {
        (Some(line), _) => {
            Some(parse_camera_line(line).with_context(|| format!("--camera {line:?}"))?)
        }
        (None, Some(index)) => Some(map.camera(index).map_err(|e| {
            anyhow::anyhow!("--camera-index {index}: {e} (see `gomatch-sim map list`)")
        })?),
        (None, None) => None,
    };
    let session = Session {
        model: Model::from_bytes(&model_blob)?,
        map,
        keypoints: KeypointSource::open(&args.keypoints)?,
        camera,
        views: view_choice(&args.views, args.k)?,
        config: localizer_config(args.min_confidence)?,
    };
    let queries = queries(&args.queries)?;
    let per_query = localize_all(session, &queries)?;
    let report = LocalizeReport {
        map: args.map.display().to_string(),
        model: model_path.display().to_string(),
        queries: per_query.len(),
        localized: per_query.iter().filter(|q| q.pose.is_some()).count(),
        per_query,
    };
    println!(
        "{} of {} queries localized",
        report.localized, report.queries
    );
    write_outputs(args, &report)?;
    Ok(report)
}

fn write_outputs(args: &Args, report: &LocalizeReport) -> anyhow::Result<()> {
    if let Some(path) = &args.results {
        let lines: String = report
            .per_query
            .iter()
            .filter_map(results_line)
            .map(|line| line + "\n")
            .collect();
        write(path, &lines)?;
    }
    if let Some(path) = &args.json {
        write(path, &serde_json::to_string_pretty(report)?)?;
    }
    Ok(())
}

fn write(path: &Path, content: &str) -> anyhow::Result<()> {
    std::fs::write(path, content).with_context(|| format!("writing {}", path.display()))?;
    println!("wrote {}", path.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};

    #[test]
    fn query_lists_pairs_and_poses_parse() {
        let list = parse_query_list("# name camera\nq1.jpg SIMPLE_RADIAL 640 480 500 320 240 0.01\n\nq2.jpg PINHOLE 10 20 5 6 5 10\n").unwrap();
        assert_eq!(list.len(), 2);
        assert_eq!(list[0].name, "q1.jpg");
        let camera = list[1].camera.unwrap();
        assert_eq!(
            (camera.width, camera.focal, camera.principal),
            (10, [5.0, 6.0], [5.0, 10.0])
        );
        assert!(parse_query_list("q.jpg PINHOLE 10 20 5\n").is_err());
        assert!(parse_query_list("q.jpg FISHEYE 10 20 5 5 5\n").is_err());

        let pairs = parse_pairs("q1.jpg a.jpg\nq1.jpg b.jpg\nq2.jpg a.jpg\n").unwrap();
        assert_eq!(pairs["q1.jpg"], ["a.jpg", "b.jpg"]);
        assert_eq!(pairs["q2.jpg"], ["a.jpg"]);
        assert!(parse_pairs("q1.jpg\n").is_err());

        let pose = parse_pose("1 0 0 0 1 2 3").unwrap();
        assert_eq!(pose.translation, Vector3::new(1.0, 2.0, 3.0));
        assert!(parse_pose("1 0 0 0 1 2").is_err());
        assert!(parse_pose("0 0 0 0 1 2 3").is_err());
    }

    #[test]
    fn min_confidence_sets_the_threshold_of_the_capacity_rule() {
        assert_eq!(localizer_config(None).unwrap().acceptance, None);
        let rule = localizer_config(Some(0.9)).unwrap().acceptance.unwrap();
        let fitted = AcceptanceRule::for_capacity(CAPACITY);
        assert_eq!((rule.bias, rule.weights), (fitted.bias, fitted.weights));
        assert_eq!(rule.min_confidence, 0.9);
        for bad in [-0.1, 1.5, f32::NAN] {
            assert!(localizer_config(Some(bad)).is_err(), "{bad}");
        }
    }

    #[test]
    fn results_lines_are_hloc_poses_with_a_non_negative_qw() {
        let pose = Pose::new(
            Rotation3::from_euler_angles(0.1, -0.2, 3.0),
            Vector3::new(1.0, -2.0, 0.5),
        );
        let colmap = ColmapPose::from(&pose);
        assert!(colmap.qvec[0] >= 0.0);
        let back = Pose::from_colmap(colmap.qvec, colmap.tvec).unwrap();
        assert!(back.rotation_error_deg(&pose) < 1e-9);
        let outcome = QueryOutcome {
            name: "q.jpg".into(),
            keypoints_total: 0,
            keypoints_used: 0,
            views: Vec::new(),
            views_used: 0,
            pose: Some(colmap),
            confidence: Some(0.99),
            operating_point: None,
            evidence: None,
            guided: GuidedCounts::default(),
            second_attempt: false,
            failure: None,
            failure_detail: None,
            counts: Counts::default(),
            inliers: Vec::new(),
            ransac_iterations: 0,
            timings_ms: TimingsMs::default(),
        };
        let line = results_line(&outcome).unwrap();
        let fields: Vec<&str> = line.split(' ').collect();
        assert_eq!(fields.len(), 8);
        assert_eq!(fields[0], "q.jpg");
        assert_eq!(fields[5..], ["1", "-2", "0.5"]);
        let refused = QueryOutcome {
            pose: None,
            failure: Some("too few inliers".into()),
            ..outcome
        };
        assert_eq!(results_line(&refused), None);
    }
}
