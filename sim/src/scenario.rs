//! Surgeon-motion scenarios: cycles of insertion, manipulation, extraction and free motion
//! to the next trocar, with ground truth.
//!
//! Geometry (metres, robot base frame): the instrument is a straight shaft of length
//! `instrument_length_m` from the wrist centre P to the tip; the tip is at `P + L·z`.
//! A trocar is a point T on the patient's skin. The instrument is **inside** trocar i from
//! the instant its tip crosses T going in (true insertion instant) to the instant the tip
//! crosses T coming out (true extraction instant). While inside, the axis passes through
//! the trocar's current pivot `T + w(t)`, where `w` is a slow wander of about
//! `compliance_m` (trocar compliance and backlash) plus optional breathing motion.

use nalgebra::{Rotation3, Unit, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use estimator::trocar::LineSample;

/// Parameters of a scenario. Durations in seconds, lengths in metres, angles in degrees.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ScenarioConfig {
    /// Seed of every random choice.
    pub seed: u64,
    /// Trocar positions, metres, robot base frame.
    pub trocars_base_m: Vec<[f64; 3]>,
    /// Insert/extract cycles.
    pub cycles: usize,
    /// Sample period, seconds.
    pub sample_period_s: f64,
    /// Instrument length from the wrist centre to the tip, metres.
    pub instrument_length_m: f64,
    /// Time inside a trocar per cycle, seconds (uniform in the range).
    pub inside_s: [f64; 2],
    /// Time outside between two trocars, seconds (uniform in the range).
    pub outside_s: [f64; 2],
    /// Peak pivot amplitude about the entry direction, degrees.
    pub pivot_amplitude_deg: f64,
    /// Pivot motion frequencies, hertz (uniform in the range).
    pub pivot_frequency_hz: [f64; 2],
    /// Trocar compliance and backlash: amplitude of the pivot's wander, metres.
    pub compliance_m: f64,
    /// Breathing: vertical amplitude of the trocars' motion, metres (0 disables).
    pub breathing_m: f64,
    /// Breathing period, seconds.
    pub breathing_period_s: f64,
    /// Probability that a free motion contains a pure rotation about the wrist (the paper's
    /// false-positive trap).
    pub wrist_rotation_probability: f64,
    /// Measurement noise on the wrist position, metres (one sigma, per axis).
    pub wrist_noise_m: f64,
    /// Measurement noise on the axis direction, degrees (one sigma, per axis).
    pub axis_noise_deg: f64,
    /// How the surgeon moves between trocars and approaches them (the motion-style family;
    /// the default is the original surgeon, every new behaviour off).
    pub style: StyleConfig,
}

/// Timing of position and axis within a free transfer between two poses.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TransferTiming {
    /// Position and axis move together (one minimum-jerk profile): the original surgeon.
    #[default]
    Together,
    /// The position moves over the whole transfer, the axis turns within a random
    /// sub-interval of it (starting at 20-40 % of the transfer and lasting 20-40 % of it):
    /// position and orientation move out of step, so for a moment the hand pivots about a
    /// point on the shaft.
    AxisWithin,
    /// The axis turns first (about the wrist), then the wrist translates.
    RotateThenTranslate,
    /// The wrist translates first, then the axis turns (about the wrist).
    TranslateThenRotate,
    /// Each free motion draws one of the four timings above at random.
    Mixed,
}

/// The motion-style family of the simulated surgeon (`docs/simulator.md`). Probabilities are
/// per transfer or per approach, in [0, 1].
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StyleConfig {
    /// Timing of position and axis in every free motion.
    pub transfer: TransferTiming,
    /// Probability that a transfer contains a hand pivot: the instrument pivots in two
    /// directions (a cone, 4-12° at 0.4-1.2 Hz) about a point of the shaft 5 cm from the
    /// wrist to 3 cm from the tip, for 0.4-1.5 s, without sliding through it.
    pub shaft_pivot_probability: f64,
    /// Probability that an approach hovers: the tip descends slowly to 1-4 cm above the port
    /// and the hand aligns the instrument by pivoting about the tip (2-6°, 0.6-2 s) before
    /// entering.
    pub hover_probability: f64,
    /// Probability that an approach aims: the tip advances from 4-8 cm above the port to
    /// 5 mm above it while the axis pivots about the port itself (lines through the port,
    /// beyond the tip), then enters. Without the instrument length this is geometrically an
    /// insertion.
    pub aim_probability: f64,
    /// Probability that after an extraction the surgeon re-enters the same trocar (after a
    /// short lift) instead of moving to another.
    pub reinsert_probability: f64,
}

impl Default for ScenarioConfig {
    fn default() -> Self {
        Self {
            seed: 1,
            trocars_base_m: vec![[0.42, -0.09, 0.02], [0.50, -0.02, 0.04], [0.44, 0.07, 0.03], [0.36, 0.01, 0.01]],
            cycles: 8,
            sample_period_s: 0.001,
            instrument_length_m: 0.30,
            inside_s: [8.0, 12.0],
            outside_s: [1.6, 2.6],
            pivot_amplitude_deg: 14.0,
            pivot_frequency_hz: [0.15, 0.45],
            compliance_m: 0.001,
            breathing_m: 0.0,
            breathing_period_s: 4.0,
            wrist_rotation_probability: 0.3,
            wrist_noise_m: 0.0001,
            axis_noise_deg: 0.03,
            style: StyleConfig::default(),
        }
    }
}

/// True state of the instrument at one sample.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum TruthState {
    /// Not in any trocar.
    Outside,
    /// Inside trocar `index` (index into `trocars_base_m`).
    Inside {
        /// Trocar index.
        index: usize,
    },
}

/// Ground truth of one sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Truth {
    /// Time since the start, seconds.
    pub t_s: f64,
    /// True state.
    pub state: TruthState,
    /// True pivot point while inside (trocar point plus wander), metres, robot base frame.
    pub fulcrum_base_m: Option<Vector3<f64>>,
    /// Noise-free instrument line.
    pub line: LineSample,
}

/// A true insertion or extraction.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrueEvent {
    /// Instant the tip crosses the trocar point, seconds.
    pub t_s: f64,
    /// Sample index of that instant (first sample of the new state).
    pub sample: usize,
    /// Trocar index.
    pub trocar: usize,
    /// True for an insertion, false for an extraction.
    pub insertion: bool,
}

/// A generated scenario: measured lines and ground truth, sample by sample.
#[derive(Clone, Debug)]
pub struct Scenario {
    /// Parameters it was generated from.
    pub config: ScenarioConfig,
    /// Measured lines (with measurement noise), one per sample.
    pub measured: Vec<LineSample>,
    /// Ground truth, one per sample.
    pub truth: Vec<Truth>,
    /// True insertions and extractions, in time order.
    pub events: Vec<TrueEvent>,
}

/// A smooth random scalar signal: a sum of three sinusoids, zero at t = 0.
#[derive(Clone, Copy, Debug)]
struct Wave {
    amp: [f64; 3],
    omega: [f64; 3],
    phase: [f64; 3],
}

impl Wave {
    fn new(rng: &mut ChaCha8Rng, amplitude: f64, f_hz: [f64; 2]) -> Self {
        let mut w = Wave { amp: [0.0; 3], omega: [0.0; 3], phase: [0.0; 3] };
        for k in 0..3 {
            w.amp[k] = amplitude * rng.random_range(0.3..1.0) / 1.8;
            w.omega[k] = 2.0 * std::f64::consts::PI * rng.random_range(f_hz[0]..f_hz[1].max(f_hz[0] + 1e-9));
            w.phase[k] = rng.random_range(0.0..2.0 * std::f64::consts::PI);
        }
        w
    }
    fn at(&self, t: f64) -> f64 {
        (0..3).map(|k| self.amp[k] * ((self.omega[k] * t + self.phase[k]).sin() - self.phase[k].sin())).sum()
    }
}

/// A hand's two-direction swing of the instrument axis about `axis0`: pitch and yaw waves
/// about two directions perpendicular to it.
#[derive(Clone, Copy, Debug)]
struct ConeSwing {
    pitch: Wave,
    yaw: Wave,
    e1: Vector3<f64>,
    e2: Vector3<f64>,
    axis0: Vector3<f64>,
}

impl ConeSwing {
    /// Peak amplitude `amplitude_rad`, frequencies in `f_hz`.
    fn new(rng: &mut ChaCha8Rng, axis0: Vector3<f64>, amplitude_rad: f64, f_hz: [f64; 2]) -> Self {
        let pitch = Wave::new(rng, amplitude_rad, f_hz);
        let yaw = Wave::new(rng, amplitude_rad, f_hz);
        let e1 = perpendicular(&axis0);
        Self { pitch, yaw, e1, e2: axis0.cross(&e1), axis0 }
    }

    /// The axis at `t` seconds, the swing scaled by `envelope` (0: `axis0`).
    fn axis(&self, t: f64, envelope: f64) -> Vector3<f64> {
        UnitQuaternion::from_scaled_axis((self.e1 * self.pitch.at(t) + self.e2 * self.yaw.at(t)) * envelope)
            * self.axis0
    }
}

/// Minimum-jerk blend from 0 to 1 over `u` in [0, 1].
fn min_jerk(u: f64) -> f64 {
    let u = u.clamp(0.0, 1.0);
    u * u * u * (10.0 - 15.0 * u + 6.0 * u * u)
}

/// Where position and axis move within a free motion: each runs its minimum-jerk profile
/// over its own sub-interval `(start, end)` of the motion's fraction `u`.
#[derive(Clone, Copy, Debug)]
struct Profile {
    pos: (f64, f64),
    axis: (f64, f64),
}

impl Profile {
    fn blend(range: (f64, f64), u: f64) -> f64 {
        if range == (0.0, 1.0) {
            // Exactly the original surgeon's profile.
            return min_jerk(u);
        }
        min_jerk((u - range.0) / (range.1 - range.0).max(1e-9))
    }
    fn position(&self, u: f64) -> f64 {
        Self::blend(self.pos, u)
    }
    fn axis(&self, u: f64) -> f64 {
        Self::blend(self.axis, u)
    }
}

/// A unit vector perpendicular to `z`.
fn perpendicular(z: &Vector3<f64>) -> Vector3<f64> {
    let a = if z.x.abs() < 0.9 { Vector3::x() } else { Vector3::y() };
    z.cross(&a).normalize()
}

struct Builder<'a> {
    cfg: &'a ScenarioConfig,
    rng: ChaCha8Rng,
    t: f64,
    out: Scenario,
    /// Current pose (noise-free): wrist and axis.
    wrist: Vector3<f64>,
    axis: Vector3<f64>,
    wrist_noise: Normal<f64>,
    axis_noise: Normal<f64>,
}

impl Builder<'_> {
    fn trocar_at(&self, index: usize, t: f64) -> Vector3<f64> {
        let c = self.cfg.trocars_base_m[index];
        let breath = if self.cfg.breathing_m > 0.0 {
            self.cfg.breathing_m * 0.5 * (1.0 - (2.0 * std::f64::consts::PI * t / self.cfg.breathing_period_s).cos())
        } else {
            0.0
        };
        Vector3::new(c[0], c[1], c[2] + breath)
    }

    fn push(&mut self, wrist: Vector3<f64>, axis: Vector3<f64>, state: TruthState, fulcrum: Option<Vector3<f64>>) {
        let axis = axis.normalize();
        self.wrist = wrist;
        self.axis = axis;
        let line = LineSample::new(wrist, axis);
        let noisy_wrist = wrist
            + Vector3::new(
                self.wrist_noise.sample(&mut self.rng),
                self.wrist_noise.sample(&mut self.rng),
                self.wrist_noise.sample(&mut self.rng),
            );
        let tilt = Vector3::new(
            self.axis_noise.sample(&mut self.rng),
            self.axis_noise.sample(&mut self.rng),
            self.axis_noise.sample(&mut self.rng),
        );
        let noisy_axis = (Rotation3::new(tilt) * axis).normalize();
        self.out.measured.push(LineSample::new(noisy_wrist, noisy_axis));
        self.out.truth.push(Truth { t_s: self.t, state, fulcrum_base_m: fulcrum, line });
        self.t += self.cfg.sample_period_s;
    }

    fn samples(&self, seconds: f64) -> usize {
        (seconds / self.cfg.sample_period_s).round().max(1.0) as usize
    }

    fn event(&mut self, trocar: usize, insertion: bool) {
        let sample = self.out.truth.len();
        self.out.events.push(TrueEvent { t_s: self.t, sample, trocar, insertion });
    }

    /// The position and axis profiles of one free motion, `(position(u), axis(u))` with `u`
    /// the fraction of the motion, each going from 0 to 1 (minimum jerk). Draws from the
    /// random stream only when the style is not [`TransferTiming::Together`], so the original
    /// surgeon's motion is unchanged.
    fn transfer_profile(&mut self) -> Profile {
        let timing = match self.cfg.style.transfer {
            TransferTiming::Mixed => match self.rng.random_range(0..4) {
                0 => TransferTiming::Together,
                1 => TransferTiming::AxisWithin,
                2 => TransferTiming::RotateThenTranslate,
                _ => TransferTiming::TranslateThenRotate,
            },
            t => t,
        };
        match timing {
            TransferTiming::Together | TransferTiming::Mixed => Profile { pos: (0.0, 1.0), axis: (0.0, 1.0) },
            TransferTiming::AxisWithin => {
                let a = self.rng.random_range(0.2..0.4);
                let len = self.rng.random_range(0.2..0.4);
                Profile { pos: (0.0, 1.0), axis: (a, a + len) }
            }
            TransferTiming::RotateThenTranslate => {
                let k = self.rng.random_range(0.35..0.55);
                Profile { pos: (k, 1.0), axis: (0.0, k) }
            }
            TransferTiming::TranslateThenRotate => {
                let k = self.rng.random_range(0.45..0.65);
                Profile { pos: (0.0, k), axis: (k, 1.0) }
            }
        }
    }

    /// Free motion from the current pose to (wrist, axis), with wobble and, sometimes, the
    /// wrist-rotation trap in the middle. Position and axis follow the style's transfer
    /// timing ([`TransferTiming`]).
    fn free_motion(&mut self, seconds: f64, target_wrist: Vector3<f64>, target_axis: Vector3<f64>) {
        let n = self.samples(seconds);
        let (w0, a0) = (self.wrist, self.axis);
        let q0 = UnitQuaternion::identity();
        let q1 = UnitQuaternion::rotation_between(&a0, &target_axis).unwrap_or(q0);
        let wob: [Wave; 3] = core::array::from_fn(|_| Wave::new(&mut self.rng, 0.02, [0.3, 0.8]));
        let trap = self.rng.random_bool(self.cfg.wrist_rotation_probability.clamp(0.0, 1.0));
        let trap_axis = perpendicular(&a0);
        let trap_amp = self.rng.random_range(0.2..0.4);
        let profile = self.transfer_profile();
        let (ps, axs) = (|u: f64| profile.position(u), |u: f64| profile.axis(u));
        for i in 0..n {
            let u = (i + 1) as f64 / n as f64;
            let env = (std::f64::consts::PI * u).sin();
            let t = i as f64 * self.cfg.sample_period_s;
            // With the trap, the wobble fades out before the wrist holds still and back in
            // after, so the motion stays continuous.
            let fade = if !trap {
                1.0
            } else if u < 0.2 {
                min_jerk((0.2 - u) / 0.2)
            } else if u < 0.6 {
                0.0
            } else {
                min_jerk((u - 0.6) / 0.4)
            };
            let wobble = Vector3::new(wob[0].at(t), wob[1].at(t), wob[2].at(t)) * env * fade;
            let mut wrist = w0 + (target_wrist - w0) * ps(u) + wobble;
            let mut axis = q0.slerp(&q1, axs(u)) * a0;
            if trap && (0.2..0.6).contains(&u) {
                // Hold the wrist still and rotate the instrument about it.
                let v = (u - 0.2) / 0.4;
                let hold = w0 + (target_wrist - w0) * ps(0.2);
                wrist = hold;
                axis = UnitQuaternion::from_axis_angle(
                    &Unit::new_normalize(trap_axis),
                    trap_amp * (2.0 * std::f64::consts::PI * v).sin(),
                ) * (q0.slerp(&q1, axs(0.2)) * a0);
            } else if trap && u >= 0.6 {
                let v = (u - 0.6) / 0.4;
                let hold = w0 + (target_wrist - w0) * ps(0.2);
                wrist = hold + (target_wrist - hold) * min_jerk(v) + wobble;
                axis = q0.slerp(&q1, axs(0.2) + (1.0 - axs(0.2)) * min_jerk(v)) * a0;
            }
            self.push(wrist, axis, TruthState::Outside, None);
        }
    }

    /// A hand pivot about a point of the shaft (style `shaft_pivot_probability`): the axis
    /// swings in two directions about the point `P + d·z` of the current line, which stays
    /// fixed in space and on the shaft (no slide through it). Starts and ends continuous.
    fn shaft_pivot(&mut self) {
        let l = self.cfg.instrument_length_m;
        let d = self.rng.random_range(0.05..(l - 0.03).max(0.06));
        let seconds = self.rng.random_range(0.4..1.5);
        let amp = self.rng.random_range(4.0_f64..12.0).to_radians();
        let swing = ConeSwing::new(&mut self.rng, self.axis, amp, [0.4, 1.2]);
        let centre = self.wrist + self.axis * d;
        for i in 0..self.samples(seconds) {
            let t = (i + 1) as f64 * self.cfg.sample_period_s;
            let axis = swing.axis(t, 1.0);
            self.push(centre - axis * d, axis, TruthState::Outside, None);
        }
    }

    /// A hovering approach (style `hover_probability`), from the approach pose (tip
    /// `approach_m` above `port` along `entry`): the tip descends slowly to `h` above the
    /// port, the hand aligns the instrument by pivoting about the tip, and the axis comes
    /// back to `entry`. Returns the tip's final height above the port, metres.
    fn hover(&mut self, port: Vector3<f64>, entry: Vector3<f64>, approach_m: f64) -> f64 {
        let l = self.cfg.instrument_length_m;
        let h = self.rng.random_range(0.01..0.04_f64).min(approach_m);
        let descend_s = self.rng.random_range(0.3..1.0);
        self.slide_above(port, entry, approach_m, h, descend_s);
        let seconds = self.rng.random_range(0.6..2.0);
        let amp = self.rng.random_range(2.0_f64..6.0).to_radians();
        let swing = ConeSwing::new(&mut self.rng, entry, amp, [0.3, 0.8]);
        let tip = port - entry * h;
        let n = self.samples(seconds);
        for i in 0..n {
            let u = (i + 1) as f64 / n as f64;
            let t = (i + 1) as f64 * self.cfg.sample_period_s;
            // The envelope brings the axis back to `entry` at the end.
            let axis = swing.axis(t, (std::f64::consts::PI * u).sin());
            self.push(tip - axis * l, axis, TruthState::Outside, None);
        }
        h
    }

    /// A pure slide along `entry` with the tip going from `from_above` to `to_above` metres
    /// above `port` in `seconds` (minimum jerk): no line carries information.
    fn slide_above(&mut self, port: Vector3<f64>, entry: Vector3<f64>, from_above: f64, to_above: f64, seconds: f64) {
        let l = self.cfg.instrument_length_m;
        let n = self.samples(seconds);
        for i in 0..n {
            let u = min_jerk((i + 1) as f64 / n as f64);
            let above = from_above + (to_above - from_above) * u;
            self.push(port - entry * (l + above), entry, TruthState::Outside, None);
        }
    }

    /// An aiming approach (style `aim_probability`), from the approach pose: the tip
    /// advances from `approach_m` to 5 mm above the port while the axis pivots about the port
    /// itself (every line passes through it, beyond the tip). Returns the tip's final height
    /// above the port, metres.
    fn aim(&mut self, port: Vector3<f64>, entry: Vector3<f64>, approach_m: f64) -> f64 {
        let l = self.cfg.instrument_length_m;
        let start = self.rng.random_range(0.04..0.08_f64);
        let end = 0.005;
        // Rise from the approach height to the aiming start along the axis first.
        self.slide_above(port, entry, approach_m, start, 0.3);
        let seconds = self.rng.random_range(0.8..1.6);
        let amp = self.rng.random_range(3.0_f64..8.0).to_radians();
        let swing = ConeSwing::new(&mut self.rng, entry, amp, [0.4, 1.0]);
        let n = self.samples(seconds);
        for i in 0..n {
            let u = (i + 1) as f64 / n as f64;
            let t = (i + 1) as f64 * self.cfg.sample_period_s;
            let axis = swing.axis(t, (std::f64::consts::PI * u).sin());
            let above = start + (end - start) * min_jerk(u);
            self.push(port - axis * (l + above), axis, TruthState::Outside, None);
        }
        end
    }

    /// One insertion, manipulation and extraction at trocar `index`, starting from the
    /// approach pose (tip `approach_m` above the trocar along `entry`).
    fn visit(&mut self, index: usize, entry: Vector3<f64>, inside_s: f64, approach_m: f64) {
        let l = self.cfg.instrument_length_m;
        let speed = self.rng.random_range(0.08..0.16); // m/s along the axis
        let depth0 = self.rng.random_range(0.05..0.09);
        // Insertion: the tip goes from -approach to depth0 below the trocar along `entry`.
        let n_in = self.samples((depth0 + approach_m) / speed);
        let mut inside = false;
        for i in 0..n_in {
            let u = (i + 1) as f64 / n_in as f64;
            let depth = -approach_m + (depth0 + approach_m) * u; // tip depth past the trocar
            let trocar = self.trocar_at(index, self.t);
            if !inside && depth >= 0.0 {
                inside = true;
                self.event(index, true);
            }
            let wrist = trocar - entry * (l - depth);
            let state = if inside { TruthState::Inside { index } } else { TruthState::Outside };
            self.push(wrist, entry, state, inside.then_some(trocar));
        }
        // Manipulation: pivot about the (wandering) trocar, vary the depth.
        let amp = self.cfg.pivot_amplitude_deg.to_radians();
        let f = self.cfg.pivot_frequency_hz;
        let pitch = Wave::new(&mut self.rng, amp, f);
        let yaw = Wave::new(&mut self.rng, amp, f);
        let dep = Wave::new(&mut self.rng, 0.03, [0.1, 0.3]);
        let wander: [Wave; 3] = core::array::from_fn(|_| Wave::new(&mut self.rng, self.cfg.compliance_m, [0.2, 1.0]));
        let e1 = perpendicular(&entry);
        let e2 = entry.cross(&e1);
        let n_man = self.samples(inside_s - (depth0 + approach_m) / speed);
        for i in 0..n_man {
            let t = i as f64 * self.cfg.sample_period_s;
            let rot = UnitQuaternion::from_scaled_axis(e1 * pitch.at(t) + e2 * yaw.at(t));
            let axis = rot * entry;
            let depth = (depth0 + dep.at(t)).max(0.02);
            let pivot = self.trocar_at(index, self.t) + Vector3::new(wander[0].at(t), wander[1].at(t), wander[2].at(t));
            self.push(pivot - axis * (l - depth), axis, TruthState::Inside { index }, Some(pivot));
        }
        // Extraction: pull out along the current axis until the tip is `approach_m` out.
        let axis = self.axis;
        let pivot = self.out.truth.last().and_then(|t| t.fulcrum_base_m).unwrap_or(self.wrist + axis * (l - depth0));
        let depth_start = tip_depth(&self.wrist, &axis, &pivot, l);
        let n_out = self.samples((depth_start + approach_m) / speed);
        let mut out = false;
        for i in 0..n_out {
            let u = (i + 1) as f64 / n_out as f64;
            let depth = depth_start - (depth_start + approach_m) * u;
            if !out && depth < 0.0 {
                out = true;
                self.event(index, false);
            }
            let state = if out { TruthState::Outside } else { TruthState::Inside { index } };
            self.push(pivot - axis * (l - depth), axis, state, (!out).then_some(pivot));
        }
    }
}

/// Tip depth past `pivot` along `axis` (metres) for a wrist at `wrist`.
fn tip_depth(wrist: &Vector3<f64>, axis: &Vector3<f64>, pivot: &Vector3<f64>, l: f64) -> f64 {
    l - axis.dot(&(pivot - wrist))
}

/// A random entry direction for a trocar: pointing down into the patient, tilted up to 25°.
fn entry_direction(rng: &mut ChaCha8Rng) -> Vector3<f64> {
    let tilt = rng.random_range(0.0_f64..25.0).to_radians();
    let az = rng.random_range(0.0..2.0 * std::f64::consts::PI);
    Vector3::new(tilt.sin() * az.cos(), tilt.sin() * az.sin(), -tilt.cos())
}

/// Generates a scenario. Deterministic: the same config gives the same samples.
///
/// Panics only on an empty trocar list, a non-positive sample period or a non-finite noise
/// (programming errors of the caller; use [`ScenarioConfig::check`] on user input first).
#[allow(clippy::expect_used, reason = "documented panic on a caller error that ScenarioConfig::check refuses")]
pub fn generate(cfg: &ScenarioConfig) -> Scenario {
    let mut rng = ChaCha8Rng::seed_from_u64(cfg.seed);
    let approach_m = 0.03;
    let l = cfg.instrument_length_m;
    let start_axis = Vector3::new(0.0, 0.0, -1.0);
    let start_wrist = Vector3::new(0.40, 0.0, 0.35);
    let mut b = Builder {
        cfg,
        rng: ChaCha8Rng::seed_from_u64(rng.random()),
        t: 0.0,
        out: Scenario { config: cfg.clone(), measured: Vec::new(), truth: Vec::new(), events: Vec::new() },
        wrist: start_wrist,
        axis: start_axis,
        wrist_noise: Normal::new(0.0, cfg.wrist_noise_m).expect("finite sigma"),
        axis_noise: Normal::new(0.0, cfg.axis_noise_deg.to_radians()).expect("finite sigma"),
    };
    // Start: hold still for a moment.
    for _ in 0..b.samples(0.2) {
        b.push(start_wrist, start_axis, TruthState::Outside, None);
    }
    let mut last = usize::MAX;
    for _ in 0..cfg.cycles {
        let mut index = rng.random_range(0..cfg.trocars_base_m.len());
        if cfg.trocars_base_m.len() > 1 {
            while index == last {
                index = rng.random_range(0..cfg.trocars_base_m.len());
            }
        }
        // Re-insertion into the same trocar (style): decided on the builder's stream, so the
        // original surgeon's draws are unchanged.
        let p = cfg.style.reinsert_probability.clamp(0.0, 1.0);
        if last != usize::MAX && p > 0.0 && b.rng.random_bool(p) {
            index = last;
        }
        last = index;
        let entry = entry_direction(&mut rng);
        let outside_s = rng.random_range(cfg.outside_s[0]..cfg.outside_s[1].max(cfg.outside_s[0] + 1e-9));
        let inside_s = rng.random_range(cfg.inside_s[0]..cfg.inside_s[1].max(cfg.inside_s[0] + 1e-9));
        // Free motion: retreat away from the patient (lift and tilt), then travel to the
        // approach pose of the next trocar; the end of the approach is the insertion itself.
        let trocar = b.trocar_at(index, b.t + outside_s);
        let approach_wrist = trocar - entry * (l + approach_m);
        let lift =
            Vector3::new(rng.random_range(-0.05..0.05), rng.random_range(-0.05..0.05), rng.random_range(0.05..0.10));
        let retreat_wrist = b.wrist + lift;
        let tilt = UnitQuaternion::from_scaled_axis(perpendicular(&b.axis) * rng.random_range(0.15..0.5));
        let retreat_axis = tilt * b.axis;
        let split = rng.random_range(0.35..0.55);
        b.free_motion(outside_s * split, retreat_wrist, retreat_axis);
        let p = cfg.style.shaft_pivot_probability.clamp(0.0, 1.0);
        if p > 0.0 && b.rng.random_bool(p) {
            b.shaft_pivot();
        }
        b.free_motion(outside_s * (1.0 - split), approach_wrist, entry);
        let port = b.trocar_at(index, b.t);
        let (hover, aim) = (cfg.style.hover_probability.clamp(0.0, 1.0), cfg.style.aim_probability.clamp(0.0, 1.0));
        let approach = if hover > 0.0 && b.rng.random_bool(hover) {
            b.hover(port, entry, approach_m)
        } else if aim > 0.0 && b.rng.random_bool(aim) {
            b.aim(port, entry, approach_m)
        } else {
            approach_m
        };
        b.visit(index, entry, inside_s, approach);
    }
    // Leave: a last stretch of free motion away from the patient.
    let away = b.wrist + Vector3::new(0.0, 0.0, 0.1);
    let axis = b.axis;
    b.free_motion(1.5, away, axis);
    b.out
}

/// Why a scenario configuration was refused; each variant names the key.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ScenarioConfigError {
    /// `trocars_base_m` is empty.
    #[error("scenario.trocars_base_m: at least one trocar is needed")]
    NoTrocar,
    /// A trocar position (metres, robot base frame) has a NaN or infinite coordinate.
    #[error("scenario.trocars_base_m: {0:?} is not finite")]
    TrocarNotFinite([f64; 3]),
    /// A number outside its allowed range (the unit is the key's: `_s` seconds, `_m` metres,
    /// `_deg` degrees, `_hz` hertz, probabilities dimensionless).
    #[error("scenario.{key} = {value}: allowed {allowed}")]
    OutOfRange {
        /// The key below `scenario.`.
        key: &'static str,
        /// The value given.
        value: f64,
        /// The allowed range, for people.
        allowed: &'static str,
    },
    /// A `[min, max]` pair that is not `0 < min <= max <= limit`.
    #[error("scenario.{key} = {value:?}: must be [min, max] with 0 < min <= max <= {limit}")]
    BadInterval {
        /// The key below `scenario.`.
        key: &'static str,
        /// The pair given.
        value: [f64; 2],
        /// The largest allowed value (the key's unit).
        limit: f64,
    },
}

impl ScenarioConfig {
    /// Checks user-supplied parameters.
    pub fn check(&self) -> Result<(), ScenarioConfigError> {
        use ScenarioConfigError::OutOfRange;
        if self.trocars_base_m.is_empty() {
            return Err(ScenarioConfigError::NoTrocar);
        }
        if !(self.sample_period_s > 0.0 && self.sample_period_s <= 0.1) {
            return Err(OutOfRange { key: "sample_period_s", value: self.sample_period_s, allowed: "(0, 0.1] s" });
        }
        if !(self.instrument_length_m > 0.1 && self.instrument_length_m < 1.0) {
            return Err(OutOfRange {
                key: "instrument_length_m",
                value: self.instrument_length_m,
                allowed: "(0.1, 1) m",
            });
        }
        for (key, sigma) in [("wrist_noise_m", self.wrist_noise_m), ("axis_noise_deg", self.axis_noise_deg)] {
            if !(sigma.is_finite() && sigma >= 0.0) {
                return Err(OutOfRange { key, value: sigma, allowed: "finite and >= 0" });
            }
        }
        let st = &self.style;
        for (key, p) in [
            ("style.shaft_pivot_probability", st.shaft_pivot_probability),
            ("style.hover_probability", st.hover_probability),
            ("style.aim_probability", st.aim_probability),
            ("style.reinsert_probability", st.reinsert_probability),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return Err(OutOfRange { key, value: p, allowed: "[0, 1]" });
            }
        }
        Ok(())
    }
}

/// A trocar layout on a simulated abdomen: `count` ports on a spherical dome of radius
/// `dome_radius_m` whose top is at `top_base_m` (metres, robot base frame), spread within
/// `spread_m` of the top (horizontal distance) and at least `min_separation_m` apart.
/// Deterministic by `seed`. Returns `None` when 10 000 draws (100 fresh starts) could not
/// place them.
pub fn dome_layout(
    seed: u64,
    count: usize,
    top_base_m: [f64; 3],
    spread_m: f64,
    min_separation_m: f64,
    dome_radius_m: f64,
) -> Option<Vec<[f64; 3]>> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let mut out: Vec<Vector3<f64>> = Vec::with_capacity(count);
    let top = Vector3::from(top_base_m);
    for draw in 0..10_000 {
        if out.len() == count {
            break;
        }
        if draw % 100 == 99 {
            // A greedy placement that got stuck: start again.
            out.clear();
        }
        let r = spread_m * rng.random_range(0.0..1.0_f64).sqrt();
        let az = rng.random_range(0.0..2.0 * std::f64::consts::PI);
        let drop = dome_radius_m - (dome_radius_m * dome_radius_m - r * r).max(0.0).sqrt();
        let p = top + Vector3::new(r * az.cos(), r * az.sin(), -drop);
        if out.iter().all(|q| (q - p).norm() >= min_separation_m) {
            out.push(p);
        }
    }
    (out.len() == count).then(|| out.iter().map(|p| [p.x, p.y, p.z]).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deterministic_and_consistent() {
        let cfg = ScenarioConfig { cycles: 3, wrist_rotation_probability: 1.0, ..Default::default() };
        let a = generate(&cfg);
        let b = generate(&cfg);
        assert_eq!(a.measured, b.measured);
        assert_eq!(a.events.len(), 6);
        assert_eq!(a.measured.len(), a.truth.len());
        // While inside, the true line passes through the true pivot, and the tip is beyond it.
        for t in &a.truth {
            if let Some(f) = t.fulcrum_base_m {
                let v = f - t.line.wrist_base_m;
                let along = t.line.axis_base.dot(&v);
                let dist = (v - t.line.axis_base * along).norm();
                assert!(dist < 1e-9, "line misses the pivot by {dist}");
                assert!(along < cfg.instrument_length_m + 1e-9, "tip not beyond the trocar");
            }
        }
        // The motion is continuous: the wrist moves less than 2 mm per 1 ms sample (2 m/s).
        let max_step =
            a.truth.windows(2).map(|w| (w[1].line.wrist_base_m - w[0].line.wrist_base_m).norm()).fold(0.0, f64::max);
        assert!(max_step < 0.002, "wrist jumps {max_step} m in one sample");
        // Events alternate insertion / extraction.
        for (i, e) in a.events.iter().enumerate() {
            assert_eq!(e.insertion, i % 2 == 0);
        }
    }

    /// Every motion style keeps the scenario's invariants: deterministic, continuous, the
    /// true line through the true pivot while inside with the tip beyond it, events
    /// alternating; and each behaviour changes the motion.
    #[test]
    fn every_style_is_continuous_consistent_and_different() {
        let base = ScenarioConfig { cycles: 4, ..Default::default() };
        let plain = generate(&base);
        let timings = [
            TransferTiming::AxisWithin,
            TransferTiming::RotateThenTranslate,
            TransferTiming::TranslateThenRotate,
            TransferTiming::Mixed,
        ];
        let mut styles: Vec<StyleConfig> =
            timings.iter().map(|&transfer| StyleConfig { transfer, ..Default::default() }).collect();
        styles.push(StyleConfig { shaft_pivot_probability: 1.0, ..Default::default() });
        styles.push(StyleConfig { hover_probability: 1.0, ..Default::default() });
        styles.push(StyleConfig { aim_probability: 1.0, ..Default::default() });
        styles.push(StyleConfig { reinsert_probability: 1.0, ..Default::default() });
        for style in styles {
            let cfg = ScenarioConfig { style, ..base.clone() };
            cfg.check().unwrap();
            let a = generate(&cfg);
            assert_eq!(a.measured, generate(&cfg).measured, "{style:?} not deterministic");
            assert_ne!(a.measured, plain.measured, "{style:?} changed nothing");
            assert_eq!(a.events.len(), 8, "{style:?}");
            for (i, e) in a.events.iter().enumerate() {
                assert_eq!(e.insertion, i % 2 == 0, "{style:?}");
            }
            let max_step = a
                .truth
                .windows(2)
                .map(|w| (w[1].line.wrist_base_m - w[0].line.wrist_base_m).norm())
                .fold(0.0, f64::max);
            assert!(max_step < 0.002, "{style:?}: wrist jumps {max_step} m in one sample");
            let max_turn = a
                .truth
                .windows(2)
                .map(|w| w[1].line.axis_base.dot(&w[0].line.axis_base).clamp(-1.0, 1.0).acos())
                .fold(0.0, f64::max);
            assert!(max_turn < 0.01, "{style:?}: axis turns {max_turn} rad in one sample");
            for t in &a.truth {
                if let Some(f) = t.fulcrum_base_m {
                    let v = f - t.line.wrist_base_m;
                    let along = t.line.axis_base.dot(&v);
                    assert!((v - t.line.axis_base * along).norm() < 1e-9, "{style:?}");
                    assert!(along < cfg.instrument_length_m + 1e-9, "{style:?}");
                }
            }
        }
        // Re-insertion always: every cycle after the first visits the same trocar.
        let cfg = ScenarioConfig { style: StyleConfig { reinsert_probability: 1.0, ..Default::default() }, ..base };
        let a = generate(&cfg);
        assert!(a.events.iter().all(|e| e.trocar == a.events[0].trocar));
    }

    #[test]
    fn style_probabilities_are_checked() {
        let cfg = ScenarioConfig {
            style: StyleConfig { hover_probability: 1.5, ..Default::default() },
            ..Default::default()
        };
        assert!(cfg.check().unwrap_err().to_string().contains("scenario.style.hover_probability"));
    }

    #[test]
    fn dome_layouts_keep_their_separation_and_lie_on_the_dome() {
        let top = [0.3, 0.0, 0.03];
        for seed in 0..20 {
            let l = dome_layout(seed, 4, top, 0.085, 0.09, 0.25).unwrap();
            assert_eq!(l, dome_layout(seed, 4, top, 0.085, 0.09, 0.25).unwrap());
            let centre = Vector3::new(top[0], top[1], top[2] - 0.25);
            for (i, p) in l.iter().enumerate() {
                let p = Vector3::from(*p);
                assert!(((p - centre).norm() - 0.25).abs() < 1e-12);
                for q in &l[i + 1..] {
                    assert!((p - Vector3::from(*q)).norm() >= 0.09);
                }
            }
        }
        assert!(dome_layout(1, 20, top, 0.05, 0.09, 0.25).is_none(), "20 ports cannot fit");
    }
}
