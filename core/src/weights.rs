//! The model blob: header, architecture configuration, zero-copy tensors in f32, f16 or int8.
//!
//! The blob is read in place from a borrowed byte slice (flash on a device, a file on the
//! host); no tensor is copied into RAM. Layout, all integers little-endian:
//!
//! ```text
//! [0..16)     the blob envelope (crate::envelope): magic b"GMWB", MODEL_VERSION,
//!             payload length, CRC-32 of the payload
//! [16..)      payload, postcard: BlobHeader { config, precision, tensor_count }
//!             then tensor_count x postcard TensorRecord { rows, cols, weights, scales, bias }
//! ```
//!
//! Tensors come in the fixed order of [`tensor_spec`], derived from the configuration, and
//! every shape is checked at load time, so the forward pass never indexes out of bounds.
//! Each tensor is a per-point linear layer `rows x cols` (output x input, row-major) with
//! its own precision (the header's is the blob's nominal one; the converter may keep a few
//! sensitive tensors in f32): f32 and f16 store the weights as they are; int8 stores
//! `round(w / s)` with one symmetric f32 scale `s = max|w_row| / 127` per output row.
//! Biases are always f32.
//!
//! Residual blocks keep the reference's three convolutions with their biases, or store
//! `preconv` folded into `conv1` (`W1 (W0 x + b0) + b1 = (W1 W0) x + (W1 b0 + b1)`, exact in
//! real arithmetic; [`Downstream::Folds`]): a third less of the encoder's and classifier's
//! work, but f32 results move ~3e-4 away from the reference's, so the converter folds int8
//! blobs only (its default; `--fold-blocks[=BOOL]`, docs/design.md, "The network").
//! The converter folds one exact identity into the stored tensors: EdgeConv
//! `W [f_i, f_j - f_i] = (Wa - Wb) f_i + Wb f_j`, so each self layer stores the centre part
//! `Wa - Wb` and the neighbour part `Wb` (a `k`-fold saving; its rounding stays ~1e-5).

use serde::{Deserialize, Serialize};

use crate::envelope::{self, HEADER_BYTES};
pub use crate::envelope::{MODEL_MAGIC, MODEL_VERSION};
use crate::error::{BlobKind, Error, Result};
pub use crate::error::{ConfigField, TensorName, TensorPart};
pub use crate::limits::{
    MAX_CLASSIFIER_BLOCKS, MAX_ENCODER_BLOCKS, MAX_FEATURE_DIM, MAX_HEADS, MAX_KNN,
    MAX_SINKHORN_ITERS, SELF_LAYERS,
};

/// Storage precision of the weight matrices.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Precision {
    /// IEEE single precision.
    F32,
    /// IEEE half precision.
    F16,
    /// Signed 8-bit with one f32 scale per output row.
    Int8,
}

impl Precision {
    /// Bytes per stored weight.
    pub const fn bytes_per_weight(self) -> usize {
        match self {
            Precision::F32 => 4,
            Precision::F16 => 2,
            Precision::Int8 => 1,
        }
    }
}

/// Architecture and inference hyper-parameters carried by the blob (supp. "Implementation
/// Details"; the reference values are in [`ModelConfig::REFERENCE`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ModelConfig {
    /// Feature width `d` of encoder and attention (reference 128).
    pub feature_dim: u16,
    /// Residual blocks of the point encoder (reference 12).
    pub encoder_blocks: u8,
    /// Width of the match classifier (reference 128).
    pub classifier_dim: u16,
    /// Residual blocks of the match classifier (reference 4).
    pub classifier_blocks: u8,
    /// Cross-attention heads; must divide `feature_dim` (reference 4).
    pub heads: u8,
    /// Neighbours of the self-attention graph (reference 10).
    pub knn: u8,
    /// Most Sinkhorn iterations (reference 20).
    pub sinkhorn_iters: u8,
    /// Entropic regularisation of Sinkhorn (reference 0.1).
    pub sinkhorn_eps: f32,
    /// Early stop when `||u - u_prev||_2` falls below this (reference 1e-6).
    pub sinkhorn_stop: f32,
    /// Classifier probability above which a match is kept (reference 0.5).
    pub match_threshold: f32,
    /// Learned dustbin cost (the reference's `bin_score`).
    pub bin_score: f32,
}

impl ModelConfig {
    /// A tiny configuration for tests and simulations that run many localizations: d = 8,
    /// one residual block each, 2 heads, k = 3 (the reference's Sinkhorn settings).
    pub const TINY: ModelConfig = ModelConfig {
        feature_dim: 8,
        encoder_blocks: 1,
        classifier_dim: 8,
        classifier_blocks: 1,
        heads: 2,
        knn: 3,
        sinkhorn_iters: 20,
        sinkhorn_eps: 0.1,
        sinkhorn_stop: 1e-6,
        match_threshold: 0.5,
        bin_score: 1.0,
    };

    /// The configuration of the paper and the reference checkpoint.
    pub const REFERENCE: ModelConfig = ModelConfig {
        feature_dim: 128,
        encoder_blocks: 12,
        classifier_dim: 128,
        classifier_blocks: 4,
        heads: 4,
        knn: 10,
        sinkhorn_iters: 20,
        sinkhorn_eps: 0.1,
        sinkhorn_stop: 1e-6,
        match_threshold: 0.5,
        bin_score: 1.0,
    };

    /// Checks every field against the compiled maximums and the network's constraints.
    pub fn validate(&self) -> Result<()> {
        let d = usize::from(self.feature_dim);
        let checks = [
            (ConfigField::FeatureDim, d, 1, MAX_FEATURE_DIM),
            (
                ConfigField::EncoderBlocks,
                usize::from(self.encoder_blocks),
                0,
                MAX_ENCODER_BLOCKS,
            ),
            (
                ConfigField::ClassifierDim,
                usize::from(self.classifier_dim),
                1,
                MAX_FEATURE_DIM,
            ),
            (
                ConfigField::ClassifierBlocks,
                usize::from(self.classifier_blocks),
                0,
                MAX_CLASSIFIER_BLOCKS,
            ),
            (ConfigField::Heads, usize::from(self.heads), 1, MAX_HEADS),
            (ConfigField::Knn, usize::from(self.knn), 1, MAX_KNN),
            (
                ConfigField::SinkhornIters,
                usize::from(self.sinkhorn_iters),
                1,
                MAX_SINKHORN_ITERS,
            ),
        ];
        for (field, value, min, max) in checks {
            if value < min || value > max {
                return Err(Error::UnsupportedConfig {
                    field,
                    value: value as u32,
                    max: max as u32,
                });
            }
        }
        if d % usize::from(self.heads) != 0 {
            return Err(Error::UnsupportedConfig {
                field: ConfigField::Heads,
                value: u32::from(self.heads),
                max: self.feature_dim as u32,
            });
        }
        let reals = [
            (ConfigField::SinkhornEps, self.sinkhorn_eps, true),
            (ConfigField::SinkhornStop, self.sinkhorn_stop, false),
            (ConfigField::MatchThreshold, self.match_threshold, false),
            (ConfigField::BinScore, self.bin_score, false),
        ];
        for (field, value, positive) in reals {
            if !value.is_finite() || (positive && value <= 0.0) {
                return Err(Error::InvalidConfigValue { field });
            }
        }
        Ok(())
    }
}

/// Header of the postcard payload.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BlobHeader {
    /// Architecture configuration.
    pub config: ModelConfig,
    /// Nominal precision of the weight matrices (each record states its own).
    pub precision: Precision,
    /// Number of tensor records that follow.
    pub tensor_count: u16,
}

/// One stored tensor: a per-point linear layer, borrowed from the blob.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TensorRecord<'a> {
    /// Output channels.
    pub rows: u32,
    /// Input channels.
    pub cols: u32,
    /// Precision of this tensor's weights.
    pub precision: Precision,
    /// `rows * cols` weights, row-major, in `precision`.
    #[serde(borrow)]
    pub weights: &'a [u8],
    /// Int8 only: `rows` f32 scales; empty otherwise.
    #[serde(borrow)]
    pub scales: &'a [u8],
    /// `rows` f32 biases, or empty for a layer without bias.
    #[serde(borrow)]
    pub bias: &'a [u8],
}

/// Expected name and shape of one tensor of the blob.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TensorSpec {
    /// Its name.
    pub name: TensorName,
    /// Output channels.
    pub rows: usize,
    /// Input channels.
    pub cols: usize,
    /// Whether it carries a bias.
    pub bias: bool,
    /// Whether it may be stored empty, folded into the next tensor ([`Downstream::Folds`]).
    pub foldable: bool,
}

const fn spec(
    role: &'static str,
    index: usize,
    rows: usize,
    cols: usize,
    bias: bool,
    foldable: bool,
) -> TensorSpec {
    TensorSpec {
        name: TensorName {
            role,
            index: index as u8,
        },
        rows,
        cols,
        bias,
        foldable,
    }
}

/// A tensor dimension in units of the configuration's widths.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Width {
    /// A fixed number of channels.
    Fixed(usize),
    /// A multiple of the feature width `d`.
    Features(usize),
    /// A multiple of the classifier width `c`.
    Classifier(usize),
}

impl Width {
    /// Channels under `config`.
    pub fn channels(self, config: &ModelConfig) -> usize {
        match self {
            Width::Fixed(n) => n,
            Width::Features(m) => m * usize::from(config.feature_dim),
            Width::Classifier(m) => m * usize::from(config.classifier_dim),
        }
    }
}

/// What the network does with a tensor's output before anything else sees it, as far as
/// an error in that output goes (supp. "Architecture Details"); the int8 calibration
/// (`gomatch-tools`) forms each tensor's input moments from it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Downstream {
    /// Used as it is: projections, the residual stream, the classifier's logit.
    Direct,
    /// An instance norm follows, directly or through the next linear layer, so an error
    /// that is constant over the set vanishes.
    Norm,
    /// The centre half of an EdgeConv: with the next tensor, its neighbour half, it acts on
    /// the edge `[x_i; x_j - x_i]`, and an instance norm follows.
    EdgeCentre,
    /// The neighbour half of an EdgeConv (the tensor before it is the centre half).
    EdgeNeighbour,
    /// The next tensor, with no activation between, then an instance norm: a residual
    /// block's `preconv`. A blob may store it folded into the next tensor
    /// (`W1 (W0 x + b0) + b1 = (W1 W0) x + (W1 b0 + b1)`), as an empty 0 x 0 tensor
    /// without bias ([`ResidualBlockWeights::folded`]).
    Folds,
}

/// One tensor of a layer: its role (name in errors and reports), output and input
/// channels, whether it has a bias, and what follows it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LayerTensor {
    /// Role, e.g. `self.fuse`.
    pub role: &'static str,
    /// Output channels.
    pub rows: Width,
    /// Input channels.
    pub cols: Width,
    /// Whether it carries a bias.
    pub bias: bool,
    /// What follows its output.
    pub downstream: Downstream,
}

const fn tensor(
    role: &'static str,
    rows: Width,
    cols: Width,
    bias: bool,
    downstream: Downstream,
) -> LayerTensor {
    LayerTensor {
        role,
        rows,
        cols,
        bias,
        downstream,
    }
}

/// The layers of a model blob in blob order, each repeated [`Section::repeats`] times and
/// holding [`Section::tensors`]: the one declaration of the blob layout, read by the
/// loader ([`Model::from_bytes`]), the converter and its calibration pass (`gomatch-tools`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Section {
    /// The encoder's input convolution (supp. "Feature Encoder").
    EncoderInput,
    /// An encoder residual block.
    EncoderBlock,
    /// An EdgeConv self-attention layer (attention layers 0 and 2).
    SelfLayer,
    /// The cross-attention layer (attention layer 1).
    CrossLayer,
    /// The classifier's input convolution on `[f2d, f3d]`.
    ClassifierInput,
    /// A classifier residual block.
    ClassifierBlock,
    /// The classifier's output convolution.
    ClassifierOutput,
}

impl Section {
    /// Blob order.
    pub const ORDER: [Section; 7] = [
        Section::EncoderInput,
        Section::EncoderBlock,
        Section::SelfLayer,
        Section::CrossLayer,
        Section::ClassifierInput,
        Section::ClassifierBlock,
        Section::ClassifierOutput,
    ];

    /// The tensors of one instance, in blob order.
    pub const fn tensors(self) -> &'static [LayerTensor] {
        match self {
            Section::EncoderInput => &EncoderWeights::INPUT_TENSORS,
            Section::EncoderBlock => &ResidualBlockWeights::ENCODER_TENSORS,
            Section::SelfLayer => &SelfLayerWeights::TENSORS,
            Section::CrossLayer => &CrossLayerWeights::TENSORS,
            Section::ClassifierInput => &ClassifierWeights::INPUT_TENSORS,
            Section::ClassifierBlock => &ResidualBlockWeights::CLASSIFIER_TENSORS,
            Section::ClassifierOutput => &ClassifierWeights::OUTPUT_TENSORS,
        }
    }

    /// Instances of the section under `config`.
    pub fn repeats(self, config: &ModelConfig) -> usize {
        match self {
            Section::EncoderBlock => usize::from(config.encoder_blocks),
            Section::SelfLayer => SELF_LAYERS,
            Section::ClassifierBlock => usize::from(config.classifier_blocks),
            _ => 1,
        }
    }

    fn len(self, config: &ModelConfig) -> usize {
        self.tensors().len() * self.repeats(config)
    }
}

/// Where a tensor sits in the layout: `part` of instance `instance` of `section`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TensorSlot {
    /// The layer kind.
    pub section: Section,
    /// Which repetition (block or layer index).
    pub instance: usize,
    /// Position in [`Section::tensors`].
    pub part: usize,
}

impl TensorSlot {
    /// The declaration of the tensor in this slot.
    pub fn tensor(self) -> Option<LayerTensor> {
        self.section.tensors().get(self.part).copied()
    }
}

/// The slot of tensor `index` (blob order), or `None` past the last one.
pub fn locate(config: &ModelConfig, index: usize) -> Option<TensorSlot> {
    let mut i = index;
    for section in Section::ORDER {
        let per = section.tensors().len();
        if i < section.len(config) {
            return Some(TensorSlot {
                section,
                instance: i / per,
                part: i % per,
            });
        }
        i -= section.len(config);
    }
    None
}

/// Blob index of `part` of instance `instance` of `section`, or `None` when the
/// configuration has no such tensor.
pub fn tensor_index(
    config: &ModelConfig,
    section: Section,
    instance: usize,
    part: usize,
) -> Option<usize> {
    let before: usize = Section::ORDER
        .iter()
        .take_while(|&&s| s != section)
        .map(|s| s.len(config))
        .sum();
    let per = section.tensors().len();
    (instance < section.repeats(config) && part < per).then_some(before + instance * per + part)
}

/// Number of tensors a blob with this configuration holds.
pub fn tensor_count(config: &ModelConfig) -> usize {
    Section::ORDER.iter().map(|s| s.len(config)).sum()
}

/// Name and shape of tensor `index` in blob order ([`Section::ORDER`]), or `None` past
/// the last one.
pub fn tensor_spec(config: &ModelConfig, index: usize) -> Option<TensorSpec> {
    let slot = locate(config, index)?;
    let t = slot.tensor()?;
    Some(spec(
        t.role,
        slot.instance,
        t.rows.channels(config),
        t.cols.channels(config),
        t.bias,
        matches!(t.downstream, Downstream::Folds),
    ))
}

/// A per-point linear layer `y = s * (W x) + b` borrowed from the blob.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Linear<'a> {
    tensor: usize,
    rows: usize,
    cols: usize,
    precision: Precision,
    weights: &'a [u8],
    scales: &'a [u8],
    bias: &'a [u8],
}

impl<'a> Linear<'a> {
    /// A 0 x 0 layer, the filler of unused block slots.
    pub const EMPTY: Linear<'static> = Linear {
        tensor: usize::MAX,
        rows: 0,
        cols: 0,
        precision: Precision::F32,
        weights: &[],
        scales: &[],
        bias: &[],
    };

    /// Blob index of the tensor ([`locate`]; `usize::MAX` for [`Linear::EMPTY`]).
    pub fn tensor(&self) -> usize {
        self.tensor
    }

    /// Output channels.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Input channels.
    pub fn cols(&self) -> usize {
        self.cols
    }

    /// Storage precision.
    pub fn precision(&self) -> Precision {
        self.precision
    }

    /// Decodes columns `cols.start..cols.end` of row `row` into `out` as f32, before the
    /// per-row scale. The caller keeps `row < rows` and `cols.end <= self.cols()`.
    pub fn decode_row(&self, row: usize, start: usize, out: &mut [f32]) {
        let first = row * self.cols + start;
        match self.precision {
            Precision::F32 => {
                let bytes = &self.weights[first * 4..(first + out.len()) * 4];
                for (o, b) in out.iter_mut().zip(bytes.chunks_exact(4)) {
                    *o = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                }
            }
            Precision::F16 => {
                let bytes = &self.weights[first * 2..(first + out.len()) * 2];
                for (o, b) in out.iter_mut().zip(bytes.chunks_exact(2)) {
                    *o = half::f16::from_bits(u16::from_le_bytes([b[0], b[1]])).to_f32();
                }
            }
            Precision::Int8 => {
                let bytes = &self.weights[first..first + out.len()];
                for (o, &b) in out.iter_mut().zip(bytes) {
                    *o = f32::from(b as i8);
                }
            }
        }
    }

    /// The stored int8 weights of row `row`, columns `start..start + len` (two's complement
    /// bytes, zero-copy), or `None` unless the layer is int8.
    pub fn int8_row(&self, row: usize, start: usize, len: usize) -> Option<&'a [u8]> {
        let first = row * self.cols + start;
        match self.precision {
            Precision::Int8 => self.weights.get(first..first + len),
            Precision::F32 | Precision::F16 => None,
        }
    }

    /// Scale applied to the accumulated product of row `row` (1 unless int8).
    pub fn scale(&self, row: usize) -> f32 {
        read_f32(self.scales, row).unwrap_or(1.0)
    }

    /// Bias of row `row` (0 for a layer without bias).
    pub fn bias(&self, row: usize) -> f32 {
        read_f32(self.bias, row).unwrap_or(0.0)
    }
}

fn read_f32(bytes: &[u8], index: usize) -> Option<f32> {
    let start = index.checked_mul(4)?;
    let b = bytes.get(start..start.checked_add(4)?)?;
    Some(f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
}

/// Tensors of one residual block in the blob: preconv, conv1, conv2.
pub const RESIDUAL_BLOCK_TENSORS: usize = 3;

/// One residual block of a point ResNet (supp. Fig. "Residual Block"), as the reference
/// stores it: `preconv`, `conv1`, `conv2`, each with its bias; or folded, with an empty
/// `preconv` and `conv1` holding `W1 W0` and `W1 b0 + b1` ([`Downstream::Folds`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ResidualBlockWeights<'a> {
    /// `preconv` (no norm, no activation); 0 x 0 where folded into `conv1`.
    pub preconv: Linear<'a>,
    /// `conv1` (instance norm follows).
    pub conv1: Linear<'a>,
    /// `conv2` (instance norm, ReLU and the skip follow).
    pub conv2: Linear<'a>,
}

impl<'a> ResidualBlockWeights<'a> {
    const EMPTY: ResidualBlockWeights<'static> = ResidualBlockWeights {
        preconv: Linear::EMPTY,
        conv1: Linear::EMPTY,
        conv2: Linear::EMPTY,
    };

    /// An encoder block's tensors in blob order (d -> d, with bias).
    pub const ENCODER_TENSORS: [LayerTensor; RESIDUAL_BLOCK_TENSORS] = [
        tensor(
            "encoder.block.preconv",
            Width::Features(1),
            Width::Features(1),
            true,
            Downstream::Folds,
        ),
        tensor(
            "encoder.block.conv1",
            Width::Features(1),
            Width::Features(1),
            true,
            Downstream::Norm,
        ),
        tensor(
            "encoder.block.conv2",
            Width::Features(1),
            Width::Features(1),
            true,
            Downstream::Norm,
        ),
    ];
    /// A classifier block's tensors in blob order (c -> c, with bias).
    pub const CLASSIFIER_TENSORS: [LayerTensor; RESIDUAL_BLOCK_TENSORS] = [
        tensor(
            "classifier.block.preconv",
            Width::Classifier(1),
            Width::Classifier(1),
            true,
            Downstream::Folds,
        ),
        tensor(
            "classifier.block.conv1",
            Width::Classifier(1),
            Width::Classifier(1),
            true,
            Downstream::Norm,
        ),
        tensor(
            "classifier.block.conv2",
            Width::Classifier(1),
            Width::Classifier(1),
            true,
            Downstream::Norm,
        ),
    ];

    /// Whether `preconv` is folded into `conv1` (stored empty).
    pub fn folded(&self) -> bool {
        self.preconv.rows() == 0
    }

    /// The convolution at position `part` of the block's tensors.
    fn slot(&mut self, part: usize) -> &mut Linear<'a> {
        match part {
            0 => &mut self.preconv,
            1 => &mut self.conv1,
            _ => &mut self.conv2,
        }
    }
}

/// Weights of the shared point encoder.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EncoderWeights<'a> {
    /// `conv_in`: 2 -> d with bias.
    pub input: Linear<'a>,
    /// Residual blocks, the first `count` are used.
    pub blocks: [ResidualBlockWeights<'a>; MAX_ENCODER_BLOCKS],
    /// Number of blocks.
    pub count: usize,
}

/// Weights of one EdgeConv self-attention layer (supp. eq. 4-5), factored per point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SelfLayerWeights<'a> {
    /// First edge conv, centre part `Wa - Wb` (d -> d).
    pub edge1_centre: Linear<'a>,
    /// First edge conv, neighbour part `Wb` (d -> d).
    pub edge1_neighbour: Linear<'a>,
    /// Second edge conv, centre part (d -> 2d).
    pub edge2_centre: Linear<'a>,
    /// Second edge conv, neighbour part (d -> 2d).
    pub edge2_neighbour: Linear<'a>,
    /// Fusing conv on `[x0, x1, x2]` (4d -> d).
    pub fuse: Linear<'a>,
}

impl EncoderWeights<'_> {
    /// `conv_in` (2 -> d, with bias).
    pub const INPUT_TENSORS: [LayerTensor; 1] = [tensor(
        "encoder.input",
        Width::Features(1),
        Width::Fixed(2),
        true,
        Downstream::Direct,
    )];
}

impl<'a> SelfLayerWeights<'a> {
    /// Part of [`Self::TENSORS`]: first edge conv, centre (the neighbour part follows).
    pub const EDGE1: usize = 0;
    /// Part of [`Self::TENSORS`]: second edge conv, centre (the neighbour part follows).
    pub const EDGE2: usize = 2;
    /// Part of [`Self::TENSORS`]: the fusing conv.
    pub const FUSE: usize = 4;
    /// Its tensors in blob order.
    pub const TENSORS: [LayerTensor; 5] = [
        tensor(
            "self.edge1_centre",
            Width::Features(1),
            Width::Features(1),
            false,
            Downstream::EdgeCentre,
        ),
        tensor(
            "self.edge1_neighbour",
            Width::Features(1),
            Width::Features(1),
            false,
            Downstream::EdgeNeighbour,
        ),
        tensor(
            "self.edge2_centre",
            Width::Features(2),
            Width::Features(1),
            false,
            Downstream::EdgeCentre,
        ),
        tensor(
            "self.edge2_neighbour",
            Width::Features(2),
            Width::Features(1),
            false,
            Downstream::EdgeNeighbour,
        ),
        tensor(
            "self.fuse",
            Width::Features(1),
            Width::Features(4),
            false,
            Downstream::Norm,
        ),
    ];

    fn slot(&mut self, part: usize) -> &mut Linear<'a> {
        match part {
            0 => &mut self.edge1_centre,
            1 => &mut self.edge1_neighbour,
            2 => &mut self.edge2_centre,
            3 => &mut self.edge2_neighbour,
            _ => &mut self.fuse,
        }
    }
}

/// Weights of the multi-head cross-attention layer (supp. eq. 6-8).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CrossLayerWeights<'a> {
    /// Query projection.
    pub query: Linear<'a>,
    /// Key projection.
    pub key: Linear<'a>,
    /// Value projection.
    pub value: Linear<'a>,
    /// Merge of the heads.
    pub merge: Linear<'a>,
    /// Message MLP hidden layer on `[x, message]` (2d -> 2d, instance norm follows).
    pub mlp_hidden: Linear<'a>,
    /// Message MLP output (2d -> d).
    pub mlp_out: Linear<'a>,
}

impl<'a> CrossLayerWeights<'a> {
    /// Part of [`Self::TENSORS`]: the query projection.
    pub const QUERY: usize = 0;
    /// Part of [`Self::TENSORS`]: the key projection.
    pub const KEY: usize = 1;
    /// Part of [`Self::TENSORS`]: the value projection.
    pub const VALUE: usize = 2;
    /// Part of [`Self::TENSORS`]: the merge of the heads.
    pub const MERGE: usize = 3;
    /// Part of [`Self::TENSORS`]: the message MLP's hidden layer.
    pub const MLP_HIDDEN: usize = 4;
    /// Part of [`Self::TENSORS`]: the message MLP's output.
    pub const MLP_OUT: usize = 5;
    /// Its tensors in blob order.
    pub const TENSORS: [LayerTensor; 6] = [
        tensor(
            "cross.query",
            Width::Features(1),
            Width::Features(1),
            true,
            Downstream::Direct,
        ),
        tensor(
            "cross.key",
            Width::Features(1),
            Width::Features(1),
            true,
            Downstream::Direct,
        ),
        tensor(
            "cross.value",
            Width::Features(1),
            Width::Features(1),
            true,
            Downstream::Direct,
        ),
        tensor(
            "cross.merge",
            Width::Features(1),
            Width::Features(1),
            true,
            Downstream::Direct,
        ),
        tensor(
            "cross.mlp_hidden",
            Width::Features(2),
            Width::Features(2),
            false,
            Downstream::Norm,
        ),
        tensor(
            "cross.mlp_out",
            Width::Features(1),
            Width::Features(2),
            true,
            Downstream::Direct,
        ),
    ];

    fn slot(&mut self, part: usize) -> &mut Linear<'a> {
        match part {
            Self::QUERY => &mut self.query,
            Self::KEY => &mut self.key,
            Self::VALUE => &mut self.value,
            Self::MERGE => &mut self.merge,
            Self::MLP_HIDDEN => &mut self.mlp_hidden,
            _ => &mut self.mlp_out,
        }
    }
}

/// Weights of the outlier classifier (supp. "Outlier Rejection").
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClassifierWeights<'a> {
    /// `conv_in`: 2d -> c with bias, on `[f2d, f3d]`.
    pub input: Linear<'a>,
    /// Residual blocks, the first `count` are used.
    pub blocks: [ResidualBlockWeights<'a>; MAX_CLASSIFIER_BLOCKS],
    /// Number of blocks.
    pub count: usize,
    /// `conv_out`: c -> 1 with bias, then sigmoid.
    pub output: Linear<'a>,
}

impl ClassifierWeights<'_> {
    /// `conv_in` (2d -> c, with bias).
    pub const INPUT_TENSORS: [LayerTensor; 1] = [tensor(
        "classifier.input",
        Width::Classifier(1),
        Width::Features(2),
        true,
        Downstream::Direct,
    )];
    /// `conv_out` (c -> 1, with bias).
    pub const OUTPUT_TENSORS: [LayerTensor; 1] = [tensor(
        "classifier.output",
        Width::Fixed(1),
        Width::Classifier(1),
        true,
        Downstream::Direct,
    )];
}

/// A loaded model: configuration and borrowed, shape-checked tensors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Model<'a> {
    config: ModelConfig,
    precision: Precision,
    checksum: u32,
    /// Point encoder shared by 2D and 3D.
    pub encoder: EncoderWeights<'a>,
    /// The two self-attention layers (attention layers 0 and 2).
    pub self_layers: [SelfLayerWeights<'a>; SELF_LAYERS],
    /// The cross-attention layer (attention layer 1).
    pub cross: CrossLayerWeights<'a>,
    /// Outlier classifier.
    pub classifier: ClassifierWeights<'a>,
}

impl<'a> Model<'a> {
    /// Parses and validates a blob in place: magic, version, checksum, configuration
    /// against the compiled maximums, then every tensor's shape and byte length.
    pub fn from_bytes(blob: &'a [u8]) -> Result<Model<'a>> {
        let payload = envelope::open(BlobKind::Model, blob)?;
        let offset_of = |rest: &[u8]| HEADER_BYTES + payload.len() - rest.len();
        let (header, mut rest): (BlobHeader, &'a [u8]) = postcard::take_from_bytes(payload)
            .map_err(|_| Error::ModelMalformed {
                offset: HEADER_BYTES,
            })?;
        header.config.validate()?;
        let expected = tensor_count(&header.config);
        if usize::from(header.tensor_count) != expected {
            return Err(Error::TensorCount {
                expected,
                found: usize::from(header.tensor_count),
            });
        }
        let mut model = Model {
            config: header.config,
            precision: header.precision,
            checksum: envelope::crc32(payload),
            encoder: EncoderWeights {
                input: Linear::EMPTY,
                blocks: [ResidualBlockWeights::EMPTY; MAX_ENCODER_BLOCKS],
                count: usize::from(header.config.encoder_blocks),
            },
            self_layers: [SelfLayerWeights {
                edge1_centre: Linear::EMPTY,
                edge1_neighbour: Linear::EMPTY,
                edge2_centre: Linear::EMPTY,
                edge2_neighbour: Linear::EMPTY,
                fuse: Linear::EMPTY,
            }; SELF_LAYERS],
            cross: CrossLayerWeights {
                query: Linear::EMPTY,
                key: Linear::EMPTY,
                value: Linear::EMPTY,
                merge: Linear::EMPTY,
                mlp_hidden: Linear::EMPTY,
                mlp_out: Linear::EMPTY,
            },
            classifier: ClassifierWeights {
                input: Linear::EMPTY,
                blocks: [ResidualBlockWeights::EMPTY; MAX_CLASSIFIER_BLOCKS],
                count: usize::from(header.config.classifier_blocks),
                output: Linear::EMPTY,
            },
        };
        for index in 0..expected {
            let offset = offset_of(rest);
            let (record, tail): (TensorRecord<'a>, &'a [u8]) =
                postcard::take_from_bytes(rest).map_err(|_| Error::ModelMalformed { offset })?;
            rest = tail;
            // `index < expected` so the spec exists.
            let Some(spec) = tensor_spec(&header.config, index) else {
                return Err(Error::TensorCount {
                    expected,
                    found: index,
                });
            };
            let linear = check_record(&record, &spec, index, offset)?;
            model.place(index, linear);
        }
        if !rest.is_empty() {
            return Err(Error::ModelMalformed {
                offset: offset_of(rest),
            });
        }
        Ok(model)
    }

    /// Architecture configuration.
    pub fn config(&self) -> &ModelConfig {
        &self.config
    }

    /// Nominal weight precision (each tensor has its own, see [`Linear::precision`]).
    pub fn precision(&self) -> Precision {
        self.precision
    }

    /// The CRC-32 of the blob's payload: which model this is, for data computed with it
    /// ([`crate::view_features`]).
    pub fn checksum(&self) -> u32 {
        self.checksum
    }

    /// Puts tensor `index` (blob order, [`locate`]) in its slot.
    fn place(&mut self, index: usize, linear: Linear<'a>) {
        let Some(TensorSlot {
            section,
            instance,
            part,
        }) = locate(&self.config, index)
        else {
            return;
        };
        let slot = match section {
            Section::EncoderInput => Some(&mut self.encoder.input),
            Section::EncoderBlock => self.encoder.blocks.get_mut(instance).map(|b| b.slot(part)),
            Section::SelfLayer => self.self_layers.get_mut(instance).map(|l| l.slot(part)),
            Section::CrossLayer => Some(self.cross.slot(part)),
            Section::ClassifierInput => Some(&mut self.classifier.input),
            Section::ClassifierBlock => self
                .classifier
                .blocks
                .get_mut(instance)
                .map(|b| b.slot(part)),
            Section::ClassifierOutput => Some(&mut self.classifier.output),
        };
        if let Some(slot) = slot {
            *slot = linear;
        }
    }
}

/// Checks one record (tensor `index`, at byte `offset` of the blob) against its expected
/// shape and byte lengths.
fn check_record<'a>(
    record: &TensorRecord<'a>,
    spec: &TensorSpec,
    index: usize,
    offset: usize,
) -> Result<Linear<'a>> {
    let precision = record.precision;
    let (rows, cols) = (record.rows as usize, record.cols as usize);
    let folded = spec.foldable && rows == 0 && cols == 0;
    if (rows != spec.rows || cols != spec.cols) && !folded {
        return Err(Error::TensorShape {
            tensor: spec.name,
            expected: [spec.rows, spec.cols],
            found: [rows, cols],
        });
    }
    // Checked: the shape equals the specification's, but no offset may wrap on a 32-bit
    // target whatever the configuration.
    let bytes = |count: Option<usize>, per_entry: usize| {
        count
            .and_then(|c| c.checked_mul(per_entry))
            .ok_or(Error::ModelMalformed { offset })
    };
    let row_values = bytes(Some(rows), 4)?;
    let lengths = [
        (
            TensorPart::Weights,
            record.weights.len(),
            bytes(rows.checked_mul(cols), precision.bytes_per_weight())?,
        ),
        (
            TensorPart::Scales,
            record.scales.len(),
            if precision == Precision::Int8 {
                row_values
            } else {
                0
            },
        ),
        (
            TensorPart::Bias,
            record.bias.len(),
            if spec.bias && !folded { row_values } else { 0 },
        ),
    ];
    for (part, found, expected) in lengths {
        if found != expected {
            return Err(Error::TensorBytes {
                tensor: spec.name,
                part,
                expected,
                found,
            });
        }
    }
    Ok(Linear {
        tensor: index,
        rows,
        cols,
        precision,
        weights: record.weights,
        scales: record.scales,
        bias: record.bias,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reference_layout_has_the_reference_parameter_count() {
        let config = ModelConfig::REFERENCE;
        assert_eq!(tensor_count(&config), 1 + 36 + 10 + 6 + 1 + 12 + 1);
        let mut weights = 0;
        let mut index = 0;
        while let Some(s) = tensor_spec(&config, index) {
            weights += s.rows * s.cols;
            index += 1;
        }
        assert_eq!(index, tensor_count(&config));
        let d = 128;
        let reference_weights = 2 * d + 12 * 3 * d * d // encoder
            + 2 * (2 * d * d + 4 * d * d + 4 * d * d) // self layers
            + 4 * d * d + 4 * d * d + 2 * d * d // cross
            + 2 * d * d + 4 * 3 * d * d + d; // classifier
        assert_eq!(weights, reference_weights);
    }

    #[test]
    fn envelope_errors_name_the_model_blob() {
        assert_eq!(
            Model::from_bytes(&[1, 2, 3]),
            Err(Error::BlobTruncated {
                blob: BlobKind::Model,
                needed: HEADER_BYTES,
                found: 3
            })
        );
        let mut map = [0u8; HEADER_BYTES];
        envelope::seal(BlobKind::Map, &mut map, 0).expect("empty payload");
        assert_eq!(
            Model::from_bytes(&map),
            Err(Error::BlobMagic {
                blob: BlobKind::Model,
                found: *b"GMAP"
            })
        );
    }

    #[test]
    fn config_limits_are_enforced() {
        let mut config = ModelConfig::REFERENCE;
        assert_eq!(config.validate(), Ok(()));
        config.feature_dim = 256;
        assert_eq!(
            config.validate(),
            Err(Error::UnsupportedConfig {
                field: ConfigField::FeatureDim,
                value: 256,
                max: 128
            })
        );
        config.feature_dim = 96;
        config.heads = 5;
        assert!(matches!(
            config.validate(),
            Err(Error::UnsupportedConfig {
                field: ConfigField::Heads,
                ..
            })
        ));
        config.heads = 3;
        assert_eq!(config.validate(), Ok(()));
        config.sinkhorn_eps = 0.0;
        assert_eq!(
            config.validate(),
            Err(Error::InvalidConfigValue {
                field: ConfigField::SinkhornEps
            })
        );
    }

    #[test]
    fn int8_rows_decode_to_integers_and_scale() {
        let weights = [1u8, 255, 127, 129];
        let scales = [0.5f32.to_le_bytes(), 2.0f32.to_le_bytes()].concat_bytes();
        let linear = Linear {
            tensor: 0,
            rows: 2,
            cols: 2,
            precision: Precision::Int8,
            weights: &weights,
            scales: &scales,
            bias: &[],
        };
        let mut out = [0.0; 2];
        linear.decode_row(1, 0, &mut out);
        assert_eq!(out, [127.0, -127.0]);
        linear.decode_row(0, 1, &mut out[..1]);
        assert_eq!(out[0], -1.0);
        assert_eq!(linear.scale(1), 2.0);
        assert_eq!(linear.bias(0), 0.0);
    }

    #[test]
    fn a_written_blob_loads_and_every_corruption_is_an_error() {
        let mut buf = [0u8; 32 * 1024];
        let len = tests_support::blob(&tests_support::TINY, 7, &mut buf);
        let blob = &buf[..len];
        let model = Model::from_bytes(blob).expect("valid blob");
        assert_eq!(*model.config(), tests_support::TINY);
        assert_eq!(model.encoder.input.rows(), 8);
        assert_eq!(model.classifier.output.cols(), 8);
        assert_eq!(
            Model::from_bytes(&blob[..len - 1]).map(|_| ()),
            Err(Error::BlobTruncated {
                blob: BlobKind::Model,
                needed: len,
                found: len - 1,
            })
        );
        let mut flipped = [0u8; 32 * 1024];
        flipped[..len].copy_from_slice(blob);
        flipped[len / 2] ^= 0x10;
        assert!(matches!(
            Model::from_bytes(&flipped[..len]),
            Err(Error::BlobChecksum { .. })
        ));
    }

    /// EdgeConv halves come in (centre, neighbour) pairs of one section, of one shape; a
    /// foldable tensor is followed by a layer on its output and an instance norm.
    #[test]
    fn edge_halves_are_declared_in_pairs() {
        for section in Section::ORDER {
            let tensors = section.tensors();
            for (part, t) in tensors.iter().enumerate() {
                let next = tensors.get(part + 1);
                let before = part.checked_sub(1).map(|p| tensors[p].downstream);
                match t.downstream {
                    Downstream::EdgeCentre => {
                        let n = next.expect("a centre half has a neighbour half");
                        assert_eq!(n.downstream, Downstream::EdgeNeighbour, "{}", t.role);
                        assert_eq!((n.rows, n.cols), (t.rows, t.cols), "{}", t.role);
                    }
                    Downstream::EdgeNeighbour => {
                        assert_eq!(before, Some(Downstream::EdgeCentre), "{}", t.role)
                    }
                    Downstream::Folds => {
                        let n = next.expect("a folding tensor has a next tensor");
                        assert_eq!(n.downstream, Downstream::Norm, "{}", t.role);
                        assert_eq!(n.cols, t.rows, "{}", t.role);
                    }
                    Downstream::Direct | Downstream::Norm => {}
                }
            }
        }
        let edges = SelfLayerWeights::TENSORS
            .iter()
            .filter(|t| t.downstream == Downstream::EdgeCentre)
            .count();
        assert_eq!(edges, 2, "two EdgeConv layers per self layer");
    }

    #[test]
    fn a_wrong_shape_names_the_tensor() {
        let mut config = tests_support::TINY;
        let mut buf = [0u8; 32 * 1024];
        let len = tests_support::blob(&config, 1, &mut buf);
        // Re-label the header: the same tensors now claim a 2-head, 16-wide model.
        config.feature_dim = 16;
        let mut relabelled = [0u8; 32 * 1024];
        let original = postcard::take_from_bytes::<BlobHeader>(&buf[HEADER_BYTES..len])
            .expect("header")
            .1;
        let header = BlobHeader {
            config,
            precision: Precision::F32,
            tensor_count: tensor_count(&config) as u16,
        };
        let written = postcard::to_slice(&header, &mut relabelled[HEADER_BYTES..])
            .expect("fits")
            .len();
        let start = HEADER_BYTES + written;
        relabelled[start..start + original.len()].copy_from_slice(original);
        let sealed = envelope::seal(BlobKind::Model, &mut relabelled, written + original.len())
            .expect("fits");
        assert_eq!(
            Model::from_bytes(&relabelled[..sealed]),
            Err(Error::TensorShape {
                tensor: TensorName {
                    role: "encoder.input",
                    index: 0
                },
                expected: [16, 2],
                found: [8, 2],
            })
        );
    }

    proptest::proptest! {
        /// Arbitrary bytes, with or without a valid envelope, never panic the decoder.
        #[test]
        fn arbitrary_bytes_never_panic(body in proptest::collection::vec(proptest::num::u8::ANY, 0..600), envelope: bool) {
            let mut buf = [0u8; 700];
            let len = if envelope {
                buf[HEADER_BYTES..HEADER_BYTES + body.len()].copy_from_slice(&body);
                envelope::seal(BlobKind::Model, &mut buf, body.len()).expect("fits")
            } else {
                buf[..body.len()].copy_from_slice(&body);
                body.len()
            };
            let _ = Model::from_bytes(&buf[..len]);
        }

        /// A valid blob with any byte changed and the checksum recomputed is either
        /// accepted or refused with an error, never a panic.
        #[test]
        fn mutated_valid_blobs_never_panic(position in 0usize..4000, value: u8) {
            let mut buf = [0u8; 32 * 1024];
            let len = tests_support::blob(&tests_support::TINY, 3, &mut buf);
            let payload = len - HEADER_BYTES;
            buf[HEADER_BYTES + position % payload] = value;
            envelope::seal(BlobKind::Model, &mut buf, payload).expect("fits");
            let _ = Model::from_bytes(&buf[..len]);
        }
    }

    trait ConcatBytes {
        fn concat_bytes(&self) -> [u8; 8];
    }

    impl ConcatBytes for [[u8; 4]; 2] {
        fn concat_bytes(&self) -> [u8; 8] {
            let mut out = [0; 8];
            out[..4].copy_from_slice(&self[0]);
            out[4..].copy_from_slice(&self[1]);
            out
        }
    }
}

/// Constructors for unit tests of the kernels.
#[cfg(test)]
pub(crate) mod tests_support {
    use super::{
        envelope, tensor_count, tensor_spec, BlobHeader, BlobKind, Linear, ModelConfig, Precision,
        TensorRecord, HEADER_BYTES,
    };

    /// A small configuration for end-to-end tests ([`ModelConfig::TINY`]).
    pub const TINY: ModelConfig = ModelConfig::TINY;

    /// Writes a valid blob of `config` with pseudo-random f32 weights in [-0.5, 0.5)
    /// into `out`; returns its length.
    pub fn blob(config: &ModelConfig, seed: u32, out: &mut [u8]) -> usize {
        let mut state = seed.wrapping_mul(747_796_405).wrapping_add(2_891_336_453);
        let mut next = move || {
            state = state.wrapping_mul(747_796_405).wrapping_add(2_891_336_453);
            (state >> 8) as f32 / (1u32 << 24) as f32 - 0.5
        };
        let mut at = HEADER_BYTES;
        let header = BlobHeader {
            config: *config,
            precision: Precision::F32,
            tensor_count: tensor_count(config) as u16,
        };
        at += postcard::to_slice(&header, &mut out[at..])
            .map(|s| s.len())
            .unwrap_or(0);
        let mut weights = [0u8; 4 * 4 * 128 * 128];
        let mut bias = [0u8; 4 * 2 * 128];
        let mut index = 0;
        while let Some(spec) = tensor_spec(config, index) {
            let count = spec.rows * spec.cols;
            for w in weights[..4 * count].chunks_exact_mut(4) {
                w.copy_from_slice(&next().to_le_bytes());
            }
            let bias_len = if spec.bias { 4 * spec.rows } else { 0 };
            for b in bias[..bias_len].chunks_exact_mut(4) {
                b.copy_from_slice(&next().to_le_bytes());
            }
            let record = TensorRecord {
                rows: spec.rows as u32,
                cols: spec.cols as u32,
                precision: Precision::F32,
                weights: &weights[..4 * count],
                scales: &[],
                bias: &bias[..bias_len],
            };
            at += postcard::to_slice(&record, &mut out[at..])
                .map(|s| s.len())
                .unwrap_or(0);
            index += 1;
        }
        envelope::seal(BlobKind::Model, out, at - HEADER_BYTES).unwrap_or(0)
    }

    /// A layer over borrowed bytes, unchecked.
    pub fn linear<'a>(
        rows: usize,
        cols: usize,
        precision: Precision,
        weights: &'a [u8],
        scales: &'a [u8],
        bias: &'a [u8],
    ) -> Linear<'a> {
        Linear {
            tensor: 0,
            rows,
            cols,
            precision,
            weights,
            scales,
            bias,
        }
    }
}
