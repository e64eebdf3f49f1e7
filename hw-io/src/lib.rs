//! # hw-io: every byte that crosses a boundary
//!
//! CAN frames and bus backends, shared-memory messages and files. Typed errors for every
//! malformed input; nothing here panics on any byte pattern.
#![warn(missing_docs)]
