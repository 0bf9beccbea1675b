//! Link setup per target: cortex-m-rt's `link.x` with this board's `memory.x` on Cortex-M,
//! `virt.ld` on AArch64. The x86_64 image's link flags come from `build.sh`. Also the map's
//! optional view features: the file `GOMATCH_FIRMWARE_VIEW_FEATURES` names (`gomatch-sim map
//! features`), or none, as `$OUT_DIR/view_features.bin`.
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
    let features = out.join("view_features.bin");
    match env::var("GOMATCH_FIRMWARE_VIEW_FEATURES") {
        Ok(path) if !path.is_empty() => {
            fs::copy(&path, &features).unwrap_or_else(|e| panic!("{path}: {e}"));
            println!("cargo:rerun-if-changed={path}");
        }
        _ => fs::write(&features, []).expect("write an empty view_features.bin"),
    }
    println!("cargo:rerun-if-env-changed=GOMATCH_FIRMWARE_VIEW_FEATURES");
    println!("cargo:rerun-if-changed=memory.x");
    println!("cargo:rerun-if-changed=virt.ld");
}
