//! `gomatch-tools mem-report`: what a firmware image needs for the capacity it picks,
//! before it is flashed.
//!
//! Per capacity `N` (128, 256, 512, 1024 keypoints), view count `k` (1, 10), weight
//! precision (f32, f16, int8) and Sinkhorn storage (f32, f16):
//! - `ram_bytes`: the static workspace, `Localizer::<N, S>::BYTES` (`size_of` of the real
//!   type, one instantiation per capacity and storage);
//! - `link_bytes`: the device link's buffers, `Device::<N, rx_frame_len(N)>::BYTES`;
//! - `stack_bytes`: the peak stack of a real localization, measured by painting the
//!   measuring thread's unused stack with a pattern and finding the lowest word changed;
//! - `heap_bytes`: bytes allocated during that call, counted by [`CountingAllocator`]
//!   (the `gomatch-tools` binary's global allocator): the core has no allocator, so this
//!   must be zero, and the report checks that the counter works before trusting a zero;
//! - `flash_model_bytes`: the model blob in that precision (a checkpoint converted in
//!   memory, or a given blob), `flash_map_bytes`: the map blob (given, or the built-in
//!   synthetic scene's map that the firmware image embeds).
//!
//! The localization: the map's most observed view seen as a query (its points projected
//! by its camera, at most `N`, the device's selection rule), matched against the `k`
//! views nearest to that view's pose. The measured call also runs the pose solver on
//! the query's true correspondences, so the solver's frames count even when an untrained
//! model leaves too few matches for the localizer to reach it.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use anyhow::{bail, ensure, Context, Result};
use gomatch::link::{rx_frame_len, Device};
use gomatch::localizer::{view_point_bearings, Localization, ViewSelection};
use gomatch::sinkhorn::PlanScalar;
use gomatch::weights::{Precision, MODEL_MAGIC};
use gomatch::{
    estimate_pose, Camera, Localizer, LocalizerConfig, Map, Model, PnpWorkspace, Pose, Query,
    RansacConfig,
};
use half::f16;
use indicatif::{ProgressBar, ProgressStyle};
use serde::Serialize;

use crate::image_layout;
use gomatch_blobs::convert::{convert, PrecisionArg};
use gomatch_blobs::files::{find_default, read_map_blob, read_model_blob};
use gomatch_blobs::view_features::build_view_features;

/// Capacities reported by default.
pub const CAPACITIES: [usize; 4] = [128, 256, 512, 1024];
/// View counts reported by default.
pub const VIEWS: [usize; 2] = [1, 10];
/// The built-in map: the synthetic scene of the firmware image
/// (`gomatch-sim firmware-data`).
pub const BUILTIN_MAP: &[u8] = include_bytes!("../../firmware/data/map.bin");
/// Viewing-direction cone of the view selection around the query's prior pose.
const PRIOR_CONE_DEG: f64 = 30.0;

/// Command-line arguments of `mem-report`.
#[derive(clap::Args, Debug, Clone)]
pub struct Args {
    /// Capacities `N` (keypoints per query and points per view); default 128 256 512 1024.
    #[arg(long, value_delimiter = ',')]
    pub capacity: Vec<usize>,
    /// View counts `k`; default 1 10.
    #[arg(long, value_delimiter = ',')]
    pub views: Vec<usize>,
    /// Weight precisions; default all three.
    #[arg(long, value_enum, value_delimiter = ',')]
    pub precision: Vec<PrecisionArg>,
    /// Sinkhorn cost storage; default both.
    #[arg(long, value_enum, value_delimiter = ',')]
    pub sinkhorn: Vec<Sinkhorn>,
    /// Fail when a row's static workspace (`ram_bytes`) exceeds this.
    #[arg(long)]
    pub budget_ram: Option<u64>,
    /// Fail when a row's model plus map blobs exceed this.
    #[arg(long)]
    pub budget_flash: Option<u64>,
    /// Fail when a row's peak stack exceeds this.
    #[arg(long)]
    pub budget_stack: Option<u64>,
    /// A float32 safetensors checkpoint (converted to each precision in memory) or a
    /// model blob (its precision only). Default: models/gomatch.safetensors, else the
    /// reference fixture weights (../shared/reference/fixtures/weights.safetensors).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// A map blob. Default: the built-in synthetic scene's map (firmware/data/map.bin).
    #[arg(long)]
    pub map: Option<PathBuf>,
    /// Also write the rows as JSON (`{"rows": [...], "images": [...]}`).
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Where the firmware images are linked (`<target>/release/gomatch-firmware` below
    /// it): their section sizes are reported after the rows.
    #[arg(long, default_value = "firmware/target")]
    pub images: PathBuf,
    /// The C example's image (`bash capi/example/qemu.sh`), reported after the firmware
    /// images with the flash the C API adds against the Rust Cortex-M7 image.
    #[arg(long, default_value = "capi/example/build/gomatch-c-example.elf")]
    pub c_image: PathBuf,
    /// Fail when the C example's image takes more than this many bytes of flash beyond
    /// the Rust Cortex-M7 image's, or when either image is missing.
    #[arg(long)]
    pub budget_capi_flash: Option<i64>,
    /// Report only the firmware images' layout (no localization is measured).
    #[arg(long)]
    pub images_only: bool,
}

/// Storage type of the Sinkhorn cost.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Sinkhorn {
    /// 4 bytes per entry.
    F32,
    /// 2 bytes per entry.
    F16,
}

impl Sinkhorn {
    fn name(self) -> &'static str {
        match self {
            Sinkhorn::F32 => "f32",
            Sinkhorn::F16 => "f16",
        }
    }
}

fn precision_name(p: Precision) -> &'static str {
    match p {
        Precision::F32 => "f32",
        Precision::F16 => "f16",
        Precision::Int8 => "int8",
    }
}

/// One configuration's memory.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Row {
    /// Keypoints per query and points per view, `N`.
    pub capacity: usize,
    /// Views matched, `k`.
    pub views: usize,
    /// Weight precision.
    pub precision: &'static str,
    /// Sinkhorn cost storage.
    pub sinkhorn: &'static str,
    /// Static workspace, `Localizer::<N, S>::BYTES`.
    pub ram_bytes: usize,
    /// Peak stack of the measured localization.
    pub stack_bytes: usize,
    /// Heap allocated during it.
    pub heap_bytes: u64,
    /// Model blob.
    pub flash_model_bytes: usize,
    /// Map blob.
    pub flash_map_bytes: usize,
    /// The map option of precomputed view features for this model and capacity
    /// (`gomatch-sim map features`; not in the flash budget, which counts what the localizer
    /// needs).
    pub flash_view_features_bytes: usize,
    /// Device link buffers, `Device::<N, rx_frame_len(N)>::BYTES`.
    pub link_bytes: usize,
    /// Keypoints of the measured query.
    pub keypoints: usize,
    /// Views the measured localization matched.
    pub views_used: usize,
}

/// The report: rows and where the blobs came from.
#[derive(Debug, Clone, PartialEq)]
pub struct Report {
    /// One row per configuration.
    pub rows: Vec<Row>,
    /// Which model was measured.
    pub model_source: String,
    /// Which map was measured.
    pub map_source: String,
}

// ---------------------------------------------------------------------------------------
// Heap: a counting global allocator.

thread_local! {
    /// Whether this thread's allocations are being counted.
    static COUNTING: Cell<bool> = const { Cell::new(false) };
    /// This thread's counted allocations and bytes.
    static COUNTED: Cell<(u64, u64)> = const { Cell::new((0, 0)) };
}

/// The system allocator, counting the allocations of threads inside [`measure`]. Install
/// it with `#[global_allocator]` (the `gomatch-tools` binary does) for heap figures.
pub struct CountingAllocator;

fn record(bytes: usize) {
    // `try_with`: no panic during thread teardown; const-initialised `Cell`s need no
    // allocation to be used.
    if COUNTING.try_with(Cell::get).unwrap_or(false) {
        let _ = COUNTED.try_with(|c| {
            let (count, total) = c.get();
            c.set((count + 1, total + bytes as u64));
        });
    }
}

// SAFETY: every call is forwarded unchanged to `System`; counting has no effect on it.
unsafe impl GlobalAlloc for CountingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        record(layout.size());
        // SAFETY: the caller's contract is `System`'s.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        record(layout.size());
        // SAFETY: as above.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        record(new_size);
        // SAFETY: as above.
        unsafe { System.realloc(ptr, layout, new_size) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: as above.
        unsafe { System.dealloc(ptr, layout) }
    }
}

// ---------------------------------------------------------------------------------------
// Stack: paint and scan.

/// Stack of the measuring thread.
const THREAD_STACK: usize = 8 << 20;
/// Bytes painted below the measuring frame: the largest measurable use.
const PAINTED: usize = 2 << 20;
/// Bytes left unpainted right below the measuring frame, for the painting function's
/// own frame.
const SKIP: usize = 4096;
/// The paint.
const PATTERN: u64 = 0xA5C3_5A3C_96E1_0FF0;

/// Stack and heap used by one call.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Usage {
    /// Peak stack below the measuring frame, in bytes (a multiple of 8; at least
    /// `SKIP`: less is not resolved).
    pub stack_bytes: usize,
    /// Bytes allocated on the heap.
    pub heap_bytes: u64,
    /// Heap allocations.
    pub heap_allocations: u64,
}

/// Writes the pattern on every word of `[from, to)`.
///
/// # Safety
/// The range must be writable memory that nothing else uses: here, the unused part of
/// the calling thread's own stack, below its stack pointer.
#[inline(never)]
unsafe fn paint(from: usize, to: usize) {
    let mut at = from;
    while at + 8 <= to {
        // SAFETY: by the caller, `at` is in unused, mapped stack memory; aligned to 8.
        unsafe { std::ptr::write_volatile(at as *mut u64, PATTERN) };
        at += 8;
    }
}

/// Lowest word of `[from, to)` that no longer holds the pattern.
///
/// # Safety
/// As for [`paint`]: the range is the calling thread's stack below its frame.
#[inline(never)]
unsafe fn lowest_changed(from: usize, to: usize) -> Option<usize> {
    let mut at = from;
    while at + 8 <= to {
        // SAFETY: as for `paint`; reading stack memory below the current frame.
        if unsafe { std::ptr::read_volatile(at as *const u64) } != PATTERN {
            return Some(at);
        }
        at += 8;
    }
    None
}

/// Runs `f` on a fresh thread and measures its peak stack and its heap allocations.
///
/// Stack: the thread (8 MiB stack) paints the 2 MiB below its current frame (less the
/// first 4 KiB, where the painting function's own frame lives), runs `f`, then scans
/// from the bottom for the first word that changed: everything `f` and its callees
/// touched lies above it. Why this is sound enough: the painted range is mapped stack of
/// this very thread (the thread's stack is 8 MiB and the range ends 2 MiB below a frame
/// near its top, far above the guard page), it lies below the stack pointer so no live
/// Rust object is there, and nothing else runs on this thread meanwhile. It is still
/// memory the language does not hand out, hence `unsafe`, confined to this tool. A
/// deeper use than 2 MiB is an error, not a wrong figure.
pub fn measure<R: Send>(f: impl FnOnce() -> R + Send) -> Result<(R, Usage)> {
    std::thread::scope(|scope| {
        let worker = std::thread::Builder::new()
            .stack_size(THREAD_STACK)
            .spawn_scoped(scope, move || {
                let marker = 0u8;
                let top = std::hint::black_box(&marker) as *const u8 as usize & !7;
                let (bottom, painted_top) = (top - PAINTED, top - SKIP);
                // SAFETY: see above: unused stack of this thread, below this frame.
                unsafe { paint(bottom, painted_top) };
                COUNTED.with(|c| c.set((0, 0)));
                COUNTING.with(|c| c.set(true));
                let result = run_opaque(f);
                COUNTING.with(|c| c.set(false));
                // SAFETY: as above.
                let lowest = unsafe { lowest_changed(bottom, painted_top) };
                let (heap_allocations, heap_bytes) = COUNTED.with(Cell::get);
                let usage = Usage {
                    stack_bytes: top - lowest.unwrap_or(painted_top),
                    heap_bytes,
                    heap_allocations,
                };
                (result, usage, lowest == Some(bottom))
            })
            .context("spawning the measuring thread")?;
        let (result, usage, overflowed) = worker
            .join()
            .map_err(|_| anyhow::anyhow!("the measured call panicked"))?;
        ensure!(
            !overflowed,
            "the call used more than the {PAINTED} bytes of painted stack"
        );
        Ok((result, usage))
    })
}

#[inline(never)]
fn run_opaque<R>(f: impl FnOnce() -> R) -> R {
    std::hint::black_box(f())
}

/// Whether [`CountingAllocator`] is the global allocator (an allocation inside
/// [`measure`] is counted).
pub fn heap_counting_active() -> Result<bool> {
    let ((), usage) = measure(|| drop(std::hint::black_box(Box::new(7u64))))?;
    Ok(usage.heap_allocations > 0)
}

// ---------------------------------------------------------------------------------------
// The measured localization.

/// A query made from one of the map's views.
#[derive(Debug, Clone, PartialEq)]
pub struct MapQuery {
    /// Keypoint pixels: the view's points projected by its camera.
    pub pixels: Vec<[f32; 2]>,
    /// The view's camera.
    pub camera: Camera,
    /// The view's pose: the prior of the view selection and the true pose.
    pub pose: Pose,
    /// The true correspondences: bearings and world points.
    pub bearings: Vec<[f64; 2]>,
    /// World points of `bearings`.
    pub points: Vec<[f64; 3]>,
}

/// The map's most observed view (first on ties) as a query of at most `capacity`
/// keypoints, chosen by the device's rule ([`view_point_bearings`]).
pub fn map_query(map: &Map<'_>, capacity: usize) -> Result<MapQuery> {
    let core = |e: gomatch::Error| anyhow::anyhow!("map: {e}");
    let mut best = (0, 0);
    for v in 0..map.view_count() {
        let observed = map.view_points(v).map_err(core)?.len();
        if observed > best.1 {
            best = (v, observed);
        }
    }
    let view = map.view(best.0).map_err(core)?;
    let camera = map.camera(view.camera_index as usize).map_err(core)?;
    // Each point tagged with its own position.
    let points = map
        .view_point_positions(best.0)
        .map_err(core)?
        .map(|(_, position)| (position, position));
    let mut query = MapQuery {
        pixels: Vec::new(),
        camera,
        pose: view.pose,
        bearings: Vec::new(),
        points: Vec::new(),
    };
    let mut depths = vec![0.0; capacity];
    for (position, bearing) in view_point_bearings(view.pose, points, capacity, &mut depths) {
        let Ok(pixel) = camera.bearing_to_pixel(bearing) else {
            continue;
        };
        query.pixels.push([pixel[0] as f32, pixel[1] as f32]);
        query.bearings.push(bearing);
        query.points.push(position);
    }
    ensure!(
        query.pixels.len() >= 10,
        "the map's most observed view has only {} usable points",
        query.pixels.len()
    );
    Ok(query)
}

/// One localization on the workspace in `slot`, plus the pose solver on the true
/// correspondences, measured.
fn measure_localization<const N: usize, S: PlanScalar + Send>(
    slot: &'static Mutex<Localizer<N, S>>,
    model: &Model<'_>,
    map: &Map<'_>,
    query: &MapQuery,
    k: usize,
) -> Result<(Localization, Usage)> {
    let mut pnp = Box::new(PnpWorkspace::<N>::new());
    let mut guard = slot.lock().unwrap_or_else(|e| e.into_inner());
    let localizer: &mut Localizer<N, S> = &mut guard;
    let (result, usage) = measure(|| {
        let q = Query {
            keypoints: &query.pixels,
            camera: query.camera,
        };
        let views = ViewSelection::NearPrior {
            prior: query.pose,
            k,
            max_angle_deg: PRIOR_CONE_DEG,
        };
        let localization = localizer.localize(model, map, &q, views, &LocalizerConfig::new(), None);
        let solver = estimate_pose(
            &query.bearings,
            &query.points,
            &RansacConfig::new(),
            &mut pnp,
        )
        .map(|e| e.pose);
        (localization, solver)
    })?;
    let (localization, solver) = result;
    let localization = localization.map_err(|e| anyhow::anyhow!("localize: {e}"))?;
    let solved = solver.map_err(|e| anyhow::anyhow!("pose solver on true matches: {e}"))?;
    ensure!(
        solved.rotation_error_deg(&query.pose) < 0.1,
        "the pose solver on the true matches is off by {} deg",
        solved.rotation_error_deg(&query.pose)
    );
    Ok((localization, usage))
}

/// One `static` workspace per capacity and Sinkhorn storage, and the dispatch to them.
macro_rules! workspaces {
    ($($name:ident: $n:literal, $s:ty, $variant:ident;)*) => {
        $(static $name: Mutex<Localizer<$n, $s>> = Mutex::new(Localizer::new());)*

        /// Static workspace, link buffers and the measured localization of capacity `n`
        /// and Sinkhorn storage `sinkhorn`.
        fn measure_capacity(
            n: usize,
            sinkhorn: Sinkhorn,
            model: &Model<'_>,
            map: &Map<'_>,
            query: &MapQuery,
            k: usize,
        ) -> Result<(usize, usize, Localization, Usage)> {
            match (n, sinkhorn) {
                $(($n, Sinkhorn::$variant) => {
                    let (l, usage) = measure_localization(&$name, model, map, query, k)?;
                    let link = Device::<$n, { rx_frame_len($n) }>::BYTES;
                    Ok((Localizer::<$n, $s>::BYTES, link, l, usage))
                })*
                _ => bail!("capacity {n} is not one of {CAPACITIES:?}"),
            }
        }
    };
}

workspaces! {
    W128_F32: 128, f32, F32;
    W128_F16: 128, f16, F16;
    W256_F32: 256, f32, F32;
    W256_F16: 256, f16, F16;
    W512_F32: 512, f32, F32;
    W512_F16: 512, f16, F16;
    W1024_F32: 1024, f32, F32;
    W1024_F16: 1024, f16, F16;
}

// ---------------------------------------------------------------------------------------
// Blobs.

/// Model blobs by precision.
pub type Blobs = Vec<(Precision, Vec<u8>)>;

/// The model blob of each wanted precision, and a description of the source.
pub fn model_blobs(path: Option<&Path>, precisions: &[Precision]) -> Result<(Blobs, String)> {
    let candidates = [
        ("models/gomatch.safetensors", "shipped trained model"),
        (
            "shared/reference/fixtures/weights.safetensors",
            "reference fixture weights (random, untrained)",
        ),
    ];
    let (path, what) = match path {
        Some(p) => (p.to_path_buf(), "given"),
        None => candidates
            .into_iter()
            .find_map(|(relative, what)| Some((find_default(relative)?, what)))
            .context("no model: models/gomatch.safetensors and shared/reference/fixtures/weights.safetensors are not found from the current folder or the executable's; pass --model")?,
    };
    let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
    if bytes.starts_with(&MODEL_MAGIC) {
        let bytes = read_model_blob(&path)?;
        let model = Model::from_bytes(&bytes).map_err(|e| anyhow::anyhow!("model blob: {e}"))?;
        let precision = model.precision();
        ensure!(
            precisions.contains(&precision),
            "{} is an {} blob; ask for --precision {}",
            path.display(),
            precision_name(precision),
            precision_name(precision)
        );
        let source = format!("{} ({what} model blob)", path.display());
        return Ok((vec![(precision, bytes)], source));
    }
    let blobs = precisions
        .iter()
        .map(|&p| Ok((p, convert(&bytes, p)?.0)))
        .collect::<Result<Vec<_>>>()
        .with_context(|| format!("converting {}", path.display()))?;
    let source = format!("{} ({what}, converted in memory)", path.display());
    Ok((blobs, source))
}

/// The map blob and a description of it.
pub fn map_blob(path: Option<&Path>) -> Result<(Vec<u8>, String)> {
    match path {
        Some(p) => Ok((read_map_blob(p)?, p.display().to_string())),
        None => Ok((
            BUILTIN_MAP.to_vec(),
            "built-in synthetic scene map (firmware/data/map.bin)".to_string(),
        )),
    }
}

/// The values given (each once, in the order first given), or `default`.
fn or_default<T: Clone + PartialEq>(given: &[T], default: &[T]) -> Vec<T> {
    let values = if given.is_empty() { default } else { given };
    let mut unique: Vec<T> = Vec::new();
    for value in values {
        if !unique.contains(value) {
            unique.push(value.clone());
        }
    }
    unique
}

/// A progress bar over `rows` measurements, on standard error.
fn progress_bar(rows: usize) -> Result<ProgressBar> {
    let bar = ProgressBar::new(rows as u64).with_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} configurations {elapsed} {msg}")
            .context("progress bar template")?,
    );
    Ok(bar)
}

/// Measures every requested configuration.
pub fn report(args: &Args) -> Result<Report> {
    ensure!(
        heap_counting_active()?,
        "heap use cannot be verified: CountingAllocator is not the global allocator"
    );
    let capacities = or_default(&args.capacity, &CAPACITIES);
    let views = or_default(&args.views, &VIEWS);
    let all = [PrecisionArg::F32, PrecisionArg::F16, PrecisionArg::Int8];
    let precisions: Vec<Precision> = or_default(&args.precision, &all)
        .into_iter()
        .map(Precision::from)
        .collect();
    let storages = or_default(&args.sinkhorn, &[Sinkhorn::F32, Sinkhorn::F16]);
    let (blobs, model_source) = model_blobs(args.model.as_deref(), &precisions)?;
    let (map_bytes, map_source) = map_blob(args.map.as_deref())?;
    let map = Map::from_bytes(&map_bytes).map_err(|e| anyhow::anyhow!("map: {e}"))?;
    let progress = progress_bar(capacities.len() * views.len() * blobs.len() * storages.len())?;
    let mut rows = Vec::new();
    for &capacity in &capacities {
        let query = map_query(&map, capacity)?;
        for &k in &views {
            for (precision, blob) in &blobs {
                let model =
                    Model::from_bytes(blob).map_err(|e| anyhow::anyhow!("model blob: {e}"))?;
                let view_features = build_view_features(&model, &map, capacity)?.len();
                for &sinkhorn in &storages {
                    progress.set_message(format!(
                        "N={capacity} k={k} {} weights, {} Sinkhorn",
                        precision_name(*precision),
                        sinkhorn.name()
                    ));
                    let (ram, link, localization, usage) =
                        measure_capacity(capacity, sinkhorn, &model, &map, &query, k)?;
                    rows.push(Row {
                        capacity,
                        views: k,
                        precision: precision_name(*precision),
                        sinkhorn: sinkhorn.name(),
                        ram_bytes: ram,
                        stack_bytes: usage.stack_bytes,
                        heap_bytes: usage.heap_bytes,
                        flash_model_bytes: blob.len(),
                        flash_map_bytes: map_bytes.len(),
                        flash_view_features_bytes: view_features,
                        link_bytes: link,
                        keypoints: query.pixels.len(),
                        views_used: localization.views_used,
                    });
                    progress.inc(1);
                }
            }
        }
    }
    progress.finish_and_clear();
    Ok(Report {
        rows,
        model_source,
        map_source,
    })
}

/// The rows over a budget, one line each, naming the budget.
pub fn budget_violations(rows: &[Row], args: &Args) -> Vec<String> {
    let mut violations = Vec::new();
    for r in rows {
        let name = format!(
            "N={} k={} {} weights, {} Sinkhorn",
            r.capacity, r.views, r.precision, r.sinkhorn
        );
        let checks = [
            ("RAM", args.budget_ram, r.ram_bytes as u64),
            (
                "flash",
                args.budget_flash,
                (r.flash_model_bytes + r.flash_map_bytes) as u64,
            ),
            ("stack", args.budget_stack, r.stack_bytes as u64),
        ];
        for (what, budget, used) in checks {
            if let Some(budget) = budget.filter(|&b| used > b) {
                violations.push(format!(
                    "{name}: {what} {used} B exceeds the budget of {budget} B by {} B",
                    used - budget
                ));
            }
        }
    }
    violations
}

/// A byte count in B, KiB or MiB (binary units; the JSON keeps exact bytes).
pub fn human_bytes(bytes: u64) -> String {
    const KIB: f64 = 1024.0;
    let b = bytes as f64;
    if b >= KIB * KIB {
        format!("{:.2} MiB", b / (KIB * KIB))
    } else if b >= KIB {
        format!("{:.1} KiB", b / KIB)
    } else {
        format!("{bytes} B")
    }
}

/// The rows as a markdown table, sizes in B / KiB / MiB.
pub fn markdown(rows: &[Row]) -> String {
    let mut out = String::from(
        "| N | k | weights | Sinkhorn | RAM | stack | heap | flash model | flash map | flash view features (option) | link buffers |\n|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        let sizes = [
            r.ram_bytes as u64,
            r.stack_bytes as u64,
            r.heap_bytes,
            r.flash_model_bytes as u64,
            r.flash_map_bytes as u64,
            r.flash_view_features_bytes as u64,
            r.link_bytes as u64,
        ]
        .map(human_bytes)
        .join(" | ");
        out.push_str(&format!(
            "| {} | {} | {} | {} | {sizes} |\n",
            r.capacity, r.views, r.precision, r.sinkhorn,
        ));
    }
    out
}

/// Runs `gomatch-tools mem-report`.
pub fn run(args: &Args) -> Result<()> {
    let rows = if args.images_only {
        Vec::new()
    } else {
        let report = report(args)?;
        println!("model: {}", report.model_source);
        println!("map: {}", report.map_source);
        println!(
            "query: the map's most observed view re-projected (keypoints per row below in the JSON), views nearest its pose; stack = peak of localize + the pose solver on the true matches\n"
        );
        print!("{}", markdown(&report.rows));
        report.rows
    };
    let mut images = image_layout::built_images(&args.images)?;
    images.extend(image_layout::c_example_image(&args.c_image)?);
    if images.is_empty() {
        println!(
            "\nfirmware images: none linked under {} (bash firmware/build.sh; bash firmware/qemu.sh cortex-m7|aarch64)",
            args.images.display()
        );
    } else {
        println!(
            "\nfirmware images under {} and {} (bytes):\n\n{}",
            args.images.display(),
            args.c_image.display(),
            image_layout::markdown(&images)
        );
    }
    let capi_delta = image_layout::capi_flash_delta(&images);
    if let Some(delta) = capi_delta {
        println!(
            "C API: the C example takes {delta:+} B of flash against the Rust Cortex-M7 image"
        );
    }
    if let Some(path) = &args.json {
        let json = serde_json::json!({ "rows": rows, "images": images });
        std::fs::write(path, serde_json::to_string_pretty(&json)? + "\n")
            .with_context(|| format!("writing {}", path.display()))?;
    }
    let mut violations = budget_violations(&rows, args);
    if let Some(budget) = args.budget_capi_flash {
        match capi_delta {
            Some(delta) if delta > budget => violations.push(format!(
                "C API: the C example's image takes {delta} B of flash beyond the Rust image's, over the budget of {budget} B"
            )),
            Some(_) => {}
            None => violations.push(format!(
                "C API: no flash comparison without both Cortex-M7 images ({} and {}/thumbv7em-none-eabihf/release/gomatch-firmware)",
                args.c_image.display(),
                args.images.display()
            )),
        }
    }
    if !violations.is_empty() {
        for v in &violations {
            eprintln!("over budget: {v}");
        }
        bail!("{} over budget", violations.len());
    }
    Ok(())
}
