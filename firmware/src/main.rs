//! Freestanding image of the gomatch core: no OS, no C runtime, no allocator.
//!
//! On x86_64 Linux it is linked without the C start files and leaves through the `exit`
//! system call; on a microcontroller, replace [`_start`] and [`exit`] by the board's entry
//! point (e.g. `cortex_m_rt::entry`) and its way of reporting a result.
#![no_std]
#![no_main]

use gomatch::camera::{Camera, CameraModel};

/// Checks the core end to end; `0` when every result is right.
fn run() -> i32 {
    let camera = match Camera::from_colmap(
        CameraModel::OpenCv,
        640,
        480,
        &[500.0, 500.0, 320.0, 240.0, -0.1, 0.01, 0.0, 0.0],
    ) {
        Ok(camera) => camera,
        Err(_) => return 1,
    };
    let pixel = [12.5, 400.25];
    let Ok(bearing) = camera.pixel_to_bearing(pixel) else {
        return 2;
    };
    let Ok(back) = camera.bearing_to_pixel(bearing) else {
        return 3;
    };
    if (back[0] - pixel[0]).abs() > 1e-6 || (back[1] - pixel[1]).abs() > 1e-6 {
        return 4;
    }
    0
}

/// Entry point called by the kernel (no C runtime, no `main`).
#[no_mangle]
pub extern "C" fn _start() -> ! {
    exit(run())
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
    exit(101)
}

/// The prebuilt `libcore` references this symbol; with `panic = "abort"` it is never called.
#[no_mangle]
pub extern "C" fn rust_eh_personality() {}
