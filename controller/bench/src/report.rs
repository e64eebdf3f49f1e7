//! Aggregating the detection benchmark over traces, and writing it as Markdown.

use std::collections::BTreeMap;
use std::fmt::Write as _;

use nalgebra::Vector3;
use rayon::prelude::*;
use sim::score::{mean, quantile};

use super::bound::{CycleBound, bounds};
use super::detection::{Analysis, Run, Setting, StepTimes, analyse, run, settings};
use super::trace::{PLACEMENTS, Placement, Trace, TraceError, TraceSpec, generate};

/// What the detection benchmark runs.
#[derive(Clone, Debug)]
pub struct DetectionOptions {
    /// Scenario seeds; every seed runs in every placement.
    pub seeds: Vec<u64>,
    /// Insert/extract cycles per trace.
    pub cycles_per_trace: usize,
    /// Placements of the trocar set.
    pub placements: Vec<Placement>,
    /// Seconds of the first trace kept for the timeline plot.
    pub timeline_s: f64,
    /// Detector parameters (paper and fast tables; see [`settings`]).
    pub detector: estimator::trocar::DetectorConfig,
    /// Simulate the arm's calibration error (true by default).
    pub model_error: bool,
}

impl Default for DetectionOptions {
    fn default() -> Self {
        Self {
            seeds: vec![101, 102, 103, 104],
            cycles_per_trace: 90,
            placements: PLACEMENTS.to_vec(),
            timeline_s: 90.0,
            detector: Default::default(),
            model_error: true,
        }
    }
}

/// Per-setting aggregate.
#[derive(Clone, Debug)]
pub struct SettingResult {
    /// The setting.
    pub setting: Setting,
    /// One analysis per trace, in trace order.
    pub analyses: Vec<Analysis>,
    /// Step times over every trace.
    pub step_times: StepTimes,
    /// Allocations over every step.
    pub allocations: u64,
    /// Steps over every trace.
    pub steps: u64,
}

/// One setting's timeline: its key, inside (1) or not (0) per sample, and the localisation
/// error per sample (metres; `None` when not inside).
pub type SettingTimeline = (&'static str, Vec<u8>, Vec<Option<f64>>);

/// The timeline of the first trace's beginning, for the plot.
#[derive(Clone, Debug, Default)]
pub struct Timeline {
    /// Seconds since the trace start, per sample.
    pub t_s: Vec<f64>,
    /// True inside (trocar index + 1, 0 outside).
    pub truth: Vec<u8>,
    /// Per setting key: detector inside (1) or not (0), and the localisation error (m).
    pub detected: Vec<SettingTimeline>,
}

/// The whole detection benchmark.
#[derive(Clone, Debug)]
pub struct DetectionReport {
    /// Options it ran with.
    pub options: DetectionOptions,
    /// Trace specs, in order.
    pub specs: Vec<TraceSpec>,
    /// Simulated duration, seconds, over every trace.
    pub simulated_s: f64,
    /// Motion-only bounds, per trace.
    pub bounds: Vec<Vec<CycleBound>>,
    /// Per setting.
    pub settings: Vec<SettingResult>,
    /// Timeline of the first trace.
    pub timeline: Timeline,
    /// Wall-clock of the run, seconds.
    pub wall_s: f64,
}

struct TraceResult {
    spec: TraceSpec,
    duration_s: f64,
    bounds: Vec<CycleBound>,
    runs: Vec<(Analysis, StepTimes, u64, u64)>,
    timeline: Option<(Timeline, Trace)>,
}

fn timeline(trace: &Trace, sets: &[Setting], runs: &[Run], seconds: f64) -> Timeline {
    let n = ((seconds / 1e-3) as usize).min(trace.lines.len());
    let step = 10; // 100 Hz is plenty for a plot
    let idx: Vec<usize> = (0..n).step_by(step).collect();
    let truth = idx
        .iter()
        .map(|&i| match trace.states[i] {
            sim::scenario::TruthState::Inside { index } => index as u8 + 1,
            sim::scenario::TruthState::Outside => 0,
        })
        .collect();
    let detected = sets
        .iter()
        .zip(runs)
        .map(|(s, r)| {
            let inside = idx.iter().map(|&i| u8::from(r.detected[i].inside)).collect();
            let err = idx.iter().map(|&i| Some((r.detected[i].fulcrum_base_m? - trace.pivots[i]?).norm())).collect();
            (s.key, inside, err)
        })
        .collect();
    Timeline { t_s: idx.iter().map(|&i| i as f64 * 1e-3).collect(), truth, detected }
}

/// Why the benchmark failed.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// A trace could not be generated.
    #[error(transparent)]
    Trace(#[from] TraceError),
    /// A detector configuration was refused.
    #[error("detector configuration: {0}")]
    Config(#[from] estimator::trocar::ConfigError),
}

/// Runs the detection benchmark. `progress` is called once per finished trace.
pub fn run_detection(opts: &DetectionOptions, progress: &(dyn Fn() + Sync)) -> Result<DetectionReport, BenchError> {
    let started = std::time::Instant::now();
    let specs: Vec<TraceSpec> = opts
        .placements
        .iter()
        .flat_map(|p| {
            opts.seeds.iter().map(move |&seed| TraceSpec {
                seed,
                cycles: opts.cycles_per_trace,
                placement: *p,
                model_error: opts.model_error,
                style: Default::default(),
                dome_seed: None,
            })
        })
        .collect();
    let length = sim::twin::TwinConfig::default().scenario.instrument_length_m;
    let sets = settings(length, &opts.detector);
    let results: Vec<Result<TraceResult, BenchError>> = specs
        .par_iter()
        .enumerate()
        .map(|(k, spec)| {
            let trace = generate(spec)?;
            let b = bounds(&trace);
            let mut runs = Vec::new();
            let mut raw = Vec::new();
            for s in &sets {
                let r = run(&trace, s, false)?;
                runs.push((analyse(&trace, &r), r.step_times.clone(), r.allocations, r.steps));
                raw.push(r);
            }
            let tl = (k == 0).then(|| (timeline(&trace, &sets, &raw, opts.timeline_s), trace.clone()));
            progress();
            Ok(TraceResult { spec: *spec, duration_s: trace.duration_s(), bounds: b, runs, timeline: tl })
        })
        .collect();
    let mut settings_out: Vec<SettingResult> = sets
        .iter()
        .map(|s| SettingResult {
            setting: s.clone(),
            analyses: Vec::new(),
            step_times: StepTimes::default(),
            allocations: 0,
            steps: 0,
        })
        .collect();
    let mut all_bounds = Vec::new();
    let mut simulated_s = 0.0;
    let mut tl = Timeline::default();
    let mut first_trace = None;
    let mut done_specs = Vec::new();
    for r in results {
        let r = r?;
        simulated_s += r.duration_s;
        all_bounds.push(r.bounds);
        done_specs.push(r.spec);
        if let Some((t, trace)) = r.timeline {
            tl = t;
            first_trace = Some(trace);
        }
        for (out, (a, _, allocs, steps)) in settings_out.iter_mut().zip(r.runs) {
            out.analyses.push(a);
            out.allocations += allocs;
            out.steps += steps;
        }
    }
    // Step times: one timed pass per setting over the first trace, on this thread alone
    // (the scoring passes above ran in parallel, which would inflate the tails).
    if let Some(trace) = &first_trace {
        for out in &mut settings_out {
            let r = run(trace, &out.setting, true)?;
            out.step_times.merge(&r.step_times);
        }
    }
    Ok(DetectionReport {
        options: opts.clone(),
        specs: done_specs,
        simulated_s,
        bounds: all_bounds,
        settings: settings_out,
        timeline: tl,
        wall_s: started.elapsed().as_secs_f64(),
    })
}

/// Summary statistics of a sample (seconds or metres).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct Stats {
    /// Values.
    pub n: usize,
    /// Mean.
    pub mean: f64,
    /// Median.
    pub p50: f64,
    /// 95th percentile.
    pub p95: f64,
    /// Largest.
    pub max: f64,
}

impl Stats {
    /// "mean / p50 / p95 / max" of seconds, in whole milliseconds.
    pub fn ms_row(&self) -> String {
        let ms = |x: f64| format!("{:.0}", x * 1e3);
        format!("{} / {} / {} / {}", ms(self.mean), ms(self.p50), ms(self.p95), ms(self.max))
    }

    /// Statistics of `v`.
    pub fn of(v: &[f64]) -> Self {
        Self {
            n: v.len(),
            mean: mean(v),
            p50: quantile(v, 0.5),
            p95: quantile(v, 0.95),
            max: v.iter().copied().fold(0.0, f64::max),
        }
    }
}

/// The headline figures of one setting.
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct Headline {
    /// Setting key.
    pub key: String,
    /// True insertions.
    pub insertions: usize,
    /// Insertions detected.
    pub insertions_detected: usize,
    /// True extractions.
    pub extractions: usize,
    /// Extractions missed.
    pub extractions_missed: usize,
    /// False detections (outside, or wrong trocar).
    pub false_detections: usize,
    /// Of which while outside.
    pub false_outside: usize,
    /// Spurious extractions (declared while the truth is inside).
    pub false_extractions: usize,
    /// Distinct trocar ids used, summed over traces (4 trocars per trace).
    pub distinct_ids: usize,
    /// Insertion delays, seconds.
    pub insertion: Stats,
    /// Re-insertion delays (a trocar visited before in the trace), seconds.
    pub reinsertion: Stats,
    /// Extraction delays, seconds.
    pub extraction: Stats,
    /// Localisation error at first detection, metres.
    pub first_error: Stats,
    /// Steady-state localisation error, metres.
    pub steady_error: Stats,
    /// RMS localisation error over every inside/inside sample, metres.
    pub rms_error_m: f64,
    /// Step time, nanoseconds: median, p99, p99.9, max.
    pub step_ns: [f64; 4],
    /// Allocations per step.
    pub allocations_per_step: f64,
}

impl SettingResult {
    /// Headline figures.
    pub fn headline(&self) -> Headline {
        let mut h = Headline { key: self.setting.key.to_string(), ..Default::default() };
        let mut ins = Vec::new();
        let mut reins = Vec::new();
        let mut ext = Vec::new();
        let mut first = Vec::new();
        let mut steady = Vec::new();
        let mut sq = 0.0;
        let mut sq_n = 0usize;
        for a in &self.analyses {
            h.insertions += a.score.insertions;
            h.insertions_detected += a.score.insertions_detected;
            h.extractions += a.score.extractions;
            h.extractions_missed += a.score.extractions - a.score.extractions_detected;
            h.false_detections += a.score.false_detections;
            h.false_outside += a.false_outside;
            h.false_extractions += a.false_extractions;
            h.distinct_ids += a.distinct_ids;
            for e in &a.events {
                if let Some(d) = e.insertion_delay_s {
                    ins.push(d);
                    if e.revisit {
                        reins.push(d);
                    }
                }
                if let Some(d) = e.extraction_delay_s {
                    ext.push(d);
                }
                if let Some(f) = e.first_error_m {
                    first.push(f);
                }
            }
            steady.extend_from_slice(&a.steady_errors_m);
            sq += a.all_errors_m.iter().map(|e| e * e).sum::<f64>();
            sq_n += a.all_errors_m.len();
        }
        h.insertion = Stats::of(&ins);
        h.reinsertion = Stats::of(&reins);
        h.extraction = Stats::of(&ext);
        h.first_error = Stats::of(&first);
        h.steady_error = Stats::of(&steady);
        h.rms_error_m = if sq_n > 0 { (sq / sq_n as f64).sqrt() } else { 0.0 };
        let st = &self.step_times;
        h.step_ns = [st.quantile_ns(0.5), st.quantile_ns(0.99), st.quantile_ns(0.999), st.max_ns() as f64];
        h.allocations_per_step = if self.steps > 0 { self.allocations as f64 / self.steps as f64 } else { 0.0 };
        h
    }

    /// Insertion delays, seconds (all detected insertions).
    pub fn insertion_delays(&self) -> Vec<f64> {
        self.analyses.iter().flat_map(|a| a.events.iter().filter_map(|e| e.insertion_delay_s)).collect()
    }

    /// Extraction delays, seconds.
    pub fn extraction_delays(&self) -> Vec<f64> {
        self.analyses.iter().flat_map(|a| a.events.iter().filter_map(|e| e.extraction_delay_s)).collect()
    }
}

impl DetectionReport {
    /// Insertion and extraction bounds, seconds (those that exist).
    /// RMS of the localisation floor over every inside sample, metres.
    pub fn floor_rms_m(&self) -> f64 {
        let v: Vec<f64> = self.bounds.iter().flatten().flat_map(|b| b.floor_sq_m2.iter().copied()).collect();
        if v.is_empty() { 0.0 } else { (v.iter().sum::<f64>() / v.len() as f64).sqrt() }
    }

    /// Insertion and extraction bounds, seconds (those that exist), and the number of cycles
    /// without one.
    pub fn bound_stats(&self) -> (Stats, Stats, usize, usize) {
        let ins: Vec<f64> = self.bounds.iter().flatten().filter_map(|b| b.insertion_s).collect();
        let ext: Vec<f64> = self.bounds.iter().flatten().filter_map(|b| b.extraction_s).collect();
        let total = self.bounds.iter().map(Vec::len).sum::<usize>();
        (Stats::of(&ins), Stats::of(&ext), total - ins.len(), total - ext.len())
    }

    /// Paper-style Table III: per setting, the distance between every pair of trocars in each
    /// placement (centroid of the final fulcrum of every insertion, grouped by true trocar),
    /// and the mean and standard deviation across placements, plus the true distance.
    pub fn consistency(&self, key: &str) -> Vec<(String, Vec<f64>, f64, f64, f64)> {
        let Some(set) = self.settings.iter().find(|s| s.setting.key == key) else { return Vec::new() };
        // (placement index, trocar) -> sum, count
        let mut acc: BTreeMap<(usize, usize), (Vector3<f64>, usize)> = BTreeMap::new();
        for (spec, a) in self.specs.iter().zip(&set.analyses) {
            let p = self.options.placements.iter().position(|p| p.name == spec.placement.name).unwrap_or(0);
            for e in &a.events {
                if let Some(f) = e.final_fulcrum_base_m {
                    let entry = acc.entry((p, e.trocar)).or_insert((Vector3::zeros(), 0));
                    entry.0 += f;
                    entry.1 += 1;
                }
            }
        }
        let trocars = sim::twin::DEFAULT_TROCARS_BASE_M.len();
        let mut rows = Vec::new();
        for i in 0..trocars {
            for j in i + 1..trocars {
                let mut d = Vec::new();
                for p in 0..self.options.placements.len() {
                    if let (Some(a), Some(b)) = (acc.get(&(p, i)), acc.get(&(p, j))) {
                        d.push((a.0 / a.1 as f64 - b.0 / b.1 as f64).norm());
                    }
                }
                let m = mean(&d);
                let sd = if d.len() > 1 {
                    (d.iter().map(|x| (x - m) * (x - m)).sum::<f64>() / (d.len() - 1) as f64).sqrt()
                } else {
                    0.0
                };
                let t = sim::twin::DEFAULT_TROCARS_BASE_M;
                let truth = (Vector3::from(t[i]) - Vector3::from(t[j])).norm();
                rows.push((format!("T{}T{}", i + 1, j + 1), d, m, sd, truth));
            }
        }
        rows
    }

    /// The Markdown report (tables only; the caller adds the plots' links).
    pub fn markdown(&self) -> String {
        let mut s = String::new();
        let heads: Vec<Headline> = self.settings.iter().map(SettingResult::headline).collect();
        let (bi, be, bi_none, be_none) = self.bound_stats();
        let cycles: usize = heads.first().map_or(0, |h| h.insertions);
        let _ = writeln!(
            s,
            "{} traces ({} seeds × {} placements), {} insert/extract cycles, {:.0} min of simulated motion; \
             benchmark wall-clock {:.0} s.\n",
            self.specs.len(),
            self.options.seeds.len(),
            self.options.placements.len(),
            cycles,
            self.simulated_s / 60.0,
            self.wall_s
        );
        let _ = writeln!(s, "| | {} |", self.settings.iter().map(|x| x.setting.label).collect::<Vec<_>>().join(" | "));
        let _ = writeln!(s, "|---|{}", "---|".repeat(self.settings.len()));
        let row = |s: &mut String, name: &str, f: &dyn Fn(&Headline) -> String| {
            let _ = writeln!(s, "| {name} | {} |", heads.iter().map(f).collect::<Vec<_>>().join(" | "));
        };
        let ms = |x: f64| format!("{:.0}", x * 1e3);
        let mm = |x: f64| format!("{:.2}", x * 1e3);
        row(&mut s, "insertions detected", &|h| format!("{}/{}", h.insertions_detected, h.insertions));
        row(&mut s, "false detections (while outside)", &|h| format!("{} ({})", h.false_detections, h.false_outside));
        row(&mut s, "missed extractions", &|h| format!("{}/{}", h.extractions_missed, h.extractions));
        row(&mut s, "spurious extractions (truth inside)", &|h| h.false_extractions.to_string());
        row(&mut s, "trocar ids used (4 trocars per trace)", &|h| {
            format!("{:.1} per trace", h.distinct_ids as f64 / self.specs.len().max(1) as f64)
        });
        row(&mut s, "insertion delay mean / p50 / p95 / max (ms)", &|h| h.insertion.ms_row());
        row(&mut s, "re-insertion delay mean / p95 (ms)", &|h| {
            format!("{} / {}", ms(h.reinsertion.mean), ms(h.reinsertion.p95))
        });
        row(&mut s, "extraction delay mean / p50 / p95 / max (ms)", &|h| h.extraction.ms_row());
        row(&mut s, "error at first detection mean / p95 (mm)", &|h| {
            format!("{} / {}", mm(h.first_error.mean), mm(h.first_error.p95))
        });
        row(&mut s, "steady-state error mean / p95 (mm)", &|h| {
            format!("{} / {}", mm(h.steady_error.mean), mm(h.steady_error.p95))
        });
        row(&mut s, "localisation RMS, all inside samples (mm)", &|h| mm(h.rms_error_m));
        row(&mut s, "step time median / p99 / p99.9 / max (ns)", &|h| {
            format!("{:.0} / {:.0} / {:.0} / {:.0}", h.step_ns[0], h.step_ns[1], h.step_ns[2], h.step_ns[3])
        });
        row(&mut s, "allocations per step", &|h| format!("{}", h.allocations_per_step));
        let _ = writeln!(s);
        let _ = writeln!(
            s,
            "Motion-only bound (`controller/bench/src/bound.rs`): insertion mean {} ms (p50 {}, p95 {}; {} cycles \
             where the motion never located the fulcrum within 5 mm of the cycle's own least-squares point), extraction (geometry only) mean {} ms (p50 \
             {}, p95 {}; {} without one).\n",
            ms(bi.mean),
            ms(bi.p50),
            ms(bi.p95),
            bi_none,
            ms(be.mean),
            ms(be.p50),
            ms(be.p95),
            be_none
        );
        let _ = writeln!(
            s,
            "Localisation floor: a fixed point fitted to all of a cycle's lines misses the moving true pivot by \
             {} mm RMS (arm calibration error and trocar compliance; no estimator can remove them from the \
             lines).\n",
            mm(self.floor_rms_m())
        );
        let _ = writeln!(s, "| mean delay / mean motion-only bound | insertion | extraction |");
        let _ = writeln!(s, "|---|---|---|");
        for h in &heads {
            let _ = writeln!(
                s,
                "| {} | {:.2} | {:.2} |",
                h.key,
                h.insertion.mean / bi.mean.max(1e-9),
                h.extraction.mean / be.mean.max(1e-9)
            );
        }
        let _ = writeln!(s);
        for key in ["paper", "fast"] {
            let rows = self.consistency(key);
            let names: Vec<&str> = self.options.placements.iter().map(|p| p.name).collect();
            let _ = writeln!(s, "Trocar inter-distances, {key} mode (centroids of the final fulcrums, metres):\n");
            let _ = writeln!(s, "| | {} | mean | std | true |", names.join(" | "));
            let _ = writeln!(s, "|---|{}---|---|---|", "---|".repeat(names.len()));
            for (name, d, m, sd, t) in rows {
                let cells: Vec<String> = d.iter().map(|x| format!("{x:.4}")).collect();
                let _ = writeln!(s, "| d{name} | {} | {m:.4} | {sd:.1e} | {t:.4} |", cells.join(" | "));
            }
            let _ = writeln!(s);
        }
        s
    }
}
