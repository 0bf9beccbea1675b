//! Integration tests across the gomatch crates live in `tests/`.
