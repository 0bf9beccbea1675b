//! `gomatch-tools`: checkpoint conversion and reports.

use clap::{Parser, Subcommand};

/// Counts heap allocations for `mem-report` (otherwise the system allocator, unchanged).
#[global_allocator]
static ALLOCATOR: gomatch_tools::mem_report::CountingAllocator =
    gomatch_tools::mem_report::CountingAllocator;

/// Tools around the GoMatch core.
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
    /// Convert a float32 safetensors checkpoint (reference layout) to a model blob.
    Convert(gomatch_blobs::convert::Args),
    /// Agreement of one model blob's matches with another's on synthetic pairs.
    Agreement(gomatch_tools::agreement::Args),
    /// Per-tensor int8 sensitivity of the matches.
    Sensitivity(gomatch_tools::sensitivity::Args),
    /// RAM, stack, heap and flash per capacity, view count and precision.
    MemReport(gomatch_tools::mem_report::Args),
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Version => println!("gomatch {}", env!("CARGO_PKG_VERSION")),
        Command::Convert(args) => gomatch_blobs::convert::run(&args)?,
        Command::Agreement(args) => gomatch_tools::agreement::run(&args)?,
        Command::Sensitivity(args) => gomatch_tools::sensitivity::run(&args)?,
        Command::MemReport(args) => gomatch_tools::mem_report::run(&args)?,
    }
    Ok(())
}
