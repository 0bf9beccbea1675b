//! int8 weights with one symmetric f32 scale per output row (`w ~ scale * q`,
//! `q` in -127..=127), the blob's int8 format.
//!
//! Two roundings: to nearest, row by row; and error-compensating rounding (GPTQ, Frantar
//! et al. 2023, after Optimal Brain Quantization): the inputs of a row are rounded one by
//! one and each rounding error is pushed onto the inputs not yet rounded through the
//! inverse of the layer's input moment matrix `H = E[x x^T]`, which minimises the
//! expected squared output error `(w - w_q)^T H (w - w_q)` greedily. Scales are either
//! `max |w| / 127` or the clipping that minimises the row's squared rounding error.

use anyhow::{ensure, Result};

use crate::float_linear::FloatLinear;

/// How rows are rounded.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rounding {
    /// Each weight to the nearest level.
    Nearest,
    /// Error-compensating rounding with the float model's input moments (GPTQ).
    Gptq,
    /// GPTQ layer by layer on the inputs of the model quantised so far, aiming at the
    /// float model's outputs (also compensates the error of the layers before).
    GptqCorrected,
}

/// How the scale of a row is chosen.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum ScaleSearch {
    /// `max |w| / 127`: no weight is clipped.
    MaxAbs,
    /// The clipping `alpha max |w|`, alpha in 0.5..=1, with the least squared rounding error.
    Mse,
}

/// One int8 tensor: `rows x cols` levels, row-major, and one scale per row.
#[derive(Debug, Clone, PartialEq)]
pub struct Int8Tensor {
    /// The levels.
    pub levels: Vec<i8>,
    /// The scales.
    pub scales: Vec<f32>,
}

/// Dampening of the moment matrix, relative to its mean diagonal (GPTQ's 1 %).
pub const DAMPENING: f64 = 0.01;

/// The scale of one row.
pub fn row_scale(row: &[f32], search: ScaleSearch) -> f32 {
    let max = row.iter().fold(0.0f32, |m, w| m.max(w.abs()));
    if max == 0.0 {
        return 1.0;
    }
    match search {
        ScaleSearch::MaxAbs => max / 127.0,
        ScaleSearch::Mse => {
            (50..=100)
                .map(|step| max * step as f32 / 100.0 / 127.0)
                .map(|s| (rounding_error(row, s), s))
                .fold((f64::INFINITY, max / 127.0), |best, c| {
                    if c.0 < best.0 {
                        c
                    } else {
                        best
                    }
                })
                .1
        }
    }
}

fn level(w: f64, scale: f64) -> f64 {
    (w / scale).round().clamp(-127.0, 127.0)
}

fn rounding_error(row: &[f32], scale: f32) -> f64 {
    let s = f64::from(scale);
    row.iter()
        .map(|&w| {
            let e = f64::from(w) - level(f64::from(w), s) * s;
            e * e
        })
        .sum()
}

/// Rounds every weight to its nearest level.
pub fn round_to_nearest(t: &FloatLinear, search: ScaleSearch) -> Int8Tensor {
    let mut levels = Vec::with_capacity(t.weights.len());
    let mut scales = Vec::with_capacity(t.rows);
    for row in t.weights.chunks_exact(t.cols) {
        let scale = row_scale(row, search);
        let s = f64::from(scale);
        levels.extend(row.iter().map(|&w| level(f64::from(w), s) as i8));
        scales.push(scale);
    }
    Int8Tensor { levels, scales }
}

/// Error-compensating rounding of tensors that act together on one input (their columns
/// concatenated), all with the same number of rows, given the input moment matrix
/// `hessian` (`dim x dim`, `dim` the total columns). Columns are rounded in order of
/// decreasing input energy (GPTQ's "act order").
pub fn gptq(
    tensors: &[&FloatLinear],
    hessian: &[f64],
    search: ScaleSearch,
) -> Result<Vec<Int8Tensor>> {
    let rows = tensors.first().map_or(0, |t| t.rows);
    let dim: usize = tensors.iter().map(|t| t.cols).sum();
    ensure!(
        tensors.iter().all(|t| t.rows == rows) && hessian.len() == dim * dim,
        "gptq: tensors of {rows} rows and {dim} columns in all, moments of {} values",
        hessian.len()
    );
    let mut order: Vec<usize> = (0..dim).collect();
    order.sort_by(|&a, &b| hessian[b * dim + b].total_cmp(&hessian[a * dim + a]));
    let h = permuted(hessian, dim, &order);
    let u = inverse_cholesky_upper(h, dim)?;
    let offsets: Vec<usize> = tensors
        .iter()
        .scan(0, |at, t| {
            let start = *at;
            *at += t.cols;
            Some(start)
        })
        .collect();
    let mut out: Vec<Int8Tensor> = tensors
        .iter()
        .map(|t| Int8Tensor {
            levels: vec![0; t.weights.len()],
            scales: Vec::with_capacity(rows),
        })
        .collect();
    let mut w = vec![0.0f64; dim];
    let mut scale = vec![0.0f64; dim];
    let mut owner = vec![(0usize, 0usize); dim];
    for r in 0..rows {
        for (p, &col) in order.iter().enumerate() {
            let t = offsets.iter().rposition(|&o| o <= col).unwrap_or(0);
            owner[p] = (t, col - offsets[t]);
        }
        for (t, tensor) in tensors.iter().enumerate() {
            out[t].scales.push(row_scale(
                &tensor.weights[r * tensor.cols..(r + 1) * tensor.cols],
                search,
            ));
        }
        for p in 0..dim {
            let (t, c) = owner[p];
            w[p] = f64::from(tensors[t].weights[r * tensors[t].cols + c]);
            scale[p] = f64::from(out[t].scales[r]);
        }
        for p in 0..dim {
            let q = level(w[p], scale[p]);
            let (t, c) = owner[p];
            out[t].levels[r * tensors[t].cols + c] = q as i8;
            let err = (w[p] - q * scale[p]) / u[p * dim + p];
            let urow = &u[p * dim..(p + 1) * dim];
            for (wj, &uj) in w[p + 1..].iter_mut().zip(&urow[p + 1..]) {
                *wj -= err * uj;
            }
        }
    }
    Ok(out)
}

fn permuted(m: &[f64], dim: usize, order: &[usize]) -> Vec<f64> {
    let mut out = vec![0.0; dim * dim];
    for (a, &i) in order.iter().enumerate() {
        for (b, &j) in order.iter().enumerate() {
            out[a * dim + b] = m[i * dim + j];
        }
    }
    out
}

/// `H` dampened by [`DAMPENING`] of its mean diagonal, dead inputs (zero diagonal) given
/// the mean energy.
pub fn dampened(mut h: Vec<f64>, dim: usize) -> Vec<f64> {
    let mean_diag = (0..dim).map(|i| h[i * dim + i]).sum::<f64>() / dim.max(1) as f64;
    let mean_diag = if mean_diag > 0.0 { mean_diag } else { 1.0 };
    for i in 0..dim {
        if h[i * dim + i] <= 0.0 {
            h[i * dim + i] = mean_diag;
        }
        h[i * dim + i] += DAMPENING * mean_diag;
    }
    h
}

/// The upper Cholesky factor `U` of `H^-1` (`H^-1 = U^T U`) for the [`dampened`] `H`.
fn inverse_cholesky_upper(h: Vec<f64>, dim: usize) -> Result<Vec<f64>> {
    let l = cholesky(&dampened(h, dim), dim)?;
    // H^-1 = L^-T L^-1; invert L (lower triangular) column by column.
    let mut linv = vec![0.0f64; dim * dim];
    for c in 0..dim {
        linv[c * dim + c] = 1.0 / l[c * dim + c];
        for r in c + 1..dim {
            let s: f64 = (c..r).map(|k| l[r * dim + k] * linv[k * dim + c]).sum();
            linv[r * dim + c] = -s / l[r * dim + r];
        }
    }
    let mut inv = vec![0.0f64; dim * dim];
    for a in 0..dim {
        for b in 0..=a {
            let s: f64 = (a..dim)
                .map(|k| linv[k * dim + a] * linv[k * dim + b])
                .sum();
            inv[a * dim + b] = s;
            inv[b * dim + a] = s;
        }
    }
    let lower = cholesky(&inv, dim)?;
    let mut upper = vec![0.0f64; dim * dim];
    for a in 0..dim {
        for b in 0..=a {
            upper[b * dim + a] = lower[a * dim + b];
        }
    }
    Ok(upper)
}

/// Lower Cholesky factor of a symmetric positive definite matrix.
pub fn cholesky(a: &[f64], dim: usize) -> Result<Vec<f64>> {
    let mut l = vec![0.0f64; dim * dim];
    for r in 0..dim {
        for c in 0..=r {
            let s: f64 = (0..c).map(|k| l[r * dim + k] * l[c * dim + k]).sum();
            if r == c {
                let v = a[r * dim + r] - s;
                ensure!(v > 0.0, "moment matrix not positive definite at {r}");
                l[r * dim + r] = v.sqrt();
            } else {
                l[r * dim + c] = (a[r * dim + c] - s) / l[c * dim + c];
            }
        }
    }
    Ok(l)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tensor(rows: usize, cols: usize, weights: Vec<f32>) -> FloatLinear {
        FloatLinear {
            rows,
            cols,
            weights,
            bias: vec![],
        }
    }

    #[test]
    fn nearest_uses_the_largest_weight_as_127() {
        let t = tensor(2, 3, vec![0.5, -1.0, 0.25, 0.0, 0.0, 0.0]);
        let q = round_to_nearest(&t, ScaleSearch::MaxAbs);
        assert_eq!(q.levels, [64, -127, 32, 0, 0, 0]);
        assert_eq!(q.scales, [1.0 / 127.0, 1.0]);
    }

    /// Weights half-way between the levels of `max |w| / 127`: a slightly clipped scale
    /// rounds them better, at a small cost for the largest weight.
    #[test]
    fn mse_scale_trades_a_little_clipping_for_rounding() {
        let mut row: Vec<f32> = (0..60).map(|j| (j as f32 + 0.5) / 127.0).collect();
        row.push(1.0);
        let s = row_scale(&row, ScaleSearch::Mse);
        assert!(s < 1.0 / 127.0);
        assert!(rounding_error(&row, s) < 0.5 * rounding_error(&row, 1.0 / 127.0));
    }

    #[test]
    fn cholesky_inverse_factor_reproduces_the_inverse() {
        let h = vec![4.0, 1.0, 0.5, 1.0, 3.0, 0.2, 0.5, 0.2, 2.0];
        let mut damped = h.clone();
        let mean = 3.0;
        for i in 0..3 {
            damped[i * 3 + i] += DAMPENING * mean;
        }
        let u = inverse_cholesky_upper(h, 3).expect("positive definite");
        // (U^T U) H_damped = I
        for a in 0..3 {
            for b in 0..3 {
                let v: f64 = (0..3)
                    .map(|k| {
                        (0..3).map(|m| u[m * 3 + a] * u[m * 3 + k]).sum::<f64>() * damped[k * 3 + b]
                    })
                    .sum();
                assert!(
                    (v - f64::from(u8::from(a == b))).abs() < 1e-12,
                    "{a} {b}: {v}"
                );
            }
        }
    }

    /// With strongly correlated inputs, compensating the rounding errors gives a smaller
    /// expected output error than rounding to nearest.
    #[test]
    fn gptq_lowers_the_output_error_on_correlated_inputs() {
        let (rows, cols) = (8, 16);
        let weights: Vec<f32> = (0..rows * cols)
            .map(|i| ((i * 7919) % 101) as f32 / 101.0 - 0.5)
            .collect();
        let t = tensor(rows, cols, weights);
        // Inputs x = a + small noise per channel: H = 1 + 0.01 I.
        let h: Vec<f64> = (0..cols * cols)
            .map(|i| 1.0 + if i / cols == i % cols { 0.01 } else { 0.0 })
            .collect();
        let error = |q: &Int8Tensor| -> f64 {
            (0..rows)
                .map(|r| {
                    let e: Vec<f64> = (0..cols)
                        .map(|c| {
                            f64::from(t.weights[r * cols + c])
                                - f64::from(q.levels[r * cols + c]) * f64::from(q.scales[r])
                        })
                        .collect();
                    (0..cols)
                        .map(|a| {
                            (0..cols)
                                .map(|b| e[a] * h[a * cols + b] * e[b])
                                .sum::<f64>()
                        })
                        .sum::<f64>()
                })
                .sum()
        };
        let nearest = round_to_nearest(&t, ScaleSearch::MaxAbs);
        let compensated = gptq(&[&t], &h, ScaleSearch::MaxAbs).expect("gptq");
        assert_eq!(compensated[0].scales, nearest.scales);
        assert!(
            error(&compensated[0]) < 0.2 * error(&nearest),
            "{} vs {}",
            error(&compensated[0]),
            error(&nearest)
        );
    }
}
