//! `comanip-track`: particle-filter tool tracking of the instrument on the tool arm from the
//! stereo endoscope's frames and both arms' encoders (`docs/tracking.md`). The maths is the
//! `track` crate; this package reads recorded sequences (frames, candump log, camera files),
//! runs the tracker, writes the per-frame estimates, overlays and the measurements' plots.
//!
//! - [`config`]: the TOML configuration (`configs/comanip-track.toml`);
//! - [`input`]: a recorded sequence, both arms' joints matched to the frames;
//! - [`run`]: the model, one step per frame, the JSON lines;
//! - [`live`]: the live process: frame service, bus, calibration in, [`hw_io::ipc::TrackSample`]s out;
//! - [`overlay`]: the best hypothesis and the particle cloud drawn on both eyes;
//! - [`experiment`]: convergence from perturbed starts, frame rate, plots;
//! - [`robustness`]: joint-sensor noise, second instrument, smoke, occluder windows (loss and
//!   recovery), plots.

pub mod calib_error;
pub mod config;
pub mod experiment;
pub mod input;
pub mod live;
pub mod live_cli;
pub mod monitor;
pub mod overlay;
pub mod robustness;
pub mod run;
