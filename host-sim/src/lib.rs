//! Host-side simulation and evaluation around the `gomatch` core: the same core code, run on
//! a desktop machine with files, threads and clocks.
//!
//! Folders by concern, layered bottom to top:
//! - [`scene`]: the in-memory structure-from-motion model everything below produces or reads.
//! - [`readers`]: model files into scenes ([`readers::colmap`], [`readers::bal`],
//!   [`readers::bundler`], [`readers::opensfm`]) and query keypoints from files.
//! - [`protocol`]: a scene into localization samples with ground truth, and their scores; the
//!   synthetic scenes ([`protocol::synthetic`]), the training set ([`protocol::dataset`]) and
//!   scene statistics ([`protocol::scenes_stats`]).
//! - [`map`]: a scene into the core's geometric-only map blob; [`view_features`] its
//!   precomputed view features.
//! - [`eval`]: localization evaluated with the paper's protocol, and beside it the fit of the
//!   acceptance rule, the demo, the PnP comparison and the conformance check.
//! - [`localize`]: new photos localized against a map blob.
//! - [`device`]: the device link simulated end to end, over a faulty line, and the firmware
//!   image's data and reply.
//!
//! [`host`] holds what the subcommands share (the evaluated capacity, the shipped model's
//! path, the host clock, the scene-source flags).

pub mod device;
pub mod eval;
pub mod host;
pub mod localize;
pub mod map;
pub mod protocol;
pub mod readers;
pub mod scene;
pub mod view_features;
