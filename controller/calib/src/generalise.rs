//! The generalisation protocol (`comanip-calib sweep --geometries N`): both pipelines on
//! random valid scene geometries ([`sim::calib::random_geometry`]), on a tuning set and a
//! held-out set of geometry seeds, per noise reading and σ, with the Cramér-Rao bound of each
//! geometry's kept lines. Writes `generalisation.md` (`docs/calibration.md`).
//!
//! A trial of ours counts as the CLI counts it (`comanip-calib calibrate --pipeline ours`):
//! returned (exit 0) when it gives a pose and its selection-aware stage modelled the data;
//! refused (non-zero, typed) otherwise. A mirror is a returned pose more than 90° from the
//! truth.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use estimator::calib::crb::cramer_rao_bound;
use estimator::calib::ours::{OursConfig, solve_ours_prepared};
use estimator::calib::paper::{PaperConfig, solve_paper_prepared};
use estimator::calib::prepare::prepare;
use estimator::calib::{KinematicNoise, PoseErrors, pose_errors};
use rayon::prelude::*;
use sim::calib::{CalibProtocol, GeometryDraw, NoiseUnits, RandomGeometryError, generate_calibration, random_geometry};

/// What to run.
#[derive(Clone, Debug)]
pub struct GeneralisationOptions {
    /// Geometries per set (tuning and held-out each).
    pub geometries: usize,
    /// Trials per geometry and condition.
    pub trials: usize,
    /// Geometry `i` of the tuning set is drawn with seed `tuning_seed + i`.
    pub tuning_seed: u64,
    /// Geometry `i` of the held-out set is drawn with seed `held_out_seed + i`.
    pub held_out_seed: u64,
    /// Trial `k` uses noise seed `trial_seed + k`.
    pub trial_seed: u64,
    /// `(reading, σ)` conditions.
    pub conditions: Vec<(NoiseUnits, f64)>,
    /// Skip the tuning set.
    pub held_out_only: bool,
}

impl GeneralisationOptions {
    /// The protocol: 20 geometries per set × 30 trials; mm at σ = 0.01, 0.02; m at
    /// σ = 0.005, 0.01, 0.014, 0.02. Tuning seeds 9000.. (the geometries looked at while
    /// developing), held-out 7000.. (not looked at before the reported run), trials 1000...
    pub fn full(geometries: usize) -> Self {
        Self {
            geometries,
            trials: 30,
            tuning_seed: 9000,
            held_out_seed: 7000,
            trial_seed: 1000,
            conditions: vec![
                (NoiseUnits::Millimetre, 0.01),
                (NoiseUnits::Millimetre, 0.02),
                (NoiseUnits::Metre, 0.005),
                (NoiseUnits::Metre, 0.01),
                (NoiseUnits::Metre, 0.014),
                (NoiseUnits::Metre, 0.02),
            ],
            held_out_only: false,
        }
    }
}

/// Why the protocol could not run.
#[derive(Debug, thiserror::Error)]
pub enum GeneralisationError {
    /// No valid geometry could be drawn for a seed.
    #[error(transparent)]
    Geometry(#[from] RandomGeometryError),
    /// The held-out and tuning geometry seeds overlap: a geometry would be in both sets.
    #[error(
        "the held-out geometries (seeds {held_out}..{}) and the tuning geometries (seeds {tuning}..{}) overlap",
        held_out + n,
        tuning + n
    )]
    Overlap {
        /// The held-out set's first seed.
        held_out: u64,
        /// The tuning set's first seed.
        tuning: u64,
        /// Geometries per set.
        n: u64,
    },
    /// A file could not be written.
    #[error("cannot write {path}: {source}")]
    Write {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
}

/// Our pipeline's outcome in one trial, as the CLI reports it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum OursOutcome {
    /// A pose with exit 0.
    Returned(PoseErrors),
    /// A typed refusal: `"ambiguous"`, `"selection"` (the selection-aware stage cannot model
    /// the data), `"unexplained"` (no candidate puts the shafts where an instrument can be;
    /// counted with `"other"` in the tables) or `"other"` (degenerate, no convergence).
    Refused(&'static str),
}

/// One trial.
#[derive(Clone, Copy, Debug)]
pub struct GenTrial {
    /// Paper pipeline errors (None: it failed).
    pub paper: Option<PoseErrors>,
    /// Ours.
    pub ours: OursOutcome,
}

/// One geometry under one condition.
#[derive(Clone, Debug)]
pub struct GeometryResult {
    /// The geometry.
    pub draw: GeometryDraw,
    /// Its trials.
    pub trials: Vec<GenTrial>,
    /// CRB of the noiseless geometry's kept lines: RMS translation (mm), rotation (°).
    pub crb: Option<[f64; 2]>,
}

fn rms(v: &[f64]) -> f64 {
    if v.is_empty() { f64::NAN } else { (v.iter().map(|x| x * x).sum::<f64>() / v.len() as f64).sqrt() }
}

fn median(v: &[f64]) -> f64 {
    let mut s: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    if s.is_empty() {
        return f64::NAN;
    }
    s.sort_by(|a, b| a.total_cmp(b));
    let n = s.len();
    if n % 2 == 1 { s[n / 2] } else { 0.5 * (s[n / 2 - 1] + s[n / 2]) }
}

/// The generalisation protocol's trial on geometry `g`: the 3⁴×3² grid, noise `sigma` in
/// `units` per frame (Eq. 11), no pixel noise, noise seed `seed` (trial k: 1000 + k).
pub fn protocol(g: &GeometryDraw, units: NoiseUnits, sigma: f64, seed: u64) -> CalibProtocol {
    CalibProtocol { geometry: g.geometry, n_e: 3, n_t: 3, sigma, units, pixel_sigma_px: 0.0, seed }
}

/// One trial: generate, both pipelines.
pub fn gen_trial(g: &GeometryDraw, units: NoiseUnits, sigma: f64, seed: u64) -> GenTrial {
    let Ok(d) = generate_calibration(&protocol(g, units, sigma, seed)) else {
        return GenTrial { paper: None, ours: OursOutcome::Refused("other") };
    };
    let Ok(set) = prepare(&d.setup, &d.observations) else {
        return GenTrial { paper: None, ours: OursOutcome::Refused("other") };
    };
    let paper = solve_paper_prepared(&set, &PaperConfig::default()).ok().map(|r| pose_errors(&r.pose, &d.truth));
    let ours = match solve_ours_prepared(&set, &OursConfig { noise: d.noise, ..OursConfig::default() }) {
        Ok(r) if r.selection_refused.is_none() => OursOutcome::Returned(pose_errors(&r.pose, &d.truth)),
        Ok(_) => OursOutcome::Refused("selection"),
        Err(estimator::calib::ours::OursError::Ambiguous { .. }) => OursOutcome::Refused("ambiguous"),
        Err(estimator::calib::ours::OursError::ShaftsNotExplained { .. }) => OursOutcome::Refused("unexplained"),
        Err(_) => OursOutcome::Refused("other"),
    };
    GenTrial { paper, ours }
}

fn crb_of(g: &GeometryDraw, units: NoiseUnits, sigma: f64) -> Option<[f64; 2]> {
    let clean = generate_calibration(&protocol(g, units, 0.0, 0)).ok()?;
    let noise = KinematicNoise { rot_rad: sigma, trans_m: sigma * units.metres(), pixel_px: 0.0 };
    let c = cramer_rao_bound(&clean.setup, &clean.observations, &clean.truth, &noise).ok()?;
    Some([c.translation_rms_m * 1e3, c.rotation_rms_rad.to_degrees()])
}

/// Runs one set of geometries under every condition (in parallel over trials).
pub fn run_set(draws: &[GeometryDraw], opts: &GeneralisationOptions) -> Vec<((NoiseUnits, f64), Vec<GeometryResult>)> {
    opts.conditions
        .iter()
        .map(|&(units, sigma)| {
            let jobs: Vec<(usize, usize)> =
                (0..draws.len()).flat_map(|g| (0..opts.trials).map(move |k| (g, k))).collect();
            let trials: Vec<GenTrial> =
                jobs.par_iter().map(|&(g, k)| gen_trial(&draws[g], units, sigma, opts.trial_seed + k as u64)).collect();
            let crbs: Vec<Option<[f64; 2]>> = draws.par_iter().map(|g| crb_of(g, units, sigma)).collect();
            let per_geometry = draws
                .iter()
                .enumerate()
                .map(|(i, g)| GeometryResult {
                    draw: *g,
                    trials: trials[i * opts.trials..(i + 1) * opts.trials].to_vec(),
                    crb: crbs[i],
                })
                .collect();
            ((units, sigma), per_geometry)
        })
        .collect()
}

/// A geometry class: its name and membership test.
pub type GeometryClass = (&'static str, fn(&GeometryDraw) -> bool);

/// The geometry classes of the table: all, by RCM distance, by tool-to-scope angle, by lens.
pub fn classes() -> Vec<GeometryClass> {
    vec![
        ("all", |_| true),
        ("RCM distance < 165 mm", |g| g.rcm_distance_m < 0.165),
        ("RCM distance ≥ 165 mm", |g| g.rcm_distance_m >= 0.165),
        ("tool-scope angle < 45°", |g| g.tool_scope_angle_rad < 45f64.to_radians()),
        ("tool-scope angle ≥ 45°", |g| g.tool_scope_angle_rad >= 45f64.to_radians()),
        ("distorted", |g| g.distorted),
        ("undistorted", |g| !g.distorted),
    ]
}

/// Aggregates of a class under a condition.
#[derive(Clone, Copy, Debug)]
pub struct ClassSummary {
    /// Geometries in the class.
    pub geometries: usize,
    /// Trials.
    pub trials: usize,
    /// Median over geometries of the paper's RMS error: mm, °.
    pub paper: [f64; 2],
    /// Median over geometries of ours' RMS error over its returned trials: mm, °.
    pub ours: [f64; 2],
    /// Median over geometries of the CRB: mm, °.
    pub crb: [f64; 2],
    /// Median over geometries of ours' RMS over the CRB: translation, rotation.
    pub ratio: [f64; 2],
    /// Ours returned a pose more than 90° off with exit 0.
    pub mirrors: usize,
    /// Ours refused (typed, non-zero).
    pub refused: usize,
    /// Of which: ambiguous, selection-aware stage refused, other.
    pub refused_by: [usize; 3],
    /// The paper's pipeline failed or was more than 90° off.
    pub paper_bad: usize,
}

/// Summarises the geometries `keep` accepts.
pub fn summarise_class(results: &[GeometryResult], keep: fn(&GeometryDraw) -> bool) -> ClassSummary {
    let sel: Vec<&GeometryResult> = results.iter().filter(|r| keep(&r.draw)).collect();
    let mut paper = [Vec::new(), Vec::new()];
    let mut ours = [Vec::new(), Vec::new()];
    let mut crb = [Vec::new(), Vec::new()];
    let mut ratio = [Vec::new(), Vec::new()];
    let (mut mirrors, mut refused, mut paper_bad, mut trials) = (0, 0, 0, 0);
    let mut refused_by = [0; 3];
    let deg = |e: &PoseErrors| e.rotation_rad.to_degrees();
    for r in &sel {
        trials += r.trials.len();
        let p: Vec<PoseErrors> = r.trials.iter().filter_map(|t| t.paper).collect();
        paper_bad += r.trials.iter().filter(|t| t.paper.is_none_or(|e| deg(&e) > 90.0)).count();
        let o: Vec<PoseErrors> = r
            .trials
            .iter()
            .filter_map(|t| match t.ours {
                OursOutcome::Returned(e) => Some(e),
                OursOutcome::Refused(_) => None,
            })
            .collect();
        refused += r.trials.len() - o.len();
        for t in &r.trials {
            if let OursOutcome::Refused(k) = t.ours {
                let i = ["ambiguous", "selection", "other"].iter().position(|x| *x == k).unwrap_or(2);
                refused_by[i] += 1;
            }
        }
        mirrors += o.iter().filter(|e| deg(e) > 90.0).count();
        let pt = [
            rms(&p.iter().map(|e| e.translation_m * 1e3).collect::<Vec<_>>()),
            rms(&p.iter().map(deg).collect::<Vec<_>>()),
        ];
        let ot = [
            rms(&o.iter().map(|e| e.translation_m * 1e3).collect::<Vec<_>>()),
            rms(&o.iter().map(deg).collect::<Vec<_>>()),
        ];
        for k in 0..2 {
            paper[k].push(pt[k]);
            ours[k].push(ot[k]);
            if let Some(c) = r.crb {
                crb[k].push(c[k]);
                ratio[k].push(ot[k] / c[k]);
            }
        }
    }
    let m = |v: &[Vec<f64>; 2]| [median(&v[0]), median(&v[1])];
    ClassSummary {
        geometries: sel.len(),
        trials,
        paper: m(&paper),
        ours: m(&ours),
        crb: m(&crb),
        ratio: m(&ratio),
        mirrors,
        refused,
        refused_by,
        paper_bad,
    }
}

fn f(v: f64, digits: usize) -> String {
    if v.is_finite() { format!("{v:.digits$}") } else { "–".into() }
}

/// The Markdown table of one set.
pub fn table(set: &[((NoiseUnits, f64), Vec<GeometryResult>)]) -> String {
    let mut s = String::from(
        "| ρ unit | σ | geometry class | geometries | trials | paper RMS t mm / R ° | ours RMS t mm / R ° | CRB t mm / R ° | ours/CRB t | ours/CRB R | ours mirror, exit 0 | ours refused (ambiguous / selection / other) | paper failed or >90° |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for ((units, sigma), results) in set {
        for (name, keep) in classes() {
            let c = summarise_class(results, keep);
            if c.geometries == 0 {
                continue;
            }
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {} | {} / {} | {} / {} | {} / {} | {} | {} | {} | {} ({} %: {} / {} / {}) | {} |",
                units.name(),
                crate::sweep::sigma_label(*sigma),
                name,
                c.geometries,
                c.trials,
                f(c.paper[0], 2),
                f(c.paper[1], 3),
                f(c.ours[0], 2),
                f(c.ours[1], 3),
                f(c.crb[0], 2),
                f(c.crb[1], 3),
                f(c.ratio[0], 2),
                f(c.ratio[1], 2),
                c.mirrors,
                c.refused,
                f(100.0 * c.refused as f64 / c.trials.max(1) as f64, 1),
                c.refused_by[0],
                c.refused_by[1],
                c.refused_by[2],
                c.paper_bad,
            );
        }
    }
    s
}

fn draw_set(base: u64, n: usize) -> Result<Vec<GeometryDraw>, RandomGeometryError> {
    (0..n).map(|i| random_geometry(base + i as u64, i % 2 == 1)).collect()
}

fn geometry_list(draws: &[GeometryDraw], base: u64) -> String {
    let mut s = String::from(
        "| seed | RCM distance mm | tool-scope angle ° | distortion | horizontal FOV ° | PSM insertion mm | lines kept (noiseless, of 729) | not generated: tool through the endoscope |\n|---|---|---|---|---|---|---|---|\n",
    );
    for (i, g) in draws.iter().enumerate() {
        let fov = 2.0 * (320.0 / g.geometry.intrinsics.fx).atan();
        let (kept, collided) = generate_calibration(&protocol(g, NoiseUnits::Millimetre, 0.0, 0))
            .map_or((0, 0), |d| (d.observations.len(), d.collided));
        let _ = writeln!(
            s,
            "| {} | {:.0} | {:.0} | {} | {:.0} | {:.0} | {kept} | {collided} |",
            base + i as u64,
            g.rcm_distance_m * 1e3,
            g.tool_scope_angle_rad.to_degrees(),
            if g.distorted { "on" } else { "off" },
            fov.to_degrees(),
            g.geometry.psm_insertion_m * 1e3
        );
    }
    s
}

/// Runs the protocol and writes `generalisation.md` into `dir`; returns the Markdown.
pub fn run_generalisation(
    opts: &GeneralisationOptions,
    dir: &Path,
    command: &str,
) -> Result<String, GeneralisationError> {
    let n = opts.geometries as u64;
    if opts.held_out_seed < opts.tuning_seed.saturating_add(n)
        && opts.tuning_seed < opts.held_out_seed.saturating_add(n)
    {
        return Err(GeneralisationError::Overlap { held_out: opts.held_out_seed, tuning: opts.tuning_seed, n });
    }
    std::fs::create_dir_all(dir).map_err(|source| GeneralisationError::Write { path: dir.to_owned(), source })?;
    let started = Instant::now();
    let held_out = draw_set(opts.held_out_seed, opts.geometries)?;
    let tuning = if opts.held_out_only { Vec::new() } else { draw_set(opts.tuning_seed, opts.geometries)? };
    let held_res = run_set(&held_out, opts);
    let tune_res = if tuning.is_empty() { Vec::new() } else { run_set(&tuning, opts) };
    let elapsed = started.elapsed().as_secs_f64();
    let mut md =
        String::from("# Calibration on random scene geometries (generated by `comanip-calib sweep --geometries`)\n\n");
    let _ = writeln!(
        md,
        "Command: `{command}`  \n{} geometries per set, {} trials per geometry and condition (n_e = n_t = 3); tuning geometries: seeds {}..{}; held-out geometries: seeds {}..{} (odd index: lens distortion on); trial k uses noise seed {} + k. Wall time {:.0} s.\n",
        opts.geometries,
        opts.trials,
        opts.tuning_seed,
        opts.tuning_seed + opts.geometries as u64,
        opts.held_out_seed,
        opts.held_out_seed + opts.geometries as u64,
        opts.trial_seed,
        elapsed
    );
    md.push_str("RMS errors are per geometry (ours over its returned trials), then the median over the class's geometries; CRB: the Cramér-Rao bound of each geometry's noiseless kept lines (as if unselected); ours/CRB: the median over geometries of the ratio. Ours as the CLI reports it: a mirror is a pose > 90° off returned with exit 0; refused: a typed, non-zero outcome (ambiguous, degenerate, or the selection-aware stage cannot model the data).\n\n");
    md.push_str("## Held-out geometries\n\n");
    md.push_str(&table(&held_res));
    if !tune_res.is_empty() {
        md.push_str("\n## Tuning geometries\n\n");
        md.push_str(&table(&tune_res));
    }
    md.push_str("\n## The held-out geometries\n\n");
    md.push_str(&geometry_list(&held_out, opts.held_out_seed));
    let path = dir.join("generalisation.md");
    std::fs::write(&path, &md).map_err(|source| GeneralisationError::Write { path: path.clone(), source })?;
    Ok(md)
}
