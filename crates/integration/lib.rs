//! Holder for the workspace-level tests in the repository's `tests/` folder (for example
//! `tests/conformance.rs`); this library itself is empty.
