//! `comanip-track monitor`: the live tracker's output read back, one line per sample, and a
//! summary of what was seen (samples per status, refused and missed samples, publisher restarts,
//! the transport's latency).
//!
//! A reader for people and scripts on the robot PC: it subscribes to the tracking service like
//! any consumer would (`hw_io::ipc::Subscriber<TrackSample>`, which refuses a sample of another
//! layout version or with a broken invariant, and counts sequence gaps), so what it prints is
//! what a guidance module would get. Lines are JSON (the same object as `comanip-track live
//! --samples-jsonl`) or a fixed-width text line.

use std::io::Write;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use hw_io::frame::monotonic_now_ns;
use hw_io::ipc::{Subscriber, SubscriberCounters, TrackSample, TrackStatus, WaitError};

use crate::live_cli::sample_json;

/// The line format of [`monitor`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MonitorFormat {
    /// One JSON object per sample (the `live --samples-jsonl` object, with `received_ns`).
    Json,
    /// One fixed-width line per sample: sequence, frame, status, the tip in the base frame
    /// (millimetres), the spread (millimetres), the cost (pixels), the jaw (degrees), the
    /// transport latency (milliseconds) and the reasons.
    Text,
}

/// What [`monitor`] reads and when it stops.
#[derive(Clone, Debug)]
pub struct MonitorOptions {
    /// Line format.
    pub format: MonitorFormat,
    /// Stop after this many accepted samples (`None`: until `stop` is set or the idle timeout).
    pub count: Option<u64>,
    /// Stop when no sample (accepted or refused) arrived for this long (`None`: never).
    pub idle_timeout: Option<Duration>,
}

/// Why [`monitor`] stopped early.
#[derive(Debug, thiserror::Error)]
pub enum MonitorError {
    /// The subscriber failed (not a refused sample: those are counted).
    #[error("the tracking service failed: {0}")]
    Service(String),
    /// The output could not be written.
    #[error("cannot write the output: {0}")]
    Write(#[from] std::io::Error),
}

/// Why [`monitor`] returned.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum StopReason {
    /// `count` samples were accepted.
    Count,
    /// Nothing arrived for the idle timeout.
    Idle,
    /// The stop flag was set (SIGINT/SIGTERM).
    Signal,
}

/// What [`monitor`] saw.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct MonitorSummary {
    /// Accepted samples.
    pub received: u64,
    /// Accepted samples per status: `INVALID`, `TRACKING`, `UNCERTAIN`, `LOST`.
    pub invalid: u64,
    /// See `invalid`.
    pub tracking: u64,
    /// See `invalid`.
    pub uncertain: u64,
    /// See `invalid`.
    pub lost: u64,
    /// Samples refused by the subscriber (another layout version, or a broken invariant such
    /// as a non-finite pose marked as tracking); each is also reported on standard error.
    pub refused: u64,
    /// Samples lost in the transport (sequence gaps).
    pub missed: u64,
    /// Publisher restarts seen (a new `run_id`).
    pub restarts: u64,
    /// Transport latency (`received − published_ns`, same `CLOCK_MONOTONIC`), milliseconds:
    /// median and 99th percentile over the accepted samples (`None` without samples).
    pub latency_ms_p50: Option<f64>,
    /// See `latency_ms_p50`.
    pub latency_ms_p99: Option<f64>,
    /// The tracker's own counters in the last sample: frames skipped for a newer one.
    pub last_frames_skipped: Option<u64>,
    /// Why the monitor stopped.
    pub stopped: StopReason,
}

/// Latencies kept for the summary's percentiles (the oldest are overwritten beyond this: a
/// day at 30 frames/s would otherwise keep 2.6 M values).
const LATENCY_WINDOW: usize = 100_000;

/// Reads `sub` until `opts.count` samples, the idle timeout or `stop`, writing one line per
/// accepted sample to `out` (flushed per line) and each refusal to standard error.
pub fn monitor(
    sub: &mut Subscriber<TrackSample>,
    opts: &MonitorOptions,
    out: &mut dyn Write,
    stop: &AtomicBool,
) -> Result<MonitorSummary, MonitorError> {
    let mut per_status = [0u64; 4];
    let mut refused = 0u64;
    let mut latencies_ms: Vec<f64> = Vec::new();
    let mut next_latency = 0usize;
    let mut last_skipped = None;
    let mut last_activity = Instant::now();
    let stopped = loop {
        if stop.load(Ordering::Relaxed) {
            break StopReason::Signal;
        }
        if opts.count.is_some_and(|n| per_status.iter().sum::<u64>() >= n) {
            break StopReason::Count;
        }
        if opts.idle_timeout.is_some_and(|t| last_activity.elapsed() >= t) {
            break StopReason::Idle;
        }
        match sub.wait(Duration::from_millis(100)) {
            Ok(Some(rx)) => {
                last_activity = Instant::now();
                let received_ns = monotonic_now_ns();
                let s = rx.sample;
                // `Subscriber` only accepts known statuses (`TrackSample::check`).
                let status = s.status().unwrap_or(TrackStatus::Invalid);
                per_status[status as usize] += 1;
                let latency_ms = received_ns.saturating_sub(s.published_ns) as f64 / 1e6;
                if latencies_ms.len() < LATENCY_WINDOW {
                    latencies_ms.push(latency_ms);
                } else {
                    latencies_ms[next_latency] = latency_ms;
                    next_latency = (next_latency + 1) % LATENCY_WINDOW;
                }
                last_skipped = Some(s.frames_skipped);
                match opts.format {
                    MonitorFormat::Json => writeln!(out, "{}", sample_json(&s, received_ns))?,
                    MonitorFormat::Text => writeln!(out, "{}", text_line(&s, latency_ms))?,
                }
                out.flush()?;
            }
            Ok(None) => {}
            Err(WaitError::Recv(e)) => {
                last_activity = Instant::now();
                refused += 1;
                eprintln!("comanip-track monitor: refused a sample: {e}");
            }
            Err(e) => return Err(MonitorError::Service(e.to_string())),
        }
    };
    let SubscriberCounters { received, missed, restarts, .. } = sub.counters();
    latencies_ms.sort_by(f64::total_cmp);
    Ok(MonitorSummary {
        received,
        invalid: per_status[TrackStatus::Invalid as usize],
        tracking: per_status[TrackStatus::Tracking as usize],
        uncertain: per_status[TrackStatus::Uncertain as usize],
        lost: per_status[TrackStatus::Lost as usize],
        refused,
        missed,
        restarts,
        latency_ms_p50: percentile(&latencies_ms, 0.5),
        latency_ms_p99: percentile(&latencies_ms, 0.99),
        last_frames_skipped: last_skipped,
        stopped,
    })
}

/// The nearest-rank percentile of sorted values.
fn percentile(sorted: &[f64], q: f64) -> Option<f64> {
    if sorted.is_empty() {
        return None;
    }
    let rank = ((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len());
    Some(sorted[rank - 1])
}

/// The `--format text` line of one sample (no pose fields for `INVALID` and `LOST`).
pub fn text_line(s: &TrackSample, latency_ms: f64) -> String {
    let status = s.status().map_or("UNKNOWN", TrackStatus::name);
    let pose = if s.status().is_some_and(TrackStatus::has_pose) {
        let [x, y, z] = s.tip_base_m.map(|v| v * 1e3);
        format!(
            "tip_base_mm=({x:8.2},{y:8.2},{z:8.2}) spread_mm={:6.2} cost_px={:5.2} jaw_deg={:6.1}",
            s.spread_m * 1e3,
            s.best_cost_px,
            s.jaw_rad.to_degrees()
        )
    } else {
        format!("{:<78}", "-")
    };
    let reasons = s.reasons();
    let reasons = if reasons.is_empty() { String::new() } else { format!(" reasons={reasons}") };
    format!("#{:<8} frame={:<8} {status:<9} {pose} latency_ms={latency_ms:7.2}{reasons}", s.sequence, s.frame_sequence)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;
    use hw_io::ipc::TrackReasons;

    #[test]
    fn percentiles_are_nearest_rank() {
        let v: Vec<f64> = (1..=100).map(f64::from).collect();
        assert_eq!(percentile(&v, 0.5), Some(50.0));
        assert_eq!(percentile(&v, 0.99), Some(99.0));
        assert_eq!(percentile(&[3.0], 0.99), Some(3.0));
        assert_eq!(percentile(&[], 0.5), None);
    }

    #[test]
    fn the_text_line_shows_a_pose_only_when_the_status_has_one() {
        let mut s = TrackSample::invalid(TrackReasons::TOOL_JOINTS_STALE);
        s.sequence = 12;
        let line = text_line(&s, 0.5);
        assert!(line.contains("INVALID") && line.contains("reasons=") && !line.contains("tip_base_mm"), "{line}");
        s.status = TrackStatus::Tracking as u32;
        s.reasons = 0;
        s.tip_base_m = [0.1, -0.02, 0.3];
        s.spread_m = 0.0012;
        let line = text_line(&s, 0.5);
        assert!(line.contains("TRACKING") && line.contains("100.00") && line.contains("-20.00"), "{line}");
        assert!(line.contains("spread_mm=  1.20") && !line.contains("reasons="), "{line}");
    }
}
