//! `gomatch-tools mem-report`: the stack painter and heap counter measure what they claim,
//! the rows agree with the types' sizes and the blobs, and the memory goals hold. The
//! rows that localize need the reference fixture weights (SKIPPED without `shared/`).

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use gomatch::link::{rx_frame_len, Device};
use gomatch::view_features::blob_len;
use gomatch::weights::Precision;
use gomatch::Localizer;
use gomatch_blobs::convert::{convert_with, Options, PrecisionArg};
use gomatch_blobs::view_features::view_bearings;
use gomatch_tools::mem_report::{
    budget_violations, human_bytes, markdown, measure, report, Args, CountingAllocator, Row,
    Sinkhorn, BUILTIN_MAP,
};
use half::f16;

#[global_allocator]
static ALLOCATOR: CountingAllocator = CountingAllocator;

fn fixture_weights() -> Option<PathBuf> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/reference/fixtures/weights.safetensors");
    if path.is_file() {
        Some(path)
    } else {
        println!("SKIPPED: {} is absent", path.display());
        None
    }
}

/// The fixture weights as an int8 blob file, rounded to nearest (memory does not depend
/// on the rounding, and the calibrated conversion takes about 40 s), once per test
/// process.
fn fixture_int8() -> Option<&'static (PathBuf, Vec<u8>)> {
    static BLOB: OnceLock<Option<(PathBuf, Vec<u8>)>> = OnceLock::new();
    BLOB.get_or_init(|| {
        let checkpoint = std::fs::read(fixture_weights()?).expect("reads");
        let options = Options::rounded_to_nearest(Precision::Int8);
        let (blob, _) = convert_with(&checkpoint, &options).expect("converts");
        let path = Path::new(env!("CARGO_TARGET_TMPDIR")).join("mem-report-fixture-int8.bin");
        std::fs::write(&path, &blob).expect("writes");
        Some((path, blob))
    })
    .as_ref()
}

fn args(capacity: &[usize], views: &[usize], sinkhorn: &[Sinkhorn], model: PathBuf) -> Args {
    Args {
        capacity: capacity.to_vec(),
        views: views.to_vec(),
        precision: vec![PrecisionArg::Int8],
        sinkhorn: sinkhorn.to_vec(),
        budget_ram: None,
        budget_flash: None,
        budget_stack: None,
        model: Some(model),
        map: None,
        json: None,
        images: PathBuf::from("firmware/target"),
        c_image: PathBuf::from("capi/example/build/gomatch-c-example.elf"),
        budget_capi_flash: None,
        images_only: false,
    }
}

#[test]
fn the_stack_painter_finds_a_known_frame_and_the_heap_counter_counts() {
    const FRAME: usize = 100_000;
    let (sum, usage) = measure(|| {
        let mut frame = [1u8; FRAME];
        std::hint::black_box(&mut frame);
        frame.iter().map(|&b| u64::from(b)).sum::<u64>()
    })
    .expect("measures");
    assert_eq!(sum, FRAME as u64);
    assert!(
        usage.stack_bytes >= FRAME && usage.stack_bytes < FRAME + 16 * 1024,
        "{usage:?}"
    );
    assert_eq!((usage.heap_bytes, usage.heap_allocations), (0, 0));

    let (_, usage) = measure(|| std::hint::black_box(vec![7u8; 5000]).len()).expect("measures");
    assert_eq!(usage.heap_allocations, 1);
    assert_eq!(usage.heap_bytes, 5000);
}

/// Rows for two capacities, both Sinkhorn storages: RAM is `Localizer::<N, S>::BYTES`,
/// link buffers `Device::<N, rx_frame_len(N)>::BYTES`, flash the converted blob and the
/// built-in map, the heap untouched.
#[test]
fn rows_agree_with_the_types_and_the_blobs() {
    let Some((blob, int8)) = fixture_int8() else {
        return;
    };
    let report = report(&args(
        &[128, 256],
        &[1],
        &[Sinkhorn::F32, Sinkhorn::F16],
        blob.clone(),
    ))
    .expect("report");
    let map = std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("../firmware/data/map.bin"))
        .expect("firmware map");
    assert_eq!(BUILTIN_MAP, &map[..]);
    // The measured query is the map's most observed view, at most `N` of its points.
    let decoded = gomatch::Map::from_bytes(&map).expect("map decodes");
    let largest_view = (0..decoded.view_count())
        .map(|i| decoded.view_points(i).expect("view").len())
        .max()
        .expect("views");
    let expected = [
        (
            128,
            "f32",
            Localizer::<128, f32>::BYTES,
            Device::<128, { rx_frame_len(128) }>::BYTES,
        ),
        (
            128,
            "f16",
            Localizer::<128, f16>::BYTES,
            Device::<128, { rx_frame_len(128) }>::BYTES,
        ),
        (
            256,
            "f32",
            Localizer::<256, f32>::BYTES,
            Device::<256, { rx_frame_len(256) }>::BYTES,
        ),
        (
            256,
            "f16",
            Localizer::<256, f16>::BYTES,
            Device::<256, { rx_frame_len(256) }>::BYTES,
        ),
    ];
    assert_eq!(report.rows.len(), expected.len());
    for (row, (n, sinkhorn, ram, link)) in report.rows.iter().zip(expected) {
        assert_eq!(
            (row.capacity, row.views, row.precision, row.sinkhorn),
            (n, 1, "int8", sinkhorn)
        );
        assert_eq!((row.ram_bytes, row.link_bytes), (ram, link));
        assert_eq!(row.flash_model_bytes, int8.len());
        assert_eq!(row.flash_map_bytes, map.len());
        // Each view's first N points with a bearing (or none below the matcher's minimum),
        // d = 128 f32 values each, and the blob's header and table.
        let parsed = gomatch::Map::from_bytes(&map).expect("map");
        let counts: Vec<usize> = (0..parsed.view_count())
            .map(|v| view_bearings(&parsed, v, n).expect("view").len())
            .map(|c| {
                if c < gomatch::matcher::MIN_KEYPOINTS {
                    0
                } else {
                    c
                }
            })
            .collect();
        assert_eq!(row.flash_view_features_bytes, blob_len(128, &counts));
        assert_eq!(row.heap_bytes, 0);
        assert!(
            row.stack_bytes > 4096 && row.stack_bytes < 64 * 1024,
            "{row:?}"
        );
        assert_eq!((row.keypoints, row.views_used), (n.min(largest_view), 1));
    }
    let table = markdown(&report.rows);
    assert_eq!(table.lines().count(), 2 + expected.len());
    let json = serde_json::to_value(&report.rows[0]).expect("serialises");
    for key in [
        "capacity",
        "views",
        "precision",
        "sinkhorn",
        "ram_bytes",
        "stack_bytes",
        "heap_bytes",
        "flash_model_bytes",
        "flash_map_bytes",
        "flash_view_features_bytes",
    ] {
        assert!(json.get(key).is_some(), "{key} missing");
    }
}

/// The goals: at 1024 keypoints, 10 views, int8 weights and f16 Sinkhorn, RAM <= 6 MiB,
/// stack <= 64 KiB, model flash <= 1.5 MiB; at 256 keypoints, RAM <= 1 MiB.
#[test]
fn memory_goals_hold() {
    let Some((blob, _)) = fixture_int8() else {
        return;
    };
    let report =
        report(&args(&[256, 1024], &[10], &[Sinkhorn::F16], blob.clone())).expect("report");
    let [small, large] = &report.rows[..] else {
        panic!("{:?}", report.rows);
    };
    assert_eq!((small.capacity, large.capacity), (256, 1024));
    assert!(small.ram_bytes <= 1 << 20, "{small:?}");
    assert!(large.ram_bytes <= 6 << 20, "{large:?}");
    assert!(large.stack_bytes <= 64 << 10, "{large:?}");
    assert!(large.flash_model_bytes <= 3 << 19, "{large:?}");
    assert_eq!((large.views_used, large.heap_bytes), (10, 0));
}

/// A value given twice is measured once: no duplicate rows.
#[test]
fn repeated_values_give_one_row() {
    let Some((blob, _)) = fixture_int8() else {
        return;
    };
    let report = report(&args(
        &[128, 128],
        &[1, 1],
        &[Sinkhorn::F16, Sinkhorn::F16],
        blob.clone(),
    ))
    .expect("report");
    assert_eq!(report.rows.len(), 1, "{:?}", report.rows);
}

#[test]
fn sizes_print_in_binary_units() {
    assert_eq!(human_bytes(512), "512 B");
    assert_eq!(human_bytes(33_167), "32.4 KiB");
    assert_eq!(human_bytes(6 << 20), "6.00 MiB");
    let row = Row {
        capacity: 1024,
        views: 10,
        precision: "int8",
        sinkhorn: "f16",
        ram_bytes: 5_000_000,
        stack_bytes: 12_000,
        heap_bytes: 0,
        flash_model_bytes: 1_178_845,
        flash_map_bytes: 33_167,
        flash_view_features_bytes: 800_000,
        link_bytes: 20_000,
        keypoints: 1024,
        views_used: 10,
    };
    let table = markdown(&[row]);
    assert!(
        table.contains("| 1024 | 10 | int8 | f16 | 4.77 MiB | 11.7 KiB | 0 B | 1.12 MiB | 32.4 KiB | 781.2 KiB | 19.5 KiB |"),
        "{table}"
    );
}

#[test]
fn budgets_name_the_rows_over_them() {
    let row = |capacity, sinkhorn, ram_bytes| Row {
        capacity,
        views: 10,
        precision: "int8",
        sinkhorn,
        ram_bytes,
        stack_bytes: 12_000,
        heap_bytes: 0,
        flash_model_bytes: 1_178_845,
        flash_map_bytes: 33_167,
        flash_view_features_bytes: 800_000,
        link_bytes: 0,
        keypoints: capacity,
        views_used: 10,
    };
    let rows = [row(256, "f16", 1_045_840), row(256, "f32", 1_158_000)];
    let mut budget = args(&[], &[], &[], PathBuf::new());
    budget.budget_ram = Some(1 << 20);
    assert_eq!(
        budget_violations(&rows, &budget),
        ["N=256 k=10 int8 weights, f32 Sinkhorn: RAM 1158000 B exceeds the budget of 1048576 B by 109424 B"]
    );
    budget.budget_flash = Some(1_200_000);
    budget.budget_stack = Some(12_000);
    let violations = budget_violations(&rows, &budget);
    assert_eq!(violations.len(), 3, "{violations:?}");
    assert!(violations[0].contains("flash 1212012 B exceeds the budget of 1200000 B by 12012 B"));
}
