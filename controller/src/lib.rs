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
//! - [`timing`]: allocation-free latency histograms.
//!
//! The offline tools live in their own packages beside this one, so that fulcrumd links no
//! plotting or parallel-iteration crate: `controller/bench` (`comanip-bench`) and
//! `controller/calib` (`comanip-calib`).
#![warn(missing_docs)]

pub mod bus_listen;
pub mod config;
pub mod cycle;
pub mod daemon;
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
