//! `gomatch-sim dataset` end to end: write a small dataset, read it back with the
//! safetensors crate, and check it against the format in `tools/train/README.md` and the protocol.

use std::path::{Path, PathBuf};

use gomatch_sim::host::ScenesArgs;
use gomatch_sim::protocol::dataset::{run, Args};
use gomatch_sim::protocol::query_sample;
use gomatch_sim::protocol::synthetic::synthetic_scene;
use gomatch_sim::readers::SceneSource;
use safetensors::{Dtype, SafeTensors};

fn args(output: PathBuf) -> Args {
    Args {
        output,
        scenes: ScenesArgs {
            synthetic_seed: 3,
            ..ScenesArgs::default()
        },
        k: 10,
        queries_per_scene: 4,
        seed: 9,
        capacity: 1024,
    }
}

fn temp_file(tag: &str) -> PathBuf {
    std::env::temp_dir().join(format!(
        "gomatch-dataset-{tag}-{}.safetensors",
        std::process::id()
    ))
}

fn i64s(tensors: &SafeTensors<'_>, name: &str) -> (Vec<usize>, Vec<i64>) {
    let view = tensors.tensor(name).unwrap();
    assert_eq!(view.dtype(), Dtype::I64, "{name}");
    let values = view
        .data()
        .chunks_exact(8)
        .map(|c| i64::from_le_bytes(c.try_into().unwrap()))
        .collect();
    (view.shape().to_vec(), values)
}

fn f32s(tensors: &SafeTensors<'_>, name: &str) -> (Vec<usize>, Vec<f32>) {
    let view = tensors.tensor(name).unwrap();
    assert_eq!(view.dtype(), Dtype::F32, "{name}");
    let values = view
        .data()
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect();
    (view.shape().to_vec(), values)
}

/// The decoded file.
struct Dataset {
    scenes: Vec<String>,
    protocol: serde_json::Value,
    pts2d: Vec<f32>,
    pts3d: Vec<f32>,
    matches: Vec<i64>,
    offsets2d: Vec<i64>,
    offsets3d: Vec<i64>,
    scene: Vec<i64>,
    query: Vec<i64>,
    view: Vec<i64>,
}

/// Reads the file and checks every structural rule of the format.
fn read_and_check(path: &Path) -> Dataset {
    let bytes = std::fs::read(path).unwrap();
    let (_, header) = SafeTensors::read_metadata(&bytes).unwrap();
    let metadata = header.metadata().clone().unwrap();
    assert_eq!(metadata["format"], "gomatch-dataset");
    assert_eq!(metadata["version"], "1");
    let scenes: Vec<String> = serde_json::from_str(&metadata["scenes"]).unwrap();
    let protocol: serde_json::Value = serde_json::from_str(&metadata["protocol"]).unwrap();
    let tensors = SafeTensors::deserialize(&bytes).unwrap();
    let (pts2d_shape, pts2d) = f32s(&tensors, "pts2d");
    let (pts3d_shape, pts3d) = f32s(&tensors, "pts3d");
    let (match_shape, matches) = i64s(&tensors, "match");
    let (_, offsets2d) = i64s(&tensors, "offsets2d");
    let (_, offsets3d) = i64s(&tensors, "offsets3d");
    let (scene_shape, scene) = i64s(&tensors, "scene");
    let (_, query) = i64s(&tensors, "query");
    let (_, view) = i64s(&tensors, "view");
    let samples = scene_shape[0];
    assert!(samples > 0);
    assert_eq!(pts2d_shape[1], 2);
    assert_eq!(pts3d_shape[1], 2);
    assert_eq!(match_shape, vec![pts2d_shape[0]]);
    assert_eq!(
        (offsets2d.len(), offsets3d.len()),
        (samples + 1, samples + 1)
    );
    assert_eq!((query.len(), view.len()), (samples, samples));
    assert_eq!((offsets2d[0], offsets3d[0]), (0, 0));
    assert_eq!(offsets2d[samples] as usize, pts2d_shape[0]);
    assert_eq!(offsets3d[samples] as usize, pts3d_shape[0]);
    for s in 0..samples {
        let (a2, b2) = (offsets2d[s] as usize, offsets2d[s + 1] as usize);
        let (a3, b3) = (offsets3d[s] as usize, offsets3d[s + 1] as usize);
        assert!(a2 < b2 && a3 < b3, "sample {s} is empty");
        assert!(b2 - a2 <= 1024 && b3 - a3 <= 1024);
        assert!((scene[s] as usize) < scenes.len());
        assert_ne!(query[s], view[s]);
        let block = &matches[a2..b2];
        let mut used = vec![false; b3 - a3];
        for &m in block {
            assert!(m >= -1 && m < (b3 - a3) as i64, "sample {s}: match {m}");
            if m >= 0 {
                assert!(!used[m as usize], "sample {s}: 3D point {m} matched twice");
                used[m as usize] = true;
            }
        }
    }
    assert!(pts2d.iter().chain(&pts3d).all(|v| v.is_finite()));
    Dataset {
        scenes,
        protocol,
        pts2d,
        pts3d,
        matches,
        offsets2d,
        offsets3d,
        scene,
        query,
        view,
    }
}

#[test]
fn synthetic_dataset_round_trips_through_safetensors() {
    let output = temp_file("synthetic");
    let mut arguments = args(output.clone());
    arguments.scenes.synthetic = 2;
    run(&arguments).unwrap();
    let first = std::fs::read(&output).unwrap();
    run(&arguments).unwrap();
    assert!(
        std::fs::read(&output).unwrap() == first,
        "the same arguments write the same bytes"
    );
    let dataset = read_and_check(&output);
    std::fs::remove_file(&output).unwrap();
    assert_eq!(dataset.scenes, vec!["synthetic/0000", "synthetic/0001"]);
    assert_eq!(dataset.protocol["k"], 10);
    assert_eq!(dataset.protocol["seed"], 9);
    assert_eq!(dataset.protocol["gt_threshold"], 1e-3);
    let matched = dataset.matches.iter().filter(|&&m| m >= 0).count();
    assert!(matched > 0);

    // The first sample is exactly the protocol's first query and its first view.
    let scene = synthetic_scene(3, dataset.scene[0] as u64);
    let sample = query_sample(&scene, dataset.query[0] as u32, &arguments.protocol()).unwrap();
    let view = &sample.views[0];
    assert_eq!(i64::from(view.image_id), dataset.view[0]);
    let n2 = dataset.offsets2d[1] as usize;
    let n3 = dataset.offsets3d[1] as usize;
    assert_eq!(n2, sample.keypoints.len());
    assert_eq!(n3, view.bearings.len());
    for (i, b) in sample.keypoints.bearings.iter().enumerate() {
        assert_eq!(dataset.pts2d[2 * i], b[0] as f32);
        assert_eq!(dataset.pts2d[2 * i + 1], b[1] as f32);
    }
    for (j, b) in view.bearings.iter().enumerate() {
        assert_eq!(dataset.pts3d[2 * j], b[0] as f32);
        assert_eq!(dataset.pts3d[2 * j + 1], b[1] as f32);
    }
    assert_eq!(dataset.matches[..n2], view.match_vector(n2)[..]);
}

#[test]
fn capacity_caps_every_sample_as_the_localizer_does() {
    let output = temp_file("capacity");
    let mut arguments = args(output.clone());
    arguments.scenes.synthetic = 2;
    arguments.capacity = 128;
    run(&arguments).unwrap();
    let dataset = read_and_check(&output);
    std::fs::remove_file(&output).unwrap();
    assert_eq!(dataset.protocol["max_keypoints"], 128);
    assert_eq!(dataset.protocol["max_points"], 128);
    let sizes = |offsets: &[i64]| -> Vec<i64> { offsets.windows(2).map(|w| w[1] - w[0]).collect() };
    let (keypoints, points) = (sizes(&dataset.offsets2d), sizes(&dataset.offsets3d));
    assert!(keypoints.iter().chain(&points).all(|&n| n <= 128));
    assert!(keypoints.contains(&128), "the cap binds on these scenes");

    // Each sample is the protocol's at that capacity.
    let scene = synthetic_scene(3, dataset.scene[0] as u64);
    let sample = query_sample(&scene, dataset.query[0] as u32, &arguments.protocol()).unwrap();
    assert_eq!(keypoints[0] as usize, sample.keypoints.len());
    assert_eq!(points[0] as usize, sample.views[0].bearings.len());
}

#[test]
fn real_training_scene_dataset_is_well_formed() {
    let data = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    if !data.is_dir() {
        println!("SKIPPED: {} is absent", data.display());
        return;
    }
    let output = temp_file("real");
    let mut arguments = args(output.clone());
    let model = data.join("colmap/wmv_video3");
    arguments.scenes.colmap = vec![model.clone()];
    run(&arguments).unwrap();
    let dataset = read_and_check(&output);
    std::fs::remove_file(&output).unwrap();
    assert_eq!(dataset.scenes, vec!["colmap/wmv_video3"]);
    let scene = SceneSource::Colmap(model).load().unwrap();
    for (&query, &view) in dataset.query.iter().zip(&dataset.view) {
        assert!(scene.images.contains_key(&(query as u32)));
        assert!(scene.images.contains_key(&(view as u32)));
    }
}
