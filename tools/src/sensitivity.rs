//! `gomatch-tools sensitivity`: which tensors lose the most matches in int8. For every
//! tensor of the blob, the agreement with the f32 model's matches
//! ([`crate::agreement`], synthetic pairs) when only that tensor is int8, and when every
//! tensor but it is int8. One calibration serves every variant.

use std::path::PathBuf;

use anyhow::{Context, Result};
use gomatch::weights::tensor_spec;
use gomatch::Precision;

use crate::agreement::ReferenceMatches;
use gomatch_blobs::calibration::synthetic_pairs;
use gomatch_blobs::convert::{
    float_tensors, fold_residual_blocks, int8_tensors, precisions, write_blob, write_blob_with,
    Options,
};
use gomatch_blobs::quantize::{Rounding, ScaleSearch};

/// Command-line arguments of `sensitivity`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Float32 safetensors checkpoint in the reference layout.
    #[arg(long)]
    pub input: PathBuf,
    /// Rounding of the int8 tensors.
    #[arg(long, value_enum, default_value = "gptq")]
    pub rounding: Rounding,
    /// Scale of each int8 row.
    #[arg(long, value_enum, default_value = "max-abs")]
    pub scale: ScaleSearch,
    /// Number of synthetic evaluation pairs.
    #[arg(long, default_value_t = 24)]
    pub pairs: usize,
    /// Seed of the evaluation pairs.
    #[arg(long, default_value_t = 2000)]
    pub seed: u64,
}

/// Runs the command.
pub fn run(args: &Args) -> Result<()> {
    let bytes =
        std::fs::read(&args.input).with_context(|| format!("reading {}", args.input.display()))?;
    let (config, mut tensors) = float_tensors(&bytes)?;
    let base = Options {
        rounding: args.rounding,
        scale: args.scale,
        keep_f32: vec![],
        keep_f16: vec![],
        ..Options::new(Precision::Int8)
    };
    let reference = write_blob(
        &config,
        &Options {
            precision: Precision::F32,
            ..base.clone()
        },
        &tensors,
    )?;
    let pairs = synthetic_pairs(args.pairs, args.seed);
    let matches = ReferenceMatches::new(&reference, &pairs)?;
    if base.fold_blocks {
        fold_residual_blocks(&config, &mut tensors)?;
    }
    // Every tensor rounded once with all of them int8; the variants pick from these.
    let int8 = int8_tensors(
        &config,
        &base,
        &tensors,
        &precisions(&config, &base, &tensors),
    )?;
    let names: Vec<String> = (0..tensors.len())
        .filter_map(|i| tensor_spec(&config, i))
        .map(|s| s.name.to_string())
        .collect();
    let all = write_blob_with(&config, &base, &tensors, Some(&int8))?;
    let s = matches.agreement(&all)?;
    println!("all int8: mean {:.4} pooled {:.4}", s.mean, s.pooled);
    println!(
        "tensor\tweights\tonly_int8_mean\tonly_int8_pooled\tall_but_int8_mean\tall_but_int8_pooled"
    );
    for (index, name) in names.iter().enumerate() {
        if tensors[index].is_folded() {
            continue;
        }
        let only = Options {
            keep_f32: names.iter().filter(|n| *n != name).cloned().collect(),
            ..base.clone()
        };
        let all_but = Options {
            keep_f32: vec![name.clone()],
            ..base.clone()
        };
        let a = matches.agreement(&write_blob_with(&config, &only, &tensors, Some(&int8))?)?;
        let b = matches.agreement(&write_blob_with(&config, &all_but, &tensors, Some(&int8))?)?;
        println!(
            "{name}\t{}\t{:.4}\t{:.4}\t{:.4}\t{:.4}",
            tensors[index].weights.len(),
            a.mean,
            a.pooled,
            b.mean,
            b.pooled
        );
    }
    Ok(())
}
