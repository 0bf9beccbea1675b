//! Checkpoint conversion and reports around the `gomatch` core. Each subcommand of the
//! `gomatch-tools` binary is a module with an `Args` struct and a `run` function.

pub mod agreement;
pub mod calibration;
pub mod convert;
pub mod files;
pub mod float_linear;
pub mod image_layout;
pub mod mem_report;
pub mod quantize;
pub mod sensitivity;
pub mod view_features;
