//! `gomatch-sim dataset`: writes training/validation samples (one per query and co-visible
//! view, format in `tools/train/README.md`, "Dataset file format") from real and synthetic scenes through the
//! localization [`protocol`](crate::protocol), as one safetensors file.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use clap::Parser;
use indicatif::{ProgressBar, ProgressStyle};
use safetensors::tensor::TensorView;
use safetensors::Dtype;

use crate::eval::parse_capacity;
use crate::host::{ScenesArgs, CAPACITY};
use crate::protocol::synthetic::{collection_scene, synthetic_scene};
use crate::protocol::{scene_samples, ProtocolParams, QuerySample};
use crate::readers::SceneSource;
use crate::scene::Scene;

/// Value of the `format` metadata entry.
pub const FORMAT: &str = "gomatch-dataset";
/// Value of the `version` metadata entry.
pub const VERSION: &str = "1";

/// Write localization training samples (query keypoints, co-visible view points, ground
/// truth matches) to a safetensors file.
#[derive(Debug, Clone, Parser)]
pub struct Args {
    /// Output safetensors file.
    #[arg(long)]
    pub output: PathBuf,
    /// The scenes.
    #[command(flatten)]
    pub scenes: ScenesArgs,
    /// Co-visible views per query.
    #[arg(long, default_value_t = 10)]
    pub k: usize,
    /// Queries sampled per scene.
    #[arg(long, default_value_t = 500)]
    pub queries_per_scene: usize,
    /// Seed of the protocol's random choices.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Localizer capacity `N` whose caps the samples get: a query's keypoints and a view's
    /// points as `eval --capacity N` (and the device) see them.
    #[arg(long, default_value_t = CAPACITY, value_parser = parse_capacity)]
    pub capacity: usize,
}

impl Args {
    /// The protocol parameters these arguments select (paper defaults otherwise).
    pub fn protocol(&self) -> ProtocolParams {
        ProtocolParams::for_localizer(self.k, self.queries_per_scene, self.seed, self.capacity)
    }
}

/// A scene to load or generate.
enum Source {
    File(SceneSource),
    Synthetic { seed: u64, index: u64 },
    Collection { seed: u64, index: u64 },
}

impl Source {
    fn load(&self) -> anyhow::Result<Scene> {
        match self {
            Source::File(source) => source.load(),
            Source::Synthetic { seed, index } => Ok(synthetic_scene(*seed, *index)),
            Source::Collection { seed, index } => Ok(collection_scene(*seed, *index)),
        }
    }
}

/// Totals of one source kind (`colmap`, `bal`, `bundler`, `opensfm`, `synthetic`).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SourceSummary {
    /// Scenes read or generated.
    pub scenes: usize,
    /// Queries that have co-visible views.
    pub queries: usize,
    /// Samples (query-view pairs).
    pub samples: usize,
    /// Sum of query keypoints over samples.
    pub keypoints: usize,
    /// Sum of view points over samples.
    pub points: usize,
    /// Sum of ground-truth matches over samples.
    pub matches: usize,
    /// Sum over samples of the share of keypoints without a match.
    pub outlier_rate_sum: f64,
}

impl SourceSummary {
    fn mean(&self, total: f64) -> f64 {
        total / self.samples.max(1) as f64
    }
}

/// Samples accumulated in the layout of the dataset format (little-endian bytes).
#[derive(Default)]
pub struct DatasetWriter {
    pts2d: Vec<u8>,
    pts3d: Vec<u8>,
    matches: Vec<u8>,
    offsets2d: Vec<i64>,
    offsets3d: Vec<i64>,
    scene: Vec<i64>,
    query: Vec<i64>,
    view: Vec<i64>,
    scenes: Vec<String>,
    summaries: BTreeMap<String, SourceSummary>,
}

fn push_f32(bytes: &mut Vec<u8>, values: &[[f64; 2]]) {
    for v in values {
        bytes.extend_from_slice(&(v[0] as f32).to_le_bytes());
        bytes.extend_from_slice(&(v[1] as f32).to_le_bytes());
    }
}

fn le_bytes(values: &[i64]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// The kind of a scene name `<kind>/<stem>`.
fn source_kind(scene_name: &str) -> &str {
    scene_name.split('/').next().unwrap_or(scene_name)
}

impl DatasetWriter {
    /// Empty dataset.
    pub fn new() -> Self {
        Self {
            offsets2d: vec![0],
            offsets3d: vec![0],
            ..Self::default()
        }
    }

    /// Registers a scene; its samples are added with [`Self::add_query`].
    pub fn add_scene(&mut self, name: &str) -> usize {
        self.scenes.push(name.to_string());
        self.summaries
            .entry(source_kind(name).to_string())
            .or_default()
            .scenes += 1;
        self.scenes.len() - 1
    }

    /// Appends one sample per co-visible view of the query.
    pub fn add_query(&mut self, scene_index: usize, sample: &QuerySample) {
        let kind = source_kind(&self.scenes[scene_index]).to_string();
        let summary = self.summaries.entry(kind).or_default();
        summary.queries += 1;
        let keypoint_count = sample.keypoints.len();
        for view in &sample.views {
            push_f32(&mut self.pts2d, &sample.keypoints.bearings);
            push_f32(&mut self.pts3d, &view.bearings);
            let matches = view.match_vector(keypoint_count);
            self.matches.extend(le_bytes(&matches));
            let last2d = self.offsets2d.last().copied().unwrap_or(0);
            let last3d = self.offsets3d.last().copied().unwrap_or(0);
            self.offsets2d.push(last2d + keypoint_count as i64);
            self.offsets3d.push(last3d + view.bearings.len() as i64);
            self.scene.push(scene_index as i64);
            self.query.push(i64::from(sample.image_id));
            self.view.push(i64::from(view.image_id));
            summary.samples += 1;
            summary.keypoints += keypoint_count;
            summary.points += view.bearings.len();
            summary.matches += view.gt_pairs.len();
            summary.outlier_rate_sum +=
                1.0 - view.gt_pairs.len() as f64 / keypoint_count.max(1) as f64;
        }
    }

    /// Samples written so far.
    pub fn sample_count(&self) -> usize {
        self.scene.len()
    }

    /// Totals per source kind.
    pub fn summaries(&self) -> &BTreeMap<String, SourceSummary> {
        &self.summaries
    }

    /// Writes the safetensors file with its metadata (`format`, `version`, `scenes`,
    /// `protocol`, and any `extra` entries).
    pub fn write(
        &self,
        path: &Path,
        params: &ProtocolParams,
        extra: &[(&str, String)],
    ) -> anyhow::Result<()> {
        let samples = self.sample_count();
        let keypoints = self.offsets2d.last().copied().unwrap_or(0) as usize;
        let points = self.offsets3d.last().copied().unwrap_or(0) as usize;
        let offsets2d = le_bytes(&self.offsets2d);
        let offsets3d = le_bytes(&self.offsets3d);
        let (scene, query, view) = (
            le_bytes(&self.scene),
            le_bytes(&self.query),
            le_bytes(&self.view),
        );
        let tensors = [
            ("pts2d", Dtype::F32, vec![keypoints, 2], &self.pts2d),
            ("pts3d", Dtype::F32, vec![points, 2], &self.pts3d),
            ("match", Dtype::I64, vec![keypoints], &self.matches),
            ("offsets2d", Dtype::I64, vec![samples + 1], &offsets2d),
            ("offsets3d", Dtype::I64, vec![samples + 1], &offsets3d),
            ("scene", Dtype::I64, vec![samples], &scene),
            ("query", Dtype::I64, vec![samples], &query),
            ("view", Dtype::I64, vec![samples], &view),
        ]
        .into_iter()
        .map(|(name, dtype, shape, data)| {
            TensorView::new(dtype, shape, data)
                .map(|t| (name, t))
                .with_context(|| format!("tensor {name}"))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
        let mut metadata = HashMap::from([
            ("format".to_string(), FORMAT.to_string()),
            ("version".to_string(), VERSION.to_string()),
            ("scenes".to_string(), serde_json::to_string(&self.scenes)?),
            ("protocol".to_string(), serde_json::to_string(params)?),
        ]);
        for (key, value) in extra {
            metadata.insert((*key).to_string(), value.clone());
        }
        let bytes = safetensors::serialize(tensors, Some(metadata))?;
        std::fs::write(path, sorted_header(bytes)?)
            .with_context(|| format!("writing {}", path.display()))
    }
}

/// The same safetensors file with its JSON header's keys sorted: `safetensors` writes the
/// metadata from a `HashMap`, whose order changes from run to run, and the dataset must be
/// bit-identical for the same inputs. The tensors' byte offsets are relative to the data
/// after the header, so only the header (padded with spaces to 8 bytes) is rewritten.
fn sorted_header(bytes: Vec<u8>) -> anyhow::Result<Vec<u8>> {
    let (length, rest) = bytes
        .split_first_chunk::<8>()
        .context("safetensors output without a header length")?;
    let length = usize::try_from(u64::from_le_bytes(*length))?;
    let (header, data) = rest
        .split_at_checked(length)
        .context("safetensors header longer than the output")?;
    let header: BTreeMap<String, serde_json::Value> = serde_json::from_slice(header)?;
    let mut json = serde_json::to_vec(&header)?;
    json.resize(json.len().next_multiple_of(8), b' ');
    let mut out = Vec::with_capacity(8 + json.len() + data.len());
    out.extend_from_slice(&(json.len() as u64).to_le_bytes());
    out.extend_from_slice(&json);
    out.extend_from_slice(data);
    Ok(out)
}

fn sources(args: &ScenesArgs) -> Vec<Source> {
    let files = args.files().into_iter().map(Source::File);
    let synthetic = (0..args.synthetic).map(|index| Source::Synthetic {
        seed: args.synthetic_seed,
        index,
    });
    let collections = (0..args.synthetic_collection).map(|index| Source::Collection {
        seed: args.synthetic_seed,
        index,
    });
    files.chain(synthetic).chain(collections).collect()
}

/// Runs the command: builds every scene's samples, writes the file, prints a summary.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let params = args.protocol();
    let sources = sources(&args.scenes);
    anyhow::ensure!(
        !sources.is_empty(),
        "no scene: give --colmap, --bal, --bundler, --opensfm, --synthetic or --synthetic-collection"
    );
    let started = Instant::now();
    let progress = ProgressBar::new(sources.len() as u64).with_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} scenes {elapsed} {msg}")
            .context("progress bar template")?,
    );
    let mut writer = DatasetWriter::new();
    for source in &sources {
        let scene = source.load()?;
        progress.set_message(format!(
            "{} ({} samples so far)",
            scene.name,
            writer.sample_count()
        ));
        let scene_index = writer.add_scene(&scene.name);
        for sample in scene_samples(&scene, &params) {
            writer.add_query(scene_index, &sample);
        }
        progress.inc(1);
    }
    progress.finish_and_clear();
    let extra = [("synthetic_seed", args.scenes.synthetic_seed.to_string())];
    writer.write(&args.output, &params, &extra)?;
    let seconds = started.elapsed().as_secs_f64();
    let size = std::fs::metadata(&args.output)?.len();
    println!(
        "wrote {} samples from {} scenes to {} ({:.1} MiB) in {seconds:.1} s ({:.0} samples/s)",
        writer.sample_count(),
        sources.len(),
        args.output.display(),
        size as f64 / (1024.0 * 1024.0),
        writer.sample_count() as f64 / seconds.max(1e-9)
    );
    print_summary(writer.summaries());
    Ok(())
}

fn print_summary(summaries: &BTreeMap<String, SourceSummary>) {
    println!(
        "{:<10} {:>6} {:>8} {:>8} {:>14} {:>14} {:>12} {:>12}",
        "source",
        "scenes",
        "queries",
        "samples",
        "keypoints/smp",
        "3D points/smp",
        "GT/sample",
        "outlier rate"
    );
    for (kind, s) in summaries {
        println!(
            "{kind:<10} {:>6} {:>8} {:>8} {:>14.1} {:>14.1} {:>12.1} {:>12.3}",
            s.scenes,
            s.queries,
            s.samples,
            s.mean(s.keypoints as f64),
            s.mean(s.points as f64),
            s.mean(s.matches as f64),
            s.mean(s.outlier_rate_sum)
        );
    }
}
