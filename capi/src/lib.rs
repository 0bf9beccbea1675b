//! C API of the gomatch localizer, for firmware written in C or C++: a `no_std` static
//! library without an allocator, and its header `include/gomatch.h`, generated from this
//! crate by cbindgen (the test `header::committed_header_is_fresh` fails when the committed
//! header is stale; `GOMATCH_WRITE_HEADER=1` rewrites it).
//!
//! A firmware opens the model and the map blobs in place (`gomatch_model_open`,
//! `gomatch_map_open`: zero-copy, fully validated), places a workspace of
//! `gomatch_localizer_bytes(capacity)` bytes where it likes (a `static` array in `.bss`,
//! external RAM) and initialises it (`gomatch_localizer_init`, an inline function of the
//! header that calls `gomatch_localizer_init_<capacity>`: an image links the code of the
//! capacities it initialises only, about 17 KiB each on a Cortex-M7), then localizes queries
//! (`gomatch_localize`) and reads the inliers (`gomatch_inliers`). The model and the map
//! are read-only once opened and may be shared; a workspace serves one call at a time.
//!
//! Every function checks its arguments before calling into the core (null and misaligned
//! pointers, handles never opened, enumeration values, counts and sizes) and returns a
//! `gomatch_error`; the core reports every bad input as a typed error. No panic is
//! expected: should one happen (a bug), the library built with `panic = "abort"` stops
//! instead of unwinding into C: on a bare-metal target (`target_os = "none"`) with an
//! undefined instruction (a HardFault on a Cortex-M), on a hosted one through std's panic
//! runtime (the message, then `abort`).
#![no_std]
// The items keep the C names of the header.
#![allow(non_camel_case_types)]
#![warn(missing_docs)]

// A hosted target links std, for its panic runtime only: a workspace build also enables std
// in the core's dependencies (the host tools' features), where a handler of this crate would
// be a second one. The code uses `core` alone on every target.
#[cfg(not(target_os = "none"))]
extern crate std;

mod blobs;
mod error;
#[cfg(test)]
mod example_query;
#[cfg(test)]
mod header;
mod link;
mod localizer;
mod types;

pub use blobs::{
    gomatch_map, gomatch_map_open, gomatch_model, gomatch_model_open, GOMATCH_MAP_WORDS,
    GOMATCH_MODEL_WORDS,
};
pub use error::{gomatch_error, gomatch_error_str, gomatch_failure, gomatch_failure_str};
pub use link::{gomatch_link_reply, gomatch_reply_form, GOMATCH_LINK_REPLY_BYTES};
pub use localizer::{
    gomatch_correspondences_digest, gomatch_inliers, gomatch_localize, gomatch_localizer,
    gomatch_localizer_bytes, gomatch_localizer_init_1024, gomatch_localizer_init_128,
    gomatch_localizer_init_256, GOMATCH_LOCALIZER_ALIGN, GOMATCH_LOCALIZER_BYTES_1024,
    GOMATCH_LOCALIZER_BYTES_128, GOMATCH_LOCALIZER_BYTES_256,
};
pub use types::{
    gomatch_camera, gomatch_camera_model, gomatch_inlier, gomatch_pose, gomatch_query,
    gomatch_result, gomatch_view_selection, gomatch_views, GOMATCH_MAX_CAMERA_PARAMS,
    GOMATCH_MAX_VIEWS,
};

/// A panic is a bug of this library (every input is checked first): on a bare-metal
/// target, stop at once with an undefined instruction rather than unwind into C.
#[cfg(target_os = "none")]
#[panic_handler]
fn panic(_: &core::panic::PanicInfo) -> ! {
    #[cfg(any(target_arch = "arm", target_arch = "aarch64"))]
    // SAFETY: `udf` raises an undefined-instruction exception and touches no memory.
    unsafe {
        core::arch::asm!("udf #0", options(noreturn, nomem, nostack))
    }
    #[cfg(not(any(target_arch = "arm", target_arch = "aarch64")))]
    loop {
        core::hint::spin_loop();
    }
}
