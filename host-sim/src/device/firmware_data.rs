//! `gomatch-sim firmware-data`: the small map, the query and its ground truth that the
//! freestanding firmware image embeds (`firmware/data/`), from a synthetic scene.
//!
//! - `map.bin`: a map blob of the query's co-visible views only (their cameras and the
//!   points they observe), so it stays small;
//! - `query.frame`: the query as the device link's localization request, one COBS frame
//!   (its zero delimiter included): keypoint pixels, camera, view image ids;
//! - `truth.bin`: 13 little-endian `f64`: the true world-to-camera rotation (row-major),
//!   translation, and the scene scale (median depth of the query's ground-truth points)
//!   that the image's translation threshold is relative to.

use std::collections::BTreeSet;
use std::path::PathBuf;

use anyhow::{bail, Context};
use clap::Parser;
use gomatch::link::{self, LocalizeRequest, Request, RequestBody, Views};
use gomatch::Map;

use crate::eval::{protocol_samples, query_pixels};
use crate::map::build_map;
use crate::protocol::synthetic::synthetic_scene;
use crate::protocol::{ProtocolParams, QuerySample};
use crate::scene::Scene;

/// Keypoint capacity of the firmware image (`firmware/src/main.rs`).
pub const FIRMWARE_CAPACITY: usize = 256;
/// Synthetic scene family of the committed firmware data: one the shipped model never saw.
pub const FIRMWARE_SEED: u64 = 1;
/// Largest map blob written, to keep the image small.
const MAX_MAP_BYTES: usize = 100 * 1024;

/// Write the firmware image's embedded map, query and ground truth.
#[derive(Debug, Clone, Parser)]
pub struct Args {
    /// Output directory.
    #[arg(long, default_value = "firmware/data")]
    pub out: PathBuf,
    /// Seed of the synthetic scene family (default 1: the shipped model trained on seed 0's
    /// scenes, see models/README.md).
    #[arg(long, default_value_t = FIRMWARE_SEED)]
    pub seed: u64,
    /// Index of the synthetic scene.
    #[arg(long, default_value_t = 0)]
    pub scene: u64,
    /// Co-visible views of the query (the map holds only these).
    #[arg(long, default_value_t = 10)]
    pub k: usize,
}

/// The files' contents.
#[derive(Debug, Clone, PartialEq)]
pub struct FirmwareData {
    /// Map blob.
    pub map: Vec<u8>,
    /// Localization request frame.
    pub query_frame: Vec<u8>,
    /// Rotation, translation, scale as little-endian `f64`.
    pub truth: Vec<u8>,
    /// The sample they come from.
    pub sample: QuerySample,
}

/// The scene restricted to some images: their cameras, and the points they observe with
/// the tracks cut to them.
fn sub_scene(scene: &Scene, image_ids: &BTreeSet<u32>) -> Scene {
    let mut sub = scene.clone();
    sub.images.retain(|id, _| image_ids.contains(id));
    let cameras: BTreeSet<u32> = sub.images.values().map(|i| i.camera_id).collect();
    sub.cameras.retain(|id, _| cameras.contains(id));
    for point in sub.points.values_mut() {
        point.track.retain(|t| image_ids.contains(&t.image_id));
    }
    sub.points.retain(|_, p| !p.track.is_empty());
    sub
}

/// Median depth of the query's ground-truth points in the query camera.
fn scene_scale(sample: &QuerySample) -> f64 {
    let mut depths: Vec<f64> = sample
        .gt_inlier_points()
        .iter()
        .map(|x| sample.pose.transform(x).z)
        .collect();
    depths.sort_by(f64::total_cmp);
    depths.get(depths.len() / 2).copied().unwrap_or(1.0)
}

/// Builds the firmware data from the first protocol query of the scene with `k` views.
pub fn firmware_data(seed: u64, scene_index: u64, k: usize) -> anyhow::Result<FirmwareData> {
    let scene = synthetic_scene(seed, scene_index);
    let params = ProtocolParams::for_localizer(k, 20, seed, FIRMWARE_CAPACITY);
    let sample = protocol_samples(&scene, &params)
        .into_iter()
        .find(|s| s.views.len() == k)
        .with_context(|| format!("no query of scene {} has {k} views", scene.name))?;
    let view_ids: Vec<u32> = sample.views.iter().map(|v| v.image_id).collect();
    let map = build_map(&sub_scene(&scene, &view_ids.iter().copied().collect()))?;
    if map.len() > MAX_MAP_BYTES {
        bail!("map of {} bytes, more than {MAX_MAP_BYTES}", map.len());
    }
    Map::from_bytes(&map).map_err(|e| anyhow::anyhow!("map: {e}"))?;
    let pixels = query_pixels(&sample);
    let mut keypoint_bytes = vec![0u8; link::KEYPOINT_BYTES * pixels.len()];
    let keypoints = link::encode_keypoints(&pixels, &mut keypoint_bytes).context("keypoints")?;
    let request = Request {
        id: 1,
        body: RequestBody::Localize(LocalizeRequest {
            camera: sample.camera,
            keypoints,
            views: Views::ImageIds(
                heapless::Vec::from_slice(&view_ids).map_err(|_| anyhow::anyhow!("k > 10"))?,
            ),
        }),
    };
    let mut frame = vec![0u8; link::rx_frame_len(FIRMWARE_CAPACITY) + 1];
    let len = link::encode_frame(&request, &mut frame)
        .context("request frame")?
        .len();
    frame.truncate(len);
    let wire = link::WirePose::from(&sample.pose);
    let truth: Vec<u8> = wire
        .rotation
        .iter()
        .flatten()
        .chain(&wire.translation)
        .chain(&[scene_scale(&sample)])
        .flat_map(|v| v.to_le_bytes())
        .collect();
    Ok(FirmwareData {
        map,
        query_frame: frame,
        truth,
        sample,
    })
}

/// Runs `gomatch-sim firmware-data`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let data = firmware_data(args.seed, args.scene, args.k)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    for (name, bytes) in [
        ("map.bin", &data.map),
        ("query.frame", &data.query_frame),
        ("truth.bin", &data.truth),
    ] {
        let path = args.out.join(name);
        std::fs::write(&path, bytes).with_context(|| format!("writing {}", path.display()))?;
        println!("{}: {} bytes", path.display(), bytes.len());
    }
    let s = &data.sample;
    println!(
        "query image {} of synthetic scene ({}, {}): {} keypoints, views {:?}",
        s.image_id,
        args.seed,
        args.scene,
        s.keypoints.len(),
        s.views.iter().map(|v| v.image_id).collect::<Vec<_>>()
    );
    Ok(())
}
