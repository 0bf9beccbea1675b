//! `gomatch-sim device`: the device link ([`gomatch::link`]) end to end in one process.
//! The device loop runs in its own thread on its `static` workspace and buffers, exactly
//! as on a microcontroller; the host talks to it through an in-process pipe (two ring
//! buffers implementing [`embedded_io::Read`] + [`embedded_io::Write`]). The host asks
//! for the device info, optionally sends noise (to show the receiver resynchronising),
//! sends the queries of a synthetic scene and checks every reply against a direct
//! [`Localizer::localize`] call on the same input.
//!
//! Beside it: [`faulty_link`] runs the link over a lossy line, [`tiny`] builds the tiny
//! scene, map and model its soak and the fuzz targets use, and [`firmware_data`] and
//! [`firmware_reply`] write the firmware image's embedded data and the host's reply to it.

pub mod faulty_link;
pub mod firmware_data;
pub mod firmware_reply;
pub mod tiny;

use std::collections::VecDeque;
use std::convert::Infallible;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use clap::Parser;
use gomatch::link::{
    self, Device, DeviceInfo, LinkError, LocalizeReply, LocalizeRequest, Request, RequestBody,
    Response, ResponseBody, Service, Views,
};
use gomatch::localizer::MAX_VIEWS;
use gomatch::weights::Precision;
use gomatch::{Camera, Localizer, LocalizerConfig, Map, Model, Pose, Query, ViewSelection};
use half::f16;
use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64Mcg;

use crate::eval::{protocol_samples, query_pixels};
use crate::host::{default_model_path, HostClock, CAPACITY};
use crate::map::build_map;
use crate::protocol::synthetic::SyntheticQueries;
use crate::protocol::QuerySample;

/// Receive buffer of the simulated device.
const RX: usize = link::rx_frame_len(CAPACITY);

static DEVICE_LOCALIZER: Mutex<Localizer<CAPACITY, f16>> = Mutex::new(Localizer::new());
static DEVICE: Mutex<Device<CAPACITY, RX>> = Mutex::new(Device::new());
static DIRECT_LOCALIZER: Mutex<Localizer<CAPACITY, f16>> = Mutex::new(Localizer::new());

/// Drive a simulated localizer device over its link with a synthetic scene's queries.
#[derive(Debug, Clone, Parser)]
pub struct Args {
    /// Model blob (default: `models/gomatch-int8.bin`, searched upwards, else the reference fixture
    /// weights converted to int8).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// The scene and the queries to send.
    #[command(flatten)]
    pub synthetic: SyntheticQueries,
    /// Random bytes sent before the first request (the device must resynchronise).
    #[arg(long, default_value_t = 1000)]
    pub noise: usize,
}

/// One end of an in-process byte pipe.
pub struct PipeEnd {
    incoming: Arc<Channel>,
    outgoing: Arc<Channel>,
}

/// One direction of a pipe: a ring buffer, and whether its writer is gone.
#[derive(Default)]
struct Channel {
    state: Mutex<(VecDeque<u8>, bool)>,
    ready: Condvar,
}

/// Two connected ends: what one writes, the other reads.
pub fn pipe() -> (PipeEnd, PipeEnd) {
    let (a, b) = (Arc::new(Channel::default()), Arc::new(Channel::default()));
    (
        PipeEnd {
            incoming: a.clone(),
            outgoing: b.clone(),
        },
        PipeEnd {
            incoming: b,
            outgoing: a,
        },
    )
}

impl embedded_io::ErrorType for PipeEnd {
    type Error = Infallible;
}

impl embedded_io::Read for PipeEnd {
    /// Blocks until a byte arrives; 0 once the other end is dropped and all is read.
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Infallible> {
        let mut state = self
            .incoming
            .state
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        while state.0.is_empty() && !state.1 && !buf.is_empty() {
            state = self
                .incoming
                .ready
                .wait(state)
                .unwrap_or_else(|e| e.into_inner());
        }
        let n = buf.len().min(state.0.len());
        for (slot, byte) in buf.iter_mut().zip(state.0.drain(..n)) {
            *slot = byte;
        }
        Ok(n)
    }
}

impl embedded_io::Write for PipeEnd {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Infallible> {
        let mut state = self
            .outgoing
            .state
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        state.0.extend(buf);
        self.outgoing.ready.notify_all();
        Ok(buf.len())
    }

    fn flush(&mut self) -> Result<(), Infallible> {
        Ok(())
    }
}

impl Drop for PipeEnd {
    fn drop(&mut self) {
        let mut state = self
            .outgoing
            .state
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        state.1 = true;
        self.outgoing.ready.notify_all();
    }
}

/// The device's busy pin as a host sees it: its level and how often it rose.
#[derive(Debug, Default)]
pub struct BusyLine {
    high: AtomicBool,
    rises: AtomicUsize,
}

impl embedded_hal::digital::ErrorType for &BusyLine {
    type Error = Infallible;
}

impl embedded_hal::digital::OutputPin for &BusyLine {
    fn set_low(&mut self) -> Result<(), Infallible> {
        self.high.store(false, Ordering::SeqCst);
        Ok(())
    }

    fn set_high(&mut self) -> Result<(), Infallible> {
        if !self.high.swap(true, Ordering::SeqCst) {
            self.rises.fetch_add(1, Ordering::SeqCst);
        }
        Ok(())
    }
}

/// What a host read from the link within its timeout.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Received {
    /// This many bytes arrived.
    Bytes(usize),
    /// Nothing arrived in time.
    TimedOut,
    /// The device end is gone.
    Closed,
}

/// The byte stream as a host sees it: writes, and reads that give up after a timeout.
pub trait Transport {
    /// Writes all of `bytes`.
    fn send(&mut self, bytes: &[u8]) -> anyhow::Result<()>;
    /// Reads what arrives into `buf`, waiting at most `timeout` for the first byte.
    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> anyhow::Result<Received>;
}

impl Transport for PipeEnd {
    fn send(&mut self, bytes: &[u8]) -> anyhow::Result<()> {
        let Ok(()) = embedded_io::Write::write_all(self, bytes);
        Ok(())
    }

    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> anyhow::Result<Received> {
        let state = self
            .incoming
            .state
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        let (mut state, _) = self
            .incoming
            .ready
            .wait_timeout_while(state, timeout, |(bytes, closed)| {
                bytes.is_empty() && !*closed
            })
            .unwrap_or_else(|e| e.into_inner());
        if state.0.is_empty() {
            return Ok(if state.1 {
                Received::Closed
            } else {
                Received::TimedOut
            });
        }
        let n = buf.len().min(state.0.len());
        for (slot, byte) in buf.iter_mut().zip(state.0.drain(..n)) {
            *slot = byte;
        }
        Ok(Received::Bytes(n))
    }
}

/// How long a host waits for a reply, and how often it sends a request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RetryPolicy {
    /// Longest wait for the reply to one attempt (longer than the device's slowest
    /// localization).
    pub timeout: Duration,
    /// Attempts per request, the first included.
    pub attempts: u32,
}

impl Default for RetryPolicy {
    /// 120 s (a `Localizer<1024>` query takes about 1 s on an idle host, many times that
    /// on a loaded one), 3 attempts.
    fn default() -> Self {
        RetryPolicy {
            timeout: Duration::from_secs(120),
            attempts: 3,
        }
    }
}

/// What the host saw on the link, over all requests.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LinkStats {
    /// Requests asked.
    pub requests: u64,
    /// Request frames sent (requests plus retries).
    pub attempts: u64,
    /// Attempts that got no valid reply in time (each one retried or reported).
    pub timeouts: u64,
    /// Reply frames that failed their checksum or did not decode.
    pub corrupt_replies: u64,
    /// Error replies without an id: the device got a broken frame.
    pub device_errors: u64,
    /// Valid replies to an earlier request (a duplicate or a late answer), dropped.
    pub stale_replies: u64,
}

/// Why a request got no reply.
#[derive(Debug, thiserror::Error)]
pub enum RequestError {
    /// Every attempt timed out.
    #[error("request {id}: no valid reply after {attempts} attempts")]
    NoReply {
        /// The request's id.
        id: u32,
        /// Attempts made.
        attempts: u32,
    },
    /// The request does not fit a frame.
    #[error("request larger than the device's frame")]
    TooLarge,
    /// The device end closed.
    #[error("the device closed the link")]
    Closed,
    /// The transport failed.
    #[error("link transport: {0}")]
    Transport(anyhow::Error),
}

/// The host end of the link: sends each request with a fresh id, accepts only a reply
/// frame whose checksum holds and whose id is the request's, and sends the request again
/// when none arrived within the timeout. A reply is never matched to the wrong request
/// and no call blocks longer than `attempts * timeout`.
pub struct HostLink<T> {
    transport: T,
    policy: RetryPolicy,
    next_id: u32,
    pending: Vec<u8>,
    stats: LinkStats,
}

/// A reply and what came before it.
#[derive(Debug, Clone, PartialEq)]
pub struct Exchange {
    /// The reply to the request.
    pub response: Response,
    /// Error replies to earlier, broken frames received before it.
    pub refused: Vec<LinkError>,
    /// Bytes of the request frame.
    pub request_bytes: usize,
    /// Attempts it took (1 without a loss).
    pub attempts: u32,
    /// First send to reply.
    pub round_trip: Duration,
}

impl<T: Transport> HostLink<T> {
    /// A host on `transport`; request ids start at 1.
    pub fn new(transport: T, policy: RetryPolicy) -> Self {
        Self {
            transport,
            policy,
            next_id: 1,
            pending: Vec::new(),
            stats: LinkStats::default(),
        }
    }

    /// What the host saw so far.
    pub fn stats(&self) -> LinkStats {
        self.stats
    }

    /// The transport under the link.
    pub fn transport(&self) -> &T {
        &self.transport
    }

    /// Writes raw bytes (e.g. line noise).
    pub fn send_raw(&mut self, bytes: &[u8]) -> anyhow::Result<()> {
        self.transport.send(bytes)
    }

    /// Sends `[0]` (closing any broken frame before it) and the request's frame, then
    /// reads replies until the one with the request's id; sends again after a timeout,
    /// up to the policy's attempts.
    pub fn request(&mut self, body: RequestBody<'_>) -> Result<Exchange, RequestError> {
        let id = self.next_id;
        self.next_id = self.next_id.wrapping_add(1);
        self.stats.requests += 1;
        let request = Request { id, body };
        let mut frame = vec![0u8; 1 + link::rx_frame_len(CAPACITY) + 1];
        let len = link::encode_frame(&request, &mut frame[1..])
            .ok_or(RequestError::TooLarge)?
            .len();
        frame.truncate(1 + len);
        let start = Instant::now();
        let mut refused = Vec::new();
        for attempt in 1..=self.policy.attempts {
            self.stats.attempts += 1;
            self.transport
                .send(&frame)
                .map_err(RequestError::Transport)?;
            if let Some(response) = self.await_reply(id, &mut refused)? {
                return Ok(Exchange {
                    response,
                    refused,
                    request_bytes: frame.len(),
                    attempts: attempt,
                    round_trip: start.elapsed(),
                });
            }
            self.stats.timeouts += 1;
        }
        Err(RequestError::NoReply {
            id,
            attempts: self.policy.attempts,
        })
    }

    /// Reads reply frames until the one of request `id` (`None` after the timeout, when
    /// the bytes of a partial frame are dropped).
    fn await_reply(
        &mut self,
        id: u32,
        refused: &mut Vec<LinkError>,
    ) -> Result<Option<Response>, RequestError> {
        let deadline = Instant::now() + self.policy.timeout;
        loop {
            while let Some(end) = self.pending.iter().position(|&b| b == 0) {
                let mut frame: Vec<u8> = self.pending.drain(..=end).collect();
                if end == 0 {
                    continue;
                }
                match link::decode_frame::<Response>(&mut frame) {
                    Ok(response) if response.id == Some(id) => return Ok(Some(response)),
                    Ok(Response {
                        id: None,
                        body: ResponseBody::Error(error),
                    }) => {
                        self.stats.device_errors += 1;
                        refused.push(error);
                    }
                    Ok(_) => self.stats.stale_replies += 1,
                    Err(_) => self.stats.corrupt_replies += 1,
                }
            }
            let left = deadline.saturating_duration_since(Instant::now());
            let mut chunk = [0u8; 256];
            match self
                .transport
                .receive(&mut chunk, left)
                .map_err(RequestError::Transport)?
            {
                Received::Bytes(n) => self.pending.extend_from_slice(&chunk[..n]),
                Received::TimedOut => {
                    self.pending.clear();
                    return Ok(None);
                }
                Received::Closed => return Err(RequestError::Closed),
            }
        }
    }
}

/// One query for the device.
#[derive(Debug, Clone, PartialEq)]
pub struct LinkQuery {
    /// Keypoint pixels.
    pub pixels: Vec<[f32; 2]>,
    /// The query camera.
    pub camera: Camera,
    /// Image ids of the views to match.
    pub view_ids: Vec<u32>,
    /// True pose, for the report.
    pub truth: Pose,
}

impl LinkQuery {
    /// The query of a protocol sample: its keypoint pixels, camera, views and true pose.
    pub fn from_sample(sample: &QuerySample) -> Self {
        LinkQuery {
            pixels: query_pixels(sample),
            camera: sample.camera,
            view_ids: sample.views.iter().map(|v| v.image_id).collect(),
            truth: sample.pose,
        }
    }

    /// The request body (`keypoint_bytes` holds the wire keypoints).
    pub fn request<'a>(&self, keypoint_bytes: &'a mut Vec<u8>) -> anyhow::Result<RequestBody<'a>> {
        keypoint_bytes.resize(link::KEYPOINT_BYTES * self.pixels.len(), 0);
        let keypoints =
            link::encode_keypoints(&self.pixels, keypoint_bytes).context("keypoint buffer")?;
        let ids = heapless::Vec::from_slice(&self.view_ids)
            .map_err(|_| anyhow::anyhow!("more than {MAX_VIEWS} views"))?;
        Ok(RequestBody::Localize(LocalizeRequest {
            camera: self.camera,
            keypoints,
            views: Views::ImageIds(ids),
        }))
    }

    /// The same query run directly on a localizer (no clock), as the device's reply.
    pub fn direct(&self, model: &Model<'_>, map: &Map<'_>) -> anyhow::Result<LocalizeReply> {
        let mut localizer = DIRECT_LOCALIZER.lock().unwrap_or_else(|e| e.into_inner());
        let query = Query {
            keypoints: &self.pixels,
            camera: self.camera,
        };
        let views = ViewSelection::ImageIds(&self.view_ids);
        let result = localizer
            .localize(model, map, &query, views, &LocalizerConfig::new(), None)
            .map_err(|e| anyhow::anyhow!("direct localize: {e}"))?;
        Ok(LocalizeReply::from(&result))
    }
}

/// What a session saw.
#[derive(Debug, Clone, PartialEq)]
pub struct Session {
    /// The device's answer to the info request.
    pub info: DeviceInfo,
    /// One exchange per query, in order.
    pub exchanges: Vec<Exchange>,
    /// Times the busy pin rose.
    pub busy_pulses: usize,
}

/// Runs a device thread on the blobs, and on the host side: an info request, `noise`
/// sent raw, then one localization request per query. The device stops when the host
/// closes the pipe.
pub fn run_session(
    model_blob: &[u8],
    map_blob: &[u8],
    noise: &[u8],
    queries: &[LinkQuery],
) -> anyhow::Result<Session> {
    let (host_end, mut device_end) = pipe();
    let busy = BusyLine::default();
    let clock = HostClock::default();
    std::thread::scope(|scope| {
        let device = scope.spawn(|| -> anyhow::Result<()> {
            let mut localizer = DEVICE_LOCALIZER.lock().unwrap_or_else(|e| e.into_inner());
            let mut device = DEVICE.lock().unwrap_or_else(|e| e.into_inner());
            let service = Service::new(&mut localizer, model_blob, map_blob, &busy);
            let mut service = service
                .map_err(|e| anyhow::anyhow!("device start: {e}"))?
                .with_clock(&clock);
            let served = device.serve_until_closed(&mut device_end, &mut service);
            served.map_err(|e| anyhow::anyhow!("device link: {e:?}"))
        });
        let mut host = HostLink::new(host_end, RetryPolicy::default());
        let session = host_session(&mut host, noise, queries);
        drop(host);
        let device = device
            .join()
            .map_err(|_| anyhow::anyhow!("device panicked"))?;
        let (info, exchanges) = session?;
        device?;
        Ok(Session {
            info,
            exchanges,
            busy_pulses: busy.rises.load(Ordering::SeqCst),
        })
    })
}

fn host_session(
    host: &mut HostLink<PipeEnd>,
    noise: &[u8],
    queries: &[LinkQuery],
) -> anyhow::Result<(DeviceInfo, Vec<Exchange>)> {
    let info = match host.request(RequestBody::Info)?.response.body {
        ResponseBody::Info(info) => info,
        other => bail!("info request answered with {other:?}"),
    };
    host.send_raw(noise)?;
    let mut exchanges = Vec::new();
    let mut keypoint_bytes = Vec::new();
    for query in queries {
        exchanges.push(host.request(query.request(&mut keypoint_bytes)?)?);
    }
    Ok((info, exchanges))
}

/// The model blob to serve: `--model`, else the shipped int8 model, else the reference
/// fixture weights converted to int8; with a description of which.
pub fn load_model(path: Option<&Path>) -> anyhow::Result<(Vec<u8>, String)> {
    let shipped = default_model_path();
    let path = path
        .map(Path::to_path_buf)
        .or_else(|| shipped.is_file().then_some(shipped));
    if let Some(path) = path {
        let blob = gomatch_blobs::files::read_model_blob(&path)?;
        return Ok((blob, path.display().to_string()));
    }
    let fixture = fixture_weights_path();
    let checkpoint = std::fs::read(&fixture).with_context(|| {
        format!(
            "no model: neither models/gomatch-int8.bin nor {} exists; pass --model",
            fixture.display()
        )
    })?;
    let (blob, _) = gomatch_blobs::convert::convert(&checkpoint, Precision::Int8)?;
    let what = format!(
        "{} converted to int8 (random reference fixture weights: poses will be wrong)",
        fixture.display()
    );
    Ok((blob, what))
}

/// The reference fixture weights, `shared/reference/fixtures/weights.safetensors` beside the
/// repository, found from the current folder or the executable's
/// ([`gomatch_blobs::files::find_default`]).
pub fn fixture_weights_path() -> PathBuf {
    const FIXTURE: &str = "shared/reference/fixtures/weights.safetensors";
    gomatch_blobs::files::find_default(FIXTURE).unwrap_or_else(|| PathBuf::from("..").join(FIXTURE))
}

/// Runs `gomatch-sim device`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let (model_blob, model_name) = load_model(args.model.as_deref())?;
    let model = Model::from_bytes(&model_blob).map_err(|e| anyhow::anyhow!("model: {e}"))?;
    let scene = args.synthetic.scene();
    let map_blob = build_map(&scene)?;
    let map = Map::from_bytes(&map_blob).map_err(|e| anyhow::anyhow!("map: {e}"))?;
    let params = args.synthetic.protocol(CAPACITY);
    let queries: Vec<LinkQuery> = protocol_samples(&scene, &params)
        .iter()
        .map(LinkQuery::from_sample)
        .collect();
    let mut rng = Pcg64Mcg::seed_from_u64(args.synthetic.seed);
    let noise: Vec<u8> = (0..args.noise).map(|_| rng.random()).collect();
    println!("model: {model_name}");
    println!(
        "device: Localizer<{CAPACITY}, f16> ({} B) + Device<{CAPACITY}, {RX}> link buffers ({} B), static",
        Localizer::<CAPACITY, f16>::BYTES,
        Device::<CAPACITY, RX>::BYTES
    );
    let session = run_session(&model_blob, &map_blob, &noise, &queries)?;
    let i = &session.info;
    println!(
        "info: protocol {}, capacity {}, Sinkhorn {} B/value, workspace {} B, rx frame {} B; model v{} {:?} {} B (d = {}); map v{} {} points, {} views, {} B",
        i.protocol_version, i.capacity, i.sinkhorn_bytes, i.workspace_bytes, i.rx_frame_bytes,
        i.model.format_version, i.model.precision, i.model.bytes, i.model.config.feature_dim,
        i.map.format_version, i.map.points, i.map.views, i.map.bytes
    );
    let mut mismatches = 0;
    for (q, (query, exchange)) in queries.iter().zip(&session.exchanges).enumerate() {
        if !exchange.refused.is_empty() {
            println!(
                "  (before query {q}: {} error replies to the noise: {:?})",
                exchange.refused.len(),
                exchange.refused
            );
        }
        let direct = query.direct(&model, &map)?;
        let ResponseBody::Localized(reply) = &exchange.response.body else {
            println!("query {q}: refused: {:?}", exchange.response.body);
            mismatches += 1;
            continue;
        };
        let identical = LocalizeReply {
            timings: None,
            ..*reply
        } == direct;
        mismatches += usize::from(!identical);
        let outcome = match reply.outcome.map(|p| p.to_pose()) {
            Ok(Ok(pose)) => format!(
                "pose: rotation error {:.3} deg, translation error {:.4}",
                pose.rotation_error_deg(&query.truth),
                pose.translation_error(&query.truth)
            ),
            Ok(Err(e)) => format!("pose not finite: {e}"),
            Err(failure) => format!("not localized: {failure}"),
        };
        let c = &reply.counts;
        println!(
            "query {q}: {} keypoints, {} views, request {} B, round trip {:.1} ms (device total {:.1} ms); matches {} mutual / {} classified / {} merged / {} inliers; {outcome}; identical to a direct localize call: {}",
            query.pixels.len(),
            query.view_ids.len(),
            exchange.request_bytes,
            exchange.round_trip.as_secs_f64() * 1e3,
            reply.timings.map_or(0.0, |t| t.total_us as f64 / 1e3),
            c.mutual, c.classified, c.merged, c.inliers,
            if identical { "yes" } else { "NO" }
        );
    }
    println!("busy pin pulses: {}", session.busy_pulses);
    if mismatches > 0 {
        bail!("{mismatches} replies differ from direct localize calls");
    }
    Ok(())
}
