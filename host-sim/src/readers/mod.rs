//! The readers: structure-from-motion models into [`Scene`](crate::scene::Scene)s (COLMAP,
//! BAL, Bundler, OpenSfM, on the strict low-level parsing of [`parse`]), and query
//! keypoints from the files a user has ([`keypoints`]).

pub mod bal;
pub mod bundler;
pub mod colmap;
pub mod keypoints;
pub mod opensfm;
pub mod parse;
