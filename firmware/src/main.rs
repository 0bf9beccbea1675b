//! Freestanding image of the gomatch localizer: no OS services, no C runtime start-up, no
//! allocator, no `std`. It embeds an int8 model blob, a small map and one query (as the
//! device link's request frame) with `include_bytes!`, serves that request through the
//! link's [`Device`] loop exactly as a device on a UART would, decodes its own reply and
//! exits with a status that says how it went ([`exit_code`]).
//!
//! Workspace and link buffers are `static`s in `.bss` (zeroed by the loader, nothing in
//! flash): `Localizer<256, f16>` and `Device<256, _>`.
//!
//! On x86_64 Linux it is linked without the C start files; [`_start`] aligns the stack
//! and calls [`firmware_main`], which leaves through the `exit` system call. On a
//! microcontroller, replace `_start` and [`exit`] by the board's entry point (e.g.
//! `cortex_m_rt::entry`) and its way of reporting a result (see README.md, "Building for a Cortex-M or RISC-V target").
#![no_std]
#![no_main]

mod mem;

use core::ptr::addr_of_mut;

use gomatch::link::{self, Device, LinkError, NoPin, Response, ResponseBody, Served, Service};
use gomatch::{Failure, Localizer, Map, Model, Pose};
use half::f16;

/// Keypoints per query and points per view.
const CAPACITY: usize = 256;
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
/// The query as one COBS-framed link request.
static QUERY: &[u8] = include_bytes!("../data/query.frame");
/// True pose (row-major rotation, translation) and scene scale, 13 little-endian `f64`.
static TRUTH: &[u8] = include_bytes!("../data/truth.bin");

/// The localizer workspace, 1 MiB, in `.bss`.
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
    /// The map blob does not validate.
    pub const MAP_INVALID: i32 = 11;
    /// The embedded query frame or truth could not be read.
    pub const DATA_INVALID: i32 = 12;
    /// The localizer refused the query's content (capacity, camera, view ids).
    pub const QUERY_REJECTED: i32 = 13;
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

/// Serves the embedded request and grades the reply.
fn run(
    localizer: &'static mut Localizer<CAPACITY, f16>,
    device: &'static mut Device<CAPACITY, RX>,
) -> i32 {
    if Model::from_bytes(MODEL).is_err() {
        return exit_code::MODEL_INVALID;
    }
    if Map::from_bytes(MAP).is_err() {
        return exit_code::MAP_INVALID;
    }
    let Some((truth, scale)) = truth() else {
        return exit_code::DATA_INVALID;
    };
    let Ok(mut service) = Service::new(localizer, MODEL, MAP, NoPin) else {
        return exit_code::MODEL_INVALID;
    };
    let mut io = Loopback {
        at: 0,
        reply: [0; link::TX_FRAME_LEN],
        reply_len: 0,
    };
    match device.serve(&mut io, &mut service) {
        Ok(Served::Answered { id: 1 }) => {}
        _ => return exit_code::DATA_INVALID,
    }
    let Ok(response) = link::decode_frame::<Response>(&mut io.reply[..io.reply_len]) else {
        return exit_code::DATA_INVALID;
    };
    match response.body {
        ResponseBody::Localized(reply) => match reply.outcome.map(|p| p.to_pose()) {
            Ok(Ok(pose)) => {
                let right = pose.rotation_error_deg(&truth) <= MAX_ROTATION_DEG
                    && pose.center_error(&truth) <= MAX_CENTER_ERROR * scale;
                if right {
                    exit_code::POSE_RIGHT
                } else {
                    exit_code::POSE_WRONG
                }
            }
            Ok(Err(_)) => exit_code::POSE_WRONG,
            Err(Failure::LowConfidence { .. }) => exit_code::REFUSED,
            Err(_) => exit_code::NOT_LOCALIZED,
        },
        ResponseBody::Error(LinkError::Rejected(_)) => exit_code::QUERY_REJECTED,
        _ => exit_code::DATA_INVALID,
    }
}

// Entry point called by the kernel (no C runtime): clears the frame pointer, aligns the
// stack to 16 bytes as the C ABI expects at a call, and calls `firmware_main`.
core::arch::global_asm!(
    ".globl _start",
    "_start:",
    "xor ebp, ebp",
    "and rsp, -16",
    "call {main}",
    "ud2",
    main = sym firmware_main,
);

/// Takes the workspaces and runs the image once.
extern "C" fn firmware_main() -> ! {
    // SAFETY: the image is single-threaded, has no interrupt handlers, and this function
    // runs once: these are the only references ever made to the two statics, so they are
    // unique for the rest of the program.
    let (localizer, device) =
        unsafe { (&mut *addr_of_mut!(LOCALIZER), &mut *addr_of_mut!(DEVICE)) };
    exit(run(localizer, device))
}

/// Ends the process with the Linux `exit` system call.
fn exit(code: i32) -> ! {
    // SAFETY: the exit system call takes one integer argument and never returns.
    unsafe {
        core::arch::asm!("syscall", in("rax") 60, in("rdi") code, options(noreturn));
    }
}

#[panic_handler]
fn panic(_: &core::panic::PanicInfo) -> ! {
    exit(exit_code::PANIC)
}

/// The prebuilt `libcore` references this symbol; with `panic = "abort"` it is never called.
#[no_mangle]
pub extern "C" fn rust_eh_personality() {}
