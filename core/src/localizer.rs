//! The localization pipeline a user calls (paper sec. 3 and 4.1): query keypoints in
//! pixels and their camera, a geometric-only [`Map`], a set of co-visible database views,
//! and out comes the query pose.
//!
//! ```text
//! pixels --camera--> bearings --encode once--> query features
//! for each selected view (streamed, one at a time):
//!     its map points in front of it (first N) --eq. 1--> bearings
//!     --> attention, Sinkhorn, classifier --> matches above the threshold
//!     --> merged: per query keypoint its best match across views
//! merged --> per 3D point its best keypoint --> RANSAC-PnP + LM --> pose
//! ```
//!
//! [`Localizer`] owns every buffer (the [`Matcher`], the [`PnpWorkspace`] and the merge
//! tables), so memory is fixed by the capacity `N` whatever the number of views; it is
//! built by a `const fn` and belongs in a `static`. The core has no clock: stage timings
//! come from an optional caller-provided [`Clock`] and go, with the match counts, to the
//! [`log`] crate and into the returned [`Localization`].

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::acceptance::{self, AcceptanceRule, Evidence, PoseSupport};
use crate::camera::Camera;
pub use crate::error::Failure;
use crate::error::{Error, Input, Result};
use crate::guided::{self, GuidedConfig, GuidedCounts, Shifted, Votes, UNPAIRED};
use crate::limits::MIN_CORRESPONDENCES;
use crate::map::Map;
use crate::matcher::Matcher;
use crate::merge;
pub use crate::merge::Correspondence;
use crate::pose::{Pose, ProjectionRule};
use crate::ransac::{estimate_pose, AdaptiveStop, PnpWorkspace, RansacConfig};
use crate::sinkhorn::PlanScalar;
use crate::weights::Model;

pub use crate::limits::MAX_VIEWS;

/// The database points a view contributes to matching, the one rule shared by the device
/// and the host's evaluation protocol: the first `capacity` of the view's observed points,
/// in stored order, that have a bearing under the view's [`ProjectionRule`] (paper supp.
/// "Keypoint Number Control": database keypoints are used "up to its first 1024"). A map
/// stores each view's points in the order a capped detector ranks them, so the first ones
/// are those a detector limited to `capacity` keypoints would have kept. The rule's
/// reference depth is the median depth of the first `depths.len()` points in front of the
/// view (`depths` is scratch; pass `capacity` slots). Yields each point's tag and its
/// bearing, and counts the points it skips.
pub fn view_point_bearings<T, I>(
    view_pose: Pose,
    points: I,
    capacity: usize,
    depths: &mut [f64],
) -> ViewPointBearings<I>
where
    I: Iterator<Item = (T, [f64; 3])> + Clone,
{
    let rule = ProjectionRule::of_camera(&view_pose, points.clone().map(|(_, p)| p), depths);
    ViewPointBearings {
        pose: view_pose,
        rule,
        points,
        remaining: capacity,
        skipped: 0,
    }
}

/// The iterator of [`view_point_bearings`].
#[derive(Debug, Clone)]
pub struct ViewPointBearings<I> {
    pose: Pose,
    rule: ProjectionRule,
    points: I,
    remaining: usize,
    skipped: usize,
}

impl<I> ViewPointBearings<I> {
    /// Points passed over so far because the view's [`ProjectionRule`] refuses them.
    pub fn skipped(&self) -> usize {
        self.skipped
    }
}

impl<T, I: Iterator<Item = (T, [f64; 3])>> Iterator for ViewPointBearings<I> {
    type Item = (T, [f64; 2]);

    fn next(&mut self) -> Option<Self::Item> {
        while self.remaining > 0 {
            let (tag, [x, y, z]) = self.points.next()?;
            match self.rule.bearing(&self.pose, &Vector3::new(x, y, z)) {
                Ok(bearing) => {
                    self.remaining -= 1;
                    return Some((tag, bearing));
                }
                Err(_) => self.skipped += 1,
            }
        }
        None
    }
}

/// A query: keypoints in pixels (at most the localizer's capacity; the caller caps) and
/// the calibrated camera that took the image.
#[derive(Debug, Clone, Copy)]
pub struct Query<'a> {
    /// Keypoint positions in pixels (COLMAP convention: origin top-left, y down).
    pub keypoints: &'a [[f32; 2]],
    /// The query camera.
    pub camera: Camera,
}

/// Which database views the query is matched against.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ViewSelection<'a> {
    /// Views by image id, in the given order, e.g. from an image-retrieval step
    /// (at most [`MAX_VIEWS`]).
    ImageIds(&'a [u32]),
    /// The `k` views nearest to a coarse prior pose ([`Map::views_near`]): views looking
    /// within `max_angle_deg` of the prior first, each group by camera-centre distance.
    NearPrior {
        /// The coarse prior pose of the query.
        prior: Pose,
        /// Number of views, at most [`MAX_VIEWS`].
        k: usize,
        /// Viewing-direction cone of the first group, in degrees.
        max_angle_deg: f64,
    },
}

/// Settings of [`Localizer::localize`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalizerConfig {
    /// RANSAC-PnP settings (threshold on the normalised image plane).
    pub ransac: RansacConfig,
    /// Fewest merged matches worth running the pose solver on (at least
    /// [`MIN_CORRESPONDENCES`]).
    pub min_matches: usize,
    /// Fewest inliers of an accepted pose (at least [`MIN_CORRESPONDENCES`]: a P3P sample
    /// always has 3, so a pose must be confirmed by at least one more correspondence).
    pub min_inliers: usize,
    /// Decides, from the pose's [`Evidence`], whether a pose with `min_inliers` inliers is
    /// trusted ([`Failure::LowConfidence`] when not); `None`: the rule fitted at the
    /// localizer's capacity, [`AcceptanceRule::for_capacity`].
    pub acceptance: Option<AcceptanceRule>,
    /// Guided re-matching of RANSAC-PnP's pose before the acceptance rule judges it
    /// ([`guided`]); `None`: the pose is RANSAC-PnP's on the network's matches, as in the
    /// paper (the rules are fitted with re-matching).
    pub guided: Option<GuidedConfig>,
    /// When the rule refuses the pose, RANSAC-PnP runs once more on the merged matches its
    /// inliers left out, and that pose, re-matched and judged, replaces it when the rule
    /// accepts it ([`Localizer::localize`]; `docs/evaluation.md`, "Second attempt").
    pub second_attempt: bool,
}

impl Default for LocalizerConfig {
    fn default() -> Self {
        Self::new()
    }
}

impl LocalizerConfig {
    /// [`RansacConfig::new`], `min_matches` and `min_inliers` = [`MIN_CORRESPONDENCES`],
    /// the acceptance rule of the localizer's capacity, guided re-matching with
    /// [`GuidedConfig::new`], a second attempt after a refusal.
    pub const fn new() -> Self {
        Self {
            ransac: RansacConfig::new(),
            min_matches: MIN_CORRESPONDENCES,
            min_inliers: MIN_CORRESPONDENCES,
            acceptance: None,
            guided: Some(GuidedConfig::new()),
            second_attempt: true,
        }
    }

    /// The RANSAC-PnP settings a localizer of this capacity applies: the configured ones with
    /// the adaptive stop resolved (the configured one, else [`AdaptiveStop::for_capacity`]).
    pub const fn ransac_config(&self, capacity: usize) -> RansacConfig {
        let stop = match self.ransac.stop {
            Some(stop) => stop,
            None => AdaptiveStop::for_capacity(capacity),
        };
        RansacConfig {
            stop: Some(stop),
            ..self.ransac
        }
    }

    /// The acceptance rule a localizer of this capacity applies: the configured one, or the
    /// one fitted at that capacity.
    pub const fn acceptance_rule(&self, capacity: usize) -> AcceptanceRule {
        match self.acceptance {
            Some(rule) => rule,
            None => AcceptanceRule::for_capacity(capacity),
        }
    }
}

/// A monotonic clock the caller provides for stage timings (the core has none).
pub trait Clock {
    /// Microseconds since an arbitrary, fixed origin.
    fn now_us(&self) -> u64;
}

/// Match counts per stage, summed over the views.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct MatchCounts {
    /// Matches of the mutual assignment (with the reference's fallback).
    pub mutual: usize,
    /// Those the classifier accepts (probability above the model's threshold).
    pub classified: usize,
    /// After merging the views: each query keypoint and each 3D point at most once.
    pub merged: usize,
    /// RANSAC-PnP inliers of the final pose.
    pub inliers: usize,
}

/// Stage timings in microseconds, from the caller's [`Clock`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct StageTimings {
    /// Input checks, keypoint bearings and view selection.
    pub prepare_us: u64,
    /// Query encoder (once).
    pub encode_us: u64,
    /// Point gathering and matching of all views.
    pub match_us: u64,
    /// Merging the views' matches.
    pub merge_us: u64,
    /// RANSAC-PnP, refinement and guided re-matching.
    pub pose_us: u64,
    /// The whole call.
    pub total_us: u64,
}

/// The outcome of one [`Localizer::localize`] call.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Localization {
    /// The world-to-camera pose of the query, or why there is none.
    pub outcome: core::result::Result<Pose, Failure>,
    /// Match counts per stage.
    pub counts: MatchCounts,
    /// Views matched.
    pub views_used: usize,
    /// Selected views skipped for having fewer points in front of them than the matcher
    /// needs.
    pub views_skipped: usize,
    /// RANSAC minimal samples drawn (0 when the solver did not run).
    pub ransac_iterations: u32,
    /// Stage timings, when a clock was given.
    pub timings: Option<StageTimings>,
    /// Evidence about the best pose, when RANSAC found one with `min_inliers` inliers.
    pub evidence: Option<Evidence>,
    /// The acceptance rule's confidence in that pose.
    pub confidence: Option<f32>,
    /// The pose the rule judged (RANSAC-PnP's, re-matched), accepted or not: for evaluating
    /// the acceptance rule only. A refused pose ([`Failure::LowConfidence`]) is not a
    /// localization.
    pub candidate: Option<Pose>,
    /// What guided re-matching did to RANSAC-PnP's pose.
    pub guided: GuidedCounts,
    /// Whether the pose is the second attempt's ([`LocalizerConfig::second_attempt`]; a
    /// refusal is the first attempt's, with its candidate, evidence and confidence).
    pub second_attempt: bool,
}

impl Localization {
    /// The pose, or the failure as an [`Error::LocalizationFailed`].
    pub fn pose(&self) -> Result<Pose> {
        self.outcome
            .map_err(|reason| Error::LocalizationFailed { reason })
    }

    fn failed(reason: Failure) -> Self {
        Self {
            outcome: Err(reason),
            counts: MatchCounts::default(),
            views_used: 0,
            views_skipped: 0,
            ransac_iterations: 0,
            timings: None,
            evidence: None,
            confidence: None,
            candidate: None,
            guided: GuidedCounts::default(),
            second_attempt: false,
        }
    }
}

/// Workspace and pipeline of the localizer for up to `N` query keypoints and `N` points
/// per view, with the Sinkhorn cost stored as `S` (`f32` or `half::f16`).
///
/// Besides the [`Matcher`] and the [`PnpWorkspace`], per slot: one bearing buffer (the
/// query's while it is encoded, then each view's in turn), the current view's map
/// indices, one correspondence table (per keypoint its best match while the views are
/// matched, then compacted by the merge) and the pose solver's input. The keypoints'
/// `f64` bearings are recomputed from the query's pixels for the merged ones only.
pub struct Localizer<const N: usize, S: PlanScalar = f32> {
    matcher: Matcher<N, S>,
    pnp: PnpWorkspace<N>,
    /// Bearings given to the network: the query's until it is encoded, then the current
    /// view's points.
    network_input: [[f32; 2]; N],
    /// Map indices of the current view's points, parallel to `network_input`.
    view_points: [u32; N],
    /// While matching: per query keypoint its best accepted match so far
    /// (`probability` = [`UNMATCHED`] when none). After the merge: the correspondences
    /// of the last call, by keypoint.
    merged: [Correspondence; N],
    merged_len: usize,
    /// Pose solver input, parallel to `merged`; during guided re-matching the depth scratch
    /// of the views' projection rules and per keypoint its nearest point's squared
    /// distance, then the pairs' input.
    bearings: [[f64; 2]; N],
    points: [[f64; 3]; N],
}

impl<const N: usize, S: PlanScalar> Default for Localizer<N, S> {
    fn default() -> Self {
        Self::new()
    }
}

/// Reads the caller's clock, or 0 without one.
fn now(clock: Option<&dyn Clock>) -> u64 {
    clock.map_or(0, |c| c.now_us())
}

impl<const N: usize, S: PlanScalar> Localizer<N, S> {
    /// Size of the workspace in bytes.
    pub const BYTES: usize = core::mem::size_of::<Self>();

    /// An empty workspace; all-zero, so a `static` lands in `.bss`.
    pub const fn new() -> Self {
        Localizer {
            matcher: Matcher::new(),
            pnp: PnpWorkspace::new(),
            network_input: [[0.0; 2]; N],
            view_points: [0; N],
            merged: [Correspondence::EMPTY; N],
            merged_len: 0,
            bearings: [[0.0; 2]; N],
            points: [[0.0; 3]; N],
        }
    }

    /// The merged correspondences of the last [`Localizer::localize`] call, by keypoint,
    /// with their inlier flags (all `false` when no pose was found).
    pub fn correspondences(&self) -> &[Correspondence] {
        self.merged.get(..self.merged_len).unwrap_or(&[])
    }

    /// The inlier correspondences of the last call.
    pub fn inliers(&self) -> impl Iterator<Item = &Correspondence> {
        self.correspondences().iter().filter(|c| c.inlier)
    }

    /// Localizes a query against the map (paper sec. 4.1): encodes the keypoints once,
    /// matches them against each selected view's points as bearing vectors (eq. 1),
    /// merges the classifier-accepted matches, estimates the pose with RANSAC-PnP,
    /// re-matches it by projection ([`guided`]) and judges it ([`acceptance`]); a refused
    /// pose gets a second attempt on the matches its inliers left out
    /// ([`LocalizerConfig::second_attempt`]).
    ///
    /// Invalid input is an `Err` and nothing runs: a camera with non-finite or
    /// non-positive intrinsics ([`Error::InvalidIntrinsics`]), more keypoints than `N`
    /// ([`Error::CapacityExceeded`]), a non-finite keypoint ([`Error::NonFinite`] with its
    /// index) or one that cannot be undistorted, more than [`MAX_VIEWS`] views, an unknown
    /// image id ([`Error::MapUnknownImage`]), a non-finite prior, an invalid configuration
    /// ([`Error::InvalidConfig`]). A valid query that cannot be localized is an `Ok`
    /// whose [`Localization::outcome`] holds the [`Failure`]. Nothing passed is modified;
    /// the result depends only on the inputs (not on earlier calls).
    pub fn localize(
        &mut self,
        model: &Model<'_>,
        map: &Map<'_>,
        query: &Query<'_>,
        views: ViewSelection<'_>,
        config: &LocalizerConfig,
        clock: Option<&dyn Clock>,
    ) -> Result<Localization> {
        let start = now(clock);
        self.merged_len = 0;
        check_config(config)?;
        self.set_query(query)?;
        let selected = select_views(map, views)?;
        let n = query.keypoints.len();
        let prepared = now(clock);
        let needed = self.matcher.min_points();
        if n < needed {
            return Ok(Localization::failed(Failure::TooFewKeypoints {
                needed,
                found: n,
            }));
        }
        if selected.is_empty() {
            return Ok(Localization::failed(Failure::NoViews { skipped: 0 }));
        }
        self.matcher
            .encode_query(model, self.network_input.get(..n).unwrap_or(&[]))?;
        let encoded = now(clock);

        self.clear_matches(n);
        let mut counts = MatchCounts::default();
        let (mut used, mut skipped) = (0, 0);
        for (slot, &view) in selected.iter().enumerate() {
            match self.match_view(model, map, (view as usize, slot as u8), &mut counts)? {
                true => used += 1,
                false => skipped += 1,
            }
        }
        let matched = now(clock);
        self.merge(map, query, n)?;
        counts.merged = self.merged_len;
        let merged = now(clock);

        let mut localization = Localization {
            outcome: Err(Failure::NoViews { skipped }),
            counts,
            views_used: used,
            views_skipped: skipped,
            ..Localization::failed(Failure::NoViews { skipped })
        };
        if used > 0 {
            let centres = view_centres(map, &selected)?;
            let inputs = PoseInputs {
                map,
                selected: &selected,
                centres: &centres,
                config,
                query,
            };
            self.decide(inputs, &mut localization)?;
        }
        let done = now(clock);
        if clock.is_some() {
            localization.timings = Some(StageTimings {
                prepare_us: prepared.saturating_sub(start),
                encode_us: encoded.saturating_sub(prepared),
                match_us: matched.saturating_sub(encoded),
                merge_us: merged.saturating_sub(matched),
                pose_us: done.saturating_sub(merged),
                total_us: done.saturating_sub(start),
            });
        }
        log_summary(&localization, n);
        Ok(localization)
    }

    /// The rounds of [`guided`]: pairs of each radius, then RANSAC-PnP on them; a radius
    /// runs again while its rounds gain inliers ([`guided::gained_inliers`]).
    fn guide(
        &mut self,
        map: &Map<'_>,
        query: &Query<'_>,
        selected: &[u32],
        mut pose: Pose,
        guided: &GuidedConfig,
        config: &LocalizerConfig,
    ) -> Result<(Pose, GuidedCounts)> {
        self.set_query(query)?;
        let n = query.keypoints.len();
        let mut counts = GuidedCounts::default();
        let focal = query.camera.mean_focal();
        let ransac = RansacConfig {
            threshold: guided.threshold(config.ransac.threshold, focal),
            ..config.ransac_config(N)
        };
        let mut previous_inliers = None;
        'radii: for radius_px in guided.radii_px {
            for _ in 0..guided::ROUNDS_PER_RADIUS {
                let radius = radius_px / focal;
                let Some(round) =
                    self.guided_round(map, query, selected, &pose, radius, &ransac)?
                else {
                    break 'radii;
                };
                pose = round.pose;
                counts = GuidedCounts {
                    rounds: counts.rounds.saturating_add(1),
                    pairs: u16::try_from(round.pairs).unwrap_or(u16::MAX),
                    inliers: u16::try_from(round.inliers).unwrap_or(u16::MAX),
                    chance: 0,
                };
                let gained = guided::gained_inliers(previous_inliers, round.inliers);
                previous_inliers = Some(round.inliers);
                if !gained {
                    continue 'radii;
                }
            }
        }
        if counts.rounds > 0 {
            let last = guided.last_radius(focal);
            counts.chance = self.chance_pairs(map, selected, &pose, last, n)?;
        }
        Ok((pose, counts))
    }

    /// One round of [`guided`] at `radius` (normalised plane) around `pose`: the keypoints
    /// moved back by the voted displacement ([`Localizer::voted_shift`]), then, when those
    /// pairs give no pose, unmoved. `None` when the pairs or the inliers are fewer than
    /// [`guided::MIN_INLIERS`] either way (the rounds stop).
    fn guided_round(
        &mut self,
        map: &Map<'_>,
        query: &Query<'_>,
        selected: &[u32],
        pose: &Pose,
        radius: f64,
        ransac: &RansacConfig,
    ) -> Result<Option<GuidedRound>> {
        let n = query.keypoints.len();
        let voted = self.voted_shift(map, selected, pose, radius, ransac.threshold, n)?;
        for shift in [voted, [0.0; 2]] {
            self.pair_by_projection(map, selected, pose, radius, shift, n)?;
            let pairs = self.pairs_to_solver_input(map, query, n)?;
            if let Some(round) = self.solve_pairs(pairs, ransac)? {
                return Ok(Some(round));
            }
            if shift == [0.0; 2] {
                break;
            }
        }
        Ok(None)
    }

    /// Step 3 of a guided round: RANSAC-PnP on the first `pairs` entries of the solver
    /// input; `None` when they or its inliers are fewer than [`guided::MIN_INLIERS`].
    fn solve_pairs(&mut self, pairs: usize, ransac: &RansacConfig) -> Result<Option<GuidedRound>> {
        if pairs < guided::MIN_INLIERS {
            return Ok(None);
        }
        let bearings = self.bearings.get(..pairs).unwrap_or(&[]);
        let points = self.points.get(..pairs).unwrap_or(&[]);
        match estimate_pose(bearings, points, ransac, &mut self.pnp) {
            Ok(estimate) if estimate.inlier_count >= guided::MIN_INLIERS => Ok(Some(GuidedRound {
                pose: estimate.pose,
                pairs,
                inliers: estimate.inlier_count,
            })),
            Ok(_) | Err(Error::NoPoseFound | Error::DegenerateConfiguration) => Ok(None),
            Err(other) => Err(other),
        }
    }

    /// Step 0 of a guided round: the shift of the keypoints (bearings in `network_input`)
    /// that undoes the displacement most pairs of `pose` within `radius` share
    /// ([`guided::voted_displacement`]; zero when shorter than `dead_zone`).
    fn voted_shift(
        &mut self,
        map: &Map<'_>,
        selected: &[u32],
        pose: &Pose,
        radius: f64,
        dead_zone: f64,
        n: usize,
    ) -> Result<[f64; 2]> {
        let mut votes: Votes = [0; guided::VOTE_CELLS * guided::VOTE_CELLS];
        let keypoints = self.network_input.get(..n).unwrap_or(&[]);
        visit_view_points(map, selected, &mut self.bearings, |points| {
            guided::vote_displacements(pose, points, keypoints, radius, &mut votes);
        })?;
        let [dx, dy] = guided::voted_displacement(&votes, radius, dead_zone);
        Ok([-dx, -dy])
    }

    /// The chance level of guided re-matching: mean pairs of `pose` at `radius` over the
    /// keypoints shifted by [`guided::CHANCE_SHIFTS`] radii.
    fn chance_pairs(
        &mut self,
        map: &Map<'_>,
        selected: &[u32],
        pose: &Pose,
        radius: f64,
        n: usize,
    ) -> Result<u16> {
        let mut total = 0;
        for [x, y] in guided::CHANCE_SHIFTS {
            self.pair_by_projection(map, selected, pose, radius, [x * radius, y * radius], n)?;
            let paired = self.view_points.iter().take(n).filter(|&&p| p != UNPAIRED);
            total += paired.count();
        }
        Ok(u16::try_from(total / guided::CHANCE_SHIFTS.len()).unwrap_or(u16::MAX))
    }

    /// Steps 1 and 2 of a guided round: per keypoint (bearing in `network_input`, from
    /// [`Localizer::set_query`], moved by `shift`) its mutual nearest point of the views
    /// within `radius` in `view_points` ([`UNPAIRED`] when none).
    fn pair_by_projection(
        &mut self,
        map: &Map<'_>,
        selected: &[u32],
        pose: &Pose,
        radius: f64,
        shift: [f64; 2],
        n: usize,
    ) -> Result<()> {
        let keypoints = Shifted {
            keypoints: self.network_input.get(..n).unwrap_or(&[]),
            shift,
        };
        let best_point = self.view_points.get_mut(..n).unwrap_or(&mut []);
        let best_distance = self
            .points
            .as_flattened_mut()
            .get_mut(..n)
            .unwrap_or(&mut []);
        best_point.fill(UNPAIRED);
        best_distance.fill(f64::INFINITY);
        visit_view_points(map, selected, &mut self.bearings, |points| {
            guided::nearest_points(pose, points, keypoints, radius, best_point, best_distance);
        })?;
        let position = |index: u32| map.point(index as usize).map(|p| p.map(f64::from));
        guided::keep_mutual(pose, keypoints, best_point, best_distance, position)
    }

    /// Fills the pose solver's input with the paired keypoints' `f64` bearings and their
    /// points, in keypoint order; returns the number of pairs.
    fn pairs_to_solver_input(
        &mut self,
        map: &Map<'_>,
        query: &Query<'_>,
        n: usize,
    ) -> Result<usize> {
        let mut pairs = 0;
        for (k, &point) in self.view_points.iter().enumerate().take(n) {
            if point == UNPAIRED {
                continue;
            }
            let (Some(bearing), Some(position)) =
                (self.bearings.get_mut(pairs), self.points.get_mut(pairs))
            else {
                break;
            };
            (*bearing, *position) = solver_pair(map, query, k, point)?;
            pairs += 1;
        }
        Ok(pairs)
    }

    /// Checks the camera and keypoints and converts them to bearing vectors for the
    /// network.
    fn set_query(&mut self, query: &Query<'_>) -> Result<()> {
        query.camera.check()?;
        let n = query.keypoints.len();
        if n > N {
            return Err(Error::CapacityExceeded {
                capacity: N,
                requested: n,
            });
        }
        for (index, (pixel, bearing)) in query
            .keypoints
            .iter()
            .zip(self.network_input.iter_mut())
            .enumerate()
        {
            let b = keypoint_bearing(&query.camera, *pixel, index)?;
            *bearing = [b[0] as f32, b[1] as f32];
        }
        Ok(())
    }

    /// Marks the first `n` keypoints as having no accepted match yet.
    fn clear_matches(&mut self, n: usize) {
        merge::clear(self.merged.get_mut(..n).unwrap_or(&mut []));
    }

    /// Matches the encoded query against one view (map index, position in the selection)
    /// and keeps, per keypoint, its best accepted match. `false` when the view has too few
    /// points in front of it.
    fn match_view(
        &mut self,
        model: &Model<'_>,
        map: &Map<'_>,
        (view, slot): (usize, u8),
        counts: &mut MatchCounts,
    ) -> Result<bool> {
        let pose = map.view(view)?.pose;
        let mut len = 0;
        // The map was validated when read, so every index and point resolves.
        let points = map.view_point_positions(view)?;
        let slots = self
            .network_input
            .iter_mut()
            .zip(self.view_points.iter_mut());
        // The pose solver's input is filled by the merge, after every view: until then
        // it is the depth scratch of the view's projection rule.
        let depths = self.bearings.as_flattened_mut();
        let mut chosen =
            view_point_bearings(pose, points, N, depths.get_mut(..N).unwrap_or(&mut []));
        for ((index, bearing), (slot, point)) in chosen.by_ref().zip(slots) {
            *slot = [bearing[0] as f32, bearing[1] as f32];
            *point = index;
            len += 1;
        }
        let refused = chosen.skipped();
        let db = self.network_input.get(..len).unwrap_or(&[]);
        if len < self.matcher.min_points() {
            log::debug!("map view {view}: {len} usable points ({refused} refused), skipped");
            return Ok(false);
        }
        // Precomputed features of this view fit when they were computed with this model at
        // this capacity (the projection rule's reference depth depends on it) for the same
        // points (the first `len` with a bearing: the same count).
        let stored = map
            .view_features()
            .filter(|f| f.model_checksum() == model.checksum() && f.capacity() == N)
            .and_then(|f| f.view(view))
            .filter(|rows| {
                rows.count == len && rows.dim == usize::from(model.config().feature_dim)
            });
        let set = match stored {
            Some(rows) => self.matcher.match_view_features(model, db, rows)?,
            None => self.matcher.match_view(model, db)?,
        };
        counts.mutual += set.len();
        let mut accepted = 0;
        for m in set.inliers() {
            accepted += 1;
            let (Some(best), Some(&point)) = (
                self.merged.get_mut(usize::from(m.i2d)),
                self.view_points.get(usize::from(m.i3d)),
            ) else {
                continue;
            };
            merge::keep_best(best, point, m.probability, slot);
        }
        counts.classified += accepted;
        log::debug!(
            "map view {view}: {len} points ({refused} refused by the projection rule), {} mutual matches, {accepted} accepted, {} Sinkhorn iterations",
            set.len(),
            set.sinkhorn_iterations()
        );
        Ok(true)
    }

    /// Merges the views' matches ([`merge::merge`]) and fills the pose solver's inputs
    /// beside them: each keypoint's bearing, recomputed in `f64` from its pixel, and its
    /// map point.
    fn merge(&mut self, map: &Map<'_>, query: &Query<'_>, n: usize) -> Result<()> {
        let kept = merge::merge(self.merged.get_mut(..n.min(N)).unwrap_or(&mut []));
        self.write_solver_input(map, query, kept)?;
        self.merged_len = kept;
        Ok(())
    }

    /// The first `len` merged correspondences as the pose solver's input (bearings, world
    /// points).
    fn write_solver_input(&mut self, map: &Map<'_>, query: &Query<'_>, len: usize) -> Result<()> {
        let merged = self.merged.get(..len).unwrap_or(&[]);
        for (c, (bearing, point)) in merged
            .iter()
            .zip(self.bearings.iter_mut().zip(self.points.iter_mut()))
        {
            (*bearing, *point) = solver_pair(map, query, usize::from(c.keypoint), c.point)?;
        }
        Ok(())
    }

    /// The pose of the merged correspondences, or why there is none: one [`Localizer::attempt`],
    /// and after a refusal the [`Localizer::second_attempt`] when configured. Without a
    /// pose no correspondence stays marked inlier.
    fn decide(&mut self, inputs: PoseInputs<'_>, localization: &mut Localization) -> Result<()> {
        self.attempt(inputs, localization)?;
        let refused = matches!(localization.outcome, Err(Failure::LowConfidence { .. }));
        if refused && inputs.config.second_attempt {
            self.second_attempt(inputs, localization)?;
        }
        if localization.outcome.is_err() {
            for c in self.merged.iter_mut() {
                c.inlier = false;
            }
        }
        Ok(())
    }

    /// One attempt at the pose: RANSAC-PnP + LM on the first `merged_len` merged
    /// correspondences ([`Localizer::solve`]), re-matched and judged ([`Localizer::judge`]);
    /// sets `localization`'s outcome.
    fn attempt(&mut self, inputs: PoseInputs<'_>, localization: &mut Localization) -> Result<()> {
        let PoseInputs {
            map,
            selected,
            centres,
            config,
            query,
        } = inputs;
        localization.outcome = match self.solve(config, query, centres, localization)? {
            Ok(found) => self.judge(map, selected, config, query, found, localization)?,
            Err(failure) => Err(failure),
        };
        Ok(())
    }

    /// The second attempt after a refused pose: RANSAC-PnP on the merged matches that were
    /// not its inliers, re-matched and judged; it replaces `localization` when the rule
    /// accepts it. Where the network's few true matches are outnumbered, RANSAC-PnP's best
    /// pose may be a chance one; without its inliers the true matches' pose can win
    /// (`docs/evaluation.md`, "Second attempt"). The merged matches keep their order.
    fn second_attempt(
        &mut self,
        inputs: PoseInputs<'_>,
        localization: &mut Localization,
    ) -> Result<()> {
        let len = self.merged_len;
        let mut second = Localization {
            second_attempt: true,
            ..*localization
        };
        let attempted = match self.set_aside_inliers(inputs.map, inputs.query) {
            Ok(others) => {
                self.merged_len = others;
                self.attempt(inputs, &mut second)
            }
            Err(error) => Err(error),
        };
        self.merged_len = len;
        let merged = self.merged.get_mut(..len).unwrap_or(&mut []);
        merged.sort_unstable_by_key(|c| c.keypoint);
        attempted?;
        if second.outcome.is_ok() {
            *localization = second;
        }
        Ok(())
    }

    /// Moves the merged correspondences marked inlier behind the others (each part in
    /// keypoint order, unmarked) and writes the others as the solver's input; returns their
    /// number.
    fn set_aside_inliers(&mut self, map: &Map<'_>, query: &Query<'_>) -> Result<usize> {
        let merged = self.merged.get_mut(..self.merged_len).unwrap_or(&mut []);
        merged.sort_unstable_by_key(|c| (c.inlier, c.keypoint));
        let others = merged.iter().take_while(|c| !c.inlier).count();
        for c in merged.iter_mut() {
            c.inlier = false;
        }
        self.write_solver_input(map, query, others)?;
        Ok(others)
    }

    /// RANSAC-PnP + LM on the merged correspondences: the pose with its [`Evidence`] (the
    /// re-matched inliers not yet counted), its inliers marked.
    fn solve(
        &mut self,
        config: &LocalizerConfig,
        query: &Query<'_>,
        view_centres: &[[f64; 3]],
        localization: &mut Localization,
    ) -> Result<core::result::Result<(Pose, Evidence), Failure>> {
        let len = self.merged_len;
        if len < config.min_matches {
            return Ok(Err(Failure::TooFewMatches {
                needed: config.min_matches,
                found: len,
            }));
        }
        let bearings = self.bearings.get(..len).unwrap_or(&[]);
        let points = self.points.get(..len).unwrap_or(&[]);
        match estimate_pose(bearings, points, &config.ransac_config(N), &mut self.pnp) {
            Ok(estimate) => {
                localization.counts.inliers = estimate.inlier_count;
                localization.ransac_iterations = estimate.iterations;
                if estimate.inlier_count < config.min_inliers {
                    return Ok(Err(Failure::TooFewInliers {
                        needed: config.min_inliers,
                        found: estimate.inlier_count,
                    }));
                }
                let support = PoseSupport {
                    pose: &estimate.pose,
                    matches: self.merged.get(..len).unwrap_or(&[]),
                    inliers: estimate.inlier_mask,
                    bearings,
                    points,
                    threshold: config.ransac.threshold,
                    view_centres,
                };
                let evidence = acceptance::gather(&support, query.keypoints, &query.camera);
                for (c, &inlier) in self.merged.iter_mut().zip(estimate.inlier_mask) {
                    c.inlier = inlier;
                }
                Ok(Ok((estimate.pose, evidence)))
            }
            Err(Error::NoPoseFound) => Ok(Err(Failure::NoPoseFound)),
            Err(Error::DegenerateConfiguration) => Ok(Err(Failure::DegenerateMatches)),
            Err(other) => Err(other),
        }
    }

    /// Re-matches RANSAC-PnP's pose by projection ([`guided`], when configured), then
    /// applies the acceptance rule to the evidence of both.
    fn judge(
        &mut self,
        map: &Map<'_>,
        selected: &[u32],
        config: &LocalizerConfig,
        query: &Query<'_>,
        (pose, mut evidence): (Pose, Evidence),
        localization: &mut Localization,
    ) -> Result<core::result::Result<Pose, Failure>> {
        let pose = match config.guided {
            Some(guided) => {
                let (refined, counts) = self.guide(map, query, selected, pose, &guided, config)?;
                localization.guided = counts;
                evidence.guided_inliers = u32::from(counts.inliers);
                evidence.guided_chance = guided.chance_inliers(
                    counts.chance,
                    config.ransac.threshold,
                    query.camera.mean_focal(),
                );
                refined
            }
            None => {
                evidence.guided_inliers = evidence.inliers;
                pose
            }
        };
        let rule = config.acceptance_rule(N);
        let confidence = rule.confidence(&evidence);
        localization.evidence = Some(evidence);
        localization.confidence = Some(confidence);
        localization.candidate = Some(pose);
        if !rule.accepts(confidence) {
            return Ok(Err(Failure::LowConfidence {
                confidence,
                needed: rule.min_confidence,
                inliers: localization.counts.inliers,
            }));
        }
        Ok(Ok(pose))
    }
}

/// What every attempt at the pose reads ([`Localizer::attempt`]).
#[derive(Clone, Copy)]
struct PoseInputs<'a> {
    map: &'a Map<'a>,
    /// Map indices of the selected views.
    selected: &'a [u32],
    /// Their camera centres, by slot.
    centres: &'a [[f64; 3]],
    config: &'a LocalizerConfig,
    query: &'a Query<'a>,
}

/// Passes to `visit`, per selected view, the points the matcher saw of it (the same rule,
/// [`view_point_bearings`] at capacity `CAP`), as map index and world position; `scratch`
/// holds the rule's depths.
fn visit_view_points<const CAP: usize>(
    map: &Map<'_>,
    selected: &[u32],
    scratch: &mut [[f64; 2]; CAP],
    mut visit: impl FnMut(&mut dyn Iterator<Item = (u32, [f64; 3])>),
) -> Result<()> {
    let depths = scratch.as_flattened_mut().get_mut(..CAP).unwrap_or(&mut []);
    for &view in selected {
        let view_pose = map.view(view as usize)?.pose;
        let positions = map
            .view_point_positions(view as usize)?
            .map(|(index, position)| ((index, position), position));
        let chosen = view_point_bearings(view_pose, positions, CAP, depths);
        visit(&mut chosen.map(|(point, _)| point));
    }
    Ok(())
}

/// What one round of guided re-matching gave ([`Localizer::guided_round`]).
struct GuidedRound {
    /// RANSAC-PnP's pose on the round's pairs.
    pose: Pose,
    /// Pairs of keypoints and projected points.
    pairs: usize,
    /// RANSAC-PnP inliers among the pairs.
    inliers: usize,
}

/// The pose solver's input for keypoint `keypoint` paired with map point `point`: the
/// keypoint's `f64` bearing, recomputed from its pixel, and the point's position.
fn solver_pair(
    map: &Map<'_>,
    query: &Query<'_>,
    keypoint: usize,
    point: u32,
) -> Result<([f64; 2], [f64; 3])> {
    let pixel = query
        .keypoints
        .get(keypoint)
        .copied()
        .unwrap_or([f32::NAN; 2]);
    let bearing = keypoint_bearing(&query.camera, pixel, keypoint)?;
    Ok((bearing, map.point(point as usize)?.map(f64::from)))
}

/// Camera centres of the selected views, by slot.
fn view_centres(map: &Map<'_>, selected: &[u32]) -> Result<heapless::Vec<[f64; 3], MAX_VIEWS>> {
    let mut centres = heapless::Vec::new();
    for &view in selected {
        let centre = map.view(view as usize)?.pose.center();
        // `selected` holds at most MAX_VIEWS views.
        let _ = centres.push([centre.x, centre.y, centre.z]);
    }
    Ok(centres)
}

/// Bearing vector of a query keypoint; a non-finite pixel, or one whose `f32` bearing
/// would not be finite, is [`Error::NonFinite`] with its index; the camera's
/// [`Error::DistortionNotInvertible`] and [`Error::UndistortionDidNotConverge`] get the
/// index too.
fn keypoint_bearing(camera: &Camera, pixel: [f32; 2], index: usize) -> Result<[f64; 2]> {
    let non_finite = Error::NonFinite {
        input: Input::Keypoints,
        index,
    };
    if !pixel.iter().all(|v| v.is_finite()) {
        return Err(non_finite);
    }
    let b = camera
        .pixel_to_bearing([f64::from(pixel[0]), f64::from(pixel[1])])
        .map_err(|error| match error {
            Error::UndistortionDidNotConverge { .. } => Error::UndistortionDidNotConverge { index },
            Error::DistortionNotInvertible { .. } => Error::DistortionNotInvertible { index },
            other => other,
        })?;
    if !b.iter().all(|&v| (v as f32).is_finite()) {
        return Err(non_finite);
    }
    Ok(b)
}

/// Checks the settings before any work.
fn check_config(config: &LocalizerConfig) -> Result<()> {
    if config.min_matches < MIN_CORRESPONDENCES {
        return Err(Error::InvalidConfig {
            parameter: "min_matches",
        });
    }
    if config.min_inliers < MIN_CORRESPONDENCES {
        return Err(Error::InvalidConfig {
            parameter: "min_inliers",
        });
    }
    if let Some(rule) = &config.acceptance {
        rule.check()?;
    }
    if let Some(guided) = &config.guided {
        guided.check()?;
    }
    let ransac = &config.ransac;
    if ransac.max_iterations == 0 {
        return Err(Error::InvalidConfig {
            parameter: "max_iterations",
        });
    }
    if !(ransac.threshold > 0.0 && ransac.threshold.is_finite()) {
        return Err(Error::InvalidConfig {
            parameter: "threshold",
        });
    }
    if !(ransac.confidence > 0.0 && ransac.confidence < 1.0) {
        return Err(Error::InvalidConfig {
            parameter: "confidence",
        });
    }
    Ok(())
}

/// Map view indices of the selection, at most [`MAX_VIEWS`].
fn select_views(map: &Map<'_>, views: ViewSelection<'_>) -> Result<heapless::Vec<u32, MAX_VIEWS>> {
    match views {
        ViewSelection::ImageIds(ids) => map.views_by_image_id::<MAX_VIEWS>(ids),
        ViewSelection::NearPrior {
            prior,
            k,
            max_angle_deg,
        } => {
            prior.check()?;
            if k > MAX_VIEWS {
                return Err(Error::CapacityExceeded {
                    capacity: MAX_VIEWS,
                    requested: k,
                });
            }
            if !max_angle_deg.is_finite() {
                return Err(Error::InvalidConfig {
                    parameter: "max_angle_deg",
                });
            }
            let mut near = map.views_near::<MAX_VIEWS>(&prior, max_angle_deg)?;
            near.truncate(k);
            Ok(near)
        }
    }
}

fn log_summary(l: &Localization, keypoints: usize) {
    let c = &l.counts;
    match &l.outcome {
        Ok(_) => log::info!(
            "localized: {keypoints} keypoints, {} views ({} skipped), matches {} mutual / {} classified / {} merged / {} inliers, {} RANSAC iterations",
            l.views_used, l.views_skipped, c.mutual, c.classified, c.merged, c.inliers, l.ransac_iterations
        ),
        Err(reason) => log::info!(
            "not localized ({reason}): {keypoints} keypoints, {} views, matches {} mutual / {} classified / {} merged",
            l.views_used, c.mutual, c.classified, c.merged
        ),
    }
    if let Some(t) = &l.timings {
        log::debug!(
            "timings (us): prepare {} encode {} match {} merge {} pose {} total {}",
            t.prepare_us,
            t.encode_us,
            t.match_us,
            t.merge_us,
            t.pose_us,
            t.total_us
        );
    }
}

#[cfg(test)]
mod tests {
    extern crate std;

    use std::sync::Mutex;
    use std::vec::Vec;

    use nalgebra::{Rotation3, Vector3};

    use super::*;
    use crate::camera::CameraModel;
    use crate::map::{encode, encoded_len, MapViewEntry};
    use crate::weights::tests_support::{blob, TINY};

    const CAP: usize = 64;
    static LOCALIZER: Mutex<Localizer<CAP>> = Mutex::new(Localizer::new());

    fn camera() -> Camera {
        Camera::from_colmap(CameraModel::SimplePinhole, 640, 480, &[500.0, 320.0, 240.0])
            .expect("valid")
    }

    fn pose(x: f64) -> Pose {
        Pose::new(
            Rotation3::from_euler_angles(0.0, 0.05 * x, 0.0),
            Vector3::new(x, 0.0, 0.0),
        )
    }

    #[test]
    fn the_adaptive_stop_is_the_capacitys_unless_configured() {
        let config = LocalizerConfig::new();
        let stop = |config: &LocalizerConfig, capacity| config.ransac_config(capacity).stop;
        assert_eq!(stop(&config, 128), Some(AdaptiveStop::Inliers));
        assert_eq!(stop(&config, 256), Some(AdaptiveStop::Inliers));
        assert_eq!(stop(&config, 1024), Some(AdaptiveStop::Support));
        let support = LocalizerConfig {
            ransac: RansacConfig {
                stop: Some(AdaptiveStop::Support),
                ..RansacConfig::new()
            },
            ..config
        };
        assert_eq!(stop(&support, 256), Some(AdaptiveStop::Support));
        // Every other setting is the configured one.
        let resolved = RansacConfig {
            stop: None,
            ..config.ransac_config(256)
        };
        assert_eq!(resolved, config.ransac);
    }

    /// 80 points on a wavy surface about 5 units in front of three views (image ids 10,
    /// 20, 30); view 30 observes only the first 8.
    struct Fixture {
        blob: Vec<u8>,
        points: Vec<[f32; 3]>,
    }

    fn fixture() -> Fixture {
        let points = crate::test_scene::wavy_surface();
        let all: Vec<u32> = (0..80).collect();
        let few: Vec<u32> = (0..8).collect();
        let views = [
            MapViewEntry {
                image_id: 10,
                name: "",
                camera_index: 0,
                pose: pose(-0.3),
                points: &all,
            },
            MapViewEntry {
                image_id: 20,
                name: "",
                camera_index: 0,
                pose: pose(0.3),
                points: &all,
            },
            MapViewEntry {
                image_id: 30,
                name: "",
                camera_index: 0,
                pose: pose(0.0),
                points: &few,
            },
        ];
        let mut blob = std::vec![0u8; encoded_len(points.len(), 1, &views)];
        let len = encode(&points, &[camera()], &views, &mut blob).expect("encodes");
        blob.truncate(len);
        Fixture { blob, points }
    }

    /// The fixture's points seen from the query pose, as pixels.
    fn keypoints(f: &Fixture, truth: &Pose) -> Vec<[f32; 2]> {
        f.points
            .iter()
            .map(|p| {
                let x = Vector3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
                let b = truth.bearing(&x, 0).expect("in front");
                let px = camera().bearing_to_pixel(b).expect("projects");
                [px[0] as f32, px[1] as f32]
            })
            .collect()
    }

    /// The fixture, the true query pose and the keypoints its points project to.
    fn keypoints_at_truth() -> (Fixture, Pose, Vec<[f32; 2]>) {
        let f = fixture();
        let truth = pose(0.1);
        let kp = keypoints(&f, &truth);
        (f, truth, kp)
    }

    /// The query of the first [`CAP`] of `keypoints`, seen by [`camera`].
    fn first_keypoints(keypoints: &[[f32; 2]]) -> Query<'_> {
        Query {
            keypoints: &keypoints[..CAP],
            camera: camera(),
        }
    }

    /// [`Localizer::decide`] on `l`'s merged matches with view 0 selected.
    fn decide_with_view_0(
        l: &mut Localizer<CAP>,
        map: &Map<'_>,
        query: &Query<'_>,
        config: &LocalizerConfig,
    ) -> Localization {
        let centres = view_centres(map, &[0]).expect("view 0");
        let inputs = PoseInputs {
            map,
            selected: &[0],
            centres: &centres,
            config,
            query,
        };
        let mut localization = Localization::failed(Failure::NoPoseFound);
        l.decide(inputs, &mut localization).expect("valid");
        localization
    }

    fn with_model<R>(f: impl FnOnce(&Model<'_>) -> R) -> R {
        let mut buf = std::vec![0u8; 64 * 1024];
        let len = blob(&TINY, 5, &mut buf);
        let model = Model::from_bytes(&buf[..len]).expect("valid blob");
        f(&model)
    }

    #[test]
    fn workspace_is_the_matcher_the_pose_solver_and_the_merge_tables() {
        // Per slot: network input bearing (f32 x 2), view point index, correspondence
        // (u16, u32, f32, bool), pose solver input (f64 x 2 + f64 x 3).
        let merge = CAP * (2 * 4 + 4 + 12 + 2 * 8 + 3 * 8) + 8;
        let expected = Matcher::<CAP, f32>::BYTES + PnpWorkspace::<CAP>::BYTES + merge;
        let bytes = Localizer::<CAP, f32>::BYTES;
        assert!(
            bytes >= expected && bytes <= expected + 16,
            "{bytes} vs {expected}"
        );
        // The memory goals: 1 MiB at 256 keypoints, 6 MiB at 1024, f16 Sinkhorn cost.
        const { assert!(Localizer::<256, half::f16>::BYTES <= 1 << 20) };
        const { assert!(Localizer::<1024, half::f16>::BYTES <= 6 << 20) };
    }

    #[test]
    fn bad_queries_and_selections_are_typed_errors() {
        let f = fixture();
        let map = Map::from_bytes(&f.blob).expect("valid map");
        let config = LocalizerConfig::new();
        let good = keypoints(&f, &pose(0.1));
        with_model(|model| {
            let mut l = LOCALIZER.lock().expect("lock");
            let mut run = |keypoints: &[[f32; 2]], camera: Camera, views: ViewSelection<'_>| {
                let query = Query { keypoints, camera };
                l.localize(model, &map, &query, views, &config, None)
                    .map(|_| ())
            };
            let ids = ViewSelection::ImageIds(&[10, 20]);
            let mut nan = good[..CAP].to_vec();
            nan[5][1] = f32::NAN;
            assert_eq!(
                run(&nan, camera(), ids),
                Err(Error::NonFinite {
                    input: Input::Keypoints,
                    index: 5
                })
            );
            assert_eq!(
                run(&good, camera(), ids),
                Err(Error::CapacityExceeded {
                    capacity: CAP,
                    requested: 80
                })
            );
            let degenerate = Camera {
                focal: [0.0, 500.0],
                ..camera()
            };
            assert_eq!(
                run(&good[..20], degenerate, ids),
                Err(Error::InvalidIntrinsics)
            );
            assert_eq!(
                run(&good[..20], camera(), ViewSelection::ImageIds(&[10, 11])),
                Err(Error::MapUnknownImage { image_id: 11 })
            );
            assert_eq!(
                run(&good[..20], camera(), ViewSelection::ImageIds(&[10; 11])),
                Err(Error::CapacityExceeded {
                    capacity: MAX_VIEWS,
                    requested: 11
                })
            );
            let near = |k| ViewSelection::NearPrior {
                prior: pose(0.0),
                k,
                max_angle_deg: 30.0,
            };
            assert_eq!(
                run(&good[..20], camera(), near(11)),
                Err(Error::CapacityExceeded {
                    capacity: MAX_VIEWS,
                    requested: 11
                })
            );
            // Issue 23: a prior whose rotation is all zeros.
            let zero_prior = ViewSelection::NearPrior {
                prior: Pose::new(
                    Rotation3::from_matrix_unchecked(nalgebra::Matrix3::zeros()),
                    Vector3::zeros(),
                ),
                k: 2,
                max_angle_deg: 30.0,
            };
            assert_eq!(
                run(&good[..20], camera(), zero_prior),
                Err(Error::InvalidRotation { input: Input::Pose })
            );
            // Issue 23: a distortion that folds 0.19 px from the principal point would
            // squeeze every keypoint's bearing into a tiny cone; keypoint 0 is beyond it.
            let squeezed = Camera::from_colmap(
                CameraModel::OpenCv,
                640,
                480,
                &[500.0, 500.0, 320.0, 240.0, -1e6, 1e6, 0.0, 0.0],
            )
            .expect("finite intrinsics");
            assert_eq!(
                run(&good[..20], squeezed, ids),
                Err(Error::DistortionNotInvertible { index: 0 })
            );
            // Strong tangential distortion: Newton's undistortion of keypoint 3 fails.
            let tangential = Camera::from_colmap(
                CameraModel::OpenCv,
                640,
                480,
                &[500.0, 500.0, 320.0, 240.0, 0.0, 0.0, 1.0, 1.0],
            )
            .expect("finite intrinsics");
            let mut corner = std::vec![[640.0f32, 480.0]; 20];
            corner[3] = [100.0, 400.0];
            assert_eq!(
                run(&corner, tangential, ids),
                Err(Error::UndistortionDidNotConverge { index: 3 })
            );
        });
    }

    #[test]
    fn unlocalizable_queries_report_a_failure_with_their_counts() {
        let f = fixture();
        let map = Map::from_bytes(&f.blob).expect("valid map");
        let kp = keypoints(&f, &pose(0.1));
        with_model(|model| {
            let mut l = LOCALIZER.lock().expect("lock");
            let mut run = |n: usize, views: ViewSelection<'_>| {
                let query = Query {
                    keypoints: &kp[..n],
                    camera: camera(),
                };
                let config = LocalizerConfig::new();
                l.localize(model, &map, &query, views, &config, None)
                    .expect("valid input")
            };
            let few = run(9, ViewSelection::ImageIds(&[10]));
            assert_eq!(
                few.outcome,
                Err(Failure::TooFewKeypoints {
                    needed: 10,
                    found: 9
                })
            );
            assert_eq!(
                few.pose(),
                Err(Error::LocalizationFailed {
                    reason: Failure::TooFewKeypoints {
                        needed: 10,
                        found: 9
                    }
                })
            );
            let none = run(40, ViewSelection::ImageIds(&[]));
            assert_eq!(none.outcome, Err(Failure::NoViews { skipped: 0 }));
            // View 30 sees 8 points, fewer than the matcher's 10.
            let skipped = run(40, ViewSelection::ImageIds(&[30]));
            assert_eq!(skipped.outcome, Err(Failure::NoViews { skipped: 1 }));
            assert_eq!((skipped.views_used, skipped.views_skipped), (0, 1));
        });
    }

    #[test]
    fn localize_is_deterministic_and_independent_of_earlier_calls() {
        let f = fixture();
        let map = Map::from_bytes(&f.blob).expect("valid map");
        let kp = keypoints(&f, &pose(0.1));
        struct Ticks(core::cell::Cell<u64>);
        impl Clock for Ticks {
            fn now_us(&self) -> u64 {
                self.0.set(self.0.get() + 7);
                self.0.get()
            }
        }
        with_model(|model| {
            let mut l = LOCALIZER.lock().expect("lock");
            let query = Query {
                keypoints: &kp[..CAP],
                camera: camera(),
            };
            let other = Query {
                keypoints: &kp[10..50],
                camera: camera(),
            };
            let views = ViewSelection::NearPrior {
                prior: pose(0.0),
                k: 3,
                max_angle_deg: 10.0,
            };
            let config = LocalizerConfig::new();
            let mut results = Vec::new();
            for q in [&query, &other, &query] {
                let clock = Ticks(core::cell::Cell::new(0));
                let result = l
                    .localize(model, &map, q, views, &config, Some(&clock))
                    .expect("valid input");
                results.push((result, l.correspondences().to_vec()));
            }
            let (first, first_matches) = &results[0];
            assert_eq!(results[2].0, *first);
            assert_eq!(results[2].1, *first_matches);
            // The near-prior selection has all three views; view 30 is skipped.
            assert_eq!((first.views_used, first.views_skipped), (2, 1));
            assert!(first.counts.classified <= first.counts.mutual);
            assert!(first.counts.merged <= first.counts.classified);
            assert!(first.counts.inliers <= first.counts.merged);
            assert_eq!(first_matches.len(), first.counts.merged);
            let t = first.timings.expect("clock given");
            assert_eq!(t.total_us, 5 * 7);
            for w in first_matches.windows(2) {
                assert!(w[0].keypoint < w[1].keypoint);
            }
            let mut points: Vec<u32> = first_matches.iter().map(|c| c.point).collect();
            points.sort_unstable();
            points.dedup();
            assert_eq!(points.len(), first_matches.len(), "each point once");
            assert!(first_matches
                .iter()
                .all(|c| usize::from(c.keypoint) < CAP && c.point < 80 && c.probability > 0.5));
        });
    }

    /// The stages after the network: merging the per-keypoint bests (each 3D point kept
    /// once, at its most probable keypoint) and the pose from the merged correspondences.
    #[test]
    fn guided_re_matching_pulls_a_nearby_pose_onto_the_keypoints() {
        let (f, truth, kp) = keypoints_at_truth();
        let map = Map::from_bytes(&f.blob).expect("valid map");
        let query = first_keypoints(&kp);
        // About 10 px off: less than half the 30 px between neighbouring points.
        let near = Pose::new(
            Rotation3::from_euler_angles(0.0, 0.01, 0.0) * truth.rotation,
            truth.translation + Vector3::new(0.05, -0.05, 0.0),
        );
        let config = LocalizerConfig::new();
        let guided = GuidedConfig::new();
        let mut l = LOCALIZER.lock().expect("lock");
        let (refined, counts) = l
            .guide(&map, &query, &[0, 1], near, &guided, &config)
            .expect("valid");
        assert!(near.rotation_error_deg(&truth) > 0.5);
        assert!(refined.rotation_error_deg(&truth) < 1e-3);
        assert!(refined.translation_error(&truth) < 1e-4);
        // Every keypoint pairs with its own point (the views' other 16 points have none).
        let all = CAP as u16;
        assert_eq!((counts.rounds, counts.pairs, counts.inliers), (4, all, all));
        // The 80 points lie tens of pixels apart: with the keypoints shifted by 20 px none
        // meets a point within the last radius, 5 px, by chance.
        assert_eq!(counts.chance, 0);
        // Within 25 px (keypoints shifted by 100 px) about half of them do.
        let wide = GuidedConfig {
            radii_px: [40.0, 30.0, 25.0, 25.0],
            ..GuidedConfig::new()
        };
        let (_, wide_counts) = l
            .guide(&map, &query, &[0, 1], near, &wide, &config)
            .expect("valid");
        assert!(
            wide_counts.chance > all / 4 && wide_counts.chance < all,
            "{wide_counts:?}"
        );
        // A round that gains inliers over the round before runs again at its radius. A pose
        // turned 0.08 rad about the optical axis moves the projections by up to 13 px, each
        // its own way (no one displacement undoes that): a first radius of 12 px pairs some
        // keypoints, whose exact pose pairs them all in a second round at 12 px. The near
        // pose from 20 px pairs them all in the first round.
        let spun = Pose::new(
            Rotation3::from_euler_angles(0.0, 0.0, 0.08) * truth.rotation,
            truth.translation,
        );
        for (start, first_radius_px, rounds) in
            [(spun, 12.0, guided::RADII + 1), (near, 20.0, guided::RADII)]
        {
            let guided = GuidedConfig {
                radii_px: [first_radius_px, 6.0, 3.0, 1.5],
                ..GuidedConfig::new()
            };
            let (refined, counts) = l
                .guide(&map, &query, &[0, 1], start, &guided, &config)
                .expect("valid");
            assert_eq!(
                (usize::from(counts.rounds), counts.pairs, counts.inliers),
                (rounds, all, all)
            );
            assert!(refined.rotation_error_deg(&truth) < 1e-3);
        }
        // A pose that puts no point near a keypoint stays as it was.
        let far = Pose::new(
            truth.rotation,
            truth.translation + Vector3::new(3.0, 0.0, 0.0),
        );
        let (kept, counts) = l
            .guide(&map, &query, &[0, 1], far, &guided, &config)
            .expect("valid");
        assert_eq!((kept, counts), (far, GuidedCounts::default()));
    }

    /// Step 0 of guided re-matching ([`guided::voted_displacement`]): a pose whose
    /// projections sit more than half the spacing of the points away from their keypoints
    /// pairs most keypoints with a neighbour of their point; the voted displacement moves
    /// them back first.
    #[test]
    fn guided_re_matching_undoes_a_displacement_beyond_half_the_point_spacing() {
        let (f, truth, kp) = keypoints_at_truth();
        let map = Map::from_bytes(&f.blob).expect("valid map");
        let query = first_keypoints(&kp);
        let near = Pose::new(
            truth.rotation,
            truth.translation + Vector3::new(0.18, -0.09, 0.0),
        );
        // The near pose's projections lie 15-25 px from their keypoints.
        let shifted = keypoints(&f, &near);
        for (a, b) in kp.iter().zip(&shifted).take(CAP) {
            let d = (a[0] - b[0]).hypot(a[1] - b[1]);
            assert!((15.0..25.0).contains(&d), "{d}");
        }
        let config = LocalizerConfig::new();
        let mut l = LOCALIZER.lock().expect("lock");
        let (refined, counts) = l
            .guide(&map, &query, &[0, 1], near, &GuidedConfig::new(), &config)
            .expect("valid");
        assert!(refined.rotation_error_deg(&truth) < 1e-3, "{counts:?}");
        assert!(refined.translation_error(&truth) < 1e-4);
        assert_eq!((counts.pairs, counts.inliers), (CAP as u16, CAP as u16));
    }

    #[test]
    fn guided_radii_are_checked_with_the_configuration() {
        let config = LocalizerConfig {
            guided: Some(GuidedConfig {
                radii_px: [40.0, 20.0, f64::NAN, 5.0],
                ..GuidedConfig::new()
            }),
            ..LocalizerConfig::new()
        };
        assert_eq!(
            check_config(&config),
            Err(Error::InvalidConfig {
                parameter: "guided_radius"
            })
        );
        let off = LocalizerConfig {
            guided: None,
            ..config
        };
        assert_eq!(check_config(&off), Ok(()));
    }

    #[test]
    fn merged_true_matches_give_the_true_pose() {
        let (f, truth, kp) = keypoints_at_truth();
        let map = Map::from_bytes(&f.blob).expect("valid map");
        let mut l = LOCALIZER.lock().expect("lock");
        let query = first_keypoints(&kp);
        l.set_query(&query).expect("valid");
        l.clear_matches(CAP);
        let mut claim = |keypoint: usize, point: u32, probability: f32| {
            (l.merged[keypoint].point, l.merged[keypoint].probability) = (point, probability);
        };
        // Keypoint 12 has no accepted match; keypoint 3 also claims point 2 with a lower
        // probability than keypoint 2 does; keypoint 7 claims point 9 with a higher one
        // than keypoint 9.
        for k in (0..CAP).filter(|&k| k != 12) {
            claim(k, k as u32, 0.9);
        }
        claim(3, 2, 0.8);
        claim(7, 9, 0.95);
        l.merge(&map, &query, CAP).expect("merges");
        let merged = l.correspondences().to_vec();
        assert_eq!(merged.len(), CAP - 3);
        assert!(!merged
            .iter()
            .any(|c| c.keypoint == 3 || c.keypoint == 9 || c.keypoint == 12));
        assert!(merged.iter().any(|c| c.keypoint == 7 && c.point == 9));
        let mut localization = Localization::failed(Failure::NoPoseFound);
        let (pose, _) = l
            .solve(
                &LocalizerConfig::new(),
                &query,
                &view_centres(&map, &[0]).expect("view 0"),
                &mut localization,
            )
            .expect("valid")
            .expect("localized");
        assert!(pose.rotation_error_deg(&truth) < 1e-3);
        assert!(pose.translation_error(&truth) < 1e-4);
        // Keypoint 7 matched to the wrong point is the only outlier.
        assert_eq!(localization.counts.inliers, CAP - 4);
        assert_eq!(l.inliers().count(), CAP - 4);
        assert!(l
            .correspondences()
            .iter()
            .any(|c| c.keypoint == 7 && !c.inlier));
    }

    /// The acceptance rule decides on the pose RANSAC found: below its threshold the pose
    /// is refused with its confidence, kept as the candidate, and no inlier is marked.
    #[test]
    fn a_pose_below_the_confidence_threshold_is_refused() {
        let (f, truth, kp) = keypoints_at_truth();
        let map = Map::from_bytes(&f.blob).expect("valid map");
        let mut l = LOCALIZER.lock().expect("lock");
        let query = first_keypoints(&kp);
        let mut solve = |acceptance: AcceptanceRule| {
            l.set_query(&query).expect("valid");
            l.clear_matches(CAP);
            for k in 0..CAP {
                (l.merged[k].point, l.merged[k].probability) = (k as u32, 0.9);
                l.merged[k].view = (k % 3) as u8;
            }
            l.merge(&map, &query, CAP).expect("merges");
            let config = LocalizerConfig {
                acceptance: Some(acceptance),
                ..LocalizerConfig::new()
            };
            let localization = decide_with_view_0(&mut l, &map, &query, &config);
            (localization.outcome, localization, l.inliers().count())
        };
        // Confidence sigmoid(6 - 1 * views) = sigmoid(3) = 0.953 with three views.
        let rule = |min_confidence| AcceptanceRule {
            bias: 6.0,
            weights: [0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0],
            min_confidence,
        };
        let (accepted, with_evidence, marked) = solve(rule(0.95));
        let pose = accepted.expect("accepted");
        assert!(pose.rotation_error_deg(&truth) < 1e-3);
        assert_eq!(marked, CAP);
        let evidence = with_evidence.evidence.expect("gathered");
        assert_eq!((evidence.inliers, evidence.views), (CAP as u32, 3));
        // Under the right pose the points lie in the query's field of view, and the view's
        // centre is at a finite distance.
        assert!(evidence.in_view as usize > CAP / 2, "{evidence:?}");
        let centre = map.view(0).expect("view 0").pose.center();
        assert!(evidence.view_distance > 0.0 || centre == pose.center());
        assert!(evidence.view_distance.is_finite(), "{evidence:?}");
        let confidence = with_evidence.confidence.expect("scored");
        assert!((confidence - 0.952_574).abs() < 1e-5, "{confidence}");

        // Every match is an inlier of the refused pose: no second attempt is possible.
        let (refused, without_pose, marked) = solve(rule(0.96));
        assert!(!without_pose.second_attempt);
        assert_eq!(
            refused,
            Err(Failure::LowConfidence {
                confidence,
                needed: 0.96,
                inliers: CAP
            })
        );
        assert_eq!(marked, 0);
        assert_eq!(without_pose.candidate, Some(pose));
        assert_eq!(without_pose.evidence, Some(evidence));
        let text = std::format!("{}", refused.unwrap_err());
        assert!(text.starts_with("low confidence: 0.953 < 0.960"), "{text}");
    }

    /// The second attempt: 40 of 64 keypoints placed where a wrong pose projects their
    /// points outnumber the 24 of the true pose, so RANSAC-PnP picks the wrong pose; a rule
    /// that refuses it (confidence falling with the inliers) accepts the true pose that
    /// RANSAC-PnP finds on the other 24 matches.
    #[test]
    fn a_refused_pose_gets_a_second_attempt_on_the_matches_it_left_out() {
        let f = fixture();
        let (truth, wrong) = (pose(0.1), pose(0.6));
        let mut kp = keypoints(&f, &wrong);
        kp[40..].copy_from_slice(&keypoints(&f, &truth)[40..]);
        let map = Map::from_bytes(&f.blob).expect("valid map");
        let query = first_keypoints(&kp);
        // Confidence sigmoid(14 - 4 ln(inliers)): 0.32 with 40 inliers, 0.78 with 24.
        let rule = AcceptanceRule {
            bias: 14.0,
            weights: [-4.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            min_confidence: 0.5,
        };
        let mut l = LOCALIZER.lock().expect("lock");
        let mut decide = |second_attempt: bool| {
            l.set_query(&query).expect("valid");
            l.clear_matches(CAP);
            for k in 0..CAP {
                (l.merged[k].point, l.merged[k].probability) = (k as u32, 0.9);
            }
            l.merge(&map, &query, CAP).expect("merges");
            let config = LocalizerConfig {
                acceptance: Some(rule),
                guided: None,
                second_attempt,
                ..LocalizerConfig::new()
            };
            let localization = decide_with_view_0(&mut l, &map, &query, &config);
            let order: Vec<u16> = l.correspondences().iter().map(|c| c.keypoint).collect();
            let inliers: Vec<u16> = l.inliers().map(|c| c.keypoint).collect();
            (localization, order, inliers)
        };
        let (refused, order, inliers) = decide(false);
        assert!(matches!(
            refused.outcome,
            Err(Failure::LowConfidence { inliers: 40, .. })
        ));
        let candidate = refused.candidate.expect("judged");
        assert!(candidate.rotation_error_deg(&wrong) < 1e-3);
        assert!(!refused.second_attempt);
        assert!(inliers.is_empty());
        let in_keypoint_order: Vec<u16> = (0..CAP as u16).collect();
        assert_eq!(order, in_keypoint_order);

        let (second, order, inliers) = decide(true);
        let pose = second.outcome.expect("the second attempt is accepted");
        assert!(pose.rotation_error_deg(&truth) < 1e-3);
        assert!(pose.translation_error(&truth) < 1e-4);
        assert!(second.second_attempt);
        assert_eq!(second.counts.inliers, 24);
        let true_keypoints: Vec<u16> = (40..CAP as u16).collect();
        assert_eq!(inliers, true_keypoints);
        // The merged correspondences keep their order.
        assert_eq!(order, in_keypoint_order);
    }

    #[test]
    fn an_invalid_acceptance_rule_is_a_config_error() {
        let f = fixture();
        let map = Map::from_bytes(&f.blob).expect("valid map");
        let kp = keypoints(&f, &pose(0.1));
        let config = LocalizerConfig {
            acceptance: Some(AcceptanceRule {
                min_confidence: 2.0,
                ..AcceptanceRule::FITTED_1024
            }),
            ..LocalizerConfig::new()
        };
        with_model(|model| {
            let mut l = LOCALIZER.lock().expect("lock");
            let query = Query {
                keypoints: &kp[..20],
                camera: camera(),
            };
            let views = ViewSelection::ImageIds(&[10]);
            assert_eq!(
                l.localize(model, &map, &query, views, &config, None),
                Err(Error::InvalidConfig {
                    parameter: "acceptance"
                })
            );
        });
    }

    #[test]
    fn view_points_are_the_first_ones_the_projection_rule_allows() {
        let behind = [0.0, 0.0, -1.0];
        let ahead = |i: f64| [i, 0.0, 4.0];
        let points = [
            (0, ahead(0.0)),
            (1, behind),
            (2, ahead(1.0)),
            (3, ahead(2.0)),
            (4, ahead(3.0)),
            (5, [1e39, 0.0, 1.0]),
            (6, ahead(4.0)),
            (7, ahead(5.0)),
            // At the camera centre (depth far below 1e-5 of the median, 4).
            (8, [0.0, 0.0, 2.3e-10]),
            (9, ahead(6.0)),
        ];
        let mut depths = [0.0; 100];
        let mut chosen_with = |capacity| -> (Vec<i32>, usize) {
            let mut chosen = view_point_bearings(
                Pose::identity(),
                points.into_iter(),
                capacity,
                &mut depths[..capacity],
            );
            let tags = chosen.by_ref().map(|(tag, _)| tag).collect();
            (tags, chosen.skipped())
        };
        // Seven points have a usable bearing; all fit in 7 or more; the point behind,
        // the one far off axis and the one at the centre are skipped.
        assert_eq!(chosen_with(7), (std::vec![0, 2, 3, 4, 6, 7, 9], 3));
        assert_eq!(chosen_with(100), chosen_with(7));
        // Fewer slots: the first usable ones.
        assert_eq!(chosen_with(3), (std::vec![0, 2, 3], 1));
        assert_eq!(chosen_with(5).0, std::vec![0, 2, 3, 4, 6]);
        assert_eq!(chosen_with(1).0, std::vec![0]);
        assert!(chosen_with(0).0.is_empty());
        let bearings: Vec<[f64; 2]> =
            view_point_bearings(Pose::identity(), points.into_iter(), 2, &mut depths[..2])
                .map(|(_, b)| b)
                .collect();
        assert_eq!(bearings, std::vec![[0.0, 0.0], [0.25, 0.0]]);
    }
}
