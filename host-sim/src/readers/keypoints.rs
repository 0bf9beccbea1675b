//! Query keypoints from the files a user has: a text file (`x y [score]` per line), a
//! NumPy array (`N x 2` or `N x 3`) or the `keypoints` table of COLMAP's `database.db`
//! (what `colmap feature_extractor` writes). Pixels follow COLMAP's convention (origin at
//! the top-left corner of the image, y down), as everywhere in this project.
//!
//! When a file holds more keypoints than the localizer's capacity, the best are kept, as a
//! detector capped at that many would keep them (paper supp. "Keypoint Number Control"):
//! - by score, highest first, when the text file or array has a third column;
//! - by scale, largest first, for a COLMAP database whose keypoints carry their shape (4
//!   columns `x y scale orientation`, or 6 columns `x y a11 a12 a21 a22`, scale the mean
//!   of the affine shape's two column norms, as COLMAP's `FeatureKeypoint::ComputeScale`);
//! - last stored first for a 2-column COLMAP database (COLMAP's SIFT lists keypoints
//!   octave by octave, fine to coarse: docs/evaluation.md "Protocol");
//! - first lines first for a text file or array without scores (list them best first).
//!
//! Ties keep the file order.

use std::path::Path;

use anyhow::{bail, ensure, Context};
use gomatch::camera::CameraModel;
use gomatch::Camera;
use rusqlite::{Connection, OpenFlags, OptionalExtension};

/// How the keypoints of a file are ranked, best first.
#[derive(Debug, Clone, PartialEq)]
pub enum Rank {
    /// Higher value first (a detector score or a feature scale).
    Descending(Vec<f64>),
    /// Last stored first.
    ReverseOrder,
    /// First stored first.
    FileOrder,
}

/// The keypoints of one image as read from a file, in file order.
#[derive(Debug, Clone, PartialEq)]
pub struct KeypointFile {
    /// Pixel positions (COLMAP convention).
    pub pixels: Vec<[f64; 2]>,
    /// Their rank.
    pub rank: Rank,
}

/// The at most `capacity` best keypoints of a file, best first, with their index in the
/// file.
#[derive(Debug, Clone, PartialEq)]
pub struct KeptKeypoints {
    /// Pixels as the localizer takes them.
    pub pixels: Vec<[f32; 2]>,
    /// Index in the file of each kept keypoint.
    pub file_index: Vec<usize>,
    /// Keypoints in the file.
    pub total: usize,
}

impl KeypointFile {
    /// Indices of the keypoints, best first ([`Rank`]; ties in file order).
    pub fn ranked(&self) -> Vec<usize> {
        let n = self.pixels.len();
        match &self.rank {
            Rank::Descending(values) => {
                let mut order: Vec<usize> = (0..n).collect();
                order.sort_by(|&a, &b| values[b].total_cmp(&values[a]).then(a.cmp(&b)));
                order
            }
            Rank::ReverseOrder => (0..n).rev().collect(),
            Rank::FileOrder => (0..n).collect(),
        }
    }

    /// The best `capacity` keypoints ([`KeypointFile::ranked`]).
    pub fn keep_best(&self, capacity: usize) -> KeptKeypoints {
        let file_index: Vec<usize> = self.ranked().into_iter().take(capacity).collect();
        KeptKeypoints {
            pixels: file_index
                .iter()
                .map(|&i| [self.pixels[i][0] as f32, self.pixels[i][1] as f32])
                .collect(),
            file_index,
            total: self.pixels.len(),
        }
    }

    /// Builds a file from rows of 2 (`x y`) or 3 (`x y score`) finite values.
    fn from_rows(rows: &[Vec<f64>], what: &str) -> anyhow::Result<Self> {
        let columns = rows.first().map_or(2, Vec::len);
        ensure!(
            columns == 2 || columns == 3,
            "{what}: {columns} columns, expected 2 (x y) or 3 (x y score)"
        );
        for (i, row) in rows.iter().enumerate() {
            ensure!(
                row.len() == columns,
                "{what}: keypoint {i} has {} values, the first has {columns}",
                row.len()
            );
            ensure!(
                row.iter().all(|v| v.is_finite()),
                "{what}: keypoint {i} is not finite"
            );
        }
        Ok(Self {
            pixels: rows.iter().map(|r| [r[0], r[1]]).collect(),
            rank: if columns == 3 {
                Rank::Descending(rows.iter().map(|r| r[2]).collect())
            } else {
                Rank::FileOrder
            },
        })
    }
}

/// Parses a keypoint text file: `x y [score]` per line; blank lines and `#` comments are
/// skipped.
pub fn parse_text(text: &str, what: &str) -> anyhow::Result<KeypointFile> {
    let rows = text
        .lines()
        .enumerate()
        .map(|(i, line)| (i + 1, line.trim()))
        .filter(|(_, line)| !line.is_empty() && !line.starts_with('#'))
        .map(|(number, line)| {
            line.split_whitespace()
                .map(|t| t.parse::<f64>())
                .collect::<Result<Vec<f64>, _>>()
                .with_context(|| format!("{what} line {number}: expected numbers, found {line:?}"))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    KeypointFile::from_rows(&rows, what)
}

/// Reads an `N x 2` or `N x 3` `.npy` array of `f32` or `f64`.
pub fn read_npy(path: &Path) -> anyhow::Result<KeypointFile> {
    let what = path.display().to_string();
    let bytes = std::fs::read(path).with_context(|| format!("reading {what}"))?;
    let open = || npyz::NpyFile::new(&bytes[..]).with_context(|| format!("parsing {what}"));
    let npy = open()?;
    ensure!(
        npy.order() == npyz::Order::C,
        "{what}: Fortran order is not supported"
    );
    let shape = npy.shape().to_vec();
    ensure!(
        shape.len() == 2 && (shape[1] == 2 || shape[1] == 3),
        "{what}: shape {shape:?}, expected (N, 2) or (N, 3)"
    );
    let values: Vec<f64> = match npy.into_vec::<f64>() {
        Ok(values) => values,
        Err(_) => open()?
            .into_vec::<f32>()
            .with_context(|| format!("{what}: expected float32 or float64 values"))?
            .into_iter()
            .map(f64::from)
            .collect(),
    };
    let rows: Vec<Vec<f64>> = values
        .chunks_exact(shape[1] as usize)
        .map(<[f64]>::to_vec)
        .collect();
    KeypointFile::from_rows(&rows, &what)
}

/// Reads a keypoint file by its extension: `.npy`, else text.
pub fn read_keypoint_file(path: &Path) -> anyhow::Result<KeypointFile> {
    if path.extension().is_some_and(|e| e == "npy") {
        return read_npy(path);
    }
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    parse_text(&text, &path.display().to_string())
}

/// Scale of a COLMAP affine keypoint shape `a11 a12 a21 a22`: the mean norm of its two
/// columns (COLMAP's `FeatureKeypoint::ComputeScale`).
pub fn affine_scale(a11: f64, a12: f64, a21: f64, a22: f64) -> f64 {
    (a11.hypot(a21) + a12.hypot(a22)) / 2.0
}

/// Keypoints from a COLMAP `keypoints` blob: `rows x cols` little-endian `f32`, row-major,
/// `cols` 2 (`x y`), 4 (`x y scale orientation`) or 6 (`x y a11 a12 a21 a22`).
pub fn from_colmap_blob(rows: usize, cols: usize, data: &[u8]) -> anyhow::Result<KeypointFile> {
    ensure!(
        matches!(cols, 2 | 4 | 6),
        "keypoints have {cols} columns, COLMAP writes 2, 4 or 6"
    );
    ensure!(
        rows.checked_mul(cols).and_then(|n| n.checked_mul(4)) == Some(data.len()),
        "corrupt keypoints: {rows} x {cols} f32 do not make {} bytes",
        data.len()
    );
    let values: Vec<f64> = data
        .chunks_exact(4)
        .map(|c| f64::from(f32::from_le_bytes([c[0], c[1], c[2], c[3]])))
        .collect();
    let rows: Vec<&[f64]> = values.chunks_exact(cols).collect();
    ensure!(
        values.iter().all(|v| v.is_finite()),
        "keypoints hold a non-finite value"
    );
    let rank = match cols {
        4 => Rank::Descending(rows.iter().map(|r| r[2]).collect()),
        6 => Rank::Descending(
            rows.iter()
                .map(|r| affine_scale(r[2], r[3], r[4], r[5]))
                .collect(),
        ),
        _ => Rank::ReverseOrder,
    };
    Ok(KeypointFile {
        pixels: rows.iter().map(|r| [r[0], r[1]]).collect(),
        rank,
    })
}

/// A COLMAP `database.db`, opened read-only.
pub struct ColmapDatabase {
    connection: Connection,
    path: String,
}

impl ColmapDatabase {
    /// Opens the database read-only.
    pub fn open(path: &Path) -> anyhow::Result<Self> {
        let connection = Connection::open_with_flags(path, OpenFlags::SQLITE_OPEN_READ_ONLY)
            .with_context(|| format!("opening the COLMAP database {}", path.display()))?;
        Ok(Self {
            connection,
            path: path.display().to_string(),
        })
    }

    /// Image id and camera id of the image called `name`.
    fn image(&self, name: &str) -> anyhow::Result<(i64, i64)> {
        self.connection
            .query_row(
                "SELECT image_id, camera_id FROM images WHERE name = ?1",
                [name],
                |row| Ok((row.get(0)?, row.get(1)?)),
            )
            .optional()
            .with_context(|| format!("{}: reading the images table", self.path))?
            .with_context(|| format!("{}: no image named {name:?}", self.path))
    }

    /// The keypoints of the image called `name`.
    pub fn keypoints(&self, name: &str) -> anyhow::Result<KeypointFile> {
        let (image_id, _) = self.image(name)?;
        let (rows, cols, data): (i64, i64, Vec<u8>) = self
            .connection
            .query_row(
                "SELECT rows, cols, data FROM keypoints WHERE image_id = ?1",
                [image_id],
                |row| {
                    Ok((
                        row.get(0)?,
                        row.get(1)?,
                        row.get::<_, Option<Vec<u8>>>(2)?.unwrap_or_default(),
                    ))
                },
            )
            .optional()
            .with_context(|| format!("{}: reading the keypoints table", self.path))?
            .with_context(|| {
                format!(
                    "{}: image {name:?} has no keypoints (run colmap feature_extractor)",
                    self.path
                )
            })?;
        let (Ok(rows), Ok(cols)) = (usize::try_from(rows), usize::try_from(cols)) else {
            bail!(
                "{}: image {name:?}: corrupt keypoint shape {rows} x {cols}",
                self.path
            );
        };
        from_colmap_blob(rows, cols, &data)
            .with_context(|| format!("{}: image {name:?}", self.path))
    }

    /// The camera of the image called `name` (COLMAP's `cameras` table: model id, width,
    /// height, parameters as `f64`).
    pub fn camera(&self, name: &str) -> anyhow::Result<Camera> {
        let (_, camera_id) = self.image(name)?;
        let (model, width, height, params): (i64, i64, i64, Vec<u8>) = self
            .connection
            .query_row(
                "SELECT model, width, height, params FROM cameras WHERE camera_id = ?1",
                [camera_id],
                |row| Ok((row.get(0)?, row.get(1)?, row.get(2)?, row.get(3)?)),
            )
            .with_context(|| format!("{}: camera {camera_id} of image {name:?}", self.path))?;
        let context = || format!("{}: camera {camera_id} (model id {model})", self.path);
        let model = i32::try_from(model)
            .ok()
            .and_then(|id| CameraModel::from_colmap_id(id).ok())
            .with_context(|| format!("{}: unsupported camera model", context()))?;
        ensure!(params.len() % 8 == 0, "{}: corrupt parameters", context());
        let params: Vec<f64> = params
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().unwrap_or([0; 8])))
            .collect();
        let (Ok(width), Ok(height)) = (u32::try_from(width), u32::try_from(height)) else {
            bail!("{}: image size {width} x {height} out of range", context());
        };
        Camera::from_colmap(model, width, height, &params)
            .map_err(|e| anyhow::anyhow!("{}: {e}", context()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_keypoints_keep_the_best_scores() {
        let file = parse_text("# x y score\n10 20 0.5\n\n30 40 0.9\n50 60 0.1\n", "t").unwrap();
        assert_eq!(file.pixels.len(), 3);
        let kept = file.keep_best(2);
        assert_eq!(kept.file_index, vec![1, 0]);
        assert_eq!(kept.pixels, vec![[30.0, 40.0], [10.0, 20.0]]);
        assert_eq!(kept.total, 3);
        let unscored = parse_text("1 2\n3 4\n5 6\n", "t").unwrap();
        assert_eq!(unscored.keep_best(2).file_index, vec![0, 1]);
        assert!(parse_text("1 2\n3 4 5\n", "t").is_err());
        assert!(parse_text("1 2 3 4\n", "t").is_err());
        assert!(parse_text("1 x\n", "t").is_err());
        assert!(parse_text("1 nan\n", "t").is_err());
    }

    fn blob(values: &[f32]) -> Vec<u8> {
        values.iter().flat_map(|v| v.to_le_bytes()).collect()
    }

    #[test]
    fn colmap_blobs_rank_by_scale_or_reverse_order() {
        // 6 columns: scales 2, 8, 1 (isotropic shapes), so the second comes first.
        let six = blob(&[
            1.0, 1.0, 2.0, 0.0, 0.0, 2.0, //
            2.0, 2.0, 0.0, 8.0, -8.0, 0.0, //
            3.0, 3.0, 1.0, 0.0, 0.0, 1.0,
        ]);
        let file = from_colmap_blob(3, 6, &six).unwrap();
        assert_eq!(file.ranked(), vec![1, 0, 2]);
        assert_eq!(affine_scale(0.0, 8.0, -8.0, 0.0), 8.0);
        let four = blob(&[1.0, 1.0, 3.0, 0.0, 2.0, 2.0, 5.0, 0.0]);
        assert_eq!(from_colmap_blob(2, 4, &four).unwrap().ranked(), vec![1, 0]);
        let two = blob(&[1.0, 1.0, 2.0, 2.0, 3.0, 3.0]);
        assert_eq!(
            from_colmap_blob(3, 2, &two).unwrap().ranked(),
            vec![2, 1, 0]
        );
        assert!(from_colmap_blob(3, 2, &two[..20]).is_err());
        assert!(from_colmap_blob(1, 3, &two[..12]).is_err());
        assert!(from_colmap_blob(usize::MAX, 2, &two).is_err());
    }
}
