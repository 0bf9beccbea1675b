//! The geometric-only map blob across crates: `gomatch-sim map build` encodes a scene, the
//! core reads it back in place; corrupt blobs are typed errors and never panics.

use std::collections::BTreeSet;
use std::path::PathBuf;
use std::sync::OnceLock;

use gomatch::envelope::{self, HEADER_BYTES};
use gomatch::error::BlobKind;
use gomatch::map::Map;
use gomatch::Error;
use gomatch_sim::map::{build_map, exclude_images};
use gomatch_sim::protocol::synthetic::synthetic_scene;
use gomatch_sim::readers::SceneSource;
use gomatch_sim::scene::Scene;
use proptest::prelude::*;

/// Checks that the map holds exactly the scene's observed points, cameras and views.
fn check_round_trip(scene: &Scene) {
    let blob = build_map(scene).unwrap();
    let map = Map::from_bytes(&blob).unwrap();
    let observed: Vec<_> = scene
        .points
        .values()
        .filter(|p| !p.track.is_empty())
        .collect();
    assert_eq!(map.point_count(), observed.len());
    assert_eq!(map.camera_count(), scene.cameras.len());
    assert_eq!(map.view_count(), scene.images.len());
    for (i, point) in observed.iter().enumerate() {
        let expected = [point.xyz.x as f32, point.xyz.y as f32, point.xyz.z as f32];
        assert_eq!(map.point(i).unwrap(), expected);
    }
    for (i, camera) in scene.cameras.values().enumerate() {
        assert_eq!(map.camera(i).unwrap(), *camera);
    }
    let ids: Vec<u64> = observed.iter().map(|p| p.id).collect();
    for (v, image) in scene.images.values().enumerate() {
        let view = map.view(v).unwrap();
        assert_eq!(view.image_id, image.id);
        assert_eq!(map.view_name(v).unwrap(), image.name);
        assert_eq!(
            map.camera(view.camera_index as usize).unwrap(),
            scene.cameras[&image.camera_id]
        );
        assert!((view.pose.rotation.matrix() - image.pose.rotation.matrix()).amax() < 1e-12);
        assert_eq!(view.pose.translation, image.pose.translation);
        let stored: BTreeSet<u64> = map
            .view_points(v)
            .unwrap()
            .iter()
            .map(|i| ids[i as usize])
            .collect();
        let expected: BTreeSet<u64> = image.keypoints.iter().filter_map(|k| k.point3d).collect();
        assert_eq!(stored, expected, "image {}", image.id);
    }
}

#[test]
fn synthetic_scene_round_trips_through_the_map() {
    check_round_trip(&synthetic_scene(2, 0));
}

#[test]
fn excluded_images_leave_the_map_with_the_points_only_they_observe() {
    let scene = synthetic_scene(2, 0);
    let names: Vec<String> = scene
        .images
        .values()
        .take(2)
        .map(|i| i.name.clone())
        .collect();
    let kept = exclude_images(&scene, &names).unwrap();
    assert_eq!(kept.images.len(), scene.images.len() - 2);
    check_round_trip(&kept);
    let map_blob = build_map(&kept).unwrap();
    let map = Map::from_bytes(&map_blob).unwrap();
    let map_names: BTreeSet<&str> = (0..map.view_count())
        .map(|v| map.view_name(v).unwrap())
        .collect();
    assert!(names.iter().all(|n| !map_names.contains(n.as_str())));
    let seen_by_kept = scene
        .points
        .values()
        .filter(|p| {
            p.track
                .iter()
                .any(|e| kept.images.contains_key(&e.image_id))
        })
        .count();
    assert_eq!(map.point_count(), seen_by_kept);
    assert!(
        seen_by_kept
            < scene
                .points
                .values()
                .filter(|p| !p.track.is_empty())
                .count()
    );
    assert!(exclude_images(&scene, &["no such image".into()]).is_err());
}

#[test]
fn real_scenes_round_trip_through_the_map() {
    let data = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    if !data.is_dir() {
        println!("SKIPPED: {} is absent", data.display());
        return;
    }
    for source in [
        SceneSource::Colmap(data.join("colmap/mouse")),
        SceneSource::Bal(data.join("bal/problem-49-7776-pre.txt")),
        SceneSource::Bundler(data.join("bundler/kermit/bundle.out")),
    ] {
        check_round_trip(&source.load().unwrap());
    }
}

/// Touches every accessor of a map that decoded.
fn read_everything(map: &Map<'_>) {
    for i in 0..map.point_count() {
        map.point(i).unwrap();
    }
    for i in 0..map.camera_count() {
        map.camera(i).unwrap();
    }
    for v in 0..map.view_count() {
        map.view(v).unwrap();
        assert!(map
            .view_points(v)
            .unwrap()
            .iter()
            .all(|p| (p as usize) < map.point_count()));
    }
}

/// A valid blob of three synthetic views, built once.
fn small_blob() -> Vec<u8> {
    static BLOB: OnceLock<Vec<u8>> = OnceLock::new();
    BLOB.get_or_init(|| {
        let mut scene = synthetic_scene(4, 1);
        let keep: Vec<u32> = scene.images.keys().copied().take(3).collect();
        scene.images.retain(|id, _| keep.contains(id));
        for point in scene.points.values_mut() {
            point.track.retain(|e| keep.contains(&e.image_id));
        }
        build_map(&scene).unwrap()
    })
    .clone()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..2048)) {
        if let Ok(map) = Map::from_bytes(&bytes) {
            read_everything(&map);
        }
    }

    #[test]
    fn arbitrary_bytes_behind_a_valid_header_never_panic(
        payload in proptest::collection::vec(any::<u8>(), 0..2048)
    ) {
        let mut blob = vec![0; HEADER_BYTES];
        blob.extend(&payload);
        envelope::seal(BlobKind::Map, &mut blob, payload.len()).expect("fits");
        if let Ok(map) = Map::from_bytes(&blob) {
            read_everything(&map);
        }
    }

    #[test]
    fn flipped_bytes_are_caught(position in any::<prop::sample::Index>(), flip in 1u8..=255) {
        let mut blob = small_blob();
        let i = position.index(blob.len());
        blob[i] ^= flip;
        prop_assert!(Map::from_bytes(&blob).is_err());
    }

    #[test]
    fn resealed_corruption_never_panics(position in any::<prop::sample::Index>(), value in any::<u8>()) {
        let mut blob = small_blob();
        let i = HEADER_BYTES + position.index(blob.len() - HEADER_BYTES);
        blob[i] = value;
        let payload = blob.len() - HEADER_BYTES;
        envelope::seal(BlobKind::Map, &mut blob, payload).expect("fits");
        if let Ok(map) = Map::from_bytes(&blob) {
            read_everything(&map);
        }
    }

    #[test]
    fn truncated_blobs_report_their_length(cut in any::<prop::sample::Index>()) {
        let blob = small_blob();
        let len = cut.index(blob.len());
        let expected_needed = if len < HEADER_BYTES { HEADER_BYTES } else { blob.len() };
        prop_assert_eq!(
            Map::from_bytes(&blob[..len]),
            Err(Error::BlobTruncated { blob: BlobKind::Map, needed: expected_needed, found: len })
        );
    }
}
