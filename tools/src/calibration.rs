//! Calibration data for the int8 conversion: synthetic query-view pairs drawn like the
//! reference fixtures, and a host-side f64 forward pass of the float model that gathers,
//! for every layer, the second moments of its inputs (the Hessian `H = X X^T` of the
//! layer's squared output error, used by [`crate::quantize`]).
//!
//! The forward pass follows the network of `gomatch::Matcher` (encoder, EdgeConv self
//! attention, cross attention, classifier; supp. "Architecture Details") on the converted
//! tensors (fused residual blocks, split EdgeConv weights). Layers followed by an instance
//! norm see their inputs centred per set, because the norm removes any error that is
//! constant over the set. The two halves of an EdgeConv layer act together on the edge
//! `[x_i; x_j]`, so they share one joint moment matrix.

use gomatch::weights::{tensor_count, tensor_spec, ModelConfig};
use gomatch::{Matcher, Model};
use rand::seq::SliceRandom;
use rand::{RngExt, SeedableRng};
use rand_distr::StandardNormal;
use rand_pcg::Pcg64Mcg;
use std::sync::Mutex;

use crate::convert::FloatLinear;

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
        query.push([rng.random_range(lo[0]..hi[0]), rng.random_range(lo[1]..hi[1])]);
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

/// Tensors that act together on one input: the centre and neighbour halves of an
/// EdgeConv layer on the edge `[x_i; x_j]`, otherwise a single tensor. Their columns
/// concatenate, in order, to the columns of the moment matrix.
#[derive(Debug, Clone)]
pub struct LayerGroup {
    /// Blob indices of the tensors.
    pub tensors: Vec<usize>,
    /// Sum of the tensors' input counts.
    pub dim: usize,
    /// Sum over calibration samples of `z z^T` (`dim x dim`, row-major).
    pub moments: Vec<f64>,
    /// Number of samples summed.
    pub samples: f64,
}

impl LayerGroup {
    /// The mean second-moment matrix `sum z z^T / samples`.
    pub fn hessian(&self) -> Vec<f64> {
        let scale = 1.0 / self.samples.max(1.0);
        self.moments.iter().map(|m| m * scale).collect()
    }
}

/// Input moments of every layer of a model.
#[derive(Debug, Clone)]
pub struct Calibration {
    /// The groups, in blob order of their first tensor.
    pub groups: Vec<LayerGroup>,
    group_of: Vec<usize>,
}

impl Calibration {
    /// Empty moments for the layout of `config`.
    pub fn new(config: &ModelConfig) -> Self {
        let mut groups: Vec<LayerGroup> = Vec::new();
        let mut group_of = Vec::new();
        for index in 0..tensor_count(config) {
            let spec = tensor_spec(config, index).expect("index within the layout");
            let joins_previous = spec.name.role.ends_with("_neighbour");
            if joins_previous {
                let group = groups.last_mut().expect("a centre tensor precedes");
                group.tensors.push(index);
                group.dim += spec.cols;
            } else {
                groups.push(LayerGroup {
                    tensors: vec![index],
                    dim: spec.cols,
                    moments: Vec::new(),
                    samples: 0.0,
                });
            }
            group_of.push(groups.len() - 1);
        }
        for g in &mut groups {
            g.moments = vec![0.0; g.dim * g.dim];
        }
        Calibration { groups, group_of }
    }

    /// The group holding tensor `index`.
    pub fn group_of(&self, index: usize) -> &LayerGroup {
        &self.groups[self.group_of[index]]
    }

    /// Adds the inputs `x` of the single tensor `index`, centred per set if `centred`.
    fn add(&mut self, index: usize, x: &Features, centred: bool) {
        let x = if centred { x.centred() } else { x.clone() };
        let g = &mut self.groups[self.group_of[index]];
        add_cross(&mut g.moments, g.dim, 0, 0, &x, &x, None);
        g.samples += x.n as f64;
    }

    /// Adds the centred edge inputs `[x_i; x_j]` of the EdgeConv group of tensor `centre`
    /// over the `k`-neighbour `graph`, without forming the edges:
    /// `sum_e [x_i; x_j][x_i; x_j]^T` has the blocks `k X X^T`, `sum_i x_i s_i^T` with
    /// `s_i` the sum of `i`'s neighbours, and `sum_j indegree_j x_j x_j^T`.
    fn add_edges(&mut self, centre: usize, x: &Features, graph: &[Vec<usize>]) {
        let n = x.n;
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
        // Centre on the edge means of both halves.
        let mut centred_i = x.clone();
        let mut centred_j = x.clone();
        for c in 0..x.channels {
            let row = x.row(c);
            let mean_i = row.iter().sum::<f64>() / n as f64;
            let mean_j = row.iter().zip(&indegree).map(|(v, d)| v * d).sum::<f64>() / edges;
            centred_i.row_mut(c).iter_mut().for_each(|v| *v -= mean_i);
            centred_j.row_mut(c).iter_mut().for_each(|v| *v -= mean_j);
        }
        let mut sums = Features::zeros(x.channels, n);
        for c in 0..x.channels {
            let src = centred_j.row(c);
            for (i, neighbours) in graph.iter().enumerate() {
                sums.row_mut(c)[i] = neighbours.iter().map(|&j| src[j]).sum();
            }
        }
        let d = x.channels;
        let g = &mut self.groups[self.group_of[centre]];
        let weights_i = vec![k as f64; n];
        add_cross(&mut g.moments, g.dim, 0, 0, &centred_i, &centred_i, Some(&weights_i));
        add_cross(&mut g.moments, g.dim, 0, d, &centred_i, &sums, None);
        add_cross(&mut g.moments, g.dim, d, 0, &sums, &centred_i, None);
        add_cross(&mut g.moments, g.dim, d, d, &centred_j, &centred_j, Some(&indegree));
        g.samples += edges;
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
        for q in 0..b.channels {
            m[(r0 + p) * dim + c0 + q] += dot(a.row(p), b.row(q));
        }
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

    /// The values point-major: point `i`, channel `c` at `i * channels + c`.
    fn point_major(&self) -> Vec<f64> {
        let mut out = vec![0.0; self.x.len()];
        for c in 0..self.channels {
            for (i, &v) in self.row(c).iter().enumerate() {
                out[i * self.channels + c] = v;
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

/// `y = W x + b` per point.
fn linear(w: &FloatLinear, x: &Features) -> Features {
    let n = x.n;
    let mut y = Features::zeros(w.rows, n);
    for r in 0..w.rows {
        let out = y.row_mut(r);
        out.fill(f64::from(w.bias.get(r).copied().unwrap_or(0.0)));
        for (k, &wk) in w.weights[r * w.cols..(r + 1) * w.cols].iter().enumerate() {
            let wk = f64::from(wk);
            for (o, &v) in out.iter_mut().zip(x.row(k)) {
                *o += wk * v;
            }
        }
    }
    y
}

/// The converted tensors of a model by role (blob order of `gomatch::weights`).
struct Layers<'t> {
    config: ModelConfig,
    tensors: &'t [FloatLinear],
}

impl Layers<'_> {
    fn encoder_blocks(&self) -> usize {
        usize::from(self.config.encoder_blocks)
    }
    fn encoder_input(&self) -> usize {
        0
    }
    fn encoder_fused(&self, b: usize) -> usize {
        1 + 2 * b
    }
    fn self_base(&self, layer: usize) -> usize {
        1 + 2 * self.encoder_blocks() + 5 * layer
    }
    fn cross_base(&self) -> usize {
        self.self_base(2)
    }
    fn classifier_input(&self) -> usize {
        self.cross_base() + 6
    }
}

/// Accumulates the input moments of every layer over `pairs`, running the float model
/// `tensors` (blob order) in f64. The classifier sees the mutual matches of the
/// `gomatch::Matcher` on the f32 blob `f32_blob` of the same tensors.
pub fn calibrate(
    config: &ModelConfig,
    tensors: &[FloatLinear],
    f32_blob: &[u8],
    pairs: &[Pair],
) -> anyhow::Result<Calibration> {
    static MATCHER: Mutex<Matcher<1024, f32>> = Mutex::new(Matcher::new());
    let model = Model::from_bytes(f32_blob).map_err(|e| anyhow::anyhow!("f32 blob: {e}"))?;
    let layers = Layers {
        config: *config,
        tensors,
    };
    let mut stats = Calibration::new(config);
    let mut matcher = MATCHER
        .lock()
        .map_err(|_| anyhow::anyhow!("matcher lock poisoned"))?;
    for pair in pairs {
        let matches: Vec<(usize, usize)> = matcher
            .match_pair(&model, &pair.query, &pair.db)
            .map_err(|e| anyhow::anyhow!("calibration pair: {e}"))?
            .as_slice()
            .iter()
            .map(|m| (usize::from(m.i2d), usize::from(m.i3d)))
            .collect();
        forward(&layers, pair, &matches, &mut stats);
    }
    Ok(stats)
}

/// One pair through the float model, recording every layer's inputs.
fn forward(l: &Layers<'_>, pair: &Pair, matches: &[(usize, usize)], stats: &mut Calibration) {
    let knn = usize::from(l.config.knn);
    let mut x2 = encode(l, &pair.query, stats);
    let mut x3 = encode(l, &pair.db, stats);
    let g2 = knn_graph(&pair.query, knn);
    let g3 = knn_graph(&pair.db, knn);
    x2 = self_layer(l, 0, &x2, &g2, stats);
    x3 = self_layer(l, 0, &x3, &g3, stats);
    x2 = cross_layer(l, &x2, &x3, stats);
    x3 = cross_layer(l, &x3, &x2, stats);
    x2 = self_layer(l, 1, &x2, &g2, stats);
    x3 = self_layer(l, 1, &x3, &g3, stats);
    let (d2, d3) = (l2_normalize(x2), l2_normalize(x3));
    classifier(l, &d2, &d3, matches, stats);
}

fn encode(l: &Layers<'_>, points: &[[f32; 2]], stats: &mut Calibration) -> Features {
    let n = points.len();
    let mut coords = Features::zeros(2, n);
    for (i, p) in points.iter().enumerate() {
        coords.x[i] = f64::from(p[0]);
        coords.x[n + i] = f64::from(p[1]);
    }
    stats.add(l.encoder_input(), &coords, false);
    let x = linear(&l.tensors[l.encoder_input()], &coords);
    residual_blocks(l, x, l.encoder_fused(0), l.encoder_blocks(), stats)
}

/// `x += ReLU(IN(W2 IN(W1 W0 x)))` per block; tensors `first`, `first + 1`, ...
fn residual_blocks(
    l: &Layers<'_>,
    mut x: Features,
    first: usize,
    blocks: usize,
    stats: &mut Calibration,
) -> Features {
    for b in 0..blocks {
        let (fused, conv2) = (first + 2 * b, first + 2 * b + 1);
        stats.add(fused, &x, true);
        let h = linear(&l.tensors[fused], &x).instance_norm();
        stats.add(conv2, &h, true);
        let z = linear(&l.tensors[conv2], &h).instance_norm();
        x.x.iter_mut()
            .zip(&z.x)
            .for_each(|(v, &z)| *v += z.max(0.0));
    }
    x
}

/// The `min(knn, n - 1)` nearest other points of each point (ties to the lower index).
fn knn_graph(points: &[[f32; 2]], knn: usize) -> Vec<Vec<usize>> {
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

fn self_layer(
    l: &Layers<'_>,
    layer: usize,
    x: &Features,
    graph: &[Vec<usize>],
    stats: &mut Calibration,
) -> Features {
    let base = l.self_base(layer);
    let x1 = edge_conv(l, base, x, graph, stats);
    let x2 = edge_conv(l, base + 2, &x1, graph, stats);
    let cat = Features::concat(&[x, &x1, &x2]);
    stats.add(base + 4, &cat, true);
    linear(&l.tensors[base + 4], &cat)
        .instance_norm()
        .map(leaky_relu)
}

/// `max_j LeakyReLU(IN(Wc x_i + Wn x_j))` with the statistics over all edges.
fn edge_conv(
    l: &Layers<'_>,
    centre: usize,
    x: &Features,
    graph: &[Vec<usize>],
    stats: &mut Calibration,
) -> Features {
    stats.add_edges(centre, x, graph);
    let a = linear(&l.tensors[centre], x);
    let b = linear(&l.tensors[centre + 1], x);
    let mut out = Features::zeros(a.channels, x.n);
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

/// `x + MLP([x, merge(attention(q(x), k(src), v(src)))])` (supp. eq. 6-8), channel `c` in
/// head `c % heads`.
fn cross_layer(
    l: &Layers<'_>,
    x: &Features,
    src: &Features,
    stats: &mut Calibration,
) -> Features {
    let base = l.cross_base();
    let t = &l.tensors[base..base + 6];
    stats.add(base, x, false);
    stats.add(base + 1, src, false);
    stats.add(base + 2, src, false);
    let q = linear(&t[0], x);
    let k = linear(&t[1], src);
    let v = linear(&t[2], src);
    let heads = usize::from(l.config.heads);
    let d = q.channels;
    let scale = 1.0 / ((d / heads) as f64).sqrt();
    let (q, k) = (q.point_major(), k.point_major());
    let mut message = Features::zeros(d, x.n);
    let mut scores = vec![0.0f64; src.n];
    for i in 0..x.n {
        let qi = &q[i * d..(i + 1) * d];
        for h in 0..heads {
            for (j, s) in scores.iter_mut().enumerate() {
                let kj = &k[j * d..(j + 1) * d];
                *s = (h..d).step_by(heads).map(|c| qi[c] * kj[c]).sum::<f64>() * scale;
            }
            let max = scores.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            scores.iter_mut().for_each(|s| *s = (*s - max).exp());
            let total: f64 = scores.iter().sum();
            for c in (h..d).step_by(heads) {
                message.row_mut(c)[i] =
                    scores.iter().zip(v.row(c)).map(|(p, v)| p * v).sum::<f64>() / total;
            }
        }
    }
    stats.add(base + 3, &message, false);
    let merged = linear(&t[3], &message);
    let cat = Features::concat(&[x, &merged]);
    stats.add(base + 4, &cat, true);
    let hidden = linear(&t[4], &cat).instance_norm().map(|v| v.max(0.0));
    stats.add(base + 5, &hidden, false);
    let update = linear(&t[5], &hidden);
    let mut out = x.clone();
    out.x.iter_mut().zip(&update.x).for_each(|(o, u)| *o += u);
    out
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

/// The match classifier on `[f2d; f3d]` of each match (a single match twice).
fn classifier(
    l: &Layers<'_>,
    d2: &Features,
    d3: &Features,
    matches: &[(usize, usize)],
    stats: &mut Calibration,
) {
    if matches.is_empty() {
        return;
    }
    let mut list = matches.to_vec();
    if list.len() == 1 {
        list.push(list[0]);
    }
    let i2: Vec<usize> = list.iter().map(|m| m.0).collect();
    let i3: Vec<usize> = list.iter().map(|m| m.1).collect();
    let input = Features::concat(&[&d2.gather(&i2), &d3.gather(&i3)]);
    let first = l.classifier_input();
    stats.add(first, &input, false);
    let x = linear(&l.tensors[first], &input);
    let blocks = usize::from(l.config.classifier_blocks);
    let x = residual_blocks(l, x, first + 1, blocks, stats);
    stats.add(first + 1 + 2 * blocks, &x, false);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn synthetic_pairs_look_like_the_fixtures() {
        let pairs = synthetic_pairs(5, 7);
        for p in &pairs {
            assert!((32..=400).contains(&p.query.len()));
            assert!(p.db.len() >= p.query.len());
            assert!(p
                .db
                .iter()
                .all(|b| b[0].abs() <= 0.6 && b[1].abs() <= 0.6));
            assert!(p.query.iter().all(|q| q[0].abs() < 2.0 && q[1].abs() < 2.0));
        }
        let again = synthetic_pairs(5, 7);
        assert_eq!(pairs[3].query, again[3].query);
    }

    /// The factored edge moments equal the ones summed over the explicit edges.
    #[test]
    fn edge_moments_match_explicit_edges() {
        let config = ModelConfig {
            feature_dim: 2,
            encoder_blocks: 1,
            ..ModelConfig::REFERENCE
        };
        let x = Features {
            channels: 2,
            n: 4,
            x: vec![1.0, -2.0, 0.5, 3.0, 0.0, 1.0, 2.0, -1.0],
        };
        let graph = vec![vec![1, 2], vec![0, 3], vec![3, 0], vec![2, 0]];
        let mut stats = Calibration::new(&config);
        let centre = 1 + 2;
        stats.add_edges(centre, &x, &graph);
        let edges: Vec<[f64; 4]> = graph
            .iter()
            .enumerate()
            .flat_map(|(i, nb)| {
                let x = &x;
                nb.iter()
                    .map(move |&j| [x.x[i], x.x[4 + i], x.x[j], x.x[4 + j]])
            })
            .collect();
        let mean: [f64; 4] =
            core::array::from_fn(|a| edges.iter().map(|e| e[a]).sum::<f64>() / 8.0);
        let g = stats.group_of(centre);
        assert_eq!((g.dim, g.tensors.len(), g.samples), (4, 2, 8.0));
        for a in 0..4 {
            for b in 0..4 {
                let expected: f64 = edges
                    .iter()
                    .map(|e| (e[a] - mean[a]) * (e[b] - mean[b]))
                    .sum();
                assert!((g.moments[a * 4 + b] - expected).abs() < 1e-12, "{a} {b}");
            }
        }
    }
}
