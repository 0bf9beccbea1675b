//! Link setup per target: cortex-m-rt's `link.x` with this board's `memory.x` on Cortex-M,
//! `virt.ld` on AArch64. The x86_64 image's link flags come from `build.sh`.
use std::{env, fs, path::PathBuf};

fn main() {
    let out = PathBuf::from(env::var("OUT_DIR").expect("cargo sets OUT_DIR"));
    match env::var("CARGO_CFG_TARGET_ARCH").as_deref() {
        Ok("arm") => {
            fs::copy("memory.x", out.join("memory.x")).expect("copy memory.x");
            println!("cargo:rustc-link-search={}", out.display());
            println!("cargo:rustc-link-arg-bins=-Tlink.x");
        }
        Ok("aarch64") => {
            let here = env::var("CARGO_MANIFEST_DIR").expect("cargo sets CARGO_MANIFEST_DIR");
            println!("cargo:rustc-link-arg-bins=-T{here}/virt.ld");
        }
        _ => {}
    }
    println!("cargo:rerun-if-changed=memory.x");
    println!("cargo:rerun-if-changed=virt.ld");
}
