//! # sim: the world outside the controller, with ground truth
//!
//! Deterministic from a seed:
//! - [`scenario`]: the surgeon's motion of the instrument through several trocars, as
//!   instrument lines in the robot base frame (metres) with the true state and fulcrum of
//!   every sample;
//! - [`robot`]: the simulated arm (nominal DH table plus a calibration error) and its
//!   inverse kinematics;
//! - [`encoders`]: the three virtual encoder nodes on the CAN bus;
//! - [`endoscope_arm`]: the endoscope-holder arm on the same bus (its motion and its two
//!   nodes, every 10th SYNC);
//! - [`twin`]: all of it together, the simulated robot answering the controller's SYNCs
//!   ([`twin::SimRobot`]);
//! - [`truth_file`]: the ground-truth file of a run (JSON Lines) and scoring against it;
//! - [`score`]: scoring a detector against ground truth;
//! - [`calib`]: the dual RCM-arm calibration paper's simulation protocol (Sec. IV);
//! - [`world`]: both arms in one world: the renderer's scene at a bus time, with the
//!   endoscope on the endoscope arm looking at the tool arm's instrument;
//! - [`endoscope`]: the simulated stereo endoscope: rendered frames of tissue and
//!   instruments with their ground truth (`docs/vision.md`);
//! - [`camera`]: the simulated endoscope as a camera source of the frame transport
//!   ([`camera::SimCamera`], `docs/frames.md`), and [`live_camera`]: it, rendering the two
//!   simulated arms in step with the live bus (`simrobot live --camera`).
//!
//! The `simrobot` binary writes a run to a candump log plus its ground truth, or plays the
//! robot live on a SocketCAN interface; see `docs/simulator.md`.
#![warn(missing_docs)]

pub mod calib;
pub mod camera;
pub mod encoders;
pub mod endoscope;
pub mod endoscope_arm;
pub mod live_camera;
pub mod robot;
pub mod scenario;
pub mod score;
pub mod truth_file;
pub mod twin;
pub mod world;
