//! The device link end to end: `gomatch-sim device`'s device thread serves the synthetic
//! scene's queries over an in-process pipe, after line noise, and every reply equals a
//! direct `localize` call; `firmware-data` regenerates the firmware image's committed
//! files byte for byte. Localization needs the reference fixture weights (SKIPPED
//! without `shared/`).

use std::path::Path;

use gomatch::link::{self, LinkError, LocalizeReply, Request, RequestBody, ResponseBody};
use gomatch::weights::Precision;
use gomatch::{Localizer, Map, Model};
use gomatch_sim::device::{run_session, LinkQuery};
use gomatch_sim::eval::{protocol_samples, CAPACITY};
use gomatch_sim::firmware_data::{firmware_data, FIRMWARE_CAPACITY, FIRMWARE_SEED};
use gomatch_sim::map::build_map;
use gomatch_sim::protocol::ProtocolParams;
use gomatch_sim::synthetic::synthetic_scene;
use half::f16;

fn fixture_model() -> Option<Vec<u8>> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/reference/fixtures/weights.safetensors");
    let Ok(checkpoint) = std::fs::read(&path) else {
        println!("SKIPPED: {} is absent", path.display());
        return None;
    };
    Some(
        gomatch_tools::convert::convert(&checkpoint, Precision::Int8)
            .expect("converts")
            .0,
    )
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
