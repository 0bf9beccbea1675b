//! The bodies of the fuzz targets, shared by the libFuzzer targets (`fuzz/fuzz_targets/`)
//! and the stable replay test (`tests/tests/fuzz_replay.rs`), which includes this file
//! with `#[path]`. A body never panics on any input; where it checks a property (the
//! device answers after noise as a fresh device does, a built map reads back) it panics
//! when the property fails, which libFuzzer records as a crash.

use std::sync::{Mutex, OnceLock};

use gomatch::camera::CameraModel;
use gomatch::envelope::{self, HEADER_BYTES};
use gomatch::error::BlobKind;
use gomatch::link::{
    self, decode_frame, encode_frame, Device, LocalizeRequest, NoPin, Request, RequestBody,
    Response, Service, Views,
};
use gomatch::view_features::ViewFeatures;
use gomatch::weights::ModelConfig;
use gomatch::{Camera, Localizer, LocalizerConfig, Map, Model, Pose, Query, ViewSelection};
use gomatch_sim::scene::Scene;

/// Keypoint capacity of the localizer under test.
pub const CAPACITY: usize = 16;
const RX: usize = link::rx_frame_len(CAPACITY);
/// RANSAC samples per localization: few, so that an execution stays short (random
/// weights give no good matches, and the default 10,000 samples would dominate).
const RANSAC_ITERATIONS: u32 = 16;
/// The fixture's model: [`ModelConfig::TINY`] with few Sinkhorn iterations, which
/// otherwise take most of an execution.
const FUZZ_MODEL: ModelConfig = ModelConfig {
    sinkhorn_iters: 3,
    ..ModelConfig::TINY
};
/// Points of the fixture's map, each seen by both views.
pub const FIXTURE_POINTS: usize = 24;
/// Keypoints of the fixture's query (the `localize` target draws its own, up to
/// `CAPACITY + 2`).
const FIXTURE_KEYPOINTS: usize = 10;
/// Ids of the requests sent after the noise in [`device_link`].
const PROBE_IDS: [u32; 2] = [0xF00D_0001, 0xF00D_0002];

/// The body of a target: runs one input.
pub type Body = fn(&[u8]);

/// Every target: its name (a folder under `fuzz/seeds/` and `fuzz/regressions/`) and body.
pub const TARGETS: [(&str, Body); 10] = [
    ("model_blob", model_blob),
    ("map_blob", map_blob),
    ("view_features", view_features),
    ("device_link", device_link),
    ("colmap_bin", colmap_bin),
    ("colmap_txt", colmap_txt),
    ("bal", bal),
    ("bundler", bundler),
    ("opensfm", opensfm),
    ("localize", localize),
];

static LOCALIZER: Mutex<Localizer<CAPACITY>> = Mutex::new(Localizer::new());

/// The tiny model, map and query of `gomatch_sim::device::tiny`, and the replies of a fresh
/// device to the probe requests.
pub struct Fixture {
    /// Model blob.
    pub model: Vec<u8>,
    /// Map blob.
    pub map: Vec<u8>,
    /// Query camera.
    pub camera: Camera,
    /// Query pixels.
    pub pixels: Vec<[f32; 2]>,
    probe_frames: Vec<u8>,
    probe_replies: Vec<Response>,
}

/// The shared fixture, built once.
pub fn fixture() -> &'static Fixture {
    static FIXTURE: OnceLock<Fixture> = OnceLock::new();
    FIXTURE.get_or_init(|| {
        let model =
            gomatch_sim::device::tiny::random_model_blob(&FUZZ_MODEL, 5).expect("tiny model");
        let map = gomatch_sim::device::tiny::tiny_map_blob(FIXTURE_POINTS).expect("tiny map");
        let camera = gomatch_sim::device::tiny::tiny_camera().expect("tiny camera");
        let pixels = gomatch_sim::device::tiny::tiny_query(0.05, FIXTURE_KEYPOINTS);
        let probe_frames = probe_frames(camera, &pixels);
        let mut fixture = Fixture {
            model,
            map,
            camera,
            pixels,
            probe_frames,
            probe_replies: Vec::new(),
        };
        fixture.probe_replies = serve(&fixture, fixture.probe_frames.clone());
        assert_eq!(fixture.probe_replies.len(), PROBE_IDS.len());
        fixture
    })
}

/// `[0]` + frame of each probe request: the info and a localization near a prior (one
/// view, so that an execution stays short; the seeds carry a localization by image ids
/// in the noise).
fn probe_frames(camera: Camera, pixels: &[[f32; 2]]) -> Vec<u8> {
    let mut keypoints = vec![0u8; link::KEYPOINT_BYTES * pixels.len()];
    link::encode_keypoints(pixels, &mut keypoints).expect("fits");
    let prior = Pose::new(
        nalgebra::Rotation3::identity(),
        nalgebra::Vector3::new(-0.05, 0.0, 0.0),
    );
    let bodies = [
        RequestBody::Info,
        RequestBody::Localize(LocalizeRequest {
            camera,
            keypoints: &keypoints,
            views: Views::NearPrior {
                prior: link::WirePose::from(&prior),
                k: 1,
                max_angle_deg: 30.0,
            },
        }),
    ];
    let mut out = Vec::new();
    for (id, body) in PROBE_IDS.into_iter().zip(bodies) {
        let mut frame = vec![0u8; RX + 2];
        let len = encode_frame(&Request { id, body }, &mut frame[1..])
            .expect("fits")
            .len();
        out.extend_from_slice(&frame[..1 + len]);
    }
    out
}

/// A byte stream: reads `input` in odd-sized pieces, collects what is written.
struct Pipe {
    input: Vec<u8>,
    at: usize,
    output: Vec<u8>,
}

impl embedded_io::ErrorType for Pipe {
    type Error = std::convert::Infallible;
}

impl embedded_io::Read for Pipe {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        let n = buf.len().min(self.input.len() - self.at).min(37);
        buf[..n].copy_from_slice(&self.input[self.at..self.at + n]);
        self.at += n;
        Ok(n)
    }
}

impl embedded_io::Write for Pipe {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        self.output.extend_from_slice(buf);
        Ok(buf.len())
    }

    fn flush(&mut self) -> Result<(), Self::Error> {
        Ok(())
    }
}

/// A fresh device on the fixture serves `input`; its replies (each must decode).
fn serve(fixture: &Fixture, input: Vec<u8>) -> Vec<Response> {
    let mut localizer = LOCALIZER.lock().unwrap_or_else(|e| e.into_inner());
    let mut device = Box::new(Device::<CAPACITY, RX>::new());
    let mut service =
        Service::new(&mut localizer, &fixture.model, &fixture.map, NoPin).expect("valid blobs");
    service.config.ransac.max_iterations = RANSAC_ITERATIONS;
    let mut pipe = Pipe {
        input,
        at: 0,
        output: Vec::new(),
    };
    let Ok(()) = device.serve_until_closed(&mut pipe, &mut service) else {
        unreachable!("the pipe cannot fail")
    };
    pipe.output
        .split_mut(|&b| b == 0)
        .filter(|f| !f.is_empty())
        .map(|f| decode_frame::<Response>(f).expect("the device's replies decode"))
        .collect()
}

/// The device link: `data` as line noise, then the probe requests; the device answers
/// each probe exactly as a fresh device answers it alone.
pub fn device_link(data: &[u8]) {
    let fixture = fixture();
    let mut input = data.to_vec();
    input.extend_from_slice(&fixture.probe_frames);
    let replies = serve(fixture, input);
    for want in &fixture.probe_replies {
        // The last reply with the id: the noise may hold a valid frame with it too.
        let got = replies.iter().rev().find(|r| r.id == want.id);
        assert_eq!(got, Some(want), "after {} bytes of noise", data.len());
    }
}

/// Runs the fixture's query on `model` against `map` by both view selections.
fn forward(model: &Model<'_>, map: &Map<'_>, camera: Camera, pixels: &[[f32; 2]]) {
    let mut localizer = LOCALIZER.lock().unwrap_or_else(|e| e.into_inner());
    let query = Query {
        keypoints: pixels,
        camera,
    };
    let mut config = LocalizerConfig::new();
    config.ransac.max_iterations = RANSAC_ITERATIONS;
    let prior = Pose::new(
        nalgebra::Rotation3::identity(),
        nalgebra::Vector3::new(-0.05, 0.0, 0.0),
    );
    let selections = [
        ViewSelection::ImageIds(&[10, 20]),
        ViewSelection::NearPrior {
            prior,
            k: 3,
            max_angle_deg: 30.0,
        },
    ];
    for views in selections {
        let _ = localizer.localize(model, map, &query, views, &config, None);
    }
}

/// Repairs the envelope of a fuzzed blob (`gomatch::envelope`) as the mode byte asks, so
/// that mutations reach the decoder: bit 0 writes a valid magic, version and reserved
/// field, bit 1 the payload length, bit 2 the CRC-32 of the payload.
fn repair_envelope(kind: BlobKind, mode: u8, blob: &mut [u8]) {
    let Some(payload) = blob.len().checked_sub(HEADER_BYTES) else {
        return;
    };
    if mode & 1 != 0 {
        blob[..4].copy_from_slice(&envelope::magic(kind));
        blob[4..6].copy_from_slice(&envelope::version(kind).to_le_bytes());
        blob[6..8].fill(0);
    }
    if mode & 2 != 0 {
        let len = u32::try_from(payload).unwrap_or(u32::MAX);
        blob[8..12].copy_from_slice(&len.to_le_bytes());
    }
    if mode & 4 != 0 {
        let crc = envelope::crc32(&blob[HEADER_BYTES..]);
        blob[12..16].copy_from_slice(&crc.to_le_bytes());
    }
}

/// The blob after the first (mode) byte, its envelope repaired as that byte asks.
fn repaired(kind: BlobKind, data: &[u8]) -> Option<Vec<u8>> {
    let (&mode, blob) = data.split_first()?;
    let mut blob = blob.to_vec();
    repair_envelope(kind, mode, &mut blob);
    Some(blob)
}

/// The model blob, its envelope repaired as the first byte asks ([`repair_envelope`]);
/// when the blob decodes, a localization runs on it (the forward pass).
pub fn model_blob(data: &[u8]) {
    let Some(blob) = repaired(BlobKind::Model, data) else {
        return;
    };
    let Ok(model) = Model::from_bytes(&blob) else {
        return;
    };
    let fixture = fixture();
    let map = Map::from_bytes(&fixture.map).expect("tiny map");
    forward(&model, &map, fixture.camera, &fixture.pixels);
}

/// The map blob, its envelope repaired as the first byte asks ([`repair_envelope`]); when
/// the blob decodes, every accessor runs on every index, and a localization.
pub fn map_blob(data: &[u8]) {
    let Some(blob) = repaired(BlobKind::Map, data) else {
        return;
    };
    let Ok(map) = Map::from_bytes(&blob) else {
        return;
    };
    visit_map(&map);
    let fixture = fixture();
    let model = Model::from_bytes(&fixture.model).expect("tiny model");
    forward(&model, &map, fixture.camera, &fixture.pixels);
}

/// The view-features blob, its envelope repaired as the first byte asks
/// ([`repair_envelope`]); when it decodes, it is attached to the fixture's map and every
/// view's features are read (and one view past the end).
pub fn view_features(data: &[u8]) {
    let Some(blob) = repaired(BlobKind::ViewFeatures, data) else {
        return;
    };
    let Ok(features) = ViewFeatures::from_bytes(&blob) else {
        return;
    };
    let mut values = vec![0.0f32; 128 * CAPACITY];
    for view in 0..=features.view_count() {
        if let Some(rows) = features.view(view) {
            rows.copy_to(&mut values);
        }
    }
    let map = Map::from_bytes(&fixture().map).expect("tiny map");
    let _ = map.with_view_features(features);
}

/// Every accessor of `map` on every index (and one past the end).
fn visit_map(map: &Map<'_>) {
    let _ = map.observation_count();
    for i in 0..=map.point_count() {
        let _ = map.point(i);
    }
    for i in 0..=map.camera_count() {
        let _ = map.camera(i);
    }
    let mut image_ids = Vec::new();
    for i in 0..=map.view_count() {
        if let Ok(view) = map.view(i) {
            image_ids.push(view.image_id);
            let _ = map.camera(view.camera_index as usize);
        }
        if let Ok(points) = map.view_points(i) {
            for j in 0..=points.len() {
                let _ = points.get(j);
            }
            for p in points.iter() {
                let _ = map.point(p as usize);
            }
        }
    }
    image_ids.push(u32::MAX);
    for ids in image_ids.chunks(10) {
        let _ = map.views_by_image_id::<10>(ids);
    }
    let _ = map.views_by_image_id::<2>(&image_ids);
    let prior = Pose::new(nalgebra::Rotation3::identity(), nalgebra::Vector3::zeros());
    for angle in [0.0, 30.0, 180.0, f64::NAN] {
        let _ = map.views_near::<10>(&prior, angle);
    }
}

/// Splits `data` into `N` files at the `N - 1` little-endian `u16` lengths it starts with
/// (the last file takes the rest).
fn files<const N: usize>(data: &[u8]) -> Option<[&[u8]; N]> {
    let (lens, mut rest) = data.split_at_checked(2 * (N - 1))?;
    let mut out = [&[][..]; N];
    for (file, len) in out.iter_mut().zip(lens.chunks_exact(2)) {
        let len = usize::from(u16::from_le_bytes([len[0], len[1]]));
        (*file, rest) = rest.split_at(len.min(rest.len()));
    }
    out[N - 1] = rest;
    Some(out)
}

/// A scene read by a reader: validated, built into a map, and the map read back (it
/// must: the builder writes only maps the reader accepts).
fn check_scene(scene: &Scene) {
    if scene.validate().is_err() {
        return;
    }
    let Ok(blob) = gomatch_sim::map::build_map(scene) else {
        return;
    };
    let map = Map::from_bytes(&blob).expect("a built map reads back");
    visit_map(&map);
}

/// The COLMAP binary readers: `cameras.bin`, `images.bin`, `points3D.bin` split by
/// [`files`]; a scene of all three is checked.
pub fn colmap_bin(data: &[u8]) {
    use gomatch_sim::readers::colmap::{parse_cameras_bin, parse_images_bin, parse_points_bin};
    let Some([cameras, images, points]) = files(data) else {
        return;
    };
    let (Ok(cameras), Ok(images), Ok(points)) = (
        parse_cameras_bin(cameras),
        parse_images_bin(images),
        parse_points_bin(points),
    ) else {
        return;
    };
    check_scene(&Scene {
        name: "fuzz".into(),
        cameras,
        images,
        points,
    });
}

/// The COLMAP text readers, as [`colmap_bin`] (invalid UTF-8 is replaced first).
pub fn colmap_txt(data: &[u8]) {
    use gomatch_sim::readers::colmap::{parse_cameras_txt, parse_images_txt, parse_points_txt};
    let Some([cameras, images, points]) = files(data) else {
        return;
    };
    let text = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
    let (Ok(cameras), Ok(images), Ok(points)) = (
        parse_cameras_txt(&text(cameras)),
        parse_images_txt(&text(images)),
        parse_points_txt(&text(points)),
    ) else {
        return;
    };
    check_scene(&Scene {
        name: "fuzz".into(),
        cameras,
        images,
        points,
    });
}

/// The BAL reader; a scene it reads is checked.
pub fn bal(data: &[u8]) {
    let text = String::from_utf8_lossy(data);
    if let Ok(scene) = gomatch_sim::readers::bal::parse_bal(&text, "fuzz".into()) {
        check_scene(&scene);
    }
}

/// The Bundler reader; a scene it reads is checked.
pub fn bundler(data: &[u8]) {
    let text = String::from_utf8_lossy(data);
    if let Ok(scene) = gomatch_sim::readers::bundler::parse_bundler(&text, "fuzz".into()) {
        check_scene(&scene);
    }
}

/// The OpenSfM reader: `reconstruction.json` and `tracks.csv` split by [`files`] (invalid
/// UTF-8 is replaced first); a scene it reads is checked.
pub fn opensfm(data: &[u8]) {
    let Some([json, csv]) = files(data) else {
        return;
    };
    let text = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
    if let Ok(scene) =
        gomatch_sim::readers::opensfm::parse_opensfm(&text(json), &text(csv), "fuzz".into())
    {
        check_scene(&scene);
    }
}

/// Reads fixed-size values from the front of a byte string (zeros once it is used up).
struct Bytes<'a>(&'a [u8]);

impl Bytes<'_> {
    fn take<const K: usize>(&mut self) -> [u8; K] {
        let mut out = [0u8; K];
        let n = K.min(self.0.len());
        out[..n].copy_from_slice(&self.0[..n]);
        self.0 = &self.0[n..];
        out
    }

    fn u8(&mut self) -> u8 {
        self.take::<1>()[0]
    }

    fn u16(&mut self) -> u16 {
        u16::from_le_bytes(self.take())
    }

    fn f64(&mut self) -> f64 {
        f64::from_le_bytes(self.take())
    }

    fn u64(&mut self) -> u64 {
        u64::from_le_bytes(self.take())
    }
}

/// `localize` with an arbitrary camera, configuration, view selection and keypoints
/// (up to two more than the capacity) on the tiny map and model.
pub fn localize(data: &[u8]) {
    let fixture = fixture();
    let mut bytes = Bytes(data);
    let models = gomatch::camera::MODELS;
    let camera_model: CameraModel = models[usize::from(bytes.u8()) % models.len()].model;
    let (width, height) = (u32::from(bytes.u16()), u32::from(bytes.u16()));
    let params: Vec<f64> = (0..camera_model.param_count())
        .map(|_| bytes.f64())
        .collect();
    let camera =
        Camera::from_colmap(camera_model, width, height, &params).unwrap_or(fixture.camera);
    let mut config = LocalizerConfig::new();
    config.ransac.max_iterations = u32::from(bytes.u16() % 2048);
    config.ransac.threshold = bytes.f64();
    config.ransac.confidence = bytes.f64();
    config.ransac.seed = bytes.u64();
    let flags = bytes.u8();
    config.ransac.local_optimization = flags & 1 != 0;
    config.ransac.refine = flags & 2 != 0;
    config.min_matches = usize::from(bytes.u8());
    config.min_inliers = usize::from(bytes.u8());
    let selector = bytes.u8();
    let ids: Vec<u32> = (0..selector % 13)
        .map(|i| {
            if bytes.u8() % 2 == 0 {
                [10, 20][i as usize % 2]
            } else {
                u32::from(bytes.u16())
            }
        })
        .collect();
    let rotation: [f64; 9] = std::array::from_fn(|_| bytes.f64());
    let translation: [f64; 3] = std::array::from_fn(|_| bytes.f64());
    let prior = Pose::new(
        nalgebra::Rotation3::from_matrix_unchecked(nalgebra::Matrix3::from_row_slice(&rotation)),
        nalgebra::Vector3::from(translation),
    );
    let views = if selector & 0x80 == 0 {
        ViewSelection::ImageIds(&ids)
    } else {
        ViewSelection::NearPrior {
            prior,
            k: usize::from(selector % 13),
            max_angle_deg: bytes.f64(),
        }
    };
    let keypoints: Vec<[f32; 2]> = bytes
        .0
        .chunks_exact(8)
        .take(CAPACITY + 2)
        .map(|c| {
            let x = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
            let y = f32::from_le_bytes([c[4], c[5], c[6], c[7]]);
            [x, y]
        })
        .collect();
    let model = Model::from_bytes(&fixture.model).expect("tiny model");
    let map = Map::from_bytes(&fixture.map).expect("tiny map");
    let query = Query {
        keypoints: &keypoints,
        camera,
    };
    let mut localizer = LOCALIZER.lock().unwrap_or_else(|e| e.into_inner());
    let _ = localizer.localize(&model, &map, &query, views, &config, None);
}
