//! Strict low-level parsing shared by the model readers: a little-endian byte cursor for
//! binary files and a whitespace token stream for text files. Every malformed input is a
//! [`FormatError`] naming where it failed; nothing panics on file contents.

use std::path::Path;
use std::str::FromStr;

/// A malformed model file.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FormatError {
    /// A binary file ends before a field it must hold.
    #[error("truncated: {what} needs {needed} bytes at offset {offset}, only {available} left")]
    Truncated {
        /// The field being read.
        what: &'static str,
        /// Byte offset of the field.
        offset: usize,
        /// Bytes the field needs.
        needed: usize,
        /// Bytes left in the file.
        available: usize,
    },
    /// A record count no COLMAP file holds (above 2^32, e.g. 2^64 - 1): the file is
    /// corrupt or not a COLMAP binary file.
    #[error("corrupt file: {what} at offset {offset} reads {count}, not a plausible count (is this a COLMAP binary file?)")]
    ImplausibleCount {
        /// The count field.
        what: &'static str,
        /// Byte offset of the field.
        offset: usize,
        /// The value read.
        count: u64,
    },
    /// A binary file goes on after its last record.
    #[error("{count} unexpected bytes after the last record at offset {offset}")]
    TrailingBytes {
        /// Where the last record ended.
        offset: usize,
        /// How many bytes follow it.
        count: usize,
    },
    /// A text field that is missing or does not parse.
    #[error("line {line}: {message}")]
    Syntax {
        /// 1-based line number.
        line: usize,
        /// What was expected.
        message: String,
    },
    /// A camera model this project does not implement.
    #[error("camera {camera_id}: unsupported camera model {model}")]
    UnsupportedCameraModel {
        /// The camera.
        camera_id: u64,
        /// The model as written in the file.
        model: String,
    },
    /// Intrinsics the core refuses (non-positive focal length, non-finite values).
    #[error("camera {camera_id}: invalid intrinsics ({reason})")]
    InvalidCamera {
        /// The camera.
        camera_id: u64,
        /// The core's reason.
        reason: gomatch::Error,
    },
    /// A pose the core refuses (non-finite values, zero quaternion).
    #[error("image {image_id}: invalid pose ({reason})")]
    InvalidPose {
        /// The image.
        image_id: u64,
        /// The core's reason.
        reason: gomatch::Error,
    },
    /// Two records with the same identifier.
    #[error("duplicate {what} id {id}")]
    DuplicateId {
        /// Which kind of record.
        what: &'static str,
        /// The repeated identifier.
        id: u64,
    },
    /// An identifier or index outside the range the format allows.
    #[error("{what} {value} out of range (limit {limit})")]
    OutOfRange {
        /// Which field.
        what: &'static str,
        /// The value found.
        value: u64,
        /// The exclusive upper limit.
        limit: u64,
    },
}

/// Little-endian reader over a byte slice that reports truncation instead of panicking.
pub struct ByteReader<'a> {
    data: &'a [u8],
    offset: usize,
}

impl<'a> ByteReader<'a> {
    /// Reader at the start of `data`.
    pub fn new(data: &'a [u8]) -> Self {
        Self { data, offset: 0 }
    }

    /// Bytes not yet read.
    pub fn remaining(&self) -> usize {
        self.data.len() - self.offset
    }

    fn take<const N: usize>(&mut self, what: &'static str) -> Result<[u8; N], FormatError> {
        let bytes = self
            .data
            .get(self.offset..self.offset.saturating_add(N))
            .and_then(|s| <[u8; N]>::try_from(s).ok())
            .ok_or(FormatError::Truncated {
                what,
                offset: self.offset,
                needed: N,
                available: self.remaining(),
            })?;
        self.offset += N;
        Ok(bytes)
    }

    /// Reads a `u8`.
    pub fn u8(&mut self, what: &'static str) -> Result<u8, FormatError> {
        Ok(self.take::<1>(what)?[0])
    }

    /// Reads a little-endian `u32`.
    pub fn u32(&mut self, what: &'static str) -> Result<u32, FormatError> {
        self.take(what).map(u32::from_le_bytes)
    }

    /// Reads a little-endian `i32`.
    pub fn i32(&mut self, what: &'static str) -> Result<i32, FormatError> {
        self.take(what).map(i32::from_le_bytes)
    }

    /// Reads a little-endian `u64`.
    pub fn u64(&mut self, what: &'static str) -> Result<u64, FormatError> {
        self.take(what).map(u64::from_le_bytes)
    }

    /// Reads a little-endian `f64`.
    pub fn f64(&mut self, what: &'static str) -> Result<f64, FormatError> {
        self.take(what).map(f64::from_le_bytes)
    }

    /// Reads `N` little-endian `f64`s.
    pub fn f64s<const N: usize>(&mut self, what: &'static str) -> Result<[f64; N], FormatError> {
        let mut values = [0.0; N];
        for v in &mut values {
            *v = self.f64(what)?;
        }
        Ok(values)
    }

    /// Reads a NUL-terminated string (lossy UTF-8).
    pub fn c_string(&mut self, what: &'static str) -> Result<String, FormatError> {
        let rest = &self.data[self.offset..];
        let len = rest
            .iter()
            .position(|&b| b == 0)
            .ok_or(FormatError::Truncated {
                what,
                offset: self.offset,
                needed: rest.len() + 1,
                available: rest.len(),
            })?;
        let text = String::from_utf8_lossy(&rest[..len]).into_owned();
        self.offset += len + 1;
        Ok(text)
    }

    /// Reads a record count and checks that `count` records of at least `min_record_bytes`
    /// each fit in the rest of the file, so a corrupt count cannot trigger a huge
    /// allocation. A count above 2^32 (COLMAP's ids are 32-bit; no image holds that many
    /// keypoints) is [`FormatError::ImplausibleCount`], a smaller one that does not fit
    /// [`FormatError::Truncated`].
    pub fn count(
        &mut self,
        what: &'static str,
        min_record_bytes: usize,
    ) -> Result<usize, FormatError> {
        let offset = self.offset;
        let count = self.u64(what)?;
        if count > u64::from(u32::MAX) {
            return Err(FormatError::ImplausibleCount {
                what,
                offset,
                count,
            });
        }
        let available = self.remaining();
        let needed = usize::try_from(count)
            .ok()
            .and_then(|c| c.checked_mul(min_record_bytes))
            .filter(|&n| n <= available);
        match needed {
            Some(_) => Ok(count as usize),
            None => Err(FormatError::Truncated {
                what,
                offset,
                needed: usize::try_from(count)
                    .unwrap_or(usize::MAX)
                    .saturating_mul(min_record_bytes),
                available,
            }),
        }
    }

    /// Fails unless every byte has been read.
    pub fn finish(&self) -> Result<(), FormatError> {
        match self.remaining() {
            0 => Ok(()),
            count => Err(FormatError::TrailingBytes {
                offset: self.offset,
                count,
            }),
        }
    }
}

/// Whitespace-separated tokens of a text file, with the line each comes from, read lazily
/// (no per-token storage); the count of tokens left bounds what a declared record count
/// may reserve ([`Tokens::count`]).
#[derive(Debug, Clone)]
pub struct Tokens<'a> {
    /// The text after the last token read.
    rest: &'a str,
    /// Line of the last token read (the first line read before any).
    line: usize,
    /// Tokens in `rest`.
    left: usize,
}

impl<'a> Tokens<'a> {
    /// Tokens of `text`, skipping the first `skip_lines` lines (headers).
    pub fn new(text: &'a str, skip_lines: usize) -> Self {
        let mut rest = text;
        for _ in 0..skip_lines {
            rest = rest.split_once('\n').map_or("", |(_, after)| after);
        }
        Self {
            rest,
            line: skip_lines + 1,
            left: rest.split_whitespace().count(),
        }
    }

    /// The next token and its line.
    fn next_token(&mut self) -> Option<(usize, &'a str)> {
        let start = self.rest.find(|c: char| !c.is_whitespace())?;
        self.line += self.rest[..start].matches('\n').count();
        let from = &self.rest[start..];
        let end = from.find(char::is_whitespace).unwrap_or(from.len());
        self.rest = &from[end..];
        self.left -= 1;
        Some((self.line, &from[..end]))
    }

    /// Parses a declared record count and checks that that many records of
    /// `tokens_per_record` tokens each fit in the tokens left, so that a count never
    /// reserves more than the file holds.
    pub fn count(&mut self, what: &str, tokens_per_record: usize) -> Result<usize, FormatError> {
        let count: usize = self.parse(what)?;
        let limit = self.left / tokens_per_record.max(1);
        if count > limit {
            return Err(FormatError::OutOfRange {
                what: "declared record count",
                value: count as u64,
                limit: limit as u64 + 1,
            });
        }
        Ok(count)
    }

    /// Parses the next token as a `T`.
    pub fn parse<T: FromStr>(&mut self, what: &str) -> Result<T, FormatError> {
        let line = self.line;
        let (line, token) = self.next_token().ok_or_else(|| FormatError::Syntax {
            line,
            message: format!("file ends where {what} was expected"),
        })?;
        token.parse().map_err(|_| FormatError::Syntax {
            line,
            message: format!("expected {what}, found {token:?}"),
        })
    }

    /// Parses the next `N` tokens as `f64`s.
    pub fn f64s<const N: usize>(&mut self, what: &str) -> Result<[f64; N], FormatError> {
        let mut values = [0.0; N];
        for v in &mut values {
            *v = self.parse(what)?;
        }
        Ok(values)
    }

    /// Fails unless every token has been consumed.
    pub fn finish(&self) -> Result<(), FormatError> {
        match self.clone().next_token() {
            None => Ok(()),
            Some((line, token)) => Err(FormatError::Syntax {
                line,
                message: format!("unexpected token {token:?} after the last record"),
            }),
        }
    }
}

/// Parses one text token as a `T`.
pub fn token<T: FromStr>(text: &str, line: usize, what: &str) -> Result<T, FormatError> {
    text.parse().map_err(|_| FormatError::Syntax {
        line,
        message: format!("expected {what}, found {text:?}"),
    })
}

/// Parses the next whitespace-separated field of a line.
pub fn field<T: FromStr>(
    fields: &mut std::str::SplitWhitespace<'_>,
    line: usize,
    what: &str,
) -> Result<T, FormatError> {
    let text = fields.next().ok_or_else(|| FormatError::Syntax {
        line,
        message: format!("line ends where {what} was expected"),
    })?;
    token(text, line, what)
}

/// The last component of `path` (lossy UTF-8), if it has one: a piece of a scene's name.
pub fn file_name(path: &Path) -> Option<String> {
    path.file_name().map(|n| n.to_string_lossy().into_owned())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn byte_reader_reports_truncation() {
        let data = [1u8, 0, 0, 0, 7];
        let mut reader = ByteReader::new(&data);
        assert_eq!(reader.u32("a").unwrap(), 1);
        assert!(matches!(
            reader.u32("b"),
            Err(FormatError::Truncated {
                what: "b",
                offset: 4,
                needed: 4,
                available: 1
            })
        ));
        assert!(matches!(
            reader.finish(),
            Err(FormatError::TrailingBytes {
                offset: 4,
                count: 1
            })
        ));
    }

    #[test]
    fn huge_counts_are_refused_before_allocating() {
        let data = u64::MAX.to_le_bytes();
        let mut reader = ByteReader::new(&data);
        let error = reader.count("records", 8).unwrap_err();
        assert_eq!(
            error,
            FormatError::ImplausibleCount {
                what: "records",
                offset: 0,
                count: u64::MAX
            }
        );
        assert!(error.to_string().starts_with("corrupt file"), "{error}");
        let data = 3u64.to_le_bytes();
        let mut reader = ByteReader::new(&data);
        assert!(matches!(
            reader.count("records", 8),
            Err(FormatError::Truncated { .. })
        ));
    }

    #[test]
    fn tokens_report_lines() {
        let mut tokens = Tokens::new("# header\n1 2\nx", 1);
        assert_eq!(tokens.parse::<u32>("a").unwrap(), 1);
        assert_eq!(tokens.parse::<u32>("b").unwrap(), 2);
        assert_eq!(
            tokens.parse::<f64>("c"),
            Err(FormatError::Syntax {
                line: 3,
                message: "expected c, found \"x\"".into()
            })
        );
        assert!(tokens.parse::<f64>("d").is_err());
    }
}
