//! Trocar detection and fulcrum localisation from the instrument's axis lines.
//!
//! Each 1 ms sample gives a line `(P, z)`: the wrist centre P (metres, robot base frame) and
//! the unit instrument axis z (robot base frame). When the instrument passes through a
//! trocar, all lines pass (nearly) through the fulcrum F; when it does not, they do not, or
//! they pivot about the wrist P itself (the paper's false-positive trap).
//!
//! Two detectors sit behind [`Detector`], chosen by [`DetectorConfig::mode`]:
//! - [`paper::PaperDetector`]: Dong & Morel's Algorithms 1 and 2, faithfully (two circular
//!   windows, batch least squares, mean-residual thresholds). The reference.
//! - [`fast::FastDetector`]: comanip's own method (O(1) sliding normal equations over the
//!   longest self-consistent recent segment of lines, a conditioning gate, a fulcrum
//!   covariance, a per-sample innovation test for extraction, a signed depth guard, and,
//!   when configured, the instrument length and a memory of known trocars).
//!
//! See `docs/trocar-detection.md` for the method, the paper's ambiguities and our choices.
//! Both detectors are allocation-free after construction, and no output field is ever NaN
//! or Inf.

pub mod config;
pub mod fast;
pub mod lsq;
pub mod paper;
#[cfg(test)]
mod test_support;

pub use config::{ConfigError, DetectorConfig, DetectorMode, FastConfig, PaperConfig};

use nalgebra::Vector3;

/// Compiled capacity of every line window (lines). Config window sizes must not exceed it.
pub const WINDOW_CAPACITY: usize = 256;

/// Most trocars the fast detector remembers (trocar memory and trocar identities).
pub const MEMORY_CAPACITY: usize = 8;

/// One instrument line: the sample every detector consumes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LineSample {
    /// Wrist centre P, metres, robot base frame.
    pub wrist_base_m: Vector3<f64>,
    /// Instrument axis z, unit vector, robot base frame, pointing from the wrist towards the tip.
    pub axis_base: Vector3<f64>,
}

impl LineSample {
    /// A line through `wrist_base_m` (metres) along `axis_base` (unit vector), both in the
    /// robot base frame. Nothing is checked here: detectors check every sample.
    ///
    /// **Real-time (1 kHz loop):** called every cycle; a copy, nothing else.
    pub fn new(wrist_base_m: Vector3<f64>, axis_base: Vector3<f64>) -> Self {
        Self { wrist_base_m, axis_base }
    }

    /// Checks that every component is finite, that |P| is below 100 m and that |z| is 1
    /// within 1e-6; renormalises z.
    ///
    /// **Real-time (1 kHz loop):** called on every sample by the detectors; allocation-free.
    pub fn validated(&self) -> Result<Self, SampleError> {
        if !self.wrist_base_m.iter().all(|v| v.is_finite()) {
            return Err(SampleError::NonFiniteWrist);
        }
        if !self.axis_base.iter().all(|v| v.is_finite()) {
            return Err(SampleError::NonFiniteAxis);
        }
        if self.wrist_base_m.norm() > 100.0 {
            return Err(SampleError::WristOutOfRange);
        }
        let n = self.axis_base.norm();
        if (n - 1.0).abs() > 1e-6 {
            return Err(SampleError::AxisNotUnit);
        }
        Ok(Self { wrist_base_m: self.wrist_base_m, axis_base: self.axis_base / n })
    }
}

/// Why a sample was refused (it is then ignored, and the estimate says so).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum SampleError {
    /// The wrist position has a NaN or infinite component.
    #[error("wrist position is not finite")]
    NonFiniteWrist,
    /// The axis has a NaN or infinite component.
    #[error("instrument axis is not finite")]
    NonFiniteAxis,
    /// The wrist is more than 100 m from the base: a corrupt sample.
    #[error("wrist position more than 100 m from the base")]
    WristOutOfRange,
    /// The axis is not a unit vector (|z| differs from 1 by more than 1e-6).
    #[error("instrument axis is not a unit vector")]
    AxisNotUnit,
}

/// Is the instrument in a trocar?
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum TrocarState {
    /// No trocar is detected: no fulcrum may be used.
    #[default]
    Outside,
    /// The instrument passes through trocar `id` (an index, stable while the detector lives,
    /// in the order trocars were first found; identical ids mean the same place within the
    /// fast mode's merge distance; the paper mode numbers every insertion anew).
    Inside {
        /// Trocar identity.
        id: u8,
    },
}

impl TrocarState {
    /// True in [`TrocarState::Inside`].
    ///
    /// **Real-time (1 kHz loop):** allocation-free.
    pub fn is_inside(&self) -> bool {
        matches!(self, TrocarState::Inside { .. })
    }
}

/// Figures of the latest least-squares fit on the window the detector currently decides on.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FitSummary {
    /// Least-squares fulcrum of that window, metres, robot base frame (may be meaningless
    /// when the state is `Outside`: it is not a trocar, only the best intersection).
    pub point_base_m: Vector3<f64>,
    /// Residual of the window, metres: the mean line distance (Eq. 8) in paper mode, the
    /// root-mean-square line distance in fast mode.
    pub residual_m: f64,
    /// `λ_min(Σ(I − z zᵀ)) / q`, dimensionless (0 for parallel lines, at most 2/3).
    pub conditioning: f64,
    /// One-sigma uncertainty of the point along its worst direction, metres, from the
    /// residual-based noise estimate (floored by the configured noise floor in fast mode).
    pub std_m: f64,
    /// Lines in the fit.
    pub lines: u16,
    /// Angular spread of the lines' directions along their narrowest direction, rad²
    /// (mean squared; 0 for a one-axis swing). See [`lsq::LsFit::minor_spread_rad2`].
    pub minor_spread_rad2: f64,
}

/// What one step reports. Every float is finite.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Estimate {
    /// Detector state after this sample.
    pub state: TrocarState,
    /// The fulcrum to use, metres, robot base frame: `Some` exactly when `state` is `Inside`.
    pub fulcrum_base_m: Option<Vector3<f64>>,
    /// The latest fit on the deciding window, when that window could be solved.
    pub fit: Option<FitSummary>,
    /// Lines in the deciding window (paper: `L_m` while outside or while `L_n` is not full,
    /// else `L_n`; fast: the current consistent segment).
    pub window_fill: u16,
    /// Capacity of that window (paper: `m` or `n`; fast: `window`).
    pub window_len: u16,
    /// Why this sample was refused, if it was (the state is then carried over unchanged).
    pub rejected: Option<SampleError>,
    /// True when this sample was included in the line windows (Algorithm 1's test passed).
    pub included: bool,
}

impl Estimate {
    fn outside() -> Self {
        Self {
            state: TrocarState::Outside,
            fulcrum_base_m: None,
            fit: None,
            window_fill: 0,
            window_len: 0,
            rejected: None,
            included: false,
        }
    }
}

/// Algorithm 1's inclusion test: is `new` far enough from `last` (the last included line)?
/// `d = |(I − z_last z_lastᵀ)(P_last − P_new)|` (Eq. 9) and `θ = acos(z_last · z_new)`
/// (Eq. 10); included when `d > delta_d_m` or `θ > delta_theta_rad`.
#[inline]
pub(crate) fn differs_enough(last: &LineSample, new: &LineSample, delta_d_m: f64, cos_delta_theta: f64) -> bool {
    let d = lsq::line_distance(last, &new.wrist_base_m);
    // θ > δθ  ⇔  cos θ < cos δθ (acos is decreasing; avoids acos on the hot path)
    d > delta_d_m || last.axis_base.dot(&new.axis_base) < cos_delta_theta
}

/// What [`Detector::resume_after_gap`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GapOutcome {
    /// The gap was short: the detector resumes with its state, checked on the next sample.
    Resumed,
    /// The gap was longer than `max_gap_s`: the detector was reset to `Outside`.
    Reset,
}

/// Either detector, chosen by configuration, with the input-gap policy. `step` once per
/// sample.
#[derive(Clone, Debug)]
pub struct Detector {
    kind: Kind,
    /// Sample period, seconds.
    sample_period_s: f64,
    /// Longest input gap resumed after, seconds.
    max_gap_s: f64,
}

// Both variants are large fixed buffers (tens of KiB) held inline on purpose: no heap, no
// indirection on the 1 kHz path. Construct once, keep it in a long-lived place.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug)]
enum Kind {
    /// The paper's method.
    Paper(paper::PaperDetector),
    /// comanip's method.
    Fast(fast::FastDetector),
}

impl Detector {
    /// Validates `config` and builds the selected detector (the only allocation-free-after
    /// point: everything is sized here).
    ///
    /// **Not for the real-time loop:** validates and sizes every window; call it at start-up.
    pub fn new(config: &DetectorConfig) -> Result<Self, ConfigError> {
        config.validate()?;
        let kind = match config.mode {
            DetectorMode::Paper => Kind::Paper(paper::PaperDetector::new(&config.paper)?),
            DetectorMode::Fast => Kind::Fast(fast::FastDetector::new(&config.fast, config.sample_period_s)?),
        };
        Ok(Self { kind, sample_period_s: config.sample_period_s, max_gap_s: config.max_gap_s })
    }

    /// Feeds one sample (one control cycle) and returns the estimate after it.
    ///
    /// **Real-time (1 kHz loop):** called every cycle; allocation-free, O(window) at worst, no
    /// I/O.
    #[inline]
    pub fn step(&mut self, sample: &LineSample) -> Estimate {
        match &mut self.kind {
            Kind::Paper(d) => d.step(sample),
            Kind::Fast(d) => d.step(sample),
        }
    }

    /// Forgets every line and returns to `Outside` (used when the input goes stale). The fast
    /// detector keeps its trocar memory.
    ///
    /// **Real-time (1 kHz loop):** called when the input goes stale; allocation-free.
    pub fn reset(&mut self) {
        match &mut self.kind {
            Kind::Paper(d) => d.reset(),
            Kind::Fast(d) => d.reset(),
        }
    }

    /// Tells the detector that `missed_samples` samples (at the configured sample period)
    /// never reached it, because the input was missing or invalid. A gap up to `max_gap_s`
    /// (seconds) freezes the detector: it resumes where it was, and the first sample after the
    /// gap is checked against its state (fast mode: inside, a line that no longer passes
    /// through the fulcrum, or a tip back over it, ends the insertion at once, without the
    /// usual persistence; outside, the segment of lines goes on: in 50 ms the hand moves a few
    /// millimetres). A longer gap resets it.
    ///
    /// **Real-time (1 kHz loop):** called after a gap in the input; allocation-free.
    pub fn resume_after_gap(&mut self, missed_samples: u64) -> GapOutcome {
        if missed_samples as f64 * self.sample_period_s > self.max_gap_s + 1e-12 {
            self.reset();
            return GapOutcome::Reset;
        }
        match &mut self.kind {
            // The paper has no notion of gaps: its windows simply go on.
            Kind::Paper(_) => {}
            Kind::Fast(d) => d.check_after_gap(),
        }
        GapOutcome::Resumed
    }

    /// The confirmed trocars the detector knows (its trocar list): `(id, fulcrum)` pairs,
    /// metres, robot base frame. Empty in paper mode, which has no trocar identity.
    pub fn known_trocars(&self) -> heapless::Vec<(u8, Vector3<f64>), MEMORY_CAPACITY> {
        match &self.kind {
            Kind::Paper(_) => heapless::Vec::new(),
            Kind::Fast(d) => d.known_trocars().collect(),
        }
    }

    /// The active mode.
    pub fn mode(&self) -> DetectorMode {
        match self.kind {
            Kind::Paper(_) => DetectorMode::Paper,
            Kind::Fast(_) => DetectorMode::Fast,
        }
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::{UnitQuaternion, Vector3};

    use super::lsq::{NormalSums, SolveError};
    use super::test_support::{
        MODES, Phase, assert_finite, cone_axis, detector, line_through, mean, moved, run_scripted, scripted,
    };
    use super::{DetectorConfig, DetectorMode, LineSample, SampleError};

    #[test]
    fn exact_fulcrum_from_noiseless_lines() {
        let f = Vector3::new(0.42, -0.05, 0.03);
        let mut sums = NormalSums::new();
        for k in 0..12 {
            let axis = cone_axis(0.1 + 0.02 * k as f64, 0.7 * k as f64);
            sums.add(&line_through(&f, &axis, 0.15 + 0.01 * k as f64));
        }
        let fit = sums.solve(1e-9).unwrap();
        assert!((fit.fulcrum_base_m - f).norm() < 1e-12, "{}", fit.fulcrum_base_m);
        // SSR comes from c − bᵀF (O(1) sums): cancellation leaves ~1e-16·c, i.e. rms ≲ 1e-8 m.
        assert!(fit.rms_m < 1e-7, "{}", fit.rms_m);

        // Both detectors find it, exactly, from a noiseless pivoting motion.
        let (lines, phases, _) = scripted(&[f], 1, 0.0, 6.0);
        assert!(phases.iter().all(|p| *p == Phase::Inside));
        for mode in MODES {
            let mut d = detector(mode);
            let mut last = None;
            for l in &lines {
                last = Some(d.step(l));
            }
            let e = last.unwrap();
            assert!(e.state.is_inside(), "{mode:?} did not detect the trocar");
            let err = (e.fulcrum_base_m.unwrap() - f).norm();
            assert!(err < 1e-9, "{mode:?}: fulcrum off by {err} m");
        }
    }

    #[test]
    fn invariant_under_rigid_motion_of_the_base() {
        let f = Vector3::new(0.40, 0.02, 0.05);
        let (lines, _, _) = scripted(&[f, Vector3::new(0.5, -0.1, 0.0)], 4, 2.0, 6.0);
        let rot = UnitQuaternion::from_euler_angles(0.3, -0.8, 1.9);
        let trans = Vector3::new(-0.7, 1.2, 0.4);
        for mode in MODES {
            let (mut a, mut b) = (detector(mode), detector(mode));
            let mut changes = 0;
            let mut prev = false;
            for l in &lines {
                let ea = a.step(l);
                let eb = b.step(&moved(l, &rot, &trans));
                assert_eq!(ea.state, eb.state, "{mode:?}: state differs after a rigid motion");
                if let (Some(fa), Some(fb)) = (ea.fulcrum_base_m, eb.fulcrum_base_m) {
                    assert!((rot * fa + trans - fb).norm() < 1e-7, "{mode:?}: fulcrum is not covariant");
                }
                if ea.state.is_inside() != prev {
                    changes += 1;
                    prev = ea.state.is_inside();
                }
            }
            assert!(changes >= 6, "{mode:?}: the sequence must exercise insertions and extractions ({changes})");
        }
    }

    #[test]
    fn parallel_lines_are_never_a_trocar() {
        let axis = Vector3::new(0.1, 0.2, -1.0).normalize();
        let mut sums = NormalSums::new();
        for k in 0..50 {
            sums.add(&LineSample::new(Vector3::new(0.4 + 0.003 * k as f64, 0.001 * k as f64, 0.3), axis));
        }
        assert!(matches!(sums.solve(1e-9), Err(SolveError::IllConditioned { .. })));
        for mode in MODES {
            let mut d = detector(mode);
            for k in 0..20_000 {
                // A wrist sliding sideways with a fixed axis (slightly noisy): nearly parallel lines.
                let t = k as f64 * 0.001;
                let wobble = Vector3::new(1e-5 * (7.0 * t).sin(), 1e-5 * (5.0 * t).cos(), 0.0);
                let l = LineSample::new(
                    Vector3::new(0.3 + 0.05 * (0.5 * t).sin(), 0.05 * (0.3 * t).cos(), 0.3),
                    (axis + wobble).normalize(),
                );
                let e = d.step(&l);
                assert_finite(&e);
                assert!(!e.state.is_inside(), "{mode:?} declared a trocar from parallel lines at {t} s");
                assert!(e.fulcrum_base_m.is_none());
            }
        }
    }

    #[test]
    fn rotation_about_the_wrist_is_not_a_trocar() {
        // The paper's false-positive case: outside the body, the surgeon turns the instrument
        // about the wrist centre P (the passive wrist), so every line passes through P.
        let p = Vector3::new(0.35, 0.05, 0.30);
        for mode in MODES {
            let mut d = detector(mode);
            let mut fits = 0;
            for k in 0..30_000 {
                let t = k as f64 * 0.001;
                let axis = cone_axis(0.1 + 0.3 * (0.5 - 0.5 * (1.1 * t).cos()), 0.9 * t);
                let e = d.step(&LineSample::new(p, axis));
                assert!(!e.state.is_inside(), "{mode:?} took the wrist for a trocar at {t} s");
                if let Some(fit) = e.fit {
                    // The lines do intersect (at P): the detector must see it and refuse it.
                    if (fit.point_base_m - p).norm() < 1e-3 {
                        fits += 1;
                    }
                }
            }
            assert!(fits > 1000, "{mode:?}: the test must produce fits at the wrist ({fits})");
        }
    }

    #[test]
    fn bad_samples_are_rejected_and_change_nothing() {
        let f = Vector3::new(0.42, -0.05, 0.03);
        let (lines, _, _) = scripted(&[f], 1, 0.0, 4.0);
        for mode in MODES {
            let mut d = detector(mode);
            let mut last = None;
            for l in &lines {
                last = Some(d.step(l));
            }
            let before = last.unwrap();
            assert!(before.state.is_inside());
            let bad = [
                (LineSample::new(Vector3::new(f64::NAN, 0.0, 0.0), Vector3::z()), SampleError::NonFiniteWrist),
                (LineSample::new(Vector3::zeros(), Vector3::new(0.0, f64::INFINITY, 0.0)), SampleError::NonFiniteAxis),
                (LineSample::new(Vector3::new(1e6, 0.0, 0.0), Vector3::z()), SampleError::WristOutOfRange),
                (LineSample::new(Vector3::zeros(), Vector3::new(0.0, 0.0, 0.5)), SampleError::AxisNotUnit),
                (LineSample::new(Vector3::zeros(), Vector3::zeros()), SampleError::AxisNotUnit),
            ];
            for (sample, err) in bad {
                let e = d.step(&sample);
                assert_eq!(e.rejected, Some(err), "{mode:?}");
                assert_eq!(e.state, before.state);
                assert_eq!(e.fulcrum_base_m, before.fulcrum_base_m);
                assert_finite(&e);
            }
            // A good sample afterwards is accepted again.
            assert_eq!(d.step(lines.last().unwrap()).rejected, None);
        }
    }

    #[test]
    fn reset_returns_to_outside() {
        let (lines, _, _) = scripted(&[Vector3::new(0.4, 0.0, 0.0)], 1, 0.0, 4.0);
        for mode in MODES {
            let mut d = detector(mode);
            for l in &lines {
                d.step(l);
            }
            d.reset();
            let e = d.step(&lines[0]);
            assert!(!e.state.is_inside() && e.fulcrum_base_m.is_none(), "{mode:?}");
        }
    }

    #[test]
    fn fast_mode_follows_them_sooner_than_the_paper() {
        let paper = run_scripted(&DetectorConfig { mode: DetectorMode::Paper, ..Default::default() }, 3.0);
        let fast = run_scripted(&DetectorConfig { mode: DetectorMode::Fast, ..Default::default() }, 3.0);
        let (pi, fi) = (mean(&paper.insertion_s), mean(&fast.insertion_s));
        let (pe, fe) = (mean(&paper.extraction_s), mean(&fast.extraction_s));
        std::eprintln!("insertion: paper {pi:.3} s, fast {fi:.3} s; extraction: paper {pe:.3} s, fast {fe:.3} s");
        assert!(fi < pi, "fast insertion {fi} s not below paper {pi} s");
        assert!(fe < pe, "fast extraction {fe} s not below paper {pe} s");
    }
}
