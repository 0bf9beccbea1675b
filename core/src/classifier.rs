//! Outlier rejection (supp. "Outlier Rejection"): a point ResNet over the set of matches,
//! each represented by `[f2d, f3d]` of its L2-normalised descriptors, then a linear layer
//! and a sigmoid giving the inlier probability.
//!
//! The input layer acts on a concatenation, so it splits as
//! `W [f2d_i; f3d_j] = Wa f2d_i + Wb f3d_j`: both halves are applied once per keypoint and
//! per point and the match features are gathered from them, with no gathered copy of the
//! descriptors.

use crate::nn::linear::store;
use crate::nn::operands::ColumnSlice;
use crate::nn::{linear, residual_block, Input, LayerInput, LayerTap};
use crate::sinkhorn::Match;
use crate::weights::ClassifierWeights;

/// The L2-normalised descriptors, whose memory the classifier reuses for the match
/// features once it has read them.
pub struct Descriptors<'s> {
    /// `desc2` (`d x n2`) at offset 0 and `desc3` (`d x n3`) at `offset3`; at least
    /// `c x max(2, matches)` values in all.
    pub memory: &'s mut [f32],
    /// Offset of `desc3`.
    pub offset3: usize,
    /// 2D keypoints.
    pub n2: usize,
    /// 3D points.
    pub n3: usize,
}

/// Sets `probability` of every match. `pool` holds at least `c x max(n2 + n3, 3, matches + 1)`
/// values and `rows` at least `ROW_BLOCK x max(2, matches)`, both scratch. A single match is
/// classified as two copies of itself, as the reference does. Each layer's input goes to
/// `tap`.
pub fn classify(
    w: &ClassifierWeights<'_>,
    descriptors: Descriptors<'_>,
    matches: &mut [Match],
    pool: &mut [f32],
    rows: &mut [f32],
    tap: &mut dyn LayerTap,
) {
    if matches.is_empty() {
        return;
    }
    let Descriptors {
        memory,
        offset3,
        n2,
        n3,
    } = descriptors;
    let d = w.input.cols() / 2;
    let c = w.input.rows();
    let m = matches.len().max(2);
    let desc2 = &memory[..d * n2];
    let desc3 = &memory[offset3..offset3 + d * n3];
    let (query, database) = (Input::one(desc2, d, n2), Input::one(desc3, d, n3));
    let pair = |k: usize| {
        let mt = &matches[k % matches.len()];
        (usize::from(mt.i2d), usize::from(mt.i3d))
    };
    tap.layer_input(
        w.input.tensor(),
        &LayerInput::Matches {
            a: query,
            b: database,
            pair: &pair,
            count: m,
        },
    );
    let (g2, rest) = pool.split_at_mut(c * n2);
    let g3 = &mut rest[..c * n3];
    let half2 = ColumnSlice {
        layer: &w.input,
        start: 0,
        cols: d,
    };
    let half3 = ColumnSlice {
        layer: &w.input,
        start: d,
        cols: d,
    };
    linear(&half2, &query, 0..c, |r, i0, v| store(g2, n2, r, i0, v));
    linear(&half3, &database, 0..c, |r, i0, v| store(g3, n3, r, i0, v));
    let x = &mut memory[..c * m];
    for r in 0..c {
        let bias = w.input.bias(r);
        let row = &mut x[r * m..(r + 1) * m];
        for (k, out) in row.iter_mut().enumerate() {
            let mt = &matches[k % matches.len()];
            *out = g2[r * n2 + usize::from(mt.i2d)] + g3[r * n3 + usize::from(mt.i3d)] + bias;
        }
    }
    for block in &w.blocks[..w.count] {
        residual_block(block, x, m, pool, rows, tap);
    }
    let features = Input::one(x, c, m);
    tap.layer_input(w.output.tensor(), &LayerInput::Points(features));
    linear(&w.output, &features, 0..1, |_, i0, logits| {
        for (t, &logit) in logits.iter().enumerate() {
            if let Some(mt) = matches.get_mut(i0 + t) {
                mt.probability = sigmoid(logit);
            }
        }
    });
}

/// `1 / (1 + e^-x)`.
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + libm::expf(-x))
}

#[cfg(test)]
mod tests {
    use super::sigmoid;

    #[test]
    fn sigmoid_values() {
        assert_eq!(sigmoid(0.0), 0.5);
        assert!((sigmoid(2.0) - 0.880_797_1).abs() < 1e-7);
        assert_eq!(sigmoid(-200.0), 0.0);
    }
}
