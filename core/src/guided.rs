//! Guided re-matching: RANSAC-PnP's pose predicts where each selected view's points fall in
//! the query, each keypoint is paired with the nearest predicted point, and RANSAC-PnP
//! ([`crate::ransac`]) re-estimates the pose on those pairs, in rounds of shrinking radius.
//! The acceptance rule then judges the re-matched pose, its inliers one of the features
//! ([`crate::acceptance`]).
//!
//! Not in the paper, whose pipeline ends with RANSAC-PnP on the network's matches (sec.
//! 4.1): it is the guided matching of structure-based localization, geometric only like the
//! matcher (positions, no descriptors). The network's matches locate the pose; the points it
//! left unmatched, once projected, pin it down, and under a wrong pose they do not line up
//! (`docs/evaluation.md`, "Guided re-matching").
//!
//! A round, on the query's normalised image plane:
//! 1. [`nearest_points`]: per keypoint, the nearest projected point within the radius;
//! 2. [`keep_mutual`]: a pair stays when no other keypoint lies closer to its point;
//! 3. RANSAC-PnP on the pairs; its pose replaces the current one when it has at least
//!    [`MIN_INLIERS`] inliers, otherwise the rounds stop.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::pose::{camera_bearing, Pose};

/// Rounds of re-matching, one per search radius.
pub const ROUNDS: usize = 4;
/// Fewest RANSAC inliers a round's pose needs to replace the pose.
pub const MIN_INLIERS: usize = 6;
/// A keypoint without a paired point.
pub const UNPAIRED: u32 = u32::MAX;

/// Settings of guided re-matching.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GuidedConfig {
    /// Search radius of each round in pixels of the query image (converted with its mean
    /// focal length), largest first.
    pub radii_px: [f64; ROUNDS],
}

impl Default for GuidedConfig {
    fn default() -> Self {
        Self::new()
    }
}

impl GuidedConfig {
    /// Radii 40, 20, 10 and 5 px (chosen on the validation scenes; 10 and 5 px alone, or
    /// from 80 px down, give the same accuracy within a few tenths of AUC at N = 1024).
    pub const fn new() -> Self {
        Self {
            radii_px: [40.0, 20.0, 10.0, 5.0],
        }
    }

    /// [`Error::InvalidConfig`] (`guided_radius`) unless every radius is finite and positive.
    pub fn check(&self) -> Result<()> {
        if self.radii_px.iter().all(|r| r.is_finite() && *r > 0.0) {
            Ok(())
        } else {
            Err(Error::InvalidConfig {
                parameter: "guided_radius",
            })
        }
    }
}

/// What guided re-matching did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct GuidedCounts {
    /// Rounds whose pose replaced the pose (0: the pose is RANSAC-PnP's on the network's
    /// matches).
    pub rounds: u8,
    /// Pairs of the last such round (at most the capacity, below 2^16).
    pub pairs: u16,
    /// RANSAC-PnP inliers among them.
    pub inliers: u16,
}

/// The bearing of a world point in the camera of `pose` ([`camera_bearing`]).
fn project(pose: &Pose, point: [f64; 3]) -> Option<[f64; 2]> {
    camera_bearing(&pose.transform(&Vector3::new(point[0], point[1], point[2])))
}

/// Squared distance between a keypoint's bearing and a projected point.
fn squared_distance(keypoint: [f32; 2], projected: [f64; 2]) -> f64 {
    let dx = f64::from(keypoint[0]) - projected[0];
    let dy = f64::from(keypoint[1]) - projected[1];
    dx * dx + dy * dy
}

/// Step 1: for each keypoint (bearing in `keypoints`), the nearest of `points` (map index,
/// world position) projected with `pose`, if closer than `radius` and than its best so far
/// (`best_point` / `best_distance`, squared; start them at [`UNPAIRED`] / infinity and call
/// once per view). A point offered twice (seen by two views) changes nothing.
pub fn nearest_points(
    pose: &Pose,
    points: impl Iterator<Item = (u32, [f64; 3])>,
    keypoints: &[[f32; 2]],
    radius: f64,
    best_point: &mut [u32],
    best_distance: &mut [f64],
) {
    let limit = radius * radius;
    for (index, position) in points {
        let Some(projected) = project(pose, position) else {
            continue;
        };
        for ((&keypoint, point), distance) in keypoints
            .iter()
            .zip(best_point.iter_mut())
            .zip(best_distance.iter_mut())
        {
            let d = squared_distance(keypoint, projected);
            if d < limit && d < *distance {
                (*point, *distance) = (index, d);
            }
        }
    }
}

/// Step 2: unpairs each keypoint whose point has another keypoint closer to its projection
/// (at equal distance the lower keypoint index keeps it), so every point ends in at most
/// one pair. `position` gives a map index's world position.
pub fn keep_mutual(
    pose: &Pose,
    keypoints: &[[f32; 2]],
    best_point: &mut [u32],
    best_distance: &[f64],
    position: impl Fn(u32) -> Result<[f64; 3]>,
) -> Result<()> {
    for k in 0..best_point.len().min(keypoints.len()) {
        let (Some(&point), Some(&own)) = (best_point.get(k), best_distance.get(k)) else {
            continue;
        };
        if point == UNPAIRED {
            continue;
        }
        let Some(projected) = project(pose, position(point)?) else {
            best_point[k] = UNPAIRED;
            continue;
        };
        let beaten = keypoints.iter().enumerate().any(|(other, &keypoint)| {
            let d = squared_distance(keypoint, projected);
            other != k && (d < own || (d == own && other < k))
        });
        if beaten {
            best_point[k] = UNPAIRED;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};

    fn identity() -> Pose {
        Pose::new(Rotation3::identity(), Vector3::zeros())
    }

    /// Points on the plane z = 1 project to their (x, y).
    fn on_plane(xy: &[[f64; 2]]) -> impl Iterator<Item = (u32, [f64; 3])> + '_ {
        xy.iter()
            .enumerate()
            .map(|(i, p)| (i as u32, [p[0], p[1], 1.0]))
    }

    #[test]
    fn each_keypoint_takes_its_nearest_point_within_the_radius() {
        let keypoints = [[0.0, 0.0], [1.0, 0.0], [5.0, 5.0]];
        let points = [[0.9, 0.0], [0.05, 0.0], [0.2, 0.0]];
        let (mut best, mut distance) = ([UNPAIRED; 3], [f64::INFINITY; 3]);
        // A second view offering the same points changes nothing.
        for _view in 0..2 {
            nearest_points(
                &identity(),
                on_plane(&points),
                &keypoints,
                0.5,
                &mut best,
                &mut distance,
            );
            assert_eq!(best, [1, 0, UNPAIRED]);
        }
    }

    #[test]
    fn points_behind_the_camera_are_never_paired() {
        let (mut best, mut distance) = ([UNPAIRED; 1], [f64::INFINITY; 1]);
        let behind = [(7, [0.0, 0.0, -1.0]), (8, [0.0, 0.0, 0.0])];
        nearest_points(
            &identity(),
            behind.into_iter(),
            &[[0.0, 0.0]],
            1.0,
            &mut best,
            &mut distance,
        );
        assert_eq!(best, [UNPAIRED]);
    }

    #[test]
    fn a_point_stays_with_its_nearest_keypoint_only() {
        // Both keypoints pick point 0; keypoint 1 is closer to it.
        let keypoints = [[0.0, 0.0], [0.3, 0.0], [2.0, 0.0], [2.2, 0.0]];
        let points = [[0.25, 0.0], [2.1, 0.0]];
        let (mut best, mut distance) = ([UNPAIRED; 4], [f64::INFINITY; 4]);
        nearest_points(
            &identity(),
            on_plane(&points),
            &keypoints,
            1.0,
            &mut best,
            &mut distance,
        );
        assert_eq!(best, [0, 0, 1, 1]);
        let position = |i: u32| Ok([points[i as usize][0], points[i as usize][1], 1.0]);
        keep_mutual(&identity(), &keypoints, &mut best, &distance, position).unwrap();
        // Point 1 is 0.1 from both keypoints 2 and 3 (up to rounding): one keeps it.
        assert_eq!(best[..2], [UNPAIRED, 0]);
        assert_eq!(best[2..].iter().filter(|&&p| p == 1).count(), 1);
    }

    #[test]
    fn radii_must_be_finite_and_positive() {
        assert!(GuidedConfig::new().check().is_ok());
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let config = GuidedConfig {
                radii_px: [40.0, bad, 10.0, 5.0],
            };
            assert_eq!(
                config.check(),
                Err(Error::InvalidConfig {
                    parameter: "guided_radius"
                })
            );
        }
    }
}
