//! The converter's unit of work: one float layer of a checkpoint, as the blob lays it out
//! ([`crate::convert`] folds them, [`crate::quantize`] rounds them, [`crate::calibration`]
//! fits their int8 rounding).

/// A float matrix `rows x cols`, row-major, with an optional bias.
#[derive(Debug, Clone, PartialEq)]
pub struct FloatLinear {
    /// Output channels.
    pub rows: usize,
    /// Input channels.
    pub cols: usize,
    /// Weights.
    pub weights: Vec<f32>,
    /// Bias (empty for none).
    pub bias: Vec<f32>,
}

impl FloatLinear {
    /// A `preconv` folded into its `conv1`
    /// ([`fold_residual_blocks`](crate::convert::fold_residual_blocks)): 0 x 0, no bias.
    pub const FOLDED: Self = FloatLinear {
        rows: 0,
        cols: 0,
        weights: Vec::new(),
        bias: Vec::new(),
    };

    /// Whether this is [`Self::FOLDED`]: it stores nothing and no layer reads it.
    pub fn is_folded(&self) -> bool {
        self.rows == 0 && self.cols == 0 && self.bias.is_empty()
    }
}
