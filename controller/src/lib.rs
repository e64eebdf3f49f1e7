//! # comanip controller: the processes
//!
//! - `fulcrumd` ([`daemon`]): the trocar daemon. A 1 kHz loop ([`rt_loop`]) sends SYNC on
//!   the encoder bus, assembles the TPDOs and checks the nodes' health ([`cycle`],
//!   [`health`]), runs forward kinematics and the trocar detector, and publishes one
//!   estimate per cycle over iceoryx2 (`hw_io::ipc`). Around it: real-time set-up ([`rt`]),
//!   systemd notifications ([`watchdog`]), the flight recorder ([`recorder`]), `replay`
//!   ([`replay`], [`scoring`]) and the built-in simulated robot ([`sim_robot`]).
//! - [`process`]: the skeleton every comanip process reuses (logging, stop signals, a
//!   real-time thread with its handshake, systemd, the JSON summary); fulcrumd's phases
//!   ([`daemon::Configured`] → [`daemon::Running`]) show how.
//! - [`config`]: the TOML configuration, validated at load with messages that name the key.
//! - [`demo`]: the detector over an in-memory simulated scenario (no bus), for quick scoring.
//! - [`timing`]: allocation-free latency histograms.
//! - `comanip-calib` ([`calib`]): dual RCM-arm calibration (simulate, calibrate, sweep).
#![warn(missing_docs)]

pub mod bench;
pub mod calib;
pub mod config;
pub mod cycle;
pub mod daemon;
pub mod demo;
pub mod health;
pub mod health_log;
pub mod monitor;
pub mod process;
pub mod recorder;
pub mod recording_dir;
pub mod replay;
pub mod rt;
pub mod rt_loop;
pub mod scoring;
pub mod sim_robot;
pub mod timing;
pub mod watchdog;
