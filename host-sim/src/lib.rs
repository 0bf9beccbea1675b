//! Host-side simulation and evaluation around the `gomatch` core: the same core code, run on
//! a desktop machine with files, threads and clocks.
//!
//! Scenes: [`scene`] is the in-memory structure-from-motion model that the readers
//! ([`colmap`], [`bal`], [`bundler`], [`opensfm`]) and the simulator ([`synthetic`]) produce;
//! [`protocol`] turns a scene into localization samples with ground truth and scores
//! results, for both the training set ([`dataset`]) and evaluation; [`map`] turns a scene
//! into the core's geometric-only map blob. [`host`] holds what the subcommands share (the
//! evaluated capacity, the shipped model's path, the host clock, the scene-source flags).

pub mod bal;
pub mod bundler;
pub mod colmap;
pub mod dataset;
pub mod host;
pub mod keypoints;
pub mod localize;
pub mod map;
pub mod opensfm;
pub mod parse;
pub mod protocol;
pub mod scene;
pub mod scenes_stats;
pub mod synthetic;
pub mod tiny;
pub mod view_features;

pub mod pnp;

pub mod conform;

pub mod demo;
pub mod eval;
pub mod fit;

pub mod device;
pub mod faulty_link;
pub mod firmware_data;
pub mod firmware_reply;
