//! Residual block of a point ResNet (supp. Fig. "Residual Block"):
//! `out = ReLU(IN(W2 IN(W1 (W0 x + b0) + b1) + b2)) + x`, no activation between the
//! convolutions, each computed as the reference does, or with `W0` folded into `W1` where
//! the blob stores it so (see [`crate::weights`]).

use super::linear::{chunk_rows, larger, linear, store};
use super::norm::{instance_norm_rows, relu};
use super::operands::Input;
use super::tap::{LayerInput, LayerTap};
use crate::weights::ResidualBlockWeights;

/// Applies one block in place to `x` (`d x n`, channel-major). `hidden` holds at least
/// `d x (n + 1)` values and `rows` at least `ROW_BLOCK x n`; both are scratch (more of
/// either, fewer passes: the last conv's rows wait for their instance norm in the larger
/// of `rows` and what `hidden` holds beyond `d x n`). Each conv's input goes to `tap`.
pub fn residual_block(
    w: &ResidualBlockWeights<'_>,
    x: &mut [f32],
    n: usize,
    hidden: &mut [f32],
    rows: &mut [f32],
    tap: &mut dyn LayerTap,
) {
    let d = w.conv1.rows();
    let (inner, tile) = hidden.split_at_mut(d * n);
    if w.folded() {
        folded_conv1(w, x, n, inner, tap);
    } else {
        conv1_of_preconv(w, x, n, inner, tile, tap);
    }
    instance_norm_rows(inner, n);
    let input = Input::one(inner, d, n);
    tap.layer_input(w.conv2.tensor(), &LayerInput::Points(input));
    let rows = larger(tile, rows);
    let chunk = chunk_rows(rows.len(), n);
    let mut r0 = 0;
    while r0 < d {
        let r1 = (r0 + chunk).min(d);
        linear(&w.conv2, &input, r0..r1, |r, i0, v| {
            store(rows, n, r - r0, i0, v)
        });
        let z = &mut rows[..(r1 - r0) * n];
        instance_norm_rows(z, n);
        for (xv, &zv) in x[r0 * n..r1 * n].iter_mut().zip(z.iter()) {
            *xv += relu(zv);
        }
        r0 = r1;
    }
}

/// `out = (W1 W0) x + (W1 b0 + b1)` (`d x n`): `conv1` of a folded block on the block input.
fn folded_conv1(
    w: &ResidualBlockWeights<'_>,
    x: &[f32],
    n: usize,
    out: &mut [f32],
    tap: &mut dyn LayerTap,
) {
    let input = Input::one(x, w.conv1.cols(), n);
    tap.layer_input(w.conv1.tensor(), &LayerInput::Points(input));
    linear(&w.conv1, &input, 0..w.conv1.rows(), |r, i0, v| {
        store(out, n, r, i0, v)
    });
}

/// `out = W1 (W0 x + b0) + b1` (`d x n`), through `tile` (at least `d` values): the
/// preconv output of as many points at once as `tile` holds (conv1 reads it, and `tap`
/// sees it, tile by tile).
fn conv1_of_preconv(
    w: &ResidualBlockWeights<'_>,
    x: &[f32],
    n: usize,
    out: &mut [f32],
    tile: &mut [f32],
    tap: &mut dyn LayerTap,
) {
    tap.layer_input(
        w.preconv.tensor(),
        &LayerInput::Points(Input::one(x, w.preconv.cols(), n)),
    );
    let d = w.preconv.rows();
    let points = (tile.len() / d.max(1)).clamp(1, n.max(1));
    let mut t0 = 0;
    while t0 < n {
        let len = points.min(n - t0);
        let input = Input::one(x, d, n).columns(t0, len);
        linear(&w.preconv, &input, 0..d, |r, i0, v| {
            store(tile, len, r, i0, v)
        });
        let preconv_out = Input::one(tile, d, len).of_set(n);
        tap.layer_input(w.conv1.tensor(), &LayerInput::Points(preconv_out));
        linear(&w.conv1, &preconv_out, 0..d, |r, i0, v| {
            store(out, n, r, t0 + i0, v)
        });
        t0 += len;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::weights::{tests_support::linear as layer, Precision};

    /// Identity weights on two channels and three points: the block adds
    /// `ReLU(IN(IN(x)))` to `x`, i.e. the positive part of the standardised channel.
    #[test]
    fn identity_block_adds_the_rectified_standardised_input() {
        let eye: [u8; 16] = {
            let mut b = [0u8; 16];
            b[..4].copy_from_slice(&1.0f32.to_le_bytes());
            b[12..].copy_from_slice(&1.0f32.to_le_bytes());
            b
        };
        let w = ResidualBlockWeights {
            preconv: layer(2, 2, Precision::F32, &eye, &[], &[]),
            conv1: layer(2, 2, Precision::F32, &eye, &[], &[]),
            conv2: layer(2, 2, Precision::F32, &eye, &[], &[]),
        };
        let mut x = [1.0f32, 2.0, 3.0, 5.0, 5.0, 5.0];
        let mut hidden = [0.0; 8];
        let mut rows = [0.0; crate::nn::ROW_BLOCK * 3];
        residual_block(&w, &mut x, 3, &mut hidden, &mut rows, &mut ());
        let mut z = [1.0f32, 2.0, 3.0];
        crate::nn::instance_norm(&mut z);
        crate::nn::instance_norm(&mut z);
        assert_eq!(x[..3], [1.0, 2.0, 3.0 + z[2]]);
        assert_eq!(x[3..], [5.0, 5.0, 5.0]);
    }

    fn bytes<const N: usize>(values: [f32; N]) -> [[u8; 4]; N] {
        values.map(f32::to_le_bytes)
    }

    /// A block with `preconv` folded into `conv1` (`W1 W0`, `W1 b0 + b1`) gives the
    /// unfolded block's output to rounding.
    #[test]
    fn folded_block_equals_the_unfolded_one() {
        const D: usize = 2;
        let (w0, b0) = ([0.5f32, -1.0, 2.0, 0.25], [0.3f32, -0.7]);
        let (w1, b1) = ([1.5f32, 0.5, -0.75, 2.0], [0.1f32, 0.2]);
        let (w2, b2) = ([1.0f32, -0.5, 0.25, 1.0], [0.05f32, -0.1]);
        let mut folded_w = [0.0f32; D * D];
        let mut folded_b = b1;
        for r in 0..D {
            for c in 0..D {
                folded_w[r * D + c] = (0..D).map(|k| w1[r * D + k] * w0[k * D + c]).sum();
            }
            folded_b[r] += (0..D).map(|k| w1[r * D + k] * b0[k]).sum::<f32>();
        }
        let raw = [bytes(w0), bytes(w1), bytes(w2), bytes(folded_w)];
        let biases = [bytes(b0), bytes(b1), bytes(b2), bytes(folded_b)];
        let layer = |i: usize| {
            layer(
                D,
                D,
                Precision::F32,
                raw[i].as_flattened(),
                &[],
                biases[i].as_flattened(),
            )
        };
        let unfolded = ResidualBlockWeights {
            preconv: layer(0),
            conv1: layer(1),
            conv2: layer(2),
        };
        let folded = ResidualBlockWeights {
            preconv: crate::weights::Linear::EMPTY,
            conv1: layer(3),
            conv2: layer(2),
        };
        assert!(folded.folded() && !unfolded.folded());
        let input = [0.3f32, -1.2, 2.5, 0.7, 1.1, -0.4, 0.9, 0.0];
        let run = |w: &ResidualBlockWeights<'_>| {
            let mut x = input;
            let (mut hidden, mut rows) = ([0.0; D * 5], [0.0; crate::nn::ROW_BLOCK * 4]);
            residual_block(w, &mut x, 4, &mut hidden, &mut rows, &mut ());
            x
        };
        let (a, b) = (run(&folded), run(&unfolded));
        for (p, q) in a.iter().zip(&b) {
            assert!((p - q).abs() < 1e-5, "{a:?} vs {b:?}");
        }
        assert_ne!(a, input);
    }
}
