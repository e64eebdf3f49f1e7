//! `comanip-calib`: the dual RCM-arm calibration tool (`docs/calibration.md`).
//!
//! - [`collector`]: the live calibration's collector (issue 19): pure logic fed in time
//!   order, refusals with reasons, predicted precision, solve trigger, drift watch.
//! - [`convert`]: file structs (`hw_io::calib_files`) ↔ estimator types.
//! - [`run`]: `generate` (simulated dataset + ground truth), `calibrate` (dataset → result
//!   file, paper / ours / both).
//! - [`residual_plot`]: the residual figure of `calibrate --plot` (SVG).
//! - [`bus_run`]: `from-run`, the calibration from a recorded run: both arms' joints from
//!   the candump log, matched to the stereo frames by time, lines detected in both eyes.
//! - [`live`]: the live calibration's loop (detector + collector), shared by its two sources;
//!   `live --replay`, the loop over a recorded natural session in time order, scored against
//!   the run's truth.
//! - [`live_process`]: `live` on the bus (frames, a passive CAN listener, fulcrumd's output,
//!   the calibration published); [`live_config`]: its TOML settings.
//! - [`detect`]: `detect`, the shaft's lines in a directory of images (lines file, overlays).
//! - [`pixels`]: `pixels`, the calibration from rendered stereo frames with detected lines,
//!   next to the same poses with exact lines.
//! - [`sweep`]: the paper's simulation protocol sweeps (σ, n_e × n_t, random initial
//!   quaternions) to a Markdown table and SVG box plots.
//! - [`generalise`]: the generalisation protocol on random scene geometries
//!   (`sweep --geometries N`), tuning and held-out sets.

pub mod bus_run;
pub mod collector;
pub mod convert;
pub mod detect;
pub mod generalise;
pub mod live;
pub mod live_config;
pub mod live_process;
pub mod pixels;
pub mod residual_plot;
pub mod run;
pub mod sweep;
