//! GoMatch: geometric-only 2D-3D matching for visual localization
//! (Zhou et al., ECCV 2022, "Is Geometry Enough for Matching in Visual Localization?").
//!
//! `#![no_std]`, no allocator: every buffer has a capacity fixed at compile time by a
//! const generic, and every bad input is a typed [`Error`], never a panic.
//!
//! One keypoint travels through the modules in this order:
//! pixel -> bearing vector ([`camera`]) -> encoder feature ([`encoder`]) -> attention
//! ([`attention`]) -> Sinkhorn plan and mutual match ([`sinkhorn`]) -> classifier
//! probability ([`classifier`]) -> pose of the query ([`pose`]). [`matcher`] runs the
//! network on one query-view pair with the weights of a [`weights::Model`] blob.
#![no_std]
#![forbid(unsafe_code)]
#![warn(missing_docs)]

pub mod attention;
pub mod camera;
pub mod classifier;
pub mod encoder;
pub mod error;
pub mod matcher;
pub mod nn;
pub mod pose;
pub mod sinkhorn;
pub mod weights;

pub use camera::Camera;
pub use error::{Error, Result};
pub use matcher::{MatchSet, Matcher, Observer, Stage};
pub use pose::Pose;
pub use sinkhorn::Match;
pub use weights::{Model, ModelConfig, Precision};
