//! `gomatch-tools convert`: a float32 safetensors checkpoint in the reference layout
//! (`shared/reference/params.tsv`) to a model blob (`gomatch::weights`).
//!
//! Feature width and block counts come from the tensor shapes; the other hyper-parameters
//! from the optional `__metadata__["gomatch_config"]` JSON (defaults: 4 heads, k 10,
//! 20 iterations, eps 0.1, threshold 0.5). Anything else is refused with the name of the
//! offending tensor. The converter splits each EdgeConv weight into its centre (`Wa - Wb`)
//! and neighbour (`Wb`) parts and, for int8 by default (`--fold-blocks[=BOOL]`), folds each
//! residual block's `preconv` into its `conv1` in f64 (`W1 W0`, `W1 b0 + b1`; the blob
//! stores an empty `preconv`, `gomatch::weights::Downstream::Folds`).

use std::collections::BTreeMap;
use std::path::PathBuf;

use anyhow::{bail, ensure, Context, Result};
use gomatch::envelope::{self, HEADER_BYTES};
use gomatch::error::BlobKind;
use gomatch::weights::{
    tensor_count, tensor_index, tensor_spec, BlobHeader, ModelConfig, Precision, Section,
    TensorRecord, TensorSpec,
};
use safetensors::{Dtype, SafeTensors};

use crate::calibration::{self, FitOptions};
use crate::float_linear::FloatLinear;
use crate::quantize::{self, Int8Tensor, Rounding, ScaleSearch};

/// Command-line arguments of `convert`.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// Float32 safetensors checkpoint in the reference layout.
    #[arg(long)]
    pub input: PathBuf,
    /// Weight precision of the blob.
    #[arg(long, value_enum, default_value = "f32")]
    pub precision: PrecisionArg,
    /// Output model blob.
    #[arg(long)]
    pub output: PathBuf,
    /// Tensors stored in f32 whatever the precision, comma-separated blob names
    /// (`encoder.block.conv1[0]`, ...); empty for none. Default: the encoder input and
    /// first block for f16, the encoder input for int8.
    #[arg(long, value_delimiter = ',')]
    pub keep_f32: Option<Vec<String>>,
    /// Tensors stored in f16 when the precision is int8, comma-separated blob names;
    /// none by default.
    #[arg(long, value_delimiter = ',')]
    pub keep_f16: Vec<String>,
    /// Rounding of int8 weights.
    #[arg(long, value_enum, default_value = "gptq-corrected")]
    pub rounding: Rounding,
    /// Scale of each int8 row.
    #[arg(long, value_enum, default_value = "max-abs")]
    pub scale: ScaleSearch,
    /// Synthetic calibration pairs for the int8 rounding.
    #[arg(long, default_value_t = CALIBRATION_PAIRS)]
    pub calibration_pairs: usize,
    /// Seed of the calibration pairs.
    #[arg(long, default_value_t = CALIBRATION_SEED)]
    pub calibration_seed: u64,
    /// Fold each residual block's `preconv` into its `conv1` (a third less of the encoder's
    /// and classifier's work and flash; f32 results move ~3e-4 from the reference's). On by
    /// default for int8, off for f32 and f16 (which stay the reference's layers):
    /// `--fold-blocks` or `--fold-blocks=false` overrides (docs/design.md, "The network").
    #[arg(long, num_args = 0..=1, require_equals = true, default_missing_value = "true")]
    pub fold_blocks: Option<bool>,
}

impl Args {
    /// The conversion options these arguments ask for.
    pub fn options(&self) -> Options {
        let names = |list: &[String]| -> Vec<String> {
            list.iter().filter(|k| !k.is_empty()).cloned().collect()
        };
        let defaults = Options::new(self.precision.into());
        Options {
            keep_f32: self
                .keep_f32
                .as_deref()
                .map_or(defaults.keep_f32.clone(), names),
            keep_f16: names(&self.keep_f16),
            rounding: self.rounding,
            scale: self.scale,
            calibration_pairs: self.calibration_pairs,
            calibration_seed: self.calibration_seed,
            fold_blocks: self.fold_blocks.unwrap_or(defaults.fold_blocks),
            ..defaults
        }
    }
}

/// How to convert: precision, per-tensor exceptions and the int8 method.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Options {
    /// Precision of every tensor not named below.
    pub precision: Precision,
    /// Tensors kept in f32.
    pub keep_f32: Vec<String>,
    /// Tensors stored in f16 when `precision` is int8.
    pub keep_f16: Vec<String>,
    /// Rounding of int8 tensors.
    pub rounding: Rounding,
    /// Scale of each int8 row.
    pub scale: ScaleSearch,
    /// Calibration pairs for [`Rounding::Gptq`].
    pub calibration_pairs: usize,
    /// Their seed.
    pub calibration_seed: u64,
    /// Whether residual blocks are stored folded ([`fold_residual_blocks`]): by default
    /// for int8 only.
    pub fold_blocks: bool,
}

impl Options {
    /// The defaults for `precision`.
    pub fn new(precision: Precision) -> Self {
        let keep_f32 = match precision {
            Precision::F32 => &[][..],
            Precision::F16 => DEFAULT_KEEP_F32_F16,
            Precision::Int8 => DEFAULT_KEEP_F32_INT8,
        };
        Options {
            precision,
            keep_f32: keep_f32.iter().map(|s| s.to_string()).collect(),
            keep_f16: vec![],
            rounding: Rounding::GptqCorrected,
            scale: ScaleSearch::MaxAbs,
            calibration_pairs: CALIBRATION_PAIRS,
            calibration_seed: CALIBRATION_SEED,
            fold_blocks: precision == Precision::Int8,
        }
    }

    /// The defaults for `precision` with every int8 tensor rounded to the nearest level:
    /// no calibration pass (which takes about 40 s at d = 128), for callers that need an
    /// int8 model rather than a calibrated one.
    pub fn rounded_to_nearest(precision: Precision) -> Self {
        Options {
            rounding: Rounding::Nearest,
            ..Options::new(precision)
        }
    }

    /// Storage precision of the tensor named `name`.
    pub fn precision_of(&self, name: &str) -> Precision {
        if self.keep_f32.iter().any(|k| k == name) {
            Precision::F32
        } else if self.precision == Precision::Int8 && self.keep_f16.iter().any(|k| k == name) {
            Precision::F16
        } else {
            self.precision
        }
    }
}

/// Default number of synthetic calibration pairs.
pub const CALIBRATION_PAIRS: usize = 32;
/// Default seed of the calibration pairs (the fixtures use seeds 0 to 3).
pub const CALIBRATION_SEED: u64 = 1000;

/// Weight precision on the command line.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum PrecisionArg {
    /// 32-bit float.
    F32,
    /// 16-bit float.
    F16,
    /// 8-bit integer, symmetric per output channel.
    Int8,
}

impl From<PrecisionArg> for Precision {
    fn from(p: PrecisionArg) -> Self {
        match p {
            PrecisionArg::F32 => Precision::F32,
            PrecisionArg::F16 => Precision::F16,
            PrecisionArg::Int8 => Precision::Int8,
        }
    }
}

/// Runs the command.
pub fn run(args: &Args) -> Result<()> {
    let bytes =
        std::fs::read(&args.input).with_context(|| format!("reading {}", args.input.display()))?;
    let (blob, config) = convert_with(&bytes, &args.options())?;
    std::fs::write(&args.output, &blob)
        .with_context(|| format!("writing {}", args.output.display()))?;
    println!(
        "wrote {} ({} bytes, {:?}): d={} encoder blocks={} classifier {}x{} heads={} k={} \
         iters={} eps={} threshold={} bin={}",
        args.output.display(),
        blob.len(),
        Precision::from(args.precision),
        config.feature_dim,
        config.encoder_blocks,
        config.classifier_dim,
        config.classifier_blocks,
        config.heads,
        config.knn,
        config.sinkhorn_iters,
        config.sinkhorn_eps,
        config.match_threshold,
        config.bin_score
    );
    Ok(())
}

const RAW: &str = "matcher.raw_matcher.";
const CLS: &str = "matcher.classifier.";

/// Tensors kept in f32 by default for f16 weights: the encoder input layer and first
/// residual block. On the reference fixtures they dominate the error of f16 weights (f16
/// match agreement 0.932 -> 1.0 on the 300 x 500 fixture for +66 KiB).
pub const DEFAULT_KEEP_F32_F16: &[&str] = &[
    "encoder.input[0]",
    "encoder.block.preconv[0]",
    "encoder.block.conv1[0]",
    "encoder.block.conv2[0]",
];

/// Tensors kept in f32 by default for int8 weights: the encoder input layer (256
/// weights). Alone in int8 it costs more agreement than any other tensor (0.887, the
/// others 0.987 or more on synthetic pairs, `gomatch-tools sensitivity`), and a layer
/// on two coordinates leaves GPTQ nothing to compensate with.
pub const DEFAULT_KEEP_F32_INT8: &[&str] = &["encoder.input[0]"];

/// Converts checkpoint bytes into a blob of the given precision with the default
/// [`Options`].
pub fn convert(safetensors: &[u8], precision: Precision) -> Result<(Vec<u8>, ModelConfig)> {
    convert_with(safetensors, &Options::new(precision))
}

/// Converts checkpoint bytes into a blob as `options` ask.
pub fn convert_with(safetensors: &[u8], options: &Options) -> Result<(Vec<u8>, ModelConfig)> {
    let (config, mut tensors) = float_tensors(safetensors)?;
    if options.fold_blocks {
        fold_residual_blocks(&config, &mut tensors)?;
    }
    Ok((write_blob(&config, options, &tensors)?, config))
}

/// Folds each residual block's `preconv` into its `conv1`, in f64: `conv1` becomes
/// `W1 W0` with the bias `W1 b0 + b1`, `preconv` an empty 0 x 0 tensor without bias
/// (`gomatch::weights::Downstream::Folds`).
pub fn fold_residual_blocks(config: &ModelConfig, tensors: &mut [FloatLinear]) -> Result<()> {
    for section in [Section::EncoderBlock, Section::ClassifierBlock] {
        for instance in 0..section.repeats(config) {
            let index = |part| {
                tensor_index(config, section, instance, part)
                    .filter(|&i| i < tensors.len())
                    .context("residual block past the tensors")
            };
            let (first, second) = (index(0)?, index(1)?);
            let folded = fold(&tensors[first], &tensors[second])?;
            tensors[second] = folded;
            tensors[first] = FloatLinear::FOLDED;
        }
    }
    Ok(())
}

/// `second` after `first` as one layer: `W2 W1`, `W2 b1 + b2` (sums in f64; a missing
/// bias counts as zero).
fn fold(first: &FloatLinear, second: &FloatLinear) -> Result<FloatLinear> {
    ensure!(
        second.cols == first.rows && first.rows > 0,
        "cannot fold a {}x{} layer after a {}x{} one",
        second.rows,
        second.cols,
        first.rows,
        first.cols
    );
    let (rows, inner, cols) = (second.rows, first.rows, first.cols);
    let mut weights = vec![0.0f32; rows * cols];
    let mut bias = vec![0.0f32; rows];
    for (r, b) in bias.iter_mut().enumerate() {
        let w2 = &second.weights[r * inner..(r + 1) * inner];
        for (c, out) in weights[r * cols..(r + 1) * cols].iter_mut().enumerate() {
            let sum: f64 = w2
                .iter()
                .enumerate()
                .map(|(k, &a)| f64::from(a) * f64::from(first.weights[k * cols + c]))
                .sum();
            *out = sum as f32;
        }
        let through: f64 = w2
            .iter()
            .zip(&first.bias)
            .map(|(&a, &b1)| f64::from(a) * f64::from(b1))
            .sum();
        let own = second.bias.get(r).copied().unwrap_or(0.0);
        *b = (through + f64::from(own)) as f32;
    }
    Ok(FloatLinear {
        rows,
        cols,
        weights,
        bias,
    })
}

/// The checkpoint's tensors in blob order (EdgeConv weights
/// split), in f32, with the configuration.
pub fn float_tensors(safetensors: &[u8]) -> Result<(ModelConfig, Vec<FloatLinear>)> {
    let checkpoint = Checkpoint::parse(safetensors)?;
    let config = checkpoint.config()?;
    let tensors = checkpoint.blob_tensors(&config)?;
    Ok((config, tensors))
}

/// Every tensor of the checkpoint, checked for dtype and finiteness, keyed by name.
struct Checkpoint {
    tensors: BTreeMap<String, (Vec<usize>, Vec<f32>)>,
    metadata: Option<String>,
}

impl Checkpoint {
    fn parse(bytes: &[u8]) -> Result<Self> {
        let (_, metadata) = SafeTensors::read_metadata(bytes).context("not a safetensors file")?;
        let st = SafeTensors::deserialize(bytes).context("not a safetensors file")?;
        let mut tensors = BTreeMap::new();
        for (name, view) in st.tensors() {
            ensure!(
                view.dtype() == Dtype::F32,
                "tensor {name}: dtype {:?}, expected F32",
                view.dtype()
            );
            let values: Vec<f32> = view
                .data()
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
            if let Some(i) = values.iter().position(|v| !v.is_finite()) {
                bail!("tensor {name}: non-finite value at flat index {i}");
            }
            tensors.insert(name, (view.shape().to_vec(), values));
        }
        let metadata = metadata
            .metadata()
            .as_ref()
            .and_then(|m| m.get("gomatch_config").cloned());
        Ok(Checkpoint { tensors, metadata })
    }

    fn count_blocks(&self, prefix: &str) -> usize {
        (0..)
            .take_while(|i| {
                self.tensors
                    .contains_key(&format!("{prefix}conv_{i}.preconv.0.weight"))
            })
            .count()
    }

    /// Infers the shape parameters and reads the metadata for the rest.
    fn config(&self) -> Result<ModelConfig> {
        let input = format!("{RAW}kp2d_enc.conv_in.0.weight");
        let (shape, _) = self
            .tensors
            .get(&input)
            .with_context(|| format!("missing tensor {input}"))?;
        let d = shape[0];
        let cls_input = format!("{CLS}encoder.conv_in.0.weight");
        let (cls_shape, _) = self
            .tensors
            .get(&cls_input)
            .with_context(|| format!("missing tensor {cls_input}"))?;
        let mut config = ModelConfig {
            feature_dim: u16::try_from(d).context("feature width")?,
            encoder_blocks: u8::try_from(self.count_blocks(&format!("{RAW}kp2d_enc.")))?,
            classifier_dim: u16::try_from(cls_shape[0]).context("classifier width")?,
            classifier_blocks: u8::try_from(self.count_blocks(&format!("{CLS}encoder.")))?,
            bin_score: 1.0,
            ..ModelConfig::REFERENCE
        };
        if let Some(json) = &self.metadata {
            apply_metadata(&mut config, json)?;
        }
        let bin = format!("{RAW}bin_score");
        let (_, value) = self
            .tensors
            .get(&bin)
            .with_context(|| format!("missing tensor {bin}"))?;
        config.bin_score = *value.first().context("bin_score is empty")?;
        config
            .validate()
            .map_err(|e| anyhow::anyhow!("configuration not supported: {e}"))?;
        Ok(config)
    }

    /// The expected reference names and shapes for `config`.
    fn expected(config: &ModelConfig) -> Vec<(String, Vec<usize>)> {
        let d = usize::from(config.feature_dim);
        let c = usize::from(config.classifier_dim);
        let mut out = vec![(format!("{RAW}bin_score"), vec![])];
        for enc in ["kp2d_enc", "kp3d_enc"] {
            let p = format!("{RAW}{enc}.");
            point_resnet(&mut out, &p, 2, d, usize::from(config.encoder_blocks));
        }
        for layer in [0, 2] {
            let p = format!("{RAW}attention.att.layers.{layer}.");
            out.push((format!("{p}conv1.weight"), vec![d, 2 * d, 1, 1]));
            out.push((format!("{p}conv2.weight"), vec![2 * d, 2 * d, 1, 1]));
            out.push((format!("{p}conv3.weight"), vec![d, 4 * d, 1, 1]));
        }
        let p = format!("{RAW}attention.att.layers.1.");
        for name in ["attn.merge", "attn.proj.0", "attn.proj.1", "attn.proj.2"] {
            out.push((format!("{p}{name}.weight"), vec![d, d, 1]));
            out.push((format!("{p}{name}.bias"), vec![d]));
        }
        out.push((format!("{p}mlp.0.weight"), vec![2 * d, 2 * d, 1]));
        out.push((format!("{p}mlp.0.bias"), vec![2 * d]));
        out.push((format!("{p}mlp.3.weight"), vec![d, 2 * d, 1]));
        out.push((format!("{p}mlp.3.bias"), vec![d]));
        let p = format!("{CLS}encoder.");
        point_resnet(
            &mut out,
            &p,
            2 * d,
            c,
            usize::from(config.classifier_blocks),
        );
        out.push((format!("{CLS}conv_out.weight"), vec![1, c, 1]));
        out.push((format!("{CLS}conv_out.bias"), vec![1]));
        out
    }

    /// Checks names, shapes and the shared encoder copy; returns the blob tensors in
    /// blob order.
    fn blob_tensors(&self, config: &ModelConfig) -> Result<Vec<FloatLinear>> {
        let expected = Self::expected(config);
        for (name, shape) in &expected {
            let (found, _) = self
                .tensors
                .get(name)
                .with_context(|| format!("missing tensor {name}"))?;
            ensure!(
                found == shape,
                "tensor {name}: shape {found:?}, expected {shape:?}"
            );
        }
        for name in self.tensors.keys() {
            ensure!(
                expected.iter().any(|(n, _)| n == name),
                "unexpected tensor {name} (not in the reference layout for this configuration)"
            );
        }
        for (name, _) in expected.iter().filter(|(n, _)| n.contains("kp3d_enc.")) {
            let twin = name.replace("kp3d_enc.", "kp2d_enc.");
            ensure!(
                self.tensors[name].1 == self.tensors[&twin].1,
                "tensor {name} differs from {twin}: the encoder must be shared"
            );
        }
        let w = |name: &str| -> &[f32] { &self.tensors[name].1 };
        let d = usize::from(config.feature_dim);
        let c = usize::from(config.classifier_dim);
        let mut out = Vec::new();
        let enc = format!("{RAW}kp2d_enc.");
        out.push(linear(
            w(&format!("{enc}conv_in.0.weight")),
            d,
            2,
            w(&format!("{enc}conv_in.0.bias")),
        ));
        residual_blocks(&mut out, &w, &enc, d, usize::from(config.encoder_blocks));
        for layer in [0, 2] {
            let p = format!("{RAW}attention.att.layers.{layer}.");
            let (centre, neighbour) = split_edge(w(&format!("{p}conv1.weight")), d, d);
            out.push(centre);
            out.push(neighbour);
            let (centre, neighbour) = split_edge(w(&format!("{p}conv2.weight")), 2 * d, d);
            out.push(centre);
            out.push(neighbour);
            out.push(linear(w(&format!("{p}conv3.weight")), d, 4 * d, &[]));
        }
        let p = format!("{RAW}attention.att.layers.1.");
        for name in ["attn.proj.0", "attn.proj.1", "attn.proj.2", "attn.merge"] {
            out.push(linear(
                w(&format!("{p}{name}.weight")),
                d,
                d,
                w(&format!("{p}{name}.bias")),
            ));
        }
        out.push(linear(w(&format!("{p}mlp.0.weight")), 2 * d, 2 * d, &[]));
        out.push(linear(
            w(&format!("{p}mlp.3.weight")),
            d,
            2 * d,
            w(&format!("{p}mlp.3.bias")),
        ));
        let p = format!("{CLS}encoder.");
        out.push(linear(
            w(&format!("{p}conv_in.0.weight")),
            c,
            2 * d,
            w(&format!("{p}conv_in.0.bias")),
        ));
        residual_blocks(&mut out, &w, &p, c, usize::from(config.classifier_blocks));
        out.push(linear(
            w(&format!("{CLS}conv_out.weight")),
            1,
            c,
            w(&format!("{CLS}conv_out.bias")),
        ));
        Ok(out)
    }
}

fn point_resnet(
    out: &mut Vec<(String, Vec<usize>)>,
    p: &str,
    input: usize,
    width: usize,
    blocks: usize,
) {
    out.push((format!("{p}conv_in.0.weight"), vec![width, input, 1]));
    out.push((format!("{p}conv_in.0.bias"), vec![width]));
    for b in 0..blocks {
        for conv in ["preconv", "conv1", "conv2"] {
            out.push((
                format!("{p}conv_{b}.{conv}.0.weight"),
                vec![width, width, 1],
            ));
            out.push((format!("{p}conv_{b}.{conv}.0.bias"), vec![width]));
        }
    }
}

fn linear(weights: &[f32], rows: usize, cols: usize, bias: &[f32]) -> FloatLinear {
    FloatLinear {
        rows,
        cols,
        weights: weights.to_vec(),
        bias: bias.to_vec(),
    }
}

/// `preconv`, `conv1` and `conv2` of each residual block, with their biases, as stored.
fn residual_blocks<'a>(
    out: &mut Vec<FloatLinear>,
    w: &impl Fn(&str) -> &'a [f32],
    p: &str,
    width: usize,
    blocks: usize,
) {
    for b in 0..blocks {
        for conv in ["preconv", "conv1", "conv2"] {
            out.push(linear(
                w(&format!("{p}conv_{b}.{conv}.0.weight")),
                width,
                width,
                w(&format!("{p}conv_{b}.{conv}.0.bias")),
            ));
        }
    }
}

/// Splits an EdgeConv weight `rows x 2 half` on `[f_i, f_j - f_i]` into the centre part
/// `Wa - Wb` (in f64) and the neighbour part `Wb`.
fn split_edge(w: &[f32], rows: usize, half: usize) -> (FloatLinear, FloatLinear) {
    let mut centre = vec![0.0f32; rows * half];
    let mut neighbour = vec![0.0f32; rows * half];
    for r in 0..rows {
        for k in 0..half {
            let a = w[r * 2 * half + k];
            let b = w[r * 2 * half + half + k];
            centre[r * half + k] = (f64::from(a) - f64::from(b)) as f32;
            neighbour[r * half + k] = b;
        }
    }
    let make = |weights| FloatLinear {
        rows,
        cols: half,
        weights,
        bias: vec![],
    };
    (make(centre), make(neighbour))
}

/// Applies the `gomatch_config` metadata JSON.
fn apply_metadata(config: &mut ModelConfig, json: &str) -> Result<()> {
    let value: serde_json::Value =
        serde_json::from_str(json).context("gomatch_config metadata is not JSON")?;
    let object = value
        .as_object()
        .context("gomatch_config metadata is not a JSON object")?;
    for (key, v) in object {
        let int = || -> Result<u64> {
            v.as_u64()
                .with_context(|| format!("gomatch_config.{key}: not a non-negative integer"))
        };
        let real = || -> Result<f32> {
            v.as_f64()
                .map(|x| x as f32)
                .with_context(|| format!("gomatch_config.{key}: not a number"))
        };
        let agree = |name: &str, found: u64, shape: u64| -> Result<()> {
            ensure!(
                found == shape,
                "gomatch_config.{name} = {found} disagrees with the tensor shapes ({shape})"
            );
            Ok(())
        };
        match key.as_str() {
            "feature_dim" => agree(key, int()?, u64::from(config.feature_dim))?,
            "encoder_blocks" => agree(key, int()?, u64::from(config.encoder_blocks))?,
            "classifier_blocks" => agree(key, int()?, u64::from(config.classifier_blocks))?,
            "heads" => config.heads = u8::try_from(int()?).context("heads")?,
            "knn" => config.knn = u8::try_from(int()?).context("knn")?,
            "sinkhorn_iters" => {
                config.sinkhorn_iters = u8::try_from(int()?).context("sinkhorn_iters")?
            }
            "sinkhorn_eps" => config.sinkhorn_eps = real()?,
            "match_threshold" => config.match_threshold = real()?,
            other => bail!("gomatch_config: unknown key {other}"),
        }
    }
    Ok(())
}

/// Serialises the blob: envelope, header, tensor records. int8 tensors are
/// rounded as `options` ask; [`Rounding::Gptq`] first runs the f32 model on the synthetic
/// calibration pairs ([`crate::calibration`]).
pub fn write_blob(
    config: &ModelConfig,
    options: &Options,
    tensors: &[FloatLinear],
) -> Result<Vec<u8>> {
    write_blob_with(config, options, tensors, None)
}

/// [`write_blob`] with the int8 tensors given (fitted when `None`).
pub fn write_blob_with(
    config: &ModelConfig,
    options: &Options,
    tensors: &[FloatLinear],
    int8: Option<&[Option<Int8Tensor>]>,
) -> Result<Vec<u8>> {
    ensure!(
        tensors.len() == tensor_count(config),
        "{} tensors for a configuration of {}",
        tensors.len(),
        tensor_count(config)
    );
    for (index, t) in tensors.iter().enumerate() {
        let spec = tensor_spec(config, index).context("tensor index past the layout")?;
        ensure!(
            is_folded_as_declared(&spec, t)
                || (spec.rows == t.rows && spec.cols == t.cols && spec.bias != t.bias.is_empty()),
            "tensor {}: {}x{} (bias {}), layout expects {}x{} (bias {})",
            spec.name,
            t.rows,
            t.cols,
            !t.bias.is_empty(),
            spec.rows,
            spec.cols,
            spec.bias
        );
    }
    let precisions = precisions(config, options, tensors);
    let fitted;
    let int8 = match int8 {
        Some(given) => given,
        None => {
            fitted = int8_tensors(config, options, tensors, &precisions)?;
            &fitted[..]
        }
    };
    let mut blob = vec![0; HEADER_BYTES];
    let header = BlobHeader {
        config: *config,
        precision: options.precision,
        tensor_count: u16::try_from(tensors.len())?,
    };
    blob.extend(postcard::to_allocvec(&header)?);
    for ((t, &precision), q) in tensors.iter().zip(&precisions).zip(int8) {
        let (weights, scales) = encode_weights(t, precision, q.as_ref())?;
        let bias: Vec<u8> = t.bias.iter().flat_map(|b| b.to_le_bytes()).collect();
        let record = TensorRecord {
            rows: t.rows as u32,
            cols: t.cols as u32,
            precision,
            weights: &weights,
            scales: &scales,
            bias: &bias,
        };
        blob.extend(postcard::to_allocvec(&record)?);
    }
    let payload = blob.len() - HEADER_BYTES;
    envelope::seal(BlobKind::Model, &mut blob, payload)?;
    Ok(blob)
}

/// The precision of every tensor under `options`; a folded (empty) tensor stores nothing
/// and counts as f32, which keeps it out of the int8 fit.
pub fn precisions(
    config: &ModelConfig,
    options: &Options,
    tensors: &[FloatLinear],
) -> Vec<Precision> {
    (0..tensor_count(config))
        .filter_map(|i| tensor_spec(config, i))
        .zip(tensors)
        .map(|(spec, t)| {
            if is_folded_as_declared(&spec, t) {
                Precision::F32
            } else {
                options.precision_of(&spec.name.to_string())
            }
        })
        .collect()
}

/// Whether `t` is folded where the layout allows it (a `preconv`, [`Downstream::Folds`]).
///
/// [`Downstream::Folds`]: gomatch::weights::Downstream::Folds
fn is_folded_as_declared(spec: &TensorSpec, t: &FloatLinear) -> bool {
    spec.foldable && t.is_folded()
}

/// The int8 encoding of every tensor stored in int8 (`None` for the others), rounded as
/// `options` ask.
pub fn int8_tensors(
    config: &ModelConfig,
    options: &Options,
    tensors: &[FloatLinear],
    precisions: &[Precision],
) -> Result<Vec<Option<Int8Tensor>>> {
    if !precisions.contains(&Precision::Int8) {
        return Ok(vec![None; tensors.len()]);
    }
    let correct = match options.rounding {
        Rounding::Nearest => {
            return Ok(tensors
                .iter()
                .zip(precisions)
                .map(|(t, &p)| {
                    (p == Precision::Int8).then(|| quantize::round_to_nearest(t, options.scale))
                })
                .collect())
        }
        Rounding::Gptq => false,
        Rounding::GptqCorrected => true,
    };
    let f32_options = Options {
        precision: Precision::F32,
        keep_f32: vec![],
        keep_f16: vec![],
        ..options.clone()
    };
    let pairs = calibration::synthetic_pairs(options.calibration_pairs, options.calibration_seed);
    let fit = FitOptions {
        scale: options.scale,
        correct,
    };
    calibration::fit_int8(config, tensors, precisions, &pairs, fit, |t| {
        write_blob(config, &f32_options, t)
    })
}

/// Weight bytes and (int8) scale bytes of one tensor.
fn encode_weights(
    t: &FloatLinear,
    precision: Precision,
    int8: Option<&Int8Tensor>,
) -> Result<(Vec<u8>, Vec<u8>)> {
    Ok(match (precision, int8) {
        (Precision::F16, _) => (
            t.weights
                .iter()
                .flat_map(|&w| half::f16::from_f32(w).to_bits().to_le_bytes())
                .collect(),
            vec![],
        ),
        (Precision::Int8, Some(q)) => (
            q.levels.iter().map(|&l| l as u8).collect(),
            q.scales.iter().flat_map(|s| s.to_le_bytes()).collect(),
        ),
        (Precision::Int8, None) => bail!("int8 tensor without levels"),
        (Precision::F32, _) => (
            t.weights.iter().flat_map(|w| w.to_le_bytes()).collect(),
            vec![],
        ),
    })
}

#[cfg(test)]
mod tests {
    use std::collections::HashMap;

    use super::*;
    use gomatch::Model;
    use safetensors::tensor::TensorView;

    const SMALL: ModelConfig = ModelConfig {
        feature_dim: 8,
        encoder_blocks: 2,
        classifier_dim: 8,
        classifier_blocks: 1,
        ..ModelConfig::REFERENCE
    };

    type Tensors = Vec<(String, Vec<usize>, Vec<f32>)>;

    /// Deterministic values per name; the kp3d copy equals kp2d.
    fn values(name: &str, count: usize) -> Vec<f32> {
        let key = name.replace("kp3d_enc.", "kp2d_enc.");
        let mut state = key.bytes().fold(2166136261u32, |h, b| {
            (h ^ u32::from(b)).wrapping_mul(16777619)
        });
        (0..count)
            .map(|_| {
                state = state.wrapping_mul(1664525).wrapping_add(1013904223);
                (state >> 8) as f32 / (1u32 << 24) as f32 - 0.5
            })
            .collect()
    }

    fn tensors(config: &ModelConfig) -> Tensors {
        Checkpoint::expected(config)
            .into_iter()
            .map(|(name, shape)| {
                let count = shape.iter().product();
                let v = values(&name, count);
                (name, shape, v)
            })
            .collect()
    }

    fn serialize(tensors: &Tensors, dtype: Dtype, metadata: Option<&str>) -> Vec<u8> {
        let bytes: Vec<(String, Vec<usize>, Vec<u8>)> = tensors
            .iter()
            .map(|(n, s, v)| {
                let b = match dtype {
                    Dtype::F64 => v.iter().flat_map(|x| f64::from(*x).to_le_bytes()).collect(),
                    _ => v.iter().flat_map(|x| x.to_le_bytes()).collect(),
                };
                (n.clone(), s.clone(), b)
            })
            .collect();
        let views: Vec<(String, TensorView<'_>)> = bytes
            .iter()
            .map(|(n, s, b)| {
                (
                    n.clone(),
                    TensorView::new(dtype, s.clone(), b).expect("view"),
                )
            })
            .collect();
        let info = metadata.map(|m| HashMap::from([("gomatch_config".to_string(), m.to_string())]));
        safetensors::serialize(views, info).expect("serialize")
    }

    fn refused(tensors: &Tensors, needle: &str) {
        let err = convert(&serialize(tensors, Dtype::F32, None), Precision::F32)
            .expect_err("must be refused")
            .to_string();
        assert!(err.contains(needle), "{err:?} should mention {needle:?}");
    }

    #[test]
    fn infers_the_shape_and_reads_the_metadata() {
        let ts = tensors(&SMALL);
        let json = r#"{"heads": 2, "knn": 5, "sinkhorn_iters": 30, "sinkhorn_eps": 0.05, "match_threshold": 0.6, "feature_dim": 8}"#;
        for precision in [Precision::F32, Precision::F16, Precision::Int8] {
            let (blob, config) =
                convert(&serialize(&ts, Dtype::F32, Some(json)), precision).expect("converts");
            let model = Model::from_bytes(&blob).expect("loads");
            assert_eq!(*model.config(), config);
            assert_eq!((config.feature_dim, config.encoder_blocks), (8, 2));
            assert_eq!((config.classifier_dim, config.classifier_blocks), (8, 1));
            assert_eq!(
                (config.heads, config.knn, config.sinkhorn_iters),
                (2, 5, 30)
            );
            assert_eq!((config.sinkhorn_eps, config.match_threshold), (0.05, 0.6));
            let bin = ts.iter().find(|t| t.0.ends_with("bin_score")).expect("bin");
            assert_eq!(config.bin_score, bin.2[0]);
        }
    }

    /// Blocks are folded by default for int8 only; `--fold-blocks[=BOOL]` overrides.
    #[test]
    fn blocks_are_folded_by_default_for_int8_only() {
        #[derive(clap::Parser)]
        struct Cli {
            #[command(flatten)]
            args: Args,
        }
        let folded = |extra: &[&str]| {
            let argv = ["convert", "--input", "in", "--output", "out"];
            let cli =
                <Cli as clap::Parser>::try_parse_from(argv.iter().chain(extra)).expect("parses");
            cli.args.options().fold_blocks
        };
        assert!(folded(&["--precision", "int8"]));
        assert!(!folded(&["--precision", "int8", "--fold-blocks=false"]));
        assert!(!folded(&["--precision", "f32"]));
        assert!(folded(&["--precision", "f32", "--fold-blocks"]));
        assert!(!Options::new(Precision::F16).fold_blocks);
    }

    /// With `fold_blocks` each block stores an empty `preconv` and `conv1` = `W1 W0` with
    /// the bias `W1 b0 + b1`, summed in f64.
    #[test]
    fn folded_blocks_store_the_product_of_preconv_and_conv1() {
        let ts = tensors(&SMALL);
        let options = Options {
            fold_blocks: true,
            ..Options::new(Precision::F32)
        };
        let (blob, _) =
            convert_with(&serialize(&ts, Dtype::F32, None), &options).expect("converts");
        let model = Model::from_bytes(&blob).expect("loads");
        let get = |suffix: &str| &ts.iter().find(|t| t.0.ends_with(suffix)).expect(suffix).2;
        let (w0, b0) = (
            get("kp2d_enc.conv_1.preconv.0.weight"),
            get("kp2d_enc.conv_1.preconv.0.bias"),
        );
        let (w1, b1) = (
            get("kp2d_enc.conv_1.conv1.0.weight"),
            get("kp2d_enc.conv_1.conv1.0.bias"),
        );
        let block = &model.encoder.blocks[1];
        assert!(block.folded() && model.classifier.blocks[0].folded());
        let d = 8;
        let mut row = [0.0f32; 8];
        block.conv1.decode_row(3, 0, &mut row);
        for (c, &v) in row.iter().enumerate() {
            let product: f64 = (0..d)
                .map(|k| f64::from(w1[3 * d + k]) * f64::from(w0[k * d + c]))
                .sum();
            assert_eq!(v, product as f32);
        }
        let through: f64 = (0..d)
            .map(|k| f64::from(w1[3 * d + k]) * f64::from(b0[k]))
            .sum();
        assert_eq!(block.conv1.bias(3), (through + f64::from(b1[3])) as f32);
    }

    /// A folded `preconv` stores nothing: its precision is f32 whatever the options, so the
    /// int8 fit (`gomatch-tools sensitivity` calls it directly) skips it.
    #[test]
    fn folded_tensors_count_as_f32_and_the_int8_fit_skips_them() {
        let (config, mut floats) =
            float_tensors(&serialize(&tensors(&SMALL), Dtype::F32, None)).expect("reads");
        fold_residual_blocks(&config, &mut floats).expect("folds");
        let options = Options::rounded_to_nearest(Precision::Int8);
        let chosen = precisions(&config, &options, &floats);
        let int8 = int8_tensors(&config, &options, &floats, &chosen).expect("rounds");
        for ((t, precision), q) in floats.iter().zip(&chosen).zip(&int8) {
            if t.weights.is_empty() {
                assert_eq!((*precision, q.is_none()), (Precision::F32, true));
            }
        }
        assert!(floats.iter().any(|t| t.weights.is_empty()));
        assert!(chosen.contains(&Precision::Int8));
    }

    #[test]
    fn residual_blocks_store_their_convolutions_and_edge_convs_their_parts() {
        let ts = tensors(&SMALL);
        let (blob, _) =
            convert(&serialize(&ts, Dtype::F32, None), Precision::F32).expect("converts");
        let model = Model::from_bytes(&blob).expect("loads");
        let get = |suffix: &str| &ts.iter().find(|t| t.0.ends_with(suffix)).expect(suffix).2;
        let mut row = [0.0f32; 8];
        let block = &model.encoder.blocks[1];
        for (conv, stored) in [
            ("preconv", &block.preconv),
            ("conv1", &block.conv1),
            ("conv2", &block.conv2),
        ] {
            stored.decode_row(3, 0, &mut row);
            assert_eq!(
                row[..],
                get(&format!("kp2d_enc.conv_1.{conv}.0.weight"))[24..32]
            );
            assert_eq!(
                stored.bias(3),
                get(&format!("kp2d_enc.conv_1.{conv}.0.bias"))[3]
            );
        }
        let w = get("layers.2.conv2.weight"); // 16 x 16 on [x_i, x_j - x_i]
        model.self_layers[1].edge2_centre.decode_row(5, 0, &mut row);
        for (k, &v) in row.iter().enumerate() {
            assert_eq!(
                v,
                (f64::from(w[5 * 16 + k]) - f64::from(w[5 * 16 + 8 + k])) as f32
            );
        }
        model.self_layers[1]
            .edge2_neighbour
            .decode_row(5, 0, &mut row);
        assert_eq!(row[..], w[5 * 16 + 8..5 * 16 + 16]);
    }

    #[test]
    fn refuses_anything_but_the_reference_layout() {
        let ts = tensors(&SMALL);
        let name = "matcher.raw_matcher.attention.att.layers.1.mlp.3.bias";
        refused(
            &ts.iter().filter(|t| t.0 != name).cloned().collect(),
            &format!("missing tensor {name}"),
        );
        let mut extra = ts.clone();
        extra.push(("matcher.extra.weight".into(), vec![2], vec![0.0, 1.0]));
        refused(&extra, "unexpected tensor matcher.extra.weight");
        let mut shape = ts.clone();
        let t = shape.iter_mut().find(|t| t.0 == name).expect("tensor");
        t.1 = vec![4];
        t.2.truncate(4);
        refused(&shape, &format!("tensor {name}: shape [4]"));
        let mut nan = ts.clone();
        nan.iter_mut().find(|t| t.0 == name).expect("tensor").2[3] = f32::NAN;
        refused(
            &nan,
            &format!("tensor {name}: non-finite value at flat index 3"),
        );
        let mut unshared = ts.clone();
        let twin = "matcher.raw_matcher.kp3d_enc.conv_0.conv2.0.weight";
        unshared.iter_mut().find(|t| t.0 == twin).expect("tensor").2[0] += 1.0;
        refused(&unshared, "the encoder must be shared");
        let err = convert(&serialize(&ts, Dtype::F64, None), Precision::F32)
            .expect_err("f64 refused")
            .to_string();
        assert!(err.contains("dtype F64, expected F32"), "{err}");
        let err = convert(
            &serialize(&ts, Dtype::F32, Some(r#"{"encoder_blocks": 12}"#)),
            Precision::F32,
        )
        .expect_err("mismatch refused")
        .to_string();
        assert!(err.contains("encoder_blocks = 12 disagrees"), "{err}");
        let err = convert(
            &serialize(&ts, Dtype::F32, Some(r#"{"heads": 3}"#)),
            Precision::F32,
        )
        .expect_err("3 heads do not divide 8")
        .to_string();
        assert!(err.contains("Heads"), "{err}");
    }
}
