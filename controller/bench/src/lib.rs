//! `comanip-bench`: detection quality and loop timing, the paper's method and ours side by
//! side, measured on the same traces in the same run (`docs/BENCHMARKS.md`).
//!
//! - [`trace`]: simulated sessions decoded as the daemon decodes them;
//! - [`detection`]: the four detector settings, per-run scoring;
//! - [`families`]: the motion-style families, tuning families marked, held-out reported;
//! - [`bound`]: the motion-only bound of each true event;
//! - [`report`]: aggregation, Markdown tables and the Table III consistency check;
//! - [`plots`]: SVG figures (plotters);
//! - [`isolation`]: the loop's timing alone and beside another process (A B A B …);
//! - [`shaft`]: the shaft-detector benchmark on rendered frames (paper, ours, OpenCV peers).

pub mod bound;
pub mod bus_loss;
pub mod detection;
pub mod families;
pub mod ipc;
pub mod isolation;
pub mod plots;
pub mod report;
pub mod shaft;
pub mod trace;
