//! Matching (supp. "Sinkhorn Matching", eq. 9-10): distance cost between L2-normalised
//! descriptors with a dustbin row and column, log-domain Sinkhorn, mutual assignment.
//!
//! The cost matrix is the only `N x N` buffer of the matcher; its element type is a
//! [`PlanScalar`] (f32 or f16). Rows are 3D points, columns 2D keypoints, as in the
//! reference; the dustbin row and column are the constant bin score and are not stored.
//! The transport plan `P = exp((-C + u_i + v_j) / eps)` is never stored either: it is
//! evaluated on demand from the cost and the potentials `u`, `v`.

use crate::nn::dispatch::{f16_to_f32, with_fma, Fma, Kernel};
use crate::nn::linear::linear_with;
use crate::nn::operands::WeightRows;
use crate::nn::{exp, sqrt, Input, COL_BLOCK};

/// Storage type of the cost matrix.
pub trait PlanScalar: bytemuck::Pod {
    /// Zero, for a `const` initialised workspace.
    const ZERO: Self;
    /// Whether Sinkhorn takes each column's sum from the row pass's terms
    /// ([`sinkhorn`]): one exponential per entry and iteration instead of two, not the
    /// reference's bits. Off for f32, the path that reproduces the reference.
    const COLUMNS_FROM_ROWS: bool;
    /// Reads storage back as f32.
    fn to_f32(self) -> f32;
    /// A stored row as f32: the row itself for f32, converted into `buf` (with the CPU's
    /// conversion instruction where `fma` has one) otherwise.
    fn row_f32<'a, F: Fma>(fma: F, row: &'a [Self], buf: &'a mut [f32]) -> &'a [f32];
    /// `values` rounded into storage (to nearest, ties to even), into `out` (as long), with
    /// the CPU's conversion instruction where `fma` has one.
    fn store_row<F: Fma>(fma: F, values: &[f32], out: &mut [Self]);
}

impl PlanScalar for f32 {
    const ZERO: Self = 0.0;
    const COLUMNS_FROM_ROWS: bool = false;
    #[inline(always)]
    fn to_f32(self) -> f32 {
        self
    }
    #[inline(always)]
    fn row_f32<'a, F: Fma>(_fma: F, row: &'a [Self], _buf: &'a mut [f32]) -> &'a [f32] {
        row
    }
    #[inline(always)]
    fn store_row<F: Fma>(_fma: F, values: &[f32], out: &mut [Self]) {
        out.copy_from_slice(values);
    }
}

impl PlanScalar for half::f16 {
    const ZERO: Self = half::f16::ZERO;
    const COLUMNS_FROM_ROWS: bool = true;
    #[inline(always)]
    fn to_f32(self) -> f32 {
        f16_to_f32(self.to_bits())
    }
    #[inline(always)]
    fn row_f32<'a, F: Fma>(fma: F, row: &'a [Self], buf: &'a mut [f32]) -> &'a [f32] {
        let out = &mut buf[..row.len()];
        fma.widen_f16(bytemuck::cast_slice(row), out);
        out
    }
    #[inline(always)]
    fn store_row<F: Fma>(fma: F, values: &[f32], out: &mut [Self]) {
        fma.narrow_f16(values, bytemuck::cast_slice_mut(out));
    }
}

/// Sinkhorn hyper-parameters (from the model configuration).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SinkhornParams {
    /// Entropic regularisation.
    pub eps: f32,
    /// Most iterations.
    pub max_iters: usize,
    /// Stop once `||u - u_prev||_2 < stop`.
    pub stop: f32,
    /// Dustbin cost.
    pub bin_score: f32,
}

/// The rows (points) of a channel-major matrix seen as weight rows: `rows()` points of
/// `cols()` channels. Used to compute all pairwise dot products with the linear kernel.
struct PointRows<'a> {
    x: &'a [f32],
    n: usize,
    channels: usize,
}

impl WeightRows for PointRows<'_> {
    fn rows(&self) -> usize {
        self.n
    }
    fn cols(&self) -> usize {
        self.channels
    }
    fn decode(&self, row: usize, out: &mut [f32]) {
        for (c, o) in out.iter_mut().enumerate() {
            *o = self.x[c * self.n + row];
        }
    }
    fn scale(&self, _row: usize) -> f32 {
        1.0
    }
    fn bias(&self, _row: usize) -> f32 {
        0.0
    }
    fn int8_row(&self, _row: usize) -> Option<&[u8]> {
        None
    }
}

/// Squared norm of every point of a channel-major `channels x n` matrix.
fn squared_norms(x: &[f32], channels: usize, n: usize, out: &mut [f32]) {
    out[..n].fill(0.0);
    for row in x[..channels * n].chunks_exact(n) {
        for (s, &v) in out[..n].iter_mut().zip(row) {
            *s += v * v;
        }
    }
}

/// Cost `C[i][j] = sqrt(max(|a_j|^2 - 2 b_i.a_j + |b_i|^2, 1e-30))` between 3D descriptor
/// `b_i` (rows) and 2D descriptor `a_j` (columns), into `plan` (`n3 x n2`, row-major).
/// `norms` holds `n2 + n3` values of scratch.
#[allow(clippy::too_many_arguments)]
pub fn cost_matrix<S: PlanScalar>(
    desc3: &[f32],
    n3: usize,
    desc2: &[f32],
    n2: usize,
    channels: usize,
    plan: &mut [S],
    norms: &mut [f32],
) {
    with_fma(CostMatrix {
        desc3,
        n3,
        desc2,
        n2,
        channels,
        plan,
        norms,
    });
}

/// The arguments of one [`cost_matrix`] call.
struct CostMatrix<'a, S> {
    desc3: &'a [f32],
    n3: usize,
    desc2: &'a [f32],
    n2: usize,
    channels: usize,
    plan: &'a mut [S],
    norms: &'a mut [f32],
}

impl<S: PlanScalar> Kernel<()> for CostMatrix<'_, S> {
    /// The dot products on the f32 linear kernel; square roots and the rounding into the
    /// plan's storage with the CPU's instructions (correctly rounded: the same bits).
    #[inline(always)]
    fn run<F: Fma>(self, fma: F) {
        let (norm2, norm3) = self.norms.split_at_mut(self.n2);
        squared_norms(self.desc2, self.channels, self.n2, norm2);
        squared_norms(self.desc3, self.channels, self.n3, norm3);
        let rows = PointRows {
            x: self.desc3,
            n: self.n3,
            channels: self.channels,
        };
        let (n2, plan) = (self.n2, self.plan);
        linear_with(
            fma,
            &rows,
            &Input::one(self.desc2, self.channels, n2),
            0..self.n3,
            |i, j0, dots| {
                let mut distances = [0.0f32; COL_BLOCK];
                let distances = &mut distances[..dots.len()];
                for ((d, &dot), &a) in distances.iter_mut().zip(dots).zip(&norm2[j0..]) {
                    let squared = (a + -2.0 * dot) + norm3[i];
                    *d = sqrt(squared.max(1e-30));
                }
                S::store_row(fma, distances, &mut plan[i * n2 + j0..][..dots.len()]);
            },
        );
    }
}

/// The solved transport problem: cost, potentials and the plan on demand.
#[derive(Clone, Copy)]
pub struct Transport<'a, S: PlanScalar> {
    /// Cost without dustbins, `n3 x n2` row-major.
    pub cost: &'a [S],
    /// Row potentials, `n3 + 1` (last: dustbin row).
    pub u: &'a [f32],
    /// Column potentials, `n2 + 1` (last: dustbin column).
    pub v: &'a [f32],
    /// 3D points (rows without the dustbin).
    pub n3: usize,
    /// 2D keypoints (columns without the dustbin).
    pub n2: usize,
    /// Hyper-parameters.
    pub params: SinkhornParams,
    /// Iterations run (early stop included).
    pub iterations: usize,
}

impl<S: PlanScalar> Transport<'_, S> {
    /// Cost of row `i <= n3`, column `j <= n2` (the bin score on the dustbins).
    #[inline(always)]
    pub fn cost(&self, i: usize, j: usize) -> f32 {
        if i < self.n3 && j < self.n2 {
            self.cost[i * self.n2 + j].to_f32()
        } else {
            self.params.bin_score
        }
    }

    /// `M_ij = ((-C_ij + u_i) + v_j) / eps`, the log of the plan entry.
    #[inline(always)]
    pub fn log_plan(&self, i: usize, j: usize) -> f32 {
        ((-self.cost(i, j) + self.u[i]) + self.v[j]) * (1.0 / self.params.eps)
    }

    /// [`Transport::log_plan`] of the real columns of row `i < n3`, into `out` (`n2`
    /// values), through `buf` (`n2` values: the row's costs as f32).
    #[inline(always)]
    pub fn log_plan_row<'o, F: Fma>(
        &self,
        fma: F,
        i: usize,
        buf: &mut [f32],
        out: &'o mut [f32],
    ) -> &'o [f32] {
        let n2 = self.n2;
        let costs = S::row_f32(fma, &self.cost[i * n2..(i + 1) * n2], buf);
        let (ui, inv_eps) = (self.u[i], 1.0 / self.params.eps);
        for ((o, &c), &vj) in out[..n2].iter_mut().zip(costs).zip(self.v) {
            *o = ((-c + ui) + vj) * inv_eps;
        }
        &out[..n2]
    }

    /// Plan entry `P_ij = exp(M_ij)` (the reference's score matrix).
    pub fn plan(&self, i: usize, j: usize) -> f32 {
        libm::expf(self.log_plan(i, j))
    }
}

/// `log(mu + 1e-8)` of the reference's uniform marginals with dustbin: `1 / (m + n)` for
/// the `m` real entries and `n / (m + n)` for the dustbin.
fn log_marginal(m: usize, n: usize, dustbin: bool) -> f32 {
    let total = (m + n) as f32;
    let mass = if dustbin {
        n as f32 / total
    } else {
        1.0 / total
    };
    libm::logf(mass + 1e-8)
}

/// `(max, sum exp(x - max))` of one row given by `values`, which are replaced by their
/// terms `exp(x - max)` (a loop of its own, so that it runs in the widest vectors), summed
/// in 8 interleaved lanes. The row's log-sum-exp is `ln(sum) + max`.
#[inline(always)]
fn exp_terms_in_place(values: &mut [f32]) -> (f32, f32) {
    let mut maxima = [f32::NEG_INFINITY; 8];
    let mut chunks = values.chunks_exact(8);
    for chunk in &mut chunks {
        for (m, &x) in maxima.iter_mut().zip(chunk) {
            *m = if x > *m { x } else { *m };
        }
    }
    let max = chunks
        .remainder()
        .iter()
        .chain(&maxima)
        .fold(f32::NEG_INFINITY, |m, &x| if x > m { x } else { m });
    for x in values.iter_mut() {
        *x = exp(*x - max);
    }
    let mut lanes = [0.0f32; 8];
    let mut chunks = values.chunks_exact(8);
    for chunk in &mut chunks {
        for (l, &x) in lanes.iter_mut().zip(chunk) {
            *l += x;
        }
    }
    for (l, &x) in lanes.iter_mut().zip(chunks.remainder()) {
        *l += x;
    }
    let sum = ((lanes[0] + lanes[1]) + (lanes[2] + lanes[3]))
        + ((lanes[4] + lanes[5]) + (lanes[6] + lanes[7]));
    (max, sum)
}

/// Log-domain Sinkhorn (supp. eq. 10) on `cost` (`n3 x n2`) with the dustbins, the
/// reference's fixed-point updates: rows first, then columns with the new `u`, stopping
/// after the first iteration whose `||u - u_prev||_2` is below `params.stop`, with
/// `M_ij = ((-C_ij + u_i) + v_j) / eps` (the division done as a product with `1 / eps`).
/// `u` (`n3 + 1`), `v` (`n2 + 1`) receive the potentials; `scratch` holds
/// `n3 + 1 + 5 n2 + 3` values. Returns the number of iterations run.
///
/// With [`PlanScalar::COLUMNS_FROM_ROWS`] (the f16 cost of the device configuration) the
/// column pass exponentiates nothing: row `i`'s terms `e_ij = exp(M_ij - max_i)` under the
/// old `u` times `w_i = mu_i / sum_j e_ij` are its plan entries under the new `u` (the new
/// `u_i` makes the row sum `mu_i`), so each column's sum of `exp(M_ij)` is summed while the
/// row is at hand (the same update in exact arithmetic, other roundings). No column max is
/// subtracted: terms are at most 1, weights at most `mu_i`, and every column holds the
/// dustbin row's term. On 3000 random cost matrices of scales up to 1000 (negative costs
/// too) the potentials stay within 1e-3 (relative) of the reference passes'
/// (`columns_from_rows_reach_the_reference_potentials_on_any_costs`).
pub fn sinkhorn<S: PlanScalar>(
    cost: &[S],
    n3: usize,
    n2: usize,
    params: &SinkhornParams,
    u: &mut [f32],
    v: &mut [f32],
    scratch: &mut [f32],
) -> usize {
    with_fma(Sinkhorn {
        cost,
        n3,
        n2,
        params,
        u,
        v,
        scratch,
    })
}

/// The arguments of one [`sinkhorn`] call.
struct Sinkhorn<'a, S> {
    cost: &'a [S],
    n3: usize,
    n2: usize,
    params: &'a SinkhornParams,
    u: &'a mut [f32],
    v: &'a mut [f32],
    scratch: &'a mut [f32],
}

impl<S: PlanScalar> Kernel<usize> for Sinkhorn<'_, S> {
    /// Plain f32 arithmetic (no fused operations): the same bits compiled for any CPU.
    #[inline(always)]
    fn run<F: Fma>(self, fma: F) -> usize {
        sinkhorn_vectorised(fma, self)
    }
}

/// [`sinkhorn`], compiled into the caller (for the widest vectors the CPU has).
#[inline(always)]
fn sinkhorn_vectorised<F: Fma, S: PlanScalar>(fma: F, args: Sinkhorn<'_, S>) -> usize {
    let Sinkhorn {
        cost,
        n3,
        n2,
        params,
        u,
        v,
        scratch,
    } = args;
    let (u, v) = (&mut u[..n3 + 1], &mut v[..n2 + 1]);
    u.fill(0.0);
    v.fill(0.0);
    let (u_prev, rest) = scratch.split_at_mut(n3 + 1);
    let (buf, rest) = rest.split_at_mut(n2);
    let (bins, rest) = rest.split_at_mut(n2);
    let (row, rest) = rest.split_at_mut(n2 + 1);
    let (col_max, rest) = rest.split_at_mut(n2 + 1);
    let col_sum = &mut rest[..n2 + 1];
    bins.fill(params.bin_score);
    let log_mu = [false, true].map(|dustbin| log_marginal(n3, n2, dustbin));
    let passes = Passes {
        fma,
        cost,
        n3,
        n2,
        bins,
        eps: params.eps,
        inv_eps: 1.0 / params.eps,
        bin: params.bin_score,
        log_mu,
        mu: log_mu.map(libm::expf),
    };
    let (log_nu, log_nu_bin) = (log_marginal(n2, n3, false), log_marginal(n2, n3, true));
    if S::COLUMNS_FROM_ROWS {
        // The row pass's column sums need no maximum taken out.
        col_max.fill(0.0);
    }
    let mut iterations = 0;
    while iterations < params.max_iters {
        iterations += 1;
        u_prev.copy_from_slice(u);
        if S::COLUMNS_FROM_ROWS {
            passes.rows_with_column_sums(u, v, buf, row, col_sum);
        } else {
            passes.rows_with_column_maxima(u, v, buf, row, col_max, col_sum);
            passes.column_sums(u, v, buf, col_max, col_sum);
        }
        // Columns with the new u: v_j = eps (log nu_j - LSE_i M_ij) + v_j.
        for (j, vj) in v.iter_mut().enumerate() {
            let target = if j < n2 { log_nu } else { log_nu_bin };
            let lse = libm::logf(col_sum[j]) + col_max[j];
            *vj += passes.eps * (target - lse);
        }
        let change: f32 = u
            .iter()
            .zip(u_prev.iter())
            .map(|(&a, &b)| (a - b) * (a - b))
            .sum();
        if sqrt(change) < params.stop {
            break;
        }
    }
    iterations
}

/// The passes of one [`sinkhorn`] call over the cost rows.
struct Passes<'a, F, S> {
    fma: F,
    cost: &'a [S],
    n3: usize,
    n2: usize,
    /// The dustbin row's costs (`n2` times the bin score).
    bins: &'a [f32],
    eps: f32,
    inv_eps: f32,
    bin: f32,
    /// `log(mu + 1e-8)` of a real row and of the dustbin row.
    log_mu: [f32; 2],
    /// `mu + 1e-8` of a real row and of the dustbin row.
    mu: [f32; 2],
}

impl<F: Fma, S: PlanScalar> Passes<'_, F, S> {
    /// `M_ij = ((-C_ij + u_i) + v_j) / eps`.
    #[inline(always)]
    fn log_plan(&self, c: f32, ui: f32, vj: f32) -> f32 {
        ((-c + ui) + vj) * self.inv_eps
    }

    /// Row `i`'s costs as f32 (through `buf`).
    #[inline(always)]
    fn costs<'b>(&'b self, i: usize, buf: &'b mut [f32]) -> &'b [f32] {
        cost_row(self.fma, self.cost, self.n3, self.n2, i, buf, self.bins)
    }

    /// Index of row `i`'s marginal in `log_mu` and `mu`: 0 for a real row, 1 for the dustbin.
    #[inline(always)]
    fn marginal(&self, i: usize) -> usize {
        usize::from(i == self.n3)
    }

    /// The reference's row update `u_i = eps (log mu_i - LSE_j M_ij) + u_i` under `v`,
    /// leaving row `i`'s terms `exp(M_ij - max_i)` under the old `u_i` in `row` (`n2 + 1`
    /// values, dustbin last); returns their sum.
    #[inline(always)]
    fn update_row(
        &self,
        i: usize,
        ui: &mut f32,
        v: &[f32],
        buf: &mut [f32],
        row: &mut [f32],
    ) -> f32 {
        let old = *ui;
        let costs = self.costs(i, buf);
        for ((r, &c), &vj) in row.iter_mut().zip(costs).zip(v) {
            *r = self.log_plan(c, old, vj);
        }
        row[self.n2] = self.log_plan(self.bin, old, v[self.n2]);
        let (max, sum) = exp_terms_in_place(row);
        *ui = self.eps * (self.log_mu[self.marginal(i)] - (libm::logf(sum) + max)) + old;
        sum
    }

    /// Row pass of the reference, `u_i = eps (log mu_i - LSE_j M_ij) + u_i`, that also
    /// leaves the column maxima of `M` under the new `u` in `col_max`, each row's into the
    /// other of two buffers (`col_sum` is free until the columns' pass): updated in place,
    /// they compile to masked stores, which are slow on AMD CPUs.
    #[inline(always)]
    fn rows_with_column_maxima(
        &self,
        u: &mut [f32],
        v: &[f32],
        buf: &mut [f32],
        row: &mut [f32],
        col_max: &mut [f32],
        col_sum: &mut [f32],
    ) {
        let n2 = self.n2;
        let (mut maxima, mut next) = (&mut *col_max, &mut *col_sum);
        maxima.fill(f32::NEG_INFINITY);
        for (i, ui) in u.iter_mut().enumerate() {
            self.update_row(i, ui, v, buf, row);
            let new = *ui;
            let costs = self.costs(i, buf);
            let columns = next.iter_mut().zip(maxima.iter()).zip(costs).zip(v.iter());
            for (((m, &before), &c), &vj) in columns {
                let x = self.log_plan(c, new, vj);
                *m = if x > before { x } else { before };
            }
            let x = self.log_plan(self.bin, new, v[n2]);
            next[n2] = if x > maxima[n2] { x } else { maxima[n2] };
            core::mem::swap(&mut maxima, &mut next);
        }
        if u.len() % 2 == 1 {
            col_max.copy_from_slice(col_sum);
        }
    }

    /// Row pass with each column's sum of `exp(M_ij)` under the new `u` and the old `v`
    /// into `col_sum`: row `i`'s terms times `mu_i / sum_j e_ij` ([`sinkhorn`]).
    #[inline(always)]
    fn rows_with_column_sums(
        &self,
        u: &mut [f32],
        v: &[f32],
        buf: &mut [f32],
        row: &mut [f32],
        col_sum: &mut [f32],
    ) {
        col_sum.fill(0.0);
        for (i, ui) in u.iter_mut().enumerate() {
            let sum = self.update_row(i, ui, v, buf, row);
            let weight = self.mu[self.marginal(i)] / sum;
            for (s, &e) in col_sum.iter_mut().zip(row.iter()) {
                *s += e * weight;
            }
        }
    }

    /// Column pass of the reference: each column's sum of `exp(M_ij - max_j)` under `u`
    /// and `v` into `col_sum`, `col_max` holding the column maxima.
    #[inline(always)]
    fn column_sums(
        &self,
        u: &[f32],
        v: &[f32],
        buf: &mut [f32],
        col_max: &[f32],
        col_sum: &mut [f32],
    ) {
        let n2 = self.n2;
        col_sum.fill(0.0);
        for (i, &ui) in u.iter().enumerate() {
            let costs = self.costs(i, buf);
            for (((s, &c), &vj), &m) in col_sum
                .iter_mut()
                .zip(costs)
                .zip(v.iter())
                .zip(col_max.iter())
            {
                *s += exp(self.log_plan(c, ui, vj) - m);
            }
            col_sum[n2] += exp(self.log_plan(self.bin, ui, v[n2]) - col_max[n2]);
        }
    }
}

/// Row `i <= n3` of the cost as f32: a real row (converted into `buf` where it is stored
/// as f16) or, for `i == n3`, the dustbin row `bins`.
#[inline(always)]
fn cost_row<'a, F: Fma, S: PlanScalar>(
    fma: F,
    cost: &'a [S],
    n3: usize,
    n2: usize,
    i: usize,
    buf: &'a mut [f32],
    bins: &'a [f32],
) -> &'a [f32] {
    if i < n3 {
        S::row_f32(fma, &cost[i * n2..(i + 1) * n2], buf)
    } else {
        bins
    }
}

/// One 2D-3D correspondence.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Match {
    /// Index of the query keypoint.
    pub i2d: u16,
    /// Index of the database point.
    pub i3d: u16,
    /// Sinkhorn plan entry `P[i3d][i2d]`.
    pub sinkhorn: f32,
    /// Classifier inlier probability.
    pub probability: f32,
}

/// Mutual assignment of the reference on the plan without dustbins: `nn12` = best column
/// of each row, `nn21` = best row of each column (first maximum on ties); the mutual pairs
/// in row order, or, if there are 4 or fewer, every pair of either direction (unique,
/// sorted by 3D then 2D index). Writes the matches into `out` and returns their count.
/// `best` holds `4 n2` values of scratch; `nn12` `n3` and `nn21` `n2` indices.
///
/// The maxima are those of the plan entries `expf(M_ij)`, as the reference compares them
/// (two entries whose logs differ may round to one plan value, a tie that the first index
/// wins), but `expf` runs only where it can decide (near each row's and column's largest log).
pub fn mutual_assignment<S: PlanScalar>(
    t: &Transport<'_, S>,
    nn12: &mut [u16],
    nn21: &mut [u16],
    best: &mut [f32],
    out: &mut [Match],
) -> usize {
    let (n3, n2) = (t.n3, t.n2);
    let (nn12, nn21) = (&mut nn12[..n3], &mut nn21[..n2]);
    plan_argmaxima(t, nn12, nn21, best);
    let mut count = 0;
    for (i, &own) in nn12.iter().enumerate() {
        let j = usize::from(own);
        if usize::from(nn21[j]) == i {
            push(out, &mut count, pair(t, i, j));
        }
    }
    if count > 4 {
        return count;
    }
    count = 0;
    for (i, &own) in nn12.iter().enumerate() {
        for (j, &column_arg) in nn21.iter().enumerate() {
            if j == usize::from(own) || usize::from(column_arg) == i {
                push(out, &mut count, pair(t, i, j));
            }
        }
    }
    count
}

/// Widest gap between two log-plan entries whose plan values can be equal where the
/// plan value is a normal f32: `libm::expf` is within 1 ulp, so `expf(x) == expf(m)` needs
/// `m - x` below about `2.4e-7`; an entry further below a row's or column's largest log
/// cannot be its maximum nor tie with it.
const TIE_WINDOW: f64 = 1e-5;

/// The first maximum of the plan in each row (`nn12`) and column (`nn21`), as a scan of
/// `expf(M_ij)` finds it, in two passes over the rows: the largest log `M_ij` per row and
/// column, then `expf` of the entries within [`TIE_WINDOW`] of it (all of them where the
/// largest plan value is not a normal f32, so underflowed or overflowed ties are decided
/// as the scan decides them). `scratch` holds `4 n2` values. Compiled for the widest
/// vectors the CPU has (comparisons and plain f32 arithmetic: the same bits on any CPU).
fn plan_argmaxima<S: PlanScalar>(
    t: &Transport<'_, S>,
    nn12: &mut [u16],
    nn21: &mut [u16],
    scratch: &mut [f32],
) {
    with_fma(PlanArgmaxima {
        t,
        nn12,
        nn21,
        scratch,
    });
}

/// The arguments of one [`plan_argmaxima`] call.
struct PlanArgmaxima<'a, 't, S: PlanScalar> {
    t: &'a Transport<'t, S>,
    nn12: &'a mut [u16],
    nn21: &'a mut [u16],
    scratch: &'a mut [f32],
}

impl<S: PlanScalar> Kernel<()> for PlanArgmaxima<'_, '_, S> {
    #[inline(always)]
    fn run<F: Fma>(self, fma: F) {
        let PlanArgmaxima {
            t,
            nn12,
            nn21,
            scratch,
        } = self;
        plan_argmaxima_vectorised(fma, t, nn12, nn21, scratch);
    }
}

/// [`plan_argmaxima`], compiled into the caller.
#[inline(always)]
fn plan_argmaxima_vectorised<F: Fma, S: PlanScalar>(
    fma: F,
    t: &Transport<'_, S>,
    nn12: &mut [u16],
    nn21: &mut [u16],
    scratch: &mut [f32],
) {
    let n2 = t.n2;
    let (column_floor, rest) = scratch[..4 * n2].split_at_mut(n2);
    let (column_best, rest) = rest.split_at_mut(n2);
    let (buf, logs) = rest.split_at_mut(n2);
    column_floor.fill(f32::NEG_INFINITY);
    for i in 0..t.n3 {
        let row = t.log_plan_row(fma, i, buf, logs);
        for (m, &x) in column_floor.iter_mut().zip(row) {
            *m = if x > *m { x } else { *m };
        }
    }
    for m in column_floor.iter_mut() {
        *m = candidate_floor(*m);
    }
    column_best.fill(f32::NEG_INFINITY);
    nn21.fill(0);
    for (i, own) in nn12.iter_mut().enumerate() {
        let row = t.log_plan_row(fma, i, buf, logs);
        let row_max = row
            .iter()
            .fold(f32::NEG_INFINITY, |m, &x| if x > m { x } else { m });
        let row_floor = candidate_floor(row_max);
        let mut row_best = f32::NEG_INFINITY;
        let mut row_arg = 0;
        for (j, (&x, &floor)) in row.iter().zip(column_floor.iter()).enumerate() {
            if x < row_floor && x < floor {
                continue;
            }
            let p = libm::expf(x);
            if x >= row_floor && p > row_best {
                row_best = p;
                row_arg = j;
            }
            if x >= floor && p > column_best[j] {
                column_best[j] = p;
                nn21[j] = i as u16;
            }
        }
        *own = row_arg as u16;
    }
}

/// The smallest log-plan value that can reach or tie the plan value of `max`: all of them
/// where that value is not a normal f32 (zero, subnormal or infinite values tie more widely).
fn candidate_floor(max: f32) -> f32 {
    if libm::expf(max).is_normal() {
        (f64::from(max) - TIE_WINDOW) as f32
    } else {
        f32::NEG_INFINITY
    }
}

fn pair<S: PlanScalar>(t: &Transport<'_, S>, i: usize, j: usize) -> Match {
    Match {
        i2d: j as u16,
        i3d: i as u16,
        sinkhorn: t.plan(i, j),
        probability: 0.0,
    }
}

fn push(out: &mut [Match], count: &mut usize, m: Match) {
    if let Some(slot) = out.get_mut(*count) {
        *slot = m;
        *count += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const PARAMS: SinkhornParams = SinkhornParams {
        eps: 0.1,
        max_iters: 20,
        stop: 1e-6,
        bin_score: 1.0,
    };

    fn transport<'a>(
        cost: &'a [f32],
        u: &'a [f32],
        v: &'a [f32],
        n3: usize,
        n2: usize,
    ) -> Transport<'a, f32> {
        Transport {
            cost,
            u,
            v,
            n3,
            n2,
            params: PARAMS,
            iterations: 0,
        }
    }

    #[test]
    fn cost_is_the_distance_of_unit_descriptors() {
        // channel-major 2 x 2: desc2 points (1,0), (0,1); desc3 points (1,0), (0.6,0.8)
        let desc2 = [1.0f32, 0.0, 0.0, 1.0];
        let desc3 = [1.0f32, 0.6, 0.0, 0.8];
        let mut plan = [0.0f32; 4];
        let mut norms = [0.0; 4];
        cost_matrix(&desc3, 2, &desc2, 2, 2, &mut plan, &mut norms);
        assert_eq!(plan[0], libm::sqrtf(1e-30));
        assert!((plan[1] - libm::sqrtf(2.0)).abs() < 1e-6);
        assert!((plan[2] - libm::sqrtf(0.8)).abs() < 1e-6);
        assert!((plan[3] - libm::sqrtf(0.4)).abs() < 1e-6);
    }

    #[test]
    fn sinkhorn_meets_the_marginals() {
        let (n3, n2) = (3, 2);
        let cost = [0.1f32, 1.5, 1.4, 0.2, 0.9, 0.8];
        let (mut u, mut v) = ([0.0; 4], [0.0; 3]);
        let mut scratch = [0.0; 4 + 13];
        let params = SinkhornParams {
            max_iters: 100,
            stop: 1e-7,
            ..PARAMS
        };
        let it = sinkhorn(&cost, n3, n2, &params, &mut u, &mut v, &mut scratch);
        assert!(it > 1);
        let t = transport(&cost, &u, &v, n3, n2);
        // Columns are updated last, so their marginals hold to rounding.
        for j in 0..=n2 {
            let col: f32 = (0..=n3).map(|i| t.plan(i, j)).sum();
            let target = if j < n2 { 1.0 / 5.0 } else { 3.0 / 5.0 };
            assert!((col - target).abs() < 1e-5, "column {j}: {col}");
        }
        for i in 0..=n3 {
            let row: f32 = (0..=n2).map(|j| t.plan(i, j)).sum();
            let target = if i < n3 { 1.0 / 5.0 } else { 2.0 / 5.0 };
            assert!((row - target).abs() < 1e-3, "row {i}: {row}");
        }
    }

    /// A seeded linear congruential sequence of numbers in `[0, 1)`.
    fn uniform(seed: u32) -> impl FnMut() -> f32 {
        let mut state = seed;
        move || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 8) as f32 / (1u32 << 24) as f32
        }
    }

    /// Iterations and potentials (`u` then `v`) of [`sinkhorn`] on `cost`.
    fn potentials<S: PlanScalar>(
        cost: &[S],
        n3: usize,
        n2: usize,
        params: &SinkhornParams,
    ) -> (usize, std::vec::Vec<f32>) {
        extern crate std;
        let mut scratch = std::vec![0.0; n3 + 1 + 5 * n2 + 3];
        let mut potentials = std::vec![0.0; n3 + n2 + 2];
        let (u, v) = potentials.split_at_mut(n3 + 1);
        let iterations = sinkhorn(cost, n3, n2, params, u, v, &mut scratch);
        (iterations, potentials)
    }

    /// [`potentials`] of `cost` rounded to f16, with the f16 cost (column sums from the
    /// row pass) and with the same values as f32 (the reference's passes).
    fn f16_and_f32_potentials(
        cost: &[f32],
        n3: usize,
        n2: usize,
        params: SinkhornParams,
    ) -> [(usize, std::vec::Vec<f32>); 2] {
        extern crate std;
        let half: std::vec::Vec<half::f16> = cost.iter().map(|&c| half::f16::from_f32(c)).collect();
        let widened: std::vec::Vec<f32> = half.iter().map(|c| c.to_f32()).collect();
        [
            potentials(&half, n3, n2, &params),
            potentials(&widened, n3, n2, &params),
        ]
    }

    /// The f16 cost's column sums from the row pass reach the reference passes' potentials
    /// (the same update in exact arithmetic) on random costs of unit descriptors.
    #[test]
    fn columns_from_rows_reach_the_reference_potentials() {
        extern crate std;
        let (n3, n2) = (37, 29);
        let mut next = uniform(7);
        let cost: std::vec::Vec<f32> = (0..n3 * n2).map(|_| 2.0 * next()).collect();
        let params = SinkhornParams {
            max_iters: 50,
            stop: 1e-7,
            ..PARAMS
        };
        let [(fused_iterations, fused), (iterations, reference)] =
            f16_and_f32_potentials(&cost, n3, n2, params);
        assert_eq!(fused_iterations, iterations);
        for (a, b) in fused.iter().zip(&reference) {
            assert!((a - b).abs() < 2e-5, "{a} vs {b}");
        }
    }

    /// The same on costs of any sign and scales up to 1000, where far entries' terms are
    /// clamped `exp`s (no column max is subtracted, see [`sinkhorn`]).
    #[test]
    fn columns_from_rows_reach_the_reference_potentials_on_any_costs() {
        extern crate std;
        let (n3, n2) = (5, 4);
        let mut next = uniform(99);
        for case in 0..3000 {
            let scale = [1.0f32, 10.0, 100.0, 1000.0][case % 4];
            let offset = [0.0f32, -0.5, 0.5][case % 3];
            let cost: std::vec::Vec<f32> = (0..n3 * n2)
                .map(|_| scale * 8.0 * (next() + offset).powi(3))
                .collect();
            let params = SinkhornParams {
                stop: 0.0,
                bin_score: scale * 4.0 * (next() - 0.5),
                ..PARAMS
            };
            let [(_, fused), (_, reference)] = f16_and_f32_potentials(&cost, n3, n2, params);
            for (a, b) in fused.iter().zip(&reference) {
                assert!(
                    (a - b).abs() < 1e-3 * b.abs().max(1.0),
                    "case {case}: {a} vs {b}"
                );
            }
        }
    }

    #[test]
    fn mutual_pairs_and_fallback() {
        // log plan = -cost/eps with zero potentials: argmax = smallest cost.
        let (n3, n2) = (3, 3);
        let cost = [0.1f32, 0.5, 0.5, 0.5, 0.1, 0.5, 0.5, 0.5, 0.1];
        let (u, v) = ([0.0; 4], [0.0; 4]);
        let t = transport(&cost, &u, &v, n3, n2);
        let (mut nn12, mut nn21, mut best) = ([0; 3], [0; 3], [0.0; 12]);
        let mut out = [Match::default(); 6];
        // 3 mutual pairs <= 4: fallback to the union, which equals them here.
        let count = mutual_assignment(&t, &mut nn12, &mut nn21, &mut best, &mut out);
        assert_eq!(count, 3);
        assert_eq!(
            out[..3]
                .iter()
                .map(|m| (m.i3d, m.i2d))
                .collect::<heapless::Vec<_, 3>>(),
            [(0, 0), (1, 1), (2, 2)]
        );
        // Row 1 prefers column 0 too: mutual (0,0), (2,2); union adds (1,0) and column 1's
        // best row (0,1) - sorted by row then column.
        let cost = [0.1f32, 0.2, 0.5, 0.15, 0.4, 0.5, 0.5, 0.5, 0.1];
        let t = transport(&cost, &u, &v, n3, n2);
        let count = mutual_assignment(&t, &mut nn12, &mut nn21, &mut best, &mut out);
        let pairs: heapless::Vec<(u16, u16), 6> =
            out[..count].iter().map(|m| (m.i3d, m.i2d)).collect();
        assert_eq!(pairs, [(0, 0), (0, 1), (1, 0), (2, 2)]);
    }

    /// The plan's first row and column maxima of a scan of `expf` over every entry.
    fn scanned_argmaxima(t: &Transport<'_, f32>) -> (std::vec::Vec<u16>, std::vec::Vec<u16>) {
        let mut rows = std::vec![0u16; t.n3];
        let mut columns = std::vec![0u16; t.n2];
        let mut column_best = std::vec![f32::NEG_INFINITY; t.n2];
        for (i, row) in rows.iter_mut().enumerate() {
            let mut best = f32::NEG_INFINITY;
            for j in 0..t.n2 {
                let p = t.plan(i, j);
                if p > best {
                    best = p;
                    *row = j as u16;
                }
                if p > column_best[j] {
                    column_best[j] = p;
                    columns[j] = i as u16;
                }
            }
        }
        (rows, columns)
    }

    /// The windowed argmaxima equal the full scan's, also where distinct logs round to
    /// one plan value (ties the first index wins) and where whole rows underflow to zero.
    #[test]
    fn plan_argmaxima_equal_a_scan_of_every_entry() {
        extern crate std;
        let (n3, n2) = (7, 9);
        let mut next = uniform(12_345);
        for case in 0..200 {
            let mut cost: std::vec::Vec<f32> = (0..n3 * n2).map(|_| 0.5 + next()).collect();
            // Ties: near-zero costs a few f32 steps apart, the smallest one later in its
            // row (or column), so both plan values round to the same f32 and the scan keeps
            // the earlier, slightly smaller log.
            let (row, column) = (case % n3, case % n2);
            let smallest = 1e-4 * (1.0 + next());
            let step = 1 + case as u32 % 3;
            if case % 2 == 0 {
                cost[row * n2 + n2 - 1] = smallest;
                cost[row * n2 + column % (n2 - 1)] = f32::from_bits(smallest.to_bits() + step);
            } else {
                cost[(n3 - 1) * n2 + column] = smallest;
                cost[(row % (n3 - 1)) * n2 + column] = f32::from_bits(smallest.to_bits() + step);
            }
            let mut u = std::vec![0.0f32; n3 + 1];
            let v = std::vec![0.0f32; n2 + 1];
            if case % 5 == 0 {
                u[(row + 1) % n3] = -200.0; // this row's plan values underflow to zero
            }
            let t = transport(&cost, &u, &v, n3, n2);
            let (mut nn12, mut nn21, mut scratch) = ([0u16; 7], [0u16; 9], [0.0f32; 36]);
            plan_argmaxima(&t, &mut nn12, &mut nn21, &mut scratch);
            let (rows, columns) = scanned_argmaxima(&t);
            assert_eq!(
                (&nn12[..], &nn21[..]),
                (&rows[..], &columns[..]),
                "case {case}"
            );
        }
    }
}
