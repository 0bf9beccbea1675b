//! Attention (supp. "Attention", eq. 4-8): EdgeConv self attention on a k-nearest-neighbour
//! graph in bearing coordinate space, and multi-head cross attention between the sets.
//!
//! Self attention never builds the `N x K x 2C` edge tensor: the edge convolution is
//! factored per point, `W [f_i, f_j - f_i] = (Wa - Wb) f_i + Wb f_j`, and because instance
//! norm has no affine parameters and leaky ReLU is monotonic, the max over neighbours
//! commutes with both: only per-channel statistics over the `N x K` edges and the per-point
//! maximum of the neighbour term are kept. Cross attention streams the source points with
//! an online softmax, so no `N x N x heads` score buffer exists.

use crate::limits::{MAX_FEATURE_DIM, MAX_HEADS, MAX_KNN};
use crate::nn::blocking::{
    self, channels_for_rows, EDGE_CHANNELS, SHORT_ROW_CHANNELS, WIDE_SHORT_ROW_CHANNELS,
};
use crate::nn::dispatch::{with_fma, Fma, Kernel};
use crate::nn::linear::{accumulate, chunk_rows, larger, store, store_point_major};
use crate::nn::transpose::TransposeVariants;
use crate::nn::{
    exp, instance_norm_rows, leaky_relu, linear, relu, sqrt, Input, LayerInput, LayerTap, Moments,
    StatSum, ROW_BLOCK,
};
use crate::weights::{CrossLayerWeights, Linear, SelfLayerWeights};

/// Neighbour lists of a set: `graph[i][..k]` are the `k` nearest points of point `i`.
pub type Neighbours = [u16; MAX_KNN];

/// Points per block of the self-attention fusing conv (its output replaces the input).
pub const FUSE_BLOCK: usize = 128;

/// Number of neighbours the reference uses for a set of `n` points: `min(knn, n - 1)`.
pub fn neighbour_count(knn: usize, n: usize) -> usize {
    knn.min(n.saturating_sub(1)).min(MAX_KNN)
}

/// Builds the k-nearest-neighbour graph in coordinate space exactly as the reference:
/// squared distance `(-2 a.b + |a|^2) + |b|^2` clamped to `>= 1e-12`, the `k + 1` smallest
/// (ties to the lower index), the first one (assumed to be the point itself) dropped.
pub fn knn_graph(points: &[[f32; 2]], k: usize, graph: &mut [Neighbours]) {
    with_fma(KnnGraph { points, k, graph });
}

/// The arguments of one [`knn_graph`] call (plain f32 arithmetic: the same bits compiled for
/// any CPU, in the widest vectors it has).
struct KnnGraph<'a> {
    points: &'a [[f32; 2]],
    k: usize,
    graph: &'a mut [Neighbours],
}

/// Candidate points whose distances are computed together (one vectorised loop), then
/// compared with the `k + 1`-th best [`DISTANCE_LANES`] at a time.
const DISTANCE_BLOCK: usize = 64;
/// Distances compared with the current bound at once (one bit each of a mask).
const DISTANCE_LANES: usize = 16;

impl Kernel<()> for KnnGraph<'_> {
    #[inline(always)]
    fn run<F: Fma>(self, _fma: F) {
        let KnnGraph { points, k, graph } = self;
        let mut distances = [0.0f32; DISTANCE_BLOCK];
        for (a, neighbours) in points.iter().zip(graph.iter_mut()) {
            let mut nearest = Nearest::new(k);
            for (block, candidates) in points.chunks(DISTANCE_BLOCK).enumerate() {
                let distances = &mut distances[..candidates.len()];
                squared_distances(a, candidates, distances);
                let lanes = distances.chunks(DISTANCE_LANES);
                for (lane, chunk) in lanes.enumerate() {
                    let first = block * DISTANCE_BLOCK + lane * DISTANCE_LANES;
                    let mut closer = nearest.closer(chunk);
                    while closer != 0 {
                        let t = closer.trailing_zeros() as usize;
                        closer &= closer - 1;
                        nearest.offer(chunk[t], (first + t) as u16);
                    }
                }
            }
            for (slot, &(_, j)) in neighbours.iter_mut().zip(nearest.without_first()) {
                *slot = j;
            }
        }
    }
}

/// `out[j]` = the reference's squared distance from `a` to `candidates[j]`,
/// `max((-2 a.b + |a|^2) + |b|^2, 1e-12)`.
#[inline(always)]
fn squared_distances(a: &[f32; 2], candidates: &[[f32; 2]], out: &mut [f32]) {
    let norm_a = a[0] * a[0] + a[1] * a[1];
    for (d, b) in out.iter_mut().zip(candidates) {
        let dot = a[0] * b[0] + a[1] * b[1];
        let norm_b = b[0] * b[0] + b[1] * b[1];
        *d = (-2.0 * dot + norm_a + norm_b).max(1e-12);
    }
}

/// The `k + 1` smallest distances offered so far, in order (ties to the earlier offer).
struct Nearest {
    best: [(f32, u16); MAX_KNN + 1],
    count: usize,
    k: usize,
}

impl Nearest {
    fn new(k: usize) -> Self {
        Nearest {
            best: [(0.0, 0); MAX_KNN + 1],
            count: 0,
            k,
        }
    }

    /// A mask of the `distances` (at most 32) that would enter the list as it is: bit `t`
    /// for `distances[t]` (all of them while it is not full). Only these are offered, in
    /// order (each offer checks again against the list it finds), so that the few entries
    /// cost a branch each instead of every distance.
    #[inline(always)]
    fn closer(&self, distances: &[f32]) -> u32 {
        if self.count < self.k + 1 {
            return u32::MAX >> (32 - distances.len().clamp(1, 32));
        }
        let bound = self.best[self.k].0;
        let bits = distances.iter().enumerate();
        bits.fold(0, |mask, (t, &d)| mask | u32::from(d < bound) << t)
    }

    /// Inserts point `j` at distance `dist` where it belongs, if it does.
    #[inline(always)]
    fn offer(&mut self, dist: f32, j: u16) {
        let k = self.k;
        if self.count == k + 1 && dist >= self.best[k].0 {
            return;
        }
        let mut at = self.count.min(k);
        while at > 0 && self.best[at - 1].0 > dist {
            self.best[at] = self.best[at - 1];
            at -= 1;
        }
        self.best[at] = (dist, j);
        self.count = (self.count + 1).min(k + 1);
    }

    /// The list without its first entry (the point itself).
    fn without_first(&self) -> &[(f32, u16)] {
        self.best.get(1..self.count).unwrap_or(&[])
    }
}

/// Scratch of one self-attention layer on a set of `n` points.
pub struct SelfScratch<'s> {
    /// `x1`, `d x n`.
    pub x1: &'s mut [f32],
    /// `x2`, `2d x n`.
    pub x2: &'s mut [f32],
    /// At least `(ROW_BLOCK + 1) x n` values: neighbour terms of a chunk of channels and
    /// per-point maxima.
    pub rows: &'s mut [f32],
    /// `d x FUSE_BLOCK` output block of the fusing conv.
    pub fused: &'s mut [f32],
    /// Any free memory (the matcher's Sinkhorn cost, unused while attention runs): where it
    /// is larger than `rows` or `fused`, it takes their place, so the linear layers run on
    /// more rows or points per call (each call unpacks its weights and, on the integer
    /// kernel, quantizes its input once).
    pub spare: &'s mut [f32],
}

/// One EdgeConv self-attention layer (supp. eq. 4-5) on `x` (`d x n`), in place: the output
/// replaces the descriptor. Each layer's input goes to `tap`.
pub fn self_layer(
    w: &SelfLayerWeights<'_>,
    graph: &[Neighbours],
    k: usize,
    x: &mut [f32],
    n: usize,
    s: SelfScratch<'_>,
    tap: &mut dyn LayerTap,
) {
    with_fma(SelfLayer {
        w,
        graph,
        k,
        x,
        n,
        s,
        tap,
    });
}

/// The arguments of one [`self_layer`] call.
struct SelfLayer<'k, 'w, 's> {
    w: &'k SelfLayerWeights<'w>,
    graph: &'k [Neighbours],
    k: usize,
    x: &'k mut [f32],
    n: usize,
    s: SelfScratch<'s>,
    tap: &'k mut dyn LayerTap,
}

impl Kernel<()> for SelfLayer<'_, '_, '_> {
    #[inline(always)]
    fn run<F: Fma>(self, fma: F) {
        let SelfLayer {
            w,
            graph,
            k,
            x,
            n,
            s,
            tap,
        } = self;
        self_layer_with(fma, w, graph, k, x, n, s, tap);
    }
}

/// [`self_layer`] with the given [`Fma`].
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn self_layer_with<F: Fma>(
    fma: F,
    w: &SelfLayerWeights<'_>,
    graph: &[Neighbours],
    k: usize,
    x: &mut [f32],
    n: usize,
    s: SelfScratch<'_>,
    tap: &mut dyn LayerTap,
) {
    let d = w.fuse.rows();
    let edges = |points| LayerInput::Edges {
        points,
        graph: &graph[..n],
        k,
    };
    let input = Input::one(x, d, n);
    tap.layer_input(w.edge1_centre.tensor(), &edges(input));
    edge_conv(
        fma,
        &w.edge1_centre,
        &w.edge1_neighbour,
        &input,
        graph,
        k,
        s.x1,
        larger(s.spare, s.rows),
    );
    let input = Input::one(s.x1, d, n);
    tap.layer_input(w.edge2_centre.tensor(), &edges(input));
    edge_conv(
        fma,
        &w.edge2_centre,
        &w.edge2_neighbour,
        &input,
        graph,
        k,
        s.x2,
        larger(s.spare, s.rows),
    );
    let concatenation = Input::parts([&*x, &*s.x1, &*s.x2], [d, d, 2 * d], n);
    tap.layer_input(w.fuse.tensor(), &LayerInput::Points(concatenation));
    let fused = larger(s.spare, s.fused);
    let block = (fused.len() / d.max(1)).clamp(1, n.max(1));
    let mut b0 = 0;
    while b0 < n {
        let len = block.min(n - b0);
        let input = Input::parts([&*x, &*s.x1, &*s.x2], [d, d, 2 * d], n).columns(b0, len);
        linear(&w.fuse, &input, 0..d, |r, i0, v| {
            store(fused, len, r, i0, v)
        });
        for r in 0..d {
            x[r * n + b0..r * n + b0 + len].copy_from_slice(&fused[r * len..(r + 1) * len]);
        }
        b0 += len;
    }
    instance_norm_rows(&mut x[..d * n], n);
    for v in x[..d * n].iter_mut() {
        *v = leaky_relu(*v);
    }
}

/// `out = max_k LeakyReLU(IN2d(W [x_i, x_j - x_i]))` over the `k` neighbours, with the
/// instance norm statistics over all `n x k` edges of each channel. `scratch` (at least
/// `(ROW_BLOCK + 1) x n` values) holds the neighbour terms of a chunk of channels, the
/// per-point maxima of a group of channels and, where there is room, the group's edge values.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn edge_conv<F: Fma>(
    fma: F,
    centre: &Linear<'_>,
    neighbour: &Linear<'_>,
    input: &Input<'_>,
    graph: &[Neighbours],
    k: usize,
    out: &mut [f32],
    scratch: &mut [f32],
) {
    let n = input.points();
    let channels = centre.rows();
    linear(centre, input, 0..channels, |r, i0, v| {
        store(out, n, r, i0, v)
    });
    // Channels finished together (as many as the scratch holds), and the neighbour rows a
    // chunk needs at least.
    let fits = |g: usize| scratch.len() >= n * (2 * g + g.max(ROW_BLOCK));
    let group = [
        channels_for_rows(EDGE_CHANNELS, n, F::WIDE_REGISTERS),
        EDGE_CHANNELS,
    ]
    .into_iter()
    .find(|&g| fits(g))
    .unwrap_or(1);
    let least_rows = n * group.max(ROW_BLOCK);
    let (maxima, rest) = scratch.split_at_mut(group * n);
    let (point_major, rest) = rest.split_at_mut(if group > 1 { group * n } else { 0 });
    // The group's edge values, kept for the variance pass when the scratch has room.
    let edge_count = if k > 0 && rest.len() >= group * n * k + least_rows {
        group * n * k
    } else {
        0
    };
    let (edges, rows) = rest.split_at_mut(edge_count);
    let chunk = chunk_rows(rows.len(), n) / group * group;
    let mut r0 = 0;
    while r0 < channels {
        let r1 = (r0 + chunk).min(channels);
        linear(neighbour, input, r0..r1, |r, i0, v| {
            store(rows, n, r - r0, i0, v)
        });
        let mut r = r0;
        while r < r1 {
            let g = if r + group <= r1 { group } else { 1 };
            let channel_group = EdgeChannels {
                a: &mut out[r * n..(r + g) * n],
                b: &rows[(r - r0) * n..(r - r0 + g) * n],
                graph: &graph[..n],
                k,
                maxima: &mut maxima[..g * n],
                point_major,
                edges,
            };
            if g == WIDE_SHORT_ROW_CHANNELS {
                channel_group.finish::<F, WIDE_SHORT_ROW_CHANNELS>(fma);
            } else if g == SHORT_ROW_CHANNELS {
                channel_group.finish::<F, SHORT_ROW_CHANNELS>(fma);
            } else if g == EDGE_CHANNELS {
                channel_group.finish::<F, EDGE_CHANNELS>(fma);
            } else {
                channel_group.finish::<F, 1>(fma);
            }
            r += g;
        }
        r0 = r1;
    }
}

/// `G` channels of an edge convolution: centre terms `a` (`G x n`, replaced by the layer
/// output), neighbour terms `b` (`G x n`), and scratch for `G x n` maxima, the neighbour
/// terms point by point (`n x G`, for `G > 1`) and up to `n x k x G` edge values.
struct EdgeChannels<'e, 'g> {
    a: &'e mut [f32],
    b: &'e [f32],
    graph: &'g [Neighbours],
    k: usize,
    maxima: &'e mut [f32],
    point_major: &'e mut [f32],
    edges: &'e mut [f32],
}

impl EdgeChannels<'_, '_> {
    /// Edge values `a_i + b_j`, their mean and variance over all edges of each channel,
    /// then `LeakyReLU((a_i + max_j b_j - mean) / std)`. The `G` channels are the lanes of
    /// one vector (the neighbour terms are first laid out point by point), and each lane's
    /// sums run over its edges in order (points, then neighbours), as one channel alone
    /// would. With room for all `n k G` edge values the variance pass reads them back
    /// instead of gathering `b_j` again (same sums).
    #[inline(always)]
    fn finish<F: Fma, const G: usize>(self, fma: F) {
        let EdgeChannels {
            a,
            b,
            graph,
            k,
            maxima,
            point_major,
            edges,
        } = self;
        let n = graph.len();
        if n == 0 {
            return;
        }
        if G > 1 {
            fma.point_major::<G>(b, n, point_major);
        }
        let terms: &[f32] = if G == 1 { b } else { point_major };
        let neighbour = |j: u16| -> [f32; G] {
            let lanes = terms.get(usize::from(j) * G..);
            lanes
                .and_then(|lanes| lanes.first_chunk::<G>())
                .map_or([0.0; G], |lanes| *lanes)
        };
        let centre = |i: usize| -> [f32; G] {
            let mut x = [0.0; G];
            for (xc, row) in x.iter_mut().zip(a.chunks_exact(n)) {
                *xc = row[i];
            }
            x
        };
        let mut sums = [StatSum::default(); G];
        let mut deviations = [StatSum::default(); G];
        let kept = edges.get_mut(..n * k * G).filter(|_| k > 0);
        match kept {
            Some(edges) => {
                // The centre terms point by point, where each point's maxima go once its
                // edges are done (a gather of `G` rows per point otherwise).
                fma.point_major::<G>(a, n, maxima);
                let points = graph.iter().zip(edges.chunks_exact_mut(k * G));
                for ((neighbours, point_edges), maxima) in points.zip(maxima.chunks_exact_mut(G)) {
                    let ai: [f32; G] = match maxima.first_chunk::<G>() {
                        Some(centre) => *centre,
                        None => [0.0; G],
                    };
                    let mut best = [f32::NEG_INFINITY; G];
                    for (&j, e) in neighbours[..k].iter().zip(point_edges.chunks_exact_mut(G)) {
                        let bj = neighbour(j);
                        let edge = edge_values(&ai, &bj);
                        e.copy_from_slice(&edge);
                        add_lanes(&mut sums, &edge);
                        best = max_lanes(best, bj);
                    }
                    maxima.copy_from_slice(&best);
                }
                let means = sums.map(|sum| Moments::of(sum, n * k).mean());
                for e in edges.chunks_exact(G) {
                    let e: &[f32; G] = e.try_into().unwrap_or(&[0.0; G]);
                    add_lanes(&mut deviations, &squared_deviations(e, &means));
                }
            }
            None => {
                let point_maxima = maxima.chunks_exact_mut(G);
                for (i, (neighbours, maxima)) in graph.iter().zip(point_maxima).enumerate() {
                    let ai = centre(i);
                    let mut best = [f32::NEG_INFINITY; G];
                    for &j in &neighbours[..k] {
                        let bj = neighbour(j);
                        add_lanes(&mut sums, &edge_values(&ai, &bj));
                        best = max_lanes(best, bj);
                    }
                    maxima.copy_from_slice(&best);
                }
                let means = sums.map(|sum| Moments::of(sum, n * k).mean());
                for (i, neighbours) in graph.iter().enumerate() {
                    let ai = centre(i);
                    for &j in &neighbours[..k] {
                        let bj = neighbour(j);
                        let edge = edge_values(&ai, &bj);
                        add_lanes(&mut deviations, &squared_deviations(&edge, &means));
                    }
                }
            }
        }
        // The maxima channel by channel (one lane per point is a gather otherwise).
        let maxima: &[f32] = if G == 1 {
            maxima
        } else {
            fma.channel_major::<G>(maxima, n, point_major);
            point_major
        };
        for ((c, row), best) in a
            .chunks_exact_mut(n)
            .enumerate()
            .zip(maxima.chunks_exact(n))
        {
            let normalizer = Moments::of(sums[c], n * k).normalizer(&deviations[c]);
            for (ai, &best) in row.iter_mut().zip(best) {
                *ai = leaky_relu(normalizer.apply_with(fma, *ai + best));
            }
        }
    }
}

/// The edge values `a_i + b_j` of a group's channels (one per lane).
#[inline(always)]
fn edge_values<const G: usize>(ai: &[f32; G], bj: &[f32; G]) -> [f32; G] {
    core::array::from_fn(|c| ai[c] + bj[c])
}

/// Adds each lane's value to its own running sum (one channel per lane).
#[inline(always)]
fn add_lanes<const G: usize>(sums: &mut [StatSum; G], values: &[f32; G]) {
    for (sum, &v) in sums.iter_mut().zip(values) {
        sum.add(v);
    }
}

/// The larger of each lane's running maximum and its new value (`vmaxps` order: the running
/// maximum stays where the new value is not larger, NaN included).
#[inline(always)]
fn max_lanes<const G: usize>(best: [f32; G], values: [f32; G]) -> [f32; G] {
    core::array::from_fn(|c| {
        if values[c] > best[c] {
            values[c]
        } else {
            best[c]
        }
    })
}

/// Each lane's [`Moments::squared_deviation`] from its mean.
#[inline(always)]
fn squared_deviations<const G: usize>(values: &[f32; G], means: &[f32; G]) -> [f32; G] {
    core::array::from_fn(|c| Moments::squared_deviation(values[c], means[c]))
}

/// Multi-head cross attention with message MLP (supp. eq. 6-8), in place:
/// `x += MLP([x, merge(attention(q(x), k(src), v(src)))])`. Channel `c` belongs to head
/// `c % heads`. `pool` holds at least `3 x d x max(nx, ns)` values of scratch. Each layer's
/// input goes to `tap`.
#[allow(clippy::too_many_arguments)]
pub fn cross_layer(
    w: &CrossLayerWeights<'_>,
    heads: usize,
    x: &mut [f32],
    nx: usize,
    src: &[f32],
    ns: usize,
    pool: &mut [f32],
    tap: &mut dyn LayerTap,
) {
    let d = w.query.rows();
    let head_dim = d / heads.max(1);
    let slot = d * nx.max(ns);
    let (front, values) = pool.split_at_mut(2 * slot);
    {
        let (queries, keys) = front.split_at_mut(slot);
        let source = Input::one(src, d, ns);
        let target = Input::one(x, d, nx);
        tap.layer_input(w.query.tensor(), &LayerInput::Points(target));
        tap.layer_input(w.key.tensor(), &LayerInput::Points(source));
        tap.layer_input(w.value.tensor(), &LayerInput::Points(source));
        linear(&w.key, &source, 0..d, |r, i0, v| store(keys, ns, r, i0, v));
        linear(&w.value, &source, 0..d, |r, i0, v| {
            store_point_major(values, d, head_major(r, heads, head_dim), i0, v)
        });
        linear(&w.query, &target, 0..d, |r, i0, v| {
            store(queries, nx, r, i0, v)
        });
        let shape = AttentionShape {
            heads,
            head_dim,
            nx,
            ns,
        };
        attend(&shape, queries, keys, values);
        // Messages (now in the query slot), merged into the value slot.
        let messages = Input::one(queries, d, nx);
        tap.layer_input(w.merge.tensor(), &LayerInput::Points(messages));
        linear(&w.merge, &messages, 0..d, |r, i0, v| {
            store(values, nx, r, i0, v)
        });
    }
    let hidden = front;
    let h = w.mlp_hidden.rows();
    let concatenation = Input::two((x, d), (values, d), nx);
    tap.layer_input(w.mlp_hidden.tensor(), &LayerInput::Points(concatenation));
    linear(&w.mlp_hidden, &concatenation, 0..h, |r, i0, v| {
        store(hidden, nx, r, i0, v)
    });
    instance_norm_rows(&mut hidden[..h * nx], nx);
    for v in hidden[..h * nx].iter_mut() {
        *v = relu(*v);
    }
    let rectified = Input::one(hidden, h, nx);
    tap.layer_input(w.mlp_out.tensor(), &LayerInput::Points(rectified));
    linear(&w.mlp_out, &rectified, 0..d, |r, i0, v| {
        accumulate(x, nx, r, i0, v)
    });
}

/// Position of channel `c` in the head-major order: head `c % heads` first, then the
/// dimension `c / heads` within the head.
#[inline(always)]
fn head_major(c: usize, heads: usize, head_dim: usize) -> usize {
    (c % heads) * head_dim + c / heads
}

/// Sizes of one attention call.
struct AttentionShape {
    heads: usize,
    head_dim: usize,
    /// Queries.
    nx: usize,
    /// Source points.
    ns: usize,
}

/// Queries attended together (`nn::blocking`); grouping queries changes no bit.
const QUERY_BLOCK: usize = blocking::ATTENTION_QUERIES;
/// Source points per block of the online softmax (a multiple of [`LANES`]).
const SOURCE_BLOCK: usize = 64;
/// Width of the inner register tiles (`nn::blocking`).
const LANES: usize = blocking::ATTENTION_LANES;
/// Width of the inner register tiles where the CPU has 32 vector registers of 16 lanes
/// ([`Fma::WIDE_REGISTERS`]): 8 x 16 score accumulators.
const WIDE_LANES: usize = 16;

/// Scaled dot-product attention (eq. 6-7) of the queries `q` (channel-major `d x nx`,
/// replaced by the messages) over the keys `k` (channel-major `d x ns`) and values `v`
/// (point-major, channels in [`head_major`] order), softmax over the source points.
///
/// Streamed: for each block of [`QUERY_BLOCK`] queries the sources are visited in blocks
/// of [`SOURCE_BLOCK`] with an online softmax (running maximum and sum per query and
/// head), so no `nx x ns` score matrix exists. Scores and messages are small register
/// tiles (`QUERY_BLOCK x LANES`) summed in a fixed order: within a block over the head's
/// dimensions (scores) or the block's sources (messages), then block after block.
fn attend(shape: &AttentionShape, q: &mut [f32], k: &[f32], v: &[f32]) {
    with_fma(Attend { shape, q, k, v });
}

/// The arguments of one [`attend`] call.
struct Attend<'a> {
    shape: &'a AttentionShape,
    q: &'a mut [f32],
    k: &'a [f32],
    v: &'a [f32],
}

impl Kernel<()> for Attend<'_> {
    /// Plain f32 arithmetic (no fused operations): the same bits compiled for any CPU, in
    /// register tiles as wide as its vectors ([`WIDE_LANES`] with 32 wide registers).
    #[inline(always)]
    fn run<F: Fma>(self, fma: F) {
        if F::WIDE_REGISTERS {
            attend_vectorised::<F, WIDE_LANES>(fma, self.shape, self.q, self.k, self.v);
        } else {
            attend_vectorised::<F, LANES>(fma, self.shape, self.q, self.k, self.v);
        }
    }
}

/// [`attend`] in register tiles of `L` lanes, compiled into the caller (for the widest
/// vectors the CPU has).
#[inline(always)]
fn attend_vectorised<F: Fma, const L: usize>(
    fma: F,
    shape: &AttentionShape,
    q: &mut [f32],
    k: &[f32],
    v: &[f32],
) {
    let mut blocks = QueryBlocks {
        queries: [[0.0; QUERY_BLOCK]; MAX_FEATURE_DIM],
        acc: [[0.0; MAX_FEATURE_DIM]; QUERY_BLOCK],
        scores: [[[0.0; SOURCE_BLOCK]; MAX_HEADS]; QUERY_BLOCK],
    };
    for h in 0..shape.heads {
        let mut i0 = 0;
        while i0 < shape.nx {
            let live = QUERY_BLOCK.min(shape.nx - i0);
            blocks.attend_head::<F, L>(fma, shape, h, q, i0, live, k, v);
            i0 += live;
        }
    }
}

/// Buffers of one block of [`QUERY_BLOCK`] queries: the queries, their running messages
/// and one source block's scores (only head `h`'s parts are used by a call for `h`).
struct QueryBlocks {
    queries: [[f32; QUERY_BLOCK]; MAX_FEATURE_DIM],
    acc: [[f32; MAX_FEATURE_DIM]; QUERY_BLOCK],
    scores: [[[f32; SOURCE_BLOCK]; MAX_HEADS]; QUERY_BLOCK],
}

impl QueryBlocks {
    /// Head `h`'s messages for the `live` queries from `i0`, which replace the head's query
    /// channels in `q` (no other head reads them): scores, online softmax and messages,
    /// source block after source block.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn attend_head<F: Fma, const L: usize>(
        &mut self,
        fma: F,
        shape: &AttentionShape,
        h: usize,
        q: &mut [f32],
        i0: usize,
        live: usize,
        k: &[f32],
        v: &[f32],
    ) {
        let (heads, head_dim, nx) = (shape.heads, shape.head_dim, shape.nx);
        let dims = h * head_dim..(h + 1) * head_dim;
        for e in 0..head_dim {
            let c = h + heads * e;
            let qc = &mut self.queries[c];
            *qc = [0.0; QUERY_BLOCK];
            qc[..live].copy_from_slice(&q[c * nx + i0..c * nx + i0 + live]);
        }
        for a in self.acc.iter_mut() {
            a[dims.clone()].fill(0.0);
        }
        let sqrt_dim = sqrt(head_dim as f32);
        let mut max = [f32::NEG_INFINITY; QUERY_BLOCK];
        let mut total = [0.0f32; QUERY_BLOCK];
        let mut j0 = 0;
        while j0 < shape.ns {
            let len = SOURCE_BLOCK.min(shape.ns - j0);
            score_tiles::<F, L>(
                fma,
                shape,
                h,
                &self.queries,
                k,
                j0,
                len,
                sqrt_dim,
                &mut self.scores,
            );
            for b in 0..QUERY_BLOCK {
                let s = &mut self.scores[b][h][..len];
                let block_max = lane_max(s);
                if block_max > max[b] {
                    let correction = softmax_weight(max[b] - block_max);
                    total[b] *= correction;
                    for a in &mut self.acc[b][dims.clone()] {
                        *a *= correction;
                    }
                    max[b] = block_max;
                }
                for x in s.iter_mut() {
                    *x = softmax_weight(*x - max[b]);
                }
                total[b] += lane_sum(s);
            }
            message_tiles::<F, L>(fma, shape, h, &self.scores, v, j0, len, &mut self.acc);
            j0 += len;
        }
        for e in 0..head_dim {
            let c = h + heads * e;
            for b in 0..live {
                q[c * nx + i0 + b] = self.acc[b][dims.start + e] / total[b];
            }
        }
    }
}

/// `scores[b][h][t] = (q_b . k_{j0 + t}) / sqrt(head_dim)` over the dimensions of head
/// `h`, for the `len` sources from `j0`.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn score_tiles<F: Fma, const L: usize>(
    fma: F,
    shape: &AttentionShape,
    h: usize,
    queries: &[[f32; QUERY_BLOCK]; MAX_FEATURE_DIM],
    k: &[f32],
    j0: usize,
    len: usize,
    sqrt_dim: f32,
    scores: &mut [[[f32; SOURCE_BLOCK]; MAX_HEADS]; QUERY_BLOCK],
) {
    let mut t0 = 0;
    while t0 < len {
        let width = L.min(len - t0);
        if width == L {
            let tile = score_tile::<F, true, L>(fma, shape, h, queries, k, j0 + t0, width);
            for (b, row) in tile.iter().enumerate() {
                if let Some(out) = scores[b][h][t0..].first_chunk_mut::<L>() {
                    *out = row.map(|x| x / sqrt_dim);
                }
            }
        } else {
            let tile = score_tile::<F, false, L>(fma, shape, h, queries, k, j0 + t0, width);
            for (b, row) in tile.iter().enumerate() {
                for (l, &x) in row[..width].iter().enumerate() {
                    scores[b][h][t0 + l] = x / sqrt_dim;
                }
            }
        }
        t0 += width;
    }
}

/// Dot products of the block's queries with `width` keys from `j`, head `h`.
#[inline(always)]
fn score_tile<F: Fma, const FULL: bool, const L: usize>(
    fma: F,
    shape: &AttentionShape,
    h: usize,
    queries: &[[f32; QUERY_BLOCK]; MAX_FEATURE_DIM],
    k: &[f32],
    j: usize,
    width: usize,
) -> [[f32; L]; QUERY_BLOCK] {
    let mut tile = [[0.0f32; L]; QUERY_BLOCK];
    for e in 0..shape.head_dim {
        let c = h + shape.heads * e;
        let key = lanes::<FULL, L>(k, c * shape.ns + j, width);
        for (row, &qb) in tile.iter_mut().zip(&queries[c]) {
            fma.add_products(qb, &key, row);
        }
    }
    tile
}

/// `acc[b][h dims] += sum_t p[b][h][t] v_{j0 + t}[h dims]` over the `len` sources from
/// `j0` (the block's sum first, then added to the running message).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn message_tiles<F: Fma, const L: usize>(
    fma: F,
    shape: &AttentionShape,
    h: usize,
    p: &[[[f32; SOURCE_BLOCK]; MAX_HEADS]; QUERY_BLOCK],
    v: &[f32],
    j0: usize,
    len: usize,
    acc: &mut [[f32; MAX_FEATURE_DIM]; QUERY_BLOCK],
) {
    let head_dim = shape.head_dim;
    let mut e0 = 0;
    while e0 < head_dim {
        let width = L.min(head_dim - e0);
        let first = h * head_dim + e0;
        if width == L {
            let tile = message_tile::<F, true, L>(fma, shape, h, p, v, j0, len, first, width);
            for (a, row) in acc.iter_mut().zip(&tile) {
                if let Some(lanes) = a[first..].first_chunk_mut::<L>() {
                    fma.add_lanes(row, lanes);
                }
            }
        } else {
            let tile = message_tile::<F, false, L>(fma, shape, h, p, v, j0, len, first, width);
            for (a, row) in acc.iter_mut().zip(&tile) {
                for (x, &y) in a[first..first + width].iter_mut().zip(row) {
                    *x += y;
                }
            }
        }
        e0 += width;
    }
}

/// The block's weighted sum of `width` value channels from `first` (head-major order).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn message_tile<F: Fma, const FULL: bool, const L: usize>(
    fma: F,
    shape: &AttentionShape,
    h: usize,
    p: &[[[f32; SOURCE_BLOCK]; MAX_HEADS]; QUERY_BLOCK],
    v: &[f32],
    j0: usize,
    len: usize,
    first: usize,
    width: usize,
) -> [[f32; L]; QUERY_BLOCK] {
    let d = shape.heads * shape.head_dim;
    let mut tile = [[0.0f32; L]; QUERY_BLOCK];
    for t in 0..len {
        let value = lanes::<FULL, L>(v, (j0 + t) * d + first, width);
        for (row, pb) in tile.iter_mut().zip(p) {
            fma.add_products(pb[h][t], &value, row);
        }
    }
    tile
}

/// `x[at..at + width]` zero-padded to `L` values (`width == L` when `FULL`);
/// zeros past the end of `x`.
#[inline(always)]
fn lanes<const FULL: bool, const L: usize>(x: &[f32], at: usize, width: usize) -> [f32; L] {
    let src = x.get(at..).unwrap_or(&[]);
    let mut out = [0.0f32; L];
    if FULL {
        if let Some(values) = src.first_chunk::<L>() {
            out = *values;
        }
    } else {
        for (o, &v) in out[..width].iter_mut().zip(src) {
            *o = v;
        }
    }
    out
}

/// Below this, a softmax term `exp(x - max)` (at most `1.6e-28` of the largest term, far
/// below f32 resolution of the sum, which is at least 1) counts as 0: no subnormal
/// products, which are slow on common CPUs, and the same result.
const SOFTMAX_CUTOFF: f32 = -64.0;

/// `exp(x)` for `x >= SOFTMAX_CUTOFF`, 0 below (`x <= 0` is the offset from the maximum).
#[inline(always)]
fn softmax_weight(x: f32) -> f32 {
    let e = exp(x);
    if x < SOFTMAX_CUTOFF {
        0.0
    } else {
        e
    }
}

/// Partial sums of [`lane_sum`]: fixed on every target (not [`LANES`], the register tile
/// width), so that the softmax totals have the same bits everywhere.
const SUM_LANES: usize = 8;

/// The largest of `values` (`-inf` for none; NaNs skipped), over [`SUM_LANES`] interleaved
/// lanes so that it vectorises. The same value as a fold in order: `max` is exact and
/// order-free up to the sign of a zero maximum, which only reaches `exp(x - max)`, where it
/// does not change the result.
#[inline(always)]
fn lane_max(values: &[f32]) -> f32 {
    let mut lanes = [f32::NEG_INFINITY; SUM_LANES];
    let mut chunks = values.chunks_exact(SUM_LANES);
    for chunk in &mut chunks {
        for l in 0..SUM_LANES {
            lanes[l] = lanes[l].max(chunk[l]);
        }
    }
    let rest = chunks.remainder().iter();
    rest.chain(&lanes).fold(f32::NEG_INFINITY, |m, &x| m.max(x))
}

/// Sum of the values in [`SUM_LANES`] interleaved partial sums, then across them in order.
#[inline(always)]
fn lane_sum(values: &[f32]) -> f32 {
    let mut lanes = [0.0f32; SUM_LANES];
    let mut chunks = values.chunks_exact(SUM_LANES);
    for chunk in &mut chunks {
        for l in 0..SUM_LANES {
            lanes[l] += chunk[l];
        }
    }
    for (l, &x) in chunks.remainder().iter().enumerate() {
        lanes[l] += x;
    }
    lanes.iter().sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The graph equals a full sort of each point's distances by (distance, index), on
    /// sets of every size around the distance blocks, with repeated points (ties) and
    /// far-away points.
    #[test]
    fn knn_graph_equals_a_full_sort() {
        extern crate std;
        use std::vec::Vec;
        let mut state = 7u64;
        let mut next = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 40) as f32 / (1u64 << 24) as f32 - 0.5
        };
        for n in [2, 3, 11, 16, 17, 63, 64, 65, 130, 300] {
            let mut points: Vec<[f32; 2]> = (0..n).map(|_| [next(), next()]).collect();
            for i in (0..n).step_by(7) {
                points[n - 1 - i / 7] = points[i];
            }
            points[n / 2] = [1e20, -1e20];
            for knn in [1, 4, 10, MAX_KNN] {
                let k = neighbour_count(knn, n);
                let mut graph = std::vec![[0u16; MAX_KNN]; n];
                knn_graph(&points, k, &mut graph);
                for (i, a) in points.iter().enumerate() {
                    let mut d = [0.0f32; 1];
                    let mut order: Vec<(f32, usize)> = points
                        .iter()
                        .enumerate()
                        .map(|(j, b)| {
                            squared_distances(a, core::slice::from_ref(b), &mut d);
                            (d[0], j)
                        })
                        .collect();
                    order.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.cmp(&y.1)));
                    let expected: Vec<u16> = order[1..=k].iter().map(|&(_, j)| j as u16).collect();
                    assert_eq!(graph[i][..k], expected[..], "n {n}, k {k}, point {i}");
                }
            }
        }
    }

    #[test]
    fn knn_graph_on_a_line_with_a_tie() {
        // x = 0, 1, 2, 4: ties (1: 0 and 2; 2: 0 and 3) go to the lower index.
        let pts = [[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [4.0, 0.0]];
        let mut graph = [[0u16; MAX_KNN]; 4];
        knn_graph(&pts, 2, &mut graph);
        assert_eq!(graph[0][..2], [1, 2]);
        assert_eq!(graph[1][..2], [0, 2]);
        assert_eq!(graph[2][..2], [1, 0]); // 0 and 3 tie at distance 2
        assert_eq!(graph[3][..2], [2, 1]);
    }

    #[test]
    fn neighbour_count_follows_the_reference() {
        assert_eq!(neighbour_count(10, 8), 7);
        assert_eq!(neighbour_count(10, 100), 10);
    }

    /// With every score equal, attention returns the mean of the values per head.
    #[test]
    fn uniform_attention_averages_values() {
        let d = 4;
        let mut q = [0.0f32; 4]; // one query, zero => all scores 0
        let k = [1.0f32; 3 * 4];
        let v: [f32; 12] = core::array::from_fn(|i| i as f32);
        let shape = AttentionShape {
            heads: 2,
            head_dim: 2,
            nx: 1,
            ns: 3,
        };
        attend(&shape, &mut q, &k, &v);
        for (c, &got) in q.iter().enumerate().take(d) {
            let at = head_major(c, 2, 2);
            let mean = (v[at] + v[4 + at] + v[8 + at]) / 3.0;
            assert!((got - mean).abs() < 1e-6, "{c}: {got} vs {mean}");
        }
    }

    /// Online softmax over several source blocks, a partial query block and a head
    /// dimension that is not a multiple of the tile width equal the direct softmax.
    #[test]
    fn streamed_softmax_matches_direct_softmax() {
        const D: usize = 6;
        const NX: usize = 6;
        const NS: usize = 70;
        let (heads, head_dim) = (2, 3);
        let query: [f32; D * NX] = core::array::from_fn(|i| libm::sinf(i as f32 * 0.71));
        let k: [f32; D * NS] = core::array::from_fn(|i| 2.0 * libm::sinf(i as f32 * 0.37));
        let v_channels: [f32; D * NS] = core::array::from_fn(|i| libm::cosf(i as f32 * 0.11));
        let mut v = [0.0f32; D * NS];
        for c in 0..D {
            for j in 0..NS {
                v[j * D + head_major(c, heads, head_dim)] = v_channels[c * NS + j];
            }
        }
        let mut q = query;
        let shape = AttentionShape {
            heads,
            head_dim,
            nx: NX,
            ns: NS,
        };
        attend(&shape, &mut q, &k, &v);
        for i in 0..NX {
            for c in 0..D {
                let h = c % heads;
                let s: [f64; NS] = core::array::from_fn(|j| {
                    (h..D)
                        .step_by(heads)
                        .map(|cc| f64::from(query[cc * NX + i]) * f64::from(k[cc * NS + j]))
                        .sum::<f64>()
                        / libm::sqrt(head_dim as f64)
                });
                let m = s.iter().cloned().fold(f64::MIN, f64::max);
                let z: f64 = s.iter().map(|&x| libm::exp(x - m)).sum();
                let expected: f64 = (0..NS)
                    .map(|j| libm::exp(s[j] - m) / z * f64::from(v_channels[c * NS + j]))
                    .sum();
                let got = f64::from(q[c * NX + i]);
                assert!(
                    (got - expected).abs() < 1e-5,
                    "{i} {c}: {got} vs {expected}"
                );
            }
        }
    }

    /// The factored edge statistics equal the ones of the explicit edge list, and a channel
    /// gives the same bits alone or in a group, with its edge values gathered twice or kept.
    #[test]
    fn edge_channels_match_explicit_edges() {
        let a = [0.5f32, -1.0, 2.0, 0.25, 1.5, 0.0, -0.75, 3.0];
        let b = [1.0f32, 3.0, -2.0, 0.5, -1.25, 0.125, 2.5, -0.5];
        let mut graph = [[0u16; MAX_KNN]; 4];
        for (i, g) in graph.iter_mut().enumerate() {
            g[0] = ((i + 1) % 4) as u16;
            g[1] = ((i + 2) % 4) as u16;
        }
        let finish = |channels: core::ops::Range<usize>, keep: bool| {
            let (first, g) = (channels.start, channels.len());
            let mut out = a;
            let mut maxima = [0.0; 8];
            let mut point_major = [0.0; 8];
            let mut edges = [0.0; 16];
            let group = EdgeChannels {
                a: &mut out[4 * first..4 * (first + g)],
                b: &b[4 * first..4 * (first + g)],
                graph: &graph,
                k: 2,
                maxima: &mut maxima[..4 * g],
                point_major: &mut point_major[..4 * g],
                edges: if keep { &mut edges[..8 * g] } else { &mut [] },
            };
            let portable = crate::nn::dispatch::Portable;
            match g {
                1 => group.finish::<_, 1>(portable),
                _ => group.finish::<_, 2>(portable),
            }
            out
        };
        for channel in 0..2 {
            let (a, b) = (&a[4 * channel..][..4], &b[4 * channel..][..4]);
            let mut normed = [0.0f32; 8];
            for i in 0..4 {
                for t in 0..2 {
                    normed[i * 2 + t] = a[i] + b[usize::from(graph[i][t])];
                }
            }
            crate::nn::instance_norm(&mut normed);
            let alone = finish(channel..channel + 1, false);
            for i in 0..4 {
                let at = 4 * channel + i;
                let expected = leaky_relu(normed[i * 2]).max(leaky_relu(normed[i * 2 + 1]));
                assert!((alone[at] - expected).abs() < 1e-6, "{at}");
                for other in [
                    finish(channel..channel + 1, true),
                    finish(0..2, false),
                    finish(0..2, true),
                ] {
                    assert_eq!(alone[at].to_bits(), other[at].to_bits(), "{at}");
                }
            }
        }
    }

    /// A self layer gives the same bits whether its rows and point blocks go through the
    /// smallest scratch it accepts (chunks of `ROW_BLOCK` rows, one point per fusing
    /// block) or through a spare buffer that holds every row at once.
    #[test]
    fn self_layer_output_does_not_depend_on_the_scratch_size() {
        extern crate std;
        use crate::nn::ROW_BLOCK;
        use crate::weights::{tests_support, Model};
        let mut buf = std::vec![0u8; 64 * 1024];
        let len = tests_support::blob(&tests_support::TINY, 5, &mut buf);
        let model = Model::from_bytes(&buf[..len]).expect("valid blob");
        let (d, n) = (usize::from(tests_support::TINY.feature_dim), 40);
        let points: std::vec::Vec<[f32; 2]> = (0..n)
            .map(|i| [(i as f32 * 0.37).sin(), (i as f32 * 0.73).cos()])
            .collect();
        let k = neighbour_count(usize::from(tests_support::TINY.knn), n);
        let mut graph = std::vec![[0u16; MAX_KNN]; n];
        knn_graph(&points, k, &mut graph);
        let input: std::vec::Vec<f32> = (0..d * n).map(|i| (i as f32 * 0.11).sin()).collect();
        let run = |spare: &mut [f32]| {
            let (mut x, mut x1, mut x2) = (
                input.clone(),
                std::vec![0.0; d * n],
                std::vec![0.0; 2 * d * n],
            );
            let (mut rows, mut fused) = (std::vec![0.0; (ROW_BLOCK + 1) * n], std::vec![0.0; d]);
            let scratch = SelfScratch {
                x1: &mut x1,
                x2: &mut x2,
                rows: &mut rows,
                fused: &mut fused,
                spare,
            };
            self_layer(
                &model.self_layers[0],
                &graph,
                k,
                &mut x,
                n,
                scratch,
                &mut (),
            );
            x
        };
        let small = run(&mut []);
        let large = run(&mut std::vec![0.0; 2 * d * n]);
        assert!(small.iter().all(|v| v.is_finite()));
        assert_eq!(
            small
                .iter()
                .map(|v| v.to_bits())
                .collect::<std::vec::Vec<_>>(),
            large
                .iter()
                .map(|v| v.to_bits())
                .collect::<std::vec::Vec<_>>()
        );
    }
}
