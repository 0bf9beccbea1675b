//! Register-block and panel sizes of the kernels, one table per target: x86-64 and AArch64
//! (16 vector registers of 8 or 4 lanes) and 32-bit Arm (Cortex-M: 13 core registers and
//! 32 single-precision FPU registers). A size changes the speed, not the results: every
//! output sums its terms in the same order whatever the block (the firmware's reply digest
//! is compared across the three instruction sets).

pub use sizes::*;

/// Channels whose statistics are summed together on rows of `n` points: [`SHORT_ROW_CHANNELS`]
/// on short rows ([`WIDE_SHORT_ROW_CHANNELS`] with `wide` registers), else `channels`.
pub const fn channels_for_rows(channels: usize, n: usize, wide: bool) -> usize {
    match (n <= SHORT_ROW_POINTS, wide) {
        (true, true) => WIDE_SHORT_ROW_CHANNELS,
        (true, false) => SHORT_ROW_CHANNELS,
        (false, _) => channels,
    }
}

#[cfg(not(target_arch = "arm"))]
mod sizes {
    /// f32 linear kernel, points per register block: two AVX2 vectors per row of the
    /// register block ([`LINEAR_ROWS`] x 16 accumulators of FMA chains hide the FMA latency).
    pub const LINEAR_POINTS: usize = 16;
    /// f32 linear kernel, output rows per register block: 6 rows x 16 points are twelve
    /// AVX2 accumulators, two input vectors and a weight (4 rows: eight FMAs per input
    /// channel for the same loop and load overhead as twelve).
    pub const LINEAR_ROWS: usize = 6;
    /// Integer kernel, output rows per register block: 4 rows x 16 points fill 8 AVX2 or
    /// 16 NEON accumulators.
    pub const INT8_ROWS: usize = 4;
    /// Integer kernel, points per register block.
    pub const INT8_POINTS: usize = 16;
    /// Integer kernel, weight pairs of one panel (32 KiB: each panel quantizes the layer
    /// input once, and the tiles' strided reads of a channel-major input miss the cache).
    pub const INT8_PANEL_PAIRS: usize = 8192;
    /// Integer kernel, most rows of a panel.
    pub const INT8_PANEL_MAX_ROWS: usize = 128;
    /// Attention, queries attended together: each key and value loaded serves all of them
    /// (8 x 8 score accumulators: half of the 16 AVX2 vector registers; 16 KiB of score
    /// tiles on the stack).
    pub const ATTENTION_QUERIES: usize = 8;
    /// Attention, width of the inner register tiles.
    pub const ATTENTION_LANES: usize = 8;
    /// Channels whose instance-norm statistics are summed together: eight independent f64
    /// sums hide the add's latency (one channel at a time waits for each add).
    pub const NORM_CHANNELS: usize = 8;
    /// Channels of an edge convolution finished together: the lanes of one AVX2 vector
    /// (edge values, their f64 sums in two vectors, the maxima).
    pub const EDGE_CHANNELS: usize = 8;
    /// [`NORM_CHANNELS`] and [`EDGE_CHANNELS`] on rows of at most [`SHORT_ROW_POINTS`]
    /// points: sixteen f64 sums are four chains of adds in flight instead of two. On longer
    /// rows sixteen rows 4 KiB apart fall in one L1 set and evict each other (N = 1024 was
    /// slower with sixteen).
    pub const SHORT_ROW_CHANNELS: usize = 16;
    /// Most points of a short row (2 KiB of `f32`).
    pub const SHORT_ROW_POINTS: usize = 512;
    /// [`SHORT_ROW_CHANNELS`] where the CPU has 32 vector registers (AVX-512): thirty-two
    /// f64 sums are four chains of 8-lane adds in flight (sixteen were four of 4 lanes).
    pub const WIDE_SHORT_ROW_CHANNELS: usize = 32;
    /// Integer kernel, running maxima of a tile's quantization group: two chains of `max`
    /// in flight (even and odd channels) instead of one that waits on each.
    pub const QUANTIZE_MAX_CHAINS: usize = 2;
}

#[cfg(target_arch = "arm")]
mod sizes {
    /// f32 linear kernel, points per register block: the 4 x 4 accumulators, four inputs
    /// and four weights stay in the FPU's 32 registers (4 x 16 spilled to the stack).
    pub const LINEAR_POINTS: usize = 4;
    /// f32 linear kernel, output rows per register block.
    pub const LINEAR_ROWS: usize = 4;
    /// Integer kernel, output rows per register block: 2 rows x 2 points keep the four
    /// accumulators, two weight pairs and two activation pairs in the 13 core registers.
    pub const INT8_ROWS: usize = 2;
    /// Integer kernel, points per register block.
    pub const INT8_POINTS: usize = 2;
    /// Integer kernel, weight pairs of one panel (64 KiB of stack: the widest layers, 384
    /// and 256 inputs, take two panels instead of four; the 32 KiB panel cost the
    /// Cortex-M7 firmware query 3.6 % more instructions).
    pub const INT8_PANEL_PAIRS: usize = 16384;
    /// Integer kernel, most rows of a panel.
    pub const INT8_PANEL_MAX_ROWS: usize = 256;
    /// Attention, queries attended together: 6 x 4 score accumulators and four key lanes
    /// fit the FPU's 32 registers (8 x 8 spilled to the stack).
    pub const ATTENTION_QUERIES: usize = 6;
    /// Attention, width of the inner register tiles.
    pub const ATTENTION_LANES: usize = 4;
    /// Channels whose instance-norm statistics are summed together (four f64 sums, their
    /// running maxima and centre terms stay in the FPU's registers).
    pub const NORM_CHANNELS: usize = 4;
    /// Channels of an edge convolution finished together: four (their sums and maxima stay
    /// in the FPU's registers, and each neighbour index is read once for all four).
    pub const EDGE_CHANNELS: usize = 4;
    /// [`NORM_CHANNELS`] and [`EDGE_CHANNELS`] on short rows: the same four (more sums
    /// would not stay in the FPU's registers).
    pub const SHORT_ROW_CHANNELS: usize = 4;
    /// Most points of a short row.
    pub const SHORT_ROW_POINTS: usize = 512;
    /// [`SHORT_ROW_CHANNELS`] with wide registers (no 32-bit Arm CPU has them).
    pub const WIDE_SHORT_ROW_CHANNELS: usize = 4;
    /// Integer kernel, running maxima of a tile's quantization group: one chain (a second
    /// tile of 16 maxima would not fit the FPU's 32 registers beside the values).
    pub const QUANTIZE_MAX_CHAINS: usize = 1;
}
