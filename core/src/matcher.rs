//! The GoMatch matcher (paper sec. 3, supp. "Architecture Details"): the full forward pass
//! of one query-view pair in a caller-owned, fixed-capacity workspace.
//!
//! ```text
//! bearings -> encoder -> self -> cross -> self -> L2 -> cost -> Sinkhorn
//!          -> mutual assignment -> classifier -> MatchSet
//! ```
//!
//! [`Matcher`] holds every buffer; it is built by a `const fn` so it can live in a `static`
//! (zero-initialised, in `.bss`) and [`Matcher::BYTES`] gives its size for placing it.
//!
//! Work is done once per query where it can be: [`Matcher::encode_query`] runs everything
//! that depends on the query alone (its encoder output, its k-NN graph and the first
//! self-attention layer, which does not yet see the view), and [`Matcher::match_view`]
//! runs, per view, the view's encoder, graph and first self-attention layer (or takes
//! them precomputed, [`Matcher::match_view_features`] with [`crate::view_features`]), then
//! per pair the cross attention, the second self attention, the cost, Sinkhorn, the mutual
//! assignment and the classifier.

use crate::attention::{
    cross_layer, knn_graph, neighbour_count, self_layer, Neighbours, SelfScratch, FUSE_BLOCK,
};
use crate::classifier::{classify, Descriptors};
use crate::encoder::encode;
use crate::error::{Error, Input as Which, Result};
use crate::nn::{l2_normalize_points, LayerTap, ROW_BLOCK};

/// Rows of `N` values in the row scratch: per-row temporaries of the layers (a chunk of
/// output rows waiting for their instance norm), Sinkhorn vectors, norms. Sized by its
/// largest user, the classifier: [`ROW_BLOCK`] rows for up to `2 N` matches (the
/// mutual assignment's fallback). That also holds Sinkhorn's `6 N + 4` values (`N >= 2`), the
/// mutual assignment's `4 N`
/// and self attention's `(1 + ROW_BLOCK) N`.
pub const SCRATCH_ROWS: usize = 2 * ROW_BLOCK;
use crate::limits::{MAX_FEATURE_DIM, MAX_KNN};
use crate::sinkhorn::{
    cost_matrix, mutual_assignment, sinkhorn, Match, PlanScalar, SinkhornParams, Transport,
};
use crate::view_features::FeatureRows;
use crate::weights::{Model, ModelConfig};

pub use crate::limits::{MIN_KEYPOINTS, MIN_POINTS_NETWORK};

/// Intermediate outputs, in forward order (names of the reference fixtures).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stage {
    /// Encoder output of the query keypoints.
    Enc2d,
    /// Encoder output of the database points.
    Enc3d,
    /// After attention layer 0 (self), query.
    Att0Self2d,
    /// After attention layer 0 (self), database.
    Att0Self3d,
    /// After attention layer 1 (cross), query.
    Att1Cross2d,
    /// After attention layer 1 (cross), database.
    Att1Cross3d,
    /// After attention layer 2 (self), query.
    Att2Self2d,
    /// After attention layer 2 (self), database.
    Att2Self3d,
    /// L2-normalised final query descriptors.
    Desc2dL2,
    /// L2-normalised final database descriptors.
    Desc3dL2,
}

/// Receives intermediate outputs during [`Matcher::match_view_observed`] and, as a
/// [`LayerTap`], every layer's input. Features are channel-major: channel `c` of point `i`
/// is `x[c * n + i]`.
pub trait Observer<S: PlanScalar>: LayerTap {
    /// A feature matrix of `channels x n`.
    fn features(&mut self, _stage: Stage, _x: &[f32], _channels: usize, _n: usize) {}
    /// The solved transport (cost, potentials, plan on demand).
    fn transport(&mut self, _t: &Transport<'_, S>) {}
}

/// The observer that ignores everything.
impl<S: PlanScalar> Observer<S> for () {}

/// The matches of one pair: every match of the mutual assignment with its Sinkhorn and
/// classifier probabilities, sorted by 3D then 2D index (the reference's order).
#[derive(Debug, Clone, Copy)]
pub struct MatchSet<const N: usize> {
    items: [[Match; N]; 2],
    len: usize,
    threshold: f32,
    iterations: usize,
}

impl<const N: usize> MatchSet<N> {
    const fn new() -> Self {
        MatchSet {
            items: [[Match {
                i2d: 0,
                i3d: 0,
                sinkhorn: 0.0,
                probability: 0.0,
            }; N]; 2],
            len: 0,
            threshold: 0.0,
            iterations: 0,
        }
    }

    /// All matches of the mutual assignment (capacity `2 N`: the reference's fallback
    /// keeps the union of both one-way assignments).
    pub fn as_slice(&self) -> &[Match] {
        &self.items.as_flattened()[..self.len]
    }

    /// Number of matches.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The matches the classifier accepts: probability above the model's threshold (strictly,
    /// as the reference's evaluation).
    pub fn inliers(&self) -> impl Iterator<Item = &Match> {
        let threshold = self.threshold;
        self.as_slice()
            .iter()
            .filter(move |m| m.probability > threshold)
    }

    /// Sinkhorn iterations run for this pair.
    pub fn sinkhorn_iterations(&self) -> usize {
        self.iterations
    }
}

/// Workspace and forward pass of the matcher for up to `N` keypoints per set, with the
/// Sinkhorn cost matrix stored as `S` (`f32` or `half::f16`).
///
/// Memory (f32 unless noted, `D` = [`MAX_FEATURE_DIM`]): encoder outputs of the query and
/// the two working descriptor sets `3 D N`; one scratch pool `3 D N` shared by the
/// encoder, self attention, cross attention and classifier (never live together); the
/// `N x N` cost in `S`; small per-point rows. See [`Matcher::BYTES`].
pub struct Matcher<const N: usize, S: PlanScalar = f32> {
    /// Query encoder output | query descriptors | database descriptors, `D x N` each.
    features: [[f32; N]; 3 * MAX_FEATURE_DIM],
    /// Stage scratch, `3 D x N`.
    pool: [[f32; N]; 3 * MAX_FEATURE_DIM],
    /// Row scratch, `SCRATCH_ROWS x N`.
    rows: [[f32; N]; SCRATCH_ROWS],
    /// Output block of the self-attention fusing conv.
    fused: [f32; MAX_FEATURE_DIM * FUSE_BLOCK],
    /// Sinkhorn cost, `N x N` (rows 3D, columns 2D); before it is computed, the
    /// self-attention layers' spare scratch ([`SelfScratch::spare`]).
    plan: [[S; N]; N],
    /// Sinkhorn potentials: `u` (`n3 + 1`) then `v` (`n2 + 1`); `3 N >= 2 N + 2` for
    /// `N >= 2`.
    potentials: [[f32; N]; 3],
    graph2d: [Neighbours; N],
    graph3d: [Neighbours; N],
    nn12: [u16; N],
    nn21: [u16; N],
    matches: MatchSet<N>,
    query_len: usize,
    query_config: ModelConfig,
    query_encoded: bool,
    /// 0: [`MIN_KEYPOINTS`].
    min_points: usize,
}

impl<const N: usize, S: PlanScalar> Default for Matcher<N, S> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize, S: PlanScalar> Matcher<N, S> {
    /// Size of the workspace in bytes (like CMSIS-NN's `*_get_buffer_size`).
    pub const BYTES: usize = core::mem::size_of::<Self>();

    /// An empty workspace; all-zero, so a `static` lands in `.bss`.
    pub const fn new() -> Self {
        const { assert!(N >= MIN_POINTS_NETWORK && N <= u16::MAX as usize) };
        Matcher {
            features: [[0.0; N]; 3 * MAX_FEATURE_DIM],
            pool: [[0.0; N]; 3 * MAX_FEATURE_DIM],
            rows: [[0.0; N]; SCRATCH_ROWS],
            fused: [0.0; MAX_FEATURE_DIM * FUSE_BLOCK],
            plan: [[S::ZERO; N]; N],
            potentials: [[0.0; N]; 3],
            graph2d: [[0; MAX_KNN]; N],
            graph3d: [[0; MAX_KNN]; N],
            nn12: [0; N],
            nn21: [0; N],
            matches: MatchSet::new(),
            query_len: 0,
            query_config: ModelConfig {
                feature_dim: 0,
                encoder_blocks: 0,
                classifier_dim: 0,
                classifier_blocks: 0,
                heads: 0,
                knn: 0,
                sinkhorn_iters: 0,
                sinkhorn_eps: 0.0,
                sinkhorn_stop: 0.0,
                match_threshold: 0.0,
                bin_score: 0.0,
            },
            query_encoded: false,
            min_points: 0,
        }
    }

    /// Fewest points accepted per set (default [`MIN_KEYPOINTS`]); values below
    /// [`MIN_POINTS_NETWORK`] are raised to it.
    pub fn set_min_points(&mut self, min: usize) {
        self.min_points = min.max(MIN_POINTS_NETWORK);
    }

    /// Fewest points accepted per set.
    pub fn min_points(&self) -> usize {
        if self.min_points == 0 {
            MIN_KEYPOINTS
        } else {
            self.min_points
        }
    }

    /// Encodes the query keypoints (bearing coordinates `(x/z, y/z)`), builds their
    /// neighbour graph and runs the first self-attention layer on them (all that depends on
    /// the query alone), for any number of following [`Matcher::match_view`] calls.
    pub fn encode_query(&mut self, model: &Model<'_>, query: &[[f32; 2]]) -> Result<()> {
        self.encode_query_observed(model, query, &mut ())
    }

    /// [`Matcher::encode_query`] reporting [`Stage::Enc2d`] and [`Stage::Att0Self2d`] to
    /// `observer`.
    pub fn encode_query_observed<O: Observer<S>>(
        &mut self,
        model: &Model<'_>,
        query: &[[f32; 2]],
        observer: &mut O,
    ) -> Result<()> {
        self.query_encoded = false;
        self.check_points(query, Which::Keypoints)?;
        let n = query.len();
        let d = usize::from(model.config().feature_dim);
        let x = &mut self.features.as_flattened_mut()[..d * n];
        let (pool, rows) = (self.pool.as_flattened_mut(), self.rows.as_flattened_mut());
        encode(&model.encoder, query, x, pool, rows, observer);
        observer.features(Stage::Enc2d, x, d, n);
        let k = neighbour_count(usize::from(model.config().knn), n);
        let graph = &mut self.graph2d[..n];
        knn_graph(query, k, graph);
        let scratch = self_scratch(
            pool,
            rows,
            &mut self.fused,
            self.plan.as_flattened_mut(),
            d,
            n,
        );
        self_layer(&model.self_layers[0], graph, k, x, n, scratch, observer);
        observer.features(Stage::Att0Self2d, x, d, n);
        self.query_len = n;
        self.query_config = *model.config();
        self.query_encoded = true;
        Ok(())
    }

    /// Matches the encoded query against one database view: `db` are the 3D points as
    /// bearing coordinates of the database camera.
    pub fn match_view(&mut self, model: &Model<'_>, db: &[[f32; 2]]) -> Result<&MatchSet<N>> {
        self.match_view_observed(model, db, &mut ())
    }

    /// Encodes the query and matches it against one view.
    pub fn match_pair(
        &mut self,
        model: &Model<'_>,
        query: &[[f32; 2]],
        db: &[[f32; 2]],
    ) -> Result<&MatchSet<N>> {
        self.encode_query(model, query)?;
        self.match_view(model, db)
    }

    /// [`Matcher::match_view`] reporting every intermediate output from [`Stage::Enc3d`]
    /// on to `observer` (the query's first two are reported when it is encoded).
    pub fn match_view_observed<O: Observer<S>>(
        &mut self,
        model: &Model<'_>,
        db: &[[f32; 2]],
        observer: &mut O,
    ) -> Result<&MatchSet<N>> {
        self.match_view_from(model, db, None, observer)
    }

    /// [`Matcher::match_view`] with the view's precomputed features (what
    /// [`Matcher::encode_view`] gives for `db`, e.g. from a map's
    /// [`crate::view_features`]): the pair starts at the cross attention, with the same
    /// result. [`Error::ViewFeaturesMismatch`] (view 0) when `features` do not have the
    /// model's dimension and one column per point of `db`.
    pub fn match_view_features(
        &mut self,
        model: &Model<'_>,
        db: &[[f32; 2]],
        features: FeatureRows<'_>,
    ) -> Result<&MatchSet<N>> {
        if features.dim != usize::from(model.config().feature_dim) || features.count != db.len() {
            return Err(Error::ViewFeaturesMismatch { view: 0 });
        }
        self.match_view_from(model, db, Some(features), &mut ())
    }

    /// What the matcher computes for a database view alone (`db`, bearing coordinates):
    /// the encoder and the first self-attention layer, `d x n` values channel-major, the
    /// input of [`Matcher::match_view_features`].
    pub fn encode_view(&mut self, model: &Model<'_>, db: &[[f32; 2]]) -> Result<&[f32]> {
        self.check_points(db, Which::Points3d)?;
        let d = usize::from(model.config().feature_dim);
        self.view_side(model, db, None, &mut ());
        let slot = MAX_FEATURE_DIM * N;
        Ok(&self.features.as_flattened()[2 * slot..2 * slot + d * db.len()])
    }

    /// The view's side before it meets the query, into the view slot of the features and
    /// `graph3d`: its neighbour graph, and its encoder and first self-attention layer, or
    /// `features` in their place.
    fn view_side<O: Observer<S>>(
        &mut self,
        model: &Model<'_>,
        db: &[[f32; 2]],
        features: Option<FeatureRows<'_>>,
        observer: &mut O,
    ) {
        let config = model.config();
        let (n3, d) = (db.len(), usize::from(config.feature_dim));
        let slot = MAX_FEATURE_DIM * N;
        let rows = self.rows.as_flattened_mut();
        let pool = self.pool.as_flattened_mut();
        let desc3d = &mut self.features.as_flattened_mut()[2 * slot..2 * slot + d * n3];
        let k3 = neighbour_count(usize::from(config.knn), n3);
        knn_graph(db, k3, &mut self.graph3d[..n3]);
        if let Some(features) = features {
            features.copy_to(desc3d);
            return;
        }
        encode(&model.encoder, db, desc3d, pool, rows, observer);
        observer.features(Stage::Enc3d, desc3d, d, n3);
        let scratch = self_scratch(
            pool,
            rows,
            &mut self.fused,
            self.plan.as_flattened_mut(),
            d,
            n3,
        );
        self_layer(
            &model.self_layers[0],
            &self.graph3d[..n3],
            k3,
            desc3d,
            n3,
            scratch,
            observer,
        );
        observer.features(Stage::Att0Self3d, desc3d, d, n3);
    }

    /// The pair from the view's side on ([`Matcher::view_side`]).
    fn match_view_from<O: Observer<S>>(
        &mut self,
        model: &Model<'_>,
        db: &[[f32; 2]],
        features: Option<FeatureRows<'_>>,
        observer: &mut O,
    ) -> Result<&MatchSet<N>> {
        let config = *model.config();
        if !self.query_encoded || self.query_config != config {
            return Err(Error::QueryNotEncoded);
        }
        self.check_points(db, Which::Points3d)?;
        self.view_side(model, db, features, observer);
        let (n2, n3) = (self.query_len, db.len());
        let d = usize::from(config.feature_dim);
        let slot = MAX_FEATURE_DIM * N;
        let rows = self.rows.as_flattened_mut();
        let pool = self.pool.as_flattened_mut();
        let (query, descriptors) = self.features.as_flattened_mut().split_at_mut(slot);
        let (desc2d, desc3d) = descriptors.split_at_mut(slot);
        let (desc2d, desc3d) = (&mut desc2d[..d * n2], &mut desc3d[..d * n3]);
        let k3 = neighbour_count(usize::from(config.knn), n3);
        let k2 = neighbour_count(usize::from(config.knn), n2);
        let graph3d = &self.graph3d[..n3];
        desc2d.copy_from_slice(&query[..d * n2]);

        let heads = usize::from(config.heads);
        cross_layer(&model.cross, heads, desc2d, n2, desc3d, n3, pool, observer);
        cross_layer(&model.cross, heads, desc3d, n3, desc2d, n2, pool, observer);
        observer.features(Stage::Att1Cross2d, desc2d, d, n2);
        observer.features(Stage::Att1Cross3d, desc3d, d, n3);

        let sets = [
            (&mut *desc2d, n2, &self.graph2d[..n2], k2),
            (&mut *desc3d, n3, graph3d, k3),
        ];
        for (x, n, graph, k) in sets {
            let scratch = self_scratch(
                pool,
                rows,
                &mut self.fused,
                self.plan.as_flattened_mut(),
                d,
                n,
            );
            self_layer(&model.self_layers[1], graph, k, x, n, scratch, observer);
        }
        observer.features(Stage::Att2Self2d, desc2d, d, n2);
        observer.features(Stage::Att2Self3d, desc3d, d, n3);

        l2_normalize_points(desc2d, d, n2, rows);
        l2_normalize_points(desc3d, d, n3, rows);
        observer.features(Stage::Desc2dL2, desc2d, d, n2);
        observer.features(Stage::Desc3dL2, desc3d, d, n3);

        let plan = self.plan.as_flattened_mut();
        cost_matrix(desc3d, n3, desc2d, n2, d, plan, rows);
        let params = SinkhornParams {
            eps: config.sinkhorn_eps,
            max_iters: usize::from(config.sinkhorn_iters),
            stop: config.sinkhorn_stop,
            bin_score: config.bin_score,
        };
        let (u, v) = self.potentials.as_flattened_mut().split_at_mut(n3 + 1);
        let iterations = sinkhorn(plan, n3, n2, &params, u, v, rows);
        let transport = Transport {
            cost: &plan[..n3 * n2],
            u: &u[..n3 + 1],
            v: &v[..n2 + 1],
            n3,
            n2,
            params,
            iterations,
        };
        observer.transport(&transport);
        let items = self.matches.items.as_flattened_mut();
        let count = mutual_assignment(&transport, &mut self.nn12, &mut self.nn21, rows, items);

        let descriptors = Descriptors {
            memory: &mut self.features.as_flattened_mut()[slot..],
            offset3: slot,
            n2,
            n3,
        };
        classify(
            &model.classifier,
            descriptors,
            &mut items[..count],
            pool,
            rows,
            observer,
        );
        self.matches.len = count;
        self.matches.threshold = config.match_threshold;
        self.matches.iterations = iterations;
        Ok(&self.matches)
    }

    /// Checks count and finiteness of one input set.
    fn check_points(&self, points: &[[f32; 2]], which: Which) -> Result<()> {
        if points.len() > N {
            return Err(Error::CapacityExceeded {
                capacity: N,
                requested: points.len(),
            });
        }
        let needed = self.min_points();
        if points.len() < needed {
            return Err(Error::TooFewPoints {
                needed,
                found: points.len(),
            });
        }
        if let Some(index) = points
            .iter()
            .position(|p| !p[0].is_finite() || !p[1].is_finite())
        {
            return Err(Error::NonFinite {
                input: which,
                index,
            });
        }
        Ok(())
    }
}

/// Splits the stage scratch for a self-attention layer on a set of `n` points of `d`
/// channels; the Sinkhorn cost `plan`, not yet in use, is its spare memory.
fn self_scratch<'s, S: PlanScalar>(
    pool: &'s mut [f32],
    rows: &'s mut [f32],
    fused: &'s mut [f32],
    plan: &'s mut [S],
    d: usize,
    n: usize,
) -> SelfScratch<'s> {
    let (x1, x2) = pool.split_at_mut(d * n);
    SelfScratch {
        x1,
        x2,
        rows,
        fused,
        spare: bytemuck::pod_align_to_mut::<S, f32>(plan).1,
    }
}

#[cfg(test)]
mod tests {
    extern crate std;

    use std::sync::Mutex;

    use super::*;
    use crate::weights::tests_support::{blob, TINY};

    const CAP: usize = 64;
    static WORKSPACE: Mutex<Matcher<CAP, f32>> = Mutex::new(Matcher::new());
    static WORKSPACE_F16: Mutex<Matcher<CAP, half::f16>> = Mutex::new(Matcher::new());

    fn points(n: usize, seed: u32) -> std::vec::Vec<[f32; 2]> {
        let mut s = seed;
        let mut next = move || {
            s = s.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (s >> 8) as f32 / (1u32 << 24) as f32 - 0.5
        };
        (0..n).map(|_| [next(), next()]).collect()
    }

    fn with_model<R>(f: impl FnOnce(&Model<'_>) -> R) -> R {
        let mut buf = std::vec![0u8; 64 * 1024];
        let len = blob(&TINY, 11, &mut buf);
        let model = Model::from_bytes(&buf[..len]).expect("valid blob");
        f(&model)
    }

    /// TFLite Micro style: fails when the workspace grows. The sizes are the sum of the
    /// buffers documented on [`Matcher`].
    #[test]
    fn workspace_size_is_pinned() {
        fn expected(n: usize, plan: usize) -> usize {
            let d = MAX_FEATURE_DIM;
            let features = 3 * d * n * 4 + 3 * d * n * 4 + SCRATCH_ROWS * n * 4;
            let fused = d * FUSE_BLOCK * 4;
            let graphs = 2 * n * MAX_KNN * 2;
            let matches = 2 * n * 12 + 8 + 4 + 8;
            let rest = 3 * n * 4 + 2 * n * 2 + 8 + core::mem::size_of::<ModelConfig>() + 8 + 8;
            features + fused + n * n * plan + graphs + matches + rest
        }
        let exact = |bytes: usize, n: usize, plan: usize| {
            let e = expected(n, plan);
            // Field order and padding may add a few bytes, never more.
            assert!(bytes >= e - 16 && bytes <= e + 16, "{bytes} vs {e}");
        };
        exact(Matcher::<256, half::f16>::BYTES, 256, 2);
        exact(Matcher::<1024, half::f16>::BYTES, 1024, 2);
        exact(Matcher::<1024, f32>::BYTES, 1024, 4);
        const { assert!(Matcher::<256, half::f16>::BYTES <= 1 << 20) };
        const { assert!(Matcher::<1024, half::f16>::BYTES <= 5_500_000) };
    }

    #[test]
    fn precomputed_view_features_give_the_same_matches() {
        use crate::view_features::{blob_len, write_blob, ViewFeatures};
        with_model(|model| {
            let (q, db) = (points(40, 1), points(50, 2));
            let mut m = WORKSPACE.lock().expect("lock");
            let want = m
                .match_pair(model, &q, &db)
                .expect("runs")
                .as_slice()
                .to_vec();
            let encoded = m.encode_view(model, &db).expect("encodes").to_vec();
            let d = usize::from(model.config().feature_dim);
            assert_eq!(encoded.len(), d * db.len());
            let mut blob = std::vec![0u8; blob_len(d, &[db.len()])];
            let len = write_blob(model.checksum(), d, 64, &[&encoded], &mut blob).expect("fits");
            assert_eq!(len, blob.len());
            let features = ViewFeatures::from_bytes(&blob).expect("valid");
            let rows = features.view(0).expect("one view");
            m.encode_query(model, &q).expect("encodes");
            let got = m.match_view_features(model, &db, rows).expect("runs");
            assert_eq!(got.as_slice(), &want[..]);
            assert_eq!(
                m.match_view_features(model, &db[..49], rows)
                    .map(|s| s.len()),
                Err(Error::ViewFeaturesMismatch { view: 0 })
            );
        });
    }

    #[test]
    fn forward_pass_is_deterministic_and_well_formed() {
        with_model(|model| {
            let (q, db) = (points(40, 1), points(50, 2));
            let mut m = WORKSPACE.lock().expect("lock");
            let first: std::vec::Vec<Match> = m
                .match_pair(model, &q, &db)
                .expect("runs")
                .as_slice()
                .to_vec();
            assert!(!first.is_empty());
            for w in first.windows(2) {
                assert!((w[0].i3d, w[0].i2d) < (w[1].i3d, w[1].i2d));
            }
            for mt in &first {
                assert!(usize::from(mt.i2d) < 40 && usize::from(mt.i3d) < 50);
                assert!(mt.sinkhorn > 0.0 && mt.sinkhorn <= 1.0);
                assert!((0.0..=1.0).contains(&mt.probability));
            }
            // Same inputs, bit-identical outputs; the encoded query is reused per view.
            let again = m.match_view(model, &db).expect("runs").as_slice().to_vec();
            assert_eq!(first, again);
            let set = m.match_view(model, &db).expect("runs");
            let accepted = set.as_slice().iter().filter(|mt| mt.probability > 0.5);
            assert!(set.inliers().eq(accepted));
            let other = m.match_view(model, &points(30, 3)).expect("runs").len();
            assert!(other > 0);
            let back = m.match_view(model, &db).expect("runs").as_slice().to_vec();
            assert_eq!(first, back);
        });
    }

    /// Reads of the layer tap: tensor, channels and points of each input.
    struct Reads(std::vec::Vec<(usize, usize, usize)>);

    impl crate::nn::LayerTap for Reads {
        fn layer_input(&mut self, tensor: usize, input: &crate::nn::LayerInput<'_>) {
            use crate::nn::LayerInput;
            let (channels, points) = match input {
                LayerInput::Points(x) => (x.channels(), x.set()),
                LayerInput::Edges { points, graph, k } => {
                    assert_eq!(graph.len(), points.points());
                    assert!(*k <= MAX_KNN);
                    (points.channels(), points.points())
                }
                LayerInput::Matches { a, b, pair, count } => {
                    for m in 0..*count {
                        let (i, j) = pair(m);
                        assert!(i < a.points() && j < b.points());
                    }
                    (a.channels() + b.channels(), *count)
                }
            };
            self.0.push((tensor, channels, points));
        }
    }

    impl Observer<f32> for Reads {}

    /// The tap (`nn::tap`) sees every tensor of the blob read, each input with the columns
    /// its tensor has (an EdgeConv pair's centre: half of the pair's), on the sets' sizes.
    #[test]
    fn every_layer_reports_its_input() {
        with_model(|model| {
            let (q, db) = (points(40, 1), points(50, 2));
            let mut m = WORKSPACE.lock().expect("lock");
            let mut reads = Reads(std::vec::Vec::new());
            m.encode_query_observed(model, &q, &mut reads)
                .expect("runs");
            let count = m
                .match_view_observed(model, &db, &mut reads)
                .expect("runs")
                .len();
            assert!(count > 0);
            let config = model.config();
            let tensors = crate::weights::tensor_count(config);
            let mut seen = std::vec![false; tensors];
            for &(tensor, channels, n) in &reads.0 {
                let spec = crate::weights::tensor_spec(config, tensor).expect("a blob tensor");
                assert_eq!(spec.cols, channels, "tensor {tensor}");
                assert!(
                    [40, 50, count.max(2)].contains(&n),
                    "tensor {tensor}: {n} points"
                );
                seen[tensor] = true;
                let declared = crate::weights::locate(config, tensor).and_then(|s| s.tensor());
                if declared.map(|t| t.downstream) == Some(crate::weights::Downstream::EdgeCentre) {
                    seen[tensor + 1] = true;
                }
            }
            assert!(seen.iter().all(|&s| s), "{seen:?}");
        });
    }

    /// The kernels chosen at run time (AVX-512 VNNI, or the FMA instruction and 256-bit
    /// vectors, where the CPU has them), every narrower set the CPU has and the portable
    /// ones give bit-identical outputs.
    #[test]
    fn portable_kernels_give_identical_matches() {
        use crate::nn::dispatch::{limit_kernels, KernelSet};
        with_model(|model| {
            let (q, db) = (points(CAP, 3), points(CAP, 4));
            let mut m = WORKSPACE.lock().expect("lock");
            let bits = |set: &[Match]| -> std::vec::Vec<(u16, u16, u32, u32)> {
                set.iter()
                    .map(|m| (m.i2d, m.i3d, m.sinkhorn.to_bits(), m.probability.to_bits()))
                    .collect()
            };
            let mut runs = std::vec::Vec::new();
            for set in [KernelSet::Avx512, KernelSet::Avx2, KernelSet::Portable] {
                limit_kernels(set);
                let matches = m.match_pair(model, &q, &db).map(|s| bits(s.as_slice()));
                runs.push(matches);
            }
            limit_kernels(KernelSet::Avx512);
            let detected = runs[0].clone().expect("runs");
            assert!(!detected.is_empty());
            for run in &runs[1..] {
                assert_eq!(run.as_ref().expect("runs"), &detected);
            }
        });
    }

    /// Widths that are not multiples of the SIMD blocks and 3 heads exercise every tail.
    #[test]
    fn odd_configuration_runs() {
        let config = ModelConfig {
            feature_dim: 12,
            encoder_blocks: 2,
            classifier_dim: 6,
            classifier_blocks: 1,
            heads: 3,
            knn: 4,
            ..TINY
        };
        let mut bytes = std::vec![0u8; 64 * 1024];
        let len = blob(&config, 5, &mut bytes);
        let model = Model::from_bytes(&bytes[..len]).expect("valid blob");
        let mut m = WORKSPACE.lock().expect("lock");
        let set = m
            .match_pair(&model, &points(13, 7), &points(21, 8))
            .expect("runs");
        assert!(!set.is_empty());
        assert!(set
            .as_slice()
            .iter()
            .all(|mt| mt.sinkhorn.is_finite() && (0.0..=1.0).contains(&mt.probability)));
    }

    #[test]
    fn f16_cost_storage_gives_nearly_the_same_matches() {
        with_model(|model| {
            let (q, db) = (points(40, 1), points(50, 2));
            let full = WORKSPACE
                .lock()
                .expect("lock")
                .match_pair(model, &q, &db)
                .expect("runs")
                .as_slice()
                .to_vec();
            let mut half = WORKSPACE_F16.lock().expect("lock");
            let halved = half.match_pair(model, &q, &db).expect("runs").as_slice();
            let common = halved
                .iter()
                .filter(|h| full.iter().any(|f| (f.i2d, f.i3d) == (h.i2d, h.i3d)))
                .count();
            assert!(common * 10 >= full.len() * 9, "{common} of {}", full.len());
        });
    }

    fn coordinate() -> impl proptest::strategy::Strategy<Value = f32> {
        use proptest::prelude::*;
        prop_oneof![
            -2.0f32..2.0,
            Just(0.0f32),
            Just(0.25f32),
            -1e30f32..1e30,
            proptest::num::f32::ANY,
        ]
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(64))]
        /// Any point sets (empty, oversized, duplicated, huge or non-finite coordinates)
        /// give a result or a typed error, never a panic.
        #[test]
        fn arbitrary_points_never_panic(
            q in proptest::collection::vec((coordinate(), coordinate()), 0..70),
            db in proptest::collection::vec((coordinate(), coordinate()), 0..70),
        ) {
            let q: std::vec::Vec<[f32; 2]> = q.into_iter().map(|(x, y)| [x, y]).collect();
            let db: std::vec::Vec<[f32; 2]> = db.into_iter().map(|(x, y)| [x, y]).collect();
            with_model(|model| {
                let mut m = WORKSPACE.lock().expect("lock");
                m.set_min_points(MIN_POINTS_NETWORK);
                if let Ok(set) = m.match_pair(model, &q, &db) {
                    proptest::prop_assert!(set.len() <= 2 * CAP);
                }
                m.min_points = 0;
                Ok(())
            })?;
        }
    }

    /// The whole forward pass runs on a 64 KiB stack (optimised build; unoptimised frames
    /// are larger, so debug builds get 1 MiB).
    #[test]
    fn forward_pass_fits_a_64_kib_stack() {
        let stack = if cfg!(debug_assertions) {
            1 << 20
        } else {
            64 * 1024
        };
        let mut bytes = std::vec![0u8; 64 * 1024];
        let len = blob(&TINY, 11, &mut bytes);
        bytes.truncate(len);
        let (q, db) = (points(CAP, 5), points(CAP, 6));
        let handle = std::thread::Builder::new()
            .stack_size(stack)
            .spawn(move || {
                let model = Model::from_bytes(&bytes)?;
                let mut m = WORKSPACE.lock().expect("lock");
                m.match_pair(&model, &q, &db).map(|set| set.len())
            })
            .expect("thread");
        assert!(handle.join().expect("no stack overflow").expect("runs") > 0);
    }

    #[test]
    fn bad_inputs_are_typed_errors() {
        with_model(|model| {
            let mut m = WORKSPACE.lock().expect("lock");
            m.set_min_points(0);
            assert_eq!(m.min_points(), MIN_POINTS_NETWORK);
            m.min_points = 0;
            assert_eq!(m.min_points(), MIN_KEYPOINTS);
            let q = points(20, 1);
            assert_eq!(
                m.match_pair(model, &q[..9], &q).map(|_| ()),
                Err(Error::TooFewPoints {
                    needed: MIN_KEYPOINTS,
                    found: 9
                })
            );
            let many = points(CAP + 1, 2);
            assert_eq!(
                m.match_pair(model, &q, &many).map(|_| ()),
                Err(Error::CapacityExceeded {
                    capacity: CAP,
                    requested: CAP + 1
                })
            );
            let mut bad = points(20, 3);
            bad[7][1] = f32::NAN;
            assert_eq!(
                m.match_pair(model, &q, &bad).map(|_| ()),
                Err(Error::NonFinite {
                    input: Which::Points3d,
                    index: 7
                })
            );
            bad[7][1] = f32::INFINITY;
            assert_eq!(
                m.encode_query(model, &bad),
                Err(Error::NonFinite {
                    input: Which::Keypoints,
                    index: 7
                })
            );
            // The failed encoding invalidated the previous query.
            assert_eq!(
                m.match_view(model, &q).map(|_| ()),
                Err(Error::QueryNotEncoded)
            );
        });
    }
}
