//! The motion-only bound: the earliest instant after a true event at which the motion so
//! far could decide it, whatever the detector.
//!
//! Computed per true event from the ground truth and the lines the detectors see (same
//! encoder quantisation, same calibration error, same trocar compliance):
//!
//! - **Insertion.** Lines measured before the tip crosses the trocar carry no information
//!   about it (they are the approach and the axial entry, all along one axis). From the
//!   crossing at sample `e` on, the least-squares intersection of the lines `e..=t` is the
//!   best estimate of the fulcrum the motion so far allows. The bound is the first `t` from
//!   which that estimate stays within [`INSERTION_TOLERANCE_M`] of where the whole cycle's
//!   motion locates it (the least-squares point of every line until the extraction) — before
//!   it, the lines have not swept enough angle about the fulcrum to locate it, whoever looks
//!   at them. The comparison is with the cycle's own least-squares point, not the true
//!   pivot, because no estimator can remove the arm's calibration error from the lines (the
//!   distance between the two is reported as the localisation floor).
//! - **Extraction** (geometry only, no instrument length). While inside, the lines stay
//!   within an envelope around the fulcrum (noise, compliance, calibration error): its
//!   radius is the largest distance from the cycle's inside lines to their least-squares
//!   point. The bound is the first sample after the tip has come out whose line leaves that
//!   envelope: before it, every line is still consistent with the instrument being in the
//!   trocar.
//!
//! With the instrument length known the tip's crossing is itself observable (the bound is
//! then the event); with a trocar memory the fulcrum is known before the insertion.

use estimator::trocar::LineSample;
use estimator::trocar::lsq::{NormalSums, line_distance};

use super::trace::Trace;

/// The insertion bound's localisation tolerance, metres: the size of a trocar port (5-12 mm).
pub const INSERTION_TOLERANCE_M: f64 = 0.005;

/// Bounds of one insertion/extraction cycle.
#[derive(Clone, Debug, PartialEq)]
pub struct CycleBound {
    /// True insertion sample.
    pub insertion_sample: usize,
    /// Insertion bound, seconds after the true insertion (None: the motion never located
    /// the fulcrum within tolerance before the extraction).
    pub insertion_s: Option<f64>,
    /// Extraction bound, seconds after the true extraction (None: no extraction, or the
    /// line never left the envelope before the next insertion).
    pub extraction_s: Option<f64>,
    /// Envelope radius of the cycle, metres.
    pub envelope_m: f64,
    /// Squared distances from the cycle's least-squares point to the true pivot, one per
    /// inside sample, square metres: what a perfect fixed-point estimate would still miss
    /// (calibration error of the arm, trocar compliance).
    pub floor_sq_m2: Vec<f64>,
}

/// The bounds of every true insertion of `trace`, in order.
pub fn bounds(trace: &Trace) -> Vec<CycleBound> {
    let n = trace.lines.len();
    let evs = &trace.events;
    let mut out = Vec::new();
    for (k, e) in evs.iter().enumerate() {
        if !e.insertion {
            continue;
        }
        let x = evs[k + 1..].iter().find(|v| !v.insertion).map_or(n, |v| v.sample).min(n);
        let next = evs[k + 1..].iter().find(|v| v.insertion).map_or(n, |v| v.sample).min(n);
        let lines: Vec<(usize, LineSample)> = (e.sample..x).filter_map(|j| trace.lines[j].map(|l| (j, l))).collect();
        let mut all = NormalSums::new();
        for (_, l) in &lines {
            all.add(l);
        }
        let whole = all.solve(1e-12).ok().map(|f| f.fulcrum_base_m);
        // Insertion: last sample whose running estimate is off (or undetermined).
        let mut sums = NormalSums::new();
        let mut last_bad: Option<usize> = None;
        for &(j, l) in &lines {
            sums.add(&l);
            let ok = match (sums.solve(1e-12), whole) {
                (Ok(fit), Some(w)) => (fit.fulcrum_base_m - w).norm() <= INSERTION_TOLERANCE_M,
                _ => false,
            };
            if !ok {
                last_bad = Some(j);
            }
        }
        let insertion_s = match last_bad {
            None => Some(0.0),
            Some(j) if j + 1 < x => Some((j + 1 - e.sample) as f64 * 1e-3),
            Some(_) => None,
        };
        // Localisation floor: the whole cycle's point against the moving true pivot.
        let mut floor_sq = Vec::new();
        if let Some(w) = whole {
            for &(j, _) in &lines {
                if let Some(p) = trace.pivots[j] {
                    floor_sq.push((w - p).norm_squared());
                }
            }
        }
        // Extraction: the envelope of the inside lines around their LS point.
        let (extraction_s, envelope_m) = match whole {
            Some(f) => {
                let env = lines.iter().map(|(_, l)| line_distance(l, &f)).fold(0.0, f64::max);
                let leave = if x < n {
                    (x..next).find(|&j| trace.lines[j].is_some_and(|l| line_distance(&l, &f) > env))
                } else {
                    None
                };
                (leave.map(|j| (j - x) as f64 * 1e-3), env)
            }
            None => (None, 0.0),
        };
        out.push(CycleBound {
            insertion_sample: e.sample,
            insertion_s,
            extraction_s,
            envelope_m,
            floor_sq_m2: floor_sq,
        });
    }
    out
}
