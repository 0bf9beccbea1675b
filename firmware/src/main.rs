//! Freestanding image of the gomatch localizer: no OS services, no C runtime start-up, no
//! allocator, no `std`. It embeds an int8 model blob, a small map and one query (as the
//! device link's request frame) with `include_bytes!`, serves that request through the
//! link's [`Device`] loop exactly as a device on a UART would, decodes its own reply and
//! exits with a status that says how it went ([`exit_code`]). It prints the reply's bytes
//! with the stage timings cleared, which must be the same on every board and on the host
//! (`firmware/cross_isa.sh`).
//!
//! Workspace and link buffers are `static`s: `Localizer<CAPACITY, f16>` and
//! `Device<CAPACITY, _>` (`CAPACITY` 256, 1024 on AArch64).
//!
//! One image, three boards; each board module provides the entry point, `print`, `exit`
//! and an instruction counter:
//! - x86_64 Linux ([`board`] = `linux.rs`): linked without the C start files, `_start`
//!   aligns the stack, `exit` is the system call; no counter.
//! - Cortex-M7 on QEMU's `mps2-an500` (`mps2.rs`): cortex-m-rt, the workspace in the
//!   board's PSRAM, semihosting for output and exit status, SysTick counts instructions.
//! - AArch64 on QEMU's `virt` (`virt.rs`): own start-up code, semihosting, the generic
//!   timer counts instructions.
#![no_std]
#![no_main]

mod fma_check;
#[cfg(target_arch = "x86_64")]
mod mem;
#[cfg(any(target_arch = "arm", target_arch = "aarch64"))]
mod semihosting;

#[cfg_attr(target_arch = "x86_64", path = "linux.rs")]
#[cfg_attr(target_arch = "arm", path = "mps2.rs")]
#[cfg_attr(target_arch = "aarch64", path = "virt.rs")]
mod board;

use core::fmt::Write as _;
use core::ptr::addr_of_mut;

use gomatch::link::{self, Device, LinkError, NoPin, Response, ResponseBody, Served, Service};
use gomatch::localizer::StageTimings;
use gomatch::{Clock, Failure, Localizer, Map, Model, Pose};
use half::f16;

/// Keypoints per query and points per view: 256 on the microcontroller boards (a 1 MiB
/// workspace).
#[cfg(not(target_arch = "aarch64"))]
const CAPACITY: usize = 256;
/// Keypoints per query and points per view: the paper's 1024 on AArch64.
#[cfg(target_arch = "aarch64")]
const CAPACITY: usize = 1024;
/// Receive buffer of the link: the longest request frame for [`CAPACITY`].
const RX: usize = link::rx_frame_len(CAPACITY);
/// A pose is right when its rotation is within this many degrees of the truth...
const MAX_ROTATION_DEG: f64 = 2.0;
/// ...and its camera centre within this fraction of the scene scale (median depth of the
/// query's ground-truth points).
const MAX_CENTER_ERROR: f64 = 0.05;

/// The model blob: `models/gomatch-int8.bin`, or the reference fixture weights converted
/// to int8 (`firmware/build.sh` chooses and sets the path).
static MODEL: &[u8] = include_bytes!(env!("GOMATCH_FIRMWARE_MODEL"));
/// Map of the query's co-visible views (`gomatch-sim firmware-data`).
static MAP: &[u8] = include_bytes!("../data/map.bin");
/// The map's precomputed view features, when the build was given them
/// (`GOMATCH_FIRMWARE_VIEW_FEATURES`, see `build.rs`); empty otherwise.
static VIEW_FEATURES: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/view_features.bin"));
/// The query as one COBS-framed link request.
static QUERY: &[u8] = include_bytes!("../data/query.frame");
/// True pose (row-major rotation, translation) and scene scale, 13 little-endian `f64`.
static TRUTH: &[u8] = include_bytes!("../data/truth.bin");

/// The localizer workspace, 1 MiB: in `.bss`, or on the Cortex-M board in its PSRAM
/// (`.psram`, not loaded and not zeroed by the start-up code: [`firmware_main`]
/// initialises it).
#[cfg_attr(target_arch = "arm", link_section = ".psram")]
static mut LOCALIZER: Localizer<CAPACITY, f16> = Localizer::new();
/// The link's receive, keypoint and reply buffers, in `.bss`.
static mut DEVICE: Device<CAPACITY, RX> = Device::new();

/// Exit statuses of the image.
pub mod exit_code {
    /// Localized, and the pose is within the thresholds of the truth.
    pub const POSE_RIGHT: i32 = 0;
    /// Ran and localized, but the pose is outside the thresholds.
    pub const POSE_WRONG: i32 = 2;
    /// Ran, and the localizer reported a failure (too few matches or inliers, no pose).
    pub const NOT_LOCALIZED: i32 = 3;
    /// Ran and found a pose, but the acceptance rule refused it (low confidence): the
    /// device says "not localized" rather than give a pose it does not trust.
    pub const REFUSED: i32 = 4;
    /// The model blob does not validate.
    pub const MODEL_INVALID: i32 = 10;
    /// The map blob, or the view features given with it, do not validate.
    pub const MAP_INVALID: i32 = 11;
    /// The embedded query frame or truth could not be read.
    pub const DATA_INVALID: i32 = 12;
    /// The localizer refused the query's content (capacity, camera, view ids).
    pub const QUERY_REJECTED: i32 = 13;
    /// The build's `mul_add` differs from `libm::fmaf` ([`crate::fma_check`]).
    pub const FMA_MISMATCH: i32 = 14;
    /// The build's int8 register block differs from the portable one
    /// ([`crate::fma_check::integer_blocks`]).
    pub const INTEGER_MISMATCH: i32 = 15;
    /// The build's f16 widening differs from the software conversion
    /// ([`crate::fma_check::f16_widening`]).
    pub const F16_MISMATCH: i32 = 16;
    /// A panic (none is expected: the core reports every bad input as a value).
    pub const PANIC: i32 = 101;
}

/// The embedded query's byte stream: reads [`QUERY`], keeps the reply written to it.
struct Loopback {
    at: usize,
    reply: [u8; link::TX_FRAME_LEN],
    reply_len: usize,
}

impl embedded_io::ErrorType for Loopback {
    type Error = embedded_io::ErrorKind;
}

impl embedded_io::Read for Loopback {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        let rest = QUERY.get(self.at..).unwrap_or(&[]);
        let n = rest.len().min(buf.len());
        buf[..n].copy_from_slice(&rest[..n]);
        self.at += n;
        Ok(n)
    }
}

impl embedded_io::Write for Loopback {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        let free = self.reply.get_mut(self.reply_len..).unwrap_or(&mut []);
        let n = free.len().min(buf.len());
        if n == 0 && !buf.is_empty() {
            return Err(embedded_io::ErrorKind::OutOfMemory);
        }
        free[..n].copy_from_slice(&buf[..n]);
        self.reply_len += n;
        Ok(n)
    }

    fn flush(&mut self) -> Result<(), Self::Error> {
        Ok(())
    }
}

/// The true pose and the scene scale from [`TRUTH`].
fn truth() -> Option<(Pose, f64)> {
    let mut values = [0.0f64; 13];
    if TRUTH.len() != 8 * values.len() {
        return None;
    }
    for (v, bytes) in values.iter_mut().zip(TRUTH.chunks_exact(8)) {
        *v = f64::from_le_bytes(bytes.try_into().ok()?);
    }
    let r = [
        [values[0], values[1], values[2]],
        [values[3], values[4], values[5]],
        [values[6], values[7], values[8]],
    ];
    let pose = Pose::from_matrix(&r, &[values[9], values[10], values[11]]).ok()?;
    Some((pose, values[12]))
}

/// Serves the embedded request and grades the reply: the exit status, and the stage
/// timings of the reply when a clock was given.
fn run(
    localizer: &'static mut Localizer<CAPACITY, f16>,
    device: &'static mut Device<CAPACITY, RX>,
    clock: Option<&dyn Clock>,
) -> (i32, Option<StageTimings>) {
    let Some((truth, scale)) = truth() else {
        return (exit_code::DATA_INVALID, None);
    };
    let mut io = Loopback {
        at: 0,
        reply: [0; link::TX_FRAME_LEN],
        reply_len: 0,
    };
    if let Err(code) = serve(localizer, device, clock, &mut io) {
        return (code, None);
    }
    let Ok(response) = link::decode_frame::<Response>(&mut io.reply[..io.reply_len]) else {
        return (exit_code::DATA_INVALID, None);
    };
    print_reply_bytes(&response);
    print_digest(localizer.correspondences());
    match response.body {
        ResponseBody::Localized(reply) => {
            let code = match reply.outcome.map(|p| p.to_pose()) {
                Ok(Ok(pose)) => grade(&pose, &truth, scale),
                Ok(Err(_)) => exit_code::POSE_WRONG,
                Err(Failure::LowConfidence { .. }) => exit_code::REFUSED,
                Err(_) => exit_code::NOT_LOCALIZED,
            };
            (code, reply.timings)
        }
        ResponseBody::Error(LinkError::Rejected(_)) => (exit_code::QUERY_REJECTED, None),
        _ => (exit_code::DATA_INVALID, None),
    }
}

/// Right ([`exit_code::POSE_RIGHT`]) when `pose` is within the thresholds of `truth`.
fn grade(pose: &Pose, truth: &Pose, scale: f64) -> i32 {
    let right = pose.rotation_error_deg(truth) <= MAX_ROTATION_DEG
        && pose.center_error(truth) <= MAX_CENTER_ERROR * scale;
    if right {
        exit_code::POSE_RIGHT
    } else {
        exit_code::POSE_WRONG
    }
}

/// Validates the blobs and serves the embedded request through the device loop; the reply
/// frame is left in `io`.
fn serve(
    localizer: &mut Localizer<CAPACITY, f16>,
    device: &mut Device<CAPACITY, RX>,
    clock: Option<&dyn Clock>,
    io: &mut Loopback,
) -> Result<(), i32> {
    if Model::from_bytes(MODEL).is_err() {
        return Err(exit_code::MODEL_INVALID);
    }
    if Map::from_bytes(MAP).is_err() {
        return Err(exit_code::MAP_INVALID);
    }
    let Ok(mut service) = Service::new(localizer, MODEL, MAP, NoPin) else {
        return Err(exit_code::MODEL_INVALID);
    };
    if !VIEW_FEATURES.is_empty() {
        service = service
            .with_view_features(VIEW_FEATURES)
            .map_err(|_| exit_code::MAP_INVALID)?;
    }
    let mut service = match clock {
        Some(clock) => service.with_clock(clock),
        None => service,
    };
    match device.serve(io, &mut service) {
        Ok(Served::Answered { id: 1 }) => Ok(()),
        _ => Err(exit_code::DATA_INVALID),
    }
}

/// A line of at most 127 bytes, formatted in place (no allocator).
struct Line {
    bytes: [u8; 128],
    len: usize,
}

impl Line {
    fn new() -> Self {
        Line {
            bytes: [0; 128],
            len: 0,
        }
    }

    fn as_str(&self) -> &str {
        core::str::from_utf8(&self.bytes[..self.len]).unwrap_or("")
    }
}

impl core::fmt::Write for Line {
    fn write_str(&mut self, s: &str) -> core::fmt::Result {
        let end = self.len + s.len();
        // One byte stays free for a terminating zero (semihosting's SYS_WRITE0).
        if end >= self.bytes.len() {
            return Err(core::fmt::Error);
        }
        self.bytes[self.len..end].copy_from_slice(s.as_bytes());
        self.len = end;
        Ok(())
    }
}

/// Prints one formatted line through the board.
fn print(args: core::fmt::Arguments<'_>) {
    let mut line = Line::new();
    // A line longer than the buffer is printed cut.
    let _ = line.write_fmt(args);
    let _ = line.write_str("\n");
    board::print(line.as_str());
}

/// Prints the instruction counts (valid when QEMU runs with `-icount shift=0`: one
/// instruction per virtual nanosecond, so a microsecond of the clock is 1,000
/// instructions).
fn print_counts(total: u64, timings: Option<&StageTimings>) {
    print(format_args!("instructions, whole query: {total}"));
    if let Some(t) = timings {
        let stages = [
            ("prepare", t.prepare_us),
            ("encode", t.encode_us),
            ("match", t.match_us),
            ("merge", t.merge_us),
            ("pose", t.pose_us),
            ("localize", t.total_us),
        ];
        for (name, kilo) in stages {
            print(format_args!("instructions (thousands), {name}: {kilo}"));
        }
    }
}

/// Reply bytes per printed line: 80 hex digits, inside a [`Line`] with its label.
const REPLY_BYTES_PER_LINE: usize = 40;

/// Prints the reply's postcard message with its stage timings cleared (the one field that
/// depends on the machine) as numbered hex lines `reply bytes (timings cleared) i/n: ...`;
/// `firmware/cross_isa.sh` compares them across boards and with the host's
/// (`gomatch-sim firmware-reply`, `firmware/data/reply.hex`).
fn print_reply_bytes(response: &Response) {
    let mut cleared = response.clone();
    if let ResponseBody::Localized(reply) = &mut cleared.body {
        reply.timings = None;
    }
    let mut buffer = [0u8; link::MAX_RESPONSE_LEN];
    let Ok(bytes) = postcard::to_slice(&cleared, &mut buffer) else {
        print(format_args!(
            "reply bytes: longer than {} bytes",
            link::MAX_RESPONSE_LEN
        ));
        return;
    };
    let lines = bytes.len().div_ceil(REPLY_BYTES_PER_LINE);
    for (i, chunk) in bytes.chunks(REPLY_BYTES_PER_LINE).enumerate() {
        print(format_args!(
            "reply bytes (timings cleared) {}/{lines}: {}",
            i + 1,
            Hex(chunk)
        ));
    }
}

/// Prints the fingerprint of the merged correspondences ([`gomatch::merge::digest`]): the
/// classifier's probabilities bit for bit, which the reply bytes carry only through the
/// pose and the confidence; `firmware/cross_isa.sh` compares it with the host's.
fn print_digest(correspondences: &[gomatch::merge::Correspondence]) {
    let digest = gomatch::merge::digest(correspondences);
    print(format_args!("correspondences digest: {digest:08x}"));
}

/// Lower-case hex digits of a byte string.
struct Hex<'a>(&'a [u8]);

impl core::fmt::Display for Hex<'_> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        self.0.iter().try_for_each(|b| write!(f, "{b:02x}"))
    }
}

/// A board's instruction counter, also the stage clock of the replies.
pub trait Counter {
    /// Instructions since an arbitrary, fixed origin.
    fn instructions(&self) -> u64;
    /// The same count as the core's [`Clock`] (microseconds of a one instruction per
    /// nanosecond machine).
    fn clock(&self) -> &dyn Clock;
}

/// Takes the workspaces, checks the FMA, serves and grades the query once, prints the
/// counts (with a `counter`) and returns the exit status.
fn firmware_main(counter: Option<&'static dyn Counter>) -> i32 {
    // The Cortex-M start-up code zeroes `.bss` only: the workspace in `.psram` is written
    // here, before any reference to it exists.
    // SAFETY: nothing has referenced the static yet; `write` does not read or drop the
    // uninitialised memory it replaces.
    #[cfg(target_arch = "arm")]
    unsafe {
        addr_of_mut!(LOCALIZER).write(Localizer::new());
    }
    // SAFETY: the image is single-threaded, its interrupt handlers (a counter's) never
    // touch these statics, and this function runs once: these are the only references
    // ever made to the two statics, so they are unique for the rest of the program.
    let (localizer, device) =
        unsafe { (&mut *addr_of_mut!(LOCALIZER), &mut *addr_of_mut!(DEVICE)) };
    if let Err(mismatch) = fma_check::run() {
        let [a, b, c] = mismatch.operands;
        print(format_args!(
            "FMA check failed: mul_add({a:#x}, {b:#x}, {c:#x}) = {:#x}, libm::fmaf = {:#x}",
            mismatch.got, mismatch.expected
        ));
        return exit_code::FMA_MISMATCH;
    }
    if let Err(block) = fma_check::integer_blocks() {
        print(format_args!(
            "integer kernel check failed: block {block} differs from the portable sums"
        ));
        return exit_code::INTEGER_MISMATCH;
    }
    if let Err(bits) = fma_check::f16_widening() {
        print(format_args!(
            "f16 check failed: {bits:#06x} widens differently from the software conversion"
        ));
        return exit_code::F16_MISMATCH;
    }
    let start = counter.map(|c| c.instructions());
    let (code, timings) = run(localizer, device, counter.map(|c| c.clock()));
    if let (Some(counter), Some(start)) = (counter, start) {
        print_counts(counter.instructions() - start, timings.as_ref());
    }
    print(format_args!("exit status {code}"));
    code
}

#[panic_handler]
fn panic(_: &core::panic::PanicInfo) -> ! {
    board::exit(exit_code::PANIC)
}
