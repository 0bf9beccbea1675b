//! The device link over a faulty line: a UART that drops, flips, duplicates and
//! truncates bytes and splits reads at seeded random positions. [`soak`] sends many
//! requests through it with the retrying [`HostLink`] to a device thread running the
//! core's [`Device`] loop, and checks every reply the host accepts against a direct call.
//!
//! The host's timeout is the line going quiet: it fires when the device waits for input
//! with nothing left to read and no reply bytes are in flight, so no reply can still come.
//! That makes a timeout exact (never too early on a slow machine) and the run the same on
//! every machine; a wait for the line that lasts [`HANG_LIMIT`] of real time is a hang.

use std::collections::VecDeque;
use std::convert::Infallible;
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;

use anyhow::bail;
use gomatch::link::{
    self, Device, LocalizeRequest, RequestBody, ResponseBody, Service, Views, WirePose,
};
use gomatch::{Localizer, LocalizerConfig, Map, Model, Pose, Query, ViewSelection};
use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64Mcg;

use crate::device::tiny::{
    tiny_camera, tiny_map_blob, tiny_model_blob, tiny_query, TINY_POINTS, TINY_VIEWS,
};
use crate::device::{HostLink, LinkStats, Received, RequestError, RetryPolicy, Transport};

/// Keypoint capacity of the soak's device.
pub const SOAK_CAPACITY: usize = 64;
const RX: usize = link::rx_frame_len(SOAK_CAPACITY);
/// Real time a host waits for the line to move or go quiet before calling it a hang.
pub const HANG_LIMIT: Duration = Duration::from_secs(60);
/// Most bytes one read returns (reads are split at random below it).
const MAX_READ: usize = 64;

static DEVICE_LOCALIZER: Mutex<Localizer<SOAK_CAPACITY>> = Mutex::new(Localizer::new());
static DEVICE: Mutex<Device<SOAK_CAPACITY, RX>> = Mutex::new(Device::new());
static DIRECT_LOCALIZER: Mutex<Localizer<SOAK_CAPACITY>> = Mutex::new(Localizer::new());

/// What the line does to one write.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fault {
    /// One byte lost.
    Drop,
    /// One bit changed.
    Flip,
    /// A run of bytes received twice.
    Duplicate,
    /// The write cut off at a random position.
    Truncate,
    /// The whole write lost.
    Lose,
    /// A random byte inserted.
    Insert,
}

const FAULTS: [Fault; 6] = [
    Fault::Drop,
    Fault::Flip,
    Fault::Duplicate,
    Fault::Truncate,
    Fault::Lose,
    Fault::Insert,
];

/// Faults applied to one direction of the line, by kind (in `FAULTS` order).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FaultCounts(pub [u64; 6]);

impl FaultCounts {
    /// All faults.
    pub fn total(&self) -> u64 {
        self.0.iter().sum()
    }
}

/// One direction of the line: its seeded generators and what it did. Faults and read
/// sizes draw from separate generators: the writes come in a fixed order, the reads
/// depend on thread timing, and only the read sizes may.
struct Direction {
    rng: Pcg64Mcg,
    split_rng: Pcg64Mcg,
    rate: f64,
    faults: FaultCounts,
}

impl Direction {
    /// With probability `rate`, one random fault at a random position of `bytes`.
    fn corrupt(&mut self, bytes: &[u8]) -> Vec<u8> {
        let mut out = bytes.to_vec();
        if out.is_empty() || !self.rng.random_bool(self.rate) {
            return out;
        }
        let kind = self.rng.random_range(0..FAULTS.len());
        self.faults.0[kind] += 1;
        let at = self.rng.random_range(0..out.len());
        match FAULTS[kind] {
            Fault::Drop => {
                out.remove(at);
            }
            Fault::Flip => out[at] ^= 1 << self.rng.random_range(0..8),
            Fault::Duplicate => {
                let end = self.rng.random_range(at..out.len()) + 1;
                let run = out[at..end].to_vec();
                out.splice(end..end, run);
            }
            Fault::Truncate => out.truncate(at),
            Fault::Lose => out.clear(),
            Fault::Insert => out.insert(at, self.rng.random()),
        }
        out
    }

    /// A read size in `1..=max`.
    fn split(&mut self, max: usize) -> usize {
        self.split_rng.random_range(1..=max.max(1))
    }
}

/// The line's state, shared by both ends.
struct Line {
    to_device: VecDeque<u8>,
    to_host: VecDeque<u8>,
    host_to_device: Direction,
    device_to_host: Direction,
    /// The device is blocked in a read with nothing to read.
    device_waiting: bool,
    host_closed: bool,
}

struct Shared {
    line: Mutex<Line>,
    changed: Condvar,
}

impl Shared {
    fn lock(&self) -> std::sync::MutexGuard<'_, Line> {
        self.line.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// The host's end of a faulty line.
pub struct FaultyHostEnd(Arc<Shared>);

/// The device's end of a faulty line ([`embedded_io`]).
pub struct FaultyDeviceEnd(Arc<Shared>);

/// A line corrupting a write with probability `rate` in each direction, seeded.
pub fn faulty_line(seed: u64, rate: f64) -> (FaultyHostEnd, FaultyDeviceEnd) {
    let direction = |stream: u64| Direction {
        rng: Pcg64Mcg::seed_from_u64(seed.wrapping_mul(4).wrapping_add(stream)),
        split_rng: Pcg64Mcg::seed_from_u64(seed.wrapping_mul(4).wrapping_add(stream + 2)),
        rate,
        faults: FaultCounts::default(),
    };
    let shared = Arc::new(Shared {
        line: Mutex::new(Line {
            to_device: VecDeque::new(),
            to_host: VecDeque::new(),
            host_to_device: direction(0),
            device_to_host: direction(1),
            device_waiting: false,
            host_closed: false,
        }),
        changed: Condvar::new(),
    });
    (FaultyHostEnd(shared.clone()), FaultyDeviceEnd(shared))
}

impl FaultyHostEnd {
    /// Faults applied so far: host to device, device to host.
    pub fn faults(&self) -> (FaultCounts, FaultCounts) {
        let line = self.0.lock();
        (line.host_to_device.faults, line.device_to_host.faults)
    }
}

impl Transport for FaultyHostEnd {
    fn send(&mut self, bytes: &[u8]) -> anyhow::Result<()> {
        let mut line = self.0.lock();
        let sent = line.host_to_device.corrupt(bytes);
        line.to_device.extend(sent);
        self.0.changed.notify_all();
        Ok(())
    }

    /// Bytes when there are some; a timeout once the line is quiet (the `timeout`
    /// argument is not used: see the module documentation).
    fn receive(&mut self, buf: &mut [u8], _timeout: Duration) -> anyhow::Result<Received> {
        let mut line = self.0.lock();
        loop {
            if !line.to_host.is_empty() {
                let available = buf.len().min(line.to_host.len());
                let n = line.device_to_host.split(available);
                for (slot, byte) in buf.iter_mut().zip(line.to_host.drain(..n)) {
                    *slot = byte;
                }
                return Ok(Received::Bytes(n));
            }
            if line.device_waiting && line.to_device.is_empty() {
                return Ok(Received::TimedOut);
            }
            let (next, wait) = self
                .0
                .changed
                .wait_timeout(line, HANG_LIMIT)
                .unwrap_or_else(|e| e.into_inner());
            line = next;
            if wait.timed_out() {
                bail!("hang: the line neither moved nor went quiet for {HANG_LIMIT:?}");
            }
        }
    }
}

impl Drop for FaultyHostEnd {
    fn drop(&mut self) {
        self.0.lock().host_closed = true;
        self.0.changed.notify_all();
    }
}

impl embedded_io::ErrorType for FaultyDeviceEnd {
    type Error = Infallible;
}

impl embedded_io::Read for FaultyDeviceEnd {
    /// Blocks until bytes arrive (a random number of them, at most `buf.len()`); 0 once
    /// the host end is gone.
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Infallible> {
        let mut line = self.0.lock();
        while line.to_device.is_empty() && !line.host_closed && !buf.is_empty() {
            line.device_waiting = true;
            self.0.changed.notify_all();
            line = self.0.changed.wait(line).unwrap_or_else(|e| e.into_inner());
        }
        line.device_waiting = false;
        let available = buf.len().min(line.to_device.len()).min(MAX_READ);
        let n = if available == 0 {
            0
        } else {
            line.host_to_device.split(available)
        };
        for (slot, byte) in buf.iter_mut().zip(line.to_device.drain(..n)) {
            *slot = byte;
        }
        Ok(n)
    }
}

impl embedded_io::Write for FaultyDeviceEnd {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Infallible> {
        let mut line = self.0.lock();
        let sent = line.device_to_host.corrupt(buf);
        line.to_host.extend(sent);
        self.0.changed.notify_all();
        Ok(buf.len())
    }

    fn flush(&mut self) -> Result<(), Infallible> {
        Ok(())
    }
}

/// Settings of a soak run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SoakConfig {
    /// Requests to send.
    pub requests: usize,
    /// Every this many requests is a localization (the others ask for the info).
    pub localize_every: usize,
    /// Probability that the line corrupts one write, per direction.
    pub fault_rate: f64,
    /// Seed of the faults.
    pub seed: u64,
    /// Attempts per request.
    pub attempts: u32,
}

/// What a soak run saw.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SoakReport {
    /// Requests answered with a reply equal to the direct call.
    pub correct: u64,
    /// Replies accepted that differ from the direct call (must be 0).
    pub wrong: u64,
    /// Requests given up after every attempt timed out (reported, not hung).
    pub gave_up: u64,
    /// The host's view of the link.
    pub stats: LinkStats,
    /// Faults the line applied, host to device.
    pub faults_to_device: FaultCounts,
    /// Faults the line applied, device to host.
    pub faults_to_host: FaultCounts,
}

/// The four localization requests of a soak: query pixels from four positions, by
/// image ids or near a prior.
fn soak_queries() -> Vec<(Vec<[f32; 2]>, Views)> {
    (0..4)
        .map(|i| {
            let x = -0.2 + 0.1 * f64::from(i);
            let views = if i % 2 == 0 {
                Views::ImageIds(heapless::Vec::from_slice(&TINY_VIEWS).unwrap_or_default())
            } else {
                let prior = Pose::new(
                    nalgebra::Rotation3::identity(),
                    nalgebra::Vector3::new(-x, 0.0, 0.0),
                );
                Views::NearPrior {
                    prior: WirePose::from(&prior),
                    k: 2,
                    max_angle_deg: 30.0,
                }
            };
            (tiny_query(x, SOAK_CAPACITY - 4 * i as usize), views)
        })
        .collect()
}

/// Runs a soak: a device thread serving the tiny map and model on a faulty line, the
/// host sending `config.requests` requests through a [`HostLink`]; each accepted reply
/// is compared with a direct call.
pub fn soak(config: &SoakConfig) -> anyhow::Result<SoakReport> {
    let model_blob = tiny_model_blob(5)?;
    let map_blob = tiny_map_blob(TINY_POINTS)?;
    let camera = tiny_camera()?;
    let queries = soak_queries();
    let keypoint_bytes: Vec<Vec<u8>> = queries
        .iter()
        .map(|(pixels, _)| {
            let mut bytes = vec![0u8; link::KEYPOINT_BYTES * pixels.len()];
            link::encode_keypoints(pixels, &mut bytes);
            bytes
        })
        .collect();
    let expected = expected_replies(&model_blob, &map_blob, camera, &queries)?;
    let (host_end, mut device_end) = faulty_line(config.seed, config.fault_rate);
    std::thread::scope(|scope| {
        let device = scope.spawn(|| -> anyhow::Result<()> {
            let mut localizer = DEVICE_LOCALIZER.lock().unwrap_or_else(|e| e.into_inner());
            let mut device = DEVICE.lock().unwrap_or_else(|e| e.into_inner());
            *device = Device::new();
            let mut service = Service::new(&mut localizer, &model_blob, &map_blob, link::NoPin)
                .map_err(|e| anyhow::anyhow!("device start: {e}"))?;
            device
                .serve_until_closed(&mut device_end, &mut service)
                .map_err(|e| anyhow::anyhow!("device link: {e:?}"))
        });
        let policy = RetryPolicy {
            timeout: HANG_LIMIT,
            attempts: config.attempts,
        };
        let mut host = HostLink::new(host_end, policy);
        let mut report = SoakReport {
            correct: 0,
            wrong: 0,
            gave_up: 0,
            stats: LinkStats::default(),
            faults_to_device: FaultCounts::default(),
            faults_to_host: FaultCounts::default(),
        };
        let mut failure = None;
        for r in 0..config.requests {
            let (body, want) = if r % config.localize_every.max(1) == 0 {
                let q = (r / config.localize_every.max(1)) % queries.len();
                let body = RequestBody::Localize(LocalizeRequest {
                    camera,
                    keypoints: &keypoint_bytes[q],
                    views: queries[q].1.clone(),
                });
                (body, &expected[1 + q])
            } else {
                (RequestBody::Info, &expected[0])
            };
            match host.request(body) {
                Ok(exchange) if exchange.response.body == *want => report.correct += 1,
                Ok(_) => report.wrong += 1,
                Err(RequestError::NoReply { .. }) => report.gave_up += 1,
                Err(e) => {
                    failure = Some(e);
                    break;
                }
            }
        }
        report.stats = host.stats();
        (report.faults_to_device, report.faults_to_host) = host.transport().faults();
        drop(host);
        device
            .join()
            .map_err(|_| anyhow::anyhow!("device panicked"))??;
        if let Some(e) = failure {
            bail!("soak stopped: {e}");
        }
        Ok(report)
    })
}

/// The replies a fresh device gives on a clean line, by direct calls: the info, then one
/// per query.
fn expected_replies(
    model_blob: &[u8],
    map_blob: &[u8],
    camera: gomatch::Camera,
    queries: &[(Vec<[f32; 2]>, Views)],
) -> anyhow::Result<Vec<ResponseBody>> {
    let mut localizer = DIRECT_LOCALIZER.lock().unwrap_or_else(|e| e.into_inner());
    let info = {
        let service = Service::new(&mut localizer, model_blob, map_blob, link::NoPin)
            .map_err(|e| anyhow::anyhow!("blobs: {e}"))?;
        service.info(RX)
    };
    let model = Model::from_bytes(model_blob).map_err(|e| anyhow::anyhow!("model: {e}"))?;
    let map = Map::from_bytes(map_blob).map_err(|e| anyhow::anyhow!("map: {e}"))?;
    let mut replies = vec![ResponseBody::Info(info)];
    for (pixels, views) in queries {
        let query = Query {
            keypoints: pixels,
            camera,
        };
        let selection = match views {
            Views::ImageIds(ids) => ViewSelection::ImageIds(ids),
            Views::NearPrior {
                prior,
                k,
                max_angle_deg,
            } => ViewSelection::NearPrior {
                prior: prior.to_pose().map_err(|e| anyhow::anyhow!("prior: {e}"))?,
                k: usize::from(*k),
                max_angle_deg: *max_angle_deg,
            },
        };
        let result = localizer
            .localize(
                &model,
                &map,
                &query,
                selection,
                &LocalizerConfig::new(),
                None,
            )
            .map_err(|e| anyhow::anyhow!("direct localize: {e}"))?;
        replies.push(ResponseBody::Localized(link::LocalizeReply::from(&result)));
    }
    Ok(replies)
}

/// Prints a report, one line per figure.
pub fn print_report(config: &SoakConfig, report: &SoakReport, seconds: f64) {
    let s = &report.stats;
    let names = FAULTS.map(|f| format!("{f:?}").to_lowercase());
    let faults = |c: &FaultCounts| {
        names
            .iter()
            .zip(c.0)
            .map(|(n, v)| format!("{n} {v}"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    println!(
        "soak: {} requests (1 in {} a localization), fault rate {} per write and direction, seed {}, {} attempts, {seconds:.1} s",
        config.requests, config.localize_every, config.fault_rate, config.seed, config.attempts
    );
    println!(
        "faults host->device: {} ({}); device->host: {} ({})",
        report.faults_to_device.total(),
        faults(&report.faults_to_device),
        report.faults_to_host.total(),
        faults(&report.faults_to_host)
    );
    println!(
        "replies: {} correct, {} wrong, {} given up; {} frames sent, {} timeouts (retried), {} corrupt reply frames, {} device error replies, {} stale replies dropped",
        report.correct, report.wrong, report.gave_up, s.attempts, s.timeouts,
        s.corrupt_replies, s.device_errors, s.stale_replies
    );
}
