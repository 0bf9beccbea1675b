//! Calibration of the int8 conversion: synthetic query-view pairs drawn like the reference
//! fixtures, and the second moments of every layer's inputs (the Hessian `H = X X^T` of
//! the layer's squared output error, used by [`crate::quantize`]) as the core's own forward
//! pass reads them: `gomatch::Matcher` and `gomatch::classifier::classify` report each
//! layer's input to a `gomatch::nn::LayerTap`, so the network exists once, in the core.
//!
//! Tensors are fitted one group at a time (an EdgeConv pair together, whose halves act on
//! the edge `[x_i; x_j]` and share one joint moment matrix) in the order the forward pass
//! reads them. With error correction every group sees the calibration pairs twice: on the
//! float model and on the model quantised so far (an f32 blob of the dequantised weights);
//! the classifier classifies the float model's matches on both, so their sets agree. What
//! follows a tensor in the core's declaration (`weights::Downstream`) sets the form of its
//! moments: centred per set where an instance norm follows it (directly or through another
//! linear layer), because the norm removes any error that is constant over the set.

use anyhow::Context;
use gomatch::classifier::{classify, Descriptors};
use gomatch::encoder::encode;
use gomatch::matcher::Stage;
use gomatch::nn::{Input, LayerInput, LayerTap, ROW_BLOCK};
use gomatch::weights::{locate, tensor_count, Downstream, ModelConfig, Section};
use gomatch::{Match, Matcher, Model, Observer, Precision};
use rand::seq::SliceRandom;
use rand::{RngExt, SeedableRng};
use rand_distr::StandardNormal;
use rand_pcg::Pcg64Mcg;
use std::sync::Mutex;

use crate::float_linear::FloatLinear;
use crate::quantize::{self, Int8Tensor, ScaleSearch};

/// One query-view pair of bearing sets.
#[derive(Debug, Clone)]
pub struct Pair {
    /// Query keypoints, `(x, y)` on the normalised image plane.
    pub query: Vec<[f32; 2]>,
    /// Database points as bearing coordinates `(X/Z, Y/Z)` of the database camera.
    pub db: Vec<[f32; 2]>,
}

/// Pairs drawn like the reference fixtures (`shared/reference/fixtures/*/index.json`):
/// database points with bearings uniform in `[-0.6, 0.6]^2` at depths 4 to 8; a query
/// camera turned by up to 10 degrees about a random axis and moved by up to 0.5 per
/// axis; 70 % of the keypoints are projections of distinct points with noise
/// `sigma = 0.001`, the rest uniform outliers in the projections' bounding box.
/// `n2` is drawn in 32..=400 and `n3` in `n2..1.7 n2`.
pub fn synthetic_pairs(count: usize, seed: u64) -> Vec<Pair> {
    let mut rng = Pcg64Mcg::seed_from_u64(seed);
    (0..count).map(|_| synthetic_pair(&mut rng)).collect()
}

fn synthetic_pair(rng: &mut Pcg64Mcg) -> Pair {
    let n2: usize = rng.random_range(32..=400);
    let n3 = ((n2 as f64) * rng.random_range(1.0..1.7)) as usize;
    let mut db = Vec::with_capacity(n3);
    let mut world = Vec::with_capacity(n3);
    for _ in 0..n3 {
        let u = rng.random_range(-0.6..0.6);
        let v = rng.random_range(-0.6..0.6);
        let z = rng.random_range(4.0..8.0);
        db.push([u as f32, v as f32]);
        world.push([u * z, v * z, z]);
    }
    let rotation = random_rotation(rng, 10f64.to_radians());
    let t: [f64; 3] = core::array::from_fn(|_| rng.random_range(-0.5..0.5));
    let mut order: Vec<usize> = (0..n3).collect();
    order.shuffle(rng);
    let inliers = (n2 * 7).div_ceil(10).min(n3);
    let noise = |rng: &mut Pcg64Mcg| 0.001 * rng.sample::<f64, _>(StandardNormal);
    let mut query: Vec<[f64; 2]> = order[..inliers]
        .iter()
        .map(|&j| {
            let p = world[j];
            let c: [f64; 3] = core::array::from_fn(|r| {
                rotation[r][0] * p[0] + rotation[r][1] * p[1] + rotation[r][2] * p[2] + t[r]
            });
            [c[0] / c[2] + noise(rng), c[1] / c[2] + noise(rng)]
        })
        .collect();
    let (lo, hi) = query.iter().fold(
        ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]),
        |(lo, hi), q| {
            (
                [lo[0].min(q[0]), lo[1].min(q[1])],
                [hi[0].max(q[0]), hi[1].max(q[1])],
            )
        },
    );
    while query.len() < n2 {
        query.push([
            rng.random_range(lo[0]..hi[0]),
            rng.random_range(lo[1]..hi[1]),
        ]);
    }
    query.shuffle(rng);
    Pair {
        query: query.iter().map(|q| [q[0] as f32, q[1] as f32]).collect(),
        db,
    }
}

/// A rotation about a uniformly random axis by an angle uniform in `[0, max_angle]`.
fn random_rotation(rng: &mut Pcg64Mcg, max_angle: f64) -> [[f64; 3]; 3] {
    let a: [f64; 3] = core::array::from_fn(|_| rng.sample::<f64, _>(StandardNormal));
    let norm = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt().max(1e-12);
    let [x, y, z] = a.map(|v| v / norm);
    let angle = rng.random_range(0.0..max_angle);
    let (s, c) = angle.sin_cos();
    let k = 1.0 - c;
    [
        [c + x * x * k, x * y * k - z * s, x * z * k + y * s],
        [y * x * k + z * s, c + y * y * k, y * z * k - x * s],
        [z * x * k - y * s, z * y * k + x * s, c + z * z * k],
    ]
}

/// Second moments of one layer group's inputs over the calibration sets: `h = sum q q^T`
/// of the quantised-path inputs and `g = sum f q^T` with the float-path inputs.
#[derive(Debug, Clone)]
struct Moments {
    dim: usize,
    h: Vec<f64>,
    g: Vec<f64>,
    /// Whether some inputs had a quantised path apart from the float one.
    apart: bool,
}

impl Moments {
    fn new(dim: usize) -> Self {
        Moments {
            dim,
            h: vec![0.0; dim * dim],
            g: vec![0.0; dim * dim],
            apart: false,
        }
    }

    /// Adds the inputs of one set, centred over the set if `centred`.
    fn add(&mut self, x: &Both, centred: bool) {
        let centre = |f: &Features| if centred { f.centred() } else { f.clone() };
        let f = centre(&x.f);
        match &x.q {
            Some(q) => {
                self.apart = true;
                let q = centre(q);
                add_gram(&mut self.h, self.dim, &q);
                add_cross(&mut self.g, self.dim, 0, 0, &f, &q, None);
            }
            None => add_gram(&mut self.h, self.dim, &f),
        }
    }

    /// Adds the edge inputs `[x_i; x_j]` of one set over its neighbour `graph`, centred
    /// over the edges (an instance norm over the edges follows).
    fn add_edges(&mut self, x: &Both, graph: &[Vec<usize>]) {
        match &x.q {
            Some(q) => {
                self.apart = true;
                edge_moments(&mut self.h, self.dim, q, None, graph);
                edge_moments(&mut self.g, self.dim, &x.f, Some(q), graph);
            }
            None => edge_moments(&mut self.h, self.dim, &x.f, None, graph),
        }
    }

    /// `g`, which equals `h` when no input had a separate quantised path.
    fn cross(&self) -> &[f64] {
        if self.apart {
            &self.g
        } else {
            &self.h
        }
    }
}

/// `m += sum_e (a_e - mean a)(b_e - mean b)^T` over the edges `e = (i, j)` of `graph`,
/// with `a_e = [a_i; a_j]` (likewise `b_e`; `b` is `a` when `None`), without forming the
/// edges: with every point having `k` neighbours the blocks are `k sum_i a_i b_i^T`,
/// `sum_i a_i s(b)_i^T`, `sum_i s(a)_i b_i^T` and `sum_j indegree_j a_j b_j^T`, `s(x)_i`
/// the sum of `x` over the neighbours of `i`, each half centred on its edge mean.
fn edge_moments(
    m: &mut [f64],
    dim: usize,
    a: &Features,
    b: Option<&Features>,
    graph: &[Vec<usize>],
) {
    let n = a.n;
    let k = graph.first().map_or(0, Vec::len);
    if k == 0 {
        return;
    }
    let mut indegree = vec![0.0f64; n];
    for neighbours in graph {
        for &j in neighbours {
            indegree[j] += 1.0;
        }
    }
    let edges = (n * k) as f64;
    let halves = |x: &Features| -> (Features, Features, Features) {
        let mut centre = x.clone();
        let mut neighbour = x.clone();
        for c in 0..x.channels {
            let row = x.row(c);
            let mean_i = row.iter().sum::<f64>() / n as f64;
            let mean_j = row.iter().zip(&indegree).map(|(v, d)| v * d).sum::<f64>() / edges;
            centre.row_mut(c).iter_mut().for_each(|v| *v -= mean_i);
            neighbour.row_mut(c).iter_mut().for_each(|v| *v -= mean_j);
        }
        let mut sums = Features::zeros(x.channels, n);
        for c in 0..x.channels {
            let src = neighbour.row(c);
            for (i, nb) in graph.iter().enumerate() {
                sums.row_mut(c)[i] = nb.iter().map(|&j| src[j]).sum();
            }
        }
        (centre, neighbour, sums)
    };
    let (ai, aj, sa) = halves(a);
    let d = a.channels;
    match b {
        Some(b) => {
            let (bi, bj, sb) = halves(b);
            add_cross(m, dim, 0, 0, &ai, &bi, Some(&vec![k as f64; n]));
            add_cross(m, dim, 0, d, &ai, &sb, None);
            add_cross(m, dim, d, 0, &sa, &bi, None);
            add_cross(m, dim, d, d, &aj, &bj, Some(&indegree));
        }
        None => {
            let mut corner = vec![0.0; d * d];
            add_cross(&mut corner, d, 0, 0, &ai, &sa, None);
            for p in 0..d {
                for q in 0..d {
                    m[p * dim + d + q] += corner[p * d + q];
                    m[(d + q) * dim + p] += corner[p * d + q];
                }
            }
            let (mut ii, mut jj) = (vec![0.0; d * d], vec![0.0; d * d]);
            add_gram(&mut ii, d, &ai);
            add_gram(&mut jj, d, &weighted(&aj, &indegree));
            for p in 0..d {
                for q in 0..d {
                    m[p * dim + q] += k as f64 * ii[p * d + q];
                    m[(d + p) * dim + d + q] += jj[p * d + q];
                }
            }
        }
    }
}

/// `x` with every point `i` scaled by `sqrt(w_i)` (so its Gram matrix is weighted by `w`).
fn weighted(x: &Features, w: &[f64]) -> Features {
    let mut out = x.clone();
    let roots: Vec<f64> = w.iter().map(|v| v.sqrt()).collect();
    for c in 0..out.channels {
        out.row_mut(c)
            .iter_mut()
            .zip(&roots)
            .for_each(|(v, r)| *v *= r);
    }
    out
}

/// `m += sum_i x_i x_i^T` (`dim = x.channels`), computing one triangle.
fn add_gram(m: &mut [f64], dim: usize, x: &Features) {
    let mut upper = vec![0.0f64; x.channels];
    for p in 0..x.channels {
        let part = &mut upper[p..];
        part.fill(0.0);
        dots(x.row(p), x, p, part);
        for (offset, &v) in part.iter().enumerate() {
            let q = p + offset;
            m[p * dim + q] += v;
            if q != p {
                m[q * dim + p] += v;
            }
        }
    }
}

/// `m[r0 + a][c0 + b] += sum_i w_i a_i b_i` over the points of two channel-major sets.
fn add_cross(
    m: &mut [f64],
    dim: usize,
    r0: usize,
    c0: usize,
    a: &Features,
    b: &Features,
    weights: Option<&[f64]>,
) {
    let weighted: Features;
    let a = match weights {
        Some(w) => {
            let mut s = a.clone();
            for c in 0..s.channels {
                s.row_mut(c).iter_mut().zip(w).for_each(|(v, w)| *v *= w);
            }
            weighted = s;
            &weighted
        }
        None => a,
    };
    for p in 0..a.channels {
        let row = &mut m[(r0 + p) * dim + c0..(r0 + p) * dim + c0 + b.channels];
        dots(a.row(p), b, 0, row);
    }
}

/// `out[q - first] += a . b_q` for the channels `q >= first` of `b`, four at a time.
fn dots(a: &[f64], b: &Features, first: usize, out: &mut [f64]) {
    let mut q = first;
    while q + 4 <= b.channels {
        let n = a.len() - a.len() % 2;
        let mut acc = [[0.0f64; 2]; 4];
        for ((((x, r0), r1), r2), r3) in a[..n]
            .chunks_exact(2)
            .zip(b.row(q)[..n].chunks_exact(2))
            .zip(b.row(q + 1)[..n].chunks_exact(2))
            .zip(b.row(q + 2)[..n].chunks_exact(2))
            .zip(b.row(q + 3)[..n].chunks_exact(2))
        {
            for l in 0..2 {
                acc[0][l] += x[l] * r0[l];
                acc[1][l] += x[l] * r1[l];
                acc[2][l] += x[l] * r2[l];
                acc[3][l] += x[l] * r3[l];
            }
        }
        for (t, s) in acc.iter().enumerate() {
            let tail: f64 = a[n..]
                .iter()
                .zip(&b.row(q + t)[n..])
                .map(|(x, y)| x * y)
                .sum();
            out[q + t - first] += (s[0] + s[1]) + tail;
        }
        q += 4;
    }
    for q in q..b.channels {
        out[q - first] += dot(a, b.row(q));
    }
}

/// Dot product with four independent sums (vectorisable).
fn dot(a: &[f64], b: &[f64]) -> f64 {
    let mut acc = [0.0f64; 4];
    let mut ca = a.chunks_exact(4);
    let mut cb = b.chunks_exact(4);
    for (x, y) in (&mut ca).zip(&mut cb) {
        for l in 0..4 {
            acc[l] += x[l] * y[l];
        }
    }
    let tail: f64 = ca
        .remainder()
        .iter()
        .zip(cb.remainder())
        .map(|(x, y)| x * y)
        .sum();
    (acc[0] + acc[1]) + (acc[2] + acc[3]) + tail
}

/// A channel-major `channels x n` feature matrix in f64.
#[derive(Debug, Clone)]
struct Features {
    channels: usize,
    n: usize,
    x: Vec<f64>,
}

impl Features {
    fn zeros(channels: usize, n: usize) -> Self {
        Features {
            channels,
            n,
            x: vec![0.0; channels * n],
        }
    }

    fn row(&self, c: usize) -> &[f64] {
        &self.x[c * self.n..(c + 1) * self.n]
    }

    fn row_mut(&mut self, c: usize) -> &mut [f64] {
        &mut self.x[c * self.n..(c + 1) * self.n]
    }

    fn centred(&self) -> Features {
        let mut out = self.clone();
        for c in 0..out.channels {
            let row = out.row_mut(c);
            let mean = row.iter().sum::<f64>() / row.len().max(1) as f64;
            row.iter_mut().for_each(|v| *v -= mean);
        }
        out
    }

    /// The values of a layer input (its parts stacked), in f64.
    fn of(input: &Input<'_>) -> Features {
        let n = input.points();
        let mut out = Features::zeros(input.channels(), n);
        let mut c = 0;
        for (part, channels) in input.part_channels().into_iter().enumerate() {
            for channel in 0..channels {
                for (o, &v) in out
                    .row_mut(c)
                    .iter_mut()
                    .zip(input.channel(part, channel, 0, n))
                {
                    *o = f64::from(v);
                }
                c += 1;
            }
        }
        out
    }
}

/// How int8 tensors are fitted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FitOptions {
    /// Scale of each row.
    pub scale: ScaleSearch,
    /// Whether each layer sees the inputs of the already quantised layers before it and
    /// aims at the float model's output (error-correcting), instead of the float inputs.
    pub correct: bool,
}

/// Float-path and quantised-path inputs of one set (`q` is `None` without a quantised
/// path: the float inputs stand for both).
#[derive(Debug, Clone)]
struct Both {
    f: Features,
    q: Option<Features>,
}

/// Rounds every tensor whose precision is int8 with GPTQ on the calibration `pairs`, one
/// group at a time in the order the forward pass reads them; `None` for the others.
/// `f32_blob` writes the f32 model blob of a set of tensors (the float model, and with
/// `correct` the model quantised so far).
///
/// With `correct`, a layer with float inputs `X` and quantised-path inputs `Xq` gets the
/// least-squares target `W~ = W + (W X Xq^T - W Hq)(Hq + lambda I)^-1` of the float
/// output from the quantised inputs (`Hq = Xq Xq^T`), which GPTQ then rounds with `Hq`:
/// the error of the layers before is compensated where the inputs allow.
pub fn fit_int8(
    config: &ModelConfig,
    tensors: &[FloatLinear],
    precisions: &[Precision],
    pairs: &[Pair],
    options: FitOptions,
    f32_blob: impl Fn(&[FloatLinear]) -> anyhow::Result<Vec<u8>>,
) -> anyhow::Result<Vec<Option<Int8Tensor>>> {
    let float_blob = f32_blob(tensors)?;
    let float = Model::from_bytes(&float_blob).map_err(|e| anyhow::anyhow!("f32 blob: {e}"))?;
    let matches = on_pairs(pairs, |_, pair, matcher| {
        let found = matcher
            .match_pair(&float, &pair.query, &pair.db)
            .map_err(|e| anyhow::anyhow!("calibration pair: {e}"))?;
        Ok(found.as_slice().to_vec())
    })?;
    let runs: Vec<Run> = pairs
        .iter()
        .zip(matches)
        .map(|(pair, matches)| Run { pair, matches })
        .collect();
    let mut fitter = Fitter {
        float: tensors,
        effective: tensors.to_vec(),
        precisions,
        options,
        int8: vec![None; tensors.len()],
    };
    let order = {
        let mut matcher = lock(0)?;
        reading_order(&mut matcher, &float, &runs)?
    };
    let mut descriptors: Option<Vec<PairDescriptors>> = None;
    for group in groups(config, tensors, &order)? {
        if !group.iter().any(|&i| precisions[i] == Precision::Int8) {
            fitter.keep_float(&group);
            continue;
        }
        let quantised_blob = match options.correct {
            true => Some(f32_blob(&fitter.effective)?),
            false => None,
        };
        let quantised = quantised_blob
            .as_deref()
            .map(Model::from_bytes)
            .transpose()
            .map_err(|e| anyhow::anyhow!("quantised f32 blob: {e}"))?;
        let reach = reach(config, group[0])?;
        if reach == Reach::Classifier && descriptors.is_none() {
            // The classifier's layers come last: the descriptors of both paths are final.
            descriptors = Some(on_pairs(&runs, |_, run, matcher| {
                let quantised = match &quantised {
                    Some(model) => Some(run.descriptors(matcher, model)?),
                    None => None,
                };
                Ok(PairDescriptors {
                    float: run.descriptors(matcher, &float)?,
                    quantised,
                })
            })?);
        }
        let inputs = on_pairs(&runs, |at, run, matcher| {
            let cached = descriptors.as_ref().map(|d| &d[at]);
            let f = run.inputs(matcher, &float, reach, cached.map(|d| &d.float[..]), &group)?;
            let q = match &quantised {
                Some(model) => {
                    let own = cached.and_then(|d| d.quantised.as_deref());
                    Some(run.inputs(matcher, model, reach, own, &group)?)
                }
                None => None,
            };
            Ok((f, q))
        })?;
        let dim = group.iter().map(|&i| tensors[i].cols).sum();
        let mut moments = Moments::new(dim);
        for (f, q) in inputs {
            moments.add_run(config, group[0], f, q)?;
        }
        fitter.fit_group(&group, &moments)?;
    }
    Ok(fitter.int8)
}

/// Matchers of the calibration's worker threads (statics: 7.5 MB each is not for a
/// thread's stack).
static MATCHERS: [Mutex<Matcher<1024, f32>>; WORKERS] = [
    Mutex::new(Matcher::new()),
    Mutex::new(Matcher::new()),
    Mutex::new(Matcher::new()),
    Mutex::new(Matcher::new()),
];
/// Most worker threads.
const WORKERS: usize = 4;

fn lock(worker: usize) -> anyhow::Result<std::sync::MutexGuard<'static, Matcher<1024, f32>>> {
    MATCHERS[worker]
        .lock()
        .map_err(|_| anyhow::anyhow!("matcher lock poisoned"))
}

/// `work(index, item, matcher)` on every item (a pair or its run), spread over up to
/// [`WORKERS`] threads; results in the items' order (so the moments are summed in the same
/// order whatever the thread count).
fn on_pairs<I: Sync, T: Send>(
    runs: &[I],
    work: impl Fn(usize, &I, &mut Matcher<1024, f32>) -> anyhow::Result<T> + Sync,
) -> anyhow::Result<Vec<T>> {
    let workers = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .clamp(1, WORKERS)
        .min(runs.len().max(1));
    let results: Vec<anyhow::Result<Vec<(usize, T)>>> = std::thread::scope(|scope| {
        let handles: Vec<_> = (0..workers)
            .map(|w| {
                let work = &work;
                scope.spawn(move || -> anyhow::Result<Vec<(usize, T)>> {
                    let mut matcher = lock(w)?;
                    (w..runs.len())
                        .step_by(workers)
                        .map(|i| Ok((i, work(i, &runs[i], &mut matcher)?)))
                        .collect()
                })
            })
            .collect();
        handles
            .into_iter()
            .map(|h| {
                h.join()
                    .unwrap_or_else(|_| Err(anyhow::anyhow!("calibration worker panicked")))
            })
            .collect()
    });
    let mut slots: Vec<Option<T>> = (0..runs.len()).map(|_| None).collect();
    for part in results {
        for (i, value) in part? {
            slots[i] = Some(value);
        }
    }
    slots
        .into_iter()
        .map(|v| v.context("a calibration pair was not run"))
        .collect()
}

/// A pair's L2-normalised descriptors (both sets stacked) on the float path and, with
/// error correction, on the quantised one.
struct PairDescriptors {
    float: Vec<f32>,
    quantised: Option<Vec<f32>>,
}

/// How far into the forward pass a tensor is read, so how much of it must run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Reach {
    /// The point encoder of each set.
    Encoder,
    /// The matcher up to the descriptors.
    Pair,
    /// The classifier on the final descriptors.
    Classifier,
}

fn reach(config: &ModelConfig, tensor: usize) -> anyhow::Result<Reach> {
    let slot = locate(config, tensor).context("tensor index past the layout")?;
    Ok(match slot.section {
        Section::EncoderInput | Section::EncoderBlock => Reach::Encoder,
        Section::SelfLayer | Section::CrossLayer => Reach::Pair,
        Section::ClassifierInput | Section::ClassifierBlock | Section::ClassifierOutput => {
            Reach::Classifier
        }
    })
}

/// One calibration pair and the float model's matches on it.
struct Run<'p> {
    pair: &'p Pair,
    matches: Vec<Match>,
}

impl Run<'_> {
    /// The inputs of the tensors of `group` when `model` runs this pair as far as `reach`
    /// (the classifier on `descriptors`), in the order read.
    fn inputs(
        &self,
        matcher: &mut Matcher<1024, f32>,
        model: &Model<'_>,
        reach: Reach,
        descriptors: Option<&[f32]>,
        group: &[usize],
    ) -> anyhow::Result<Vec<Captured>> {
        let mut tap = Tap::new(*model.config(), group);
        match reach {
            Reach::Encoder => self.encode(model, &mut tap),
            Reach::Pair => self.describe(matcher, model, &mut tap)?,
            Reach::Classifier => {
                let descriptors = descriptors.context("descriptors of the classifier's pair")?;
                self.classify(model, descriptors, &mut tap);
            }
        }
        anyhow::ensure!(tap.tile.is_none(), "a tile set left incomplete");
        Ok(tap.inputs)
    }

    /// The core's point encoder on both sets.
    fn encode(&self, model: &Model<'_>, tap: &mut Tap) {
        let d = usize::from(model.config().feature_dim);
        for points in [&self.pair.query, &self.pair.db] {
            let n = points.len();
            let mut x = vec![0.0; d * n];
            // Room for the whole set's preconv output and conv2 rows (one call per layer,
            // as in the matcher's pool).
            let mut hidden = vec![0.0; 2 * d * n + d];
            let mut rows = vec![0.0; ROW_BLOCK * n];
            encode(&model.encoder, points, &mut x, &mut hidden, &mut rows, tap);
        }
    }

    /// The core's matcher on this pair (its classifier, on its own matches, not kept).
    fn describe(
        &self,
        matcher: &mut Matcher<1024, f32>,
        model: &Model<'_>,
        tap: &mut Tap,
    ) -> anyhow::Result<()> {
        let fail = |e: gomatch::Error| anyhow::anyhow!("calibration pair: {e}");
        tap.in_matcher = true;
        matcher
            .encode_query_observed(model, &self.pair.query, tap)
            .map_err(fail)?;
        matcher
            .match_view_observed(model, &self.pair.db, tap)
            .map_err(fail)?;
        tap.in_matcher = false;
        Ok(())
    }

    /// The L2-normalised descriptors of both sets on `model`, stacked.
    fn descriptors(
        &self,
        matcher: &mut Matcher<1024, f32>,
        model: &Model<'_>,
    ) -> anyhow::Result<Vec<f32>> {
        let mut tap = Tap::new(*model.config(), &[]);
        self.describe(matcher, model, &mut tap)?;
        let [desc2, desc3] = tap.descriptors;
        Ok([desc2, desc3].concat())
    }

    /// The core's classifier on the float model's matches, given the stacked descriptors.
    fn classify(&self, model: &Model<'_>, descriptors: &[f32], tap: &mut Tap) {
        if self.matches.is_empty() {
            return;
        }
        let (n2, n3) = (self.pair.query.len(), self.pair.db.len());
        let classifier = &model.classifier;
        let c = classifier.input.rows();
        let m = self.matches.len().max(2);
        let mut memory = descriptors.to_vec();
        memory.resize(memory.len().max(c * m), 0.0);
        let mut pool = vec![0.0; c * (n2 + n3).max(2 * m + 1)];
        let mut rows = vec![0.0; ROW_BLOCK * m];
        let d = usize::from(model.config().feature_dim);
        let descriptors = Descriptors {
            memory: &mut memory,
            offset3: d * n2,
            n2,
            n3,
        };
        let mut matches = self.matches.clone();
        classify(
            classifier,
            descriptors,
            &mut matches,
            &mut pool,
            &mut rows,
            tap,
        );
    }
}

/// The blob index of every tensor in the order the forward pass first reads it (on the
/// first pair with a match, so that the classifier runs).
fn reading_order(
    matcher: &mut Matcher<1024, f32>,
    float: &Model<'_>,
    runs: &[Run<'_>],
) -> anyhow::Result<Vec<usize>> {
    let run = runs
        .iter()
        .find(|r| !r.matches.is_empty())
        .context("no calibration pair has a match: the classifier cannot be calibrated")?;
    let mut tap = Tap::new(*float.config(), &[]);
    run.describe(matcher, float, &mut tap)?;
    let descriptors = [&tap.descriptors[0][..], &tap.descriptors[1][..]].concat();
    run.classify(float, &descriptors, &mut tap);
    Ok(tap.order)
}

/// The fit groups in reading order: each tensor alone, an EdgeConv pair (reported by its
/// centre tensor) together. Every tensor of the layout must be read.
fn groups(
    config: &ModelConfig,
    tensors: &[FloatLinear],
    order: &[usize],
) -> anyhow::Result<Vec<Vec<usize>>> {
    let mut groups = Vec::with_capacity(order.len());
    // A folded (empty) tensor is never read.
    let mut covered: Vec<bool> = tensors.iter().map(FloatLinear::is_folded).collect();
    anyhow::ensure!(
        covered.len() == tensor_count(config),
        "{} tensors for a configuration of {}",
        covered.len(),
        tensor_count(config)
    );
    for &index in order {
        let group = match downstream(config, index)? {
            Downstream::EdgeCentre => vec![index, index + 1],
            Downstream::EdgeNeighbour => anyhow::bail!("tensor {index} read as an EdgeConv centre"),
            Downstream::Direct | Downstream::Norm | Downstream::Folds => vec![index],
        };
        for &member in &group {
            *covered
                .get_mut(member)
                .context("tensor index past the layout")? = true;
        }
        groups.push(group);
    }
    if let Some(missing) = covered.iter().position(|&c| !c) {
        anyhow::bail!("the forward pass never reads tensor {missing}");
    }
    Ok(groups)
}

/// What follows tensor `index` in the network (the core's declaration).
fn downstream(config: &ModelConfig, index: usize) -> anyhow::Result<Downstream> {
    let tensor = locate(config, index)
        .and_then(|slot| slot.tensor())
        .context("tensor index past the layout")?;
    Ok(tensor.downstream)
}

/// One input read by a tensor of the group.
#[derive(Debug, Clone)]
enum Captured {
    /// The points of one set.
    Points(Features),
    /// The points of one set and their neighbour lists (an EdgeConv pair's input).
    Edges(Features, Vec<Vec<usize>>),
}

/// Keeps the inputs of the tensors of one group (and the reading order and the final
/// descriptors) as the core's forward pass reports them.
struct Tap {
    config: ModelConfig,
    group: Vec<usize>,
    inputs: Vec<Captured>,
    /// A set read in tiles: its columns so far and how many are filled.
    tile: Option<(Features, usize)>,
    order: Vec<usize>,
    /// The L2-normalised query and database descriptors.
    descriptors: [Vec<f32>; 2],
    /// Whether the matcher is running: its classifier (on its own matches) is not kept.
    in_matcher: bool,
}

impl Tap {
    fn new(config: ModelConfig, group: &[usize]) -> Self {
        Tap {
            config,
            group: group.to_vec(),
            inputs: Vec::new(),
            tile: None,
            order: Vec::new(),
            descriptors: [Vec::new(), Vec::new()],
            in_matcher: false,
        }
    }

    fn is_classifier(&self, tensor: usize) -> bool {
        reach(&self.config, tensor).is_ok_and(|r| r == Reach::Classifier)
    }

    /// Adds columns of a set: the whole set, or its next tile.
    fn add_points(&mut self, x: &Input<'_>) {
        let columns = Features::of(x);
        if x.points() == x.set() {
            self.inputs.push(Captured::Points(columns));
            return;
        }
        let (set, filled) = self
            .tile
            .get_or_insert_with(|| (Features::zeros(columns.channels, x.set()), 0));
        for c in 0..columns.channels {
            set.row_mut(c)[*filled..*filled + columns.n].copy_from_slice(columns.row(c));
        }
        *filled += columns.n;
        if *filled == set.n {
            if let Some((set, _)) = self.tile.take() {
                self.inputs.push(Captured::Points(set));
            }
        }
    }
}

impl LayerTap for Tap {
    fn layer_input(&mut self, tensor: usize, input: &LayerInput<'_>) {
        if self.in_matcher && self.is_classifier(tensor) {
            return;
        }
        if !self.order.contains(&tensor) {
            self.order.push(tensor);
        }
        if !self.group.contains(&tensor) {
            return;
        }
        match *input {
            LayerInput::Points(x) => self.add_points(&x),
            LayerInput::Edges { points, graph, k } => {
                let lists = graph
                    .iter()
                    .map(|nb| nb[..k].iter().map(|&j| usize::from(j)).collect())
                    .collect();
                self.inputs
                    .push(Captured::Edges(Features::of(&points), lists));
            }
            LayerInput::Matches { a, b, pair, count } => {
                let (a, b) = (Features::of(&a), Features::of(&b));
                let mut x = Features::zeros(a.channels + b.channels, count);
                for m in 0..count {
                    let (i, j) = pair(m);
                    for c in 0..a.channels {
                        x.row_mut(c)[m] = a.row(c)[i];
                    }
                    for c in 0..b.channels {
                        x.row_mut(a.channels + c)[m] = b.row(c)[j];
                    }
                }
                self.inputs.push(Captured::Points(x));
            }
        }
    }
}

impl Observer<f32> for Tap {
    fn features(&mut self, stage: Stage, x: &[f32], _channels: usize, _n: usize) {
        match stage {
            Stage::Desc2dL2 => self.descriptors[0] = x.to_vec(),
            Stage::Desc3dL2 => self.descriptors[1] = x.to_vec(),
            _ => {}
        }
    }
}

impl Moments {
    /// Adds the inputs one pair gave a group led by tensor `lead`: `f` on the float model,
    /// `q` on the quantised one (read in the same order).
    fn add_run(
        &mut self,
        config: &ModelConfig,
        lead: usize,
        f: Vec<Captured>,
        q: Option<Vec<Captured>>,
    ) -> anyhow::Result<()> {
        let centred = matches!(
            downstream(config, lead)?,
            Downstream::Norm | Downstream::Folds
        );
        let q: Vec<Option<Captured>> = match q {
            Some(q) => {
                anyhow::ensure!(q.len() == f.len(), "the two paths read different inputs");
                q.into_iter().map(Some).collect()
            }
            None => vec![None; f.len()],
        };
        for (f, q) in f.into_iter().zip(q) {
            match (f, q) {
                (Captured::Points(f), q) => {
                    let q = match q {
                        Some(Captured::Points(q)) => Some(same_shape(&f, q)?),
                        None => None,
                        Some(_) => anyhow::bail!("the two paths read different inputs"),
                    };
                    self.add(&Both { f, q }, centred);
                }
                (Captured::Edges(f, graph), q) => {
                    let q = match q {
                        Some(Captured::Edges(q, _)) => Some(same_shape(&f, q)?),
                        None => None,
                        Some(_) => anyhow::bail!("the two paths read different inputs"),
                    };
                    self.add_edges(&Both { f, q }, &graph);
                }
            }
        }
        Ok(())
    }
}

/// `q`, checked to have the shape of `f`.
fn same_shape(f: &Features, q: Features) -> anyhow::Result<Features> {
    anyhow::ensure!(
        (f.channels, f.n) == (q.channels, q.n),
        "the two paths read inputs of different shapes"
    );
    Ok(q)
}

/// The tensors of the float and the quantised model, and the int8 ones fitted so far.
struct Fitter<'t> {
    float: &'t [FloatLinear],
    /// Weights of the quantised path: dequantised int8, f16-rounded or f32.
    effective: Vec<FloatLinear>,
    precisions: &'t [Precision],
    options: FitOptions,
    int8: Vec<Option<Int8Tensor>>,
}

impl Fitter<'_> {
    /// Sets the quantised path's weights of a group's f16 members (f32 ones stay).
    fn keep_float(&mut self, group: &[usize]) {
        for &index in group {
            if self.precisions[index] == Precision::F16 {
                self.effective[index] = rounded_f16(&self.float[index]);
            }
        }
    }

    /// Rounds the int8 members of a group whose columns concatenate to the moments'.
    fn fit_group(&mut self, group: &[usize], m: &Moments) -> anyhow::Result<()> {
        self.keep_float(group);
        let mut int8_columns = Vec::new();
        let mut members = Vec::new();
        let mut at = 0;
        for &index in group {
            let cols = self.float[index].cols;
            if self.precisions[index] == Precision::Int8 {
                int8_columns.extend(at..at + cols);
                members.push(index);
            }
            at += cols;
        }
        if members.is_empty() {
            return Ok(());
        }
        let dim = m.dim;
        let sub = |full: &[f64]| -> Vec<f64> {
            int8_columns
                .iter()
                .flat_map(|&a| int8_columns.iter().map(move |&b| full[a * dim + b]))
                .collect()
        };
        let h = sub(&m.h);
        let mut targets: Vec<FloatLinear> =
            members.iter().map(|&i| self.float[i].clone()).collect();
        if self.options.correct {
            let solver = Ridge::new(&h, int8_columns.len())?;
            let g = m.cross();
            let rows = self.float[group[0]].rows;
            for r in 0..rows {
                let row = |ts: &[FloatLinear]| -> Vec<f64> {
                    group
                        .iter()
                        .flat_map(|&i| {
                            let t = &ts[i];
                            t.weights[r * t.cols..(r + 1) * t.cols]
                                .iter()
                                .map(|&w| f64::from(w))
                        })
                        .collect()
                };
                let (w, w_eff) = (row(self.float), row(&self.effective));
                // rhs = (G^T w - H w_eff) restricted to the int8 columns (w_eff keeps the
                // f16/f32 members' stored values and the float int8 weights).
                let mut w_eff = w_eff;
                for &a in &int8_columns {
                    w_eff[a] = w[a];
                }
                let rhs: Vec<f64> = int8_columns
                    .iter()
                    .map(|&a| {
                        (0..dim)
                            .map(|b| g[b * dim + a] * w[b] - m.h[a * dim + b] * w_eff[b])
                            .sum()
                    })
                    .collect();
                let delta = solver.solve(&rhs);
                let mut k = 0;
                for t in &mut targets {
                    for c in 0..t.cols {
                        let v = &mut t.weights[r * t.cols + c];
                        *v = (f64::from(*v) + delta[k]) as f32;
                        k += 1;
                    }
                }
            }
        }
        let refs: Vec<&FloatLinear> = targets.iter().collect();
        let rounded = quantize::gptq(&refs, &h, self.options.scale)?;
        for (index, q) in members.into_iter().zip(rounded) {
            self.effective[index] = dequantized(&self.float[index], &q);
            self.int8[index] = Some(q);
        }
        Ok(())
    }
}

/// Solves `(H + lambda I) x = b` for the dampened moments (see [`quantize::DAMPENING`]).
struct Ridge {
    dim: usize,
    lower: Vec<f64>,
}

impl Ridge {
    fn new(h: &[f64], dim: usize) -> anyhow::Result<Self> {
        Ok(Ridge {
            dim,
            lower: quantize::cholesky(&quantize::dampened(h.to_vec(), dim), dim)?,
        })
    }

    fn solve(&self, b: &[f64]) -> Vec<f64> {
        let (n, l) = (self.dim, &self.lower);
        let mut y = vec![0.0; n];
        for r in 0..n {
            let s: f64 = (0..r).map(|k| l[r * n + k] * y[k]).sum();
            y[r] = (b[r] - s) / l[r * n + r];
        }
        let mut x = vec![0.0; n];
        for r in (0..n).rev() {
            let s: f64 = (r + 1..n).map(|k| l[k * n + r] * x[k]).sum();
            x[r] = (y[r] - s) / l[r * n + r];
        }
        x
    }
}

/// The weights an f16 tensor holds.
fn rounded_f16(t: &FloatLinear) -> FloatLinear {
    FloatLinear {
        weights: t
            .weights
            .iter()
            .map(|&w| half::f16::from_f32(w).to_f32())
            .collect(),
        ..t.clone()
    }
}

/// The weights an int8 tensor holds, `scale * level`.
fn dequantized(t: &FloatLinear, q: &Int8Tensor) -> FloatLinear {
    FloatLinear {
        weights: q
            .levels
            .iter()
            .enumerate()
            .map(|(i, &l)| f32::from(l) * q.scales[i / t.cols])
            .collect(),
        ..t.clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every intermediate output of the core's matcher, in the order reported.
    struct Stages(Vec<(Stage, Vec<f32>)>);

    impl LayerTap for Stages {}

    impl Observer<f32> for Stages {
        fn features(&mut self, stage: Stage, x: &[f32], _: usize, _: usize) {
            self.0.push((stage, x.to_vec()));
        }
    }

    impl Stages {
        fn get(&self, stage: Stage) -> Features {
            let (_, x) = self.0.iter().find(|(s, _)| *s == stage).expect("observed");
            Features {
                channels: 128,
                n: x.len() / 128,
                x: x.iter().map(|&v| f64::from(v)).collect(),
            }
        }
    }

    fn points(c: &Captured) -> &Features {
        match c {
            Captured::Points(x) | Captured::Edges(x, _) => x,
        }
    }

    /// The shipped checkpoint's float model and one calibration pair with its matches.
    fn float_model() -> Option<(ModelConfig, Vec<u8>, Vec<FloatLinear>)> {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../models/gomatch.safetensors");
        let Ok(checkpoint) = std::fs::read(path) else {
            println!("SKIPPED: no shipped checkpoint {path}");
            return None;
        };
        let (blob, _) = crate::convert::convert(&checkpoint, Precision::F32).expect("f32 blob");
        let (config, tensors) = crate::convert::float_tensors(&checkpoint).expect("tensors");
        Some((config, blob, tensors))
    }

    /// What the tap keeps is what the core's layers read: the encoder's input is the
    /// sets' coordinates; the cross layer's query reads the first self layer's output of
    /// the 2D set, then of the 3D set; the classifier reads `[f2d_i; f3d_j]` of the float
    /// model's matches. Every tensor is read, in an order that follows the network.
    #[test]
    fn the_tap_keeps_what_the_core_reads() {
        let Some((config, blob, tensors)) = float_model() else {
            return;
        };
        let model = Model::from_bytes(&blob).expect("blob");
        let pair = synthetic_pairs(1, 3).remove(0);
        let mut matcher = lock(0).expect("matcher");
        let mut stages = Stages(Vec::new());
        matcher
            .encode_query_observed(&model, &pair.query, &mut stages)
            .expect("query");
        let matches = matcher
            .match_view_observed(&model, &pair.db, &mut stages)
            .expect("pair")
            .as_slice()
            .to_vec();
        assert!(!matches.is_empty());
        let run = Run {
            pair: &pair,
            matches,
        };
        let index = |section, instance, part| {
            gomatch::weights::tensor_index(&config, section, instance, part).expect("tensor")
        };
        let read = |matcher: &mut Matcher<1024, f32>, reach, descriptors, tensor| {
            run.inputs(matcher, &model, reach, descriptors, &[tensor])
                .expect("runs")
        };

        let coordinates = read(
            &mut matcher,
            Reach::Encoder,
            None,
            index(Section::EncoderInput, 0, 0),
        );
        assert_eq!(coordinates.len(), 2);
        for (x, set) in coordinates.iter().zip([&pair.query, &pair.db]) {
            let x = points(x);
            assert_eq!((x.channels, x.n), (2, set.len()));
            for (i, p) in set.iter().enumerate() {
                assert_eq!([x.row(0)[i], x.row(1)[i]], p.map(f64::from));
            }
        }

        let query = gomatch::weights::CrossLayerWeights::QUERY;
        let targets = read(
            &mut matcher,
            Reach::Pair,
            None,
            index(Section::CrossLayer, 0, query),
        );
        assert_eq!(targets.len(), 2, "one read per direction");
        assert_eq!(points(&targets[0]).x, stages.get(Stage::Att0Self2d).x);
        assert_eq!(points(&targets[1]).x, stages.get(Stage::Att0Self3d).x);

        let descriptors = run.descriptors(&mut matcher, &model).expect("descriptors");
        let input = read(
            &mut matcher,
            Reach::Classifier,
            Some(&descriptors),
            index(Section::ClassifierInput, 0, 0),
        );
        let (d2, d3) = (stages.get(Stage::Desc2dL2), stages.get(Stage::Desc3dL2));
        let x = points(&input[0]);
        assert_eq!(x.n, run.matches.len().max(2));
        for (m, mt) in run.matches.iter().enumerate() {
            let (i, j) = (usize::from(mt.i2d), usize::from(mt.i3d));
            for c in 0..128 {
                assert_eq!(x.row(c)[m], d2.row(c)[i]);
                assert_eq!(x.row(128 + c)[m], d3.row(c)[j]);
            }
        }

        let order = reading_order(&mut matcher, &model, std::slice::from_ref(&run)).expect("order");
        let groups = groups(&config, &tensors, &order).expect("every tensor read");
        assert_eq!(groups[0], vec![index(Section::EncoderInput, 0, 0)]);
        let at = |tensor| order.iter().position(|&t| t == tensor).expect("read");
        let second_self = index(
            Section::SelfLayer,
            1,
            gomatch::weights::SelfLayerWeights::EDGE1,
        );
        assert!(at(index(Section::CrossLayer, 0, query)) < at(second_self));
        assert!(at(second_self) < at(index(Section::ClassifierInput, 0, 0)));
    }

    #[test]
    fn synthetic_pairs_look_like_the_fixtures() {
        let pairs = synthetic_pairs(5, 7);
        for p in &pairs {
            assert!((32..=400).contains(&p.query.len()));
            assert!(p.db.len() >= p.query.len());
            assert!(p.db.iter().all(|b| b[0].abs() <= 0.6 && b[1].abs() <= 0.6));
            assert!(p.query.iter().all(|q| q[0].abs() < 2.0 && q[1].abs() < 2.0));
        }
        let again = synthetic_pairs(5, 7);
        assert_eq!(pairs[3].query, again[3].query);
    }

    fn features(channels: usize, n: usize, seed: usize) -> Features {
        Features {
            channels,
            n,
            x: (0..channels * n)
                .map(|i| (((i + seed) * 7919) % 23) as f64 / 7.0 - 1.5)
                .collect(),
        }
    }

    /// The factored edge moments equal the ones summed over the explicit edges, for the
    /// moments of one path (`b = a`) and across two paths.
    #[test]
    fn edge_moments_match_explicit_edges() {
        let (d, n) = (3, 5);
        let a = features(d, n, 0);
        let b = features(d, n, 11);
        let graph: Vec<Vec<usize>> = (0..n).map(|i| vec![(i + 1) % n, (i + 3) % n]).collect();
        let edge = |x: &Features, i: usize, j: usize| -> Vec<f64> {
            (0..d)
                .map(|c| x.row(c)[i])
                .chain((0..d).map(|c| x.row(c)[j]))
                .collect()
        };
        let explicit = |x: &Features, y: &Features| -> Vec<f64> {
            type Edge = (Vec<f64>, Vec<f64>);
            let edges: Vec<Edge> = graph
                .iter()
                .enumerate()
                .flat_map(|(i, nb)| nb.iter().map(move |&j| (edge(x, i, j), edge(y, i, j))))
                .collect();
            let mean = |pick: &dyn Fn(&Edge) -> f64| {
                edges.iter().map(pick).sum::<f64>() / edges.len() as f64
            };
            let ma: Vec<f64> = (0..2 * d).map(|p| mean(&|e| e.0[p])).collect();
            let mb: Vec<f64> = (0..2 * d).map(|q| mean(&|e| e.1[q])).collect();
            (0..4 * d * d)
                .map(|k| {
                    let (p, q) = (k / (2 * d), k % (2 * d));
                    edges
                        .iter()
                        .map(|e| (e.0[p] - ma[p]) * (e.1[q] - mb[q]))
                        .sum()
                })
                .collect()
        };
        for (second, expected) in [(None, explicit(&a, &a)), (Some(&b), explicit(&a, &b))] {
            let mut m = vec![0.0; 4 * d * d];
            edge_moments(&mut m, 2 * d, &a, second, &graph);
            for (k, (got, want)) in m.iter().zip(&expected).enumerate() {
                assert!((got - want).abs() < 1e-9, "{k}: {got} vs {want}");
            }
        }
    }

    /// The least-squares target leaves a layer unchanged when the quantised path equals
    /// the float path and compensates a known input error otherwise.
    #[test]
    fn corrected_target_compensates_input_error() {
        let (rows, cols, n) = (2, 3, 40);
        let f = features(cols, n, 3);
        // The quantised path sees input channel 0 scaled by 0.9.
        let mut q = f.clone();
        q.row_mut(0).iter_mut().for_each(|v| *v *= 0.9);
        let w = FloatLinear {
            rows,
            cols,
            weights: vec![0.5, -0.25, 0.125, 0.75, 0.3, -0.6],
            bias: vec![],
        };
        let run = |x: &Both| -> Vec<Option<Int8Tensor>> {
            let mut m = Moments::new(cols);
            m.add(x, false);
            let precisions = [Precision::Int8];
            let mut engine = Fitter {
                float: std::slice::from_ref(&w),
                effective: vec![w.clone()],
                precisions: &precisions,
                options: FitOptions {
                    scale: ScaleSearch::MaxAbs,
                    correct: true,
                },
                int8: vec![None],
            };
            engine.fit_group(&[0], &m).expect("fits");
            engine.int8
        };
        let same = run(&Both {
            f: f.clone(),
            q: None,
        })[0]
            .clone()
            .expect("int8");
        let nearest = quantize::round_to_nearest(&w, ScaleSearch::MaxAbs);
        assert_eq!(same.levels, nearest.levels);
        let apart = run(&Both {
            f: f.clone(),
            q: Some(q),
        })[0]
            .clone()
            .expect("int8");
        // Column 0 grows by about 1 / 0.9 to undo the input's shrinkage.
        for r in 0..rows {
            let ratio = f32::from(apart.levels[r * cols]) * apart.scales[r] / w.weights[r * cols];
            assert!((ratio - 1.0 / 0.9).abs() < 0.02, "row {r}: {ratio}");
        }
    }
}
