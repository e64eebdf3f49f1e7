//! # sim: the world outside the controller, with ground truth
//!
//! Deterministic from a seed. Today: the surgeon's motion of the instrument through several
//! trocars ([`scenario`]), as instrument lines in the robot base frame with the true state
//! and fulcrum of every sample. Virtual encoder nodes on the CAN bus build on it.
#![warn(missing_docs)]

pub mod encoders;
pub mod robot;
pub mod scenario;
pub mod score;
