//! The motion-style families: the detectors on surgeons they were tuned on and on surgeons
//! they never saw, reported per family and marked as such (`docs/BENCHMARKS.md`).
//!
//! A threshold that works on one simulated surgeon is not a method. Each [`Family`] is a
//! motion style of `sim::scenario` ([`StyleConfig`]) on a trocar layout; the fast detector's
//! thresholds were chosen on the **tuning** families with the **tuning seeds** only
//! ([`TUNING_SEEDS`]); every family is reported on the **report seeds** ([`REPORT_SEEDS`]),
//! which were never run while tuning, and the held-out families were never run while tuning
//! at all.
//!
//! Per family and detector setting: false detections (outside, or at the wrong place),
//! samples published inside with the fulcrum more than [`FAR_FULCRUM_M`] from the true pivot,
//! insertions detected, mean delays against the motion-only bound, spurious extractions,
//! and whether the detector's trocar list is exactly the true trocars at the end.

use rayon::prelude::*;
use sim::scenario::{StyleConfig, TransferTiming, TruthState};
use sim::score::mean;

use super::bound::bounds;
use super::detection::{Setting, analyse, run, settings};
use super::report::BenchError;
use super::trace::{PLACEMENTS, Trace, TraceSpec, generate};

/// A published fulcrum farther than this from the true pivot while the instrument is truly
/// inside counts as a far-fulcrum sample, metres.
pub const FAR_FULCRUM_M: f64 = 0.02;

/// An extraction declared at most this long before the tip truly crossed the trocar is
/// early, not spurious, seconds.
pub const EARLY_EXTRACTION_S: f64 = 0.05;

/// A trocar-list entry within this distance of a true trocar is that trocar, metres.
pub const LIST_MATCH_M: f64 = 0.01;

/// Seeds the fast detector's thresholds were tuned on (tuning families only).
pub const TUNING_SEEDS: [u64; 2] = [11, 12];

/// Seeds every family is reported on (never run while tuning).
pub const REPORT_SEEDS: [u64; 6] = [201, 202, 203, 204, 205, 206];

/// One motion-style family.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Family {
    /// Short key (report rows).
    pub key: &'static str,
    /// What the surgeon does differently.
    pub description: &'static str,
    /// The style.
    pub style: StyleConfig,
    /// Random trocar layouts on a dome (a new layout per seed) instead of the default four
    /// trocars in the three placements.
    pub dome: bool,
    /// Used to tune the fast detector (on [`TUNING_SEEDS`] only).
    pub tuned: bool,
}

const fn style(transfer: TransferTiming, shaft_pivot: f64, hover: f64, aim: f64, reinsert: f64) -> StyleConfig {
    StyleConfig {
        transfer,
        shaft_pivot_probability: shaft_pivot,
        hover_probability: hover,
        aim_probability: aim,
        reinsert_probability: reinsert,
    }
}

/// The families, tuning families first.
pub const FAMILIES: [Family; 9] = [
    Family {
        key: "together",
        description: "position and axis move together (the original surgeon)",
        style: style(TransferTiming::Together, 0.0, 0.0, 0.0, 0.0),
        dome: false,
        tuned: true,
    },
    Family {
        key: "axis-within",
        description: "the axis turns within a 20-40 % sub-interval of each transfer",
        style: style(TransferTiming::AxisWithin, 0.0, 0.0, 0.0, 0.0),
        dome: false,
        tuned: true,
    },
    Family {
        key: "shaft-pivot",
        description: "the hand pivots in two directions about a point of the shaft in 60 % of transfers",
        style: style(TransferTiming::Together, 0.6, 0.0, 0.0, 0.0),
        dome: false,
        tuned: true,
    },
    Family {
        key: "rotate-first",
        description: "rotate about the wrist, then translate",
        style: style(TransferTiming::RotateThenTranslate, 0.0, 0.0, 0.0, 0.0),
        dome: false,
        tuned: false,
    },
    Family {
        key: "translate-first",
        description: "translate, then rotate about the wrist",
        style: style(TransferTiming::TranslateThenRotate, 0.0, 0.0, 0.0, 0.0),
        dome: false,
        tuned: false,
    },
    Family {
        key: "hover",
        description: "slow hovering approaches, pivoting about the tip above the port, in 70 % of approaches",
        style: style(TransferTiming::Mixed, 0.0, 0.7, 0.0, 0.0),
        dome: false,
        tuned: false,
    },
    Family {
        key: "reinsert",
        description: "re-insertions into the same trocar in 50 % of cycles, mixed timings",
        style: style(TransferTiming::Mixed, 0.0, 0.0, 0.0, 0.5),
        dome: false,
        tuned: false,
    },
    Family {
        key: "mixed-dome",
        description: "every behaviour at once on random layouts (4 ports ≥ 9 cm apart on a dome)",
        style: style(TransferTiming::Mixed, 0.3, 0.3, 0.0, 0.3),
        dome: true,
        tuned: false,
    },
    Family {
        key: "aim",
        description: "aiming approaches: the axis pivots about the port while the tip advances to it, in 70 % of approaches",
        style: style(TransferTiming::Mixed, 0.0, 0.0, 0.7, 0.0),
        dome: false,
        tuned: false,
    },
];

/// What the family benchmark runs.
#[derive(Clone, Debug)]
pub struct FamilyOptions {
    /// Seeds (every family runs once per seed; the placement cycles with the seed).
    pub seeds: Vec<u64>,
    /// Insert/extract cycles per trace.
    pub cycles_per_trace: usize,
    /// Only the tuning families.
    pub tuning_only: bool,
    /// Detector parameters (paper and fast tables; see [`settings`]).
    pub detector: estimator::trocar::DetectorConfig,
}

impl Default for FamilyOptions {
    fn default() -> Self {
        Self { seeds: REPORT_SEEDS.to_vec(), cycles_per_trace: 100, tuning_only: false, detector: Default::default() }
    }
}

/// One family × setting, summed over the family's traces.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Cell {
    /// True insertions.
    pub insertions: usize,
    /// Detected at the right trocar before the true extraction.
    pub detected: usize,
    /// Outside→inside transitions while the truth is outside.
    pub false_outside: usize,
    /// Outside→inside transitions at the wrong place while the truth is inside.
    pub false_wrong_place: usize,
    /// Samples published inside, truly inside, with the fulcrum more than [`FAR_FULCRUM_M`]
    /// from the true pivot.
    pub far_samples: usize,
    /// Inside→outside transitions while the truth is inside, more than
    /// [`EARLY_EXTRACTION_S`] before the true extraction.
    pub spurious_extractions: usize,
    /// Inside→outside transitions while the truth is inside, at most [`EARLY_EXTRACTION_S`]
    /// before the true extraction (the tip within millimetres of the port: the fulcrum's
    /// error along the axis).
    pub early_extractions: usize,
    /// Insertion delays, seconds.
    pub insertion_delays_s: Vec<f64>,
    /// Motion-only insertion bounds of the insertions that have one, seconds.
    pub insertion_bounds_s: Vec<f64>,
    /// Extraction delays, seconds.
    pub extraction_delays_s: Vec<f64>,
    /// Traces whose final trocar list is exactly their true trocars.
    pub lists_exact: usize,
    /// Traces.
    pub traces: usize,
    /// Sample indices (trace, sample) of the false detections, for diagnosis.
    pub false_at: Vec<(usize, usize)>,
}

impl Cell {
    /// Adds another cell's counts and samples.
    pub fn add(&mut self, c: &Cell) {
        self.insertions += c.insertions;
        self.detected += c.detected;
        self.false_outside += c.false_outside;
        self.false_wrong_place += c.false_wrong_place;
        self.far_samples += c.far_samples;
        self.spurious_extractions += c.spurious_extractions;
        self.early_extractions += c.early_extractions;
        self.insertion_delays_s.extend(&c.insertion_delays_s);
        self.insertion_bounds_s.extend(&c.insertion_bounds_s);
        self.extraction_delays_s.extend(&c.extraction_delays_s);
        self.lists_exact += c.lists_exact;
        self.traces += c.traces;
        self.false_at.extend(&c.false_at);
    }

    /// Mean insertion delay over the mean motion-only bound (the main detection table's
    /// ratio).
    pub fn insertion_ratio(&self) -> f64 {
        let b = mean(&self.insertion_bounds_s);
        if b > 0.0 { mean(&self.insertion_delays_s) / b } else { f64::NAN }
    }
}

/// Results of one family.
#[derive(Clone, Debug)]
pub struct FamilyResult {
    /// The family.
    pub family: Family,
    /// One cell per setting, in [`settings`] order.
    pub cells: Vec<Cell>,
    /// Traces the twin could not run (the inverse kinematics did not converge), with the reason.
    pub skipped: Vec<String>,
}

/// The whole family benchmark.
#[derive(Clone, Debug)]
pub struct FamilyReport {
    /// Options.
    pub options: FamilyOptions,
    /// The settings (columns).
    pub settings: Vec<Setting>,
    /// Per family.
    pub families: Vec<FamilyResult>,
    /// Wall-clock, seconds.
    pub wall_s: f64,
}

/// Is `list` exactly the trocars of `trace` that were visited (one entry within
/// [`LIST_MATCH_M`] of each, nothing else)?
fn list_exact(trace: &Trace, list: &[nalgebra::Vector3<f64>]) -> bool {
    let visited: std::collections::BTreeSet<usize> = trace.events.iter().map(|e| e.trocar).collect();
    let trocars: Vec<nalgebra::Vector3<f64>> =
        trace.trocars_base_m.iter().map(|t| nalgebra::Vector3::new(t[0], t[1], t[2])).collect();
    if list.len() != visited.len() {
        return false;
    }
    visited.iter().all(|&i| list.iter().filter(|f| (*f - trocars[i]).norm() <= LIST_MATCH_M).count() == 1)
}

fn spec(family: &Family, seed: u64, cycles: usize) -> TraceSpec {
    TraceSpec {
        seed,
        cycles,
        placement: PLACEMENTS[(seed % PLACEMENTS.len() as u64) as usize],
        model_error: true,
        style: family.style,
        dome_seed: family.dome.then_some(seed),
    }
}

/// Runs the family benchmark; `progress` is called once per finished trace.
pub fn run_families(opts: &FamilyOptions, progress: &(dyn Fn() + Sync)) -> Result<FamilyReport, BenchError> {
    let started = std::time::Instant::now();
    let length = sim::twin::TwinConfig::default().scenario.instrument_length_m;
    let sets = settings(length, &opts.detector);
    let fams: Vec<Family> = FAMILIES.iter().filter(|f| f.tuned || !opts.tuning_only).copied().collect();
    let jobs: Vec<(usize, u64)> = (0..fams.len()).flat_map(|f| opts.seeds.iter().map(move |&s| (f, s))).collect();
    type Job = (usize, Result<Vec<Cell>, String>);
    let results: Vec<Result<Job, BenchError>> = jobs
        .par_iter()
        .map(|&(f, seed)| {
            let s = spec(&fams[f], seed, opts.cycles_per_trace);
            let trace = match generate(&s) {
                Ok(t) => t,
                Err(e) => {
                    progress();
                    return Ok((f, Err(format!("{} seed {seed}: {e}", fams[f].key))));
                }
            };
            let b = bounds(&trace);
            let mut cells = Vec::new();
            for set in &sets {
                let r = run(&trace, set, false)?;
                let a = analyse(&trace, &r);
                let mut c = Cell { traces: 1, insertions: a.score.insertions, ..Default::default() };
                c.false_outside = a.false_outside;
                c.false_wrong_place = a.score.false_detections - a.false_outside;
                c.false_at = a.score.false_detection_samples.iter().map(|&i| (seed as usize, i)).collect();
                let early_samples = (EARLY_EXTRACTION_S / 1e-3) as usize;
                for i in 1..r.detected.len().min(trace.lines.len()) {
                    if r.detected[i - 1].inside
                        && !r.detected[i].inside
                        && matches!(trace.states[i], TruthState::Inside { .. })
                    {
                        let next_out = trace.events.iter().find(|e| !e.insertion && e.sample >= i);
                        if next_out.is_some_and(|e| e.sample - i <= early_samples) {
                            c.early_extractions += 1;
                        } else {
                            c.spurious_extractions += 1;
                        }
                    }
                }
                for (ev, bound) in a.events.iter().zip(&b) {
                    if let Some(d) = ev.insertion_delay_s {
                        c.detected += 1;
                        c.insertion_delays_s.push(d);
                    }
                    // As the main detection table: the mean bound over the cycles that have
                    // one, the mean delay over the detected insertions.
                    if let Some(x) = bound.insertion_s {
                        c.insertion_bounds_s.push(x);
                    }
                    if let Some(d) = ev.extraction_delay_s {
                        c.extraction_delays_s.push(d);
                    }
                }
                c.far_samples = (0..r.detected.len().min(trace.lines.len()))
                    .filter(|&i| match (r.detected[i].fulcrum_base_m, trace.states[i], trace.pivots[i]) {
                        (Some(f), TruthState::Inside { .. }, Some(p)) => (f - p).norm() > FAR_FULCRUM_M,
                        _ => false,
                    })
                    .count();
                c.lists_exact = usize::from(list_exact(&trace, &r.final_trocars_base_m));
                cells.push(c);
            }
            progress();
            Ok((f, Ok(cells)))
        })
        .collect();
    let mut out: Vec<FamilyResult> = fams
        .iter()
        .map(|f| FamilyResult { family: *f, cells: vec![Cell::default(); sets.len()], skipped: Vec::new() })
        .collect();
    for r in results {
        let (f, cells) = r?;
        match cells {
            Ok(cells) => {
                for (acc, c) in out[f].cells.iter_mut().zip(&cells) {
                    acc.add(c);
                }
            }
            Err(reason) => out[f].skipped.push(reason),
        }
    }
    Ok(FamilyReport { options: opts.clone(), settings: sets, families: out, wall_s: started.elapsed().as_secs_f64() })
}

impl FamilyReport {
    /// The per-family tables as Markdown: one table per setting, a row per family, tuning
    /// families marked.
    pub fn markdown(&self) -> String {
        use std::fmt::Write as _;
        let mut s = String::new();
        let seeds: Vec<String> = self.options.seeds.iter().map(|x| x.to_string()).collect();
        let _ = writeln!(
            s,
            "Seeds {} ({} cycles per trace, one trace per family and seed); the fast mode's thresholds were tuned on the families marked **tuned**, with seeds {:?} only. Wall-clock {:.0} s.\n",
            seeds.join(", "),
            self.options.cycles_per_trace,
            TUNING_SEEDS,
            self.wall_s
        );
        let _ = writeln!(s, "| family | what the surgeon does | used for tuning |\n|---|---|---|");
        for f in &self.families {
            let _ = writeln!(
                s,
                "| {} | {} | {} |",
                f.family.key,
                f.family.description,
                if f.family.tuned { "**tuned**" } else { "held out" }
            );
        }
        for (k, set) in self.settings.iter().enumerate() {
            let _ = writeln!(s, "\n**{}**\n", set.label);
            let _ = writeln!(
                s,
                "| family | cycles | detected | false outside | false at wrong place | samples inside > 20 mm off | spurious extractions (early ≤ 50 ms) | insertion delay mean (ms) | / motion-only bound | extraction delay mean (ms) | trocar list exact |"
            );
            let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|---|");
            let mut held = Cell::default();
            for f in &self.families {
                let c = &f.cells[k];
                if !f.family.tuned {
                    held.add(c);
                }
                let name = if f.family.tuned { format!("{} (tuned)", f.family.key) } else { f.family.key.to_string() };
                let _ = writeln!(s, "{}", row(&name, c, set.key != "paper"));
            }
            let _ = writeln!(s, "{}", row("**all held-out families**", &held, set.key != "paper"));
        }
        let skipped: Vec<&String> = self.families.iter().flat_map(|f| &f.skipped).collect();
        if !skipped.is_empty() {
            let _ = writeln!(
                s,
                "\nTraces the twin could not run (a line of the planned motion lies beyond the reach of the miscalibrated true arm, which the nominal arm the surgeon was planned on reaches: the twin's inverse kinematics stops micrometres short and the trace ends), not counted:"
            );
            for r in skipped {
                let _ = writeln!(s, "- {r}");
            }
        }
        s
    }
}

fn row(name: &str, c: &Cell, has_list: bool) -> String {
    // A family whose every trace was skipped has no delays: say so, never print NaN.
    if c.traces == 0 {
        return format!("| {name} | 0 | no trace ran | | | | | | | | |");
    }
    format!(
        "| {} | {} | {}/{} | {} | {} | {} | {} ({}) | {:.0} | {:.2} | {:.0} | {} |",
        name,
        c.insertions,
        c.detected,
        c.insertions,
        c.false_outside,
        c.false_wrong_place,
        c.far_samples,
        c.spurious_extractions,
        c.early_extractions,
        mean(&c.insertion_delays_s) * 1e3,
        c.insertion_ratio(),
        mean(&c.extraction_delays_s) * 1e3,
        if has_list { format!("{}/{}", c.lists_exact, c.traces) } else { "n/a".into() },
    )
}
