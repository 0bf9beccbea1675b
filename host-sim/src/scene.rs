//! The common in-memory structure-from-motion model: cameras, posed images with their 2D
//! keypoints, and 3D points with their tracks. Every reader (COLMAP, BAL, Bundler, OpenSfM,
//! [`crate::readers`]) and the synthetic simulator produce a [`Scene`]; the localization
//! protocol consumes one.
//!
//! Conventions (COLMAP's): poses map world to camera, `x_cam = R x + t`; the camera looks
//! along +z; pixels have their origin at the top-left corner with y pointing down.

use std::collections::{BTreeMap, BTreeSet};

use gomatch::{Camera, Pose};
use nalgebra::Vector3;
use rand::SeedableRng;
use rand_pcg::Pcg64Mcg;

/// Identifier of a camera (intrinsics) in its source model.
pub type CameraId = u32;
/// Identifier of an image in its source model.
pub type ImageId = u32;
/// Identifier of a 3D point in its source model.
pub type PointId = u64;

/// One 2D keypoint of an image: its pixel and the 3D point it triangulates, if any.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Keypoint {
    /// Pixel position (origin top-left, y down).
    pub pixel: [f64; 2],
    /// The 3D point observed at this keypoint, `None` for an untriangulated keypoint.
    pub point3d: Option<PointId>,
}

/// A registered image: its camera, its world-to-camera pose and its keypoints.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    /// Identifier in the source model.
    pub id: ImageId,
    /// File name in the source model (or a generated name).
    pub name: String,
    /// The camera (intrinsics) this image was taken with.
    pub camera_id: CameraId,
    /// World-to-camera pose.
    pub pose: Pose,
    /// All keypoints, triangulated or not, in the order the source model stores them.
    pub keypoints: Vec<Keypoint>,
}

impl Image {
    /// The keypoints with their indices in the order a detector capped at N keypoints
    /// keeps them, best first: the reverse stored order. A capped SIFT detector keeps its
    /// larger-scale features (COLMAP's `max_num_features`), and the VLFeat extractors
    /// behind COLMAP and openMVG models emit keypoints octave by octave, fine to coarse, as
    /// OpenSfM sorts its features by increasing size; models of extractors that store their
    /// best keypoints first are turned around on loading ([`Scene::orient_keypoint_order`]).
    /// (BAL and Bundler files store no keypoint order and the simulator shuffles, so there
    /// the rank is arbitrary.)
    pub fn ranked_keypoints(&self) -> impl Iterator<Item = (usize, &Keypoint)> {
        self.keypoints.iter().enumerate().rev()
    }

    /// Distinct 3D points the image observes, in [`Image::ranked_keypoints`] order (a
    /// point seen at several keypoints comes at its best rank).
    pub fn observed_points(&self) -> Vec<PointId> {
        let mut seen = BTreeSet::new();
        self.ranked_keypoints()
            .filter_map(|(_, k)| k.point3d)
            .filter(|id| seen.insert(*id))
            .collect()
    }

    /// Number of keypoints that observe a 3D point.
    pub fn triangulated_count(&self) -> usize {
        self.keypoints
            .iter()
            .filter(|k| k.point3d.is_some())
            .count()
    }
}

/// One observation of a 3D point: which image, and which keypoint of that image.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TrackElement {
    /// The observing image.
    pub image_id: ImageId,
    /// Index into that image's `keypoints`.
    pub keypoint_index: u32,
}

/// A triangulated 3D point and the keypoints that observe it.
#[derive(Debug, Clone, PartialEq)]
pub struct Point3d {
    /// Identifier in the source model.
    pub id: PointId,
    /// World coordinates.
    pub xyz: Vector3<f64>,
    /// Every observation of the point.
    pub track: Vec<TrackElement>,
}

/// A whole structure-from-motion model. Maps are ordered by id, so every iteration over a
/// scene is deterministic.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Scene {
    /// Name used in reports and dataset metadata, e.g. `colmap/mouse`.
    pub name: String,
    /// Intrinsics by id.
    pub cameras: BTreeMap<CameraId, Camera>,
    /// Registered images by id.
    pub images: BTreeMap<ImageId, Image>,
    /// 3D points by id.
    pub points: BTreeMap<PointId, Point3d>,
}

/// A model that is not a consistent scene.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SceneError {
    /// An image refers to a camera the model does not define.
    #[error("image {image_id} uses camera {camera_id}, which the model does not define")]
    MissingCamera {
        /// The image.
        image_id: ImageId,
        /// The undefined camera.
        camera_id: CameraId,
    },
    /// A keypoint refers to a 3D point the model does not define.
    #[error("image {image_id} keypoint {keypoint_index} refers to undefined 3D point {point_id}")]
    MissingPoint {
        /// The image.
        image_id: ImageId,
        /// The keypoint.
        keypoint_index: usize,
        /// The undefined point.
        point_id: PointId,
    },
    /// A track element names an image or keypoint that does not exist, or a keypoint that
    /// does not refer back to the point.
    #[error("3D point {point_id}: track element (image {image_id}, keypoint {keypoint_index}) does not refer back to it")]
    BrokenTrack {
        /// The point.
        point_id: PointId,
        /// The image of the track element.
        image_id: ImageId,
        /// The keypoint index of the track element.
        keypoint_index: u32,
    },
    /// A keypoint triangulates a point whose track does not list it.
    #[error("image {image_id} keypoint {keypoint_index} observes 3D point {point_id}, whose track does not list it")]
    UntrackedObservation {
        /// The image.
        image_id: ImageId,
        /// The keypoint.
        keypoint_index: usize,
        /// The point.
        point_id: PointId,
    },
    /// A pixel or a 3D coordinate is NaN or infinite.
    #[error("non-finite coordinate in {what}")]
    NonFinite {
        /// Which item holds it.
        what: String,
    },
}

impl Scene {
    /// Checks that every reference resolves: image cameras, keypoint points, and tracks in
    /// both directions (a track element's keypoint points back to the point, and every
    /// triangulated keypoint appears in its point's track); and that coordinates are finite.
    pub fn validate(&self) -> Result<(), SceneError> {
        for image in self.images.values() {
            if !self.cameras.contains_key(&image.camera_id) {
                return Err(SceneError::MissingCamera {
                    image_id: image.id,
                    camera_id: image.camera_id,
                });
            }
            for (index, keypoint) in image.keypoints.iter().enumerate() {
                if !keypoint.pixel.iter().all(|v| v.is_finite()) {
                    return Err(SceneError::NonFinite {
                        what: format!("image {} keypoint {index}", image.id),
                    });
                }
                let Some(point_id) = keypoint.point3d else {
                    continue;
                };
                let Some(point) = self.points.get(&point_id) else {
                    return Err(SceneError::MissingPoint {
                        image_id: image.id,
                        keypoint_index: index,
                        point_id,
                    });
                };
                let listed = point.track.iter().any(|e| {
                    e.image_id == image.id && usize::try_from(e.keypoint_index) == Ok(index)
                });
                if !listed {
                    return Err(SceneError::UntrackedObservation {
                        image_id: image.id,
                        keypoint_index: index,
                        point_id,
                    });
                }
            }
        }
        for point in self.points.values() {
            if !point.xyz.iter().all(|v| v.is_finite()) {
                return Err(SceneError::NonFinite {
                    what: format!("3D point {}", point.id),
                });
            }
            for element in &point.track {
                let refers_back = self
                    .keypoint(element.image_id, element.keypoint_index)
                    .is_some_and(|k| k.point3d == Some(point.id));
                if !refers_back {
                    return Err(SceneError::BrokenTrack {
                        point_id: point.id,
                        image_id: element.image_id,
                        keypoint_index: element.keypoint_index,
                    });
                }
            }
        }
        Ok(())
    }

    /// The keypoint `index` of image `image_id`, if both exist.
    pub fn keypoint(&self, image_id: ImageId, index: u32) -> Option<&Keypoint> {
        let image = self.images.get(&image_id)?;
        image.keypoints.get(usize::try_from(index).ok()?)
    }

    /// The camera of an image. A validated scene always has it.
    pub fn camera_of(&self, image: &Image) -> Option<&Camera> {
        self.cameras.get(&image.camera_id)
    }

    /// Total number of observations (track elements) over all points.
    pub fn observation_count(&self) -> usize {
        self.points.values().map(|p| p.track.len()).sum()
    }

    /// Pixel reprojection errors of one point over its observations: the distance between
    /// each observing keypoint and the point projected with that image's pose and camera.
    /// Observations behind the camera or outside the camera model's range are skipped.
    pub fn reprojection_errors(&self, point: &Point3d) -> Vec<f64> {
        point
            .track
            .iter()
            .filter_map(|element| {
                let image = self.images.get(&element.image_id)?;
                let camera = self.camera_of(image)?;
                let keypoint = self.keypoint(element.image_id, element.keypoint_index)?;
                let bearing = image.pose.bearing(&point.xyz, 0).ok()?;
                let projected = camera.bearing_to_pixel(bearing).ok()?;
                Some(
                    ((projected[0] - keypoint.pixel[0]).powi(2)
                        + (projected[1] - keypoint.pixel[1]).powi(2))
                    .sqrt(),
                )
            })
            .collect()
    }

    /// Median pixel reprojection error over all observations of `sample` points drawn
    /// without replacement with `seed` (all points when `sample` is `None` or exceeds their
    /// number). `None` when there is no observation.
    pub fn median_reprojection_error(&self, sample: Option<usize>, seed: u64) -> Option<f64> {
        let points: Vec<&Point3d> = self.points.values().collect();
        let chosen: Vec<&Point3d> = match sample {
            Some(n) if n < points.len() => {
                let mut rng = Pcg64Mcg::seed_from_u64(seed);
                let mut indices = rand::seq::index::sample(&mut rng, points.len(), n).into_vec();
                indices.sort_unstable();
                indices.into_iter().map(|i| points[i]).collect()
            }
            _ => points,
        };
        let mut errors: Vec<f64> = chosen
            .iter()
            .flat_map(|p| self.reprojection_errors(p))
            .collect();
        median(&mut errors)
    }
}

/// Keypoints per block when the two ends of the stored order are compared: the protocol's
/// cap, the only place where the order matters.
pub const RANK_BLOCK: usize = 1024;

impl Scene {
    /// Mean triangulated share of the first and of the last `block` stored keypoints over
    /// the images with more than `block` keypoints; `None` when no image has that many.
    pub fn stored_order_shares(&self, block: usize) -> Option<(f64, f64)> {
        let share = |keypoints: &[Keypoint]| {
            let triangulated = keypoints.iter().filter(|k| k.point3d.is_some()).count();
            triangulated as f64 / keypoints.len().max(1) as f64
        };
        let capped: Vec<(f64, f64)> = self
            .images
            .values()
            .filter(|image| image.keypoints.len() > block.max(1))
            .map(|image| {
                let k = &image.keypoints;
                (share(&k[..block]), share(&k[k.len() - block..]))
            })
            .collect();
        let n = capped.len() as f64;
        (!capped.is_empty()).then(|| {
            let first = capped.iter().map(|c| c.0).sum::<f64>() / n;
            let last = capped.iter().map(|c| c.1).sum::<f64>() / n;
            (first, last)
        })
    }

    /// Makes the stored order end with the keypoints a capped detector keeps, as
    /// [`Image::ranked_keypoints`] expects: when the first `block` stored keypoints are
    /// triangulated more often than the last ones over the scene (an extractor that stores
    /// its best keypoints first, seen in 7 of the 25 COLMAP training models with capped
    /// images, docs/evaluation.md "Keypoint order"), every image's keypoints are reversed and the
    /// tracks renumbered. Which end is best is one bit per model (one extractor); scenes
    /// without capped images keep their order. Returns whether the order was reversed.
    pub fn orient_keypoint_order(&mut self, block: usize) -> bool {
        match self.stored_order_shares(block) {
            Some((first, last)) if first > last => {}
            _ => return false,
        }
        let mut lengths = BTreeMap::new();
        for image in self.images.values_mut() {
            image.keypoints.reverse();
            lengths.insert(image.id, image.keypoints.len() as u32);
        }
        for point in self.points.values_mut() {
            for element in &mut point.track {
                if let Some(&n) = lengths.get(&element.image_id) {
                    element.keypoint_index =
                        n.saturating_sub(1).saturating_sub(element.keypoint_index);
                }
            }
        }
        true
    }
}

/// Median of a list (mean of the two middle values for an even count); `None` when empty.
/// The slice is sorted in place.
pub fn median(values: &mut [f64]) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    values.sort_by(f64::total_cmp);
    let mid = values.len() / 2;
    Some(if values.len().is_multiple_of(2) {
        0.5 * (values[mid - 1] + values[mid])
    } else {
        values[mid]
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use gomatch::camera::CameraModel;

    fn two_view_scene() -> Scene {
        let camera =
            Camera::from_colmap(CameraModel::SimplePinhole, 640, 480, &[500.0, 320.0, 240.0])
                .unwrap();
        let point = Vector3::new(0.2, -0.1, 5.0);
        let poses = [
            Pose::identity(),
            Pose::new(
                nalgebra::Rotation3::identity(),
                Vector3::new(-0.5, 0.0, 0.0),
            ),
        ];
        let mut scene = Scene {
            name: "test".into(),
            ..Scene::default()
        };
        scene.cameras.insert(1, camera);
        let mut track = Vec::new();
        for (i, pose) in poses.iter().enumerate() {
            let id = i as ImageId + 1;
            let pixel = camera
                .bearing_to_pixel(pose.bearing(&point, 0).unwrap())
                .unwrap();
            let offset = if i == 0 { 0.0 } else { 3.0 };
            scene.images.insert(
                id,
                Image {
                    id,
                    name: format!("{id}.png"),
                    camera_id: 1,
                    pose: *pose,
                    keypoints: vec![
                        Keypoint {
                            pixel: [10.0, 10.0],
                            point3d: None,
                        },
                        Keypoint {
                            pixel: [pixel[0] + offset, pixel[1]],
                            point3d: Some(7),
                        },
                    ],
                },
            );
            track.push(TrackElement {
                image_id: id,
                keypoint_index: 1,
            });
        }
        scene.points.insert(
            7,
            Point3d {
                id: 7,
                xyz: point,
                track,
            },
        );
        scene
    }

    #[test]
    fn reprojection_errors_measure_pixel_offsets() {
        let scene = two_view_scene();
        scene.validate().unwrap();
        let errors = scene.reprojection_errors(&scene.points[&7]);
        assert_eq!(errors.len(), 2);
        assert!(errors[0] < 1e-9);
        assert!((errors[1] - 3.0).abs() < 1e-9);
        assert!((scene.median_reprojection_error(None, 0).unwrap() - 1.5).abs() < 1e-9);
    }

    #[test]
    fn validation_catches_broken_references() {
        let mut scene = two_view_scene();
        scene.images.get_mut(&2).unwrap().keypoints[0].point3d = Some(7);
        assert!(matches!(
            scene.validate(),
            Err(SceneError::UntrackedObservation { image_id: 2, .. })
        ));
        let mut scene = two_view_scene();
        scene.points.get_mut(&7).unwrap().track.push(TrackElement {
            image_id: 2,
            keypoint_index: 0,
        });
        assert!(matches!(
            scene.validate(),
            Err(SceneError::BrokenTrack { point_id: 7, .. })
        ));
        let mut scene = two_view_scene();
        scene.images.get_mut(&1).unwrap().camera_id = 9;
        assert!(matches!(
            scene.validate(),
            Err(SceneError::MissingCamera { camera_id: 9, .. })
        ));
    }

    #[test]
    fn keypoint_order_is_turned_when_the_best_come_first() {
        let mut scene = two_view_scene();
        // Keypoint 1 (triangulated) after keypoint 0 (not): already best last.
        assert_eq!(scene.stored_order_shares(1), Some((0.0, 1.0)));
        assert!(!scene.orient_keypoint_order(1));
        for image in scene.images.values_mut() {
            image.keypoints.swap(0, 1);
        }
        for element in &mut scene.points.get_mut(&7).unwrap().track {
            element.keypoint_index = 0;
        }
        scene.validate().unwrap();
        assert!(scene.orient_keypoint_order(1));
        scene.validate().unwrap();
        assert_eq!(scene.stored_order_shares(1), Some((0.0, 1.0)));
        assert_eq!(scene.stored_order_shares(2), None);
    }

    #[test]
    fn median_of_even_and_odd_lists() {
        assert_eq!(median(&mut [3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&mut [4.0, 1.0, 2.0, 3.0]), Some(2.5));
        assert_eq!(median(&mut []), None);
    }
}
