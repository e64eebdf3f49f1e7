//! Dong & Morel's trocar detector, reproduced faithfully (the reference mode).
//!
//! | Paper | Here |
//! |---|---|
//! | Algorithm 1 (inclusion test, Eq. 9-10, against the last *included* sample) | [`PaperDetector::step`] → `include` via `differs_enough` |
//! | circular lists `L_m`, `L_n` | `short`, `long` (fixed-capacity `heapless::Deque`) |
//! | Eq. 7 (LS fulcrum) | [`super::lsq::NormalSums::solve`] over the window, rebuilt from the window's lines |
//! | Eq. 8 (mean residual `e_q`) | [`super::lsq::mean_distance`] |
//! | Algorithm 2 (insertion / extraction rules) | `PaperDetector::decide` |
//!
//! Choices where the paper is silent (also in `docs/trocar-detection.md`):
//! 1. `L_n` holds the lines of the current insertion: it is seeded with `L_m`'s lines when an
//!    insertion is declared and emptied at extraction. Otherwise `L_n` would be full a few
//!    seconds after start-up and Algorithm 2's "`L_n` not yet full" branch would never run.
//!    `L_m` is never emptied (a plain circular buffer, as Algorithm 1 says).
//! 2. `|F − P|` in the depth test uses the current sample's wrist P.
//! 3. The paper inverts `AᵀA` unconditionally. We refuse a window whose lines are parallel
//!    within numerical precision (`λ_min(AᵀA)/q < 1e-9`): no fulcrum, hence no insertion;
//!    while inside, the previous fulcrum is kept (no new information).
//! 4. Algorithm 2 runs every sample, but its LS result only changes when a line enters a
//!    window, so the fit is cached between inclusions (same decisions, less work).

use heapless::Deque;
use nalgebra::Vector3;

use super::config::{ConfigError, PaperConfig};
use super::lsq::{self, LsFit, NormalSums};
use super::{Estimate, FitSummary, LineSample, TrocarState, WINDOW_CAPACITY, differs_enough};

/// Numerical guard on `λ_min(AᵀA)/q` (choice 3 above).
const PAPER_MIN_CONDITIONING: f64 = 1e-9;

/// A fit of one window: the LS point and the paper's mean residual.
#[derive(Clone, Copy, Debug)]
struct WindowFit {
    ls: LsFit,
    /// Eq. 8, metres.
    mean_residual_m: f64,
}

/// The paper's detector. Construct with [`PaperDetector::new`]; call [`PaperDetector::step`]
/// once per sample.
#[derive(Clone, Debug)]
pub struct PaperDetector {
    cfg: PaperConfig,
    cos_include: f64,
    short: Deque<LineSample, WINDOW_CAPACITY>,
    long: Deque<LineSample, WINDOW_CAPACITY>,
    last_included: Option<LineSample>,
    short_fit: Option<WindowFit>,
    long_fit: Option<WindowFit>,
    present: bool,
    fulcrum_base_m: Vector3<f64>,
    next_id: u8,
    id: u8,
    last: Estimate,
}

fn fit_window(lines: &Deque<LineSample, WINDOW_CAPACITY>) -> Option<WindowFit> {
    let mut sums = NormalSums::new();
    sums.rebuild(lines.iter());
    let ls = sums.solve(PAPER_MIN_CONDITIONING).ok()?;
    let mean_residual_m = lsq::mean_distance(lines.iter(), &ls.fulcrum_base_m);
    Some(WindowFit { ls, mean_residual_m })
}

fn push_circular(list: &mut Deque<LineSample, WINDOW_CAPACITY>, len: usize, line: LineSample) {
    while list.len() >= len {
        list.pop_front();
    }
    // Cannot fail: len <= WINDOW_CAPACITY is validated and we just made room.
    let _ = list.push_back(line);
}

impl PaperDetector {
    /// Builds the detector (validates `cfg`).
    pub fn new(cfg: &PaperConfig) -> Result<Self, ConfigError> {
        cfg.validate()?;
        Ok(Self {
            cfg: *cfg,
            cos_include: nalgebra::ComplexField::cos(cfg.include_angle_deg.to_radians()),
            short: Deque::new(),
            long: Deque::new(),
            last_included: None,
            short_fit: None,
            long_fit: None,
            present: false,
            fulcrum_base_m: Vector3::zeros(),
            next_id: 0,
            id: 0,
            last: Estimate::outside(),
        })
    }

    /// Empties both lists and returns to `Outside`.
    pub fn reset(&mut self) {
        self.short.clear();
        self.long.clear();
        self.last_included = None;
        self.short_fit = None;
        self.long_fit = None;
        self.present = false;
        self.last = Estimate::outside();
    }

    /// Algorithm 1: includes `line` when it differs enough from the last included line.
    fn include(&mut self, line: &LineSample) -> bool {
        let take = match &self.last_included {
            None => true, // initialisation: L_q ← {c_1}
            Some(last) => differs_enough(last, line, self.cfg.include_distance_m, self.cos_include),
        };
        if take {
            push_circular(&mut self.short, self.cfg.window_short, *line);
            self.short_fit = None;
            if self.present {
                push_circular(&mut self.long, self.cfg.window_long, *line);
                self.long_fit = None;
            }
            self.last_included = Some(*line);
        }
        take
    }

    fn short_fit(&mut self) -> Option<WindowFit> {
        if self.short_fit.is_none() {
            self.short_fit = fit_window(&self.short);
        }
        self.short_fit
    }

    fn long_fit(&mut self) -> Option<WindowFit> {
        if self.long_fit.is_none() {
            self.long_fit = fit_window(&self.long);
        }
        self.long_fit
    }

    /// Algorithm 2. Returns the fit the decision used and the window it came from.
    fn decide(&mut self, line: &LineSample) -> (Option<WindowFit>, usize, usize) {
        let (m, n) = (self.cfg.window_short, self.cfg.window_long);
        if !self.present {
            if self.short.len() < m {
                return (None, self.short.len(), m);
            }
            let fit = self.short_fit();
            if let Some(f) = fit {
                let depth = (f.ls.fulcrum_base_m - line.wrist_base_m).norm();
                if f.mean_residual_m < self.cfg.insert_max_residual_m && depth > self.cfg.insert_min_depth_m {
                    self.present = true;
                    self.fulcrum_base_m = f.ls.fulcrum_base_m;
                    self.id = self.next_id;
                    self.next_id = self.next_id.wrapping_add(1);
                    // Choice 1: L_n starts with the lines that revealed the trocar.
                    self.long.clear();
                    for l in self.short.iter() {
                        let _ = self.long.push_back(*l);
                    }
                    self.long_fit = None;
                }
            }
            (fit, self.short.len(), m)
        } else if self.long.len() < n {
            let fit = self.short_fit();
            self.extract_or_follow(fit, self.cfg.extract_residual_short_m);
            (fit, self.short.len(), m)
        } else {
            let fit = self.long_fit();
            self.extract_or_follow(fit, self.cfg.extract_residual_long_m);
            (fit, self.long.len(), n)
        }
    }

    /// Inside: extraction when the window's mean residual exceeds `threshold_m` (Δ_em or
    /// Δ_en), else the fulcrum follows the window's fit.
    fn extract_or_follow(&mut self, fit: Option<WindowFit>, threshold_m: f64) {
        if let Some(f) = fit {
            if f.mean_residual_m > threshold_m {
                self.extract();
            } else {
                self.fulcrum_base_m = f.ls.fulcrum_base_m;
            }
        }
    }

    fn extract(&mut self) {
        self.present = false;
        self.long.clear();
        self.long_fit = None;
    }

    /// Feeds one sample; returns the estimate after it. Allocation-free.
    pub fn step(&mut self, sample: &LineSample) -> Estimate {
        let line = match sample.validated() {
            Ok(l) => l,
            Err(e) => {
                return Estimate { rejected: Some(e), included: false, ..self.last };
            }
        };
        let included = self.include(&line);
        let (fit, fill, len) = self.decide(&line);
        let state = if self.present { TrocarState::Inside { id: self.id } } else { TrocarState::Outside };
        let est = Estimate {
            state,
            fulcrum_base_m: self.present.then_some(self.fulcrum_base_m),
            fit: fit.map(|f| FitSummary {
                point_base_m: f.ls.fulcrum_base_m,
                residual_m: f.mean_residual_m,
                conditioning: f.ls.conditioning,
                std_m: f.ls.fulcrum_std_m(f.ls.noise_estimate_m()),
                lines: f.ls.count as u16,
                minor_spread_rad2: f.ls.minor_spread_rad2,
            }),
            window_fill: fill as u16,
            window_len: len as u16,
            rejected: None,
            included,
        };
        self.last = est;
        est
    }
}

#[cfg(test)]
mod tests {
    use crate::trocar::test_support::run_scripted;
    use crate::trocar::{DetectorConfig, DetectorMode};

    #[test]
    fn paper_mode_follows_insertions_and_extractions() {
        run_scripted(&DetectorConfig { mode: DetectorMode::Paper, ..Default::default() }, 3.0);
    }
}
