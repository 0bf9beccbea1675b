//! Files the command lines are given: what kind a file is (so a file of the wrong kind is
//! named, with what to do, instead of a bare decoding error), how model and map blobs are
//! read with such messages, and where default files are found (from the current folder or
//! the executable, never from a path compiled into the binary).

use std::path::{Path, PathBuf};

use gomatch::map::{Map, MAP_MAGIC};
use gomatch::weights::MODEL_MAGIC;
use gomatch::{Error, Model};

/// The shipped int8 model, relative to the repository root.
pub const SHIPPED_MODEL: &str = "models/gomatch-int8.bin";

/// What a file holds, judged from its first bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FileKind {
    /// A `gomatch` map blob (`GMAP`).
    MapBlob,
    /// A `gomatch` model blob (`GMWB`).
    ModelBlob,
    /// A safetensors checkpoint (little-endian u64 header length, then a JSON header).
    Safetensors,
    /// A NumPy `.npy` array.
    Npy,
    /// An SQLite database (e.g. COLMAP's `database.db`).
    Sqlite,
    /// Anything else.
    Unknown,
}

impl FileKind {
    /// Kind of a file whose contents start with `bytes`.
    pub fn of(bytes: &[u8]) -> Self {
        let safetensors_header = bytes
            .get(..8)
            .and_then(|b| <[u8; 8]>::try_from(b).ok())
            .map(u64::from_le_bytes)
            .is_some_and(|len| len > 1 && bytes.get(8) == Some(&b'{'));
        match bytes {
            [a, b, c, d, ..] if [*a, *b, *c, *d] == MAP_MAGIC => Self::MapBlob,
            [a, b, c, d, ..] if [*a, *b, *c, *d] == MODEL_MAGIC => Self::ModelBlob,
            _ if bytes.starts_with(b"\x93NUMPY") => Self::Npy,
            _ if bytes.starts_with(b"SQLite format 3\0") => Self::Sqlite,
            _ if safetensors_header => Self::Safetensors,
            _ => Self::Unknown,
        }
    }

    /// What the kind is, for messages.
    pub fn describe(self) -> &'static str {
        match self {
            Self::MapBlob => "a gomatch map blob",
            Self::ModelBlob => "a gomatch model blob",
            Self::Safetensors => "a safetensors checkpoint",
            Self::Npy => "a NumPy .npy array",
            Self::Sqlite => "an SQLite database",
            Self::Unknown => "not a gomatch file",
        }
    }
}

/// What to do about a file given where a model blob was expected.
fn model_advice(kind: FileKind, error: Error) -> String {
    match (kind, error) {
        (FileKind::Safetensors, _) => "it is a safetensors checkpoint: convert it to a model blob with \
             `gomatch-tools convert --input CHECKPOINT --precision int8 --output MODEL.bin`"
            .into(),
        (FileKind::MapBlob, _) => {
            "it is a map blob: pass it as the map, and a model blob (e.g. models/gomatch-int8.bin) as the model".into()
        }
        (FileKind::ModelBlob, Error::BlobChecksum { .. } | Error::BlobTruncated { .. }) => {
            "the file is truncated or damaged: copy it again or rebuild it with `gomatch-tools convert`".into()
        }
        (FileKind::ModelBlob, Error::BlobVersion { .. }) => {
            "the blob was written by another version: rebuild it from its checkpoint with `gomatch-tools convert`".into()
        }
        (kind, _) => format!("it is {}; a model blob is written by `gomatch-tools convert`", kind.describe()),
    }
}

/// What to do about a file given where a map blob was expected.
fn map_advice(kind: FileKind, error: Error) -> String {
    match (kind, error) {
        (FileKind::ModelBlob | FileKind::Safetensors, _) => format!(
            "it is {}: pass it as the model, and a map blob (from `gomatch-sim map build`) as the map",
            kind.describe()
        ),
        (FileKind::MapBlob, Error::BlobVersion { .. }) => {
            "the map was written by another version: rebuild it with `gomatch-sim map build`".into()
        }
        (FileKind::MapBlob, Error::BlobTruncated { .. } | Error::BlobChecksum { .. }) => {
            "the file is truncated or damaged: copy it again or rebuild it with `gomatch-sim map build`".into()
        }
        (FileKind::MapBlob, _) => "rebuild it with `gomatch-sim map build`".into(),
        (kind, _) => format!(
            "it is {}; a map blob is written by `gomatch-sim map build`",
            kind.describe()
        ),
    }
}

/// Reads `path` whole.
fn read(path: &Path, what: &str) -> anyhow::Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| anyhow::anyhow!("reading the {what} {}: {e}", path.display()))
}

/// Reads a model blob file and checks that it decodes; a file of another kind or a
/// damaged blob is an error that says what the file is and what to do.
pub fn read_model_blob(path: &Path) -> anyhow::Result<Vec<u8>> {
    let blob = read(path, "model")?;
    if let Err(error) = Model::from_bytes(&blob) {
        let advice = model_advice(FileKind::of(&blob), error);
        anyhow::bail!(
            "{} is not a usable model blob ({error}): {advice}",
            path.display()
        );
    }
    Ok(blob)
}

/// Reads a map blob file and checks that it decodes, with [`read_model_blob`]'s messages.
pub fn read_map_blob(path: &Path) -> anyhow::Result<Vec<u8>> {
    let blob = read(path, "map")?;
    if let Err(error) = Map::from_bytes(&blob) {
        let advice = map_advice(FileKind::of(&blob), error);
        anyhow::bail!(
            "{} is not a usable map blob ({error}): {advice}",
            path.display()
        );
    }
    Ok(blob)
}

/// Folders searched for a default file: the current folder and its parents, then the
/// executable's folder and its parents (a `target/release` binary finds the repository).
fn search_roots() -> Vec<PathBuf> {
    let mut roots = Vec::new();
    if let Ok(dir) = std::env::current_dir() {
        roots.extend(dir.ancestors().map(Path::to_path_buf));
    }
    if let Some(dir) = std::env::current_exe()
        .ok()
        .and_then(|e| e.parent().map(Path::to_path_buf))
    {
        roots.extend(dir.ancestors().map(Path::to_path_buf));
    }
    roots
}

/// The first existing `root/relative` over `search_roots`.
pub fn find_default(relative: &str) -> Option<PathBuf> {
    search_roots()
        .into_iter()
        .map(|root| root.join(relative))
        .find(|path| path.exists())
}

/// [`find_default`], or an error naming where it looked and the option to pass instead.
pub fn require_default(relative: &str, option: &str) -> anyhow::Result<PathBuf> {
    find_default(relative).ok_or_else(|| {
        anyhow::anyhow!(
            "{relative} was not found in the current folder, the executable's folder or their parents: run from the repository or pass {option}"
        )
    })
}

/// The shipped model's path when it can be found ([`find_default`]), else the relative
/// path, which reading then reports as missing.
pub fn shipped_model_path() -> PathBuf {
    find_default(SHIPPED_MODEL).unwrap_or_else(|| PathBuf::from(SHIPPED_MODEL))
}

#[cfg(test)]
mod tests {
    use super::*;
    use gomatch::error::BlobKind;

    #[test]
    fn kinds_are_recognised_from_their_first_bytes() {
        assert_eq!(FileKind::of(b"GMAP\x02\0"), FileKind::MapBlob);
        assert_eq!(FileKind::of(b"GMWB\x02\0"), FileKind::ModelBlob);
        assert_eq!(FileKind::of(b"\x93NUMPY\x01\0"), FileKind::Npy);
        assert_eq!(FileKind::of(b"SQLite format 3\0..."), FileKind::Sqlite);
        let mut safetensors = 20u64.to_le_bytes().to_vec();
        safetensors.extend_from_slice(b"{\"__metadata__\":{}}");
        assert_eq!(FileKind::of(&safetensors), FileKind::Safetensors);
        assert_eq!(FileKind::of(b"GM"), FileKind::Unknown);
        assert_eq!(FileKind::of(b""), FileKind::Unknown);
    }

    #[test]
    fn wrong_kinds_get_advice() {
        let advice = model_advice(
            FileKind::Safetensors,
            Error::BlobMagic {
                blob: BlobKind::Model,
                found: [0; 4],
            },
        );
        assert!(advice.contains("gomatch-tools convert"), "{advice}");
        let advice = model_advice(
            FileKind::MapBlob,
            Error::BlobMagic {
                blob: BlobKind::Model,
                found: *b"GMAP",
            },
        );
        assert!(advice.contains("map blob"), "{advice}");
        let advice = model_advice(
            FileKind::ModelBlob,
            Error::BlobChecksum {
                blob: BlobKind::Model,
                stored: 0,
                computed: 1,
            },
        );
        assert!(advice.contains("truncated"), "{advice}");
        let advice = map_advice(
            FileKind::ModelBlob,
            Error::BlobMagic {
                blob: BlobKind::Map,
                found: *b"GMWB",
            },
        );
        assert!(advice.contains("as the model"), "{advice}");
        let advice = map_advice(
            FileKind::MapBlob,
            Error::BlobVersion {
                blob: BlobKind::Map,
                expected: 2,
                found: 1,
            },
        );
        assert!(advice.contains("map build"), "{advice}");
    }
}
