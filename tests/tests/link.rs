//! The device link end to end: `gomatch-sim device`'s device thread serves the synthetic
//! scene's queries over an in-process pipe, after line noise, and every reply equals a
//! direct `localize` call; the retrying host over a line that drops, flips, duplicates and
//! truncates bytes accepts only correct replies and never hangs (a soak; the 100,000
//! request run is ignored by default); `firmware-data` regenerates the firmware image's
//! committed files byte for byte, and the host's reply to them (timings cleared) is the
//! committed `firmware/data/reply.hex` that the firmware images on x86_64, Cortex-M7 and
//! AArch64 must print (`firmware/cross_isa.sh`). Localization on the synthetic scene needs the reference
//! fixture weights (SKIPPED without `shared/`).

use std::path::Path;

use gomatch::link::{self, LinkError, LocalizeReply, Request, RequestBody, ResponseBody};
use gomatch::weights::Precision;
use gomatch::{Localizer, Map, Model};
use gomatch_blobs::convert::{convert_with, Options};
use gomatch_sim::device::faulty_link::{print_report, soak, SoakConfig, SoakReport};
use gomatch_sim::device::firmware_data::{firmware_data, FIRMWARE_CAPACITY, FIRMWARE_SEED};
use gomatch_sim::device::firmware_reply::{
    firmware_reply_from_files, reply_lines, AARCH64_CAPACITY,
};
use gomatch_sim::device::{run_session, LinkQuery};
use gomatch_sim::eval::protocol_samples;
use gomatch_sim::host::CAPACITY;
use gomatch_sim::map::build_map;
use gomatch_sim::protocol::synthetic::synthetic_scene;
use gomatch_sim::protocol::ProtocolParams;
use half::f16;

fn fixture_model() -> Option<Vec<u8>> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/reference/fixtures/weights.safetensors");
    let Ok(checkpoint) = std::fs::read(&path) else {
        println!("SKIPPED: {} is absent", path.display());
        return None;
    };
    // Rounded to nearest: these tests need an int8 model, not a calibrated one
    // (`conformance.rs` checks the calibrated conversion).
    let options = Options::rounded_to_nearest(Precision::Int8);
    Some(convert_with(&checkpoint, &options).expect("converts").0)
}

/// Noise (every byte value, a long run without zeros, stray delimiters), then two
/// queries: the device reports the noise as errors, answers both queries exactly like a
/// direct call, raises its busy pin once per query, and describes its model and map.
#[test]
fn device_replies_equal_direct_calls_after_noise() {
    let Some(model_blob) = fixture_model() else {
        return;
    };
    let scene = synthetic_scene(0, 0);
    let map_blob = build_map(&scene).expect("map");
    let params = ProtocolParams {
        k: 2,
        queries_per_scene: 2,
        max_keypoints: 300,
        max_points: CAPACITY,
        ..ProtocolParams::default()
    };
    let queries: Vec<LinkQuery> = protocol_samples(&scene, &params)
        .iter()
        .map(LinkQuery::from_sample)
        .collect();
    assert_eq!(queries.len(), 2);
    let mut noise: Vec<u8> = (0..=255u8).collect();
    noise.extend(std::iter::repeat_n(
        0x55,
        link::rx_frame_len(CAPACITY) + 100,
    ));
    noise.extend([0, 0, 0x05, 0x01, 0]);

    let session = run_session(&model_blob, &map_blob, &noise, &queries).expect("session");

    let info = session.info;
    assert_eq!(info.protocol_version, link::PROTOCOL_VERSION);
    assert_eq!(info.capacity as usize, CAPACITY);
    assert_eq!(info.sinkhorn_bytes, 2);
    assert_eq!(
        info.workspace_bytes as usize,
        Localizer::<CAPACITY, f16>::BYTES
    );
    assert_eq!(info.rx_frame_bytes as usize, link::rx_frame_len(CAPACITY));
    assert_eq!(info.model.precision, Precision::Int8);
    assert_eq!(info.model.bytes as usize, model_blob.len());
    assert_eq!(info.map.bytes as usize, map_blob.len());
    let map = Map::from_bytes(&map_blob).expect("map");
    assert_eq!(info.map.points as usize, map.point_count());
    assert_eq!(info.map.views as usize, map.view_count());

    // The noise: a frame of bytes 1..=255 cut by the first zero, an oversized run, an
    // undecodable frame; empty frames are ignored.
    let refused = &session.exchanges[0].refused;
    assert!(refused.contains(&LinkError::Oversized {
        limit: link::rx_frame_len(CAPACITY) as u32
    }));
    assert!(refused.len() >= 2, "{refused:?}");
    assert!(session.exchanges[1].refused.is_empty());

    let model = Model::from_bytes(&model_blob).expect("model");
    for (query, exchange) in queries.iter().zip(&session.exchanges) {
        let ResponseBody::Localized(reply) = &exchange.response.body else {
            panic!("{:?}", exchange.response);
        };
        assert!(reply.timings.is_some(), "the device has a clock");
        let direct = query.direct(&model, &map).expect("direct");
        assert_eq!(
            LocalizeReply {
                timings: None,
                ..*reply
            },
            direct
        );
        assert!(reply.views_used > 0 && reply.counts.mutual > 0);
        assert!(exchange.request_bytes > link::KEYPOINT_BYTES * query.pixels.len());
    }
    assert_eq!(session.busy_pulses, queries.len());
}

/// `gomatch-sim firmware-data` reproduces the committed files; they decode to a request
/// the firmware's capacity accepts, and the map is small.
#[test]
fn firmware_data_regenerates_the_committed_files() {
    let data = firmware_data(FIRMWARE_SEED, 0, 10).expect("firmware data");
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../firmware/data");
    let read = |name: &str| std::fs::read(dir.join(name)).expect("committed file");
    assert_eq!(data.map, read("map.bin"));
    assert_eq!(data.query_frame, read("query.frame"));
    assert_eq!(data.truth, read("truth.bin"));
    assert!(data.map.len() < 100 * 1024);

    let map = Map::from_bytes(&data.map).expect("valid map");
    assert_eq!(map.view_count(), 10);
    let mut frame = data.query_frame.clone();
    assert_eq!(frame.last(), Some(&0));
    assert!(frame.len() - 1 <= link::rx_frame_len(FIRMWARE_CAPACITY));
    let request: Request<'_> = link::decode_frame(&mut frame).expect("decodes");
    let RequestBody::Localize(localize) = request.body else {
        panic!("not a localization request");
    };
    let mut keypoints = [[0.0f32; 2]; FIRMWARE_CAPACITY];
    let n = link::decode_keypoints(localize.keypoints, &mut keypoints).expect("fits");
    assert_eq!(n, data.sample.keypoints.len());
    assert_eq!(localize.camera, data.sample.camera);
    assert_eq!(data.truth.len(), 13 * 8);
}

/// The host's reply to the firmware's embedded request, with the shipped int8 model and
/// `f16` Sinkhorn storage, and the digest of its merged correspondences, are the committed
/// files byte for byte at both capacities the images use (256: Cortex-M7 and x86_64,
/// `firmware/data/reply.hex`; 1024: AArch64, `firmware/data/reply-1024.hex`: each capacity
/// has its own acceptance rule, so the confidence differs), and it localizes.
#[test]
fn firmware_reply_matches_the_committed_hex() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let data = root.join("firmware/data");
    let model = root.join("models/gomatch-int8.bin");
    for (capacity, file) in [
        (FIRMWARE_CAPACITY, "reply.hex"),
        (AARCH64_CAPACITY, "reply-1024.hex"),
    ] {
        let committed = std::fs::read_to_string(data.join(file)).expect(file);
        let reply = firmware_reply_from_files(&data, &model, capacity).expect("served");
        assert_eq!(reply_lines(&reply), committed, "capacity {capacity}");
        let (response, []) =
            postcard::take_from_bytes::<link::Response>(&reply.bytes).expect("decodes")
        else {
            panic!("trailing bytes");
        };
        let ResponseBody::Localized(reply) = response.body else {
            panic!("not a localization reply: {:?}", response.body);
        };
        assert!(reply.outcome.is_ok() && reply.timings.is_none());
    }
}

/// Runs a soak and checks what the link guarantees: every accepted reply equals the
/// direct call, every request is answered, every lost or corrupted exchange was detected
/// (a timeout) and retried, and a loss happens only where the line applied a fault.
fn soak_and_check(config: &SoakConfig) -> SoakReport {
    let start = std::time::Instant::now();
    let report = soak(config).expect("the soak finishes (no hang)");
    print_report(config, &report, start.elapsed().as_secs_f64());
    let stats = report.stats;
    let requests = config.requests as u64;
    assert_eq!(report.wrong, 0, "wrong replies accepted");
    assert_eq!(report.gave_up, 0, "requests given up");
    assert_eq!(report.correct, requests);
    assert_eq!(stats.requests, requests);
    assert_eq!(
        stats.attempts,
        requests + stats.timeouts,
        "every timeout retried"
    );
    let faults = report.faults_to_device.total() + report.faults_to_host.total();
    assert!(
        stats.timeouts <= faults,
        "a loss without a fault: {stats:?}"
    );
    report
}

/// 3,000 requests (1 in 20 a localization), one write in ten corrupted per direction.
#[test]
fn faulty_line_accepts_only_correct_replies() {
    let report = soak_and_check(&SoakConfig {
        requests: 3000,
        localize_every: 20,
        fault_rate: 0.1,
        seed: 1,
        attempts: 16,
    });
    let faults = report.faults_to_device.total() + report.faults_to_host.total();
    assert!(faults > 300, "{report:?}");
    assert!(report.faults_to_device.0.iter().all(|&n| n > 0));
    assert!(report.faults_to_host.0.iter().all(|&n| n > 0));
    assert!(report.stats.timeouts > 0 && report.stats.corrupt_replies > 0);
    assert!(report.stats.device_errors > 0 && report.stats.stale_replies > 0);
}

/// On a clean line nothing is lost or retried.
#[test]
fn clean_line_needs_no_retry() {
    let report = soak_and_check(&SoakConfig {
        requests: 500,
        localize_every: 10,
        fault_rate: 0.0,
        seed: 1,
        attempts: 1,
    });
    assert_eq!(report.stats.attempts, 500);
    assert_eq!(report.stats.timeouts, 0);
    assert_eq!(report.stats.corrupt_replies + report.stats.device_errors, 0);
}

/// The full soak: 100,000 requests (1 in 20 a localization), one write in ten corrupted
/// per direction. `cargo test --release -p gomatch-integration --test link -- --ignored
/// --nocapture soak_100k`.
#[test]
#[ignore = "the full soak takes minutes"]
fn soak_100k() {
    soak_and_check(&SoakConfig {
        requests: 100_000,
        localize_every: 20,
        fault_rate: 0.1,
        seed: 2026,
        attempts: 16,
    });
}
