//! GoMatch: geometric-only 2D-3D matching for visual localization
//! (Zhou et al., ECCV 2022, "Is Geometry Enough for Matching in Visual Localization?").
//!
//! `#![no_std]`, no allocator: every buffer has a capacity fixed at compile time by a
//! const generic, and every bad input is a typed [`Error`], never a panic.
//!
//! One keypoint travels through the modules in this order:
//! pixel -> bearing vector ([`camera`]) -> RANSAC-PnP inlier ([`p3p`], [`ransac`],
//! [`refine`]) -> pose of the query ([`pose`]). The database side is the geometric-only
//! [`map`]: 3D points, database views and their poses.
#![no_std]
#![forbid(unsafe_code)]
#![warn(missing_docs)]

#[cfg(test)]
extern crate std;

pub mod camera;
pub mod error;
pub mod map;
pub mod p3p;
pub mod pose;
pub mod ransac;
pub mod refine;
pub mod rng;
#[cfg(test)]
mod test_scene;

pub use camera::Camera;
pub use error::{Error, Result};
pub use pose::Pose;
pub use ransac::{estimate_pose, PnpEstimate, PnpWorkspace, RansacConfig};
