//! `gomatch-sim firmware-reply`: the host's reply to the firmware image's embedded request
//! (`firmware/data/`), as the image prints it: the postcard message with its stage timings
//! cleared (the one field that depends on the machine), in numbered hex lines
//! `reply bytes (timings cleared) i/n: ...`, and the digest of the merged correspondences
//! ([`gomatch::merge::digest`]). `firmware/data/reply.hex` holds them at capacity 256,
//! `firmware/data/reply-1024.hex` at 1024, and `firmware/cross_isa.sh` compares each board's
//! lines with its capacity's byte for byte.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use anyhow::{bail, Context};
use clap::Parser;
use gomatch::link::{self, Device, NoPin, Response, ResponseBody, Served, Service};
use gomatch::{merge, Localizer};
use half::f16;

use crate::device::firmware_data::FIRMWARE_CAPACITY;

/// Keypoint capacity of the AArch64 image (`firmware/src/main.rs`).
pub const AARCH64_CAPACITY: usize = 1024;
/// Reply bytes per printed line, as the image prints them.
const BYTES_PER_LINE: usize = 40;

/// The localizer and link buffers of the Cortex-M7 and x86_64 images (capacity 256).
static SMALL: Mutex<(
    Localizer<FIRMWARE_CAPACITY, f16>,
    Device<FIRMWARE_CAPACITY, { link::rx_frame_len(FIRMWARE_CAPACITY) }>,
)> = Mutex::new((Localizer::new(), Device::new()));
/// The localizer and link buffers of the AArch64 image (capacity 1024).
static LARGE: Mutex<(
    Localizer<AARCH64_CAPACITY, f16>,
    Device<AARCH64_CAPACITY, { link::rx_frame_len(AARCH64_CAPACITY) }>,
)> = Mutex::new((Localizer::new(), Device::new()));

/// Print (or write) the host's reply bytes to the firmware image's embedded request.
#[derive(Debug, Clone, Parser)]
pub struct Args {
    /// Directory of the embedded data (`map.bin`, `query.frame`).
    #[arg(long, default_value = "firmware/data")]
    pub data: PathBuf,
    /// Model blob the images embed.
    #[arg(long, default_value = "models/gomatch-int8.bin")]
    pub model: PathBuf,
    /// Keypoint capacity of the localizer: 256 (Cortex-M7, x86_64) or 1024 (AArch64).
    #[arg(long, default_value_t = FIRMWARE_CAPACITY)]
    pub capacity: usize,
    /// Also write the lines to this file (firmware/data/reply.hex at 256,
    /// firmware/data/reply-1024.hex at 1024).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// A request stream that reads one frame and keeps the reply written to it.
struct Loopback<'a> {
    request: &'a [u8],
    reply: Vec<u8>,
}

impl embedded_io::ErrorType for Loopback<'_> {
    type Error = std::convert::Infallible;
}

impl embedded_io::Read for Loopback<'_> {
    fn read(&mut self, buf: &mut [u8]) -> Result<usize, Self::Error> {
        let n = self.request.len().min(buf.len());
        buf[..n].copy_from_slice(&self.request[..n]);
        self.request = &self.request[n..];
        Ok(n)
    }
}

impl embedded_io::Write for Loopback<'_> {
    fn write(&mut self, buf: &[u8]) -> Result<usize, Self::Error> {
        self.reply.extend_from_slice(buf);
        Ok(buf.len())
    }

    fn flush(&mut self) -> Result<(), Self::Error> {
        Ok(())
    }
}

/// Serves `frame` through the link's device loop with no clock, as the firmware image does,
/// and returns the decoded reply and the digest of the merged correspondences.
fn serve<const N: usize, const RX: usize>(
    localizer: &mut Localizer<N, f16>,
    device: &mut Device<N, RX>,
    model: &[u8],
    map: &[u8],
    frame: &[u8],
) -> anyhow::Result<(Response, u32)> {
    let mut io = Loopback {
        request: frame,
        reply: Vec::new(),
    };
    let mut service = Service::new(&mut *localizer, model, map, NoPin)
        .map_err(|e| anyhow::anyhow!("model or map: {e}"))?;
    match device.serve(&mut io, &mut service) {
        Ok(Served::Answered { .. }) => {}
        other => bail!("the request was not answered: {other:?}"),
    }
    let response =
        link::decode_frame(&mut io.reply).map_err(|e| anyhow::anyhow!("reply frame: {e:?}"))?;
    Ok((response, merge::digest(localizer.correspondences())))
}

/// What the firmware image prints of its query, the host's way.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct FirmwareReply {
    /// The reply's postcard bytes with the stage timings cleared.
    pub bytes: Vec<u8>,
    /// [`merge::digest`] of the merged correspondences.
    pub digest: u32,
}

/// The reply for a localizer of `capacity` keypoints (256 or 1024) and `f16` Sinkhorn
/// storage, as the images use.
pub fn firmware_reply(
    model: &[u8],
    map: &[u8],
    frame: &[u8],
    capacity: usize,
) -> anyhow::Result<FirmwareReply> {
    let (mut response, digest) = match capacity {
        FIRMWARE_CAPACITY => {
            let mut guard = SMALL.lock().unwrap_or_else(|e| e.into_inner());
            let (localizer, device) = &mut *guard;
            serve(localizer, device, model, map, frame)?
        }
        AARCH64_CAPACITY => {
            let mut guard = LARGE.lock().unwrap_or_else(|e| e.into_inner());
            let (localizer, device) = &mut *guard;
            serve(localizer, device, model, map, frame)?
        }
        _ => bail!("capacity {capacity}: the images use {FIRMWARE_CAPACITY} or {AARCH64_CAPACITY}"),
    };
    if let ResponseBody::Localized(reply) = &mut response.body {
        reply.timings = None;
    }
    let mut buffer = [0u8; link::MAX_RESPONSE_LEN];
    let bytes = postcard::to_slice(&response, &mut buffer).context("re-encoding the reply")?;
    Ok(FirmwareReply {
        bytes: bytes.to_vec(),
        digest,
    })
}

/// The lines the firmware image prints for its reply, each ending with a newline: the
/// numbered hex lines of the bytes, then the correspondences' digest.
pub fn reply_lines(reply: &FirmwareReply) -> String {
    let lines = reply.bytes.len().div_ceil(BYTES_PER_LINE);
    let mut text: String = reply
        .bytes
        .chunks(BYTES_PER_LINE)
        .enumerate()
        .map(|(i, chunk)| {
            let hex: String = chunk.iter().map(|b| format!("{b:02x}")).collect();
            format!("reply bytes (timings cleared) {}/{lines}: {hex}\n", i + 1)
        })
        .collect();
    text += &format!("correspondences digest: {:08x}\n", reply.digest);
    text
}

/// The reply to the request in `data` (`map.bin`, `query.frame`) with `model`.
pub fn firmware_reply_from_files(
    data: &Path,
    model: &Path,
    capacity: usize,
) -> anyhow::Result<FirmwareReply> {
    let read = |path: &Path| std::fs::read(path).with_context(|| format!("{}", path.display()));
    firmware_reply(
        &read(model)?,
        &read(&data.join("map.bin"))?,
        &read(&data.join("query.frame"))?,
        capacity,
    )
}

/// Runs `gomatch-sim firmware-reply`.
pub fn run(args: &Args) -> anyhow::Result<()> {
    let reply = firmware_reply_from_files(&args.data, &args.model, args.capacity)?;
    let lines = reply_lines(&reply);
    print!("{lines}");
    if let Some(out) = &args.out {
        std::fs::write(out, &lines).with_context(|| format!("writing {}", out.display()))?;
    }
    Ok(())
}
