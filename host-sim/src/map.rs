//! `gomatch-sim map`: builds the core's geometric-only map blob ([`gomatch::map`]) from a
//! structure-from-motion model, and reports its storage next to what visual descriptors
//! for the same points would cost (paper supp. Table 1: a visual-matching map stores
//! descriptors on top of the same 3D points and cameras).

use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::Context;
use clap::{Args as ClapArgs, Parser, Subcommand};
use gomatch::map::{
    encode, encoded_len, Map, MapViewEntry, CAMERA_BYTES, HEADER_BYTES, INDEX_BYTES, POINT_BYTES,
    VIEW_BYTES,
};
use gomatch::pose::{MAX_BEARING, MIN_DEPTH_RATIO};

use crate::host::ModelArgs;
use crate::protocol::{audit_projections, ProjectionAudit, ProtocolParams};
use crate::readers::colmap::camera_line;
use crate::scene::{ImageId, Keypoint, Scene};

/// Bytes of one SIFT descriptor (128 x u8).
pub const SIFT_DESCRIPTOR_BYTES: usize = 128;
/// Bytes of one SuperPoint descriptor (256 x f32).
pub const SUPERPOINT_DESCRIPTOR_BYTES: usize = 256 * 4;

/// Build or inspect a geometric-only map blob.
#[derive(Debug, Clone, Parser)]
pub struct Args {
    /// What to do.
    #[command(subcommand)]
    pub command: MapCommand,
}

/// The `map` subcommands.
#[derive(Debug, Clone, Subcommand)]
pub enum MapCommand {
    /// Build a map blob from a COLMAP, BAL or Bundler model.
    Build(BuildArgs),
    /// Print the storage breakdown of a map blob.
    Stats(StatsArgs),
    /// Print each view of a map blob: view index, image id, name, camera and point count.
    List(ListArgs),
    /// Print the triangulated share per block of each image's stored keypoints: the
    /// evidence for the rank `build` stores view points in.
    Rank(RankArgs),
    /// Precompute each view's features for one model and capacity (a blob beside the
    /// map, given to `localize --view-features`): the localizer skips the view's encoder
    /// and first self-attention layer, with the same results.
    Features(crate::view_features::FeaturesArgs),
}

/// Arguments of `map build`.
#[derive(Debug, Clone, ClapArgs)]
pub struct BuildArgs {
    /// The model to convert.
    #[command(flatten)]
    pub source: ModelArgs,
    /// Output map blob.
    #[arg(long)]
    pub output: PathBuf,
    /// Leave these images (by name) out of the map, e.g. to localize them against it.
    #[arg(long, num_args = 1..)]
    pub exclude: Vec<String>,
}

/// Arguments of `map stats`.
#[derive(Debug, Clone, ClapArgs)]
pub struct StatsArgs {
    /// Map blob to inspect.
    pub map: PathBuf,
    /// Its view-features blob (`map features`), to count its flash too.
    #[arg(long)]
    pub view_features: Option<PathBuf>,
}

/// Arguments of `map list`.
#[derive(Debug, Clone, ClapArgs)]
pub struct ListArgs {
    /// Map blob to list.
    pub map: PathBuf,
}

/// Arguments of `map rank`.
#[derive(Debug, Clone, ClapArgs)]
pub struct RankArgs {
    /// The model to inspect.
    #[command(flatten)]
    pub source: ModelArgs,
    /// Keypoints per block (the protocol's cap).
    #[arg(long, default_value_t = 1024)]
    pub block: usize,
}

/// Share of `keypoints` that observe a 3D point (0 for none).
fn triangulated_share(keypoints: &[Keypoint]) -> f64 {
    let triangulated = keypoints.iter().filter(|k| k.point3d.is_some()).count();
    triangulated as f64 / keypoints.len().max(1) as f64
}

/// Triangulated share of each consecutive block of `block` stored keypoints (the last
/// block may be shorter).
pub fn block_shares(keypoints: &[Keypoint], block: usize) -> Vec<f64> {
    keypoints
        .chunks(block.max(1))
        .map(triangulated_share)
        .collect()
}

/// Per image with more than `block` keypoints: its id and the triangulated shares of its
/// first and last `block` stored keypoints. A higher share at the end supports
/// [`crate::scene::Image::ranked_keypoints`]: larger-scale, more repeatable detections
/// stored last.
pub fn first_and_last_shares(scene: &Scene, block: usize) -> Vec<(ImageId, f64, f64)> {
    scene
        .images
        .values()
        .filter(|image| image.keypoints.len() > block)
        .map(|image| {
            let keypoints = &image.keypoints;
            let last = &keypoints[keypoints.len() - block..];
            (
                image.id,
                triangulated_share(&keypoints[..block]),
                triangulated_share(last),
            )
        })
        .collect()
}

/// Prints [`block_shares`] per capped image and the mean [`first_and_last_shares`].
fn print_rank(scene: &Scene, block: usize) {
    let capped = first_and_last_shares(scene, block);
    for (id, _, _) in &capped {
        let keypoints = &scene.images[id].keypoints;
        let shares: Vec<String> = block_shares(keypoints, block)
            .iter()
            .map(|s| format!("{s:.2}"))
            .collect();
        let (count, shares) = (keypoints.len(), shares.join(" "));
        println!("image {id}: {count} keypoints, blocks {shares}");
    }
    if capped.is_empty() {
        println!("no image has more than {block} keypoints");
        return;
    }
    let n = capped.len() as f64;
    let first = capped.iter().map(|c| c.1).sum::<f64>() / n;
    let last = capped.iter().map(|c| c.2).sum::<f64>() / n;
    println!(
        "{} images: triangulated share of the first {block} keypoints {first:.3}, of the last {block} {last:.3}",
        capped.len()
    );
}

/// The ids of the 3D points a map blob of the scene holds, in blob order: those with at
/// least one observation, in id order.
fn mapped_point_ids(scene: &Scene) -> Vec<u64> {
    scene
        .points
        .values()
        .filter(|p| !p.track.is_empty())
        .map(|p| p.id)
        .collect()
}

/// Index in the map blob ([`build_map`]) of each mapped 3D point id.
pub fn map_point_index(scene: &Scene) -> anyhow::Result<BTreeMap<u64, u32>> {
    index_by_id(&mapped_point_ids(scene))
}

/// Position of each id in `ids`.
fn index_by_id(ids: &[u64]) -> anyhow::Result<BTreeMap<u64, u32>> {
    ids.iter()
        .enumerate()
        .map(|(i, &id)| Ok((id, u32::try_from(i)?)))
        .collect()
}

/// Encodes a scene as a map blob: every 3D point with at least one observation (in id
/// order), every camera (in id order), and every image as a view with the distinct points
/// it observes, ranked as a capped detector keeps them
/// ([`crate::scene::Image::observed_points`]), so the device's "first `capacity`" rule
/// keeps the best ones.
pub fn build_map(scene: &Scene) -> anyhow::Result<Vec<u8>> {
    let point_ids = mapped_point_ids(scene);
    let point_index = index_by_id(&point_ids)?;
    let points: Vec<[f32; 3]> = point_ids
        .iter()
        .map(|id| {
            let xyz = scene.points[id].xyz;
            [xyz.x as f32, xyz.y as f32, xyz.z as f32]
        })
        .collect();
    let camera_index: BTreeMap<u32, u32> = scene
        .cameras
        .keys()
        .enumerate()
        .map(|(i, &id)| Ok((id, u32::try_from(i)?)))
        .collect::<anyhow::Result<_>>()?;
    let cameras: Vec<gomatch::Camera> = scene.cameras.values().copied().collect();
    let observed: Vec<Vec<u32>> = scene
        .images
        .values()
        .map(|image| {
            image
                .observed_points()
                .iter()
                .filter_map(|id| point_index.get(id).copied())
                .collect()
        })
        .collect();
    let views = scene
        .images
        .values()
        .zip(&observed)
        .map(|(image, points)| {
            Ok(MapViewEntry {
                image_id: image.id,
                name: &image.name,
                camera_index: *camera_index
                    .get(&image.camera_id)
                    .with_context(|| format!("image {} has no camera", image.id))?,
                pose: image.pose,
                points,
            })
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    let mut blob = vec![0u8; encoded_len(points.len(), cameras.len(), &views)];
    let len = encode(&points, &cameras, &views, &mut blob).context("encoding the map")?;
    blob.truncate(len);
    Ok(blob)
}

/// Storage of a map blob by part, and the descriptor storage a visual map would add.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StorageBreakdown {
    /// 3D points.
    pub points: usize,
    /// Cameras.
    pub cameras: usize,
    /// Views.
    pub views: usize,
    /// View-point observations.
    pub observations: usize,
    /// Bytes of point coordinates.
    pub point_bytes: usize,
    /// Bytes of camera records.
    pub camera_bytes: usize,
    /// Bytes of view records (poses).
    pub view_bytes: usize,
    /// Bytes of the observation indices.
    pub observation_bytes: usize,
    /// Header and encoding overhead (magic, version, checksum, lengths).
    pub overhead_bytes: usize,
    /// Whole blob.
    pub total_bytes: usize,
}

impl StorageBreakdown {
    /// Breakdown of a decoded map whose blob has `total_bytes`.
    pub fn of(map: &Map<'_>, total_bytes: usize) -> Self {
        let point_bytes = map.point_count() * POINT_BYTES;
        let camera_bytes = map.camera_count() * CAMERA_BYTES;
        let view_bytes = map.view_count() * VIEW_BYTES;
        let observation_bytes = map.observation_count() * INDEX_BYTES;
        Self {
            points: map.point_count(),
            cameras: map.camera_count(),
            views: map.view_count(),
            observations: map.observation_count(),
            point_bytes,
            camera_bytes,
            view_bytes,
            observation_bytes,
            overhead_bytes: total_bytes
                - (point_bytes + camera_bytes + view_bytes + observation_bytes),
            total_bytes,
        }
    }
}

fn human(bytes: usize) -> String {
    let b = bytes as f64;
    if b >= 1024.0 * 1024.0 * 1024.0 {
        format!("{:.2} GiB", b / (1024.0 * 1024.0 * 1024.0))
    } else if b >= 1024.0 * 1024.0 {
        format!("{:.2} MiB", b / (1024.0 * 1024.0))
    } else if b >= 1024.0 {
        format!("{:.1} KiB", b / 1024.0)
    } else {
        format!("{bytes} B")
    }
}

fn print_stats(s: &StorageBreakdown) {
    let share = |bytes: usize| 100.0 * bytes as f64 / s.total_bytes.max(1) as f64;
    println!(
        "geometric-only map: {} points, {} cameras, {} views, {} observations",
        s.points, s.cameras, s.views, s.observations
    );
    for (part, bytes) in [
        ("3D points (3 x f32)", s.point_bytes),
        ("cameras", s.camera_bytes),
        ("views (pose, ranges)", s.view_bytes),
        ("observations (u32)", s.observation_bytes),
        (
            &*format!("header {HEADER_BYTES} B + lengths"),
            s.overhead_bytes,
        ),
    ] {
        println!("  {part:<24} {:>12} {:>6.1} %", human(bytes), share(bytes));
    }
    println!("  {:<24} {:>12}", "total", human(s.total_bytes));
    println!("descriptors a visual-matching map adds for the same points:");
    for (name, size) in [
        ("SIFT (128 x u8)", SIFT_DESCRIPTOR_BYTES),
        ("SuperPoint (256 x f32)", SUPERPOINT_DESCRIPTOR_BYTES),
    ] {
        let per_point = s.points * size;
        let per_observation = s.observations * size;
        println!(
            "  {name:<24} one per point {:>12} ({:.1}x the map), one per observation {:>12} ({:.1}x)",
            human(per_point),
            per_point as f64 / s.total_bytes.max(1) as f64,
            human(per_observation),
            per_observation as f64 / s.total_bytes.max(1) as f64
        );
    }
}

/// Prints how many observations the localizer's projection rule skips.
fn print_audit(audit: &ProjectionAudit) {
    let ratio = |r: Option<f64>| r.map_or("none".to_string(), |r| format!("{r:.2e}"));
    println!(
        "projection rule (depth >= {MIN_DEPTH_RATIO} x the view's median depth, |bearing| <= {MAX_BEARING}): {} of {} observations skipped ({} at or behind the camera, {} too close, {} off axis); relative depth of the farthest too close: {}, of the closest kept: {}",
        audit.behind + audit.too_close + audit.off_axis,
        audit.observations,
        audit.behind,
        audit.too_close,
        audit.off_axis,
        ratio(audit.farthest_refused_ratio),
        ratio(audit.closest_kept_ratio),
    );
}

/// The scene without the images named in `names`; fails on a name the scene does not
/// hold. Points only those images observed keep no observation, so [`build_map`] leaves
/// them out.
pub fn exclude_images(scene: &Scene, names: &[String]) -> anyhow::Result<Scene> {
    let mut kept = scene.clone();
    for name in names {
        let id = scene
            .images
            .values()
            .find(|image| &image.name == name)
            .map(|image| image.id)
            .with_context(|| format!("{}: no image named {name:?}", scene.name))?;
        kept.images.remove(&id);
    }
    for point in kept.points.values_mut() {
        point
            .track
            .retain(|element| kept.images.contains_key(&element.image_id));
    }
    Ok(kept)
}

/// Prints the cameras of a map (index and COLMAP line) and one line per view: index,
/// image id, camera index, point count and name.
fn print_views(map: &Map<'_>) -> anyhow::Result<()> {
    for index in 0..map.camera_count() {
        println!("camera {index}: {}", camera_line(&map.camera(index)?));
    }
    println!("view image_id camera points name");
    for index in 0..map.view_count() {
        let view = map.view(index)?;
        println!(
            "{index} {} {} {} {}",
            view.image_id,
            view.camera_index,
            map.view_points(index)?.len(),
            map.view_name(index)?
        );
    }
    Ok(())
}

/// Prints the size of the view-features blob at `path` beside the map's `map_bytes`.
fn print_view_features(
    map: Map<'_>,
    path: &std::path::Path,
    map_bytes: usize,
) -> anyhow::Result<()> {
    let blob = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    gomatch_blobs::view_features::attach(map, &blob)?;
    let features = gomatch::view_features::ViewFeatures::from_bytes(&blob)?;
    println!(
        "view features ({}): {} ({:.1}x the map) for N = {}, d = {}, model CRC-32 {:08x}",
        path.display(),
        human(blob.len()),
        blob.len() as f64 / map_bytes.max(1) as f64,
        features.capacity(),
        features.dim(),
        features.model_checksum()
    );
    Ok(())
}

/// Runs `map build`, `map stats`, `map list`, `map rank` or `map features`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    match &args.command {
        MapCommand::Build(build) => {
            let scene = exclude_images(&build.source.source()?.load()?, &build.exclude)?;
            let blob = build_map(&scene)?;
            std::fs::write(&build.output, &blob)
                .with_context(|| format!("writing {}", build.output.display()))?;
            println!(
                "wrote {} ({}) from {}",
                build.output.display(),
                human(blob.len()),
                scene.name
            );
            let map = Map::from_bytes(&blob).context("reading back the map")?;
            print_stats(&StorageBreakdown::of(&map, blob.len()));
            print_audit(&audit_projections(
                &scene,
                ProtocolParams::default().max_points,
            ));
        }
        MapCommand::Stats(stats) => {
            let blob = gomatch_blobs::files::read_map_blob(&stats.map)?;
            let map = Map::from_bytes(&blob)?;
            print_stats(&StorageBreakdown::of(&map, blob.len()));
            if let Some(path) = &stats.view_features {
                print_view_features(map, path, blob.len())?;
            }
        }
        MapCommand::List(list) => {
            let blob = gomatch_blobs::files::read_map_blob(&list.map)?;
            print_views(&Map::from_bytes(&blob)?)?;
        }
        MapCommand::Rank(rank) => print_rank(&rank.source.source()?.load_as_stored()?, rank.block),
        MapCommand::Features(features) => crate::view_features::run(features)?,
    }
    Ok(())
}
