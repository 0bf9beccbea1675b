//! The `gomatch` core's blobs on a host, shared by the simulator (`gomatch-sim`) and the tools
//! (`gomatch-tools`): [`convert`] turns a float checkpoint into a model blob (with [`quantize`]
//! and [`calibration`] for int8 weights, layer by layer as [`float_linear`]),
//! [`view_features`] precomputes a map's view-features blob, and [`files`] finds the shipped
//! blobs and reads blob files with advice on the wrong ones.

pub mod calibration;
pub mod convert;
pub mod files;
pub mod float_linear;
pub mod quantize;
pub mod view_features;
