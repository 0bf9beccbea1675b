//! Helpers every host subcommand shares: the evaluated localizer's capacity, the shipped
//! model's path, the host clock, the command-line scene sources and the plots' font.

use std::path::PathBuf;
use std::time::Instant;

use clap::Args as ClapArgs;
use gomatch::localizer::Clock;

use crate::readers::SceneSource;

/// Keypoint and per-view point capacity of the evaluated localizer (the paper's 1024).
pub const CAPACITY: usize = 1024;

/// The repository's shipped model, `models/gomatch-int8.bin`, found from the current
/// folder or the executable's ([`gomatch_blobs::files::shipped_model_path`]).
pub fn default_model_path() -> PathBuf {
    gomatch_blobs::files::shipped_model_path()
}

/// Microseconds from [`Instant`], the host's [`Clock`] for the core's stage timings.
#[derive(Debug, Clone, Copy)]
pub struct HostClock(Instant);

impl Default for HostClock {
    fn default() -> Self {
        Self(Instant::now())
    }
}

impl Clock for HostClock {
    fn now_us(&self) -> u64 {
        u64::try_from(self.0.elapsed().as_micros()).unwrap_or(u64::MAX)
    }
}

/// Exactly one model source.
#[derive(Debug, Clone, ClapArgs)]
#[group(required = true, multiple = false)]
pub struct ModelArgs {
    /// COLMAP sparse model folder.
    #[arg(long)]
    pub colmap: Option<PathBuf>,
    /// BAL problem file.
    #[arg(long)]
    pub bal: Option<PathBuf>,
    /// Bundler v0.3 bundle.out file.
    #[arg(long)]
    pub bundler: Option<PathBuf>,
    /// OpenSfM dataset folder (reconstruction.json + tracks.csv; the largest reconstruction).
    #[arg(long)]
    pub opensfm: Option<PathBuf>,
}

impl ModelArgs {
    /// The selected source.
    pub fn source(&self) -> anyhow::Result<SceneSource> {
        match (&self.colmap, &self.bal, &self.bundler, &self.opensfm) {
            (Some(dir), None, None, None) => Ok(SceneSource::Colmap(dir.clone())),
            (None, Some(file), None, None) => Ok(SceneSource::Bal(file.clone())),
            (None, None, Some(file), None) => Ok(SceneSource::Bundler(file.clone())),
            (None, None, None, Some(dir)) => Ok(SceneSource::OpenSfm(dir.clone())),
            _ => anyhow::bail!("give exactly one of --colmap, --bal, --bundler, --opensfm"),
        }
    }
}

/// Any number of model sources of each format, and synthetic scenes to generate.
#[derive(Debug, Clone, Default, ClapArgs)]
pub struct ScenesArgs {
    /// COLMAP sparse model folder (repeatable).
    #[arg(long)]
    pub colmap: Vec<PathBuf>,
    /// BAL problem file (repeatable).
    #[arg(long)]
    pub bal: Vec<PathBuf>,
    /// Bundler v0.3 bundle.out file (repeatable).
    #[arg(long)]
    pub bundler: Vec<PathBuf>,
    /// OpenSfM dataset folder, reconstruction.json + tracks.csv (repeatable).
    #[arg(long)]
    pub opensfm: Vec<PathBuf>,
    /// Number of synthetic scenes to generate.
    #[arg(long, default_value_t = 0)]
    pub synthetic: u64,
    /// Seed of the synthetic scene family.
    #[arg(long, default_value_t = 0)]
    pub synthetic_seed: u64,
    /// Number of synthetic photo collections of a landmark to generate (seeded by
    /// `--synthetic-seed`; scenes `collection/<index>`).
    #[arg(long, default_value_t = 0)]
    pub synthetic_collection: u64,
}

impl ScenesArgs {
    /// The model files in flag order: COLMAP, BAL, Bundler, then OpenSfM.
    pub fn files(&self) -> Vec<SceneSource> {
        self.colmap
            .iter()
            .map(|p| SceneSource::Colmap(p.clone()))
            .chain(self.bal.iter().map(|p| SceneSource::Bal(p.clone())))
            .chain(self.bundler.iter().map(|p| SceneSource::Bundler(p.clone())))
            .chain(self.opensfm.iter().map(|p| SceneSource::OpenSfm(p.clone())))
            .collect()
    }
}

/// Font files tried for the plots' text (plotters draws text with `ab_glyph`, pure Rust,
/// from a font it is given; no system font library is needed).
const FONT_FILES: [&str; 3] = [
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
];

/// Registers the first readable font of `FONT_FILES` as "sans-serif" (once); whether
/// one is available.
pub fn register_font() -> bool {
    static REGISTERED: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *REGISTERED.get_or_init(|| {
        FONT_FILES.iter().any(|path| {
            let Ok(bytes) = std::fs::read(path) else {
                return false;
            };
            let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
            plotters::style::register_font("sans-serif", plotters::style::FontStyle::Normal, bytes)
                .is_ok()
        })
    })
}
