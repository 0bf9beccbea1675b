//! The flash and RAM layout of the linked firmware images, for `mem-report`: the size of
//! each section, read from the ELF files that `firmware/build.sh` and `firmware/qemu.sh`
//! link (what the device really holds, beside the workspace sizes of the types).

use std::path::Path;

use anyhow::{Context, Result};
use object::{Object, ObjectSection};
use serde::Serialize;

/// The firmware's targets, in the order reported.
pub const TARGETS: [&str; 3] = [
    "x86_64-unknown-linux-gnu",
    "thumbv7em-none-eabihf",
    "aarch64-unknown-none",
];
/// The target column of the C example's image (`capi/example`, `bash capi/example/qemu.sh`):
/// the Cortex-M7 firmware in C, linked against the C API's static library.
pub const C_EXAMPLE_TARGET: &str = "thumbv7em-none-eabihf (C example)";
/// The sections reported: the Cortex-M vector table, code, read-only data (the model and
/// map blobs), initialised and zeroed data, the Cortex-M7 workspace in PSRAM and the
/// AArch64 image's stack.
pub const SECTIONS: [&str; 7] = [
    ".vector_table",
    ".text",
    ".rodata",
    ".data",
    ".bss",
    ".psram",
    ".stack",
];
/// Sections stored in the image (flash): vector table, code, read-only data and the load
/// copy of `.data`.
const FLASH: [&str; 4] = [".vector_table", ".text", ".rodata", ".data"];
/// Sections in RAM at run time.
const RAM: [&str; 4] = [".data", ".bss", ".psram", ".stack"];

/// One linked image.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct ImageLayout {
    /// The Rust target it was built for.
    pub target: String,
    /// Bytes of each of [`SECTIONS`] (0 where the image has none).
    pub sections: [u64; SECTIONS.len()],
    /// Bytes stored in the image (AArch64's QEMU image is loaded into RAM, so there this is
    /// the loaded part of RAM).
    pub flash_bytes: u64,
    /// Bytes of RAM (on Cortex-M the stack is the rest of RAM and not counted).
    pub ram_bytes: u64,
}

/// The layout of the ELF image `elf` built for `target`.
pub fn layout(target: &str, elf: &[u8]) -> Result<ImageLayout> {
    let file = object::File::parse(elf).with_context(|| format!("{target}: not an ELF image"))?;
    let size = |name: &str| {
        file.section_by_name(name)
            .map_or(0, |section| section.size())
    };
    let sum = |names: &[&str]| names.iter().map(|n| size(n)).sum();
    Ok(ImageLayout {
        target: target.to_owned(),
        sections: SECTIONS.map(size),
        flash_bytes: sum(&FLASH),
        ram_bytes: sum(&RAM),
    })
}

/// The layouts of the images built under `target_dir` (`firmware/target`: its
/// `<target>/release/gomatch-firmware`), in [`TARGETS`] order; targets not built are left
/// out.
pub fn built_images(target_dir: &Path) -> Result<Vec<ImageLayout>> {
    let mut layouts = Vec::new();
    for target in TARGETS {
        let path = target_dir.join(target).join("release/gomatch-firmware");
        if !path.is_file() {
            continue;
        }
        let elf = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
        layouts.push(layout(target, &elf)?);
    }
    Ok(layouts)
}

/// The layout of the C example's image at `path`; `None` when it was not linked.
pub fn c_example_image(path: &Path) -> Result<Option<ImageLayout>> {
    if !path.is_file() {
        return Ok(None);
    }
    let elf = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    layout(C_EXAMPLE_TARGET, &elf).map(Some)
}

/// Flash the C API adds to a Cortex-M7 image: the C example's flash minus the Rust
/// firmware's (both embed the same model and map), negative when it takes less; `None`
/// unless both images are in `layouts`.
pub fn capi_flash_delta(layouts: &[ImageLayout]) -> Option<i64> {
    let flash = |target: &str| {
        layouts
            .iter()
            .find(|l| l.target == target)
            .map(|l| l.flash_bytes as i64)
    };
    Some(flash(C_EXAMPLE_TARGET)? - flash("thumbv7em-none-eabihf")?)
}

/// The layouts as a markdown table, bytes.
pub fn markdown(layouts: &[ImageLayout]) -> String {
    let mut out = format!(
        "| target | {} | flash | RAM |\n|---|{}---|---|\n",
        SECTIONS.map(|s| format!("`{s}`")).join(" | "),
        "---|".repeat(SECTIONS.len())
    );
    for l in layouts {
        let sizes: Vec<String> = l.sections.iter().map(|b| b.to_string()).collect();
        out.push_str(&format!(
            "| {} | {} | {} | {} |\n",
            l.target,
            sizes.join(" | "),
            l.flash_bytes,
            l.ram_bytes
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_running_test_binary_has_a_layout() {
        let path = std::env::current_exe().expect("test binary");
        let elf = std::fs::read(path).expect("readable");
        let l = layout("host", &elf).expect("an ELF file");
        let [vector_table, text, rodata, data, ..] = l.sections;
        assert!(text > 0 && rodata > 0);
        assert_eq!(l.flash_bytes, vector_table + text + rodata + data);
        assert!(l.ram_bytes >= data);
        assert!(markdown(&[l])
            .lines()
            .nth(2)
            .expect("a row")
            .starts_with("| host |"));
    }

    #[test]
    fn the_c_api_delta_compares_the_two_cortex_m7_images() {
        let image = |target: &str, flash_bytes| ImageLayout {
            target: target.to_owned(),
            sections: [0; SECTIONS.len()],
            flash_bytes,
            ram_bytes: 0,
        };
        let rust = image("thumbv7em-none-eabihf", 1_481_032);
        let c = image(C_EXAMPLE_TARGET, 1_458_044);
        let x86 = image("x86_64-unknown-linux-gnu", 2_000_000);
        assert_eq!(
            capi_flash_delta(&[x86.clone(), rust.clone(), c.clone()]),
            Some(-22_988)
        );
        assert_eq!(capi_flash_delta(&[x86, rust]), None);
        assert_eq!(capi_flash_delta(&[c]), None);
        let missing = Path::new("capi/example/build/no-such-image.elf");
        assert_eq!(c_example_image(missing).expect("no error"), None);
    }

    #[test]
    fn a_file_that_is_not_elf_is_an_error() {
        let err = layout("host", b"GMAP not an image").expect_err("not ELF");
        assert!(err.to_string().contains("not an ELF image"), "{err}");
    }
}
