//! `gomatch-sim`: command line of the host simulator. Each subcommand lives in its own
//! module of the `gomatch_sim` library with an `Args` struct and a `run` function.

use clap::{Parser, Subcommand};

/// Host simulator of the GoMatch visual localizer.
#[derive(Parser)]
#[command(version, about)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Print the version of the core library.
    Version,
    /// Write localization training samples from real and synthetic scenes.
    Dataset(gomatch_sim::protocol::dataset::Args),
    /// Scene statistics: real scenes against the synthetic generator.
    Scenes(gomatch_sim::protocol::scenes_stats::Args),
    /// Build or inspect a geometric-only map blob.
    Map(gomatch_sim::map::Args),
    /// Run RANSAC-PnP on the shared synthetic sets and compare with PoseLib.
    Pnp(gomatch_sim::eval::pnp::Args),
    /// Run the matcher on a reference fixture and compare every stage with it.
    Conform(gomatch_sim::eval::conform::Args),
    /// Localize a few queries of a built-in synthetic scene end to end.
    Demo(gomatch_sim::eval::demo::Args),
    /// Evaluate localization on a scene with the paper's protocol (AUC, pose errors).
    Eval(gomatch_sim::eval::Args),
    /// Fit the localizer's acceptance rule on `eval` reports of training scenes.
    FitAcceptance(gomatch_sim::eval::fit::Args),
    /// Drive a simulated device over its link (COBS/postcard) with synthetic queries.
    Device(gomatch_sim::device::Args),
    /// Write the firmware image's embedded map, query and ground truth.
    FirmwareData(gomatch_sim::device::firmware_data::Args),
    /// Print the host's reply bytes to the firmware image's request (timings cleared).
    FirmwareReply(gomatch_sim::device::firmware_reply::Args),
    /// Localize photos (keypoints and camera) against a map blob.
    Localize(gomatch_sim::localize::Args),
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Version => println!("gomatch {}", env!("CARGO_PKG_VERSION")),
        Command::Dataset(args) => gomatch_sim::protocol::dataset::run(&args)?,
        Command::Scenes(args) => gomatch_sim::protocol::scenes_stats::run(&args)?,
        Command::Map(args) => gomatch_sim::map::run(&args)?,
        Command::Pnp(args) => gomatch_sim::eval::pnp::run(&args)?,
        Command::Conform(args) => gomatch_sim::eval::conform::run(&args)?,
        Command::Demo(args) => gomatch_sim::eval::demo::run(&args)?,
        Command::Eval(args) => gomatch_sim::eval::run(&args)?,
        Command::FitAcceptance(args) => gomatch_sim::eval::fit::run(&args)?,
        Command::Device(args) => gomatch_sim::device::run(&args)?,
        Command::FirmwareData(args) => gomatch_sim::device::firmware_data::run(&args)?,
        Command::FirmwareReply(args) => gomatch_sim::device::firmware_reply::run(&args)?,
        Command::Localize(args) => {
            gomatch_sim::localize::run(&args)?;
        }
    }
    Ok(())
}
