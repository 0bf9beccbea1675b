//! OpenSfM reader: `reconstruction.json` (a list of reconstructions: cameras, shots, points)
//! with the `tracks.csv` beside it (one row per tracked feature).
//!
//! Conventions. Shots store the world-to-camera pose as an angle-axis `rotation` and a
//! `translation`, `x_cam = R x + t`, camera looking along +z, y down: COLMAP's. A
//! `perspective` camera has `focal`, `k1`, `k2` normalised by the larger image side `s`;
//! it projects as COLMAP's `RADIAL` camera with `f = focal s`, principal point at the image
//! centre. Track rows give `image, track id, feature id, x, y, size, ...` with `(x, y)` in
//! units of `s` around the image centre, so the pixel is `(x s + w/2, y s + h/2)`.
//!
//! What the files hold, and how it maps to a [`Scene`]: `tracks.csv` lists only features
//! matched in two or more images (untracked keypoints are absent), and the chosen
//! reconstruction triangulates some of those tracks. Each shot's keypoints are its rows of
//! `tracks.csv`; a row whose track is a point of the reconstruction is triangulated, the
//! other rows (tracked but not reconstructed) are the untriangulated keypoints, the
//! localization outliers. Keypoints are stored in feature-id order, OpenSfM's extraction
//! order, which sorts features by increasing size (so [`Image::ranked_keypoints`], the
//! reverse stored order, puts larger scales first as for COLMAP's VLFeat features).
//!
//! Several reconstructions per file: the one with the most shots is loaded (the first of
//! equals), as OpenSfM's own tools treat the first, largest, one as the main model.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::Context;
use gomatch::camera::CameraModel;
use gomatch::{Camera, Pose};
use nalgebra::{Rotation3, Vector3};
use serde::Deserialize;

use crate::readers::parse::{file_name, FormatError};
use crate::scene::{CameraId, Image, ImageId, Keypoint, Point3d, PointId, Scene, TrackElement};

/// One reconstruction of `reconstruction.json` (fields this reader uses).
#[derive(Debug, Deserialize)]
struct Reconstruction {
    cameras: BTreeMap<String, CameraJson>,
    shots: BTreeMap<String, ShotJson>,
    #[serde(default)]
    points: BTreeMap<String, PointJson>,
}

#[derive(Debug, Deserialize)]
struct CameraJson {
    projection_type: String,
    width: u64,
    height: u64,
    focal: Option<f64>,
    #[serde(default)]
    k1: f64,
    #[serde(default)]
    k2: f64,
}

#[derive(Debug, Deserialize)]
struct ShotJson {
    rotation: [f64; 3],
    translation: [f64; 3],
    camera: String,
}

#[derive(Debug, Deserialize)]
struct PointJson {
    coordinates: [f64; 3],
}

/// One row of `tracks.csv`.
#[derive(Debug, Clone, PartialEq)]
struct TrackRow {
    track: PointId,
    feature: u64,
    position: [f64; 2],
}

/// The `reconstruction.json` and `tracks.csv` paths of an OpenSfM source: a dataset folder,
/// or its `reconstruction.json` (with `tracks.csv` beside it).
pub fn model_files(path: &Path) -> (PathBuf, PathBuf) {
    let folder = if path.is_dir() {
        path
    } else {
        path.parent().unwrap_or(Path::new("."))
    };
    let reconstruction = if path.is_dir() {
        folder.join("reconstruction.json")
    } else {
        path.to_path_buf()
    };
    (reconstruction, folder.join("tracks.csv"))
}

/// The name of the scene of an OpenSfM dataset folder (or its `reconstruction.json`):
/// `opensfm/<dataset folder>`.
pub fn scene_name(path: &Path) -> String {
    let (reconstruction, _) = model_files(path);
    let folder = reconstruction.parent().and_then(file_name);
    format!("opensfm/{}", folder.unwrap_or_default())
}

/// Reads the largest reconstruction of an OpenSfM dataset folder (or `reconstruction.json`).
pub fn read_opensfm(path: &Path) -> anyhow::Result<Scene> {
    let (reconstruction, tracks) = model_files(path);
    let read =
        |p: &Path| std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()));
    let name = scene_name(path);
    parse_opensfm(&read(&reconstruction)?, &read(&tracks)?, name)
        .with_context(|| format!("parsing {}", reconstruction.display()))
}

/// Parses the texts of `reconstruction.json` and `tracks.csv` into the scene of the
/// reconstruction with the most shots (see the module documentation).
pub fn parse_opensfm(
    reconstruction_json: &str,
    tracks_csv: &str,
    name: String,
) -> Result<Scene, FormatError> {
    let reconstructions: Vec<Reconstruction> =
        serde_json::from_str(reconstruction_json).map_err(|e| FormatError::Syntax {
            line: e.line(),
            message: format!("reconstruction.json: {e}"),
        })?;
    let largest = reconstructions
        .iter()
        .rev()
        .max_by_key(|r| r.shots.len())
        .ok_or_else(|| FormatError::Syntax {
            line: 1,
            message: "reconstruction.json holds no reconstruction".into(),
        })?;
    let rows = parse_tracks(tracks_csv)?;
    assemble(name, largest, &rows)
}

/// Rows of `tracks.csv` by image name, in file order. The optional first line is the
/// `OPENSFM_TRACKS_VERSION_*` header; rows are tab-separated `image, track, feature, x, y`
/// followed by columns this reader ignores (size, colour, segmentation).
fn parse_tracks(text: &str) -> Result<BTreeMap<&str, Vec<TrackRow>>, FormatError> {
    let mut rows: BTreeMap<&str, Vec<TrackRow>> = BTreeMap::new();
    for (index, line) in text.lines().enumerate() {
        let line_number = index + 1;
        if line.trim().is_empty() || (index == 0 && line.starts_with("OPENSFM_TRACKS_VERSION")) {
            continue;
        }
        let fields: Vec<&str> = line.split('\t').collect();
        let syntax = |message: String| FormatError::Syntax {
            line: line_number,
            message,
        };
        if fields.len() < 5 {
            return Err(syntax(format!(
                "expected at least 5 tab-separated fields, found {}",
                fields.len()
            )));
        }
        let number = |i: usize, what: &str| -> Result<f64, FormatError> {
            fields[i]
                .trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| syntax(format!("{what} {:?} is not a finite number", fields[i])))
        };
        let integer = |i: usize, what: &str| -> Result<u64, FormatError> {
            fields[i]
                .trim()
                .parse::<u64>()
                .map_err(|_| syntax(format!("{what} {:?} is not an unsigned integer", fields[i])))
        };
        rows.entry(fields[0]).or_default().push(TrackRow {
            track: integer(1, "track id")?,
            feature: integer(2, "feature id")?,
            position: [number(3, "x")?, number(4, "y")?],
        });
    }
    Ok(rows)
}

/// A `perspective` camera as a COLMAP `RADIAL` camera in pixels.
fn to_camera(camera_id: CameraId, camera: &CameraJson) -> Result<Camera, FormatError> {
    let unsupported = || FormatError::UnsupportedCameraModel {
        camera_id: camera_id.into(),
        model: camera.projection_type.clone(),
    };
    if camera.projection_type != "perspective" {
        return Err(unsupported());
    }
    let focal = camera.focal.ok_or_else(unsupported)?;
    let side = |value: u64| {
        u32::try_from(value).map_err(|_| FormatError::OutOfRange {
            what: "image side",
            value,
            limit: u64::from(u32::MAX),
        })
    };
    let (width, height) = (side(camera.width)?, side(camera.height)?);
    let size = f64::from(width.max(height));
    Camera::from_colmap(
        CameraModel::Radial,
        width,
        height,
        &[
            focal * size,
            f64::from(width) / 2.0,
            f64::from(height) / 2.0,
            camera.k1,
            camera.k2,
        ],
    )
    .map_err(|reason| FormatError::InvalidCamera {
        camera_id: camera_id.into(),
        reason,
    })
}

fn point_id(key: &str) -> Result<PointId, FormatError> {
    key.parse().map_err(|_| FormatError::Syntax {
        line: 1,
        message: format!("point id {key:?} is not an unsigned integer"),
    })
}

/// Builds the scene of one reconstruction: camera and image ids are the positions of their
/// keys in sorted order, point ids the (integer) point keys.
fn assemble(
    name: String,
    reconstruction: &Reconstruction,
    rows: &BTreeMap<&str, Vec<TrackRow>>,
) -> Result<Scene, FormatError> {
    let mut scene = Scene {
        name,
        ..Scene::default()
    };
    let mut camera_ids = BTreeMap::new();
    for (index, (key, camera)) in reconstruction.cameras.iter().enumerate() {
        let id = CameraId::try_from(index).map_err(|_| FormatError::OutOfRange {
            what: "camera count",
            value: index as u64,
            limit: u64::from(CameraId::MAX),
        })?;
        if reconstruction.shots.values().any(|s| &s.camera == key) {
            scene.cameras.insert(id, to_camera(id, camera)?);
        }
        camera_ids.insert(key.as_str(), id);
    }
    for (key, point) in &reconstruction.points {
        let id = point_id(key)?;
        let xyz = Vector3::from(point.coordinates);
        scene.points.insert(
            id,
            Point3d {
                id,
                xyz,
                track: Vec::new(),
            },
        );
    }
    for (index, (shot_name, shot)) in reconstruction.shots.iter().enumerate() {
        let id = ImageId::try_from(index).map_err(|_| FormatError::OutOfRange {
            what: "shot count",
            value: index as u64,
            limit: u64::from(ImageId::MAX),
        })?;
        let camera_id =
            *camera_ids
                .get(shot.camera.as_str())
                .ok_or_else(|| FormatError::Syntax {
                    line: 1,
                    message: format!("shot {shot_name:?} uses undefined camera {:?}", shot.camera),
                })?;
        let image = build_image(&mut scene, id, shot_name, shot, camera_id, rows)?;
        scene.images.insert(id, image);
    }
    Ok(scene)
}

/// One shot's image: its pose and its tracked features in feature-id order, linked to the
/// scene's points (whose tracks it extends).
fn build_image(
    scene: &mut Scene,
    id: ImageId,
    shot_name: &str,
    shot: &ShotJson,
    camera_id: CameraId,
    rows: &BTreeMap<&str, Vec<TrackRow>>,
) -> Result<Image, FormatError> {
    let rotation = Rotation3::new(Vector3::from(shot.rotation)).into_inner();
    let matrix = [0, 1, 2].map(|i| [rotation[(i, 0)], rotation[(i, 1)], rotation[(i, 2)]]);
    let pose = Pose::from_matrix(&matrix, &shot.translation).map_err(|reason| {
        FormatError::InvalidPose {
            image_id: id.into(),
            reason,
        }
    })?;
    let camera = scene.cameras[&camera_id];
    let size = f64::from(camera.width.max(camera.height));
    let centre = [
        f64::from(camera.width) / 2.0,
        f64::from(camera.height) / 2.0,
    ];
    let mut features = rows.get(shot_name).cloned().unwrap_or_default();
    features.sort_by_key(|row| row.feature);
    let mut keypoints = Vec::with_capacity(features.len());
    for row in features {
        let keypoint_index =
            u32::try_from(keypoints.len()).map_err(|_| FormatError::OutOfRange {
                what: "features of one shot",
                value: keypoints.len() as u64,
                limit: u64::from(u32::MAX),
            })?;
        let point = scene.points.get_mut(&row.track);
        let point3d = point.map(|p| {
            p.track.push(TrackElement {
                image_id: id,
                keypoint_index,
            });
            p.id
        });
        keypoints.push(Keypoint {
            pixel: [
                row.position[0] * size + centre[0],
                row.position[1] * size + centre[1],
            ],
            point3d,
        });
    }
    Ok(Image {
        id,
        name: shot_name.to_string(),
        camera_id,
        pose,
        keypoints,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const JSON: &str = r#"[
      {"cameras": {"c": {"projection_type": "perspective", "width": 200, "height": 100,
                          "focal": 1.0, "k1": 0.0, "k2": 0.0}},
       "shots": {"a.jpg": {"rotation": [0, 0, 0], "translation": [0, 0, 2], "camera": "c"}},
       "points": {"7": {"coordinates": [0.5, 0.25, 0.0]}}},
      {"cameras": {"c": {"projection_type": "perspective", "width": 200, "height": 100,
                          "focal": 1.0}},
       "shots": {"a.jpg": {"rotation": [0, 0, 0], "translation": [0, 0, 2], "camera": "c"},
                 "b.jpg": {"rotation": [0, 0, 0], "translation": [1, 0, 2], "camera": "c"}},
       "points": {"7": {"coordinates": [0.5, 0.25, 0.0]}}}
    ]"#;
    const TRACKS: &str = "OPENSFM_TRACKS_VERSION_v1\n\
        a.jpg\t7\t5\t0.25\t0.125\t0.01\t0\t0\t0\n\
        a.jpg\t9\t2\t0.1\t0.1\t0.01\t0\t0\t0\n\
        b.jpg\t7\t3\t0.75\t0.125\t0.01\t0\t0\t0\n\
        c.jpg\t7\t1\t0.0\t0.0\t0.01\t0\t0\t0\n";

    #[test]
    fn largest_reconstruction_with_untriangulated_tracks() {
        let scene = parse_opensfm(JSON, TRACKS, "opensfm/tiny".into()).unwrap();
        scene.validate().unwrap();
        assert_eq!(scene.images.len(), 2);
        assert_eq!(scene.points[&7].track.len(), 2);
        // Feature order: feature 2 (track 9, not reconstructed) before feature 5.
        let a = &scene.images[&0];
        assert_eq!(a.keypoints[0].point3d, None);
        assert_eq!(a.keypoints[1].point3d, Some(7));
        assert_eq!(a.keypoints[1].pixel, [150.0, 75.0]);
        // The stored poses reproject the point exactly onto its features.
        assert!(scene.median_reprojection_error(None, 0).unwrap() < 1e-9);
    }

    #[test]
    fn malformed_inputs_are_typed_errors() {
        let bad_json = parse_opensfm("[{", TRACKS, "x".into());
        assert!(matches!(bad_json, Err(FormatError::Syntax { .. })));
        let bad_row = parse_opensfm(JSON, "a.jpg\t7\t5\t0.25\n", "x".into());
        assert!(matches!(bad_row, Err(FormatError::Syntax { line: 1, .. })));
        let nan = parse_opensfm(JSON, "a.jpg\t7\t5\tnan\t0\n", "x".into());
        assert!(matches!(nan, Err(FormatError::Syntax { .. })));
        let huge = JSON.replace("\"width\": 200", "\"width\": 99999999999");
        assert!(matches!(
            parse_opensfm(&huge, TRACKS, "x".into()),
            Err(FormatError::OutOfRange { .. })
        ));
        let fisheye = JSON.replace("perspective", "fisheye");
        assert!(matches!(
            parse_opensfm(&fisheye, TRACKS, "x".into()),
            Err(FormatError::UnsupportedCameraModel { .. })
        ));
        assert!(matches!(
            parse_opensfm("[]", TRACKS, "x".into()),
            Err(FormatError::Syntax { .. })
        ));
    }
}
