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
//! 0. [`vote_displacements`], [`voted_displacement`]: the displacement from projected point
//!    to keypoint that most pairs within the radius share; the keypoints are moved back by
//!    it in steps 1 and 2 unless it is shorter than RANSAC-PnP's threshold;
//! 1. [`nearest_points`]: per keypoint, the nearest projected point within the radius;
//! 2. [`keep_mutual`]: a pair stays when no other keypoint lies closer to its point;
//! 3. RANSAC-PnP on the pairs (the matches' threshold, at most [`MAX_THRESHOLD_PX`]); its
//!    pose replaces the current one when it has at least [`MIN_INLIERS`] inliers. When the
//!    moved keypoints' pairs give no such pose, steps 1-3 run again without the move;
//!    when those give none either, the rounds stop.
//!
//! Step 0 is for dense points (a narrow field of view, many points per view): there a pose
//! a few pixels off pairs most keypoints with a neighbour of their true point, and RANSAC-PnP
//! on those pairs keeps the pose where it is, as the pairs were chosen by it. The true pairs
//! share one displacement (a pose a few pixels off moves the projections nearly alike across
//! a narrow view) while the chance pairs spread evenly over the radius, so the true one
//! stands out in a vote (a Hough transform over displacements: `docs/evaluation.md`,
//! "Displacement vote").
//!
//! A round whose pose has more inliers than the round before runs again at its radius (at
//! most [`ROUNDS_PER_RADIUS`] times, [`gained_inliers`]): its pose moved, and pairs at the
//! same radius reach true points the last pose put beyond it. Without the repeat a pose
//! still a few pixels off when the radius shrinks stays there, as pairing each keypoint with
//! its nearest projection holds it in place (the iterated closest point's slow convergence).
//!
//! Then the chance level: steps 1 and 2 at the last radius with the keypoints shifted by
//! [`CHANCE_SHIFTS`] pair keypoints with points that do not correspond, as many as the
//! density of both sets makes coincide; [`chance_inliers`] turns their mean into the inliers
//! a pose would have by chance. Where points are dense in the image (a narrow field of view,
//! many points per view) a wrong pose's projections still fall on many keypoints, and the
//! rule weighs the inliers against that level.

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::pose::{camera_bearing, Pose};

/// Search radii of re-matching, each searched in one round or more ([`ROUNDS_PER_RADIUS`]).
pub const RADII: usize = 4;
/// Most rounds at one radius ([`gained_inliers`]).
pub const ROUNDS_PER_RADIUS: usize = 3;
/// Fewest RANSAC inliers a round's pose needs to replace the pose.
pub const MIN_INLIERS: usize = 6;
/// Loosest RANSAC-PnP inlier threshold of the rounds, in pixels
/// ([`GuidedConfig::max_threshold_px`]).
pub const MAX_THRESHOLD_PX: f64 = 2.0;
/// A keypoint without a paired point.
pub const UNPAIRED: u32 = u32::MAX;
/// Shifts of the keypoints, in multiples of the last radius, under which the pose's
/// projections pair with them by chance only (four directions, beyond the radius).
pub const CHANCE_SHIFTS: [[f64; 2]; 4] = [[4.0, 0.0], [-4.0, 0.0], [0.0, 4.0], [0.0, -4.0]];
/// Cells per side of the displacement vote's grid, which spans the square of half-width the
/// radius ([`vote_displacements`]).
pub const VOTE_CELLS: usize = 16;

/// Votes per displacement cell, row by row ([`vote_displacements`]).
pub type Votes = [u16; VOTE_CELLS * VOTE_CELLS];

/// Settings of guided re-matching.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GuidedConfig {
    /// Search radius of each round in pixels of the query image (converted with its mean
    /// focal length), largest first.
    pub radii_px: [f64; RADII],
    /// Cap on RANSAC-PnP's inlier threshold in the rounds, in pixels of the query image
    /// (converted like the radii): the rounds use the matches' threshold on the normalised
    /// plane ([`crate::ransac::RansacConfig::threshold`]) unless it is looser than this. At
    /// a long focal length that threshold spans many pixels, and a chance pair's residual,
    /// spread over the radius, passes it as easily as a true pair's.
    pub max_threshold_px: f64,
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
            max_threshold_px: MAX_THRESHOLD_PX,
        }
    }

    /// The rounds' RANSAC-PnP inlier threshold on the normalised image plane: `threshold`,
    /// the matches' one, capped at [`GuidedConfig::max_threshold_px`] with the query's mean
    /// focal length `focal`.
    pub fn threshold(&self, threshold: f64, focal: f64) -> f64 {
        threshold.min(self.max_threshold_px / focal)
    }

    /// The last radius on the normalised image plane, with the query's mean focal length.
    pub fn last_radius(&self, focal: f64) -> f64 {
        self.radii_px[RADII - 1] / focal
    }

    /// [`chance_inliers`] of `chance_pairs` at the rounds' threshold ([`Self::threshold`] of
    /// the matches' `threshold`) and the last radius.
    pub fn chance_inliers(&self, chance_pairs: u16, threshold: f64, focal: f64) -> f32 {
        chance_inliers(
            chance_pairs,
            self.threshold(threshold, focal),
            self.last_radius(focal),
        )
    }

    /// [`Error::InvalidConfig`] (`guided_radius`) unless every radius and the threshold cap
    /// are finite and positive.
    pub fn check(&self) -> Result<()> {
        let positive = |v: &f64| v.is_finite() && *v > 0.0;
        if self.radii_px.iter().all(positive) && positive(&self.max_threshold_px) {
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
    /// Mean pairs at the last radius under the final pose with the keypoints shifted by
    /// [`CHANCE_SHIFTS`] (0 when no round kept a pose).
    #[serde(default)]
    pub chance: u16,
}

/// Whether a round with `inliers` gained over the round before it (`previous`, `None` for
/// the first round): then the next round keeps its radius.
pub fn gained_inliers(previous: Option<usize>, inliers: usize) -> bool {
    previous.is_some_and(|previous| inliers > previous)
}

/// Inliers a pose has by chance: `chance_pairs` pairs within `radius` whose residuals spread
/// evenly over the disc, of which the share within RANSAC's `threshold` (both on the
/// normalised image plane) are inliers.
pub fn chance_inliers(chance_pairs: u16, threshold: f64, radius: f64) -> f32 {
    let ratio = threshold / radius;
    let share = (ratio * ratio).min(1.0);
    (f64::from(chance_pairs) * share) as f32
}

/// The bearing of a world point in the camera of `pose` ([`camera_bearing`]).
fn project(pose: &Pose, point: [f64; 3]) -> Option<[f64; 2]> {
    camera_bearing(&pose.transform(&Vector3::new(point[0], point[1], point[2])))
}

/// Squared distance between a keypoint's bearing moved by `shift` and a projected point.
fn squared_distance(keypoint: [f32; 2], shift: [f64; 2], projected: [f64; 2]) -> f64 {
    let dx = f64::from(keypoint[0]) + shift[0] - projected[0];
    let dy = f64::from(keypoint[1]) + shift[1] - projected[1];
    dx * dx + dy * dy
}

/// Where the keypoints are, as bearings, and how far they are moved (zero, or a chance
/// shift).
#[derive(Debug, Clone, Copy)]
pub struct Shifted<'a> {
    /// Keypoint bearings.
    pub keypoints: &'a [[f32; 2]],
    /// Added to every keypoint.
    pub shift: [f64; 2],
}

/// Step 0, the votes: adds to `votes` the displacement from each of `points` (map index,
/// world position), projected with `pose`, to each keypoint within `radius` on both axes
/// (cells of `2 radius / VOTE_CELLS`, saturating). Call once per view.
pub fn vote_displacements(
    pose: &Pose,
    points: impl Iterator<Item = (u32, [f64; 3])>,
    keypoints: &[[f32; 2]],
    radius: f64,
    votes: &mut Votes,
) {
    let cell = 2.0 * radius / VOTE_CELLS as f64;
    for (_, position) in points {
        let Some(projected) = project(pose, position) else {
            continue;
        };
        for &keypoint in keypoints {
            let from_corner = |axis: usize| f64::from(keypoint[axis]) - projected[axis] + radius;
            let (x, y) = (from_corner(0), from_corner(1));
            if !(x >= 0.0 && y >= 0.0) {
                continue;
            }
            let (column, row) = ((x / cell) as usize, (y / cell) as usize);
            if column < VOTE_CELLS && row < VOTE_CELLS {
                if let Some(count) = votes.get_mut(row * VOTE_CELLS + column) {
                    *count = count.saturating_add(1);
                }
            }
        }
    }
}

/// Step 0, the winner: the vote-weighted mean displacement of the 3 x 3 cells with the most
/// votes (the first such block in row order), or zero when there are no votes or that
/// displacement is shorter than `dead_zone` (a shift RANSAC-PnP's threshold absorbs).
pub fn voted_displacement(votes: &Votes, radius: f64, dead_zone: f64) -> [f64; 2] {
    let cell = 2.0 * radius / VOTE_CELLS as f64;
    let centre = |index: usize| (index as f64 + 0.5) * cell - radius;
    let mut best = (0u32, [0.0; 2]);
    for row in 1..VOTE_CELLS - 1 {
        for column in 1..VOTE_CELLS - 1 {
            let (mut total, mut sum) = (0u32, [0.0; 2]);
            for y in row - 1..=row + 1 {
                for x in column - 1..=column + 1 {
                    let count = votes.get(y * VOTE_CELLS + x).copied().unwrap_or(0);
                    total += u32::from(count);
                    sum[0] += f64::from(count) * centre(x);
                    sum[1] += f64::from(count) * centre(y);
                }
            }
            if total > best.0 {
                let mean = sum.map(|s| s / f64::from(total));
                best = (total, mean);
            }
        }
    }
    let [dx, dy] = best.1;
    if dx * dx + dy * dy < dead_zone * dead_zone {
        [0.0; 2]
    } else {
        [dx, dy]
    }
}

/// Step 1: for each keypoint of `keypoints`, the nearest of `points` (map index, world
/// position) projected with `pose`, if closer than `radius` and than its best so far
/// (`best_point` / `best_distance`, squared; start them at [`UNPAIRED`] / infinity and call
/// once per view). A point offered twice (seen by two views) changes nothing.
pub fn nearest_points(
    pose: &Pose,
    points: impl Iterator<Item = (u32, [f64; 3])>,
    keypoints: Shifted<'_>,
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
            .keypoints
            .iter()
            .zip(best_point.iter_mut())
            .zip(best_distance.iter_mut())
        {
            let d = squared_distance(keypoint, keypoints.shift, projected);
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
    keypoints: Shifted<'_>,
    best_point: &mut [u32],
    best_distance: &[f64],
    position: impl Fn(u32) -> Result<[f64; 3]>,
) -> Result<()> {
    for k in 0..best_point.len().min(keypoints.keypoints.len()) {
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
        let beaten = keypoints
            .keypoints
            .iter()
            .enumerate()
            .any(|(other, &keypoint)| {
                let d = squared_distance(keypoint, keypoints.shift, projected);
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
    use crate::rng::SplitMix64;
    use nalgebra::{Rotation3, Vector3};
    use std::vec::Vec;

    fn unshifted(keypoints: &[[f32; 2]]) -> Shifted<'_> {
        Shifted {
            keypoints,
            shift: [0.0; 2],
        }
    }

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
                unshifted(&keypoints),
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
            unshifted(&[[0.0, 0.0]]),
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
            unshifted(&keypoints),
            1.0,
            &mut best,
            &mut distance,
        );
        assert_eq!(best, [0, 0, 1, 1]);
        let position = |i: u32| Ok([points[i as usize][0], points[i as usize][1], 1.0]);
        keep_mutual(
            &identity(),
            unshifted(&keypoints),
            &mut best,
            &distance,
            position,
        )
        .unwrap();
        // Point 1 is 0.1 from both keypoints 2 and 3 (up to rounding): one keeps it.
        assert_eq!(best[..2], [UNPAIRED, 0]);
        assert_eq!(best[2..].iter().filter(|&&p| p == 1).count(), 1);
    }

    #[test]
    fn shifted_keypoints_pair_with_the_points_at_their_new_place() {
        let keypoints = [[0.0, 0.0], [1.0, 0.0]];
        let points = [[0.0, 0.0], [1.0, 0.0], [2.05, 0.0]];
        let (mut best, mut distance) = ([UNPAIRED; 2], [f64::INFINITY; 2]);
        let shifted = Shifted {
            keypoints: &keypoints,
            shift: [1.0, 0.0],
        };
        nearest_points(
            &identity(),
            on_plane(&points),
            shifted,
            0.1,
            &mut best,
            &mut distance,
        );
        assert_eq!(best, [1, 2]);
        assert!((distance[1] - 0.05 * 0.05).abs() < 1e-12);
    }

    /// Points scattered over [-1, 1]^2 on the plane z = 1 (a fixed sequence).
    fn scattered(count: usize, seed: u64) -> Vec<[f64; 2]> {
        let mut rng = SplitMix64::new(seed);
        let mut next = move || 2.0 * rng.unit_f64() - 1.0;
        (0..count).map(|_| [next(), next()]).collect()
    }

    #[test]
    fn the_vote_finds_the_displacement_the_true_pairs_share() {
        // 40 points seen 0.13 right and 0.07 up of where the pose projects them, among 80
        // keypoints that match nothing; radius 0.4: the vote is right within a cell (0.05),
        // the chance votes around the winning cells pulling the mean towards their centre.
        let points = scattered(40, 1);
        let shift = [0.13, -0.07];
        let mut keypoints: Vec<[f32; 2]> = points
            .iter()
            .map(|p| [(p[0] + shift[0]) as f32, (p[1] + shift[1]) as f32])
            .collect();
        keypoints.extend(scattered(80, 2).iter().map(|p| [p[0] as f32, p[1] as f32]));
        let mut votes: Votes = [0; VOTE_CELLS * VOTE_CELLS];
        vote_displacements(&identity(), on_plane(&points), &keypoints, 0.4, &mut votes);
        let [dx, dy] = voted_displacement(&votes, 0.4, 0.01);
        assert!(
            (dx - shift[0]).abs() < 0.05 && (dy - shift[1]).abs() < 0.05,
            "{dx} {dy}"
        );
        // A displacement within the dead zone is none.
        assert_eq!(voted_displacement(&votes, 0.4, 0.2), [0.0; 2]);
        // Without keypoints within the radius of any point there are no votes.
        let far: Vec<[f32; 2]> = keypoints.iter().map(|k| [k[0] + 5.0, k[1]]).collect();
        let mut none: Votes = [0; VOTE_CELLS * VOTE_CELLS];
        vote_displacements(&identity(), on_plane(&points), &far, 0.4, &mut none);
        assert!(none.iter().all(|&v| v == 0));
        assert_eq!(voted_displacement(&none, 0.4, 0.01), [0.0; 2]);
    }

    #[test]
    fn chance_inliers_are_the_pairs_within_the_threshold_share_of_the_disc() {
        assert_eq!(chance_inliers(100, 1.0, 5.0), 4.0);
        assert_eq!(chance_inliers(100, 1.0, 2.0), 25.0);
        // A threshold beyond the radius makes every chance pair an inlier.
        assert_eq!(chance_inliers(100, 6.0, 5.0), 100.0);
        assert_eq!(chance_inliers(0, 1.0, 5.0), 0.0);
    }

    #[test]
    fn the_rounds_threshold_is_the_matches_capped_in_pixels() {
        let config = GuidedConfig::new();
        // 1e-3 is 1 px at a focal length of 1000 px: kept.
        assert_eq!(config.threshold(1e-3, 1000.0), 1e-3);
        // At 5000 px it would be 5 px: capped at 2 px.
        assert_eq!(config.threshold(1e-3, 5000.0), 2.0 / 5000.0);
        assert_eq!(config.last_radius(500.0), 0.01);
    }

    #[test]
    fn radii_and_threshold_must_be_finite_and_positive() {
        assert!(GuidedConfig::new().check().is_ok());
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let radius = GuidedConfig {
                radii_px: [40.0, bad, 10.0, 5.0],
                ..GuidedConfig::new()
            };
            let threshold = GuidedConfig {
                max_threshold_px: bad,
                ..GuidedConfig::new()
            };
            for config in [radius, threshold] {
                assert_eq!(
                    config.check(),
                    Err(Error::InvalidConfig {
                        parameter: "guided_radius"
                    })
                );
            }
        }
    }
}
