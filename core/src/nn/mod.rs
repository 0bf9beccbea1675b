//! Reusable kernels of the network: per-point linear layers (f32, and integer for int8
//! weights), instance norm, activations, the residual block of a point ResNet, a
//! deterministic exponential, square root and fused multiply-add, and the tap through which
//! each layer reports its input.
//!
//! Every feature matrix is channel-major: channel `c` of point `i` of a set of `n` points is
//! `x[c * n + i]`. A per-point linear layer is then a small matrix product whose inner
//! loops run over contiguous points, and each weight is decoded from the blob once per
//! layer call (see [`mod@linear`]).

pub mod blocking;
pub mod dispatch;
pub mod exp;
pub mod fma;
pub mod integer;
pub mod linear;
pub mod norm;
pub mod operands;
pub mod residual;
pub mod sqrt;
pub mod tap;
pub mod transpose;

pub use exp::exp;
pub use linear::{linear, COL_BLOCK, MAX_INPUT, ROW_BLOCK, SMALL_SET};
pub use norm::{
    instance_norm, instance_norm_rows, l2_normalize_points, leaky_relu, relu, Moments, Normalizer,
    StatSum,
};
pub use operands::{Input, WeightRows};
pub use residual::residual_block;
pub use sqrt::{sqrt, sqrt_f64};
pub use tap::{LayerInput, LayerTap};
