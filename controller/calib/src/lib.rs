//! `comanip-calib`: the dual RCM-arm calibration tool (`docs/calibration.md`).
//!
//! - [`convert`]: file structs (`hw_io::calib_files`) ↔ estimator types.
//! - [`run`]: `generate` (simulated dataset + ground truth), `calibrate` (dataset → result
//!   file, paper / ours / both).
//! - [`residual_plot`]: the residual figure of `calibrate --plot` (SVG).
//! - [`sweep`]: the paper's simulation protocol sweeps (σ, n_e × n_t, random initial
//!   quaternions) to a Markdown table and SVG box plots.
//! - [`generalise`]: the generalisation protocol on random scene geometries
//!   (`sweep --geometries N`), tuning and held-out sets.

pub mod convert;
pub mod generalise;
pub mod residual_plot;
pub mod run;
pub mod sweep;
