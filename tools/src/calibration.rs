//! Calibration data for the int8 conversion: synthetic query-view pairs drawn like the
//! reference fixtures, and a host-side f64 forward pass of the float model that gathers,
//! for every layer, the second moments of its inputs (the Hessian `H = X X^T` of the
//! layer's squared output error, used by [`crate::quantize`]).
//!
//! The forward pass follows the network of `gomatch::Matcher` (encoder, EdgeConv self
//! attention, cross attention, classifier; supp. "Architecture Details") on the converted
//! tensors (split EdgeConv weights). Layers followed by an instance norm, directly or
//! through another linear layer, see their inputs centred per set, because the norm
//! removes any error that is constant over the set. The two halves of an EdgeConv layer
//! act together on the edge `[x_i; x_j]`, so they share one joint moment matrix.

use anyhow::Context;
use gomatch::matcher::Stage;
use gomatch::weights::{
    locate, tensor_index, CrossLayerWeights, Downstream, ModelConfig, Section, SelfLayerWeights,
};
use gomatch::{Matcher, Model, Precision};
use rand::seq::SliceRandom;
use rand::{RngExt, SeedableRng};
use rand_distr::StandardNormal;
use rand_pcg::Pcg64Mcg;
use std::sync::Mutex;

use crate::convert::FloatLinear;
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

    fn concat(parts: &[&Features]) -> Features {
        let n = parts[0].n;
        let mut x = Vec::new();
        for p in parts {
            x.extend_from_slice(&p.x);
        }
        Features {
            channels: parts.iter().map(|p| p.channels).sum(),
            n,
            x,
        }
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

    /// The points `idx` in that order.
    fn gather(&self, idx: &[usize]) -> Features {
        let mut out = Features::zeros(self.channels, idx.len());
        for c in 0..self.channels {
            let src = self.row(c);
            for (o, &i) in out.row_mut(c).iter_mut().zip(idx) {
                *o = src[i];
            }
        }
        out
    }

    fn map(mut self, f: impl Fn(f64) -> f64) -> Features {
        self.x.iter_mut().for_each(|v| *v = f(*v));
        self
    }

    fn instance_norm(mut self) -> Features {
        for c in 0..self.channels {
            let row = self.row_mut(c);
            let (mean, inv_std) = normalizer(row.iter().copied());
            row.iter_mut().for_each(|v| *v = (*v - mean) * inv_std);
        }
        self
    }
}

/// Mean and `1 / sqrt(biased variance + 1e-5)` of the values (instance norm, no affine).
fn normalizer(values: impl Iterator<Item = f64> + Clone) -> (f64, f64) {
    let count = values.clone().count().max(1) as f64;
    let mean = values.clone().sum::<f64>() / count;
    let variance = values.map(|v| (v - mean) * (v - mean)).sum::<f64>() / count;
    (mean, 1.0 / (variance + 1e-5).sqrt())
}

fn leaky_relu(v: f64) -> f64 {
    if v > 0.0 {
        v
    } else {
        0.2 * v
    }
}

/// `y = W x + b` per point, in register blocks of 4 outputs x 4 points.
fn linear(w: &FloatLinear, x: &Features) -> Features {
    const B: usize = 4;
    let (rows, cols, n) = (w.rows, w.cols, x.n);
    let blocks = rows.div_ceil(B);
    // Weights interleaved by blocks of rows: `[block][input][B]`.
    let mut weights = vec![[0.0f64; B]; blocks * cols];
    for (r, row) in w.weights.chunks_exact(cols.max(1)).enumerate() {
        for (k, &v) in row.iter().enumerate() {
            weights[r / B * cols + k][r % B] = f64::from(v);
        }
    }
    let mut y = Features::zeros(rows, n);
    let mut packed = vec![[0.0f64; B]; cols];
    let mut t0 = 0;
    while t0 < n {
        let len = B.min(n - t0);
        for (k, p) in packed.iter_mut().enumerate() {
            *p = [0.0; B];
            p[..len].copy_from_slice(&x.row(k)[t0..t0 + len]);
        }
        for (b, block) in weights.chunks_exact(cols.max(1)).enumerate() {
            let mut acc = [[0.0f64; B]; B];
            for (wk, xk) in block.iter().zip(&packed) {
                for (a, &wr) in acc.iter_mut().zip(wk) {
                    for l in 0..B {
                        a[l] += wr * xk[l];
                    }
                }
            }
            for (i, a) in acc.iter().enumerate() {
                let r = b * B + i;
                if r < rows {
                    let bias = f64::from(w.bias.get(r).copied().unwrap_or(0.0));
                    for (o, &v) in y.row_mut(r)[t0..t0 + len].iter_mut().zip(a) {
                        *o = bias + v;
                    }
                }
            }
        }
        t0 += len;
    }
    y
}

/// Float-path and quantised-path features of one set (`q` is `None` while both agree).
#[derive(Debug, Clone)]
struct Both {
    f: Features,
    q: Option<Features>,
}

impl Both {
    fn exact(f: Features) -> Self {
        Both { f, q: None }
    }

    fn q(&self) -> &Features {
        self.q.as_ref().unwrap_or(&self.f)
    }

    fn map(self, op: impl Fn(Features) -> Features) -> Both {
        Both {
            f: op(self.f),
            q: self.q.map(&op),
        }
    }

    /// `op(self, other)` on both paths.
    fn update(&mut self, other: &Both, op: impl Fn(&mut Features, &Features)) {
        if other.q.is_some() && self.q.is_none() {
            self.q = Some(self.f.clone());
        }
        op(&mut self.f, &other.f);
        if let Some(q) = &mut self.q {
            op(q, other.q());
        }
    }

    fn concat(parts: &[&Both]) -> Both {
        let f: Vec<&Features> = parts.iter().map(|p| &p.f).collect();
        let q: Vec<&Features> = parts.iter().map(|p| p.q()).collect();
        Both {
            f: Features::concat(&f),
            q: parts
                .iter()
                .any(|p| p.q.is_some())
                .then(|| Features::concat(&q)),
        }
    }

    fn gather(&self, idx: &[usize]) -> Both {
        Both {
            f: self.f.gather(idx),
            q: self.q.as_ref().map(|q| q.gather(idx)),
        }
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

/// Rounds every tensor whose precision is int8 with GPTQ on the calibration `pairs`,
/// layer by layer in forward order; `None` for the others. `f32_blob` (the f32
/// conversion of `tensors`) gives the classifier's matches through `gomatch::Matcher`.
///
/// With `correct`, the f64 forward pass runs twice in lockstep: the float model and the
/// model quantised so far. A layer with float inputs `X` and quantised-path inputs `Xq`
/// gets the least-squares target `W~ = W + (W X Xq^T - W Hq)(Hq + lambda I)^-1` of the
/// float output from the quantised inputs (`Hq = Xq Xq^T`), which GPTQ then rounds with
/// `Hq`: the error of the layers before is compensated where the inputs allow.
pub fn fit_int8(
    config: &ModelConfig,
    tensors: &[FloatLinear],
    precisions: &[Precision],
    f32_blob: &[u8],
    pairs: &[Pair],
    options: FitOptions,
) -> anyhow::Result<Vec<Option<Int8Tensor>>> {
    static MATCHER: Mutex<Matcher<1024, f32>> = Mutex::new(Matcher::new());
    let model = Model::from_bytes(f32_blob).map_err(|e| anyhow::anyhow!("f32 blob: {e}"))?;
    let mut matches = Vec::with_capacity(pairs.len());
    {
        let mut matcher = MATCHER
            .lock()
            .map_err(|_| anyhow::anyhow!("matcher lock poisoned"))?;
        for pair in pairs {
            let set = matcher
                .match_pair(&model, &pair.query, &pair.db)
                .map_err(|e| anyhow::anyhow!("calibration pair: {e}"))?;
            let list: Vec<(usize, usize)> = set
                .as_slice()
                .iter()
                .map(|m| (usize::from(m.i2d), usize::from(m.i3d)))
                .collect();
            matches.push(list);
        }
    }
    let mut engine = Engine {
        config: *config,
        float: tensors,
        effective: tensors.to_vec(),
        precisions,
        options,
        int8: vec![None; tensors.len()],
    };
    engine.run(pairs, &matches)?;
    Ok(engine.int8)
}

type Graph = Vec<Vec<usize>>;

/// The two forward paths and the fitted tensors.
struct Engine<'t> {
    config: ModelConfig,
    float: &'t [FloatLinear],
    /// Weights of the quantised path: dequantised int8, f16-rounded or f32.
    effective: Vec<FloatLinear>,
    precisions: &'t [Precision],
    options: FitOptions,
    int8: Vec<Option<Int8Tensor>>,
}

impl Engine<'_> {
    /// Blob index of `part` of instance `instance` of `section` (the core's layout).
    fn index(&self, section: Section, instance: usize, part: usize) -> usize {
        tensor_index(&self.config, section, instance, part)
            .expect("the layout holds every tensor the forward pass uses")
    }

    /// Layer `index` on both paths.
    fn apply(&self, index: usize, x: &Both) -> Both {
        Both {
            f: linear(&self.float[index], &x.f),
            q: self
                .options
                .correct
                .then(|| linear(&self.effective[index], x.q())),
        }
    }

    /// What follows tensor `index` in the network (the core's declaration).
    fn downstream(&self, index: usize) -> anyhow::Result<Downstream> {
        let tensor = locate(&self.config, index)
            .and_then(|slot| slot.tensor())
            .context("tensor index past the layout")?;
        Ok(tensor.downstream)
    }

    /// Fits the single tensor `index` on the inputs `xs`, centred over each set where an
    /// instance norm follows it.
    fn fit(&mut self, index: usize, xs: &[&Both]) -> anyhow::Result<()> {
        let centred = match self.downstream(index)? {
            Downstream::Direct => false,
            Downstream::Norm => true,
            edge => anyhow::bail!(
                "tensor {index} is an EdgeConv half ({edge:?}): fit it as an edge pair"
            ),
        };
        let mut m = Moments::new(self.float[index].cols);
        for x in xs {
            m.add(x, centred);
        }
        self.fit_group(&[index], &m)
    }

    /// Fits the EdgeConv pair `centre`, `centre + 1` on the edges of `xs`.
    fn fit_edges(&mut self, centre: usize, xs: &[Both], graphs: &[Graph]) -> anyhow::Result<()> {
        let pair = (self.downstream(centre)?, self.downstream(centre + 1)?);
        anyhow::ensure!(
            pair == (Downstream::EdgeCentre, Downstream::EdgeNeighbour),
            "tensors {centre}, {} are not an EdgeConv pair ({pair:?})",
            centre + 1
        );
        let mut m = Moments::new(self.float[centre].cols + self.float[centre + 1].cols);
        for (x, g) in xs.iter().zip(graphs) {
            m.add_edges(x, g);
        }
        self.fit_group(&[centre, centre + 1], &m)
    }

    /// Rounds the int8 members of a group whose columns concatenate to the moments'.
    fn fit_group(&mut self, group: &[usize], m: &Moments) -> anyhow::Result<()> {
        let mut int8_columns = Vec::new();
        let mut members = Vec::new();
        let mut at = 0;
        for &index in group {
            let t = &self.float[index];
            match self.precisions[index] {
                Precision::Int8 => {
                    int8_columns.extend(at..at + t.cols);
                    members.push(index);
                }
                Precision::F16 => self.effective[index] = rounded_f16(t),
                Precision::F32 => {}
            }
            at += t.cols;
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

    fn run(&mut self, pairs: &[Pair], matches: &[Vec<(usize, usize)>]) -> anyhow::Result<()> {
        let x = self.descriptors(pairs, |_, _| {})?;
        let (d2, d3) = x.split_at(pairs.len());
        self.classifier(d2, d3, matches)
    }

    /// Encoder and attention on every pair (fitting each layer on the way), then the
    /// L2-normalised descriptors: the query sets', then the database sets'. Each stage's
    /// output goes to `seen` with the core matcher's names for it (query, database).
    fn descriptors(
        &mut self,
        pairs: &[Pair],
        mut seen: impl FnMut([Stage; 2], &[Both]),
    ) -> anyhow::Result<Vec<Both>> {
        let knn = usize::from(self.config.knn);
        let sets: Vec<&[[f32; 2]]> = pairs
            .iter()
            .map(|p| &p.query[..])
            .chain(pairs.iter().map(|p| &p.db[..]))
            .collect();
        let graphs: Vec<Graph> = sets.iter().map(|s| knn_graph(s, knn)).collect();
        let x = self.encode(&sets)?;
        seen([Stage::Enc2d, Stage::Enc3d], &x);
        let x = self.self_layer(0, &x, &graphs)?;
        seen([Stage::Att0Self2d, Stage::Att0Self3d], &x);
        let (x2, x3) = x.split_at(pairs.len());
        let (x2, x3) = self.cross_layer(x2, x3)?;
        let x: Vec<Both> = x2.into_iter().chain(x3).collect();
        seen([Stage::Att1Cross2d, Stage::Att1Cross3d], &x);
        let x = self.self_layer(1, &x, &graphs)?;
        seen([Stage::Att2Self2d, Stage::Att2Self3d], &x);
        let x: Vec<Both> = x.into_iter().map(|b| b.map(l2_normalize)).collect();
        seen([Stage::Desc2dL2, Stage::Desc3dL2], &x);
        Ok(x)
    }

    fn encode(&mut self, sets: &[&[[f32; 2]]]) -> anyhow::Result<Vec<Both>> {
        let coords: Vec<Both> = sets
            .iter()
            .map(|points| {
                let n = points.len();
                let mut c = Features::zeros(2, n);
                for (i, p) in points.iter().enumerate() {
                    c.x[i] = f64::from(p[0]);
                    c.x[n + i] = f64::from(p[1]);
                }
                Both::exact(c)
            })
            .collect();
        let input = self.index(Section::EncoderInput, 0, 0);
        self.fit(input, &coords.iter().collect::<Vec<_>>())?;
        let x = coords.iter().map(|c| self.apply(input, c)).collect();
        self.residual_blocks(x, Section::EncoderBlock)
    }

    /// `x += ReLU(IN(W2 IN(W1 W0 x)))` per block of `section` (biases included).
    fn residual_blocks(&mut self, mut x: Vec<Both>, section: Section) -> anyhow::Result<Vec<Both>> {
        for b in 0..section.repeats(&self.config) {
            let [preconv, conv1, conv2] = [0, 1, 2].map(|part| self.index(section, b, part));
            self.fit(preconv, &x.iter().collect::<Vec<_>>())?;
            let h0: Vec<Both> = x.iter().map(|x| self.apply(preconv, x)).collect();
            self.fit(conv1, &h0.iter().collect::<Vec<_>>())?;
            let h: Vec<Both> = h0
                .iter()
                .map(|h0| self.apply(conv1, h0).map(Features::instance_norm))
                .collect();
            self.fit(conv2, &h.iter().collect::<Vec<_>>())?;
            for (x, h) in x.iter_mut().zip(&h) {
                let z = self
                    .apply(conv2, h)
                    .map(|z| z.instance_norm().map(|v| v.max(0.0)));
                x.update(&z, |x, z| {
                    x.x.iter_mut().zip(&z.x).for_each(|(v, z)| *v += z)
                });
            }
        }
        Ok(x)
    }

    fn self_layer(
        &mut self,
        layer: usize,
        x: &[Both],
        graphs: &[Graph],
    ) -> anyhow::Result<Vec<Both>> {
        let part = |p| self.index(Section::SelfLayer, layer, p);
        let (edge1, edge2, fuse) = (
            part(SelfLayerWeights::EDGE1),
            part(SelfLayerWeights::EDGE2),
            part(SelfLayerWeights::FUSE),
        );
        let x1 = self.edge_conv(edge1, x, graphs)?;
        let x2 = self.edge_conv(edge2, &x1, graphs)?;
        let cat: Vec<Both> = x
            .iter()
            .zip(&x1)
            .zip(&x2)
            .map(|((a, b), c)| Both::concat(&[a, b, c]))
            .collect();
        self.fit(fuse, &cat.iter().collect::<Vec<_>>())?;
        Ok(cat
            .iter()
            .map(|c| {
                self.apply(fuse, c)
                    .map(|y| y.instance_norm().map(leaky_relu))
            })
            .collect())
    }

    fn edge_conv(
        &mut self,
        centre: usize,
        x: &[Both],
        graphs: &[Graph],
    ) -> anyhow::Result<Vec<Both>> {
        self.fit_edges(centre, x, graphs)?;
        Ok(x.iter()
            .zip(graphs)
            .map(|(x, g)| {
                let (a, b) = (self.apply(centre, x), self.apply(centre + 1, x));
                Both {
                    f: finish_edges(&a.f, &b.f, g),
                    q: a.q.as_ref().map(|aq| finish_edges(aq, b.q(), g)),
                }
            })
            .collect())
    }

    /// The cross layer on both directions (2D from 3D, then 3D from the updated 2D). Its
    /// tensors are fitted on the inputs of both calls; the second call's sources on the
    /// quantised path are the first call's outputs with the float cross layer.
    fn cross_layer(&mut self, x2: &[Both], x3: &[Both]) -> anyhow::Result<(Vec<Both>, Vec<Both>)> {
        // The layer's tensors are consecutive, in the order of `CrossLayerWeights::TENSORS`.
        let base = self.index(Section::CrossLayer, 0, 0);
        let [query, key, value, merge, mlp_hidden, mlp_out] = [
            CrossLayerWeights::QUERY,
            CrossLayerWeights::KEY,
            CrossLayerWeights::VALUE,
            CrossLayerWeights::MERGE,
            CrossLayerWeights::MLP_HIDDEN,
            CrossLayerWeights::MLP_OUT,
        ]
        .map(|part| base + part);
        let heads = usize::from(self.config.heads);
        let float = &self.float[base..base + CrossLayerWeights::TENSORS.len()];
        let first: Vec<Both> = x2
            .iter()
            .zip(x3)
            .map(|(a, b)| Both {
                f: cross(float, heads, &a.f, &b.f),
                q: (a.q.is_some() || b.q.is_some()).then(|| cross(float, heads, a.q(), b.q())),
            })
            .collect();
        let targets: Vec<&Both> = x2.iter().chain(x3).collect();
        let sources: Vec<&Both> = x3.iter().chain(&first).collect();
        self.fit(query, &targets)?;
        self.fit(key, &sources)?;
        self.fit(value, &sources)?;
        let messages: Vec<Both> = targets
            .iter()
            .zip(&sources)
            .map(|(t, s)| {
                let (q, k, v) = (
                    self.apply(query, t),
                    self.apply(key, s),
                    self.apply(value, s),
                );
                Both {
                    f: attention(heads, &q.f, &k.f, &v.f),
                    q: q.q.as_ref().map(|qq| attention(heads, qq, k.q(), v.q())),
                }
            })
            .collect();
        self.fit(merge, &messages.iter().collect::<Vec<_>>())?;
        let cat: Vec<Both> = targets
            .iter()
            .zip(&messages)
            .map(|(t, m)| Both::concat(&[t, &self.apply(merge, m)]))
            .collect();
        self.fit(mlp_hidden, &cat.iter().collect::<Vec<_>>())?;
        let hidden: Vec<Both> = cat
            .iter()
            .map(|c| {
                self.apply(mlp_hidden, c)
                    .map(|h| h.instance_norm().map(|v| v.max(0.0)))
            })
            .collect();
        self.fit(mlp_out, &hidden.iter().collect::<Vec<_>>())?;
        let both = |x: &Both, src: &Both| -> Both {
            Both {
                f: cross(
                    &self.float[base..base + CrossLayerWeights::TENSORS.len()],
                    heads,
                    &x.f,
                    &src.f,
                ),
                q: self.options.correct.then(|| {
                    cross(
                        &self.effective[base..base + CrossLayerWeights::TENSORS.len()],
                        heads,
                        x.q(),
                        src.q(),
                    )
                }),
            }
        };
        let new2: Vec<Both> = x2.iter().zip(x3).map(|(a, b)| both(a, b)).collect();
        let new3: Vec<Both> = x3.iter().zip(&new2).map(|(a, b)| both(a, b)).collect();
        Ok((new2, new3))
    }

    /// The match classifier on `[f2d; f3d]` of each match (a single match twice).
    fn classifier(
        &mut self,
        d2: &[Both],
        d3: &[Both],
        matches: &[Vec<(usize, usize)>],
    ) -> anyhow::Result<()> {
        let inputs: Vec<Both> = d2
            .iter()
            .zip(d3)
            .zip(matches)
            .filter(|(_, m)| !m.is_empty())
            .map(|((a, b), m)| {
                let mut list = m.clone();
                if list.len() == 1 {
                    list.push(list[0]);
                }
                let i2: Vec<usize> = list.iter().map(|m| m.0).collect();
                let i3: Vec<usize> = list.iter().map(|m| m.1).collect();
                Both::concat(&[&a.gather(&i2), &b.gather(&i3)])
            })
            .collect();
        let input = self.index(Section::ClassifierInput, 0, 0);
        self.fit(input, &inputs.iter().collect::<Vec<_>>())?;
        let x = inputs.iter().map(|x| self.apply(input, x)).collect();
        let x = self.residual_blocks(x, Section::ClassifierBlock)?;
        let output = self.index(Section::ClassifierOutput, 0, 0);
        self.fit(output, &x.iter().collect::<Vec<_>>())
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

/// `LeakyReLU((a_i + max_j b_j - mean) / std)` per channel, the statistics over all edges
/// `a_i + b_j` (EdgeConv with instance norm, then the max over neighbours).
fn finish_edges(a: &Features, b: &Features, graph: &[Vec<usize>]) -> Features {
    let mut out = Features::zeros(a.channels, a.n);
    for c in 0..a.channels {
        let (ac, bc) = (a.row(c), b.row(c));
        let edges = graph
            .iter()
            .enumerate()
            .flat_map(|(i, nb)| nb.iter().map(move |&j| ac[i] + bc[j]));
        let (mean, inv_std) = normalizer(edges);
        for (i, nb) in graph.iter().enumerate() {
            let best = nb.iter().map(|&j| bc[j]).fold(f64::NEG_INFINITY, f64::max);
            out.row_mut(c)[i] = leaky_relu((ac[i] + best - mean) * inv_std);
        }
    }
    out
}

/// The `min(knn, n - 1)` nearest other points of each point (ties to the lower index).
fn knn_graph(points: &[[f32; 2]], knn: usize) -> Graph {
    let k = knn.min(points.len().saturating_sub(1));
    points
        .iter()
        .enumerate()
        .map(|(i, a)| {
            let mut order: Vec<(f64, usize)> = points
                .iter()
                .enumerate()
                .filter(|&(j, _)| j != i)
                .map(|(j, b)| {
                    let dx = f64::from(a[0] - b[0]);
                    let dy = f64::from(a[1] - b[1]);
                    (dx * dx + dy * dy, j)
                })
                .collect();
            order.sort_by(|p, q| p.partial_cmp(q).expect("finite distances"));
            order[..k].iter().map(|&(_, j)| j).collect()
        })
        .collect()
}

/// `x + MLP([x, merge(attention(q(x), k(src), v(src)))])` (supp. eq. 6-8) with the six
/// cross layer's tensors `t` (in the order of `CrossLayerWeights::TENSORS`).
fn cross(t: &[FloatLinear], heads: usize, x: &Features, src: &Features) -> Features {
    let message = attention(
        heads,
        &linear(&t[CrossLayerWeights::QUERY], x),
        &linear(&t[CrossLayerWeights::KEY], src),
        &linear(&t[CrossLayerWeights::VALUE], src),
    );
    let merged = linear(&t[CrossLayerWeights::MERGE], &message);
    let hidden = linear(
        &t[CrossLayerWeights::MLP_HIDDEN],
        &Features::concat(&[x, &merged]),
    )
    .instance_norm()
    .map(|v| v.max(0.0));
    let update = linear(&t[CrossLayerWeights::MLP_OUT], &hidden);
    let mut out = x.clone();
    out.x.iter_mut().zip(&update.x).for_each(|(o, u)| *o += u);
    out
}

/// Scaled dot-product attention of queries `q` over keys `k` and values `v`, channel `c`
/// in head `c % heads`.
fn attention(heads: usize, q: &Features, k: &Features, v: &Features) -> Features {
    let d = q.channels;
    let head_dim = d / heads;
    let scale = 1.0 / (head_dim as f64).sqrt();
    // Point-major, head-major: point `i`, head `h`, dimension `e` at `i d + h head_dim + e`.
    let order = |x: &Features| -> Vec<f64> {
        let mut out = vec![0.0; x.x.len()];
        for c in 0..d {
            let at = (c % heads) * head_dim + c / heads;
            for (i, &value) in x.row(c).iter().enumerate() {
                out[i * d + at] = value;
            }
        }
        out
    };
    let (qt, kt, vt) = (order(q), order(k), order(v));
    let mut message = Features::zeros(d, q.n);
    let mut scores = vec![0.0f64; k.n];
    let mut acc = vec![0.0f64; head_dim];
    for i in 0..q.n {
        for h in 0..heads {
            let range = h * head_dim..(h + 1) * head_dim;
            let qi = &qt[i * d..(i + 1) * d][range.clone()];
            for (j, s) in scores.iter_mut().enumerate() {
                *s = dot(qi, &kt[j * d..(j + 1) * d][range.clone()]) * scale;
            }
            let max = scores.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            scores.iter_mut().for_each(|s| *s = (*s - max).exp());
            let total: f64 = scores.iter().sum();
            acc.fill(0.0);
            for (j, &p) in scores.iter().enumerate() {
                let vj = &vt[j * d..(j + 1) * d][range.clone()];
                acc.iter_mut().zip(vj).for_each(|(a, &v)| *a += p * v);
            }
            for (e, &a) in acc.iter().enumerate() {
                message.row_mut(h + heads * e)[i] = a / total;
            }
        }
    }
    message
}

fn l2_normalize(mut x: Features) -> Features {
    for i in 0..x.n {
        let norm = (0..x.channels)
            .map(|c| x.x[c * x.n + i].powi(2))
            .sum::<f64>()
            .sqrt()
            .max(1e-12);
        for c in 0..x.channels {
            x.x[c * x.n + i] /= norm;
        }
    }
    x
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every intermediate output of the core's matcher, in the order reported.
    struct Stages(Vec<(Stage, Vec<f32>)>);

    impl gomatch::matcher::Observer<f32> for Stages {
        fn features(&mut self, stage: Stage, x: &[f32], _: usize, _: usize) {
            self.0.push((stage, x.to_vec()));
        }
    }

    impl Stages {
        /// Largest difference of `ours` from the core's `stage`, relative to the largest
        /// magnitude there.
        fn relative_difference(&self, stage: Stage, ours: &Both) -> f64 {
            let (_, core) = self
                .0
                .iter()
                .find(|(s, _)| *s == stage)
                .unwrap_or_else(|| panic!("{stage:?} observed"));
            assert_eq!(core.len(), ours.f.x.len(), "{stage:?} size");
            let scale = core.iter().map(|&a| f64::from(a).abs()).fold(0.0, f64::max);
            let worst = core
                .iter()
                .zip(&ours.f.x)
                .map(|(&a, &b)| (f64::from(a) - b).abs())
                .fold(0.0, f64::max);
            worst / scale.max(f64::MIN_POSITIVE)
        }
    }

    /// The calibration's f64 forward pass is the core's network: on the shipped
    /// checkpoint each stage's output (encoder, the three attention layers, the
    /// L2-normalised descriptors, both sets) equals the core matcher's (f32) within float
    /// rounding, so a change to either that the other misses fails here, at its stage.
    #[test]
    fn the_f64_forward_pass_follows_the_cores_matcher() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../models/gomatch.safetensors");
        let Ok(checkpoint) = std::fs::read(path) else {
            println!("SKIPPED: no shipped checkpoint {path}");
            return;
        };
        let (config, tensors) = crate::convert::float_tensors(&checkpoint).expect("checkpoint");
        let (blob, _) = crate::convert::convert(&checkpoint, Precision::F32).expect("f32 blob");
        let model = Model::from_bytes(&blob).expect("blob");
        let pair = synthetic_pairs(1, 3).remove(0);
        let mut observed = Stages(Vec::new());
        // A static, like the other matchers here: 7.5 MB is not for a test thread's stack.
        static MATCHER: std::sync::Mutex<Matcher<1024, f32>> =
            std::sync::Mutex::new(Matcher::new());
        let mut matcher = MATCHER.lock().expect("matcher");
        matcher
            .encode_query_observed(&model, &pair.query, &mut observed)
            .expect("query encodes");
        matcher
            .match_view_observed(&model, &pair.db, &mut observed)
            .expect("pair matches");
        let precisions = vec![Precision::F32; tensors.len()];
        let mut engine = Engine {
            config,
            float: &tensors,
            effective: tensors.clone(),
            precisions: &precisions,
            options: FitOptions {
                scale: ScaleSearch::MaxAbs,
                correct: false,
            },
            int8: vec![None; tensors.len()],
        };
        let mut compared = 0;
        engine
            .descriptors(std::slice::from_ref(&pair), |stages, ours| {
                for (stage, x) in stages.into_iter().zip(ours) {
                    let difference = observed.relative_difference(stage, x);
                    // Measured: at most 6.4e-6 (the cross layer's view side).
                    assert!(difference < 1e-4, "{stage:?} differs by {difference:e}");
                    compared += 1;
                }
            })
            .expect("forward pass");
        assert_eq!(compared, 10, "five stages of both sets compared");
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
            let mut engine = Engine {
                config: ModelConfig::REFERENCE,
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
        let same = run(&Both::exact(f.clone()))[0].clone().expect("int8");
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
