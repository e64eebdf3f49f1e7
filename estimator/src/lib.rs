//! # comanip estimator: the product's own mathematics
//!
//! Pure, deterministic maths with no I/O, no threads and no clocks (one exception, opt-in: the
//! feature `parallel` runs an offline calibration's independent work on rayon's pool, results
//! bit for bit the serial build's; off by default). Everything here is
//! `no_std`-capable (disable the default `std` feature) and allocation-free after
//! construction: windows are fixed-capacity [`heapless`] buffers and every matrix is a
//! fixed-size [`nalgebra`] type.
//!
//! ## Layers
//! - [`kinematics`]: the Achilles-type comanipulator (3 motorised joints place the wrist
//!   centre P, 3 passive joints whose axes meet at P orient the instrument). Joint angles
//!   (radians) in, wrist centre P (metres, robot base frame) and instrument axis z (unit
//!   vector, robot base frame) out.
//! - [`trocar`]: is the instrument in a trocar, and where is the fulcrum? Two detectors
//!   behind one [`trocar::Detector`]: the paper's method (Dong & Morel) reproduced
//!   faithfully, and comanip's faster method. Both consume one [`trocar::LineSample`] per
//!   1 ms cycle and return one [`trocar::Estimate`], never NaN or Inf.
//!
//! - [`calib`] (feature `std`): offline dual RCM-arm calibration (Wang et al. 2017), the
//!   paper's pipeline and ours, and the Cramér-Rao bound.
//!
//! ## Frames and units
//! All positions are in metres, all angles in radians, and every vector is expressed in the
//! robot base frame unless a name or doc comment says otherwise.
//!
//! ```
//! use estimator::kinematics::{Achilles, AchillesConfig};
//! use estimator::trocar::{Detector, DetectorConfig, LineSample};
//!
//! let arm = Achilles::new(&AchillesConfig::default()).unwrap();
//! let mut detector = Detector::new(&DetectorConfig::default()).unwrap();
//! let pose = arm.forward(&[0.1, 0.9, 0.4, 0.0, 0.3, 0.0]).unwrap();
//! let estimate = detector.step(&LineSample::new(pose.wrist_base_m, pose.axis_base));
//! assert!(!estimate.state.is_inside()); // one line says nothing about a trocar
//! ```
#![cfg_attr(not(feature = "std"), no_std)]
#![forbid(unsafe_code)]
#![warn(missing_docs)]

// Unit tests use `std` (vectors of scripted lines) even when the crate is built without it.
#[cfg(all(test, not(feature = "std")))]
extern crate std;

#[cfg(feature = "std")]
pub mod calib;
pub mod kinematics;
pub mod trocar;

pub use nalgebra;
