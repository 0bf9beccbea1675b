//! GoMatch: geometric-only 2D-3D matching for visual localization
//! (Zhou et al., ECCV 2022, "Is Geometry Enough for Matching in Visual Localization?").
//!
//! `#![no_std]`, no allocator: every buffer has a capacity fixed at compile time by a
//! const generic, and every bad input is a typed [`Error`], never a panic.
//!
//! One keypoint travels through the modules in this order:
//! pixel -> bearing vector ([`camera`]) -> encoder feature ([`encoder`]) -> attention
//! ([`attention`]) -> Sinkhorn plan and mutual match ([`sinkhorn`]) -> classifier
//! probability ([`classifier`]) -> RANSAC-PnP inlier ([`p3p`], [`ransac`], [`refine`]) ->
//! pose of the query ([`pose`]) -> the pose re-matched by projection ([`guided`]).
//! [`matcher`] runs the network on one query-view pair with the weights of a
//! [`weights::Model`] blob. The database side is the geometric-only [`map`]: 3D points,
//! database views and their poses. [`localizer`] runs the whole pipeline for one query
//! against several views of a map. `link` (cargo feature `link`, on by default) serves it to
//! a host over a byte stream (COBS-framed postcard messages).
#![no_std]
#![deny(unsafe_code)]
#![warn(missing_docs)]

#[cfg(test)]
extern crate std;

pub mod acceptance;
pub mod attention;
pub mod camera;
pub mod classifier;
pub mod encoder;
pub mod envelope;
pub mod error;
pub mod guided;
pub mod limits;
#[cfg(feature = "link")]
pub mod link;
pub mod localizer;
pub mod map;
pub mod matcher;
pub mod merge;
pub mod nn;
pub mod p3p;
pub mod pose;
pub mod ransac;
pub mod refine;
pub mod rng;
pub mod sinkhorn;
#[cfg(test)]
mod test_scene;
pub mod view_features;
pub mod weights;

pub use camera::Camera;
pub use error::{Error, Result};
pub use localizer::{
    Clock, Correspondence, Failure, Localization, Localizer, LocalizerConfig, Query, ViewSelection,
};
pub use map::Map;
pub use matcher::{MatchSet, Matcher, Observer, Stage};
pub use pose::Pose;
pub use ransac::{estimate_pose, AdaptiveStop, PnpEstimate, PnpWorkspace, RansacConfig};
pub use sinkhorn::Match;
pub use weights::{Model, ModelConfig, Precision};

/// The README's firmware example, compiled and run as a doctest.
#[cfg(doctest)]
#[doc = include_str!("../../README.md")]
pub struct ReadmeDoctests;
