//! Host-side simulation and evaluation around the `gomatch` core: the same core code, run on
//! a desktop machine with files, threads and clocks.

pub mod conform;
