//! Robust absolute pose from 2D-3D matches: LO-RANSAC around the P3P solver with MSAC
//! scoring, then Levenberg-Marquardt (paper supp. "Pose Estimation"; the reference used
//! OpenCV's RANSAC-PnP, this stage follows PoseLib's LO-RANSAC instead).
//!
//! - Sampling: three distinct correspondences per iteration from a seeded [`SplitMix64`];
//!   P3P ([`crate::p3p`]) gives up to four hypotheses.
//! - Scoring: MSAC cost `sum min(r^2, threshold^2)` of the squared reprojection errors on the
//!   normalised image plane (a point at or behind the camera costs `threshold^2`); inliers
//!   are the points with `r^2 < threshold^2`. The same pass counts the *support*: the points
//!   within the LO radius, `LO_RADIUS_FACTOR` (4) times the threshold. With a threshold
//!   near the noise level a correct but noisy minimal model may have no inlier beyond its own
//!   sample while its support already stands out from random hypotheses.
//! - Local optimisation: a hypothesis whose cost beats every earlier minimal hypothesis, or
//!   whose support beats the best pose so far, is refitted by least squares on its support,
//!   again while the support grows or the cost drops; the refit of lowest cost competes
//!   with the best pose.
//! - Stopping: at `max_iterations` (hard cap), or once `confidence` is reached for the
//!   inlier ratio estimated by the best pose's support or its inliers at the threshold
//!   ([`AdaptiveStop`]; the localizer picks by its capacity, [`AdaptiveStop::for_capacity`]).
//! - Refinement: Levenberg-Marquardt with a Cauchy loss of scale `threshold` on the best
//!   pose's support, gathered again after each of three rounds; then the inliers are
//!   counted once more at the threshold.
//!
//! All scratch memory lives in a caller-owned [`PnpWorkspace`] whose capacity `N` is a
//! const generic; nothing is allocated and the stack use is small and fixed.

use nalgebra::Vector3;

use crate::error::{Error, Result};
use crate::p3p::{self, P3pSolutions};
use crate::pose::Pose;
use crate::refine::{self, Loss, RefineConfig, SelectedCorrespondences};
use crate::rng::SplitMix64;

pub use crate::limits::MIN_CORRESPONDENCES;
/// Points scored between two checks of the early exit of the MSAC loop.
const SCORE_BLOCK: usize = 64;
/// Local optimisation refits on the correspondences within this multiple of the threshold;
/// the count of those (the support) also selects the hypotheses worth optimising.
const LO_RADIUS_FACTOR: f64 = 4.0;
/// Most rounds of gather-and-refit of one local optimisation.
const LO_MAX_ROUNDS: usize = 4;
/// Gather-and-refine rounds of the final refinement.
const FINAL_ROUNDS: usize = 3;
/// Levenberg-Marquardt iterations of one local optimisation round.
const LO_LM_ITERATIONS: u32 = 10;
/// Relative spread below which the world points (or the bearings) count as coincident or
/// collinear.
const DEGENERATE_RELATIVE: f64 = 1e-12;

/// Settings of [`estimate_pose`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RansacConfig {
    /// Hard cap on the number of minimal samples drawn.
    pub max_iterations: u32,
    /// Inlier threshold on the normalised image plane: a correspondence is an inlier when
    /// its squared reprojection error is below `threshold^2`.
    pub threshold: f64,
    /// Stop once an all-inlier sample was drawn with this probability.
    pub confidence: f64,
    /// Seed of the sampling generator; the same seed and input give the same output bits.
    pub seed: u64,
    /// Locally optimise every new best hypothesis (LO-RANSAC).
    pub local_optimization: bool,
    /// Refine the final pose on its inliers with Levenberg-Marquardt.
    pub refine: bool,
    /// What estimates the inlier ratio of the adaptive stop; `None`: [`AdaptiveStop::Support`]
    /// for [`estimate_pose`], [`AdaptiveStop::for_capacity`] for a localizer.
    pub stop: Option<AdaptiveStop>,
}

/// The count of the best pose that estimates the inlier ratio of RANSAC's adaptive stop.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum AdaptiveStop {
    /// The correspondences within the LO radius: with the threshold at the noise level
    /// only ~40 % of the true inliers pass it, so the support stops sooner.
    Support,
    /// The inliers at the threshold. Where the LO radius spans wrong matches to
    /// neighbouring points (under a narrow field of view: `colmap/softmurata`'s 5,120 px
    /// focal length on 640 px images, a 20 px radius) the support stopped sampling after
    /// tens to hundreds of samples on a wrong pose (docs/evaluation.md, "RANSAC's stop").
    Inliers,
}

impl AdaptiveStop {
    /// The stop of a localizer of this capacity: [`AdaptiveStop::Inliers`] up to 256
    /// keypoints, where a query's few true matches are easily outnumbered by near misses
    /// in the support; [`AdaptiveStop::Support`] above (docs/evaluation.md, "RANSAC's stop").
    pub const fn for_capacity(capacity: usize) -> Self {
        if capacity <= 256 {
            Self::Inliers
        } else {
            Self::Support
        }
    }

    /// The count of a scored hypothesis this stop reads.
    fn count(self, score: &Score) -> usize {
        match self {
            Self::Support => score.support,
            Self::Inliers => score.inliers,
        }
    }
}

impl Default for RansacConfig {
    fn default() -> Self {
        Self::new()
    }
}

impl RansacConfig {
    /// 10,000 iterations, threshold `1e-3`, confidence 0.999, seed 0, LO and refinement on,
    /// no stop chosen (see [`RansacConfig::stop`]). (PoseLib caps at 100,000; at 1000 the
    /// matcher's outputs, a few correct matches among ~300, often went unsampled:
    /// docs/evaluation.md, `--ransac-iterations`.)
    pub const fn new() -> Self {
        Self {
            max_iterations: 10_000,
            threshold: 1e-3,
            confidence: 0.999,
            seed: 0,
            local_optimization: true,
            refine: true,
            stop: None,
        }
    }

    /// Squared LO radius: the correspondences within it form a hypothesis's support and
    /// enter local optimisation and the final refinement.
    fn support_limit2(&self) -> f64 {
        self.threshold * self.threshold * LO_RADIUS_FACTOR * LO_RADIUS_FACTOR
    }

    fn validate(&self) -> Result<()> {
        let invalid = |parameter| Err(Error::InvalidConfig { parameter });
        if self.max_iterations == 0 {
            return invalid("max_iterations");
        }
        if !(self.threshold > 0.0 && self.threshold.is_finite()) {
            return invalid("threshold");
        }
        if !(self.confidence > 0.0 && self.confidence < 1.0) {
            return invalid("confidence");
        }
        Ok(())
    }
}

/// Scratch memory of [`estimate_pose`] for up to `N` correspondences: a structure-of-arrays
/// copy of the input for the scoring loop, the inlier mask and an index buffer. Build it
/// once, e.g. in a `static`, and reuse it for every call.
#[derive(Debug, Clone)]
pub struct PnpWorkspace<const N: usize> {
    world_x: [f64; N],
    world_y: [f64; N],
    world_z: [f64; N],
    bearing_x: [f64; N],
    bearing_y: [f64; N],
    inliers: [bool; N],
    selection: [u32; N],
}

impl<const N: usize> Default for PnpWorkspace<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> PnpWorkspace<N> {
    /// Size of the workspace in bytes.
    pub const BYTES: usize = core::mem::size_of::<Self>();

    /// An empty workspace; usable in a `static` initialiser.
    pub const fn new() -> Self {
        const { assert!(N <= u32::MAX as usize, "capacity must fit in u32 indices") };
        Self {
            world_x: [0.0; N],
            world_y: [0.0; N],
            world_z: [0.0; N],
            bearing_x: [0.0; N],
            bearing_y: [0.0; N],
            inliers: [false; N],
            selection: [0; N],
        }
    }

    /// The compiled capacity `N`.
    pub const fn capacity(&self) -> usize {
        N
    }
}

/// Result of [`estimate_pose`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PnpEstimate<'w> {
    /// The estimated pose, world to camera.
    pub pose: Pose,
    /// Per correspondence: inlier of `pose` under the threshold.
    pub inlier_mask: &'w [bool],
    /// Number of `true` entries of `inlier_mask`.
    pub inlier_count: usize,
    /// Minimal samples drawn.
    pub iterations: u32,
}

/// Robust pose of a camera from bearing vectors `(x/z, y/z)` and their world points.
///
/// Fails with a typed error, never a panic: [`Error::LengthMismatch`], fewer than
/// [`MIN_CORRESPONDENCES`] ([`Error::TooFewPoints`]), more than `N`
/// ([`Error::CapacityExceeded`]), a NaN or infinity ([`Error::NonFinite`] with the index),
/// coincident or collinear world points or coincident bearings
/// ([`Error::DegenerateConfiguration`]), an invalid configuration
/// ([`Error::InvalidConfig`]) and no hypothesis at all ([`Error::NoPoseFound`]).
pub fn estimate_pose<'w, const N: usize>(
    bearings: &[[f64; 2]],
    points: &[[f64; 3]],
    config: &RansacConfig,
    workspace: &'w mut PnpWorkspace<N>,
) -> Result<PnpEstimate<'w>> {
    config.validate()?;
    check_input::<N>(bearings, points)?;
    let n = bearings.len();
    let mut ransac = Ransac::new(bearings, points, config, workspace);
    let (best, iterations) = ransac.sample_hypotheses().ok_or(Error::NoPoseFound)?;
    let pose = if config.refine {
        ransac.refine_on_support(&best.pose)
    } else {
        best.pose
    };
    let inlier_count = ransac.mark_inliers(&pose);
    let inlier_mask = workspace.inliers.get(..n).unwrap_or(&[]);
    Ok(PnpEstimate {
        pose,
        inlier_mask,
        inlier_count,
        iterations,
    })
}

/// Input checks of [`estimate_pose`], in the order the errors are documented.
fn check_input<const N: usize>(bearings: &[[f64; 2]], points: &[[f64; 3]]) -> Result<()> {
    if bearings.len() != points.len() {
        return Err(Error::LengthMismatch {
            left: bearings.len(),
            right: points.len(),
        });
    }
    let n = bearings.len();
    if n < MIN_CORRESPONDENCES {
        return Err(Error::TooFewPoints {
            needed: MIN_CORRESPONDENCES,
            found: n,
        });
    }
    if n > N {
        return Err(Error::CapacityExceeded {
            capacity: N,
            requested: n,
        });
    }
    refine::check_finite(bearings, points)?;
    if world_points_are_degenerate(points) || bearings_coincide(bearings) {
        return Err(Error::DegenerateConfiguration);
    }
    Ok(())
}

fn vector(p: &[f64; 3]) -> Vector3<f64> {
    Vector3::new(p[0], p[1], p[2])
}

/// True when all world points coincide or lie on one line.
fn world_points_are_degenerate(points: &[[f64; 3]]) -> bool {
    let Some(origin) = points.first().map(vector) else {
        return true;
    };
    let farthest = points.iter().map(|p| vector(p) - origin).fold(
        Vector3::zeros(),
        |best: Vector3<f64>, d| {
            if d.norm_squared() > best.norm_squared() {
                d
            } else {
                best
            }
        },
    );
    let length2 = farthest.norm_squared();
    if length2.is_nan() || length2 <= 0.0 {
        return true;
    }
    // Largest squared distance to the line through the origin point and the farthest one.
    let off_line2 = points
        .iter()
        .map(|p| (vector(p) - origin).cross(&farthest).norm_squared() / length2)
        .fold(0.0, f64::max);
    off_line2.is_nan() || off_line2 <= DEGENERATE_RELATIVE * length2
}

/// True when all bearings are the same point of the image plane.
fn bearings_coincide(bearings: &[[f64; 2]]) -> bool {
    let Some(first) = bearings.first() else {
        return true;
    };
    let spread2 = bearings
        .iter()
        .map(|b| {
            let (dx, dy) = (b[0] - first[0], b[1] - first[1]);
            dx * dx + dy * dy
        })
        .fold(0.0, f64::max);
    let scale2 = 1.0 + first[0] * first[0] + first[1] * first[1];
    spread2.is_nan() || spread2 <= DEGENERATE_RELATIVE * scale2
}

/// MSAC cost of a pose, its inliers, and its support: the correspondences within the wider
/// local-optimisation radius.
#[derive(Debug, Clone, Copy, Default)]
struct Score {
    cost: f64,
    inliers: usize,
    support: usize,
}

/// What a hypothesis must beat (lower cost or larger support) to be kept.
#[derive(Debug, Clone, Copy)]
struct Bounds {
    cost: f64,
    support: usize,
}

/// A pose with its score.
#[derive(Debug, Clone, Copy)]
struct Scored {
    pose: Pose,
    score: Score,
}

/// State of one call of [`estimate_pose`].
struct Ransac<'a, 'w, const N: usize> {
    bearings: &'a [[f64; 2]],
    points: &'a [[f64; 3]],
    config: &'a RansacConfig,
    workspace: &'w mut PnpWorkspace<N>,
    n: usize,
    threshold2: f64,
    support_limit2: f64,
}

impl<'a, 'w, const N: usize> Ransac<'a, 'w, N> {
    /// Copies the input into the workspace's scoring layout.
    fn new(
        bearings: &'a [[f64; 2]],
        points: &'a [[f64; 3]],
        config: &'a RansacConfig,
        workspace: &'w mut PnpWorkspace<N>,
    ) -> Self {
        let n = bearings.len().min(N);
        for (i, (b, p)) in bearings.iter().zip(points).take(n).enumerate() {
            workspace.world_x[i] = p[0];
            workspace.world_y[i] = p[1];
            workspace.world_z[i] = p[2];
            workspace.bearing_x[i] = b[0];
            workspace.bearing_y[i] = b[1];
        }
        Self {
            bearings,
            points,
            config,
            workspace,
            n,
            threshold2: config.threshold * config.threshold,
            support_limit2: config.support_limit2(),
        }
    }

    /// The sampling loop: best (locally optimised) hypothesis and the samples drawn.
    fn sample_hypotheses(&mut self) -> Option<(Scored, u32)> {
        let mut rng = SplitMix64::new(self.config.seed);
        let mut solutions = P3pSolutions::new();
        let mut best: Option<Scored> = None;
        // A hypothesis is kept (and locally optimised) when its cost beats every earlier
        // minimal hypothesis or its support beats the best pose so far.
        let mut bounds = Bounds {
            cost: f64::INFINITY,
            support: if self.config.local_optimization {
                0
            } else {
                usize::MAX
            },
        };
        let stop = self.config.stop.unwrap_or(AdaptiveStop::Support);
        let mut needed = self.config.max_iterations;
        let mut iterations = 0;
        while iterations < needed {
            iterations += 1;
            let sample = rng.three_distinct(self.n as u32);
            let rays = sample.map(|i| p3p::unit_ray(&self.bearings[i]));
            let world = sample.map(|i| vector(&self.points[i]));
            p3p::solve_rays(&rays, &world, &mut solutions);
            for pose in solutions.as_slice() {
                let Some(score) = self.score(pose, &bounds) else {
                    continue;
                };
                bounds.cost = bounds.cost.min(score.cost);
                let candidate = Scored { pose: *pose, score };
                let improved = if self.config.local_optimization {
                    self.locally_optimize(candidate)
                } else {
                    candidate
                };
                if best.is_none_or(|b| improved.score.cost < b.score.cost) {
                    best = Some(improved);
                    if self.config.local_optimization {
                        bounds.support = bounds.support.max(improved.score.support);
                    }
                    needed = needed.min(self.iterations_needed(stop.count(&improved.score)));
                }
            }
        }
        best.map(|b| (b, iterations))
    }

    /// Samples needed to draw an all-inlier sample with the configured confidence when a
    /// fraction `count / n` of the correspondences are inliers (`count`: the best pose's
    /// count that the [`AdaptiveStop`] reads): `log(1 - confidence) / log(1 - ratio^3)`.
    fn iterations_needed(&self, count: usize) -> u32 {
        let ratio = count as f64 / self.n as f64;
        let all_inlier_sample = ratio * ratio * ratio;
        if all_inlier_sample >= 1.0 {
            return 0;
        }
        let needed = libm::log(1.0 - self.config.confidence) / libm::log1p(-all_inlier_sample);
        if needed.is_finite() && needed < self.config.max_iterations as f64 {
            libm::ceil(needed) as u32
        } else {
            self.config.max_iterations
        }
    }

    /// Score of a pose if it beats `bounds` in cost or in support; `None` as soon as it
    /// can no longer.
    fn score(&self, pose: &Pose, bounds: &Bounds) -> Option<Score> {
        let ws = &*self.workspace;
        let scorer = MsacScorer::new(pose, self.threshold2, self.support_limit2);
        let n = self.n;
        let columns = [
            ws.world_x.get(..n)?,
            ws.world_y.get(..n)?,
            ws.world_z.get(..n)?,
            ws.bearing_x.get(..n)?,
            ws.bearing_y.get(..n)?,
        ];
        let mut total = Score::default();
        let mut start = 0;
        while start < n {
            let end = (start + SCORE_BLOCK).min(n);
            let block = columns.map(|c| c.get(start..end).unwrap_or(&[]));
            let block_score = scorer.score_block(&block);
            total.cost += block_score.cost;
            total.inliers += block_score.inliers;
            total.support += block_score.support;
            let reachable_support = total.support + (n - end);
            if total.cost >= bounds.cost && reachable_support <= bounds.support {
                return None;
            }
            start = end;
        }
        Some(total)
    }

    /// Writes the indices of the correspondences with squared error below `limit2` into the
    /// selection buffer; returns how many.
    fn select_within(&mut self, pose: &Pose, limit2: f64) -> usize {
        let mut count = 0;
        for (i, (b, p)) in self.bearings.iter().zip(self.points).enumerate() {
            if squared_error(pose, b, p).is_some_and(|r2| r2 < limit2) {
                if let Some(slot) = self.workspace.selection.get_mut(count) {
                    *slot = i as u32;
                    count += 1;
                }
            }
        }
        count
    }

    /// Least-squares refit of a pose on the correspondences within `limit2` of it.
    fn refit(&mut self, pose: &Pose, limit2: f64, loss: Loss, max_iterations: u32) -> Option<Pose> {
        let count = self.select_within(pose, limit2);
        if count < 3 {
            return None;
        }
        let set = SelectedCorrespondences {
            bearings: self.bearings,
            points: self.points,
            indices: self.workspace.selection.get(..count).unwrap_or(&[]),
        };
        let config = RefineConfig {
            loss,
            max_iterations,
            ..RefineConfig::new()
        };
        Some(refine::refine_on(&set, pose, &config).pose)
    }

    /// LO step: least-squares refit on the support (the correspondences within the LO
    /// radius), repeated while the support grows or the cost drops; returns the refit of
    /// lowest MSAC cost (the hypothesis itself when none is better).
    fn locally_optimize(&mut self, hypothesis: Scored) -> Scored {
        let limit2 = self.support_limit2;
        let unbounded = Bounds {
            cost: f64::INFINITY,
            support: 0,
        };
        let mut best = hypothesis;
        let mut current = hypothesis;
        for _ in 0..LO_MAX_ROUNDS {
            let Some(pose) = self.refit(&current.pose, limit2, Loss::Squared, LO_LM_ITERATIONS)
            else {
                break;
            };
            let Some(score) = self.score(&pose, &unbounded) else {
                break;
            };
            let refit = Scored { pose, score };
            if score.cost < best.score.cost {
                best = refit;
            }
            let progress = score.support > current.score.support || score.cost < current.score.cost;
            if !progress {
                break;
            }
            current = refit;
        }
        best
    }

    /// Final Levenberg-Marquardt with a Cauchy loss of scale `threshold` on the
    /// correspondences within the local-optimisation radius, gathered again after each round.
    fn refine_on_support(&mut self, pose: &Pose) -> Pose {
        let loss = Loss::Cauchy {
            scale: self.config.threshold,
        };
        let mut pose = *pose;
        for _ in 0..FINAL_ROUNDS {
            let limit2 = self.support_limit2;
            match self.refit(&pose, limit2, loss, RefineConfig::new().max_iterations) {
                Some(refined) => pose = refined,
                None => break,
            }
        }
        pose
    }

    /// Fills the inlier mask for a pose; returns the inlier count.
    fn mark_inliers(&mut self, pose: &Pose) -> usize {
        let threshold2 = self.threshold2;
        let mut count = 0;
        let pairs = self.bearings.iter().zip(self.points);
        for (flag, (b, p)) in self.workspace.inliers.iter_mut().zip(pairs) {
            *flag = squared_error(pose, b, p).is_some_and(|r2| r2 < threshold2);
            count += usize::from(*flag);
        }
        count
    }
}

/// The MSAC cost of one pose, point by point: the hot loop of RANSAC.
struct MsacScorer {
    r: [f64; 9],
    t: [f64; 3],
    threshold2: f64,
    support_limit2: f64,
}

impl MsacScorer {
    fn new(pose: &Pose, threshold2: f64, support_limit2: f64) -> Self {
        let m = pose.rotation.matrix();
        Self {
            r: [
                m.m11, m.m12, m.m13, m.m21, m.m22, m.m23, m.m31, m.m32, m.m33,
            ],
            t: [pose.translation.x, pose.translation.y, pose.translation.z],
            threshold2,
            support_limit2,
        }
    }

    /// Squared reprojection error of one point scaled by its squared depth, `(e^2, z^2)`
    /// with `r^2 = e^2 / z^2`, and whether it lies in front of the camera.
    #[inline(always)]
    fn point(&self, x: f64, y: f64, z: f64, u: f64, v: f64) -> (f64, f64, bool) {
        let [r11, r12, r13, r21, r22, r23, r31, r32, r33] = self.r;
        let px = r11 * x + r12 * y + r13 * z + self.t[0];
        let py = r21 * x + r22 * y + r23 * z + self.t[1];
        let pz = r31 * x + r32 * y + r33 * z + self.t[2];
        let (ex, ey) = (px - u * pz, py - v * pz);
        (ex * ex + ey * ey, pz * pz, pz > 0.0)
    }

    /// Score of a block given as columns `x, y, z, u, v` of equal length, summed in four
    /// interleaved lanes (a fixed order, so the result is reproducible). Inlier and support
    /// tests compare `e^2` with `limit^2 z^2`; the division `e^2 / z^2` is only done for a
    /// group of four holding an inlier.
    fn score_block(&self, columns: &[&[f64]; 5]) -> Score {
        let [xs, ys, zs, us, vs] = columns.map(|c| c.chunks_exact(4));
        let tail = [&xs, &ys, &zs, &us, &vs].map(|c| c.remainder());
        let mut cost = [0.0f64; 4];
        let mut inliers = [0usize; 4];
        let mut support = [0usize; 4];
        for ((((x, y), z), u), v) in xs.zip(ys).zip(zs).zip(us).zip(vs) {
            let mut e2 = [0.0f64; 4];
            let mut z2 = [0.0f64; 4];
            let mut inlier = [false; 4];
            for lane in 0..4 {
                let (e, zz, in_front) = self.point(x[lane], y[lane], z[lane], u[lane], v[lane]);
                // Non-short-circuit `&` keeps the lanes branch-free.
                inlier[lane] = in_front & (e < self.threshold2 * zz);
                support[lane] += usize::from(in_front & (e < self.support_limit2 * zz));
                (e2[lane], z2[lane]) = (e, zz);
            }
            if inlier.iter().any(|&f| f) {
                for lane in 0..4 {
                    cost[lane] += if inlier[lane] {
                        e2[lane] / z2[lane]
                    } else {
                        self.threshold2
                    };
                    inliers[lane] += usize::from(inlier[lane]);
                }
            } else {
                for c in &mut cost {
                    *c += self.threshold2;
                }
            }
        }
        let [x, y, z, u, v] = tail;
        let rest = x.iter().zip(y).zip(z).zip(u).zip(v);
        for (lane, ((((&x, &y), &z), &u), &v)) in rest.enumerate() {
            let (e, zz, in_front) = self.point(x, y, z, u, v);
            let inlier = in_front & (e < self.threshold2 * zz);
            cost[lane] += if inlier { e / zz } else { self.threshold2 };
            inliers[lane] += usize::from(inlier);
            support[lane] += usize::from(in_front & (e < self.support_limit2 * zz));
        }
        Score {
            cost: (cost[0] + cost[1]) + (cost[2] + cost[3]),
            inliers: inliers.iter().sum(),
            support: support.iter().sum(),
        }
    }
}

/// Squared reprojection error on the normalised plane, `None` for a point at or behind the
/// camera.
fn squared_error(pose: &Pose, bearing: &[f64; 2], point: &[f64; 3]) -> Option<f64> {
    let p = pose.transform(&vector(point));
    if p.z.is_nan() || p.z <= 0.0 {
        return None;
    }
    let (ex, ey) = (p.x / p.z - bearing[0], p.y / p.z - bearing[1]);
    Some(ex * ex + ey * ey)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::Input;
    use crate::rng::SplitMix64;
    use crate::test_scene::{random_pose, rotation_distance, transform_points, Scene};
    use proptest::prelude::*;
    use std::boxed::Box;
    use std::sync::Mutex;
    use std::vec::Vec;

    const CAPACITY: usize = 256;

    fn workspace() -> Box<PnpWorkspace<CAPACITY>> {
        Box::new(PnpWorkspace::new())
    }

    fn close(a: &Pose, b: &Pose, tolerance: f64) -> bool {
        rotation_distance(a, b) < tolerance
            && a.translation_error(b) < tolerance * (1.0 + b.translation.norm())
    }

    /// A workspace in a `static`, as firmware would hold it.
    static SHARED: Mutex<PnpWorkspace<64>> = Mutex::new(PnpWorkspace::new());

    #[test]
    fn workspace_size_is_pinned() {
        // Five f64 columns, a bool mask and u32 indices per correspondence.
        assert_eq!(PnpWorkspace::<1024>::BYTES, 1024 * (5 * 8 + 1 + 4));
        assert_eq!(
            PnpWorkspace::<64>::BYTES,
            core::mem::size_of::<PnpWorkspace<64>>()
        );
    }

    #[test]
    fn static_workspace_solves_a_small_scene() {
        let scene = Scene::new(5, 40, 30, 0.0);
        let mut ws = SHARED.lock().unwrap();
        let estimate = estimate_pose(
            &scene.bearings,
            &scene.points,
            &RansacConfig::new(),
            &mut ws,
        )
        .unwrap();
        assert!(close(&estimate.pose, &scene.pose, 1e-9));
        assert_eq!(estimate.inlier_mask.len(), 40);
        assert!(estimate.inlier_mask[..30].iter().all(|&f| f));
    }

    #[test]
    fn same_seed_gives_identical_bits() {
        let scene = Scene::new(9, 120, 60, 1e-3);
        let config = RansacConfig::new();
        let (mut a, mut b) = (workspace(), workspace());
        let first = estimate_pose(&scene.bearings, &scene.points, &config, &mut a).unwrap();
        let second = estimate_pose(&scene.bearings, &scene.points, &config, &mut b).unwrap();
        assert_eq!(first, second);
        let count = first.inlier_mask.iter().filter(|&&f| f).count();
        assert_eq!(count, first.inlier_count);
        assert!(first.iterations >= 1 && first.iterations <= config.max_iterations);
    }

    #[test]
    fn noisy_half_outlier_scene_is_solved_accurately() {
        let scene = Scene::new(21, 200, 100, 1e-3);
        let mut ws = workspace();
        let estimate = estimate_pose(
            &scene.bearings,
            &scene.points,
            &RansacConfig::new(),
            &mut ws,
        )
        .unwrap();
        assert!(estimate.pose.rotation_error_deg(&scene.pose) < 0.2);
        assert!(estimate.pose.center_error(&scene.pose) < 0.05);
        // About 40% of the true inliers are within a threshold equal to the noise level.
        assert!(estimate.inlier_count > 25, "{}", estimate.inlier_count);
    }

    /// The inlier stop: correspondences 2-3.5 thresholds off (matches to neighbouring points
    /// under a narrow field of view) fill the LO radius of any nearby pose, and sampling
    /// goes on until an all-inlier sample is likely; the support stop ends at once.
    #[test]
    fn near_misses_in_the_support_stop_only_the_support_stop() {
        let config = RansacConfig {
            stop: Some(AdaptiveStop::Inliers),
            ..RansacConfig::new()
        };
        let mut scene = Scene::new(33, 200, 200, 0.0);
        let mut rng = SplitMix64::new(7);
        for bearing in &mut scene.bearings[30..] {
            let angle = 2.0 * core::f64::consts::PI * rng.unit_f64();
            let offset = config.threshold * (2.0 + 1.5 * rng.unit_f64());
            bearing[0] += offset * libm::cos(angle);
            bearing[1] += offset * libm::sin(angle);
        }
        let mut ws = workspace();
        let estimate = estimate_pose(&scene.bearings, &scene.points, &config, &mut ws).unwrap();
        // log(1 - 0.999) / log(1 - 0.15^3): the samples that draw three of the 30 inliers.
        assert!(estimate.iterations >= 2_043, "{}", estimate.iterations);
        assert_eq!(estimate.inlier_count, 30);
        // The final refinement's Cauchy loss still weighs the near misses a little.
        assert!(estimate.pose.rotation_error_deg(&scene.pose) < 0.05);
        let support = RansacConfig {
            stop: Some(AdaptiveStop::Support),
            ..config
        };
        let mut other = workspace();
        let early = estimate_pose(&scene.bearings, &scene.points, &support, &mut ws).unwrap();
        assert!(early.iterations < 10, "{}", early.iterations);
        let default = RansacConfig::new();
        let by_default = estimate_pose(&scene.bearings, &scene.points, &default, &mut other);
        assert_eq!(by_default.unwrap(), early);
    }

    #[test]
    fn lo_and_refinement_can_be_switched_off() {
        let scene = Scene::new(4, 100, 80, 0.0);
        let config = RansacConfig {
            local_optimization: false,
            refine: false,
            ..RansacConfig::new()
        };
        let mut ws = workspace();
        let estimate = estimate_pose(&scene.bearings, &scene.points, &config, &mut ws).unwrap();
        assert!(close(&estimate.pose, &scene.pose, 1e-8));
        assert_eq!(estimate.inlier_count, 80);
    }

    #[test]
    fn bad_input_is_a_typed_error() {
        let scene = Scene::new(3, 20, 20, 0.0);
        let config = RansacConfig::new();
        let mut ws = workspace();
        let (b, p) = (&scene.bearings, &scene.points);
        assert_eq!(
            estimate_pose(&b[..10], p, &config, &mut ws).unwrap_err(),
            Error::LengthMismatch {
                left: 10,
                right: 20
            }
        );
        assert_eq!(
            estimate_pose(&b[..3], &p[..3], &config, &mut ws).unwrap_err(),
            Error::TooFewPoints {
                needed: 4,
                found: 3
            }
        );
        let mut small = PnpWorkspace::<8>::new();
        assert_eq!(
            estimate_pose(b, p, &config, &mut small).unwrap_err(),
            Error::CapacityExceeded {
                capacity: 8,
                requested: 20
            }
        );
        let mut nan_bearings = b.clone();
        nan_bearings[7][1] = f64::NAN;
        assert_eq!(
            estimate_pose(&nan_bearings, p, &config, &mut ws).unwrap_err(),
            Error::NonFinite {
                input: Input::Keypoints,
                index: 7
            }
        );
        let mut inf_points = p.clone();
        inf_points[12][0] = f64::NEG_INFINITY;
        assert_eq!(
            estimate_pose(b, &inf_points, &config, &mut ws).unwrap_err(),
            Error::NonFinite {
                input: Input::Points3d,
                index: 12
            }
        );
        let coincident: Vec<[f64; 3]> = p.iter().map(|_| [1.0, 2.0, 3.0]).collect();
        assert_eq!(
            estimate_pose(b, &coincident, &config, &mut ws).unwrap_err(),
            Error::DegenerateConfiguration
        );
        let collinear: Vec<[f64; 3]> = (0..20).map(|i| [i as f64, 2.0 * i as f64, 5.0]).collect();
        assert_eq!(
            estimate_pose(b, &collinear, &config, &mut ws).unwrap_err(),
            Error::DegenerateConfiguration
        );
        let same_bearing: Vec<[f64; 2]> = b.iter().map(|_| [0.1, -0.2]).collect();
        assert_eq!(
            estimate_pose(&same_bearing, p, &config, &mut ws).unwrap_err(),
            Error::DegenerateConfiguration
        );
        let bad_threshold = RansacConfig {
            threshold: -1.0,
            ..config
        };
        assert_eq!(
            estimate_pose(b, p, &bad_threshold, &mut ws).unwrap_err(),
            Error::InvalidConfig {
                parameter: "threshold"
            }
        );
        let bad_confidence = RansacConfig {
            confidence: 1.0,
            ..config
        };
        assert!(matches!(
            estimate_pose(b, p, &bad_confidence, &mut ws),
            Err(Error::InvalidConfig { .. })
        ));
    }

    #[test]
    fn no_hypothesis_is_an_error() {
        // No triple of these four correspondences has a pose with positive depths (checked
        // independently by scanning the depth of the first point of each triple).
        let bearings = [[0.3, -0.6], [-0.2, 0.8], [0.4, 0.9], [0.5, -0.7]];
        let points = [
            [-1.3, 1.0, 1.1],
            [-0.4, -1.6, 1.8],
            [0.4, -1.6, 1.4],
            [1.4, -2.0, -0.8],
        ];
        let mut ws = workspace();
        let result = estimate_pose(&bearings, &points, &RansacConfig::new(), &mut ws);
        assert_eq!(result.unwrap_err(), Error::NoPoseFound);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        #[test]
        fn noise_free_scenes_with_outliers_recover_the_pose(
            seed in any::<u64>(),
            count in 20usize..150,
            outlier_percent in 0usize..60,
        ) {
            let inliers = count - count * outlier_percent / 100;
            let scene = Scene::new(seed, count, inliers, 0.0);
            let mut ws = workspace();
            let config = RansacConfig::new();
            let estimate = estimate_pose(&scene.bearings, &scene.points, &config, &mut ws).unwrap();
            // The final refinement runs on everything within the LO radius, so an outlier that
            // happens to lie there (outside the inlier threshold) pulls the pose slightly.
            let outlier_in_radius = (inliers..count).any(|i| {
                squared_error(&scene.pose, &scene.bearings[i], &scene.points[i])
                    .is_some_and(|r2| r2 < config.support_limit2())
            });
            let tolerance = if outlier_in_radius { 1e-3 } else { 1e-6 };
            prop_assert!(close(&estimate.pose, &scene.pose, tolerance));
            prop_assert!(estimate.inlier_mask[..inliers].iter().all(|&f| f));
        }

        #[test]
        fn permuting_the_correspondences_gives_the_same_pose(
            seed in any::<u64>(),
            shuffle_seed in any::<u64>(),
        ) {
            let scene = Scene::new(seed, 60, 40, 0.0);
            let mut order: Vec<usize> = (0..60).collect();
            let mut rng = SplitMix64::new(shuffle_seed);
            for i in (1..order.len()).rev() {
                order.swap(i, rng.below(i as u32 + 1) as usize);
            }
            let bearings: Vec<[f64; 2]> = order.iter().map(|&i| scene.bearings[i]).collect();
            let points: Vec<[f64; 3]> = order.iter().map(|&i| scene.points[i]).collect();
            let config = RansacConfig::new();
            let (mut a, mut b) = (workspace(), workspace());
            let original = estimate_pose(&scene.bearings, &scene.points, &config, &mut a).unwrap();
            let permuted = estimate_pose(&bearings, &points, &config, &mut b).unwrap();
            prop_assert!(close(&original.pose, &permuted.pose, 1e-8));
            for (k, &i) in order.iter().enumerate() {
                prop_assert_eq!(permuted.inlier_mask[k], original.inlier_mask[i]);
            }
        }

        #[test]
        fn rigid_change_of_world_frame_moves_the_pose_with_it(
            seed in any::<u64>(),
            frame_seed in any::<u64>(),
        ) {
            let scene = Scene::new(seed, 60, 40, 0.0);
            let frame = random_pose(&mut SplitMix64::new(frame_seed));
            let moved = transform_points(&frame, &scene.points);
            let config = RansacConfig::new();
            let (mut a, mut b) = (workspace(), workspace());
            let original = estimate_pose(&scene.bearings, &scene.points, &config, &mut a).unwrap();
            let in_new_frame = estimate_pose(&scene.bearings, &moved, &config, &mut b).unwrap();
            let expected = original.pose.compose(&frame.inverse());
            prop_assert!(close(&in_new_frame.pose, &expected, 1e-8));
            prop_assert_eq!(original.inlier_mask, in_new_frame.inlier_mask);
        }
    }
}
