//! The live calibration's output (issue 19): `comanip-calib live` publishes the registration
//! of the tool arm to the endoscope arm as [`CalibrationSample`]s (iceoryx2 type name
//! `comanip::CalibrationSample`, 432 bytes, `#[repr(C)]`) on [`DEFAULT_CALIBRATION_SERVICE`],
//! so that the tracker starts from it. Publish with [`Publisher<CalibrationSample>`], read
//! with [`Subscriber<CalibrationSample>`] (`hw-io/tests/ipc_calibration.rs`). A tracker that
//! starts later should get the latest calibration: the live process is meant to republish
//! its current state periodically (a service history is not relied on: untested).
//!
//! [`Publisher<CalibrationSample>`]: super::Publisher
//! [`Subscriber<CalibrationSample>`]: super::Subscriber

use iceoryx2::prelude::ZeroCopySend;

use super::message::{InvalidMessage, Message};

/// Layout version of [`CalibrationSample`].
pub const CALIBRATION_SAMPLE_VERSION: u32 = 1;

/// The service `comanip-calib live` publishes on.
pub const DEFAULT_CALIBRATION_SERVICE: &str = "comanip/calibration";

/// What a [`CalibrationSample`] says.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u32)]
pub enum CalibrationState {
    /// Collecting: no calibration yet (the pose fields are zero, the predicted precision is
    /// what the data support so far, or zero).
    Collecting = 0,
    /// A calibration whose predicted precision reached the target: use it.
    Valid = 1,
    /// The last calibration no longer fits new observations (drift): do not use it;
    /// collection restarted.
    Drift = 2,
}

/// One calibration message: the wire layout.
///
/// `T_e_t`: the tool arm's base frame `{t}` (for comanip's Achilles-type arm, its robot base)
/// in the endoscope arm's RCM frame `{e}`, metres and a unit quaternion `[w, x, y, z]`; its
/// covariance in the order `(tx, ty, tz m, φx, φy, φz rad)`, `φ` a left rotation increment in
/// `{e}`. Every float is finite.
#[derive(Clone, Copy, Debug, PartialEq, ZeroCopySend)]
#[type_name("comanip::CalibrationSample")]
#[repr(C)]
pub struct CalibrationSample {
    /// Layout version, [`CALIBRATION_SAMPLE_VERSION`].
    pub version: u32,
    /// The [`CalibrationState`] as its `u32`.
    pub state: u32,
    /// Message number of this publisher run (0 first).
    pub sequence: u64,
    /// Random identifier of the publisher run.
    pub run_id: u64,
    /// Exposure mid time of the last frame used, nanoseconds (the frame service's clock).
    pub timestamp_ns: u64,
    /// Observations (eye lines) the calibration rests on, or collected so far.
    pub observations: u32,
    /// Drift events since the process started.
    pub drifts: u32,
    /// Translation of `T_e_t`, metres, `{e}`.
    pub translation_m: [f64; 3],
    /// Rotation of `T_e_t`, unit quaternion `[w, x, y, z]` (zero while collecting).
    pub quaternion_wxyz: [f64; 4],
    /// Covariance of `(t, φ)`, row-major 6×6 (m², m·rad, rad²), from the Fisher information.
    pub covariance: [f64; 36],
    /// Predicted RMS translation error at the mean fulcrum, metres.
    pub predicted_fulcrum_m: f64,
    /// Predicted RMS translation error of `{t}`'s origin, metres.
    pub predicted_origin_m: f64,
    /// Predicted RMS rotation error, radians.
    pub predicted_rotation_rad: f64,
    /// The mean fulcrum of the observations, metres, `{t}` (where the translation precision
    /// above holds).
    pub mean_fulcrum_m: [f64; 3],
}

impl CalibrationSample {
    /// A "collecting" message with every pose field zero.
    pub const fn collecting(observations: u32) -> Self {
        Self {
            version: CALIBRATION_SAMPLE_VERSION,
            state: CalibrationState::Collecting as u32,
            sequence: 0,
            run_id: 0,
            timestamp_ns: 0,
            observations,
            drifts: 0,
            translation_m: [0.0; 3],
            quaternion_wxyz: [0.0; 4],
            covariance: [0.0; 36],
            predicted_fulcrum_m: 0.0,
            predicted_origin_m: 0.0,
            predicted_rotation_rad: 0.0,
            mean_fulcrum_m: [0.0; 3],
        }
    }

    /// The typed state; `None` for a value no [`CalibrationState`] has.
    pub fn state(&self) -> Option<CalibrationState> {
        match self.state {
            0 => Some(CalibrationState::Collecting),
            1 => Some(CalibrationState::Valid),
            2 => Some(CalibrationState::Drift),
            _ => None,
        }
    }
}

impl Message for CalibrationSample {
    const TYPE_NAME: &'static str = "comanip::CalibrationSample";
    const VERSION: u32 = CALIBRATION_SAMPLE_VERSION;
    const PUBLISHER_NODE_NAME: &'static str = "comanip-calib-live";
    const SUBSCRIBER_NODE_NAME: &'static str = "calibration-subscriber";

    fn version(&self) -> u32 {
        self.version
    }

    fn sequence(&self) -> u64 {
        self.sequence
    }

    fn run_id(&self) -> u64 {
        self.run_id
    }

    fn check(&self) -> Result<(), InvalidMessage> {
        let Some(state) = self.state() else {
            return Err(InvalidMessage { what: "unknown calibration state" });
        };
        let predicted = [self.predicted_fulcrum_m, self.predicted_origin_m, self.predicted_rotation_rad];
        let mut floats = self
            .translation_m
            .iter()
            .chain(&self.quaternion_wxyz)
            .chain(&self.covariance)
            .chain(&self.mean_fulcrum_m)
            .chain(&predicted);
        if !floats.all(|v| v.is_finite()) {
            return Err(InvalidMessage { what: "a calibration field is not finite" });
        }
        if state == CalibrationState::Valid {
            let n2: f64 = self.quaternion_wxyz.iter().map(|v| v * v).sum();
            if (n2 - 1.0).abs() > 1e-6 {
                return Err(InvalidMessage { what: "a valid calibration's quaternion is not unit" });
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_is_fixed() {
        assert_eq!(core::mem::size_of::<CalibrationSample>(), 432);
        assert_eq!(core::mem::align_of::<CalibrationSample>(), 8);
        assert_eq!(core::mem::offset_of!(CalibrationSample, translation_m), 40);
        assert_eq!(core::mem::offset_of!(CalibrationSample, covariance), 96);
    }

    #[test]
    fn the_type_name_is_iceoryx2s() {
        // SAFETY: `type_name` only returns the string of `#[type_name(..)]`; its safety contract
        // concerns implementing the trait (the layout), not calling it.
        let iceoryx2_name = unsafe { <CalibrationSample as ZeroCopySend>::type_name() };
        assert_eq!(iceoryx2_name, CalibrationSample::TYPE_NAME);
    }

    #[test]
    fn check_refuses_unknown_states_non_finite_fields_and_non_unit_quaternions() {
        let c = CalibrationSample::collecting(3);
        assert_eq!(c.check(), Ok(()));
        assert_eq!(c.state(), Some(CalibrationState::Collecting));
        let mut v = c;
        v.state = CalibrationState::Valid as u32;
        assert!(v.check().is_err(), "zero quaternion marked valid");
        v.quaternion_wxyz = [1.0, 0.0, 0.0, 0.0];
        assert_eq!(v.check(), Ok(()));
        v.covariance[7] = f64::NAN;
        assert!(v.check().is_err());
        let mut u = c;
        u.state = 9;
        assert!(u.state().is_none() && u.check().is_err());
    }
}
