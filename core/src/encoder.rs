//! Shared point encoder (supp. "Feature Encoder"): a point ResNet on 2D bearing
//! coordinates, `conv_in` 2 -> d followed by the residual blocks. The same weights encode
//! the query keypoints and the database points (the reference's shared `kp2d_enc`).

use crate::nn::linear::store;
use crate::nn::{linear, residual_block, Input, LayerInput, LayerTap};
use crate::weights::EncoderWeights;

/// Encodes `points` into `x` (`d x n`, channel-major). `hidden` (`d x (n + 1)`) and `rows`
/// (at least `ROW_BLOCK x n`) are scratch; each layer's input goes to `tap`.
pub fn encode(
    w: &EncoderWeights<'_>,
    points: &[[f32; 2]],
    x: &mut [f32],
    hidden: &mut [f32],
    rows: &mut [f32],
    tap: &mut dyn LayerTap,
) {
    let n = points.len();
    let d = w.input.rows();
    let (xs, ys) = rows[..2 * n].split_at_mut(n);
    for ((p, x0), y0) in points.iter().zip(xs.iter_mut()).zip(ys.iter_mut()) {
        *x0 = p[0];
        *y0 = p[1];
    }
    let coordinates = Input::one(&rows[..2 * n], 2, n);
    tap.layer_input(w.input.tensor(), &LayerInput::Points(coordinates));
    linear(&w.input, &coordinates, 0..d, |r, i0, v| {
        store(x, n, r, i0, v)
    });
    for block in &w.blocks[..w.count] {
        residual_block(block, x, n, hidden, rows, tap);
    }
}
