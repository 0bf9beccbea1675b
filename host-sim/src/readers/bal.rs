//! Bundle Adjustment in the Large (BAL) problem reader, and the conversion of the
//! Bundler/BAL camera convention to the project's (COLMAP's) one, shared with the Bundler
//! reader.
//!
//! BAL/Bundler: `P = R X + t`, the camera looks down -z, `p = -P / P_z`, and the observed
//! pixel, with its origin at the image centre and y pointing up, is
//! `f (1 + k1 |p|^2 + k2 |p|^4) p`.
//!
//! Conversion, exact: with `C = diag(1, -1, -1)` (a rotation by pi about x), the camera
//! frame `P' = C P` looks down +z with y down, so the pose becomes `R' = C R`, `t' = C t`;
//! its bearing `(P'_x / P'_z, P'_y / P'_z) = (p_x, -p_y)`; and the observation `(x, y)`
//! becomes the pixel `(x, -y)` of a COLMAP `RADIAL` camera `f, cx = 0, cy = 0, k1, k2`.
//! The principal point stays at the origin because these files do not record image sizes.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::Context;
use gomatch::camera::CameraModel;
use gomatch::{Camera, Pose};
use nalgebra::{Matrix3, Rotation3, Vector3};

use crate::readers::parse::{FormatError, Tokens};
use crate::scene::{Image, ImageId, Keypoint, Point3d, Scene, TrackElement};

/// One camera of a BAL/Bundler file in its own convention.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BundlerCamera {
    /// World-to-camera rotation (camera looking down -z, y up).
    pub rotation: Matrix3<f64>,
    /// Translation.
    pub translation: Vector3<f64>,
    /// Focal length in pixels.
    pub focal: f64,
    /// Radial distortion coefficients of `|p|^2` and `|p|^4`.
    pub k1: f64,
    /// See `k1`.
    pub k2: f64,
}

impl BundlerCamera {
    /// The equivalent COLMAP `RADIAL` camera (principal point at the origin) and
    /// world-to-camera pose in the +z-forward, y-down convention.
    pub fn to_colmap(&self, camera_id: u64) -> Result<(Camera, Pose), FormatError> {
        let camera = Camera::from_colmap(
            CameraModel::Radial,
            0,
            0,
            &[self.focal, 0.0, 0.0, self.k1, self.k2],
        )
        .map_err(|reason| FormatError::InvalidCamera { camera_id, reason })?;
        let flip = Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0));
        let r = flip * self.rotation;
        let t = flip * self.translation;
        let rows = [
            [r[(0, 0)], r[(0, 1)], r[(0, 2)]],
            [r[(1, 0)], r[(1, 1)], r[(1, 2)]],
            [r[(2, 0)], r[(2, 1)], r[(2, 2)]],
        ];
        let pose = Pose::from_matrix(&rows, &[t.x, t.y, t.z]).map_err(|reason| {
            FormatError::InvalidPose {
                image_id: camera_id,
                reason,
            }
        })?;
        Ok((camera, pose))
    }
}

/// An observation `(x, y)` (origin at the image centre, y up) as a pixel of the converted
/// camera (y down).
pub fn observation_to_pixel([x, y]: [f64; 2]) -> [f64; 2] {
    [x, -y]
}

/// One observation of a BAL/Bundler file: camera index, point index, observed position.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Observation {
    /// Index of the observing camera in the file.
    pub camera: usize,
    /// Index of the observed point in the file.
    pub point: usize,
    /// Position as stored (origin at the image centre, y up).
    pub position: [f64; 2],
}

/// Builds a [`Scene`] from BAL/Bundler cameras (`None` for unplaced ones, which are
/// skipped with their observations), points and observations. Image and camera ids are the
/// camera indices, point ids the point indices; each image's keypoints are its
/// observations in file order.
pub fn assemble_scene(
    name: String,
    cameras: &[Option<BundlerCamera>],
    points: &[Vector3<f64>],
    observations: &[Observation],
) -> Result<Scene, FormatError> {
    let mut scene = Scene {
        name,
        ..Scene::default()
    };
    for (index, camera) in cameras.iter().enumerate() {
        let Some(camera) = camera else { continue };
        let id = image_id(index, cameras.len())?;
        let (intrinsics, pose) = camera.to_colmap(id.into())?;
        scene.cameras.insert(id, intrinsics);
        scene.images.insert(
            id,
            Image {
                id,
                name: format!("{index:05}"),
                camera_id: id,
                pose,
                keypoints: Vec::new(),
            },
        );
    }
    let mut tracks: BTreeMap<usize, Vec<TrackElement>> = BTreeMap::new();
    for observation in observations {
        if observation.point >= points.len() {
            return Err(FormatError::OutOfRange {
                what: "observed point index",
                value: observation.point as u64,
                limit: points.len() as u64,
            });
        }
        let id = image_id(observation.camera, cameras.len())?;
        let Some(image) = scene.images.get_mut(&id) else {
            continue; // an unplaced camera
        };
        let keypoint_index =
            u32::try_from(image.keypoints.len()).map_err(|_| FormatError::OutOfRange {
                what: "observations of one camera",
                value: image.keypoints.len() as u64,
                limit: u64::from(u32::MAX),
            })?;
        image.keypoints.push(Keypoint {
            pixel: observation_to_pixel(observation.position),
            point3d: Some(observation.point as u64),
        });
        tracks
            .entry(observation.point)
            .or_default()
            .push(TrackElement {
                image_id: id,
                keypoint_index,
            });
    }
    for (index, xyz) in points.iter().enumerate() {
        let id = index as u64;
        let track = tracks.remove(&index).unwrap_or_default();
        scene.points.insert(
            id,
            Point3d {
                id,
                xyz: *xyz,
                track,
            },
        );
    }
    Ok(scene)
}

fn image_id(camera_index: usize, camera_count: usize) -> Result<ImageId, FormatError> {
    if camera_index >= camera_count {
        return Err(FormatError::OutOfRange {
            what: "camera index",
            value: camera_index as u64,
            limit: camera_count as u64,
        });
    }
    ImageId::try_from(camera_index).map_err(|_| FormatError::OutOfRange {
        what: "camera index",
        value: camera_index as u64,
        limit: u64::from(ImageId::MAX),
    })
}

/// Tokens of one BAL camera record: Rodrigues rotation, translation, f, k1, k2.
const CAMERA_TOKENS: usize = 9;
/// Tokens of one BAL point record.
const POINT_TOKENS: usize = 3;
/// Tokens of one BAL observation record: camera, point, x, y.
const OBSERVATION_TOKENS: usize = 4;

/// Reads a BAL problem file (see the module documentation for the conversion).
pub fn read_bal(path: &Path) -> anyhow::Result<Scene> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let name = scene_name(path);
    parse_bal(&text, name).with_context(|| format!("parsing {}", path.display()))
}

/// The name of the scene of a BAL problem file: `bal/<file stem>`.
pub fn scene_name(path: &Path) -> String {
    let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned());
    format!("bal/{}", stem.unwrap_or_default())
}

/// Parses the text of a BAL problem: `num_cameras num_points num_observations`, the
/// observations `camera point x y`, 9 parameters per camera (Rodrigues rotation,
/// translation, f, k1, k2), 3 coordinates per point.
pub fn parse_bal(text: &str, name: String) -> Result<Scene, FormatError> {
    let mut tokens = Tokens::new(text, 0);
    // Each count is bounded by the records the rest of the file can hold, so that the
    // reservations below never exceed what the file holds.
    let camera_count = tokens.count("the camera count", CAMERA_TOKENS)?;
    let point_count = tokens.count("the point count", POINT_TOKENS)?;
    let observation_count = tokens.count("the observation count", OBSERVATION_TOKENS)?;
    let mut observations = Vec::with_capacity(observation_count);
    for _ in 0..observation_count {
        observations.push(Observation {
            camera: tokens.parse("an observation's camera index")?,
            point: tokens.parse("an observation's point index")?,
            position: tokens.f64s::<2>("an observation's coordinates")?,
        });
    }
    let mut cameras = Vec::with_capacity(camera_count);
    for _ in 0..camera_count {
        let [rx, ry, rz, tx, ty, tz, focal, k1, k2] = tokens.f64s::<9>("a camera parameter")?;
        cameras.push(Some(BundlerCamera {
            rotation: Rotation3::new(Vector3::new(rx, ry, rz)).into_inner(),
            translation: Vector3::new(tx, ty, tz),
            focal,
            k1,
            k2,
        }));
    }
    let mut points = Vec::with_capacity(point_count);
    for _ in 0..point_count {
        points.push(Vector3::from(tokens.f64s::<3>("a point coordinate")?));
    }
    tokens.finish()?;
    assemble_scene(name, &cameras, &points, &observations)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Projects a point with the BAL model as its documentation states it.
    fn bal_project(camera: &BundlerCamera, x: &Vector3<f64>) -> [f64; 2] {
        let p = camera.rotation * x + camera.translation;
        let (px, py) = (-p.x / p.z, -p.y / p.z);
        let r2 = px * px + py * py;
        let scale = camera.focal * (1.0 + camera.k1 * r2 + camera.k2 * r2 * r2);
        [scale * px, scale * py]
    }

    #[test]
    fn conversion_reproduces_the_bal_projection_exactly() {
        let camera = BundlerCamera {
            rotation: Rotation3::new(Vector3::new(0.1, -0.2, 0.3)).into_inner(),
            translation: Vector3::new(0.2, -0.1, -4.0),
            focal: 800.0,
            k1: -0.05,
            k2: 0.01,
        };
        let point = Vector3::new(0.3, 0.4, 0.5);
        let observed = bal_project(&camera, &point);
        let (intrinsics, pose) = camera.to_colmap(0).unwrap();
        let bearing = pose.bearing(&point, 0).unwrap();
        let pixel = intrinsics.bearing_to_pixel(bearing).unwrap();
        let expected = observation_to_pixel(observed);
        assert!((pixel[0] - expected[0]).abs() < 1e-9);
        assert!((pixel[1] - expected[1]).abs() < 1e-9);
    }

    #[test]
    fn parses_a_tiny_problem_into_consistent_tracks() {
        let text = "2 1 2\n0 0 1.0 2.0\n1 0 -1.0 0.5\n\
                    0 0 0 0 0 -5 500 0 0\n0 0 0 1 0 -5 500 0 0\n0 0 0\n";
        let scene = parse_bal(text, "bal/tiny".into()).unwrap();
        scene.validate().unwrap();
        assert_eq!(scene.images.len(), 2);
        assert_eq!(scene.points[&0].track.len(), 2);
        assert_eq!(scene.images[&1].keypoints[0].pixel, [-1.0, -0.5]);
    }

    #[test]
    fn malformed_problems_are_typed_errors() {
        assert!(matches!(
            parse_bal("1 1 1\n0 3 1 2\n0 0 0 0 0 -5 500 0 0\n0 0 0\n", "x".into()),
            Err(FormatError::OutOfRange {
                what: "observed point index",
                ..
            })
        ));
        assert!(matches!(
            parse_bal("1 1 1\n0 0 1 2\n0 0 0 0 0 -5 500 0\n", "x".into()),
            Err(FormatError::Syntax { .. })
        ));
        assert!(matches!(
            parse_bal("1 1 0\n0 0 0 0 0 -5 0 0 0\n0 0 0\n", "x".into()),
            Err(FormatError::InvalidCamera { camera_id: 0, .. })
        ));
        assert!(matches!(
            parse_bal("1 1 0\n0 0 0 0 0 -5 500 0 0\n0 0 0\n7\n", "x".into()),
            Err(FormatError::Syntax { line: 4, .. })
        ));
        assert!(matches!(
            parse_bal("99999999999 1 1", "x".into()),
            Err(FormatError::OutOfRange { .. })
        ));
    }
}
