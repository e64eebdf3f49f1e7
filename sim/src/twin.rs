//! The simulated Achilles-type robot on the encoder bus: the digital twin.
//!
//! [`SimRobot`] puts the pieces of this crate together. At every SYNC of the controller it
//! advances the surgeon's motion by one sample ([`crate::scenario`]), solves the inverse
//! kinematics of the **true** instrument line on the **true** arm ([`crate::robot`]:
//! nominal DH table plus a calibration error) and lets the three virtual encoder nodes
//! ([`crate::encoders`]) answer with TPDOs, heartbeats and EMCYs. The endoscope-holder arm
//! ([`crate::endoscope_arm`], on by default) answers on the same bus with its two nodes, every
//! 10th SYNC. Ground truth (state, pivot, line, the true insertions and extractions, the
//! endoscope arm's joints) is available at every sample.
//!
//! ## What the controller sees, and why
//! The controller turns the encoder counts into joint angles and runs the *nominal* forward
//! kinematics (the `[kinematics]` of its config, [`TwinConfig::kinematics`] here). The twin
//! moves the *true* arm, so the line the controller computes differs from the true line by
//! exactly two physical effects:
//! - the **calibration error** of the arm ([`ModelErrorConfig`]; by default ±0.5 mm on
//!   every DH length and ±1 mrad on every joint offset): a smooth, pose-dependent bias of a
//!   millimetre or less (0.8 mm and 1.3 mrad at most in `sim/tests/twin.rs`);
//! - the **encoder quantisation** (2^17 counts per revolution by default: 48 µrad per joint,
//!   under 20 µm at the wrist).
//!
//! The scenario's white measurement noise (`scenario.wrist_noise_m`, `axis_noise_deg`, which
//! the in-memory demo feeds its detector) is **not** applied by default: encoders have no
//! such noise. Set [`TwinConfig::measurement_noise`] to solve the inverse kinematics for the
//! scenario's noisy *measured* line instead, e.g. to compare with the in-memory demo; the
//! ground truth stays the noise-free line either way.
//!
//! ## Time
//! One SYNC is one sample: the scenario's sample period must be the 1 ms SYNC period
//! ([`SYNC_PERIOD_US`]). Sample `n` (counted from 0 over the whole run) is at
//! `t_s = n · 0.001 s`. Times in [`NodeOptions`] (dropout windows, EMCY injections) are
//! microseconds since the first SYNC the twin answered; the frames returned by
//! [`SimRobot::on_sync`] are stamped in the caller's time base (the `t_us` it passes, plus
//! each node's latency).
//!
//! ## Endless mode
//! With [`TwinConfig::endless`], when a scenario is over the twin generates the next one with
//! the seed plus one (same trocars and parameters) and goes on. To keep the motion
//! continuous, a **transition** joins the last pose of the old scenario to the first pose of
//! the new one (wrist straight line, axis by the shortest rotation, minimum-jerk timing over
//! 0.5-5 s: 0.1 m/s and 0.5 rad/s on average, 0.19 m/s and 0.94 rad/s at the peak). The
//! instrument is outside every trocar during the transition. Generating the next scenario
//! allocates (about 150 bytes per sample); nothing else in [`SimRobot::on_sync`] does.
//!
//! ## Cost
//! The inverse kinematics is a damped Gauss-Newton iteration seeded by the previous
//! sample's solution (see [`crate::robot`]); `docs/simulator.md` gives the measured cost per
//! sample.

use estimator::kinematics::{AchillesConfig, JOINTS, KinematicsConfigError};
use estimator::trocar::LineSample;
use hw_io::can::{ENCODER_NODES, EncoderConfig, JointToCountsError};
use nalgebra::{Unit, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use crate::encoders::{MAX_FRAMES_PER_SYNC, NodeOptions, VirtualNodes, VirtualNodesError};
use crate::endoscope_arm::{
    ECM_JOINTS, ECM_MAX_FRAMES_PER_SYNC, EcmNodes, EndoscopeArmConfig, EndoscopeArmConfigError, EndoscopeMotion,
};
use crate::robot::{IkError, IkTracker, ModelError, SimulatedArm};
use crate::scenario::{Scenario, ScenarioConfig, ScenarioConfigError, Truth, TruthState, generate};

/// The SYNC period of the encoder bus, microseconds: one sample of the twin per SYNC.
pub const SYNC_PERIOD_US: u64 = 1000;

/// Default trocar positions of the twin, metres, robot base frame: those of
/// [`ScenarioConfig::default`] moved 10-12 cm towards the robot (0.26-0.35 m from the base
/// axis, 1 cm lower). With the scenario's defaults the wrist goes up to 0.72 m from the
/// shoulder in about 1-2 % of the samples (entry tilt up to 25° plus pivoting, and the lift
/// of the free motions), out of the 0.6 m reach of the default arm; with these, at most
/// 0.582 m (20 seeds of 99 cycles), and the wrist stays at least 4 cm from the base axis.
pub const DEFAULT_TROCARS_BASE_M: [[f64; 3]; 4] =
    [[0.30, -0.09, 0.0], [0.34, -0.02, 0.02], [0.31, 0.07, 0.01], [0.26, 0.01, -0.01]];

/// Most frames [`SimRobot::on_sync`] returns for one SYNC: the tool arm's nodes and the
/// endoscope arm's.
pub const MAX_TWIN_FRAMES_PER_SYNC: usize = MAX_FRAMES_PER_SYNC + ECM_MAX_FRAMES_PER_SYNC;

/// The frames of one SYNC (both arms' nodes), in bus order; microseconds in the caller's time
/// base.
pub type TwinFrames = heapless::Vec<hw_io::can::TimedFrame, MAX_TWIN_FRAMES_PER_SYNC>;

/// Most true events one sample can cross (an insertion and an extraction need at least one
/// sample between them, so one is the practical maximum).
pub const MAX_EVENTS_PER_SAMPLE: usize = 4;

/// Calibration error of the simulated arm: the true arm is the nominal arm plus a random,
/// fixed error drawn from `seed` ([`ModelError::from_seed`]), except that the passive wrist
/// stays spherical: the lengths that must be zero for the axes of joints 4, 5 and 6 to meet
/// in one point (`a_m` of joints 4, 5 and 6, `d_m` of joint 5) get no error. A wrist whose
/// axes miss each other by a fraction of a millimetre makes some lines near the wrist
/// singularity (instrument parallel to the forearm) unreachable: 2 inverse-kinematics
/// failures in 7.7 million samples of default scenarios, none with the spherical wrist.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModelErrorConfig {
    /// Seed of the error draw.
    pub seed: u64,
    /// Bound of the error of every DH length (`d_m`, `a_m` of joints 1..6), metres: each is
    /// uniform in `±link_length_m`. 0 for none.
    pub link_length_m: f64,
    /// Bound of the error of every DH angle offset (joints 1..6), radians: each is uniform in
    /// `±joint_offset_rad`. 0 for none.
    pub joint_offset_rad: f64,
}

impl Default for ModelErrorConfig {
    fn default() -> Self {
        Self { seed: 1, link_length_m: 0.0005, joint_offset_rad: 0.001 }
    }
}

impl ModelErrorConfig {
    /// No calibration error: the true arm is the nominal arm.
    pub fn zero() -> Self {
        Self { seed: 0, link_length_m: 0.0, joint_offset_rad: 0.0 }
    }

    /// The error these bounds and seed give (with a spherical wrist, see above).
    pub fn model_error(&self) -> ModelError {
        let mut e = ModelError::from_seed(self.seed, self.link_length_m, self.joint_offset_rad);
        // [d_m, a_m] of joints 1..6: keep a4, d5, a5 and a6 exact.
        e.link_length_errors_m[3][1] = 0.0;
        e.link_length_errors_m[4] = [0.0, 0.0];
        e.link_length_errors_m[5][1] = 0.0;
        e
    }
}

/// Everything that defines a twin; the `--config` file of `simrobot` (see
/// `configs/simrobot.toml`, which lists the defaults).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TwinConfig {
    /// The surgeon's motion (trocars, cycles, timing). `sample_period_s` must be 0.001 s. The
    /// default is [`ScenarioConfig::default`] with the trocars at [`DEFAULT_TROCARS_BASE_M`];
    /// a key missing from a given `[scenario]` table takes that default too.
    #[serde(deserialize_with = "scenario_with_twin_defaults")]
    pub scenario: ScenarioConfig,
    /// The nominal arm: the DH table the controller believes in (must match its
    /// `[kinematics]`).
    pub kinematics: AchillesConfig,
    /// Calibration error of the true arm against the nominal one.
    pub model_error: ModelErrorConfig,
    /// Encoder node IDs and counts-to-radians conversion (must match the controller's
    /// `[bus.encoder]`).
    pub encoder: EncoderConfig,
    /// Behaviour of the nodes carrying joints 1-2, 3-4 and 5-6 (exactly three).
    pub nodes: [NodeOptions; ENCODER_NODES],
    /// Seed of the nodes' random TPDO dropouts.
    pub nodes_seed: u64,
    /// Angle of joint 6 (roll about the instrument axis), radians, held constant.
    pub roll_rad: f64,
    /// Solve the inverse kinematics for the scenario's noisy *measured* line instead of the
    /// true line (adds the scenario's white measurement noise; off by default).
    pub measurement_noise: bool,
    /// When the scenario is over, go on with the next one (seed + 1) instead of stopping.
    pub endless: bool,
    /// The endoscope-holder arm on the same bus (`[endoscope_arm]`; on by default; see
    /// [`crate::endoscope_arm`]).
    pub endoscope_arm: EndoscopeArmConfig,
}

/// The twin's default scenario.
fn default_scenario() -> ScenarioConfig {
    ScenarioConfig { trocars_base_m: DEFAULT_TROCARS_BASE_M.to_vec(), ..ScenarioConfig::default() }
}

/// A `[scenario]` table whose missing keys take the twin's defaults (not those of
/// [`ScenarioConfig::default`], whose trocars are partly out of the arm's reach).
fn scenario_with_twin_defaults<'de, D: serde::Deserializer<'de>>(d: D) -> Result<ScenarioConfig, D::Error> {
    use serde::de::Error;
    use serde_json::{Map, Value};
    let given = Map::<String, Value>::deserialize(d)?;
    let mut merged = match serde_json::to_value(default_scenario()) {
        Ok(Value::Object(m)) => m,
        _ => Map::new(),
    };
    merged.extend(given);
    serde_json::from_value(Value::Object(merged)).map_err(D::Error::custom)
}

impl Default for TwinConfig {
    fn default() -> Self {
        Self {
            scenario: default_scenario(),
            kinematics: AchillesConfig::default(),
            model_error: ModelErrorConfig::default(),
            encoder: EncoderConfig::default(),
            nodes: Default::default(),
            nodes_seed: 1,
            roll_rad: 0.0,
            measurement_noise: false,
            endless: false,
            endoscope_arm: EndoscopeArmConfig::default(),
        }
    }
}

/// Why a twin could not be built from a [`TwinConfig`]; the message names the key.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TwinConfigError {
    /// A scenario parameter is out of range.
    #[error(transparent)]
    Scenario(#[from] ScenarioConfigError),
    /// The nominal or the true DH table is invalid.
    #[error("kinematics (nominal, or nominal plus model_error): {0}")]
    Kinematics(#[from] KinematicsConfigError),
    /// A model-error bound is negative, not finite or implausibly large.
    #[error("model_error.{key} = {value}: allowed 0 ..= {max}")]
    ModelError {
        /// The key.
        key: &'static str,
        /// The value given.
        value: f64,
        /// Largest value allowed.
        max: f64,
    },
    /// The encoder or node configuration is invalid.
    #[error("encoder / nodes: {0}")]
    Nodes(#[from] VirtualNodesError),
    /// The roll angle is not finite.
    #[error("roll_rad = {0}: must be finite")]
    Roll(f64),
    /// The endoscope arm's configuration is invalid.
    #[error(transparent)]
    EndoscopeArm(#[from] EndoscopeArmConfigError),
}

/// A true insertion or extraction as the twin crosses it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TwinEvent {
    /// Sample index over the whole run (0 = first SYNC answered): the first sample of the new
    /// state, i.e. the sample at which the tip has crossed the trocar point.
    pub sample: u64,
    /// Time of that sample, seconds since sample 0 (`sample · 0.001`).
    pub t_s: f64,
    /// Time of the SYNC of that sample in the caller's time base (the `t_us` given to
    /// [`SimRobot::on_sync`]; microseconds since the Unix epoch for `simrobot`).
    pub unix_time_us: u64,
    /// Trocar index into `scenario.trocars_base_m`.
    pub trocar: usize,
    /// True for an insertion, false for an extraction.
    pub insertion: bool,
}

/// Why one SYNC could not be answered. Nothing advanced: the next call retries the same
/// sample.
#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
pub enum TwinError {
    /// The true line of this sample has no inverse kinematics on the true arm (usually a
    /// trocar out of the arm's reach).
    #[error("sample {sample}: {source}")]
    Ik {
        /// Sample index over the whole run.
        sample: u64,
        /// The solver's error.
        source: IkError,
    },
    /// An endoscope-arm joint has no encoder count (out of the `i32` range).
    #[error("sample {sample}: an endoscope-arm joint is outside the i32 count range")]
    EndoscopeCounts {
        /// Sample index over the whole run.
        sample: u64,
    },
    /// A joint angle has no encoder count (out of the `i32` range).
    #[error("sample {sample}: {source}")]
    Counts {
        /// Sample index over the whole run.
        sample: u64,
        /// The conversion error.
        source: JointToCountsError,
    },
}

/// Where the next sample comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Next {
    /// Sample `k` of the transition into the current scenario.
    Transition(usize),
    /// Sample `k` of the current scenario.
    Scenario(usize),
    /// The finite scenario is over.
    Done,
}

/// The simulated robot on the bus. See the module documentation.
#[derive(Debug)]
pub struct SimRobot {
    config: TwinConfig,
    tracker: IkTracker,
    nodes: VirtualNodes,
    scenario: Scenario,
    scenario_seed: u64,
    scenarios_started: u64,
    scenario_start_sample: u64,
    transition: Vec<LineSample>,
    next: Next,
    next_event: usize,
    samples_done: u64,
    t0_us: Option<u64>,
    truth: Truth,
    events: heapless::Vec<TwinEvent, MAX_EVENTS_PER_SAMPLE>,
    endoscope: Option<(EndoscopeMotion, EcmNodes)>,
    endoscope_joints: Option<[f64; ECM_JOINTS]>,
    endoscope_sent: bool,
}

/// Seconds of endoscope motion generated beyond a scenario's end (so that a caller rendering
/// a little past it still sees the schedule).
const ENDOSCOPE_MARGIN_S: f64 = 60.0;

/// Checks the scenario parameters a twin relies on (beyond [`ScenarioConfig::check`]), so
/// that generation cannot panic on user input.
fn check_scenario(s: &ScenarioConfig) -> Result<(), TwinConfigError> {
    use ScenarioConfigError::{BadInterval, OutOfRange, TrocarNotFinite};
    s.check()?;
    if (s.sample_period_s * 1e6 - SYNC_PERIOD_US as f64).abs() > 1e-6 {
        return Err(OutOfRange {
            key: "sample_period_s",
            value: s.sample_period_s,
            allowed: "0.001 s only (the twin answers one sample per 1 ms SYNC)",
        }
        .into());
    }
    for (key, r, limit) in [
        ("inside_s", s.inside_s, 3600.0),
        ("outside_s", s.outside_s, 3600.0),
        ("pivot_frequency_hz", s.pivot_frequency_hz, 50.0),
    ] {
        if !(r.iter().all(|v| v.is_finite() && *v > 0.0 && *v <= limit) && r[0] <= r[1]) {
            return Err(BadInterval { key, value: r, limit }.into());
        }
    }
    for (key, v, allowed, max) in [
        ("pivot_amplitude_deg", s.pivot_amplitude_deg, "0 ..= 60", 60.0),
        ("compliance_m", s.compliance_m, "0 ..= 0.05", 0.05),
        ("breathing_m", s.breathing_m, "0 ..= 0.05", 0.05),
        ("wrist_rotation_probability", s.wrist_rotation_probability, "0 ..= 1", 1.0),
        ("wrist_noise_m", s.wrist_noise_m, "0 ..= 0.01", 0.01),
        ("axis_noise_deg", s.axis_noise_deg, "0 ..= 10", 10.0),
    ] {
        if !(v.is_finite() && (0.0..=max).contains(&v)) {
            return Err(OutOfRange { key, value: v, allowed }.into());
        }
    }
    if s.breathing_m > 0.0 && !(s.breathing_period_s.is_finite() && s.breathing_period_s > 0.0) {
        return Err(OutOfRange { key: "breathing_period_s", value: s.breathing_period_s, allowed: "> 0" }.into());
    }
    if let Some(t) = s.trocars_base_m.iter().find(|t| t.iter().any(|v| !v.is_finite())) {
        return Err(TrocarNotFinite(*t).into());
    }
    Ok(())
}

/// Minimum-jerk blend from 0 to 1 over `u` in [0, 1].
fn min_jerk(u: f64) -> f64 {
    let u = u.clamp(0.0, 1.0);
    u * u * u * (10.0 - 15.0 * u + 6.0 * u * u)
}

/// The lines of the transition from `from` to `to` (metres, robot base frame): the first
/// one has already moved off `from`, the last one is `to`.
fn transition(from: &LineSample, to: &LineSample, sample_period_s: f64) -> Vec<LineSample> {
    let (w0, w1) = (from.wrist_base_m, to.wrist_base_m);
    let (a0, a1) = (from.axis_base.normalize(), to.axis_base.normalize());
    let rotation = UnitQuaternion::rotation_between(&a0, &a1).unwrap_or_else(|| {
        // Opposite axes: half a turn about any perpendicular.
        let helper = if a0.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
        UnitQuaternion::from_axis_angle(&Unit::new_normalize(a0.cross(&helper)), std::f64::consts::PI)
    });
    let seconds = ((w1 - w0).norm() / 0.1).max(rotation.angle() / 0.5).clamp(0.5, 5.0);
    let n = (seconds / sample_period_s).round().max(1.0) as usize;
    let identity = UnitQuaternion::identity();
    (1..=n)
        .map(|k| {
            let s = min_jerk(k as f64 / n as f64);
            LineSample::new(w0 + (w1 - w0) * s, identity.slerp(&rotation, s) * a0)
        })
        .collect()
}

impl SimRobot {
    /// Builds the twin: validates the configuration, generates the first scenario (this
    /// allocates about 150 bytes per sample), builds the true arm and the nodes.
    pub fn new(config: &TwinConfig) -> Result<Self, TwinConfigError> {
        check_scenario(&config.scenario)?;
        let m = &config.model_error;
        for (key, value, max) in
            [("link_length_m", m.link_length_m, 0.01), ("joint_offset_rad", m.joint_offset_rad, 0.1)]
        {
            if !(value.is_finite() && (0.0..=max).contains(&value)) {
                return Err(TwinConfigError::ModelError { key, value, max });
            }
        }
        if !config.roll_rad.is_finite() {
            return Err(TwinConfigError::Roll(config.roll_rad));
        }
        let arm = SimulatedArm::new(&config.kinematics, m.model_error())?;
        let options: [NodeOptions; ENCODER_NODES] = core::array::from_fn(|k| config.nodes[k].clone());
        let nodes = VirtualNodes::new(&config.encoder, options, config.nodes_seed)?;
        let scenario = generate(&config.scenario);
        let endoscope = if config.endoscope_arm.enabled {
            let e = &config.endoscope_arm;
            e.validate(&config.encoder.node_ids)?;
            let nodes = EcmNodes::new(e).ok_or(EndoscopeArmConfigError::NodeClash(e.node_ids[0], e.node_ids[1]))?;
            let mut motion = EndoscopeMotion::new(e);
            motion.extend_to(scenario.truth.len() as f64 * config.scenario.sample_period_s + ENDOSCOPE_MARGIN_S);
            Some((motion, nodes))
        } else {
            None
        };
        let truth = scenario.truth.first().copied().unwrap_or(Truth {
            t_s: 0.0,
            state: TruthState::Outside,
            fulcrum_base_m: None,
            line: LineSample::new(Vector3::zeros(), Vector3::z()),
        });
        Ok(Self {
            config: config.clone(),
            tracker: IkTracker::new(arm),
            nodes,
            scenario_seed: config.scenario.seed,
            scenario,
            scenarios_started: 1,
            scenario_start_sample: 0,
            transition: Vec::new(),
            next: Next::Scenario(0),
            next_event: 0,
            samples_done: 0,
            t0_us: None,
            truth,
            events: heapless::Vec::new(),
            endoscope,
            endoscope_joints: None,
            endoscope_sent: false,
        })
    }

    /// Answers one SYNC with `counter` (1..=240) sent at `t_us` (microseconds, any time base;
    /// the Unix epoch for `simrobot`): advances one sample, solves the joint angles of the
    /// true arm and returns the nodes' frames (the tool arm's and, when on, the endoscope
    /// arm's) stamped in the same time base, in bus order.
    /// `Ok(None)` once a finite scenario is over (nothing is sent any more). On error nothing
    /// advances. Allocation-free, except when endless mode starts the next scenario.
    pub fn on_sync(&mut self, counter: u8, t_us: u64) -> Result<Option<TwinFrames>, TwinError> {
        if self.next == Next::Done {
            return Ok(None);
        }
        if let Next::Scenario(k) = self.next
            && k >= self.scenario.truth.len()
        {
            if !self.config.endless {
                self.next = Next::Done;
                self.events.clear();
                return Ok(None);
            }
            self.start_next_scenario();
        }
        let sample = self.samples_done;
        let t_s = sample as f64 * self.config.scenario.sample_period_s;
        let (truth, line) = match self.next {
            Next::Transition(k) => {
                let line = self.transition[k];
                (Truth { t_s, state: TruthState::Outside, fulcrum_base_m: None, line }, line)
            }
            Next::Scenario(k) => {
                let truth = Truth { t_s, ..self.scenario.truth[k] };
                let line = if self.config.measurement_noise { self.scenario.measured[k] } else { truth.line };
                (truth, line)
            }
            Next::Done => return Ok(None),
        };
        let q = self.tracker.solve(&line, self.config.roll_rad).map_err(|source| TwinError::Ik { sample, source })?;
        let t0 = *self.t0_us.get_or_insert(t_us);
        let t_rel = t_us.saturating_sub(t0);
        // Checked before any node changes state: on error nothing advances.
        let ecm_q = self.endoscope.as_ref().map(|(motion, _)| motion.joints_at(t_s));
        if ecm_q.is_some_and(|q| self.config.endoscope_arm.joints_to_counts(&q).is_none()) {
            return Err(TwinError::EndoscopeCounts { sample });
        }
        let tool_frames =
            self.nodes.on_sync(counter, t_rel, &q).map_err(|source| TwinError::Counts { sample, source })?;
        let ecm_frames = match (self.endoscope.as_mut(), ecm_q) {
            (Some((_, nodes)), Some(q)) => nodes.on_sync(counter, t_rel, &q).unwrap_or_default(),
            _ => Default::default(),
        };
        let mut frames = TwinFrames::new();
        for f in tool_frames.iter().chain(ecm_frames.iter()) {
            // Capacity: MAX_TWIN_FRAMES_PER_SYNC covers both arms.
            let _ =
                frames.push(hw_io::can::TimedFrame { frame: f.frame, unix_time_us: f.unix_time_us.saturating_add(t0) });
        }
        frames.sort_unstable_by_key(|f| (f.unix_time_us, f.frame.id().raw()));
        self.endoscope_sent = self.endoscope.as_ref().is_some_and(|(_, n)| n.answers(counter));
        self.endoscope_joints = ecm_q;
        // Commit.
        self.events.clear();
        self.next = match self.next {
            Next::Transition(k) if k + 1 < self.transition.len() => Next::Transition(k + 1),
            Next::Transition(_) => Next::Scenario(0),
            Next::Scenario(k) => {
                while let Some(e) = self.scenario.events.get(self.next_event).filter(|e| e.sample == k) {
                    // At most one event per sample in practice; see MAX_EVENTS_PER_SAMPLE.
                    let _ = self.events.push(TwinEvent {
                        sample,
                        t_s,
                        unix_time_us: t_us,
                        trocar: e.trocar,
                        insertion: e.insertion,
                    });
                    self.next_event += 1;
                }
                Next::Scenario(k + 1)
            }
            Next::Done => Next::Done,
        };
        self.truth = truth;
        self.samples_done += 1;
        Ok(Some(frames))
    }

    /// Generates the next scenario (seed + 1) and the transition into it.
    fn start_next_scenario(&mut self) {
        let last = self.truth.line;
        self.scenario_seed = self.scenario_seed.wrapping_add(1);
        let cfg = ScenarioConfig { seed: self.scenario_seed, ..self.config.scenario.clone() };
        self.scenario = generate(&cfg);
        self.scenarios_started += 1;
        self.next_event = 0;
        match self.scenario.truth.first() {
            Some(first) => {
                self.transition = transition(&last, &first.line, cfg.sample_period_s);
                self.scenario_start_sample = self.samples_done + self.transition.len() as u64;
                self.next = Next::Transition(0);
            }
            None => {
                self.transition.clear();
                self.scenario_start_sample = self.samples_done;
                self.next = Next::Scenario(0);
            }
        }
        if let Some((motion, _)) = self.endoscope.as_mut() {
            let end = self.scenario_start_sample + self.scenario.truth.len() as u64;
            motion.extend_to(end as f64 * cfg.sample_period_s + ENDOSCOPE_MARGIN_S);
        }
    }

    /// Joints of the endoscope arm at the sample answered by the last [`SimRobot::on_sync`],
    /// `[yaw rad, pitch rad, insertion m, roll rad]`; `None` before the first sample or when
    /// the arm is off.
    pub fn endoscope_joints(&self) -> Option<[f64; ECM_JOINTS]> {
        self.endoscope_joints
    }

    /// `true` when the endoscope arm's nodes sent their TPDOs in answer to the last SYNC.
    pub fn endoscope_tpdos_sent(&self) -> bool {
        self.endoscope_sent
    }

    /// The endoscope arm's motion (a pure function of the twin's time), `None` when the arm
    /// is off.
    pub fn endoscope_motion(&self) -> Option<&EndoscopeMotion> {
        self.endoscope.as_ref().map(|(m, _)| m)
    }

    /// The endoscope arm's nodes (their TPDO counter), `None` when the arm is off.
    pub fn endoscope_nodes(&self) -> Option<&EcmNodes> {
        self.endoscope.as_ref().map(|(_, n)| n)
    }

    /// Ground truth of the sample answered by the last successful [`SimRobot::on_sync`]
    /// (before the first one: sample 0 of the scenario). `t_s` is seconds since sample 0 of
    /// the run; positions in metres, robot base frame.
    pub fn truth(&self) -> &Truth {
        &self.truth
    }

    /// The true events crossed at the sample answered by the last [`SimRobot::on_sync`]
    /// (usually empty).
    pub fn events(&self) -> &[TwinEvent] {
        &self.events
    }

    /// Number of SYNCs answered so far, which is also the index of the next sample.
    pub fn samples_done(&self) -> u64 {
        self.samples_done
    }

    /// Index of the sample answered by the last [`SimRobot::on_sync`], `None` before the
    /// first.
    pub fn sample(&self) -> Option<u64> {
        self.samples_done.checked_sub(1)
    }

    /// `true` once a finite scenario is over (`on_sync` returned `None`).
    pub fn is_done(&self) -> bool {
        self.next == Next::Done
    }

    /// The current scenario (the only one unless endless), for scoring: its sample `k` is
    /// run sample [`SimRobot::scenario_start_sample`]` + k`.
    pub fn scenario(&self) -> &Scenario {
        &self.scenario
    }

    /// Run sample index of sample 0 of the current scenario.
    pub fn scenario_start_sample(&self) -> u64 {
        self.scenario_start_sample
    }

    /// Seed of the current scenario.
    pub fn scenario_seed(&self) -> u64 {
        self.scenario_seed
    }

    /// Scenarios started so far (1, plus one per endless restart).
    pub fn scenarios_started(&self) -> u64 {
        self.scenarios_started
    }

    /// `true` when the sample answered by the last [`SimRobot::on_sync`] belongs to the
    /// transition into the current scenario (endless mode).
    pub fn in_transition(&self) -> bool {
        self.sample().is_some_and(|s| s < self.scenario_start_sample)
    }

    /// Measured joint angles of the last sample (radians, joints 1..6), `None` before the
    /// first.
    pub fn joints_rad(&self) -> Option<&[f64; JOINTS]> {
        self.tracker.last()
    }

    /// The simulated arm (nominal and true parameters).
    pub fn arm(&self) -> &SimulatedArm {
        self.tracker.arm()
    }

    /// The virtual encoder nodes (counters of sent and dropped TPDOs).
    pub fn nodes(&self) -> &VirtualNodes {
        &self.nodes
    }

    /// The configuration the twin was built from.
    pub fn config(&self) -> &TwinConfig {
        &self.config
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn transition_is_smooth_and_ends_on_target() {
        let from = LineSample::new(Vector3::new(0.4, 0.1, 0.2), Vector3::new(0.3, 0.0, -1.0).normalize());
        let to = LineSample::new(Vector3::new(0.4, 0.0, 0.35), Vector3::new(0.0, 0.0, -1.0));
        let lines = transition(&from, &to, 0.001);
        assert!(lines.len() >= 500 && lines.len() <= 5000, "{} samples", lines.len());
        let last = lines.last().unwrap();
        assert!((last.wrist_base_m - to.wrist_base_m).norm() < 1e-12);
        assert!((last.axis_base - to.axis_base).norm() < 1e-12);
        let mut prev = from;
        for l in &lines {
            assert!((l.wrist_base_m - prev.wrist_base_m).norm() < 0.0002, "wrist step over 0.2 mm");
            assert!((l.axis_base - prev.axis_base).norm() < 0.001, "axis step over 1 mrad");
            prev = *l;
        }
    }

    #[test]
    fn bad_configs_are_refused_with_the_key() {
        let mut c = TwinConfig::default();
        c.scenario.sample_period_s = 0.002;
        assert!(SimRobot::new(&c).unwrap_err().to_string().contains("sample_period_s"));
        let mut c = TwinConfig::default();
        c.scenario.inside_s = [3.0, f64::NAN];
        assert!(SimRobot::new(&c).unwrap_err().to_string().contains("inside_s"));
        let mut c = TwinConfig::default();
        c.scenario.wrist_noise_m = -1.0;
        assert!(SimRobot::new(&c).unwrap_err().to_string().contains("wrist_noise_m"));
        let mut c = TwinConfig::default();
        c.model_error.link_length_m = 0.5;
        assert!(matches!(SimRobot::new(&c), Err(TwinConfigError::ModelError { key: "link_length_m", .. })));
        let mut c = TwinConfig::default();
        c.nodes[1].dropout_probability = 2.0;
        assert!(matches!(SimRobot::new(&c), Err(TwinConfigError::Nodes(_))));
        let mut c = TwinConfig::default();
        c.encoder.node_ids = [1, 1, 2];
        assert!(matches!(SimRobot::new(&c), Err(TwinConfigError::Nodes(_))));
    }
}
