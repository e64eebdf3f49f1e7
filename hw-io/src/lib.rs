//! # hw-io: every byte that crosses a boundary
//!
//! CAN frames and bus backends, shared-memory messages and files. Typed errors for every
//! malformed input; nothing here panics on any byte pattern.
//!
//! ## Modules and features
//! Each boundary is a Cargo feature (all three are default); a client links only what it reads.
//! A guidance-force module that subscribes to fulcrumd's output needs
//! `hw-io = { default-features = false, features = ["ipc"] }`: no SocketCAN, nix or nalgebra.
//!
//! - [`can`] (feature `can`: socketcan, nix): the encoder bus. Our own allocation-free
//!   [`can::CanFrame`], the CANopen-style protocol (SYNC every 1 ms, one TPDO1 per encoder
//!   node, heartbeat, EMCY; see `docs/can-protocol.md`), encoder counts to radians, and the bus
//!   backends behind the one trait [`can::CanBus`]: Linux SocketCAN, an in-process bus,
//!   candump-log replay.
//! - [`ipc`] (feature `ipc`: iceoryx2, bitflags, tracing): shared-memory messages. The
//!   versioned [`ipc::Message`] trait and the generic [`ipc::Publisher`] /
//!   [`ipc::Subscriber`] (version check, continuity); the daemon's [`ipc::FulcrumSample`] with
//!   its typed [`ipc::OutputState`] and [`ipc::HealthFlags`], [`ipc::FulcrumPublisher`] and
//!   the client library [`ipc::FulcrumSubscriber`] (see `docs/output.md`).
//! - [`calib_files`] (feature `calib-files`: estimator, serde_json, serde_yaml_ng): the dual
//!   RCM-arm calibration's files: camera intrinsics (OpenCV / ROS YAML), dataset, ground truth
//!   and result (JSON), see `docs/calibration.md`.
//! - `camera` (feature `camera`: image): camera sources behind one trait, `camera::CameraSource`
//!   (image-sequence directories; Video4Linux2 devices with feature `v4l2`: zune-jpeg for
//!   MJPEG), writing each frame into a buffer the caller owns (a loaned shared-memory slot of the
//!   frame service, `ipc::FramePublisher`).
//! - [`frame`] (always): camera frames as they cross a boundary: pixel formats, image layouts
//!   and the metadata of one (stereo) frame, shared by the camera sources and the frame
//!   transport (`docs/vision.md`).
//! - [`stdout`] (always): the command-line tools' standard output, quiet on a closed pipe
//!   ([`outln!`]).
//! - [`rt_alloc`] (always): a global allocator that serves the small allocations of real-time
//!   threads (iceoryx2's 48 bytes per published sample) from a static lock-free pool.
//!
//! Units: times are microseconds since the Unix epoch (`unix_time_us`) or
//! [`std::time::Duration`]s; joint positions on the bus are encoder counts, and radians
//! after [`can::EncoderConfig::counts_to_rad`].
#![warn(missing_docs)]

#[cfg(feature = "calib-files")]
pub mod calib_files;
#[cfg(feature = "camera")]
pub mod camera;
#[cfg(feature = "can")]
pub mod can;
pub mod frame;
#[cfg(feature = "ipc")]
pub mod ipc;
pub mod rt_alloc;
pub mod stdout;
