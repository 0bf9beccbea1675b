//! GoMatch: geometric-only 2D-3D matching for visual localization
//! (Zhou et al., ECCV 2022, "Is Geometry Enough for Matching in Visual Localization?").
//!
//! `#![no_std]`, no allocator: every buffer has a capacity fixed at compile time by a
//! const generic, and every bad input is a typed [`Error`], never a panic.
//!
//! One keypoint travels through the modules in this order:
//! pixel -> bearing vector ([`camera`]) -> pose of the query ([`pose`]).
#![no_std]
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod camera;
pub mod error;
pub mod nn;
pub mod pose;
pub mod weights;

pub use camera::Camera;
pub use error::{Error, Result};
pub use pose::Pose;
