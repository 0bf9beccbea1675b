//! The operands of a per-point linear layer ([`mod@super::linear`]): the source of its weight
//! rows (a stored layer, or some of its columns) and its channel-major input (up to three
//! matrices stacked along channels).

use crate::weights::Linear;

/// A source of weight rows decoded to f32.
pub trait WeightRows {
    /// Output channels.
    fn rows(&self) -> usize;
    /// Input channels.
    fn cols(&self) -> usize;
    /// Writes row `row` (`cols()` values) into `out`.
    fn decode(&self, row: usize, out: &mut [f32]);
    /// Factor applied to the accumulated sum of row `row`.
    fn scale(&self, row: usize) -> f32;
    /// Added after the scale.
    fn bias(&self, row: usize) -> f32;
    /// Row `row`'s stored int8 weights (`cols()` bytes) when the layer is int8: it then runs
    /// on the integer kernel ([`super::integer`]).
    fn int8_row(&self, row: usize) -> Option<&[u8]>;
}

impl WeightRows for Linear<'_> {
    fn rows(&self) -> usize {
        Linear::rows(self)
    }
    fn cols(&self) -> usize {
        Linear::cols(self)
    }
    fn decode(&self, row: usize, out: &mut [f32]) {
        self.decode_row(row, 0, out);
    }
    fn scale(&self, row: usize) -> f32 {
        Linear::scale(self, row)
    }
    fn bias(&self, row: usize) -> f32 {
        Linear::bias(self, row)
    }
    fn int8_row(&self, row: usize) -> Option<&[u8]> {
        Linear::int8_row(self, row, 0, Linear::cols(self))
    }
}

/// Columns `start..start + cols` of a layer, without its bias: the part of a layer on a
/// concatenated input that acts on one operand.
pub struct ColumnSlice<'l, 'a> {
    /// The layer.
    pub layer: &'l Linear<'a>,
    /// First column.
    pub start: usize,
    /// Number of columns.
    pub cols: usize,
}

impl WeightRows for ColumnSlice<'_, '_> {
    fn rows(&self) -> usize {
        self.layer.rows()
    }
    fn cols(&self) -> usize {
        self.cols
    }
    fn decode(&self, row: usize, out: &mut [f32]) {
        self.layer.decode_row(row, self.start, out);
    }
    fn scale(&self, row: usize) -> f32 {
        self.layer.scale(row)
    }
    fn bias(&self, _row: usize) -> f32 {
        0.0
    }
    fn int8_row(&self, row: usize) -> Option<&[u8]> {
        self.layer.int8_row(row, self.start, self.cols)
    }
}

/// Channel-major input of up to three parts stacked along channels (a concatenation
/// without a copy). Part `p` holds `rows[p]` channels; channel `r` of part `p` is
/// `parts[p][r * stride + start..][..n]`. `set` is the number of points of the whole set
/// the layer runs on (it picks the summation path, see [`SMALL_SET`](super::linear::SMALL_SET)).
#[derive(Clone, Copy)]
pub struct Input<'a> {
    /// The parts (the linear kernel reads them in place).
    pub(super) parts: [&'a [f32]; 3],
    /// Channels of each part.
    pub(super) rows: [usize; 3],
    /// Distance from one channel of a part to the next.
    pub(super) stride: usize,
    /// First point.
    pub(super) start: usize,
    /// Points.
    pub(super) n: usize,
    /// Points of the whole set.
    pub(super) set: usize,
}

impl<'a> Input<'a> {
    /// One matrix of `rows` channels by `n` points.
    pub fn one(x: &'a [f32], rows: usize, n: usize) -> Self {
        Self::parts([x, &[], &[]], [rows, 0, 0], n)
    }

    /// Concatenation `[a; b]` of two matrices of `n` points.
    pub fn two(a: (&'a [f32], usize), b: (&'a [f32], usize), n: usize) -> Self {
        Self::parts([a.0, b.0, &[]], [a.1, b.1, 0], n)
    }

    /// Concatenation of three matrices of `n` points.
    pub fn parts(parts: [&'a [f32]; 3], rows: [usize; 3], n: usize) -> Self {
        Input {
            parts,
            rows,
            stride: n,
            start: 0,
            n,
            set: n,
        }
    }

    /// The same matrix, a tile of a set of `set` points.
    pub fn of_set(self, set: usize) -> Self {
        Input { set, ..self }
    }

    /// The points `start..start + len` only.
    pub fn columns(self, start: usize, len: usize) -> Self {
        Input {
            start: self.start + start,
            n: len,
            ..self
        }
    }

    /// Total channels.
    pub fn channels(&self) -> usize {
        self.rows.iter().sum()
    }

    /// Points.
    pub fn points(&self) -> usize {
        self.n
    }

    /// Points of the whole set (more than [`Input::points`] for a tile).
    pub fn set(&self) -> usize {
        self.set
    }

    /// Channels of each part.
    pub fn part_channels(&self) -> [usize; 3] {
        self.rows
    }

    /// Part `part`'s values from channel `first` at point `i0` on, and the distance from one
    /// channel to the next (for a caller that takes a few points of each of several
    /// channels).
    #[inline(always)]
    pub fn channels_from(&self, part: usize, first: usize, i0: usize) -> (&'a [f32], usize) {
        let at = self.start + i0 + first * self.stride;
        (self.parts[part].get(at..).unwrap_or(&[]), self.stride)
    }

    /// Channel `channel` of part `part` at points `i0..i0 + len` (fewer where the part is
    /// too short).
    #[inline(always)]
    pub fn channel(&self, part: usize, channel: usize, i0: usize, len: usize) -> &'a [f32] {
        let first = self.start + i0 + channel * self.stride;
        let values = self.parts[part].get(first..).unwrap_or(&[]);
        values.get(..len).unwrap_or(values)
    }
}
