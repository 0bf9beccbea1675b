//! Reports around the `gomatch` core; the `gomatch-tools` binary also runs the checkpoint
//! converter of `gomatch_blobs`. Each subcommand is a module with an `Args` struct and a
//! `run` function.

pub mod agreement;
pub mod image_layout;
pub mod mem_report;
pub mod sensitivity;
