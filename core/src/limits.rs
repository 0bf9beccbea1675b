//! Compile-time capacities and minimum sizes of the pipeline: every fixed-size buffer of the
//! core is sized from these (and from the caller's const generic `N`), so the memory bound is
//! known at compile time (`gomatch-tools mem-report`). A leaf module: it imports nothing.

/// Widest feature (and classifier) width the compiled workspace holds.
pub const MAX_FEATURE_DIM: usize = 128;
/// Widest input of any layer (the self-attention fusing conv, 4d).
pub const MAX_INPUT: usize = 4 * MAX_FEATURE_DIM;
/// Most residual blocks in the point encoder.
pub const MAX_ENCODER_BLOCKS: usize = 16;
/// Most residual blocks in the match classifier.
pub const MAX_CLASSIFIER_BLOCKS: usize = 8;
/// Most neighbours of the self-attention graph.
pub const MAX_KNN: usize = 16;
/// Most cross-attention heads.
pub const MAX_HEADS: usize = 8;
/// Most Sinkhorn iterations.
pub const MAX_SINKHORN_ITERS: usize = 100;
/// Number of self-attention layers (the reference order is self, cross, self).
pub const SELF_LAYERS: usize = 2;
/// Most database views one query is matched against (the paper's largest `k`).
pub const MAX_VIEWS: usize = 10;
/// Fewest keypoints (and points) per set: the paper counts a sample with fewer than 10 as
/// failed (supp. "Keypoint Number Control").
pub const MIN_KEYPOINTS: usize = 10;
/// Fewest points the network itself can process (a neighbour graph needs two).
pub const MIN_POINTS_NETWORK: usize = 2;
/// Fewest correspondences accepted: three for P3P and at least one to verify it.
pub const MIN_CORRESPONDENCES: usize = 4;
