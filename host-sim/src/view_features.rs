//! `gomatch-sim map features`: writes the view-features blob of a map
//! ([`gomatch_blobs::view_features`]) for one model and capacity. The localizer then starts
//! each query-view pair at the cross attention; the matches and poses are the same bits.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args as ClapArgs;
use gomatch::{Map, Model};
use gomatch_blobs::view_features::{attach, build_view_features};

/// Arguments of `map features`.
#[derive(Debug, Clone, ClapArgs)]
pub struct FeaturesArgs {
    /// Map blob (`map build`).
    pub map: PathBuf,
    /// Model blob the localizer will use (default: models/gomatch-int8.bin, searched from
    /// the current folder and the executable's).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Points per view, the localizer's capacity `N` (each view's first `N` points with a
    /// bearing, as the localizer picks them).
    #[arg(long, default_value_t = 1024)]
    pub capacity: usize,
    /// Output view-features blob.
    #[arg(long)]
    pub output: PathBuf,
}

/// Runs `map features`.
pub fn run(args: &FeaturesArgs) -> anyhow::Result<()> {
    let map_blob = gomatch_blobs::files::read_map_blob(&args.map)?;
    let map = Map::from_bytes(&map_blob)?;
    let model_path = args
        .model
        .clone()
        .unwrap_or_else(gomatch_blobs::files::shipped_model_path);
    let model_blob = gomatch_blobs::files::read_model_blob(&model_path)?;
    let model = Model::from_bytes(&model_blob)?;
    let blob = build_view_features(&model, &map, args.capacity)?;
    std::fs::write(&args.output, &blob)
        .with_context(|| format!("writing {}", args.output.display()))?;
    let map = attach(map, &blob)?;
    let points: usize = (0..map.view_count())
        .filter_map(|v| map.view_features()?.view(v))
        .map(|rows| rows.count)
        .sum();
    println!(
        "wrote {} ({} B: {} views, {points} view points x {} values) for model {} at N = {}",
        args.output.display(),
        blob.len(),
        map.view_count(),
        model.config().feature_dim,
        model_path.display(),
        args.capacity
    );
    Ok(())
}
