//! `gomatch-sim scenes stats`: the distributions that decide whether a matcher trained on
//! one kind of scene transfers to another, per real scene and for the synthetic generator,
//! side by side (quartile tables, JSON, a box plot). The simulator's ranges are tuned on
//! these figures for the training scenes only.
//!
//! Per image: horizontal field of view, radial distortion at the image's side edge,
//! keypoints and their triangulated share. Per protocol view (the samples `dataset` and
//! `eval` use): the points it keeps after the cap and, for the query-view pair, the rotation
//! angle, the baseline relative to the query's median depth, the overlap, the depth (scale)
//! ratio and the ground-truth match count. Per scene: 3D points closer to a registered
//! camera than a negligible depth (issue 24).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::{Args as ClapArgs, Parser, Subcommand};
use gomatch::Camera;
use nalgebra::Vector3;
use serde::Serialize;

use crate::host::ScenesArgs;
use crate::protocol::synthetic::{collection_scene, synthetic_layout, synthetic_scene, Layout};
use crate::protocol::{quantiles, scene_samples, ProtocolParams, QuerySample};
use crate::readers::SceneSource;
use crate::scene::{median, Image, Scene};

/// The validation scenes of `shared/data/README.md`: listed per scene, never pooled into
/// the training column the simulator is tuned on.
pub const VALIDATION_SCENES: [&str; 5] = [
    "colmap/mouse",
    "colmap/sceaux",
    "colmap/mamechun",
    "colmap/softmurata",
    "opensfm/projcv_cc9d27",
];

/// Depth, relative to the scene's median observation depth, under which a 3D point counts
/// as at a camera's centre (issue 24; the protocol's own rule is defined there).
pub const NEAR_CAMERA_RELATIVE_DEPTH: f64 = 1e-6;

/// Commands about scenes.
#[derive(Debug, Clone, Parser)]
pub struct Args {
    /// What to do.
    #[command(subcommand)]
    pub command: ScenesCommand,
}

/// `scenes` subcommands.
#[derive(Debug, Clone, Subcommand)]
pub enum ScenesCommand {
    /// Distributions that decide transfer, real scenes against the synthetic generator.
    Stats(StatsArgs),
}

/// Arguments of `scenes stats`.
#[derive(Debug, Clone, ClapArgs)]
pub struct StatsArgs {
    /// The scenes.
    #[command(flatten)]
    pub scenes: ScenesArgs,
    /// Every scene of a data folder laid out as `shared/data` (colmap/*, opensfm/*,
    /// bundler/*/bundle.out, bal/*.txt).
    #[arg(long)]
    pub all: Option<PathBuf>,
    /// Protocol queries per scene.
    #[arg(long, default_value_t = 20)]
    pub queries: usize,
    /// Co-visible views per query.
    #[arg(long, default_value_t = 10)]
    pub k: usize,
    /// Seed of the protocol's query selection.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Write every scene's and group's quantiles as JSON here.
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Draw the groups' distributions as box plots into this PNG.
    #[arg(long)]
    pub plot: Option<PathBuf>,
}

/// The measured quantities, in table order: (key, column header).
pub const METRICS: [(&str, &str); 11] = [
    ("hfov_deg", "HFOV deg"),
    ("distortion_pct", "dist. %"),
    ("keypoints", "kpts/img"),
    ("triangulated_pct", "triang. %"),
    ("points_per_view", "pts/view"),
    ("rotation_deg", "rot. deg"),
    ("baseline_rel", "baseline/depth"),
    ("overlap", "overlap"),
    ("depth_ratio", "depth ratio"),
    ("gt_matches", "GT/pair"),
    ("queries", "queries"),
];

/// The raw values of every metric for one scene or group.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Distributions {
    /// Values by metric key.
    pub values: BTreeMap<&'static str, Vec<f64>>,
    /// 3D points nearer to some registered camera than [`NEAR_CAMERA_RELATIVE_DEPTH`].
    pub near_camera_points: usize,
    /// 3D points.
    pub points: usize,
}

impl Distributions {
    fn push(&mut self, key: &'static str, value: f64) {
        if value.is_finite() {
            self.values.entry(key).or_default().push(value);
        }
    }

    fn extend(&mut self, other: &Distributions) {
        for (key, values) in &other.values {
            self.values.entry(key).or_default().extend(values);
        }
        self.near_camera_points += other.near_camera_points;
        self.points += other.points;
    }

    /// 5/25/50/75/95 % quantiles of a metric, `None` without values.
    pub fn quantiles(&self, key: &str) -> Option<[f64; 5]> {
        let q = quantiles(self.values.get(key)?, &[0.05, 0.25, 0.5, 0.75, 0.95])?;
        Some([q[0], q[1], q[2], q[3], q[4]])
    }
}

/// Horizontal field of view in degrees: from the image width, or for files without image
/// sizes (BAL, Bundler) from twice the widest keypoint offset from the principal point.
pub fn horizontal_fov_deg(camera: &Camera, image: &Image) -> f64 {
    let half_width = if camera.width > 0 {
        f64::from(camera.width) / 2.0
    } else {
        image
            .keypoints
            .iter()
            .map(|k| (k.pixel[0] - camera.principal[0]).abs())
            .fold(0.0, f64::max)
    };
    2.0 * (half_width / camera.focal[0]).atan().to_degrees()
}

/// Radial distortion at the image's side edge, in percent of the undistorted radius: the
/// pixel offset of the bearing that projects at `half_width` without distortion, relative
/// to that ideal offset (negative: barrel).
pub fn edge_distortion_pct(camera: &Camera, half_width: f64) -> f64 {
    let radius = half_width / camera.focal[0];
    let Ok(pixel) = camera.bearing_to_pixel([radius, 0.0]) else {
        return f64::NAN;
    };
    100.0 * ((pixel[0] - camera.principal[0]) / half_width - 1.0)
}

/// Median depth of the points a camera observes (in front of it).
fn median_depth(scene: &Scene, image: &Image) -> Option<f64> {
    let mut depths: Vec<f64> = image
        .keypoints
        .iter()
        .filter_map(|k| scene.points.get(&k.point3d?))
        .map(|p| image.pose.transform(&p.xyz).z)
        .filter(|z| *z > 0.0)
        .collect();
    median(&mut depths)
}

/// Points nearer to some registered camera than `relative` times the median observation
/// depth over the scene (the depth along the camera's axis, either side).
pub fn near_camera_points(scene: &Scene, relative: f64) -> usize {
    let mut depths: Vec<f64> = scene
        .images
        .values()
        .filter_map(|image| median_depth(scene, image))
        .collect();
    let Some(scale) = median(&mut depths) else {
        return 0;
    };
    let limit = relative * scale;
    scene
        .points
        .values()
        .filter(|p| {
            scene
                .images
                .values()
                .any(|image| image.pose.transform(&p.xyz).z.abs() < limit)
        })
        .count()
}

fn per_image(scene: &Scene, stats: &mut Distributions) {
    for image in scene.images.values() {
        let Some(camera) = scene.camera_of(image) else {
            continue;
        };
        let fov = horizontal_fov_deg(camera, image);
        let half_width = camera.focal[0] * (fov.to_radians() / 2.0).tan();
        stats.push("hfov_deg", fov);
        stats.push("distortion_pct", edge_distortion_pct(camera, half_width));
        stats.push("keypoints", image.keypoints.len() as f64);
        let share = image.triangulated_count() as f64 / image.keypoints.len().max(1) as f64;
        stats.push("triangulated_pct", 100.0 * share);
    }
}

fn per_pair(scene: &Scene, sample: &QuerySample, stats: &mut Distributions) {
    let Some(query) = scene.images.get(&sample.image_id) else {
        return;
    };
    let query_depth = median_depth(scene, query).unwrap_or(f64::NAN);
    let query_points: BTreeSet<_> = query.observed_points().into_iter().collect();
    for view in &sample.views {
        let Some(image) = scene.images.get(&view.image_id) else {
            continue;
        };
        stats.push("points_per_view", view.point_ids.len() as f64);
        stats.push("rotation_deg", query.pose.rotation_error_deg(&image.pose));
        let baseline = (query.pose.center() - image.pose.center()).norm();
        stats.push("baseline_rel", baseline / query_depth);
        stats.push("overlap", view.overlap);
        stats.push(
            "depth_ratio",
            shared_depth_ratio(scene, query, image, &query_points),
        );
        stats.push("gt_matches", view.gt_pairs.len() as f64);
    }
}

/// Scale change between two images: the ratio (at least 1) of the median depths of the
/// points both observe.
fn shared_depth_ratio(
    scene: &Scene,
    query: &Image,
    view: &Image,
    query_points: &BTreeSet<u64>,
) -> f64 {
    let shared: Vec<Vector3<f64>> = view
        .observed_points()
        .into_iter()
        .filter(|id| query_points.contains(id))
        .filter_map(|id| Some(scene.points.get(&id)?.xyz))
        .collect();
    let depth = |image: &Image| {
        let mut z: Vec<f64> = shared.iter().map(|x| image.pose.transform(x).z).collect();
        median(&mut z)
    };
    match (depth(query), depth(view)) {
        (Some(a), Some(b)) if a > 0.0 && b > 0.0 => a.max(b) / a.min(b),
        _ => f64::NAN,
    }
}

/// Every distribution of one scene under the protocol `params`.
pub fn scene_distributions(scene: &Scene, params: &ProtocolParams) -> Distributions {
    let mut stats = Distributions::default();
    per_image(scene, &mut stats);
    let samples = scene_samples(scene, params);
    stats.push("queries", samples.len() as f64);
    for sample in &samples {
        per_pair(scene, sample, &mut stats);
    }
    stats.near_camera_points = near_camera_points(scene, NEAR_CAMERA_RELATIVE_DEPTH);
    stats.points = scene.points.len();
    stats
}

/// Every scene of a folder laid out as `shared/data`, in path order.
pub fn data_folder_sources(root: &Path) -> anyhow::Result<Vec<SceneSource>> {
    let entries = |kind: &str| -> anyhow::Result<Vec<PathBuf>> {
        let dir = root.join(kind);
        if !dir.is_dir() {
            return Ok(Vec::new());
        }
        let mut paths: Vec<PathBuf> = std::fs::read_dir(&dir)
            .with_context(|| format!("listing {}", dir.display()))?
            .map(|e| e.map(|e| e.path()))
            .collect::<Result<_, _>>()?;
        paths.sort();
        Ok(paths)
    };
    let mut sources = Vec::new();
    sources.extend(entries("colmap")?.into_iter().map(SceneSource::Colmap));
    sources.extend(entries("opensfm")?.into_iter().map(SceneSource::OpenSfm));
    let bundles = entries("bundler")?
        .into_iter()
        .map(|d| d.join("bundle.out"));
    sources.extend(bundles.filter(|p| p.is_file()).map(SceneSource::Bundler));
    let bal = entries("bal")?.into_iter();
    sources.extend(
        bal.filter(|p| p.extension().is_some_and(|e| e == "txt"))
            .map(SceneSource::Bal),
    );
    Ok(sources)
}

/// The split of a scene name: `validation`, `training` or `synthetic`.
pub fn split_of(name: &str) -> &'static str {
    if name.starts_with("synthetic") {
        "synthetic"
    } else if VALIDATION_SCENES.contains(&name) {
        "validation"
    } else {
        "training"
    }
}

/// One row of the output: a scene or a pooled group.
#[derive(Debug, Clone)]
struct Row {
    name: String,
    split: &'static str,
    stats: Distributions,
}

fn file_sources(args: &StatsArgs) -> anyhow::Result<Vec<SceneSource>> {
    let mut sources = args.scenes.files();
    if let Some(root) = &args.all {
        sources.extend(data_folder_sources(root)?);
    }
    Ok(sources)
}

/// Runs `scenes`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    match &args.command {
        ScenesCommand::Stats(stats) => run_stats(stats),
    }
}

fn run_stats(args: &StatsArgs) -> anyhow::Result<()> {
    let params = ProtocolParams {
        k: args.k,
        queries_per_scene: args.queries,
        seed: args.seed,
        ..ProtocolParams::default()
    };
    let mut rows = Vec::new();
    for source in file_sources(args)? {
        let scene = source.load()?;
        eprintln!("{}", scene.name);
        let stats = scene_distributions(&scene, &params);
        rows.push(Row {
            split: split_of(&scene.name),
            name: scene.name,
            stats,
        });
    }
    let mut layouts: BTreeMap<String, Distributions> = BTreeMap::new();
    let seed = args.scenes.synthetic_seed;
    let generated = (0..args.scenes.synthetic)
        .map(|i| (synthetic_layout(seed, i), synthetic_scene(seed, i)))
        .chain(
            (0..args.scenes.synthetic_collection)
                .map(|i| (Layout::Collection, collection_scene(seed, i))),
        );
    for (layout, scene) in generated {
        let layout = format!("{layout:?}");
        eprintln!("{} ({layout})", scene.name);
        layouts
            .entry(format!("synthetic/{}", layout.to_lowercase()))
            .or_default()
            .extend(&scene_distributions(&scene, &params));
    }
    rows.extend(layouts.into_iter().map(|(name, stats)| Row {
        name,
        split: "synthetic",
        stats,
    }));
    let groups = pooled_groups(&rows);
    print_scene_table(&rows);
    println!();
    print_group_table(&groups);
    if let Some(path) = &args.json {
        write_json(path, &rows, &groups)?;
    }
    if let Some(path) = &args.plot {
        plot_groups(path, &groups)?;
    }
    Ok(())
}

/// Rows pooled by split (training, validation, synthetic), those present.
fn pooled_groups(rows: &[Row]) -> Vec<Row> {
    ["training", "validation", "synthetic"]
        .into_iter()
        .filter_map(|split| {
            let members: Vec<&Row> = rows.iter().filter(|r| r.split == split).collect();
            if members.is_empty() {
                return None;
            }
            let mut stats = Distributions::default();
            members.iter().for_each(|r| stats.extend(&r.stats));
            Some(Row {
                name: format!("{split} ({} rows)", members.len()),
                split,
                stats,
            })
        })
        .collect()
}

fn format_value(value: f64) -> String {
    if value.abs() >= 100.0 {
        format!("{value:.0}")
    } else if value.abs() >= 10.0 {
        format!("{value:.1}")
    } else {
        format!("{value:.2}")
    }
}

/// Per scene: the median of each metric (the query count itself for `queries`), the 3D
/// points and those at a camera.
fn print_scene_table(rows: &[Row]) {
    let headers: Vec<&str> = METRICS.iter().map(|m| m.1).collect();
    println!(
        "| scene | split | {} | 3D points | near-camera points |",
        headers.join(" | ")
    );
    println!("|---|---|{}---|---|", "---|".repeat(METRICS.len()));
    for row in rows {
        let cells: Vec<String> = METRICS
            .iter()
            .map(|(key, _)| match (*key, row.stats.values.get(key)) {
                ("queries", Some(v)) => format!("{}", v.iter().sum::<f64>()),
                _ => row
                    .stats
                    .quantiles(key)
                    .map_or("-".into(), |q| format_value(q[2])),
            })
            .collect();
        println!(
            "| {} | {} | {} | {} | {} |",
            row.name,
            row.split,
            cells.join(" | "),
            row.stats.points,
            row.stats.near_camera_points
        );
    }
}

/// Per metric, each group's quartiles `q1 / median / q3`.
fn print_group_table(groups: &[Row]) {
    let names: Vec<&str> = groups.iter().map(|g| g.name.as_str()).collect();
    println!("| metric (q1 / median / q3) | {} |", names.join(" | "));
    println!("|---|{}", "---|".repeat(groups.len()));
    for (key, header) in METRICS.iter().filter(|m| m.0 != "queries") {
        let cells: Vec<String> = groups
            .iter()
            .map(|g| {
                g.stats.quantiles(key).map_or("-".into(), |q| {
                    format!(
                        "{} / {} / {}",
                        format_value(q[1]),
                        format_value(q[2]),
                        format_value(q[3])
                    )
                })
            })
            .collect();
        println!("| {header} | {} |", cells.join(" | "));
    }
    let near: Vec<String> = groups
        .iter()
        .map(|g| format!("{} of {}", g.stats.near_camera_points, g.stats.points))
        .collect();
    println!(
        "| 3D points at a camera (depth < 1e-6 median) | {} |",
        near.join(" | ")
    );
}

#[derive(Serialize)]
struct JsonRow<'a> {
    name: &'a str,
    split: &'a str,
    points: usize,
    near_camera_points: usize,
    /// Per metric: count and 5/25/50/75/95 % quantiles.
    metrics: BTreeMap<&'static str, (usize, [f64; 5])>,
}

fn json_row(row: &Row) -> JsonRow<'_> {
    let metrics = METRICS
        .iter()
        .filter_map(|(key, _)| {
            let count = row.stats.values.get(key)?.len();
            Some((*key, (count, row.stats.quantiles(key)?)))
        })
        .collect();
    JsonRow {
        name: &row.name,
        split: row.split,
        points: row.stats.points,
        near_camera_points: row.stats.near_camera_points,
        metrics,
    }
}

fn write_json(path: &Path, rows: &[Row], groups: &[Row]) -> anyhow::Result<()> {
    let value = serde_json::json!({
        "scenes": rows.iter().map(json_row).collect::<Vec<_>>(),
        "groups": groups.iter().map(json_row).collect::<Vec<_>>(),
    });
    std::fs::write(path, serde_json::to_string_pretty(&value)?)
        .with_context(|| format!("writing {}", path.display()))
}

/// One panel per metric, one box per group: 25-75 % box, median line, 5-95 % whiskers.
fn plot_groups(path: &Path, groups: &[Row]) -> anyhow::Result<()> {
    use plotters::prelude::*;
    let metrics: Vec<(&str, &str)> = METRICS
        .iter()
        .copied()
        .filter(|m| m.0 != "queries")
        .collect();
    let font = crate::host::register_font();
    let root = BitMapBackend::new(path, (1500, 1000)).into_drawing_area();
    root.fill(&WHITE)?;
    let panels = root.split_evenly((3, 4));
    let colours = [BLUE, GREEN, RED, MAGENTA];
    for ((key, header), panel) in metrics.iter().zip(&panels) {
        let boxes: Vec<(usize, [f64; 5])> = groups
            .iter()
            .enumerate()
            .filter_map(|(i, g)| Some((i, g.stats.quantiles(key)?)))
            .collect();
        let low = boxes.iter().map(|b| b.1[0]).fold(f64::INFINITY, f64::min);
        let high = boxes
            .iter()
            .map(|b| b.1[4])
            .fold(f64::NEG_INFINITY, f64::max);
        if !(low.is_finite() && high.is_finite()) {
            continue;
        }
        let margin = 0.05 * (high - low).max(1e-9);
        let mut chart = ChartBuilder::on(panel)
            .caption(*header, ("sans-serif", 18))
            .margin(8)
            .x_label_area_size(20)
            .y_label_area_size(50)
            .build_cartesian_2d(
                -0.5f64..groups.len() as f64 - 0.5,
                low - margin..high + margin,
            )?;
        chart.configure_mesh().disable_x_mesh().x_labels(0).draw()?;
        for (i, [q05, q25, q50, q75, q95]) in &boxes {
            let x = *i as f64;
            let colour = colours[i % colours.len()];
            chart.draw_series([Rectangle::new(
                [(x - 0.3, *q25), (x + 0.3, *q75)],
                colour.stroke_width(2),
            )])?;
            chart.draw_series([
                PathElement::new(
                    vec![(x - 0.3, *q50), (x + 0.3, *q50)],
                    colour.stroke_width(3),
                ),
                PathElement::new(vec![(x, *q05), (x, *q25)], colour.stroke_width(1)),
                PathElement::new(vec![(x, *q75), (x, *q95)], colour.stroke_width(1)),
            ])?;
        }
    }
    let legend = panels.last().context("plot panels")?;
    if !font {
        eprintln!("no TrueType font found: the plot has boxes but no text");
    }
    for (i, group) in groups.iter().enumerate().filter(|_| font) {
        let colour = colours[i % colours.len()];
        legend.draw(&Text::new(
            group.name.clone(),
            (20, 30 + 30 * i as i32),
            ("sans-serif", 20).into_font().color(&colour),
        ))?;
    }
    root.present()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use gomatch::camera::CameraModel;

    #[test]
    fn field_of_view_and_edge_distortion() {
        let pinhole = Camera::simple_pinhole(1000, 800, 500.0, 500.0, 400.0).unwrap();
        let image = Image {
            id: 1,
            name: String::new(),
            camera_id: 1,
            pose: gomatch::Pose::identity(),
            keypoints: Vec::new(),
        };
        assert!((horizontal_fov_deg(&pinhole, &image) - 90.0).abs() < 1e-9);
        assert!(edge_distortion_pct(&pinhole, 500.0).abs() < 1e-9);
        let barrel = Camera::from_colmap(
            CameraModel::SimpleRadial,
            1000,
            800,
            &[500.0, 500.0, 400.0, -0.1],
        )
        .unwrap();
        // r = 1 at the edge: 1 + k1 r^2 = 0.9, 10 % barrel.
        assert!((edge_distortion_pct(&barrel, 500.0) + 10.0).abs() < 1e-9);
    }

    #[test]
    fn splits_follow_the_data_readme() {
        assert_eq!(split_of("colmap/mouse"), "validation");
        assert_eq!(split_of("opensfm/projcv_cc9d27"), "validation");
        assert_eq!(split_of("colmap/kwrous"), "training");
        assert_eq!(split_of("synthetic/landmark"), "synthetic");
    }
}
