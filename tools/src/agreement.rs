//! `gomatch-tools agreement`: how closely one model blob reproduces another's matches on
//! synthetic query-view pairs drawn like the reference fixtures
//! ([`gomatch_blobs::calibration::synthetic_pairs`], seeds apart from the calibration seed), run
//! through `gomatch::Matcher`. Per pair the agreement is `|A ∩ R| / |A ∪ R|` of the
//! mutual-match sets `(i3d, i2d)` of the model `A` and the reference model `R`, as
//! `gomatch-sim conform` measures it against the reference implementation.

use std::collections::BTreeSet;
use std::path::PathBuf;
use std::sync::Mutex;

use anyhow::{Context, Result};
use gomatch::{Matcher, Model};

use gomatch_blobs::calibration::{synthetic_pairs, Pair};

/// Command-line arguments of `agreement`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// The model blob under test.
    #[arg(long)]
    pub model: PathBuf,
    /// The model blob whose matches count as right (usually the f32 conversion).
    #[arg(long)]
    pub reference: PathBuf,
    /// Number of synthetic pairs.
    #[arg(long, default_value_t = 24)]
    pub pairs: usize,
    /// Seed of the pairs (keep it apart from the calibration seed).
    #[arg(long, default_value_t = 2000)]
    pub seed: u64,
    /// Print the sizes and agreement of every pair.
    #[arg(long)]
    pub verbose: bool,
}

/// Agreement statistics over the pairs.
#[derive(Debug, Clone, PartialEq)]
pub struct Summary {
    /// Mean per-pair agreement.
    pub mean: f64,
    /// Smallest per-pair agreement.
    pub min: f64,
    /// `sum |A ∩ R| / sum |A ∪ R|` over all pairs.
    pub pooled: f64,
    /// Per pair: query keypoints, database points, agreement.
    pub per_pair: Vec<(usize, usize, f64)>,
}

/// Runs the command.
pub fn run(args: &Args) -> Result<()> {
    let read = |p: &PathBuf| std::fs::read(p).with_context(|| format!("reading {}", p.display()));
    let (model, reference) = (read(&args.model)?, read(&args.reference)?);
    let s = agreement(&model, &reference, &synthetic_pairs(args.pairs, args.seed))?;
    if args.verbose {
        for (n2, n3, a) in &s.per_pair {
            println!("pair {n2} x {n3}: agreement {a:.4}");
        }
    }
    println!(
        "{} vs {} on {} pairs (seed {}): mean {:.4} min {:.4} pooled {:.4} ({} bytes)",
        args.model.display(),
        args.reference.display(),
        args.pairs,
        args.seed,
        s.mean,
        s.min,
        s.pooled,
        model.len()
    );
    Ok(())
}

/// Agreement of the matches of blob `model` with those of blob `reference` on `pairs`.
pub fn agreement(model: &[u8], reference: &[u8], pairs: &[Pair]) -> Result<Summary> {
    ReferenceMatches::new(reference, pairs)?.agreement(model)
}

type MatchPairs = BTreeSet<(u16, u16)>;

static MATCHER: Mutex<Matcher<1024, f32>> = Mutex::new(Matcher::new());

/// The mutual matches `(i3d, i2d)` of `blob` on every pair.
fn match_sets(blob: &[u8], pairs: &[Pair]) -> Result<Vec<MatchPairs>> {
    let model = Model::from_bytes(blob).map_err(|e| anyhow::anyhow!("loading blob: {e}"))?;
    let mut matcher = MATCHER
        .lock()
        .map_err(|_| anyhow::anyhow!("matcher lock poisoned"))?;
    pairs
        .iter()
        .map(|p| {
            Ok(matcher
                .match_pair(&model, &p.query, &p.db)
                .map_err(|e| anyhow::anyhow!("matching: {e}"))?
                .as_slice()
                .iter()
                .map(|m| (m.i3d, m.i2d))
                .collect())
        })
        .collect()
}

/// The reference model's matches on a set of pairs, for comparing several models.
pub struct ReferenceMatches<'p> {
    pairs: &'p [Pair],
    sets: Vec<MatchPairs>,
}

impl<'p> ReferenceMatches<'p> {
    /// Runs the reference blob on `pairs`.
    pub fn new(reference: &[u8], pairs: &'p [Pair]) -> Result<Self> {
        Ok(ReferenceMatches {
            pairs,
            sets: match_sets(reference, pairs)?,
        })
    }

    /// Agreement of blob `model` with the reference matches.
    pub fn agreement(&self, model: &[u8]) -> Result<Summary> {
        let ours = match_sets(model, self.pairs)?;
        let (mut sum, mut min, mut common, mut union) = (0.0, 1.0f64, 0usize, 0usize);
        let mut per_pair = Vec::with_capacity(ours.len());
        for ((a, r), p) in ours.iter().zip(&self.sets).zip(self.pairs) {
            let both = a.intersection(r).count();
            let either = a.len() + r.len() - both;
            let value = if either == 0 {
                1.0
            } else {
                both as f64 / either as f64
            };
            per_pair.push((p.query.len(), p.db.len(), value));
            sum += value;
            min = min.min(value);
            common += both;
            union += either;
        }
        Ok(Summary {
            mean: sum / ours.len().max(1) as f64,
            min,
            pooled: if union == 0 {
                1.0
            } else {
                common as f64 / union as f64
            },
            per_pair,
        })
    }
}
