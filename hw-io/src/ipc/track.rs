//! The tool tracker's output (issue 18): `comanip-track live` publishes one [`TrackSample`]
//! per frame it handles (iceoryx2 type name `comanip::TrackSample`, 288 bytes, `#[repr(C)]`)
//! on [`DEFAULT_TRACK_SERVICE`]: the instrument tip's pose in the endoscope's left camera frame
//! and in the tool arm's base frame, the jaw angle, a status, the particles' spread, which
//! frame and which calibration it rests on, and the frame counters. Publish with
//! [`Publisher<TrackSample>`], read with [`Subscriber<TrackSample>`]
//! (`hw-io/tests/ipc_track.rs`); the C declaration is in `hw-io/include/comanip/messages.h`.
//!
//! [`Publisher<TrackSample>`]: super::Publisher
//! [`Subscriber<TrackSample>`]: super::Subscriber

use core::fmt;

use iceoryx2::prelude::ZeroCopySend;

use super::message::{InvalidMessage, Message};

/// Layout version of [`TrackSample`].
pub const TRACK_SAMPLE_VERSION: u32 = 1;

/// The service `comanip-track live` publishes on.
pub const DEFAULT_TRACK_SERVICE: &str = "comanip/track";

/// What a [`TrackSample`] says about its frame. On the wire ([`TrackSample::status`]) it is the
/// `u32` of the variant.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u32)]
pub enum TrackStatus {
    /// The frame was not tracked: its input was refused (stale or non-finite joints, a frame
    /// of the wrong format, a corrupt frame header, the tracker refused it); the reasons say
    /// which. Every pose field is zero. Wire value 0.
    Invalid = 0,
    /// The best hypothesis fits the images and the particles agree: use the pose. Wire value 1.
    Tracking = 1,
    /// The best hypothesis fits but the particles' tip spread exceeds the configured limit:
    /// the pose is the best guess, with the spread as its uncertainty. Wire value 2.
    Uncertain = 2,
    /// The best hypothesis does not fit the images (likelihood collapse, the instrument out of
    /// view or occluded): no pose (every pose field zero). Wire value 3.
    Lost = 3,
}

impl TrackStatus {
    /// Upper-case name (`INVALID`, `TRACKING`, `UNCERTAIN`, `LOST`).
    pub const fn name(self) -> &'static str {
        match self {
            Self::Invalid => "INVALID",
            Self::Tracking => "TRACKING",
            Self::Uncertain => "UNCERTAIN",
            Self::Lost => "LOST",
        }
    }

    /// True when the sample carries a pose (`Tracking`, `Uncertain`).
    pub const fn has_pose(self) -> bool {
        matches!(self, Self::Tracking | Self::Uncertain)
    }
}

impl fmt::Display for TrackStatus {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

bitflags::bitflags! {
    /// Why a [`TrackSample`] has its status, and what it rests on: one flag per condition.
    /// On the wire ([`TrackSample::reasons`]) the `u32` of its bits; unknown bits are kept.
    #[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
    pub struct TrackReasons: u32 {
        /// No valid live calibration (none received, still collecting, or drift): the cameras
        /// come from the configuration's transform (`[rig]` of comanip-track.toml). Bit 0.
        /// Informational.
        const CALIBRATION_FROM_CONFIG = 1 << 0;
        /// The live calibration reported drift: its last pose is no longer used. Bit 1.
        /// Informational.
        const CALIBRATION_DRIFT = 1 << 1;
        /// A calibration message was refused (another layout version or a broken invariant,
        /// e.g. a NaN): the previous one stays in use. Bit 2. Informational.
        const CALIBRATION_REFUSED = 1 << 2;
        /// The tool arm's joints at the frame's time are unknown (no encoder readings around
        /// it: the bus is silent, or the frame is older or newer than the readings kept).
        /// Bit 3. Invalidating.
        const TOOL_JOINTS_STALE = 1 << 3;
        /// The endoscope arm's joints at the frame's time are unknown. Bit 4. Invalidating.
        const ENDOSCOPE_JOINTS_STALE = 1 << 4;
        /// A joint (either arm) or the cameras computed from them are not finite. Bit 5.
        /// Invalidating.
        const NOT_FINITE = 1 << 5;
        /// The frame is not a stereo RGB frame of the cameras' size. Bit 6. Invalidating.
        const FRAME_FORMAT = 1 << 6;
        /// A frame with a corrupt header arrived (refused by the frame subscriber; this sample
        /// stands for it, its frame fields zero). Bit 7. Invalidating.
        const FRAME_HEADER = 1 << 7;
        /// The tracker refused the frame (the joints are not a pose of the arm, the cameras
        /// are invalid). Bit 8. Invalidating.
        const TRACKER_REFUSED = 1 << 8;
        /// The particles were re-initialised from the kinematics at this frame (start, or after
        /// several lost frames). Bit 9. Informational.
        const REINITIALISED = 1 << 9;
        /// Frames were skipped before this one (the tracker keeps the newest frame when several
        /// arrived while it worked): the sequence numbers are not consecutive. Bit 10.
        /// Informational.
        const SKIPPED_BEFORE = 1 << 10;
    }
}

impl TrackReasons {
    /// The flags that make a sample [`TrackStatus::Invalid`].
    pub const INVALIDATING: Self = Self::TOOL_JOINTS_STALE
        .union(Self::ENDOSCOPE_JOINTS_STALE)
        .union(Self::NOT_FINITE)
        .union(Self::FRAME_FORMAT)
        .union(Self::FRAME_HEADER)
        .union(Self::TRACKER_REFUSED);
}

impl fmt::Display for TrackReasons {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        const NAMES: [(TrackReasons, &str); 11] = [
            (TrackReasons::CALIBRATION_FROM_CONFIG, "calibration-from-config"),
            (TrackReasons::CALIBRATION_DRIFT, "calibration-drift"),
            (TrackReasons::CALIBRATION_REFUSED, "calibration-refused"),
            (TrackReasons::TOOL_JOINTS_STALE, "tool-joints-stale"),
            (TrackReasons::ENDOSCOPE_JOINTS_STALE, "endoscope-joints-stale"),
            (TrackReasons::NOT_FINITE, "not-finite"),
            (TrackReasons::FRAME_FORMAT, "frame-format"),
            (TrackReasons::FRAME_HEADER, "frame-header"),
            (TrackReasons::TRACKER_REFUSED, "tracker-refused"),
            (TrackReasons::REINITIALISED, "reinitialised"),
            (TrackReasons::SKIPPED_BEFORE, "skipped-before"),
        ];
        if self.is_empty() {
            return f.write_str("ok");
        }
        let mut first = true;
        for (flag, name) in NAMES {
            if self.contains(flag) {
                if !first {
                    f.write_str(",")?;
                }
                f.write_str(name)?;
                first = false;
            }
        }
        let unknown = self.bits() & !Self::all().bits();
        if unknown != 0 {
            if !first {
                f.write_str(",")?;
            }
            write!(f, "unknown-{unknown:#x}")?;
        }
        Ok(())
    }
}

/// One tracking message: the wire layout (288 bytes, 8-byte aligned, no padding).
///
/// Frames: `{c}` the endoscope's left camera (x right, y down, z forward, metres), `{b}` the
/// tool arm's base. The pose is the instrument tip's (the jaw pivot; axes of the arm's frame 6,
/// `z` along the instrument): translation in metres, rotation as a unit quaternion
/// `[w, x, y, z]`. Every float is finite; the pose fields are zero unless the status is
/// `Tracking` or `Uncertain`.
#[derive(Clone, Copy, Debug, PartialEq, ZeroCopySend)]
#[type_name("comanip::TrackSample")]
#[repr(C)]
pub struct TrackSample {
    /// Layout version, [`TRACK_SAMPLE_VERSION`]. Offset 0.
    pub version: u32,
    /// The [`TrackStatus`] as its `u32`. Offset 4.
    pub status: u32,
    /// Message number of this publisher run (0 first). Offset 8.
    pub sequence: u64,
    /// Random identifier of the publisher run. Offset 16.
    pub run_id: u64,
    /// The frame's mid-exposure time, nanoseconds (the frame service's clock, `CLOCK_MONOTONIC`
    /// live). Offset 24.
    pub frame_timestamp_ns: u64,
    /// The frame's sequence number on the frame service. Offset 32.
    pub frame_sequence: u64,
    /// When this sample was published, nanoseconds of `CLOCK_MONOTONIC` (latency:
    /// `published_ns − frame_timestamp_ns` when the frames are stamped live). Offset 40.
    pub published_ns: u64,
    /// The [`TrackReasons`] as the `u32` of its bits. Offset 48.
    pub reasons: u32,
    /// Where the camera-to-base transform came from: 0 the configuration, 1 a live calibration
    /// (`comanip-calib live`'s `CalibrationSample`). Offset 52.
    pub calibration_source: u32,
    /// The `sequence` of the `CalibrationSample` used (0 with the configuration's). Offset 56.
    pub calibration_sequence: u64,
    /// The `run_id` of the `CalibrationSample` used (0 with the configuration's). Offset 64.
    pub calibration_run_id: u64,
    /// Tip position in the left camera frame `{c}`, metres. Offset 72.
    pub tip_camera_m: [f64; 3],
    /// Tip orientation in `{c}`, unit quaternion `[w, x, y, z]`. Offset 96.
    pub tip_camera_wxyz: [f64; 4],
    /// Tip position in the tool arm's base frame `{b}`, metres. Offset 128.
    pub tip_base_m: [f64; 3],
    /// Tip orientation in `{b}`, unit quaternion `[w, x, y, z]`. Offset 152.
    pub tip_base_wxyz: [f64; 4],
    /// Each jaw's opening, radians. Offset 184.
    pub jaw_rad: f64,
    /// The particles' tip spread (weighted standard deviation), metres; −1 when undefined (the
    /// weights collapsed, or the frame was not tracked). Offset 192.
    pub spread_m: f64,
    /// The best hypothesis's cost per eye, pixels; −1 when undefined. Offset 200.
    pub best_cost_px: f64,
    /// The estimated correction of the camera-to-base transform `g_CB` (rotation vector,
    /// radians, then translation, metres; zeros unless the augmentation is on). Offset 208.
    pub camera_delta: [f64; 6],
    /// Frames tracked or refused for their input since the process started (each has a
    /// sample). Offset 256.
    pub frames_processed: u64,
    /// Frames never looked at: dropped for a newer frame while the tracker worked, or lost in
    /// the transport (sequence gaps). Offset 264.
    pub frames_skipped: u64,
    /// Frames refused for a corrupt header. Offset 272.
    pub frames_rejected: u64,
    /// Of `frames_processed`, those whose input was refused (status `Invalid`). Offset 280.
    pub frames_invalid: u64,
}

impl TrackSample {
    /// An `Invalid` message with `reasons`, every other field zero (the pose's quaternions too).
    pub const fn invalid(reasons: TrackReasons) -> Self {
        Self {
            version: TRACK_SAMPLE_VERSION,
            status: TrackStatus::Invalid as u32,
            sequence: 0,
            run_id: 0,
            frame_timestamp_ns: 0,
            frame_sequence: 0,
            published_ns: 0,
            reasons: reasons.bits(),
            calibration_source: 0,
            calibration_sequence: 0,
            calibration_run_id: 0,
            tip_camera_m: [0.0; 3],
            tip_camera_wxyz: [0.0; 4],
            tip_base_m: [0.0; 3],
            tip_base_wxyz: [0.0; 4],
            jaw_rad: 0.0,
            spread_m: -1.0,
            best_cost_px: -1.0,
            camera_delta: [0.0; 6],
            frames_processed: 0,
            frames_skipped: 0,
            frames_rejected: 0,
            frames_invalid: 0,
        }
    }

    /// The typed status; `None` for a value no [`TrackStatus`] has.
    pub const fn status(&self) -> Option<TrackStatus> {
        match self.status {
            0 => Some(TrackStatus::Invalid),
            1 => Some(TrackStatus::Tracking),
            2 => Some(TrackStatus::Uncertain),
            3 => Some(TrackStatus::Lost),
            _ => None,
        }
    }

    /// The typed reasons (unknown bits kept).
    pub const fn reasons(&self) -> TrackReasons {
        TrackReasons::from_bits_retain(self.reasons)
    }

    fn floats(&self) -> impl Iterator<Item = &f64> {
        self.tip_camera_m
            .iter()
            .chain(&self.tip_camera_wxyz)
            .chain(&self.tip_base_m)
            .chain(&self.tip_base_wxyz)
            .chain([&self.jaw_rad, &self.spread_m, &self.best_cost_px])
            .chain(&self.camera_delta)
    }
}

impl Message for TrackSample {
    const TYPE_NAME: &'static str = "comanip::TrackSample";
    const VERSION: u32 = TRACK_SAMPLE_VERSION;
    const PUBLISHER_NODE_NAME: &'static str = "comanip-track-live";
    const SUBSCRIBER_NODE_NAME: &'static str = "track-subscriber";

    fn version(&self) -> u32 {
        self.version
    }

    fn sequence(&self) -> u64 {
        self.sequence
    }

    fn run_id(&self) -> u64 {
        self.run_id
    }

    /// Refuses an unknown status, any non-finite float, a pose-carrying status with a
    /// non-unit quaternion or an invalidating reason, and an `Invalid` sample without one.
    fn check(&self) -> Result<(), InvalidMessage> {
        let Some(status) = self.status() else {
            return Err(InvalidMessage { what: "unknown track status" });
        };
        if !self.floats().all(|v| v.is_finite()) {
            return Err(InvalidMessage { what: "a track field is not finite" });
        }
        let invalidating = self.reasons().intersects(TrackReasons::INVALIDATING);
        if status.has_pose() {
            if invalidating {
                return Err(InvalidMessage { what: "a pose published with an invalidating reason" });
            }
            for q in [&self.tip_camera_wxyz, &self.tip_base_wxyz] {
                let n2: f64 = q.iter().map(|v| v * v).sum();
                if (n2 - 1.0).abs() > 1e-6 {
                    return Err(InvalidMessage { what: "a tracked pose's quaternion is not unit" });
                }
            }
        } else if status == TrackStatus::Invalid && !invalidating {
            return Err(InvalidMessage { what: "an invalid sample without an invalidating reason" });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_is_fixed() {
        assert_eq!(core::mem::size_of::<TrackSample>(), 288);
        assert_eq!(core::mem::align_of::<TrackSample>(), 8);
        assert_eq!(core::mem::offset_of!(TrackSample, reasons), 48);
        assert_eq!(core::mem::offset_of!(TrackSample, tip_camera_m), 72);
        assert_eq!(core::mem::offset_of!(TrackSample, camera_delta), 208);
        assert_eq!(core::mem::offset_of!(TrackSample, frames_invalid), 280);
    }

    #[test]
    fn the_type_name_is_iceoryx2s() {
        // SAFETY: `type_name` only returns the string of `#[type_name(..)]`; its safety contract
        // concerns implementing the trait (the layout), not calling it.
        let iceoryx2_name = unsafe { <TrackSample as ZeroCopySend>::type_name() };
        assert_eq!(iceoryx2_name, TrackSample::TYPE_NAME);
    }

    fn tracking() -> TrackSample {
        let mut s = TrackSample::invalid(TrackReasons::empty());
        s.status = TrackStatus::Tracking as u32;
        s.tip_camera_wxyz = [1.0, 0.0, 0.0, 0.0];
        s.tip_base_wxyz = [0.0, 0.0, 1.0, 0.0];
        s.tip_camera_m = [0.01, -0.02, 0.12];
        s.spread_m = 0.001;
        s
    }

    #[test]
    fn check_refuses_nan_unknown_status_non_unit_quaternions_and_inconsistent_reasons() {
        assert_eq!(tracking().check(), Ok(()));
        let mut s = tracking();
        s.tip_base_m[1] = f64::NAN;
        assert!(s.check().is_err(), "NaN published as tracking");
        let mut s = tracking();
        s.spread_m = f64::INFINITY;
        assert!(s.check().is_err());
        let mut s = tracking();
        s.tip_camera_wxyz = [0.0; 4];
        assert!(s.check().is_err(), "zero quaternion marked tracking");
        let mut s = tracking();
        s.reasons = TrackReasons::TOOL_JOINTS_STALE.bits();
        assert!(s.check().is_err(), "pose with stale joints");
        let mut s = tracking();
        s.reasons = (TrackReasons::CALIBRATION_FROM_CONFIG | TrackReasons::REINITIALISED).bits();
        assert_eq!(s.check(), Ok(()), "informational reasons");
        let mut s = tracking();
        s.status = 7;
        assert!(s.status().is_none() && s.check().is_err());
        assert!(TrackSample::invalid(TrackReasons::empty()).check().is_err(), "invalid without a reason");
        let inv = TrackSample::invalid(TrackReasons::FRAME_HEADER);
        assert_eq!(inv.check(), Ok(()));
        assert_eq!(inv.status(), Some(TrackStatus::Invalid));
        let mut lost = TrackSample::invalid(TrackReasons::empty());
        lost.status = TrackStatus::Lost as u32;
        assert_eq!(lost.check(), Ok(()));
    }

    #[test]
    fn reasons_display_names_every_flag_and_keeps_unknown_bits() {
        assert_eq!(TrackReasons::empty().to_string(), "ok");
        let r = TrackReasons::TOOL_JOINTS_STALE | TrackReasons::CALIBRATION_FROM_CONFIG;
        assert_eq!(r.to_string(), "calibration-from-config,tool-joints-stale");
        assert_eq!(TrackReasons::from_bits_retain(1 << 20).to_string(), "unknown-0x100000");
        assert!(TrackReasons::all().iter().all(|f| !f.to_string().starts_with("unknown")));
    }
}
