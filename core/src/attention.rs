//! Attention (supp. "Attention", eq. 4-8): EdgeConv self attention on a k-nearest-neighbour
//! graph in bearing coordinate space, and multi-head cross attention between the sets.
//!
//! Self attention never builds the `N x K x 2C` edge tensor: the edge convolution is
//! factored per point, `W [f_i, f_j - f_i] = (Wa - Wb) f_i + Wb f_j`, and because instance
//! norm has no affine parameters and leaky ReLU is monotonic, the max over neighbours
//! commutes with both: only per-channel statistics over the `N x K` edges and the per-point
//! maximum of the neighbour term are kept. Cross attention streams the source points with
//! an online softmax, so no `N x N x heads` score buffer exists.

use crate::nn::linear::{accumulate, chunk_rows, store, store_point_major};
use crate::nn::{exp, instance_norm, leaky_relu, linear, relu, Input, Moments};
use crate::weights::{CrossLayerWeights, Linear, SelfLayerWeights, MAX_FEATURE_DIM, MAX_KNN};

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
    let mut best = [(0.0f32, 0u16); MAX_KNN + 1];
    for (a, neighbours) in points.iter().zip(graph.iter_mut()) {
        let norm_a = a[0] * a[0] + a[1] * a[1];
        let mut count = 0;
        for (j, b) in points.iter().enumerate() {
            let dot = a[0] * b[0] + a[1] * b[1];
            let norm_b = b[0] * b[0] + b[1] * b[1];
            let dist = (-2.0 * dot + norm_a + norm_b).max(1e-12);
            if count == k + 1 && dist >= best[k].0 {
                continue;
            }
            let mut at = count.min(k);
            while at > 0 && best[at - 1].0 > dist {
                best[at] = best[at - 1];
                at -= 1;
            }
            best[at] = (dist, j as u16);
            count = (count + 1).min(k + 1);
        }
        for (slot, &(_, j)) in neighbours.iter_mut().zip(&best[1..count]) {
            *slot = j;
        }
    }
}

/// Scratch of one self-attention layer on a set of `n` points.
pub struct SelfScratch<'s> {
    /// `x1`, `d x n`.
    pub x1: &'s mut [f32],
    /// `x2`, `2d x n`.
    pub x2: &'s mut [f32],
    /// At least `ROW_BLOCK x n` values: neighbour terms of a chunk of channels.
    pub rows: &'s mut [f32],
    /// `n` per-point maxima.
    pub maxima: &'s mut [f32],
    /// `d x FUSE_BLOCK` output block of the fusing conv.
    pub fused: &'s mut [f32],
}

/// One EdgeConv self-attention layer (supp. eq. 4-5) on `x` (`d x n`), in place: the output
/// replaces the descriptor.
pub fn self_layer(
    w: &SelfLayerWeights<'_>,
    graph: &[Neighbours],
    k: usize,
    x: &mut [f32],
    n: usize,
    s: SelfScratch<'_>,
) {
    let d = w.fuse.rows();
    edge_conv(
        &w.edge1_centre,
        &w.edge1_neighbour,
        &Input::one(x, d, n),
        graph,
        k,
        s.x1,
        s.rows,
        s.maxima,
    );
    edge_conv(
        &w.edge2_centre,
        &w.edge2_neighbour,
        &Input::one(s.x1, d, n),
        graph,
        k,
        s.x2,
        s.rows,
        s.maxima,
    );
    let mut b0 = 0;
    while b0 < n {
        let len = FUSE_BLOCK.min(n - b0);
        let input = Input::parts([&*x, &*s.x1, &*s.x2], [d, d, 2 * d], n).columns(b0, len);
        linear(&w.fuse, &input, 0..d, |r, i0, v| {
            store(s.fused, len, r, i0, v)
        });
        for r in 0..d {
            x[r * n + b0..r * n + b0 + len].copy_from_slice(&s.fused[r * len..(r + 1) * len]);
        }
        b0 += len;
    }
    for row in x[..d * n].chunks_exact_mut(n) {
        instance_norm(row);
        for v in row.iter_mut() {
            *v = leaky_relu(*v);
        }
    }
}

/// `out = max_k LeakyReLU(IN2d(W [x_i, x_j - x_i]))` over the `k` neighbours, with the
/// instance norm statistics over all `n x k` edges of each channel.
#[allow(clippy::too_many_arguments)]
fn edge_conv(
    centre: &Linear<'_>,
    neighbour: &Linear<'_>,
    input: &Input<'_>,
    graph: &[Neighbours],
    k: usize,
    out: &mut [f32],
    rows: &mut [f32],
    maxima: &mut [f32],
) {
    let n = input.points();
    let channels = centre.rows();
    let chunk = chunk_rows(centre.cols(), rows.len(), n);
    let mut r0 = 0;
    while r0 < channels {
        let r1 = (r0 + chunk).min(channels);
        linear(centre, input, r0..r1, |r, i0, v| store(out, n, r, i0, v));
        linear(neighbour, input, r0..r1, |r, i0, v| {
            store(rows, n, r - r0, i0, v)
        });
        for r in r0..r1 {
            finish_edge_channel(
                &mut out[r * n..(r + 1) * n],
                &rows[(r - r0) * n..(r - r0 + 1) * n],
                &graph[..n],
                k,
                &mut maxima[..n],
            );
        }
        r0 = r1;
    }
}

/// Turns the centre term `a` of one channel into the layer output, given the neighbour
/// term `b`: edge values `a_i + b_j`, their mean and variance over all edges, then
/// `LeakyReLU((a_i + max_j b_j - mean) / std)`.
fn finish_edge_channel(
    a: &mut [f32],
    b: &[f32],
    graph: &[Neighbours],
    k: usize,
    maxima: &mut [f32],
) {
    let mut moments = Moments::default();
    for ((&ai, neighbours), m) in a.iter().zip(graph).zip(maxima.iter_mut()) {
        let mut best = f32::NEG_INFINITY;
        for &j in &neighbours[..k] {
            let bj = b[usize::from(j)];
            moments.add(ai + bj);
            best = best.max(bj);
        }
        *m = best;
    }
    let mean = moments.mean();
    let mut deviations = 0.0f64;
    for (&ai, neighbours) in a.iter().zip(graph) {
        for &j in &neighbours[..k] {
            let e = f64::from(ai + b[usize::from(j)]) - mean;
            deviations += e * e;
        }
    }
    let (mean, inv_std) = moments.normalizer(deviations);
    for (ai, &m) in a.iter_mut().zip(maxima.iter()) {
        *ai = leaky_relu((*ai + m - mean) * inv_std);
    }
}

/// Multi-head cross attention with message MLP (supp. eq. 6-8), in place:
/// `x += MLP([x, merge(attention(q(x), k(src), v(src)))])`. Channel `c` belongs to head
/// `c % heads`. `pool` holds at least `3 x d x max(nx, ns)` values of scratch.
pub fn cross_layer(
    w: &CrossLayerWeights<'_>,
    heads: usize,
    x: &mut [f32],
    nx: usize,
    src: &[f32],
    ns: usize,
    pool: &mut [f32],
) {
    let d = w.query.rows();
    let slot = d * nx.max(ns);
    let (front, values) = pool.split_at_mut(2 * slot);
    {
        let (queries, keys) = front.split_at_mut(slot);
        let source = Input::one(src, d, ns);
        linear(&w.key, &source, 0..d, |r, i0, v| {
            store_point_major(keys, d, r, i0, v)
        });
        linear(&w.value, &source, 0..d, |r, i0, v| {
            store_point_major(values, d, r, i0, v)
        });
        linear(&w.query, &Input::one(x, d, nx), 0..d, |r, i0, v| {
            store_point_major(queries, d, r, i0, v)
        });
        attend(heads, queries, nx, keys, values, ns, d);
        // Messages to channel-major (into the key slot), then merge (into the value slot).
        for (i, message) in queries[..nx * d].chunks_exact(d).enumerate() {
            for (c, &m) in message.iter().enumerate() {
                keys[c * nx + i] = m;
            }
        }
        linear(&w.merge, &Input::one(keys, d, nx), 0..d, |r, i0, v| {
            store(values, nx, r, i0, v)
        });
    }
    let hidden = front;
    let h = w.mlp_hidden.rows();
    linear(
        &w.mlp_hidden,
        &Input::two((x, d), (values, d), nx),
        0..h,
        |r, i0, v| store(hidden, nx, r, i0, v),
    );
    for row in hidden[..h * nx].chunks_exact_mut(nx) {
        instance_norm(row);
        for v in row.iter_mut() {
            *v = relu(*v);
        }
    }
    linear(&w.mlp_out, &Input::one(hidden, h, nx), 0..d, |r, i0, v| {
        accumulate(x, nx, r, i0, v)
    });
}

/// Source points per block of the online softmax.
const SOURCE_BLOCK: usize = 64;

/// Replaces each query (point-major `nx x d`) by its attention message over the source
/// keys and values (point-major `ns x d`).
fn attend(heads: usize, q: &mut [f32], nx: usize, k: &[f32], v: &[f32], ns: usize, d: usize) {
    match heads {
        1 => attend_heads::<1, 8>(q, nx, k, v, ns, d),
        2 => attend_heads::<2, 16>(q, nx, k, v, ns, d),
        3 => attend_heads::<3, 24>(q, nx, k, v, ns, d),
        4 => attend_heads::<4, 32>(q, nx, k, v, ns, d),
        5 => attend_heads::<5, 40>(q, nx, k, v, ns, d),
        6 => attend_heads::<6, 48>(q, nx, k, v, ns, d),
        7 => attend_heads::<7, 56>(q, nx, k, v, ns, d),
        _ => attend_heads::<8, 64>(q, nx, k, v, ns, d),
    }
}

/// Repeats the per-head values over `L` channels (channel `c` belongs to head `c % H`).
#[inline(always)]
fn spread<const H: usize, const L: usize>(per_head: &[f32; H]) -> [f32; L] {
    let mut out = [0.0f32; L];
    for (l, o) in out.iter_mut().enumerate() {
        *o = per_head[l % H];
    }
    out
}

/// Scaled dot-product attention with `H` interleaved heads (head dimension `d / H`),
/// softmax over the source points computed online block by block (eq. 6-7). Channels
/// are processed in runs of `L = 8 H` so that every lane belongs to a fixed head: the dot
/// products accumulate in `L` lanes summed per head at the end, and the message update
/// is an element-wise multiply-add with the per-head weights spread over the lanes.
fn attend_heads<const H: usize, const L: usize>(
    q: &mut [f32],
    nx: usize,
    k: &[f32],
    v: &[f32],
    ns: usize,
    d: usize,
) {
    let sqrt_dim = libm::sqrtf((d / H) as f32);
    let main = d - d % L;
    let mut query = [0.0f32; MAX_FEATURE_DIM];
    let mut acc = [0.0f32; MAX_FEATURE_DIM];
    let mut scores = [[0.0f32; H]; SOURCE_BLOCK];
    for qi in q[..nx * d].chunks_exact_mut(d) {
        query[..d].copy_from_slice(qi);
        acc[..d].fill(0.0);
        let mut max = [f32::NEG_INFINITY; H];
        let mut total = [0.0f32; H];
        let mut j0 = 0;
        while j0 < ns {
            let len = SOURCE_BLOCK.min(ns - j0);
            let mut block_max = max;
            for (t, s) in scores[..len].iter_mut().enumerate() {
                let kj = &k[(j0 + t) * d..(j0 + t + 1) * d];
                let mut lanes = [0.0f32; L];
                for (qc, kc) in query[..main]
                    .chunks_exact(L)
                    .zip(kj[..main].chunks_exact(L))
                {
                    for l in 0..L {
                        lanes[l] += qc[l] * kc[l];
                    }
                }
                let mut dot = [0.0f32; H];
                for (l, &x) in lanes.iter().enumerate() {
                    dot[l % H] += x;
                }
                for c in main..d {
                    dot[c % H] += query[c] * kj[c];
                }
                for h in 0..H {
                    s[h] = dot[h] / sqrt_dim;
                    block_max[h] = block_max[h].max(s[h]);
                }
            }
            if block_max != max {
                let mut correction = [0.0f32; H];
                for h in 0..H {
                    correction[h] = exp(max[h] - block_max[h]);
                    total[h] *= correction[h];
                }
                scale_spread::<H, L>(&mut acc[..d], &correction, None);
                max = block_max;
            }
            for (t, s) in scores[..len].iter().enumerate() {
                let vj = &v[(j0 + t) * d..(j0 + t + 1) * d];
                let mut p = [0.0f32; H];
                for h in 0..H {
                    p[h] = exp(s[h] - max[h]);
                    total[h] += p[h];
                }
                scale_spread::<H, L>(&mut acc[..d], &p, Some(vj));
            }
            j0 += len;
        }
        for (c, (o, &a)) in qi.iter_mut().zip(&acc[..d]).enumerate() {
            *o = a / total[c % H];
        }
    }
}

/// `acc[c] *= w[c % H]` (no `values`) or `acc[c] += w[c % H] * values[c]`.
#[inline(always)]
fn scale_spread<const H: usize, const L: usize>(
    acc: &mut [f32],
    w: &[f32; H],
    values: Option<&[f32]>,
) {
    let d = acc.len();
    let main = d - d % L;
    let pattern = spread::<H, L>(w);
    match values {
        Some(values) => {
            for (a, x) in acc[..main]
                .chunks_exact_mut(L)
                .zip(values[..main].chunks_exact(L))
            {
                for l in 0..L {
                    a[l] += pattern[l] * x[l];
                }
            }
            for c in main..d {
                acc[c] += w[c % H] * values[c];
            }
        }
        None => {
            for a in acc[..main].chunks_exact_mut(L) {
                for l in 0..L {
                    a[l] *= pattern[l];
                }
            }
            for c in main..d {
                acc[c] *= w[c % H];
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
        attend(2, &mut q, 1, &k, &v, 3, d);
        for c in 0..d {
            let mean = (v[c] + v[4 + c] + v[8 + c]) / 3.0;
            assert!((q[c] - mean).abs() < 1e-6, "{c}: {} vs {mean}", q[c]);
        }
    }

    /// Online softmax over several source blocks equals the direct softmax.
    #[test]
    fn streamed_softmax_matches_direct_softmax() {
        let (d, ns) = (4, 70);
        let query: [f32; 4] = [0.3, -0.2, 0.5, 0.1];
        let k: [f32; 280] = core::array::from_fn(|i| libm::sinf(i as f32 * 0.37));
        let v: [f32; 280] = core::array::from_fn(|i| libm::cosf(i as f32 * 0.11));
        let mut q = query;
        attend(4, &mut q, 1, &k, &v, ns, d);
        for c in 0..d {
            let s: [f32; 70] = core::array::from_fn(|j| query[c] * k[j * d + c]);
            let m = s.iter().cloned().fold(f32::MIN, f32::max);
            let z: f32 = s.iter().map(|&x| libm::expf(x - m)).sum();
            let expected: f32 = (0..ns)
                .map(|j| libm::expf(s[j] - m) / z * v[j * d + c])
                .sum();
            assert!(
                (q[c] - expected).abs() < 1e-5,
                "{c}: {} vs {expected}",
                q[c]
            );
        }
    }

    /// The factored edge statistics equal the ones of the explicit edge list.
    #[test]
    fn edge_channel_matches_explicit_edges() {
        let a = [0.5f32, -1.0, 2.0, 0.25];
        let b = [1.0f32, 3.0, -2.0, 0.5];
        let mut graph = [[0u16; MAX_KNN]; 4];
        for (i, g) in graph.iter_mut().enumerate() {
            g[0] = ((i + 1) % 4) as u16;
            g[1] = ((i + 2) % 4) as u16;
        }
        let mut edges = [0.0f32; 8];
        for i in 0..4 {
            for t in 0..2 {
                edges[i * 2 + t] = a[i] + b[usize::from(graph[i][t])];
            }
        }
        let mut normed = edges;
        instance_norm(&mut normed);
        let mut out = a;
        let mut maxima = [0.0; 4];
        finish_edge_channel(&mut out, &b, &graph, 2, &mut maxima);
        for i in 0..4 {
            let expected = leaky_relu(normed[i * 2]).max(leaky_relu(normed[i * 2 + 1]));
            assert!((out[i] - expected).abs() < 1e-6, "{i}");
        }
    }
}
