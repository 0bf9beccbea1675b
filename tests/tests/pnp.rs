//! RANSAC-PnP on the shared synthetic PnP sets (`shared/pnp`): success rate per
//! configuration at least PoseLib's on the very same sets and under the same cap of 1000
//! minimal samples (statistical floors, no timing).

use std::path::{Path, PathBuf};

use gomatch::RansacConfig;
use gomatch_sim::eval::pnp::{
    evaluate_file, list_set_files, load_anchors, load_set_file, ANCHOR_MAX_ITERATIONS,
};

/// `shared/pnp` beside the repository root, if present.
fn shared_pnp() -> Option<PathBuf> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/pnp");
    dir.join("anchors.json").is_file().then_some(dir)
}

#[test]
fn success_rates_reach_poselib_on_the_shared_sets() {
    let Some(dir) = shared_pnp() else {
        eprintln!("SKIP: shared/pnp (sets and anchors.json) not found beside the repository");
        return;
    };
    let anchors = load_anchors(&dir.join("anchors.json")).unwrap();
    let poselib = anchors
        .get("poselib")
        .expect("anchors.json has a poselib entry");
    let files = list_set_files(&dir.join("sets")).unwrap();
    assert_eq!(
        files.len(),
        poselib.len(),
        "one set file per PoseLib configuration"
    );
    let config = RansacConfig {
        max_iterations: ANCHOR_MAX_ITERATIONS,
        ..RansacConfig::new()
    };
    let mut shortfalls = Vec::new();
    for (name, path) in &files {
        let file = load_set_file(path).unwrap();
        let ours = evaluate_file(&file, &config, 0).unwrap();
        let theirs = poselib[name].success_rate;
        println!(
            "{name}: success {:.2} (PoseLib {theirs:.2})",
            ours.success_rate
        );
        if ours.success_rate + 1e-9 < theirs {
            shortfalls.push(format!("{name}: {:.2} < {theirs:.2}", ours.success_rate));
        }
    }
    assert!(shortfalls.is_empty(), "below PoseLib: {shortfalls:?}");
}
