//! # comanip controller: the processes
//!
//! - `fulcrumd`: the trocar daemon. Today it runs the detector over the built-in simulated
//!   surgeon ([`demo`]); the 1 kHz CAN loop and iceoryx2 output build on the same pieces.
//! - [`config`]: the TOML configuration, validated at load with messages that name the key.
#![warn(missing_docs)]

pub mod config;
pub mod demo;
