//! `gomatch-tools`: checkpoint conversion and reports.

use clap::{Parser, Subcommand};

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
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Version => println!("gomatch {}", env!("CARGO_PKG_VERSION")),
    }
    Ok(())
}
