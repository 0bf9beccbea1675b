//! Every layer's input as the forward pass reads it, for tools that fit weights to the
//! network's own activations (the int8 calibration of `gomatch-tools convert`). Each layer
//! reports its input to a [`LayerTap`] (a `&mut dyn LayerTap`: one indirect call per layer)
//! just before it reads it; the matcher's [`crate::Observer`] is one, `()` ignores them.

use super::operands::Input;
use crate::limits::MAX_KNN;

/// What one tensor (or EdgeConv pair) reads.
#[derive(Clone, Copy)]
pub enum LayerInput<'a> {
    /// A per-point layer's input: the whole set, or one tile of it in order
    /// ([`Input::set`] gives the set's size).
    Points(Input<'a>),
    /// An EdgeConv layer (supp. eq. 4): the centre tensor reads `x_i` and the neighbour
    /// tensor `x_j` on every edge `(i, j)`, `j` among the first `k` of `graph[i]`.
    Edges {
        /// Point features.
        points: Input<'a>,
        /// Neighbour lists, one per point.
        graph: &'a [[u16; MAX_KNN]],
        /// Neighbours per point.
        k: usize,
    },
    /// The classifier's input layer: `[a_i; b_j]` for every match `(i, j)`.
    Matches {
        /// Query descriptors.
        a: Input<'a>,
        /// Database descriptors.
        b: Input<'a>,
        /// Match `m` as `(i, j)`, for `m < count`.
        pair: &'a dyn Fn(usize) -> (usize, usize),
        /// Number of matches (the set the next layers run on).
        count: usize,
    },
}

/// Receives each layer's input.
pub trait LayerTap {
    /// Tensor `tensor` (its blob index, [`crate::weights::locate`]; an EdgeConv pair is
    /// reported by its centre tensor) is about to read `input`.
    fn layer_input(&mut self, _tensor: usize, _input: &LayerInput<'_>) {}
}

/// The tap that ignores everything.
impl LayerTap for () {}
