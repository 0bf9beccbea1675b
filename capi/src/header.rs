//! The committed C header is what cbindgen generates from this crate.

use std::path::Path;
use std::vec::Vec;

/// Fails when `include/gomatch.h` differs from cbindgen's output for the current sources;
/// `GOMATCH_WRITE_HEADER=1 cargo test -p gomatch-capi header` rewrites it.
#[test]
fn committed_header_is_fresh() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR"));
    let config = cbindgen::Config::from_file(dir.join("cbindgen.toml")).expect("cbindgen.toml");
    let mut generated = Vec::new();
    cbindgen::Builder::new()
        .with_config(config)
        .with_src(dir.join("src/lib.rs"))
        .generate()
        .expect("cbindgen parses the crate")
        .write(&mut generated);
    let path = dir.join("include/gomatch.h");
    if std::env::var_os("GOMATCH_WRITE_HEADER").is_some_and(|v| v == "1") {
        std::fs::write(&path, &generated).expect("write the header");
    }
    let committed = std::fs::read(&path).unwrap_or_default();
    assert!(
        committed == generated,
        "{} is stale: regenerate it with GOMATCH_WRITE_HEADER=1 cargo test -p gomatch-capi header",
        path.display()
    );
}
