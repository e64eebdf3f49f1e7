//! `comanip-calib live` on the bus (issue 19): the live calibration process beside fulcrumd.
//!
//! Inputs, each on its own clock and paired at the frame's exposure mid time:
//! - **frames** from the frame service (`hw_io::ipc::FrameSubscriber`, `CLOCK_MONOTONIC`
//!   stamps), converted to packed sRGB for the detector;
//! - **both arms' joints** from a passive socket on the bus
//!   (`controller::bus_listen::ListenerThread`, `CLOCK_REALTIME` stamps; the frame's time moved
//!   there with `hw_io::frame::realtime_minus_monotonic_ns`): the endoscope arm's joints
//!   interpolated at the frame's time, the tool arm's used as a liveness check (an arm that
//!   stops answering makes the frame *stale encoders*);
//! - **the tool line** from fulcrumd's output (`FulcrumSample`: fulcrum, axis, wrist centre;
//!   `CLOCK_MONOTONIC` SYNC stamps), read on a thread of its own into a bounded history so
//!   that no sample around a frame's time is lost while the detector runs; the sample nearest
//!   the frame's time is used (none within `output.max_age_ms`: *no fulcrum*).
//!
//! The frame and its data go through [`crate::live::LiveLoop`], the loop `live --replay` runs.
//! When the collector reaches the target ([`crate::collector::Event::Solved`]) the result file
//! is written (atomically: a temporary file renamed) and a `Valid` [`CalibrationSample`] is
//! published; a drift publishes `Drift` and collection restarts; the current state is
//! republished every `output.republish_s` (a subscriber started later gets it). SIGUSR1 asks
//! for a solve now: the result file is written, published only when it reaches the target.

use std::collections::{BTreeMap, VecDeque};
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use controller::bus_listen::{Arm, JointsAtError, ListenConfig, ListenerThread, Staleness, bus_time_ns};
use hw_io::frame::{PixelFormat, realtime_minus_monotonic_ns};
use hw_io::ipc::{
    CalibrationSample, CalibrationState, FrameSubscriber, FulcrumSample, HealthFlags, OutputState, Publisher,
    PublisherOptions, Subscriber,
};
use serde::Serialize;
use tracing::{info, warn};

use crate::collector::{Calibration, CollectorConfig, Event, Progress, Refusal, ToolSample};
use crate::live::{FrameInput, LiveLoop, progress_line};
use crate::live_config::Resolved;

/// fulcrumd samples kept for pairing (4 s at 1 kHz).
const FULCRUM_HISTORY: usize = 4096;

/// Longest wait for the bus listener and the fulcrum reader to reach a frame's time.
const CATCH_UP: Duration = Duration::from_millis(500);

/// Why the live process stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    /// The bus listener cannot start.
    #[error("bus: {0}")]
    Bus(#[from] controller::bus_listen::ListenError),
    /// A shared-memory service cannot be opened.
    #[error("{service}: {message}")]
    Ipc {
        /// The service.
        service: String,
        /// Why.
        message: String,
    },
    /// The detector cannot be built for the camera.
    #[error(transparent)]
    Loop(#[from] crate::live::ReplayError),
    /// The fulcrum reader thread cannot start.
    #[error("cannot start the fulcrum reader thread: {0}")]
    Thread(#[source] std::io::Error),
}

/// The calibration as published, for the summary.
#[derive(Clone, Debug, Serialize)]
pub struct PublishedSummary {
    /// Seconds from the process's first frame to the publication.
    pub after_first_frame_s: f64,
    /// Seconds from the process's start to the publication.
    pub after_start_s: f64,
    /// Observations (eye lines) used.
    pub observations: usize,
    /// `T_e_t` translation, metres.
    pub translation_m: [f64; 3],
    /// `T_e_t` rotation, `[w, x, y, z]`.
    pub quaternion_wxyz: [f64; 4],
    /// Predicted RMS translation at the mean fulcrum, metres.
    pub predicted_fulcrum_m: f64,
    /// Predicted RMS translation of `{t}`'s origin, metres.
    pub predicted_origin_m: f64,
    /// Predicted RMS rotation, radians.
    pub predicted_rotation_rad: f64,
    /// Mean fulcrum of the observations, metres, `{t}`.
    pub mean_fulcrum_m: [f64; 3],
}

/// What the process did, written as JSON at exit (`--summary-json`).
#[derive(Clone, Debug, Default, Serialize)]
pub struct LiveSummary {
    /// Frames received.
    pub frames: u64,
    /// Frames lost by the frame subscriber (its buffer overflowed while the detector ran).
    pub frames_missed: u64,
    /// Frames in a pixel format or layout the process cannot read.
    pub frames_unreadable: u64,
    /// Observations kept in the current collection.
    pub kept: usize,
    /// Refusals by reason (frame-level reasons count frames, the others eye images).
    pub refused: BTreeMap<String, usize>,
    /// Calibrations published (`Valid`).
    pub published: u64,
    /// The first published calibration.
    pub first_published: Option<PublishedSummary>,
    /// Drift events.
    pub drifts: usize,
    /// Solves run (provisional, final, on request).
    pub solves: usize,
    /// Solves asked with SIGUSR1, and the result files they wrote.
    pub requested_solves: u64,
    /// Result files written.
    pub result_files: u64,
    /// Messages published on the calibration service (every state).
    pub messages: u64,
    /// Bus listener: tool cycles kept, endoscope samples, receive errors, kernel drops.
    pub bus_tool_samples: u64,
    /// Endoscope samples decoded.
    pub bus_endoscope_samples: u64,
    /// Receive errors.
    pub bus_errors: u64,
    /// Frames the kernel dropped from the listener's receive queue (it fell behind).
    pub bus_dropped_rx_frames: u64,
    /// fulcrumd samples received.
    pub fulcrum_samples: u64,
    /// Why pairing failed, by reason (per frame and arm: `endoscope: stale`, `tool: gap`...).
    pub pairing: BTreeMap<String, u64>,
}

/// fulcrumd's samples, read on a thread into a bounded history (`CLOCK_MONOTONIC` ns).
struct FulcrumReader {
    history: Arc<Mutex<VecDeque<FulcrumSample>>>,
    received: Arc<Mutex<u64>>,
    stop: Arc<AtomicBool>,
    handle: Option<std::thread::JoinHandle<()>>,
}

impl FulcrumReader {
    fn spawn(service: String, opts: PublisherOptions) -> Result<Self, LiveError> {
        let history: Arc<Mutex<VecDeque<FulcrumSample>>> =
            Arc::new(Mutex::new(VecDeque::with_capacity(FULCRUM_HISTORY)));
        let received = Arc::new(Mutex::new(0u64));
        let stop = Arc::new(AtomicBool::new(false));
        let (h, r, st) = (Arc::clone(&history), Arc::clone(&received), Arc::clone(&stop));
        let handle = std::thread::Builder::new()
            .name("fulcrum-reader".into())
            .spawn(move || {
                // Connects (again) until it works: fulcrumd may start after this process.
                let mut sub: Option<Subscriber<FulcrumSample>> = None;
                let mut warned = false;
                while !st.load(Ordering::Relaxed) {
                    let Some(s) = sub.as_mut() else {
                        match Subscriber::<FulcrumSample>::connect_with(&service, &opts) {
                            Ok(s) => {
                                info!("subscribed to fulcrumd's output {service}");
                                sub = Some(s);
                            }
                            Err(e) => {
                                if !warned {
                                    warn!("fulcrumd's output {service}: {e}; retrying");
                                    warned = true;
                                }
                                std::thread::sleep(Duration::from_millis(500));
                            }
                        }
                        continue;
                    };
                    match s.wait(Duration::from_millis(100)) {
                        Ok(Some(rx)) => {
                            let mut q = h.lock().unwrap_or_else(PoisonError::into_inner);
                            if q.len() == FULCRUM_HISTORY {
                                q.pop_front();
                            }
                            // Time order within one daemon run; a restart starts a new order.
                            if q.back().is_some_and(|b| b.timestamp_ns >= rx.sample.timestamp_ns) {
                                q.clear();
                            }
                            q.push_back(rx.sample);
                            *r.lock().unwrap_or_else(PoisonError::into_inner) += 1;
                        }
                        Ok(None) => {}
                        // A refused sample (version, invariant) is skipped; the reader goes on.
                        Err(hw_io::ipc::WaitError::Recv(_)) => {}
                        Err(e) => {
                            warn!("fulcrumd's output: {e}; reconnecting");
                            sub = None;
                        }
                    }
                }
            })
            .map_err(LiveError::Thread)?;
        Ok(Self { history, received, stop, handle: Some(handle) })
    }

    /// The sample nearest `t_ns` (`CLOCK_MONOTONIC`) and its distance in time, nanoseconds.
    fn nearest(&self, t_ns: u64) -> Option<(FulcrumSample, u64)> {
        let q = self.history.lock().unwrap_or_else(PoisonError::into_inner);
        let j = q.partition_point(|s| s.timestamp_ns <= t_ns);
        let before = j.checked_sub(1).and_then(|i| q.get(i));
        let after = q.get(j);
        [before, after].into_iter().flatten().map(|s| (*s, s.timestamp_ns.abs_diff(t_ns))).min_by_key(|(_, d)| *d)
    }

    /// The newest sample's time, `CLOCK_MONOTONIC` nanoseconds.
    fn newest_ns(&self) -> Option<u64> {
        self.history.lock().unwrap_or_else(PoisonError::into_inner).back().map(|s| s.timestamp_ns)
    }

    fn received(&self) -> u64 {
        *self.received.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

impl Drop for FulcrumReader {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(h) = self.handle.take() {
            let _ = h.join();
        }
    }
}

/// One eye of a received frame as packed sRGB into `out` (resized as needed); `false` for a
/// layout it cannot read.
fn eye_to_rgb(eye: &[u8], layout: &hw_io::frame::ImageLayout, out: &mut Vec<u8>) -> bool {
    let (w, h, stride) = (layout.width as usize, layout.height as usize, layout.stride as usize);
    if w == 0 || h == 0 || eye.len() < stride.saturating_mul(h) {
        return false;
    }
    out.clear();
    out.reserve(w * h * 3);
    for row in eye.chunks(stride).take(h) {
        match layout.format {
            PixelFormat::Rgb8 => match row.get(..w * 3) {
                Some(r) => out.extend_from_slice(r),
                None => return false,
            },
            PixelFormat::Gray8 => match row.get(..w) {
                Some(r) => r.iter().for_each(|&g| out.extend_from_slice(&[g, g, g])),
                None => return false,
            },
            PixelFormat::Yuyv => {
                let Some(r) = row.get(..w * 2) else { return false };
                for px in r.chunks_exact(4) {
                    let (y0, u, y1, v) = (px[0], px[1], px[2], px[3]);
                    for y in [y0, y1] {
                        out.extend_from_slice(&yuv_to_rgb(y, u, v));
                    }
                }
            }
        }
    }
    out.len() == w * h * 3
}

/// BT.601 limited-range YUV to sRGB bytes.
fn yuv_to_rgb(y: u8, u: u8, v: u8) -> [u8; 3] {
    let c = (f32::from(y) - 16.0) * 1.164;
    let d = f32::from(u) - 128.0;
    let e = f32::from(v) - 128.0;
    let clamp = |x: f32| x.round().clamp(0.0, 255.0) as u8;
    [clamp(c + 1.596 * e), clamp(c - 0.392 * d - 0.813 * e), clamp(c + 2.017 * d)]
}

fn sample_of(cal: &Calibration, t_ns: u64, drifts: usize) -> CalibrationSample {
    let mut s = CalibrationSample::collecting(cal.observations as u32);
    s.state = CalibrationState::Valid as u32;
    s.timestamp_ns = t_ns;
    s.drifts = drifts as u32;
    s.translation_m = cal.pose.translation.vector.into();
    let q = cal.pose.rotation.quaternion();
    s.quaternion_wxyz = [q.w, q.i, q.j, q.k];
    for (k, v) in s.covariance.iter_mut().enumerate() {
        *v = cal.precision.covariance[(k / 6, k % 6)];
    }
    s.predicted_fulcrum_m = cal.precision.fulcrum_m;
    s.predicted_origin_m = cal.precision.origin_m;
    s.predicted_rotation_rad = cal.precision.rotation_rad;
    s
}

fn mean_fulcrum(lp: &LiveLoop) -> [f64; 3] {
    let obs = lp.collector().observations();
    let n = obs.len().max(1) as f64;
    let mut m = [0.0; 3];
    for o in obs {
        for (mk, pk) in m.iter_mut().zip(o.tool_point_m) {
            *mk += pk / n;
        }
    }
    m
}

/// Writes the versioned result file (our pipeline, its covariance) atomically.
fn write_result(path: &Path, cal: &Calibration) -> Result<(), String> {
    let entry = crate::convert::result_json("ours", &cal.pose, &cal.ours.residuals, Some(&cal.ours), 0.0);
    let file = hw_io::calib_files::ResultFile {
        format: hw_io::calib_files::RESULT_FORMAT.into(),
        version: hw_io::calib_files::CALIB_FILE_VERSION,
        results: vec![entry],
        failures: Vec::new(),
    };
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = PathBuf::from(tmp);
    std::fs::write(&tmp, hw_io::calib_files::to_json(&file)).map_err(|e| format!("{}: {e}", tmp.display()))?;
    std::fs::rename(&tmp, path).map_err(|e| format!("{}: {e}", path.display()))
}

fn summarise(summary: &mut LiveSummary, p: &Progress) {
    summary.kept = p.kept;
    summary.refused =
        Refusal::ALL.iter().filter_map(|r| p.refused.get(r).map(|n| (r.name().to_string(), *n))).collect();
    summary.drifts = p.drifts;
    summary.solves = p.solves;
}

/// Runs the live calibration until `stop` is set. `request` (SIGUSR1) asks for a solve now.
pub fn run(cfg: &Resolved, stop: &AtomicBool, request: &AtomicBool) -> Result<LiveSummary, LiveError> {
    let started = Instant::now();
    let file = &cfg.file;
    let mut ccfg = CollectorConfig::new(cfg.setup, cfg.noise);
    ccfg.target_translation_m = file.target.translation_mm * 1e-3;
    ccfg.target_rotation_rad = file.target.rotation_deg.to_radians();
    ccfg.max_age_ns = (file.output.max_age_ms * 1e6) as u64;
    ccfg.max_observations = file.collection.max_observations;
    let mut lp = LiveLoop::new(ccfg)?;

    let mut listen = ListenConfig::from_daemon(&cfg.fulcrumd);
    listen.endoscope = file.bus.endoscope_arm.clone();
    // The endoscope arm only (kernel filters): the tool arm's data come through fulcrumd, whose
    // health flags say when its nodes stop answering.
    let listener = ListenerThread::open_for(&file.bus.iface, &listen, &[Arm::Endoscope])?;
    info!("listening on {} for the endoscope arm (passive: this process never sends)", file.bus.iface);
    let fopts = PublisherOptions { subscriber_buffer: cfg.fulcrumd.output.subscriber_buffer, ..Default::default() };
    let fulcrum = FulcrumReader::spawn(cfg.fulcrum_service.clone(), fopts)?;
    // The collection and the solves run below the two reader threads started above: a solve
    // (tens of milliseconds, more on a slow machine) never keeps them from the bus.
    match controller::rt::lower_current_thread() {
        controller::rt::Lowered::Unchanged { reason } => {
            warn!(%reason, "the collecting thread could not be put below the bus listener")
        }
        l => info!(collecting_thread = %l, "the collecting thread runs below the bus and fulcrum readers"),
    }
    let ipc_err = |service: &str, e: &dyn std::fmt::Display| LiveError::Ipc {
        service: service.to_string(),
        message: e.to_string(),
    };
    let mut frames = FrameSubscriber::connect(&file.services.frames, &PublisherOptions::frames())
        .map_err(|e| ipc_err(&file.services.frames, &e))?;
    let mut publisher =
        Publisher::<CalibrationSample>::create(&file.services.calibration, &PublisherOptions::default())
            .map_err(|e| ipc_err(&file.services.calibration, &e))?;
    info!("subscribed to frames on {}, publishing on {}", file.services.frames, file.services.calibration);

    let run_id = hw_io::can::unix_time_now_us() ^ (u64::from(std::process::id()) << 40);
    let mut sequence = 0u64;
    let mut summary = LiveSummary::default();
    let mut current = CalibrationSample::collecting(0);
    let mut rgb = [Vec::new(), Vec::new()];
    let terminal = std::io::stderr().is_terminal();
    let bar = if terminal { indicatif::ProgressBar::new_spinner() } else { indicatif::ProgressBar::hidden() };
    if let Ok(style) = indicatif::ProgressStyle::with_template("{spinner} [{elapsed_precise}] {msg}") {
        bar.set_style(style);
    }
    let republish = Duration::from_secs_f64(file.output.republish_s);
    let log_every = Duration::from_secs_f64(file.output.progress_every_s);
    let (mut last_publish, mut last_log) = (Instant::now(), Instant::now());
    let mut first_frame: Option<Instant> = None;
    let mut last_t = 0u64;
    let publish = |publisher: &mut Publisher<CalibrationSample>, msg: &mut CalibrationSample, seq: &mut u64| {
        msg.sequence = *seq;
        msg.run_id = run_id;
        *seq += 1;
        if let Err(e) = publisher.publish(msg) {
            warn!("publishing the calibration: {e}");
        }
    };
    publish(&mut publisher, &mut current, &mut sequence);
    while !stop.load(Ordering::Relaxed) {
        let frame = match frames.wait(Duration::from_millis(100)) {
            Ok(f) => f,
            Err(e) => {
                warn!("frame service: {e}");
                std::thread::sleep(Duration::from_millis(100));
                None
            }
        };
        if let Some(frame) = frame {
            summary.frames += 1;
            first_frame.get_or_insert_with(Instant::now);
            let meta = *frame.meta();
            let t_mono = meta.timestamp_ns;
            last_t = t_mono;
            let mut readable = meta.eyes == 2;
            for (k, buf) in rgb.iter_mut().enumerate() {
                readable &= frame.eye(k as u32).is_some_and(|eye| eye_to_rgb(eye, &meta.layout, buf));
            }
            drop(frame);
            if !readable {
                summary.frames_unreadable += 1;
            } else {
                let input = pair(&listener, &fulcrum, t_mono, cfg, &mut summary, &rgb, &meta);
                let event = lp.on_frame(&input);
                match event {
                    Event::Solved(cal) => {
                        let mut msg = sample_of(&cal, t_mono, lp.collector().progress().drifts);
                        msg.mean_fulcrum_m = mean_fulcrum(&lp);
                        match write_result(&file.output.result_file, &cal) {
                            Ok(()) => summary.result_files += 1,
                            Err(e) => warn!("result file: {e}"),
                        }
                        publish(&mut publisher, &mut msg, &mut sequence);
                        summary.published += 1;
                        let p = &cal.precision;
                        info!(
                            "calibration published: {} observations, predicted {:.2} mm at the fulcrum, {:.3}°; wrote {}",
                            cal.observations,
                            p.fulcrum_m * 1e3,
                            p.rotation_rad.to_degrees(),
                            file.output.result_file.display()
                        );
                        if summary.first_published.is_none() {
                            summary.first_published = Some(PublishedSummary {
                                after_first_frame_s: first_frame.map_or(0.0, |t| t.elapsed().as_secs_f64()),
                                after_start_s: started.elapsed().as_secs_f64(),
                                observations: cal.observations,
                                translation_m: msg.translation_m,
                                quaternion_wxyz: msg.quaternion_wxyz,
                                predicted_fulcrum_m: p.fulcrum_m,
                                predicted_origin_m: p.origin_m,
                                predicted_rotation_rad: p.rotation_rad,
                                mean_fulcrum_m: msg.mean_fulcrum_m,
                            });
                        }
                        current = msg;
                        last_publish = Instant::now();
                    }
                    Event::Drift { misfit_fraction } => {
                        warn!(
                            "drift: {:.0} % of recent observations misfit; collection restarted",
                            misfit_fraction * 100.0
                        );
                        current = CalibrationSample::collecting(0);
                        current.state = CalibrationState::Drift as u32;
                        current.drifts = lp.collector().progress().drifts as u32;
                        current.timestamp_ns = t_mono;
                        publish(&mut publisher, &mut current, &mut sequence);
                        last_publish = Instant::now();
                    }
                    Event::None => {}
                }
            }
        }
        if request.swap(false, Ordering::Relaxed) {
            summary.requested_solves += 1;
            match lp.collector_mut().solve_now(last_t) {
                None => {
                    info!("solve requested: too little data ({} observations)", lp.collector().observations().len())
                }
                Some(Err(e)) => warn!("solve requested: {e}"),
                Some(Ok(cal)) => {
                    let p = cal.precision;
                    let reached = p.fulcrum_m <= file.target.translation_mm * 1e-3
                        && p.rotation_rad <= file.target.rotation_deg.to_radians();
                    match write_result(&file.output.result_file, &cal) {
                        Ok(()) => summary.result_files += 1,
                        Err(e) => warn!("result file: {e}"),
                    }
                    info!(
                        "solve requested: predicted {:.2} mm at the fulcrum, {:.3}°: {}",
                        p.fulcrum_m * 1e3,
                        p.rotation_rad.to_degrees(),
                        if reached { "target reached, published" } else { "below the target, written, not published" }
                    );
                    if reached {
                        let mut msg = sample_of(&cal, last_t, lp.collector().progress().drifts);
                        msg.mean_fulcrum_m = mean_fulcrum(&lp);
                        publish(&mut publisher, &mut msg, &mut sequence);
                        summary.published += 1;
                        current = msg;
                    }
                }
            }
        }
        let progress = lp.collector().progress();
        if last_publish.elapsed() >= republish {
            if current.state() != Some(CalibrationState::Valid) {
                // Collecting: the counts and the precision the data already support.
                let st = current.state;
                current = CalibrationSample::collecting(progress.kept as u32);
                current.state = st;
                current.drifts = progress.drifts as u32;
                current.timestamp_ns = last_t;
                if let Some(p) = &progress.precision {
                    (current.predicted_fulcrum_m, current.predicted_origin_m, current.predicted_rotation_rad) =
                        (p.fulcrum_m, p.origin_m, p.rotation_rad);
                }
            }
            publish(&mut publisher, &mut current, &mut sequence);
            last_publish = Instant::now();
        }
        let t_s = started.elapsed().as_secs_f64();
        if terminal {
            bar.set_message(progress_line(progress, t_s));
            bar.tick();
        } else if last_log.elapsed() >= log_every {
            info!("{}", progress_line(progress, t_s));
            last_log = Instant::now();
        }
    }
    bar.finish_and_clear();
    summarise(&mut summary, lp.collector().progress());
    info!("{}", progress_line(lp.collector().progress(), started.elapsed().as_secs_f64()));
    let fc = frames.counters();
    summary.frames_missed = fc.missed;
    let b = listener.stats();
    (summary.bus_tool_samples, summary.bus_endoscope_samples, summary.bus_errors, summary.bus_dropped_rx_frames) =
        (b.tool_samples, b.endoscope_samples, b.errors, b.dropped_rx_frames);
    summary.fulcrum_samples = fulcrum.received();
    summary.messages = publisher.published();
    Ok(summary)
}

fn count(summary: &mut LiveSummary, arm: &str, e: &JointsAtError) {
    let why = match e {
        JointsAtError::NoData => "no data",
        JointsAtError::BeforeHistory { .. } => "before history",
        JointsAtError::Gap { .. } => "gap",
        JointsAtError::Stale { .. } => "stale",
    };
    *summary.pairing.entry(format!("{arm}: {why}")).or_insert(0) += 1;
}

/// Both arms' data at the frame's time `t_mono` (`CLOCK_MONOTONIC` ns).
fn pair<'a>(
    listener: &ListenerThread,
    fulcrum: &FulcrumReader,
    t_mono: u64,
    cfg: &Resolved,
    summary: &mut LiveSummary,
    rgb: &'a [Vec<u8>; 2],
    meta: &hw_io::frame::FrameMeta,
) -> FrameInput<'a> {
    let t_bus = bus_time_ns(t_mono, realtime_minus_monotonic_ns()).unwrap_or(0);
    let ms = |v: f64| (v * 1e6) as u64;
    // The readers are threads of this process, behind when the machine is busy: give them until
    // the endoscope arm and fulcrumd have a sample past the frame's time (at most CATCH_UP), so
    // that a frame is refused for what the bus did, not for how late this process read it.
    let caught_up =
        || listener.latest_ns().1.is_some_and(|t| t >= t_bus) && fulcrum.newest_ns().is_some_and(|t| t >= t_mono);
    let start = Instant::now();
    while !caught_up() && start.elapsed() < CATCH_UP {
        std::thread::sleep(Duration::from_millis(5));
    }
    let ecm_gap = ms(cfg.file.pairing.endoscope_max_gap_ms);
    let ecm_policy = Staleness { max_gap_ns: ecm_gap, max_age_ns: ecm_gap };
    let (ecm_joints, ecm_age_ns) = match listener.endoscope_at(t_bus, &ecm_policy) {
        Ok(j) => (j.joints, j.age_ns),
        Err(e) => {
            count(summary, "endoscope", &e);
            ([f64::NAN; 4], u64::MAX)
        }
    };
    // The tool arm's nodes: stale or silent per fulcrumd's health flags of the sample.
    let silent = HealthFlags::NODE1_STALE
        | HealthFlags::NODE2_STALE
        | HealthFlags::NODE3_STALE
        | HealthFlags::NODE1_HEARTBEAT
        | HealthFlags::NODE2_HEARTBEAT
        | HealthFlags::NODE3_HEARTBEAT;
    let tool = match fulcrum.nearest(t_mono) {
        Some((s, dt)) => {
            let stale = s.health().intersects(silent);
            if stale {
                *summary.pairing.entry("tool: nodes stale (fulcrumd)".into()).or_insert(0) += 1;
            }
            ToolSample {
                fulcrum_valid: s.state() == Ok(OutputState::Inside),
                fulcrum_m: s.fulcrum_base_m,
                axis: s.axis_base,
                wrist_m: s.wrist_base_m,
                wrist_to_tip_m: cfg.file.tool.wrist_to_tip_m,
                age_ns: if stale { u64::MAX } else { dt },
                fulcrum_age_ns: dt,
            }
        }
        None => {
            *summary.pairing.entry("fulcrum: no data".into()).or_insert(0) += 1;
            ToolSample {
                fulcrum_valid: false,
                fulcrum_m: [0.0; 3],
                axis: [0.0; 3],
                wrist_m: [0.0; 3],
                wrist_to_tip_m: cfg.file.tool.wrist_to_tip_m,
                age_ns: 0,
                fulcrum_age_ns: u64::MAX,
            }
        }
    };
    let (w, h) = (meta.layout.width as usize, meta.layout.height as usize);
    FrameInput {
        t_ns: t_mono,
        eyes: [Some((w, h, rgb[0].as_slice())), Some((w, h, rgb[1].as_slice()))],
        ecm_joints,
        ecm_age_ns,
        tool,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn eyes_of_every_format_become_packed_rgb_and_short_buffers_are_refused() {
        let mut out = Vec::new();
        let rgb = hw_io::frame::ImageLayout { width: 2, height: 2, stride: 8, format: PixelFormat::Rgb8 };
        let bytes: Vec<u8> = (0..16).collect();
        assert!(eye_to_rgb(&bytes, &rgb, &mut out));
        assert_eq!(out, vec![0, 1, 2, 3, 4, 5, 8, 9, 10, 11, 12, 13]);
        let gray = hw_io::frame::ImageLayout { width: 2, height: 1, stride: 2, format: PixelFormat::Gray8 };
        assert!(eye_to_rgb(&[7, 9], &gray, &mut out));
        assert_eq!(out, vec![7, 7, 7, 9, 9, 9]);
        let yuyv = hw_io::frame::ImageLayout { width: 2, height: 1, stride: 4, format: PixelFormat::Yuyv };
        assert!(eye_to_rgb(&[235, 128, 16, 128], &yuyv, &mut out));
        assert_eq!(out, vec![255, 255, 255, 0, 0, 0]);
        assert!(!eye_to_rgb(&bytes[..10], &rgb, &mut out), "short buffer");
        let empty = hw_io::frame::ImageLayout { width: 0, height: 2, stride: 0, format: PixelFormat::Rgb8 };
        assert!(!eye_to_rgb(&bytes, &empty, &mut out));
    }
}
