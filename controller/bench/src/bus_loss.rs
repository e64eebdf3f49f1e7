//! Bus loss and gaps: the daemon's own stale-data policy (`controller::cycle::Estimation`) under
//! random TPDO loss and bursts of missing TPDOs, on the benchmark's traces
//! (`docs/BENCHMARKS.md`, "Bus loss and gaps").
//!
//! Each condition reruns the twin of a trace ([`super::trace::twin_config`]) and drops TPDO
//! frames before the controller's [`Acquisition`] sees them: either each frame independently
//! with a probability, or every TPDO of one node (drawn at random) for a burst of a given
//! length, at random instants about every 20 s. The cycles then go through [`Estimation`]
//! with the daemon's policy (a gap up to `max_gap_s` freezes and resumes, a longer one
//! resets) for every detector setting, on the same frames.
//!
//! Per condition and setting: spurious extractions (the published state goes from inside to
//! outside, through any number of invalid cycles, while the instrument is truly inside and
//! its tip is more than 50 ms from crossing out), detector resets, cycles published invalid,
//! and the detection figures of the scorer (false detections, insertions detected, mean
//! delays; an invalid cycle holds the last valid state), to compare with the loss-free run.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use sim::scenario::TrueEvent;
use sim::scenario::TruthState;
use sim::score::{Detected, mean, score_against};
use sim::twin::SimRobot;

use hw_io::can::Message;
use hw_io::ipc::{HealthFlags, OutputState};

use super::detection::{Setting, settings};
use super::report::BenchError;
use super::trace::{PLACEMENTS, Trace, TraceError, TraceSpec, drive, twin_config, twin_events};
use controller::cycle::{Acquisition, Estimation};
use controller::health::HealthConfig;

/// An extraction declared at most this long before the tip truly crossed out is early, not
/// spurious, seconds (as in the family benchmark).
pub const EARLY_EXTRACTION_S: f64 = 0.05;

/// Mean interval between bursts, seconds.
pub const BURST_INTERVAL_S: f64 = 20.0;

/// One loss condition.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Loss {
    /// No loss (the reference).
    None,
    /// Each TPDO frame lost independently with this probability.
    Random(f64),
    /// Every TPDO of one random node lost for this many milliseconds, about every
    /// [`BURST_INTERVAL_S`].
    Burst(u64),
}

impl Loss {
    /// Row label.
    pub fn label(&self) -> String {
        match self {
            Loss::None => "no loss".into(),
            Loss::Random(p) => format!("random TPDO loss {p:e} per frame"),
            Loss::Burst(ms) => format!("bursts of {ms} ms (one node, every ~{BURST_INTERVAL_S:.0} s)"),
        }
    }
}

/// The conditions of the report.
pub const CONDITIONS: [Loss; 10] = [
    Loss::None,
    Loss::Random(1e-4),
    Loss::Random(1e-3),
    Loss::Random(1e-2),
    Loss::Burst(1),
    Loss::Burst(3),
    Loss::Burst(10),
    Loss::Burst(30),
    Loss::Burst(50),
    Loss::Burst(100),
];

/// Figures of one condition × setting, summed over the traces.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LossCell {
    /// Simulated time, hours.
    pub hours: f64,
    /// TPDO frames dropped.
    pub dropped_frames: u64,
    /// Spurious extractions (see the module doc).
    pub spurious_extractions: usize,
    /// Detector resets (`DETECTOR_RESET` published).
    pub resets: usize,
    /// Cycles published invalid.
    pub invalid_cycles: u64,
    /// False detections (the scorer's definition).
    pub false_detections: usize,
    /// True insertions.
    pub insertions: usize,
    /// Insertions detected.
    pub detected: usize,
    /// Insertion delays, seconds.
    pub insertion_delays_s: Vec<f64>,
    /// Extraction delays, seconds.
    pub extraction_delays_s: Vec<f64>,
}

/// The bus-loss report.
#[derive(Clone, Debug)]
pub struct LossReport {
    /// Settings (columns of each row group).
    pub settings: Vec<Setting>,
    /// Per condition, one cell per setting.
    pub rows: Vec<(Loss, Vec<LossCell>)>,
    /// The traces it ran on.
    pub specs: Vec<TraceSpec>,
    /// Wall-clock, seconds.
    pub wall_s: f64,
}

/// Runs every condition on the traces of `seeds` (placement C1, `cycles` each).
pub fn run_bus_loss(seeds: &[u64], cycles: usize, progress: &(dyn Fn() + Sync)) -> Result<LossReport, BenchError> {
    let started = std::time::Instant::now();
    let specs: Vec<TraceSpec> = seeds
        .iter()
        .map(|&seed| TraceSpec {
            seed,
            cycles,
            placement: PLACEMENTS[0],
            model_error: true,
            style: Default::default(),
            dome_seed: None,
        })
        .collect();
    let length = sim::twin::TwinConfig::default().scenario.instrument_length_m;
    let sets = settings(length, &Default::default());
    let jobs: Vec<(usize, usize)> = (0..CONDITIONS.len()).flat_map(|c| (0..specs.len()).map(move |t| (c, t))).collect();
    let results: Vec<Result<(usize, Vec<LossCell>), BenchError>> = jobs
        .par_iter()
        .map(|&(c, t)| {
            let cells = run_one(&specs[t], CONDITIONS[c], &sets)?;
            progress();
            Ok((c, cells))
        })
        .collect();
    let mut rows: Vec<(Loss, Vec<LossCell>)> =
        CONDITIONS.iter().map(|&l| (l, vec![LossCell::default(); sets.len()])).collect();
    for r in results {
        let (c, cells) = r?;
        for (acc, x) in rows[c].1.iter_mut().zip(cells) {
            acc.hours += x.hours;
            acc.dropped_frames += x.dropped_frames;
            acc.spurious_extractions += x.spurious_extractions;
            acc.resets += x.resets;
            acc.invalid_cycles += x.invalid_cycles;
            acc.false_detections += x.false_detections;
            acc.insertions += x.insertions;
            acc.detected += x.detected;
            acc.insertion_delays_s.extend(x.insertion_delays_s);
            acc.extraction_delays_s.extend(x.extraction_delays_s);
        }
    }
    Ok(LossReport { settings: sets, rows, specs, wall_s: started.elapsed().as_secs_f64() })
}

/// Is a TPDO of this frame to be dropped?
fn is_tpdo(frame: &hw_io::can::CanFrame) -> Option<u8> {
    match Message::decode(frame) {
        Ok(Message::Tpdo { node, .. }) => Some(node.get()),
        _ => None,
    }
}

fn run_one(spec: &TraceSpec, loss: Loss, sets: &[Setting]) -> Result<Vec<LossCell>, BenchError> {
    let cfg = twin_config(spec);
    let mut twin = SimRobot::new(&cfg).map_err(TraceError::from)?;
    let mut acq =
        Acquisition::new(&cfg.encoder, HealthConfig::default()).map_err(|e| TraceError::Pipeline(e.to_string()))?;
    let mut ests: Vec<Estimation> = sets
        .iter()
        .map(|s| Estimation::new(&cfg.encoder, &cfg.kinematics, &s.config))
        .collect::<Result<_, _>>()
        .map_err(|e| TraceError::Pipeline(e.to_string()))?;
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed ^ 0x6275_735f_6c6f_7373);
    let node_ids: Vec<u8> = cfg.encoder.node_ids.to_vec();
    let mut burst_until: u64 = 0;
    let mut burst_node: u8 = 0;
    let mut states: Vec<Vec<OutputState>> = vec![Vec::new(); sets.len()];
    let mut fulcrums: Vec<Vec<Option<nalgebra::Vector3<f64>>>> = vec![Vec::new(); sets.len()];
    let mut cells = vec![LossCell::default(); sets.len()];
    let mut truth_states = Vec::new();
    let mut pivots = Vec::new();
    let mut events: Vec<TrueEvent> = Vec::new();
    let mut dropped = 0u64;
    let mut k: u64 = 0;
    drive(&mut twin, spec, |frames, t_us, twin| {
        if let Loss::Burst(ms) = loss
            && k >= burst_until
            && rng.random_bool(1e-3 / BURST_INTERVAL_S)
        {
            burst_until = k + ms;
            burst_node = node_ids[rng.random_range(0..node_ids.len())];
        }
        acq.start_cycle();
        for f in frames {
            let drop = match (loss, is_tpdo(&f.frame)) {
                (Loss::Random(p), Some(_)) => rng.random_bool(p),
                (Loss::Burst(_), Some(node)) => k < burst_until && node == burst_node,
                _ => false,
            };
            if drop {
                dropped += 1;
                continue;
            }
            acq.on_frame(&f.frame, f.unix_time_us * 1000);
        }
        let input = acq.end_cycle((t_us + 900) * 1000, false);
        for (j, e) in ests.iter_mut().enumerate() {
            let out = e.process(&input);
            if out.health.contains(HealthFlags::DETECTOR_RESET) {
                cells[j].resets += 1;
            }
            if out.health.intersects(HealthFlags::INVALIDATING) {
                cells[j].invalid_cycles += 1;
            }
            states[j].push(out.state);
            fulcrums[j].push(out.state.is_inside().then(|| nalgebra::Vector3::from(out.fulcrum_base_m)));
        }
        let truth = twin.truth();
        truth_states.push(truth.state);
        pivots.push(truth.fulcrum_base_m);
        events.extend(twin_events(twin));
        k += 1;
    })?;
    let trace = Trace {
        spec: *spec,
        lines: vec![None; truth_states.len()],
        states: truth_states,
        pivots,
        events,
        trocars_base_m: cfg.scenario.trocars_base_m.clone(),
        instrument_length_m: cfg.scenario.instrument_length_m,
    };
    let early = (EARLY_EXTRACTION_S / 1e-3) as usize;
    for (j, cell) in cells.iter_mut().enumerate() {
        cell.hours = trace.states.len() as f64 * 1e-3 / 3600.0;
        cell.dropped_frames = dropped;
        // An invalid cycle says nothing: for the scorer it holds the last valid state (a
        // guidance module holds or pauses; counting it as "outside" would turn every lost
        // frame into an extraction and a new detection).
        let mut held = Detected { inside: false, fulcrum_base_m: None };
        let detected: Vec<Detected> = states[j]
            .iter()
            .zip(&fulcrums[j])
            .map(|(s, f)| {
                if s.is_valid() {
                    held = Detected { inside: s.is_inside(), fulcrum_base_m: *f };
                }
                held
            })
            .collect();
        let score = score_against(&trace, &detected, super::detection::WRONG_TROCAR_M);
        cell.false_detections = score.false_detections;
        cell.insertions = score.insertions;
        cell.detected = score.insertions_detected;
        cell.insertion_delays_s = score.insertion_delays_s;
        cell.extraction_delays_s = score.extraction_delays_s;
        // Spurious extractions: the last valid state was inside, this valid one is outside.
        let mut last_valid_inside = false;
        for (i, s) in states[j].iter().enumerate() {
            match *s {
                OutputState::Inside => last_valid_inside = true,
                OutputState::Outside => {
                    if last_valid_inside && matches!(trace.states[i], TruthState::Inside { .. }) {
                        let next_out = trace.events.iter().find(|e| !e.insertion && e.sample >= i);
                        if next_out.is_none_or(|e| e.sample - i > early) {
                            cell.spurious_extractions += 1;
                        }
                    }
                    last_valid_inside = false;
                }
                OutputState::Invalid => {}
            }
        }
    }
    Ok(cells)
}

impl LossReport {
    /// The report as Markdown: one table per setting, a row per condition.
    pub fn markdown(&self) -> String {
        use std::fmt::Write as _;
        let mut s = String::new();
        let hours = self.rows.first().map_or(0.0, |r| r.1.first().map_or(0.0, |c| c.hours));
        let seeds: Vec<String> = self.specs.iter().map(|x| x.seed.to_string()).collect();
        let _ = writeln!(
            s,
            "{} traces (seeds {}, placement C1, {} cycles each), {:.2} h of simulated motion per condition; wall-clock {:.0} s. \
             The daemon's policy: a gap up to `max_gap_s` = 50 ms freezes and resumes, a longer one resets.\n",
            self.specs.len(),
            seeds.join(", "),
            self.specs.first().map_or(0, |x| x.cycles),
            hours,
            self.wall_s
        );
        for (k, set) in self.settings.iter().enumerate() {
            let _ = writeln!(s, "**{}**\n", set.label);
            let _ = writeln!(
                s,
                "| condition | TPDOs dropped | cycles invalid | spurious extractions / h | resets / h | false detections | insertions detected | insertion delay mean (ms) | extraction delay mean (ms) |"
            );
            let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|");
            for (loss, cells) in &self.rows {
                let c = &cells[k];
                let h = c.hours.max(1e-9);
                let _ = writeln!(
                    s,
                    "| {} | {} | {} | {:.1} ({}) | {:.1} ({}) | {} | {}/{} | {:.0} | {:.0} |",
                    loss.label(),
                    c.dropped_frames,
                    c.invalid_cycles,
                    c.spurious_extractions as f64 / h,
                    c.spurious_extractions,
                    c.resets as f64 / h,
                    c.resets,
                    c.false_detections,
                    c.detected,
                    c.insertions,
                    mean(&c.insertion_delays_s) * 1e3,
                    mean(&c.extraction_delays_s) * 1e3,
                );
            }
            let _ = writeln!(s);
        }
        s
    }
}
