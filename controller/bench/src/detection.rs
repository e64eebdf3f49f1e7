//! Running the detectors over benchmark traces, and what is measured per run.
//!
//! Four settings run on the same lines ([`settings`]): the paper's method (reference), and
//! comanip's fast method with the paper's information only, with the instrument length
//! known, and with the length and the trocar memory. Each run yields the per-sample output
//! and the per-step time and allocations; [`analyse`] turns it into per-event figures.

use std::time::Instant;

use estimator::trocar::{Detector, DetectorConfig, DetectorMode, FastConfig, TrocarState};
use nalgebra::Vector3;
use sim::scenario::TruthState;
use sim::score::{Detected, GroundTruth, Score, score_against};

use super::trace::Trace;

/// A fulcrum farther than this from the true pivot at the first detection counts as a
/// wrong-trocar (false) detection, metres. The trocars are 6-12 cm apart.
pub const WRONG_TROCAR_M: f64 = 0.02;

/// Steady state starts this long after a detection, seconds.
pub const STEADY_AFTER_S: f64 = 1.0;

/// One detector configuration of the benchmark.
#[derive(Clone, Debug)]
pub struct Setting {
    /// Short key (report columns, file names).
    pub key: &'static str,
    /// Human-readable name.
    pub label: &'static str,
    /// The detector's configuration.
    pub config: DetectorConfig,
}

/// The four settings, for an instrument of `instrument_length_m` (metres, wrist centre to
/// tip), built on `base` (its paper and fast parameters; the mode, the instrument length and
/// the trocar memory are set per setting).
pub fn settings(instrument_length_m: f64, base: &DetectorConfig) -> Vec<Setting> {
    let paper = DetectorConfig { mode: DetectorMode::Paper, ..*base };
    let plain = FastConfig { instrument_length_m: None, trocar_memory: false, ..base.fast };
    let fast = DetectorConfig { mode: DetectorMode::Fast, fast: plain, ..*base };
    let with_length = |memory: bool| DetectorConfig {
        fast: FastConfig { instrument_length_m: Some(instrument_length_m), trocar_memory: memory, ..fast.fast },
        ..fast
    };
    vec![
        Setting { key: "paper", label: "paper (Dong & Morel)", config: paper },
        Setting { key: "fast", label: "fast, paper's information", config: fast },
        Setting { key: "fast_length", label: "fast + instrument length", config: with_length(false) },
        Setting { key: "fast_memory", label: "fast + length + trocar memory", config: with_length(true) },
    ]
}

/// Step-time histogram with 5 ns buckets up to 100 µs (and an overflow count with the max).
#[derive(Clone, Debug)]
pub struct StepTimes {
    buckets: Vec<u64>,
    count: u64,
    max_ns: u64,
}

/// Width of a [`StepTimes`] bucket, nanoseconds.
pub const STEP_BUCKET_NS: u64 = 5;
const STEP_BUCKETS: usize = 20_000;

impl Default for StepTimes {
    fn default() -> Self {
        Self { buckets: vec![0; STEP_BUCKETS + 1], count: 0, max_ns: 0 }
    }
}

impl StepTimes {
    /// Records one step of `ns` nanoseconds.
    pub fn record(&mut self, ns: u64) {
        let i = ((ns / STEP_BUCKET_NS) as usize).min(STEP_BUCKETS);
        self.buckets[i] += 1;
        self.count += 1;
        self.max_ns = self.max_ns.max(ns);
    }
    /// Adds another histogram.
    pub fn merge(&mut self, other: &StepTimes) {
        for (a, b) in self.buckets.iter_mut().zip(&other.buckets) {
            *a += b;
        }
        self.count += other.count;
        self.max_ns = self.max_ns.max(other.max_ns);
    }
    /// Steps recorded.
    pub fn count(&self) -> u64 {
        self.count
    }
    /// Largest step, nanoseconds.
    pub fn max_ns(&self) -> u64 {
        self.max_ns
    }
    /// Quantile `q` in [0, 1], nanoseconds (upper edge of the bucket; the max for the last).
    pub fn quantile_ns(&self, q: f64) -> f64 {
        if self.count == 0 {
            return 0.0;
        }
        let target = ((q.clamp(0.0, 1.0) * self.count as f64).ceil() as u64).max(1);
        let mut seen = 0;
        for (i, n) in self.buckets.iter().enumerate() {
            seen += n;
            if seen >= target {
                return if i == STEP_BUCKETS { self.max_ns as f64 } else { ((i as u64 + 1) * STEP_BUCKET_NS) as f64 };
            }
        }
        self.max_ns as f64
    }
    /// Non-empty buckets as (lower edge ns, count).
    pub fn buckets(&self) -> impl Iterator<Item = (u64, u64)> + '_ {
        self.buckets.iter().enumerate().filter(|(_, n)| **n > 0).map(|(i, n)| (i as u64 * STEP_BUCKET_NS, *n))
    }
}

/// One detector over one trace.
#[derive(Clone, Debug)]
pub struct Run {
    /// Per sample: inside, and the fulcrum when inside (metres, robot base frame).
    pub detected: Vec<Detected>,
    /// Per sample: the trocar id when inside.
    pub ids: Vec<Option<u8>>,
    /// Per-step times (when timed).
    pub step_times: StepTimes,
    /// Heap allocations made by the detector steps on this thread (counted by
    /// [`hw_io::rt_alloc`] when it is the global allocator; 0 otherwise).
    pub allocations: u64,
    /// Steps run.
    pub steps: u64,
    /// The detector's trocar list after the last sample (metres, robot base frame).
    pub final_trocars_base_m: Vec<Vector3<f64>>,
}

/// Runs `setting` over `trace`. With `timed`, every step is timed with the monotonic clock
/// (the figures include the clock read, about 20-30 ns here). A sample without a line (an
/// incomplete cycle) resets the detector, as the daemon does.
pub fn run(trace: &Trace, setting: &Setting, timed: bool) -> Result<Run, estimator::trocar::ConfigError> {
    let mut det = Detector::new(&setting.config)?;
    let n = trace.lines.len();
    let mut detected = Vec::with_capacity(n);
    let mut ids = Vec::with_capacity(n);
    let mut times = StepTimes::default();
    let mut outputs = Vec::with_capacity(n);
    let (allocations, ()) = hw_io::rt_alloc::count_thread_allocs(|| {
        for line in &trace.lines {
            match line {
                Some(l) => {
                    let est = if timed {
                        let t0 = Instant::now();
                        let e = det.step(l);
                        times.record(t0.elapsed().as_nanos() as u64);
                        e
                    } else {
                        det.step(l)
                    };
                    outputs.push((est.state, est.fulcrum_base_m));
                }
                None => {
                    det.reset();
                    outputs.push((TrocarState::Outside, None));
                }
            }
        }
    });
    for (state, f) in outputs {
        let inside = state.is_inside();
        detected.push(Detected { inside, fulcrum_base_m: if inside { f } else { None } });
        ids.push(match state {
            TrocarState::Inside { id } => Some(id),
            TrocarState::Outside => None,
        });
    }
    let final_trocars_base_m = det.known_trocars().iter().map(|(_, f)| *f).collect();
    Ok(Run { detected, ids, step_times: times, allocations, steps: n as u64, final_trocars_base_m })
}

/// One true insertion and what a detector made of it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EventOutcome {
    /// True trocar index.
    pub trocar: usize,
    /// True insertion sample.
    pub insertion_sample: usize,
    /// True extraction sample (the trace's end if none).
    pub extraction_sample: usize,
    /// The trocar was visited earlier in the same trace (a re-insertion).
    pub revisit: bool,
    /// Insertion delay, seconds (None: missed).
    pub insertion_delay_s: Option<f64>,
    /// Extraction delay, seconds (None: missed or no extraction).
    pub extraction_delay_s: Option<f64>,
    /// Localisation error at the first detection, metres.
    pub first_error_m: Option<f64>,
    /// Fulcrum reported on the last inside sample before the true extraction (metres, robot
    /// base frame).
    pub final_fulcrum_base_m: Option<Vector3<f64>>,
}

/// Everything measured on one run.
#[derive(Clone, Debug)]
pub struct Analysis {
    /// The scorer's figures (the same as `fulcrumd replay --truth`).
    pub score: Score,
    /// Per true insertion.
    pub events: Vec<EventOutcome>,
    /// Localisation errors in steady state (≥ [`STEADY_AFTER_S`] after the detection, while
    /// both the truth and the detector are inside), metres.
    pub steady_errors_m: Vec<f64>,
    /// Localisation errors over every inside/inside sample, metres.
    pub all_errors_m: Vec<f64>,
    /// Outside→inside transitions while the truth was outside (a subset of false detections).
    pub false_outside: usize,
    /// Distinct trocar ids the detector used.
    pub distinct_ids: usize,
    /// Inside→outside transitions while the truth was inside (spurious extractions).
    pub false_extractions: usize,
}

/// Scores `run` against `trace`.
pub fn analyse(trace: &Trace, run: &Run) -> Analysis {
    let score = score_against(trace, &run.detected, WRONG_TROCAR_M);
    let n = run.detected.len().min(trace.samples());
    let mut events = Vec::new();
    let mut visited = std::collections::BTreeSet::new();
    let mut steady = Vec::new();
    let mut all = Vec::new();
    let steady_after = (STEADY_AFTER_S / 1e-3) as usize;
    let evs = &trace.events;
    for (k, e) in evs.iter().enumerate() {
        if !e.insertion {
            continue;
        }
        let extraction = evs[k + 1..].iter().find(|x| !x.insertion).map_or(n, |x| x.sample).min(n);
        let next_insertion = evs[k + 1..].iter().find(|x| x.insertion).map_or(n, |x| x.sample).min(n);
        // As the scorer: inside at the right trocar (nearest trocar, within WRONG_TROCAR_M).
        let detect = (e.sample..extraction).find(|&j| match (run.detected[j].fulcrum_base_m, trace.pivots[j]) {
            (Some(f), Some(p)) => {
                (f - p).norm() <= WRONG_TROCAR_M
                    && sim::score::nearest_trocar_of(&trace.trocars_base_m, &f) == Some(e.trocar)
            }
            _ => false,
        });
        let out = if extraction < n {
            (extraction..next_insertion).find(|&j| !run.detected[j].inside).map(|j| (j - extraction) as f64 * 1e-3)
        } else {
            None
        };
        let first_error = detect.and_then(|j| {
            let (_, p) = trace.truth_at(j);
            Some((run.detected[j].fulcrum_base_m? - p?).norm())
        });
        if let Some(j0) = detect {
            for j in j0..extraction {
                if let (true, Some(f), (_, Some(p))) =
                    (run.detected[j].inside, run.detected[j].fulcrum_base_m, trace.truth_at(j))
                {
                    let err = (f - p).norm();
                    all.push(err);
                    if j >= j0 + steady_after {
                        steady.push(err);
                    }
                }
            }
        }
        let final_fulcrum = (e.sample..extraction).rev().find_map(|j| run.detected[j].fulcrum_base_m);
        events.push(EventOutcome {
            trocar: e.trocar,
            insertion_sample: e.sample,
            extraction_sample: extraction,
            revisit: !visited.insert(e.trocar),
            insertion_delay_s: detect.map(|j| (j - e.sample) as f64 * 1e-3),
            extraction_delay_s: out,
            first_error_m: first_error,
            final_fulcrum_base_m: final_fulcrum,
        });
    }
    let false_outside =
        score.false_detection_samples.iter().filter(|&&i| matches!(trace.truth_at(i).0, TruthState::Outside)).count();
    let false_extractions = (1..n)
        .filter(|&i| run.detected[i - 1].inside && !run.detected[i].inside)
        .filter(|&i| matches!(trace.truth_at(i).0, TruthState::Inside { .. }))
        .count();
    let distinct_ids = run.ids.iter().flatten().collect::<std::collections::BTreeSet<_>>().len();
    Analysis {
        score,
        events,
        steady_errors_m: steady,
        all_errors_m: all,
        false_outside,
        distinct_ids,
        false_extractions,
    }
}
