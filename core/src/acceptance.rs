//! Whether a pose is trusted: RANSAC-PnP always returns its best hypothesis, and with few
//! true matches that hypothesis is often wrong while still having a handful of inliers.
//! The [`AcceptanceRule`] scores the [`Evidence`] the pipeline has about the pose with a
//! logistic model, `confidence = 1 / (1 + exp(-(bias + weights . features)))`, an estimate
//! of the probability that the pose is right (reprojection error at most 10 px and
//! rotation error at most 5 deg), and accepts the pose when `confidence >= min_confidence`.
//!
//! The features ([`Evidence::features`]):
//!
//! | # | feature | why |
//! |---|---|---|
//! | 0 | `ln(inliers)` | more independent support |
//! | 1 | `ln(inliers / merged matches)` | a wrong pose's inliers are chance agreements, a number that grows with the matches |
//! | 2 | share of the 8 x 8 image cells holding an inlier keypoint | a wrong pose often rests on a clump of keypoints |
//! | 3 | area of the inliers' bounding box / image area | the same, at the image scale |
//! | 4 | mean classifier probability of the inliers | the network's own belief |
//! | 5 | views whose matches are among the inliers | agreement between database views |
//! | 6 | share of the non-inliers within [`LOOSE_FACTOR`] x the threshold | near-misses of a right pose are noisy true matches |
//! | 7 | share of the merged matches whose point projects in front of the camera, inside the box of the merged keypoints | the matched views overlap the query: under a right pose their points lie in its field of view |
//! | 8 | `ln(1 + d / depth)`: distance `d` from the camera centre to the nearest selected view's centre over the inliers' mean depth | a right pose sits among the views that see what it sees |
//! | 9 | `ln((1 + g) / (1 + c))`: RANSAC-PnP inliers `g` of the pose re-matched by projection ([`crate::guided`]; 0 when no round kept a pose) over those `c` it would have by chance ([`crate::guided::chance_inliers`]) | under a right pose the views' projected points fall on many keypoints, under a wrong one on few, or on as many as their density makes coincide |
//!
//! Before the logistic model, a gate: a pose whose re-matched inliers are less than
//! [`MIN_CHANCE_RATIO`] times the chance level (both plus one) has confidence 0. Re-matching
//! did not confirm it: where the views' points are dense in the query image (a narrow field
//! of view, a small image) a wrong pose re-matches to many inliers, and the other features
//! cannot tell it from a right one.
//!
//! The weights are fitted on training scenes by `gomatch-sim fit-acceptance` from
//! `gomatch-sim eval` reports (see docs/evaluation.md, "Acceptance rule").

use serde::{Deserialize, Serialize};

use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::merge::Correspondence;
use crate::pose::{camera_bearing, Pose};

mod fitted;

/// Number of features of [`Evidence::features`].
pub const FEATURES: usize = 10;
/// Cells per image side of the coverage grid.
pub const GRID: u32 = 8;
/// The looser threshold of the support feature, as a multiple of RANSAC's threshold.
pub const LOOSE_FACTOR: f64 = 4.0;
/// Bound of [`Evidence::view_distance`] (no views, or a pose far off).
pub const MAX_VIEW_DISTANCE: f64 = 1e6;
/// Least [`Evidence::chance_ratio`] of a pose the rule scores (below it the confidence is 0).
/// All but 3 of the 2,044 right training poses at N = 128, 256 and 1024 reach it (median
/// about 23); at N = 256 so do 94 of the 184 right poses of `colmap/softmurata` (640 x 480
/// frames, 7 deg field of view) and 3 of its 170 wrong ones (`docs/acceptance.md`, "Chance
/// level").
pub const MIN_CHANCE_RATIO: f32 = 3.0;

/// What the pipeline knows about a pose, gathered after RANSAC-PnP.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct Evidence {
    /// Merged matches given to the pose solver.
    pub merged: u32,
    /// Inliers of the pose.
    pub inliers: u32,
    /// Merged matches within [`LOOSE_FACTOR`] x the threshold (inliers included).
    pub loose: u32,
    /// Cells of the [`GRID`] x [`GRID`] image grid holding at least one inlier keypoint.
    pub cells: u32,
    /// Area of the inlier keypoints' bounding box as a fraction of the image area.
    pub bbox_area: f32,
    /// Mean classifier probability of the inliers.
    pub mean_probability: f32,
    /// Views (of those matched) that gave at least one inlier.
    pub views: u32,
    /// Merged matches whose point lies in front of the camera and projects inside the
    /// bounding box of the merged keypoints' bearings.
    #[serde(default)]
    pub in_view: u32,
    /// Distance from the camera centre to the nearest centre of the selected views, over the
    /// inliers' mean depth.
    #[serde(default)]
    pub view_distance: f32,
    /// Inliers of the pose re-matched by projection ([`crate::guided::GuidedCounts`]; 0 when
    /// no round kept a pose; RANSAC-PnP's inliers when the localizer does not re-match).
    #[serde(default)]
    pub guided_inliers: u32,
    /// Re-matched inliers expected by chance ([`crate::guided::chance_inliers`]; 0 without
    /// re-matching).
    #[serde(default)]
    pub guided_chance: f32,
}

impl Evidence {
    /// The rule's inputs, in the order of the module's table.
    pub fn features(&self) -> [f32; FEATURES] {
        let inliers = (self.inliers as f32).max(1.0);
        let outliers = self.merged.saturating_sub(self.inliers).max(1) as f32;
        let near = self.loose.saturating_sub(self.inliers) as f32;
        [
            libm::logf(inliers),
            libm::logf(inliers / self.merged.max(self.inliers).max(1) as f32),
            self.cells as f32 / (GRID * GRID) as f32,
            self.bbox_area,
            self.mean_probability,
            self.views as f32,
            near / outliers,
            self.in_view as f32 / self.merged.max(1) as f32,
            libm::log1pf(self.view_distance.max(0.0)),
            libm::logf(self.chance_ratio()),
        ]
    }

    /// `(1 + guided_inliers) / (1 + guided_chance)`: how many times the re-matched inliers
    /// exceed the chance level.
    pub fn chance_ratio(&self) -> f32 {
        (1.0 + self.guided_inliers as f32) / (1.0 + self.guided_chance.max(0.0))
    }

    /// Whether re-matching confirmed the pose: [`Evidence::chance_ratio`] at least
    /// [`MIN_CHANCE_RATIO`].
    pub fn beyond_chance(&self) -> bool {
        self.chance_ratio() >= MIN_CHANCE_RATIO
    }
}

/// A logistic acceptance rule over [`Evidence::features`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AcceptanceRule {
    /// Constant term of the logistic model.
    pub bias: f32,
    /// One weight per feature.
    pub weights: [f32; FEATURES],
    /// Least confidence of an accepted pose, in `[0, 1]`; 0 accepts every pose with
    /// `min_inliers` inliers (the rule before this one).
    pub min_confidence: f32,
}

/// The capacities (keypoints per query and points per view) the project fits a rule at.
pub const FITTED_CAPACITIES: [usize; 3] = [128, 256, 1024];

impl AcceptanceRule {
    /// The rule fitted at the fitted capacity nearest to `capacity` (nearest on a log scale,
    /// ties to the smaller): the evidence of a pose (inlier counts, spread, near-miss support)
    /// depends on how many keypoints and points the localizer matches.
    pub const fn for_capacity(capacity: usize) -> Self {
        match fitted_capacity(capacity) {
            128 => Self::FITTED_128,
            256 => Self::FITTED_256,
            _ => Self::FITTED_1024,
        }
    }

    /// The rule fitted at N = 128 (`models/acceptance/128/rule.json`).
    pub const FITTED_128: Self = Self::fitted(fitted::RULE_128);
    /// The rule fitted at N = 256 (`models/acceptance/256/rule.json`).
    pub const FITTED_256: Self = Self::fitted(fitted::RULE_256);
    /// The rule fitted at N = 1024 (`models/acceptance/1024/rule.json`).
    pub const FITTED_1024: Self = Self::fitted(fitted::RULE_1024);

    const fn fitted((bias, weights, min_confidence): fitted::FittedRule) -> Self {
        Self {
            bias,
            weights,
            min_confidence,
        }
    }

    /// Accepts every pose (confidence 0.5, threshold 0): the bare `min_inliers` rule.
    pub const ACCEPT_ALL: Self = Self {
        bias: 0.0,
        weights: [0.0; FEATURES],
        min_confidence: 0.0,
    };

    /// The logistic score of the evidence, in `[0, 1]`; 0 for a pose re-matching did not
    /// confirm ([`Evidence::beyond_chance`]).
    pub fn confidence(&self, evidence: &Evidence) -> f32 {
        if !evidence.beyond_chance() {
            return 0.0;
        }
        let z = self
            .weights
            .iter()
            .zip(evidence.features())
            .fold(self.bias, |z, (w, x)| z + w * x);
        1.0 / (1.0 + libm::expf(-z))
    }

    /// Whether a pose of this confidence is accepted.
    pub fn accepts(&self, confidence: f32) -> bool {
        confidence >= self.min_confidence
    }

    /// Finite weights and a threshold in `[0, 1]`.
    pub(crate) fn check(&self) -> Result<()> {
        let finite = self.bias.is_finite() && self.weights.iter().all(|w| w.is_finite());
        if !finite || !(0.0..=1.0).contains(&self.min_confidence) {
            return Err(Error::InvalidConfig {
                parameter: "acceptance",
            });
        }
        Ok(())
    }
}

/// The capacity of [`FITTED_CAPACITIES`] nearest to `capacity` on a log scale (ties to the
/// smaller): 128 up to 181, 256 up to 512, 1024 above.
pub const fn fitted_capacity(capacity: usize) -> usize {
    // Geometric midpoints: sqrt(128 * 256) = 181.02, sqrt(256 * 1024) = 512.
    if capacity <= 181 {
        128
    } else if capacity <= 512 {
        256
    } else {
        1024
    }
}

/// The wrong shares of the [`OperatingPoint`]s fitted at each capacity.
pub const OPERATING_SHARES: [f32; 4] = [0.005, 0.01, 0.02, 0.05];

/// A threshold of a fitted rule and what it gave on the training scenes: the least
/// confidence at which at most `max_wrong` of the accepted poses were wrong, and the share
/// of the right poses it kept.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct OperatingPoint {
    /// Largest share of wrong poses among the accepted ones (one of [`OPERATING_SHARES`]).
    pub max_wrong: f32,
    /// The threshold.
    pub min_confidence: f32,
    /// Share of the right training poses accepted at that threshold.
    pub recall: f32,
}

impl OperatingPoint {
    /// The operating points of the rule fitted at `capacity`'s [`fitted_capacity`], strictest
    /// (smallest `max_wrong`) first.
    pub const fn for_capacity(capacity: usize) -> &'static [Self; OPERATING_SHARES.len()] {
        const AT_128: [OperatingPoint; 4] = OperatingPoint::fitted(fitted::POINTS_128);
        const AT_256: [OperatingPoint; 4] = OperatingPoint::fitted(fitted::POINTS_256);
        const AT_1024: [OperatingPoint; 4] = OperatingPoint::fitted(fitted::POINTS_1024);
        match fitted_capacity(capacity) {
            128 => &AT_128,
            256 => &AT_256,
            _ => &AT_1024,
        }
    }

    const fn fitted(points: fitted::FittedPoints) -> [Self; 4] {
        let mut out = [Self {
            max_wrong: 0.0,
            min_confidence: 0.0,
            recall: 0.0,
        }; 4];
        let mut i = 0;
        while i < out.len() {
            let (max_wrong, min_confidence, recall) = points[i];
            out[i] = Self {
                max_wrong,
                min_confidence,
                recall,
            };
            i += 1;
        }
        out
    }

    /// The strictest of `points` a pose of this confidence passes (`None`: none).
    pub fn strictest_passed(points: &[Self], confidence: f32) -> Option<Self> {
        points
            .iter()
            .filter(|p| confidence >= p.min_confidence)
            .min_by(|a, b| a.max_wrong.total_cmp(&b.max_wrong))
            .copied()
    }
}

/// The pose and the solver's inputs the evidence is gathered from.
pub(crate) struct PoseSupport<'a> {
    /// The pose.
    pub pose: &'a Pose,
    /// The merged correspondences (keypoint, probability, view slot).
    pub matches: &'a [Correspondence],
    /// Per correspondence: inlier of the pose.
    pub inliers: &'a [bool],
    /// Per correspondence: the keypoint's bearing.
    pub bearings: &'a [[f64; 2]],
    /// Per correspondence: the world point.
    pub points: &'a [[f64; 3]],
    /// RANSAC's inlier threshold on the normalised image plane.
    pub threshold: f64,
    /// Camera centres of the selected views, by slot.
    pub view_centres: &'a [[f64; 3]],
}

/// Gathers the [`Evidence`] of a pose: inlier keypoints' spread over the query image
/// (`keypoints` in pixels, `camera` for the image size), their probabilities and views,
/// and the support at [`LOOSE_FACTOR`] x the threshold.
pub(crate) fn gather(
    support: &PoseSupport<'_>,
    keypoints: &[[f32; 2]],
    camera: &Camera,
) -> Evidence {
    let (width, height) = (camera.width.max(1) as f32, camera.height.max(1) as f32);
    let loose = LOOSE_FACTOR * support.threshold;
    let loose2 = loose * loose;
    let (mut cells, mut views) = (0u64, 0u32);
    let (mut lo, mut hi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
    let (mut evidence, mut probability) = (Evidence::default(), 0.0f32);
    let field = bearing_box(support.bearings);
    let mut depth = 0.0f64;
    let rows = support
        .matches
        .iter()
        .zip(support.inliers)
        .zip(support.bearings.iter().zip(support.points));
    for ((c, &inlier), (bearing, point)) in rows {
        evidence.merged += 1;
        let in_camera = support
            .pose
            .transform(&nalgebra::Vector3::new(point[0], point[1], point[2]));
        let projected = camera_bearing(&in_camera);
        if projected.is_some_and(|b| inside(&field, b)) {
            evidence.in_view += 1;
        }
        let (dx, dy) = projected.map_or((f64::INFINITY, 0.0), |b| {
            (b[0] - bearing[0], b[1] - bearing[1])
        });
        if dx * dx + dy * dy < loose2 {
            evidence.loose += 1;
        }
        let Some(&[x, y]) = keypoints.get(usize::from(c.keypoint)).filter(|_| inlier) else {
            continue;
        };
        evidence.inliers += 1;
        depth += in_camera.z;
        probability += c.probability;
        views |= 1 << (c.view % 32);
        let cell = |v: f32, size: f32| ((v / size * GRID as f32) as u32).min(GRID - 1);
        cells |= 1 << (cell(y, height) * GRID + cell(x, width));
        (lo, hi) = ([lo[0].min(x), lo[1].min(y)], [hi[0].max(x), hi[1].max(y)]);
    }
    if evidence.inliers > 0 {
        let side = |a: usize, size: f32| ((hi[a].min(size) - lo[a].max(0.0)) / size).max(0.0);
        evidence.bbox_area = side(0, width) * side(1, height);
        evidence.mean_probability = probability / evidence.inliers as f32;
    }
    evidence.cells = cells.count_ones();
    evidence.views = views.count_ones();
    if evidence.inliers > 0 {
        let mean_depth = depth / f64::from(evidence.inliers);
        evidence.view_distance = (nearest_view(support) / mean_depth).min(MAX_VIEW_DISTANCE) as f32;
    }
    evidence
}

/// The smallest box holding every bearing: `[min, max]`.
fn bearing_box(bearings: &[[f64; 2]]) -> [[f64; 2]; 2] {
    bearings.iter().fold(
        [[f64::INFINITY; 2], [f64::NEG_INFINITY; 2]],
        |[lo, hi], b| {
            [
                [lo[0].min(b[0]), lo[1].min(b[1])],
                [hi[0].max(b[0]), hi[1].max(b[1])],
            ]
        },
    )
}

/// Whether a bearing lies in the box.
fn inside(field: &[[f64; 2]; 2], b: [f64; 2]) -> bool {
    (0..2).all(|a| field[0][a] <= b[a] && b[a] <= field[1][a])
}

/// Distance from the pose's camera centre to the nearest view centre (infinite when none).
fn nearest_view(support: &PoseSupport<'_>) -> f64 {
    let centre = support.pose.center();
    support
        .view_centres
        .iter()
        .map(|c| (nalgebra::Vector3::new(c[0], c[1], c[2]) - centre).norm())
        .fold(f64::INFINITY, f64::min)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn evidence(inliers: u32, merged: u32, cells: u32) -> Evidence {
        Evidence {
            merged,
            inliers,
            loose: inliers + (merged - inliers) / 2,
            cells,
            bbox_area: cells as f32 / 64.0,
            mean_probability: 0.6,
            views: 3,
            in_view: merged / 4,
            view_distance: 1.5,
            guided_inliers: 3 * inliers,
            guided_chance: 2.0,
        }
    }

    #[test]
    fn features_follow_the_documented_table() {
        let f = evidence(20, 60, 16).features();
        assert!((f[0] - libm::logf(20.0)).abs() < 1e-6);
        assert!((f[1] - libm::logf(1.0 / 3.0)).abs() < 1e-6);
        assert_eq!(f[2], 0.25);
        assert_eq!(f[3], 0.25);
        assert_eq!(f[4], 0.6);
        assert_eq!(f[5], 3.0);
        assert_eq!(f[6], 0.5);
        assert_eq!(f[7], 0.25);
        assert!((f[8] - libm::logf(2.5)).abs() < 1e-6);
        // 60 re-matched inliers where chance gives 2.
        assert!((f[9] - libm::logf(61.0 / 3.0)).abs() < 1e-6);
        // No division by zero without matches.
        assert!(Evidence::default().features().iter().all(|v| v.is_finite()));
    }

    #[test]
    fn a_pose_re_matched_to_its_chance_level_has_no_confidence() {
        let rule = AcceptanceRule {
            bias: 0.0,
            weights: [1.0; FEATURES],
            min_confidence: 0.5,
        };
        let confirmed = evidence(20, 60, 16);
        assert!(confirmed.beyond_chance() && rule.confidence(&confirmed) > 0.99);
        // 60 re-matched inliers where chance gives 25: fewer than 3 times.
        let at_chance = Evidence {
            guided_chance: 25.0,
            ..confirmed
        };
        assert!((at_chance.chance_ratio() - 61.0 / 26.0).abs() < 1e-6);
        assert!(!at_chance.beyond_chance());
        assert_eq!(rule.confidence(&at_chance), 0.0);
        assert!(!rule.accepts(0.0) && AcceptanceRule::ACCEPT_ALL.accepts(0.0));
        // Exactly 3 times passes.
        let at_gate = Evidence {
            guided_inliers: 59,
            guided_chance: 19.0,
            ..confirmed
        };
        assert!(at_gate.beyond_chance());
    }

    #[test]
    fn confidence_is_a_logistic_score_and_the_threshold_decides() {
        let rule = AcceptanceRule {
            bias: -6.0,
            weights: [2.0, 0.0, 4.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            min_confidence: 0.5,
        };
        let weak = rule.confidence(&evidence(5, 40, 2));
        let strong = rule.confidence(&evidence(60, 80, 30));
        assert!((0.0..0.5).contains(&weak), "{weak}");
        assert!((0.5..=1.0).contains(&strong), "{strong}");
        assert!(!rule.accepts(weak) && rule.accepts(strong));
        assert_eq!(
            AcceptanceRule::ACCEPT_ALL.confidence(&evidence(4, 4, 1)),
            0.5
        );
        assert!(AcceptanceRule::ACCEPT_ALL.accepts(0.0));
        // Bit-identical on repetition.
        assert_eq!(
            rule.confidence(&evidence(60, 80, 30)).to_bits(),
            strong.to_bits()
        );
    }

    #[test]
    fn each_capacity_takes_the_rule_fitted_nearest_to_it() {
        for (capacity, fitted) in [
            (1, 128),
            (128, 128),
            (181, 128),
            (182, 256),
            (256, 256),
            (512, 256),
            (513, 1024),
            (1024, 1024),
            (usize::MAX, 1024),
        ] {
            assert_eq!(fitted_capacity(capacity), fitted, "{capacity}");
            assert_eq!(
                AcceptanceRule::for_capacity(capacity),
                AcceptanceRule::for_capacity(fitted)
            );
        }
        for n in FITTED_CAPACITIES {
            assert_eq!(AcceptanceRule::for_capacity(n).check(), Ok(()));
            let points = OperatingPoint::for_capacity(n);
            let shares = points.map(|p| p.max_wrong);
            assert_eq!(shares, OPERATING_SHARES);
        }
    }

    #[test]
    fn a_confidence_passes_the_strictest_point_at_or_below_it() {
        let point = |max_wrong, min_confidence| OperatingPoint {
            max_wrong,
            min_confidence,
            recall: 0.5,
        };
        let points = [point(0.005, 0.95), point(0.01, 0.8), point(0.05, 0.4)];
        let passed = |c| OperatingPoint::strictest_passed(&points, c).map(|p| p.max_wrong);
        assert_eq!(passed(0.99), Some(0.005));
        assert_eq!(passed(0.95), Some(0.005));
        assert_eq!(passed(0.9), Some(0.01));
        assert_eq!(passed(0.4), Some(0.05));
        assert_eq!(passed(0.3), None);
        assert_eq!(passed(f32::NAN), None);
    }

    #[test]
    fn a_rule_with_non_finite_weights_or_threshold_is_invalid() {
        let invalid = Err(Error::InvalidConfig {
            parameter: "acceptance",
        });
        let mut rule = AcceptanceRule::FITTED_1024;
        assert_eq!(rule.check(), Ok(()));
        rule.weights[3] = f32::NAN;
        assert_eq!(rule.check(), invalid);
        for threshold in [-0.1, 1.5, f32::NAN] {
            let rule = AcceptanceRule {
                min_confidence: threshold,
                ..AcceptanceRule::FITTED_1024
            };
            assert_eq!(rule.check(), invalid);
        }
    }

    #[test]
    fn evidence_counts_spread_views_and_loose_support() {
        let camera = Camera::simple_pinhole(800, 600, 500.0, 400.0, 300.0).expect("valid");
        let pose = Pose::identity();
        // Four matches: three inliers at three corners (views 0, 0, 2), one outlier whose
        // bearing is off by 2x the threshold (within the loose radius) and one off by far.
        let keypoints = [
            [10.0, 10.0],
            [790.0, 10.0],
            [10.0, 590.0],
            [400.0, 300.0],
            [5.0, 5.0],
        ];
        let matches: [Correspondence; 5] = core::array::from_fn(|i| Correspondence {
            keypoint: i as u16,
            point: i as u32,
            probability: [0.9, 0.6, 0.6, 0.3, 0.3][i],
            view: [0, 0, 2, 1, 1][i],
            inlier: false,
        });
        let inliers = [true, true, true, false, false];
        // The far-off outlier's point lies behind the camera: not in view.
        let mut points: [[f64; 3]; 5] = core::array::from_fn(|i| [0.1 * i as f64, 0.0, 1.0]);
        points[4][2] = -1.0;
        let mut bearings: [[f64; 2]; 5] = core::array::from_fn(|i| [0.1 * i as f64, 0.0]);
        bearings[3][1] += 2e-3;
        bearings[4][1] += 1.0;
        let support = PoseSupport {
            pose: &pose,
            matches: &matches,
            inliers: &inliers,
            bearings: &bearings,
            points: &points,
            threshold: 1e-3,
            view_centres: &[[3.0, 0.0, 4.0], [0.0, 0.0, -2.0]],
        };
        let e = gather(&support, &keypoints, &camera);
        assert_eq!(
            (e.merged, e.inliers, e.loose, e.cells, e.views, e.in_view),
            (5, 3, 4, 3, 2, 4)
        );
        // Nearest centre 2 away, inliers 1 deep.
        assert_eq!(e.view_distance, 2.0);
        assert!((e.mean_probability - 0.7).abs() < 1e-6);
        let expected_area = (780.0 / 800.0) * (580.0 / 600.0);
        assert!(
            (e.bbox_area - expected_area).abs() < 1e-6,
            "{}",
            e.bbox_area
        );
    }
}
