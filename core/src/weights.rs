//! The model blob: header, architecture configuration, zero-copy tensors in f32, f16 or int8.
//!
//! The blob is read in place from a borrowed byte slice (flash on a device, a file on the
//! host); no tensor is copied into RAM. Layout, all integers little-endian:
//!
//! ```text
//! [0..4)      magic  b"GMWB"
//! [4..6)      format version (u16), see FORMAT_VERSION
//! [6..len-4)  postcard: BlobHeader { config, precision, tensor_count }
//!             then tensor_count x postcard TensorRecord { rows, cols, weights, scales, bias }
//! [len-4..)   CRC-32 (IEEE) of bytes [0..len-4)
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
//! Residual blocks keep the reference's three convolutions with their biases: folding
//! them (`IN(W1 (W0 x + b0) + b1) = IN((W1 W0) x)`) would save a third of the encoder's
//! work but moves f32 results ~3e-4 away from the reference's (README.md, "Conformance").
//! The converter folds one exact identity into the stored tensors: EdgeConv
//! `W [f_i, f_j - f_i] = (Wa - Wb) f_i + Wb f_j`, so each self layer stores the centre part
//! `Wa - Wb` and the neighbour part `Wb` (a `k`-fold saving; its rounding stays ~1e-5).

use serde::{Deserialize, Serialize};

pub use crate::error::{ConfigField, TensorName, TensorPart};
use crate::error::{Error, Result};
pub use crate::limits::{
    MAX_CLASSIFIER_BLOCKS, MAX_ENCODER_BLOCKS, MAX_FEATURE_DIM, MAX_HEADS, MAX_KNN,
    MAX_SINKHORN_ITERS, SELF_LAYERS,
};

/// First four bytes of every model blob.
pub const MAGIC: [u8; 4] = *b"GMWB";
/// Version of the blob layout this build reads.
pub const FORMAT_VERSION: u16 = 2;

/// Bytes before the postcard payload: magic and version.
const PREAMBLE: usize = 6;
/// Bytes of the trailing checksum.
const CHECKSUM_BYTES: usize = 4;

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
}

const fn spec(
    role: &'static str,
    index: usize,
    rows: usize,
    cols: usize,
    bias: bool,
) -> TensorSpec {
    TensorSpec {
        name: TensorName {
            role,
            index: index as u8,
        },
        rows,
        cols,
        bias,
    }
}

/// Number of tensors a blob with this configuration holds.
pub fn tensor_count(config: &ModelConfig) -> usize {
    1 + RESIDUAL_BLOCK_TENSORS * usize::from(config.encoder_blocks)
        + 5 * SELF_LAYERS
        + 6
        + 1
        + RESIDUAL_BLOCK_TENSORS * usize::from(config.classifier_blocks)
        + 1
}

/// Name and shape of tensor `index` in blob order, or `None` past the last one.
///
/// Order: encoder input, encoder blocks (preconv, conv1, conv2), self layer 0 and 1 (edge1 centre,
/// edge1 neighbour, edge2 centre, edge2 neighbour, fuse), cross layer (query, key, value,
/// merge, mlp_hidden, mlp_out), classifier input, classifier blocks, classifier output.
pub fn tensor_spec(config: &ModelConfig, index: usize) -> Option<TensorSpec> {
    let d = usize::from(config.feature_dim);
    let c = usize::from(config.classifier_dim);
    let eb = usize::from(config.encoder_blocks);
    let cb = usize::from(config.classifier_blocks);
    let mut i = index;
    if i == 0 {
        return Some(spec("encoder.input", 0, d, 2, true));
    }
    i -= 1;
    if i < RESIDUAL_BLOCK_TENSORS * eb {
        let (block, role) = (i / RESIDUAL_BLOCK_TENSORS, i % RESIDUAL_BLOCK_TENSORS);
        return Some(spec(BLOCK_ROLES[0][role], block, d, d, true));
    }
    i -= RESIDUAL_BLOCK_TENSORS * eb;
    if i < 5 * SELF_LAYERS {
        let layer = i / 5;
        return Some(match i % 5 {
            0 => spec("self.edge1_centre", layer, d, d, false),
            1 => spec("self.edge1_neighbour", layer, d, d, false),
            2 => spec("self.edge2_centre", layer, 2 * d, d, false),
            3 => spec("self.edge2_neighbour", layer, 2 * d, d, false),
            _ => spec("self.fuse", layer, d, 4 * d, false),
        });
    }
    i -= 5 * SELF_LAYERS;
    if i < 6 {
        return Some(match i {
            0 => spec("cross.query", 0, d, d, true),
            1 => spec("cross.key", 0, d, d, true),
            2 => spec("cross.value", 0, d, d, true),
            3 => spec("cross.merge", 0, d, d, true),
            4 => spec("cross.mlp_hidden", 0, 2 * d, 2 * d, false),
            _ => spec("cross.mlp_out", 0, d, 2 * d, true),
        });
    }
    i -= 6;
    if i == 0 {
        return Some(spec("classifier.input", 0, c, 2 * d, true));
    }
    i -= 1;
    if i < RESIDUAL_BLOCK_TENSORS * cb {
        let (block, role) = (i / RESIDUAL_BLOCK_TENSORS, i % RESIDUAL_BLOCK_TENSORS);
        return Some(spec(BLOCK_ROLES[1][role], block, c, c, true));
    }
    i -= RESIDUAL_BLOCK_TENSORS * cb;
    if i == 0 {
        return Some(spec("classifier.output", 0, 1, c, true));
    }
    None
}

/// A per-point linear layer `y = s * (W x) + b` borrowed from the blob.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Linear<'a> {
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
        rows: 0,
        cols: 0,
        precision: Precision::F32,
        weights: &[],
        scales: &[],
        bias: &[],
    };

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

/// Tensor roles of a residual block's convolutions, in blob order: encoder, classifier.
const BLOCK_ROLES: [[&str; RESIDUAL_BLOCK_TENSORS]; 2] = [
    [
        "encoder.block.preconv",
        "encoder.block.conv1",
        "encoder.block.conv2",
    ],
    [
        "classifier.block.preconv",
        "classifier.block.conv1",
        "classifier.block.conv2",
    ],
];

/// One residual block of a point ResNet (supp. Fig. "Residual Block"), as the reference
/// stores it: `preconv`, `conv1`, `conv2`, each with its bias.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ResidualBlockWeights<'a> {
    /// `preconv` (no norm, no activation).
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

    /// The convolution at position `role` (< [`RESIDUAL_BLOCK_TENSORS`]) of the block.
    fn slot(&mut self, role: usize) -> &mut Linear<'a> {
        match role {
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

/// A loaded model: configuration and borrowed, shape-checked tensors.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Model<'a> {
    config: ModelConfig,
    precision: Precision,
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
        let payload = check_envelope(blob)?;
        let (header, mut rest): (BlobHeader, &'a [u8]) = postcard::take_from_bytes(payload)
            .map_err(|_| Error::BlobMalformed { offset: PREAMBLE })?;
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
            let offset = blob.len() - CHECKSUM_BYTES - rest.len();
            let (record, tail): (TensorRecord<'a>, &'a [u8]) =
                postcard::take_from_bytes(rest).map_err(|_| Error::BlobMalformed { offset })?;
            rest = tail;
            // `index < expected` so the spec exists.
            let Some(spec) = tensor_spec(&header.config, index) else {
                return Err(Error::TensorCount {
                    expected,
                    found: index,
                });
            };
            let linear = check_record(&record, &spec, offset)?;
            model.place(index, linear);
        }
        if !rest.is_empty() {
            return Err(Error::BlobMalformed {
                offset: blob.len() - CHECKSUM_BYTES - rest.len(),
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

    /// Puts tensor `index` (blob order of [`tensor_spec`]) in its slot.
    fn place(&mut self, index: usize, linear: Linear<'a>) {
        let eb = self.encoder.count;
        let cb = self.classifier.count;
        let mut i = index;
        if i == 0 {
            self.encoder.input = linear;
            return;
        }
        i -= 1;
        if i < RESIDUAL_BLOCK_TENSORS * eb {
            let block = &mut self.encoder.blocks[i / RESIDUAL_BLOCK_TENSORS];
            *block.slot(i % RESIDUAL_BLOCK_TENSORS) = linear;
            return;
        }
        i -= RESIDUAL_BLOCK_TENSORS * eb;
        if i < 5 * SELF_LAYERS {
            let layer = &mut self.self_layers[i / 5];
            match i % 5 {
                0 => layer.edge1_centre = linear,
                1 => layer.edge1_neighbour = linear,
                2 => layer.edge2_centre = linear,
                3 => layer.edge2_neighbour = linear,
                _ => layer.fuse = linear,
            }
            return;
        }
        i -= 5 * SELF_LAYERS;
        if i < 6 {
            let cross = &mut self.cross;
            match i {
                0 => cross.query = linear,
                1 => cross.key = linear,
                2 => cross.value = linear,
                3 => cross.merge = linear,
                4 => cross.mlp_hidden = linear,
                _ => cross.mlp_out = linear,
            }
            return;
        }
        i -= 6;
        if i == 0 {
            self.classifier.input = linear;
            return;
        }
        i -= 1;
        if i < RESIDUAL_BLOCK_TENSORS * cb {
            let block = &mut self.classifier.blocks[i / RESIDUAL_BLOCK_TENSORS];
            *block.slot(i % RESIDUAL_BLOCK_TENSORS) = linear;
            return;
        }
        self.classifier.output = linear;
    }
}

/// Checks length, magic, version and checksum; returns the postcard payload.
fn check_envelope(blob: &[u8]) -> Result<&[u8]> {
    let minimum = PREAMBLE + CHECKSUM_BYTES;
    if blob.len() < minimum {
        return Err(Error::BlobTruncated {
            needed: minimum,
            found: blob.len(),
        });
    }
    let magic = [blob[0], blob[1], blob[2], blob[3]];
    if magic != MAGIC {
        return Err(Error::BlobMagic { found: magic });
    }
    let version = u16::from_le_bytes([blob[4], blob[5]]);
    if version != FORMAT_VERSION {
        return Err(Error::BlobVersion {
            expected: FORMAT_VERSION,
            found: version,
        });
    }
    let body = blob.len() - CHECKSUM_BYTES;
    let t = &blob[body..];
    let stored = u32::from_le_bytes([t[0], t[1], t[2], t[3]]);
    let computed = crc32(&blob[..body]);
    if stored != computed {
        return Err(Error::BlobChecksum { stored, computed });
    }
    Ok(&blob[PREAMBLE..body])
}

/// Checks one record (at byte `offset` of the blob) against its expected shape and byte
/// lengths.
fn check_record<'a>(
    record: &TensorRecord<'a>,
    spec: &TensorSpec,
    offset: usize,
) -> Result<Linear<'a>> {
    let precision = record.precision;
    let (rows, cols) = (record.rows as usize, record.cols as usize);
    if rows != spec.rows || cols != spec.cols {
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
            .ok_or(Error::BlobMalformed { offset })
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
            if spec.bias { row_values } else { 0 },
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
        rows,
        cols,
        precision,
        weights: record.weights,
        scales: record.scales,
        bias: record.bias,
    })
}

/// Lookup table of the reflected CRC-32 (IEEE 802.3, polynomial 0xEDB88320).
const CRC_TABLE: [u32; 256] = {
    let mut table = [0u32; 256];
    let mut i = 0;
    while i < 256 {
        let mut c = i as u32;
        let mut bit = 0;
        while bit < 8 {
            c = if c & 1 != 0 {
                0xEDB8_8320 ^ (c >> 1)
            } else {
                c >> 1
            };
            bit += 1;
        }
        table[i] = c;
        i += 1;
    }
    table
};

/// CRC-32 (IEEE, as zlib's `crc32`) of `bytes`.
pub fn crc32(bytes: &[u8]) -> u32 {
    let mut c = 0xFFFF_FFFFu32;
    for &b in bytes {
        c = CRC_TABLE[((c ^ u32::from(b)) & 0xFF) as usize] ^ (c >> 8);
    }
    c ^ 0xFFFF_FFFF
}

/// Preamble (magic and version) every blob starts with.
pub const fn preamble() -> [u8; PREAMBLE] {
    let v = FORMAT_VERSION.to_le_bytes();
    [MAGIC[0], MAGIC[1], MAGIC[2], MAGIC[3], v[0], v[1]]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc32_matches_the_standard_check_value() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
        assert_eq!(crc32(b""), 0);
    }

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
    fn envelope_errors_carry_their_numbers() {
        assert_eq!(
            Model::from_bytes(&[1, 2, 3]),
            Err(Error::BlobTruncated {
                needed: 10,
                found: 3
            })
        );
        let mut blob = [0u8; 12];
        blob[..4].copy_from_slice(b"ABCD");
        assert_eq!(
            Model::from_bytes(&blob),
            Err(Error::BlobMagic { found: *b"ABCD" })
        );
        blob[..4].copy_from_slice(&MAGIC);
        blob[4..6].copy_from_slice(&7u16.to_le_bytes());
        assert_eq!(
            Model::from_bytes(&blob),
            Err(Error::BlobVersion {
                expected: FORMAT_VERSION,
                found: 7
            })
        );
        blob[4..6].copy_from_slice(&FORMAT_VERSION.to_le_bytes());
        let computed = crc32(&blob[..8]);
        assert_eq!(
            Model::from_bytes(&blob),
            Err(Error::BlobChecksum {
                stored: 0,
                computed
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
            Err(Error::BlobChecksum {
                stored: u32::from_le_bytes([
                    blob[len - 5],
                    blob[len - 4],
                    blob[len - 3],
                    blob[len - 2]
                ]),
                computed: crc32(&blob[..len - 5]),
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

    #[test]
    fn a_wrong_shape_names_the_tensor() {
        let mut config = tests_support::TINY;
        let mut buf = [0u8; 32 * 1024];
        let len = tests_support::blob(&config, 1, &mut buf);
        // Re-label the header: the same tensors now claim a 2-head, 16-wide model.
        config.feature_dim = 16;
        let mut relabelled = [0u8; 32 * 1024];
        let pre = preamble();
        relabelled[..6].copy_from_slice(&pre);
        let original = postcard::take_from_bytes::<BlobHeader>(&buf[6..len - 4])
            .expect("header")
            .1;
        let header = BlobHeader {
            config,
            precision: Precision::F32,
            tensor_count: tensor_count(&config) as u16,
        };
        let written = postcard::to_slice(&header, &mut relabelled[6..])
            .expect("fits")
            .len();
        let body_end = 6 + written + original.len();
        relabelled[6 + written..body_end].copy_from_slice(original);
        let crc = crc32(&relabelled[..body_end]);
        relabelled[body_end..body_end + 4].copy_from_slice(&crc.to_le_bytes());
        assert_eq!(
            Model::from_bytes(&relabelled[..body_end + 4]),
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
                buf[..6].copy_from_slice(&preamble());
                buf[6..6 + body.len()].copy_from_slice(&body);
                let crc = crc32(&buf[..6 + body.len()]);
                buf[6 + body.len()..10 + body.len()].copy_from_slice(&crc.to_le_bytes());
                10 + body.len()
            } else {
                buf[..body.len()].copy_from_slice(&body);
                body.len()
            };
            let _ = Model::from_bytes(&buf[..len]);
        }

        /// A valid blob with any byte changed and the checksum recomputed is either
        /// accepted or refused with an error, never a panic.
        #[test]
        fn mutated_valid_blobs_never_panic(position in 6usize..4000, value: u8) {
            let mut buf = [0u8; 32 * 1024];
            let len = tests_support::blob(&tests_support::TINY, 3, &mut buf);
            let at = position % (len - 10) + 6;
            buf[at] = value;
            let crc = crc32(&buf[..len - 4]);
            buf[len - 4..len].copy_from_slice(&crc.to_le_bytes());
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
        crc32, preamble, tensor_count, tensor_spec, BlobHeader, Linear, ModelConfig, Precision,
        TensorRecord,
    };

    /// A small configuration for end-to-end tests: d = 8, one block each, 2 heads, k = 3.
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

    /// Writes a valid blob of `config` with pseudo-random f32 weights in [-0.5, 0.5)
    /// into `out`; returns its length.
    pub fn blob(config: &ModelConfig, seed: u32, out: &mut [u8]) -> usize {
        let mut state = seed.wrapping_mul(747_796_405).wrapping_add(2_891_336_453);
        let mut next = move || {
            state = state.wrapping_mul(747_796_405).wrapping_add(2_891_336_453);
            (state >> 8) as f32 / (1u32 << 24) as f32 - 0.5
        };
        let pre = preamble();
        out[..pre.len()].copy_from_slice(&pre);
        let mut at = pre.len();
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
        let crc = crc32(&out[..at]);
        out[at..at + 4].copy_from_slice(&crc.to_le_bytes());
        at + 4
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
            rows,
            cols,
            precision,
            weights,
            scales,
            bias,
        }
    }
}
