//! The live process (`comanip-track live`, `docs/tracking.md` "Live"): frames from the frame
//! service, both arms' joints at each frame's time from the CAN bus, the calibration from
//! `comanip-calib live`, our tracker (the offline run's own [`crate::run::step_frame`]), one
//! [`TrackSample`] per frame on the track service.
//!
//! The loop ([`run`]) is generic over its four boundaries, so that the same code runs on
//! iceoryx2 and the bus in the process and on in-process inputs in the tests:
//!
//! - [`FrameSource`]: frames (the iceoryx2 [`FrameSubscriber`]; in tests [`MemoryFrames`]);
//! - [`JointsAt`]: both arms' joints at a frame's time ([`BusJoints`]: the passive bus
//!   listener `controller::bus_listen`, on the bus or on a replayed candump log);
//! - [`CalibrationSource`]: the newest calibration message (`Subscriber<CalibrationSample>`;
//!   [`NoCalibration`]);
//! - [`TrackSink`]: where samples go (`Publisher<TrackSample>`; a `Vec`).
//!
//! **Newest frame wins.** Frames that arrive while a frame is tracked wait in the subscriber's
//! buffer (two deep); before the next step the loop drains it and keeps the newest, counting
//! the others as skipped, and frames lost in the transport (sequence gaps) are counted as
//! skipped too. Every frame is accounted for: `processed + skipped + rejected` = the frames
//! published since the first one received; when the loop stops, the frames still waiting
//! (and the transport's gap up to the newest of them) are counted as skipped.
//!
//! **Bad input is flagged, never published as valid**: stale or non-finite joints, a frame of
//! the wrong format, a corrupt frame header, a tracker refusal each give an `Invalid` sample
//! with its [`TrackReasons`]; a refused or drifting calibration is flagged and not used.
//!
//! **No allocation per frame** after start-up in our mode (`tests/live_alloc.rs` counts them
//! with an in-process source).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use estimator::calib::Intrinsics;
use hw_io::frame::{FrameMeta, PixelFormat, monotonic_now_ns};
use hw_io::ipc::{
    CalibrationSample, CalibrationState, FrameHeaderError, FrameRecvError, FrameSubscriber, FrameWaitError, Publisher,
    ReceivedFrame, RecvError, Subscriber, TrackReasons, TrackSample, TrackStatus,
};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use track::{Status, StepError, StereoCameras, ToolModel, Tracker, TrackerConfig};

use crate::input::left_from_base;
use crate::run::step_frame;

/// Both arms' joints at one instant.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ArmJoints {
    /// The tool arm's joints 1-6 from its encoders, radians.
    pub tool_rad: [f64; 6],
    /// The endoscope arm's joints `[yaw rad, pitch rad, insertion m, roll rad]`.
    pub endoscope: [f64; 4],
}

/// Why the joints at a frame's time are unknown.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
pub enum JointsError {
    /// No tool arm readings on both sides of the time (within the allowed gap).
    #[error("no tool arm readings around the frame's time")]
    ToolStale,
    /// No endoscope arm readings around the time.
    #[error("no endoscope arm readings around the frame's time")]
    EndoscopeStale,
    /// Neither arm.
    #[error("no readings of either arm around the frame's time")]
    BothStale,
}

impl JointsError {
    /// The sample's reasons for this error.
    pub fn reasons(self) -> TrackReasons {
        match self {
            Self::ToolStale => TrackReasons::TOOL_JOINTS_STALE,
            Self::EndoscopeStale => TrackReasons::ENDOSCOPE_JOINTS_STALE,
            Self::BothStale => TrackReasons::TOOL_JOINTS_STALE | TrackReasons::ENDOSCOPE_JOINTS_STALE,
        }
    }
}

/// Both arms' joints at a frame's time.
pub trait JointsAt {
    /// The joints at `frame.timestamp_ns`, the frame's mid-exposure time on the frame service's
    /// clock (nanoseconds); an implementation on another clock converts. May block briefly
    /// until the bus has passed that time. Allocation-free.
    fn joints_at(&mut self, frame: &FrameMeta) -> Result<ArmJoints, JointsError>;
}

/// How a frame's time maps to the bus clock (`CLOCK_REALTIME` nanoseconds on a live bus, the
/// log's clock for a recorded one).
#[derive(Clone, Debug, PartialEq)]
pub enum FrameClock {
    /// Live: the frame's `CLOCK_MONOTONIC` time moved to `CLOCK_REALTIME`
    /// (`controller::bus_listen::bus_time_ns` with
    /// [`hw_io::frame::realtime_minus_monotonic_ns`], re-read every second).
    Monotonic,
    /// The frame's timestamp plus this offset, nanoseconds (0: the frames carry the log's clock,
    /// as `comanip-camera images` plays a `simrobot generate` directory).
    Offset(i64),
    /// The recorded time of the frame's sequence number in a `frames.txt` (nanoseconds on the
    /// log's clock; `sequence mod len`): frames played from that directory with any timing
    /// (`comanip-camera images --paced [--repeat]`).
    Index(Vec<u64>),
}

/// Maps frames to the bus clock ([`FrameClock`]), keeping the clock offset of the live case.
#[derive(Clone, Debug)]
pub struct ClockMap {
    clock: FrameClock,
    offset: Option<(i128, Instant)>,
}

impl ClockMap {
    /// A map of `clock`.
    pub fn new(clock: FrameClock) -> Self {
        Self { clock, offset: None }
    }

    /// `frame`'s time on the bus clock, nanoseconds; `None` when it cannot be (an empty index,
    /// out of range).
    pub fn bus_time(&mut self, frame: &FrameMeta) -> Option<u64> {
        match &self.clock {
            FrameClock::Monotonic => {
                let now = Instant::now();
                let offset = match self.offset {
                    Some((o, at)) if now.duration_since(at) < Duration::from_secs(1) => o,
                    _ => {
                        let o = hw_io::frame::realtime_minus_monotonic_ns();
                        self.offset = Some((o, now));
                        o
                    }
                };
                controller::bus_listen::bus_time_ns(frame.timestamp_ns, offset)
            }
            FrameClock::Offset(o) => frame.timestamp_ns.checked_add_signed(*o),
            FrameClock::Index(times) => {
                let i = usize::try_from(frame.sequence).ok()?.checked_rem(times.len())?;
                times.get(i).copied()
            }
        }
    }
}

/// Both arms' joints from the passive bus listener (`controller::bus_listen`, its own
/// SocketCAN socket or a replayed candump log): each arm's history read at the frame's time on
/// the bus clock, with staleness rules per arm (by default the 1 kHz ones, `Staleness::TOOL`,
/// `ENDOSCOPE`; [`BusJoints::with_staleness`] for another control period). When
/// the frame is newer than the newest tool sample, or no sample came yet (the listener has not
/// caught up), it waits up to `catch_up` (1 ms sleeps; not at all once a replayed log ended).
#[derive(Debug)]
pub struct BusJoints {
    listener: controller::bus_listen::ListenerThread,
    clock: ClockMap,
    catch_up: Duration,
    tool_staleness: controller::bus_listen::Staleness,
    endoscope_staleness: controller::bus_listen::Staleness,
}

impl BusJoints {
    /// Reads `listener`'s histories, frames mapped by `clock`.
    pub fn new(listener: controller::bus_listen::ListenerThread, clock: FrameClock, catch_up: Duration) -> Self {
        use controller::bus_listen::Staleness;
        Self {
            listener,
            clock: ClockMap::new(clock),
            catch_up,
            tool_staleness: Staleness::TOOL,
            endoscope_staleness: Staleness::ENDOSCOPE,
        }
    }

    /// The same, with these staleness rules for the tool arm and the endoscope arm.
    pub fn with_staleness(
        mut self,
        tool: controller::bus_listen::Staleness,
        endoscope: controller::bus_listen::Staleness,
    ) -> Self {
        (self.tool_staleness, self.endoscope_staleness) = (tool, endoscope);
        self
    }

    /// The listener's counters.
    pub fn stats(&self) -> controller::bus_listen::ListenStats {
        self.listener.stats()
    }

    /// Stops the listener's thread.
    pub fn stop(&mut self) {
        self.listener.stop();
    }
}

impl JointsAt for BusJoints {
    fn joints_at(&mut self, frame: &FrameMeta) -> Result<ArmJoints, JointsError> {
        let t = self.clock.bus_time(frame).ok_or(JointsError::BothStale)?;
        let start = Instant::now();
        while self.listener.latest_ns().0.is_none_or(|l| l < t)
            && !self.listener.ended()
            && start.elapsed() < self.catch_up
        {
            std::thread::sleep(Duration::from_millis(1));
        }
        let tool = self.listener.tool_at(t, &self.tool_staleness);
        let ecm = self.listener.endoscope_at(t, &self.endoscope_staleness);
        match (tool, ecm) {
            (Ok(a), Ok(b)) => Ok(ArmJoints { tool_rad: a.joints, endoscope: b.joints }),
            (Err(_), Ok(_)) => Err(JointsError::ToolStale),
            (Ok(_), Err(_)) => Err(JointsError::EndoscopeStale),
            (Err(_), Err(_)) => Err(JointsError::BothStale),
        }
    }
}

/// A received frame, read in place.
pub trait LiveFrame {
    /// Its checked metadata.
    fn meta(&self) -> &FrameMeta;
    /// Eye `index`'s bytes (0 left, 1 right).
    fn eye(&self, index: u32) -> Option<&[u8]>;
}

impl LiveFrame for ReceivedFrame {
    fn meta(&self) -> &FrameMeta {
        ReceivedFrame::meta(self)
    }
    fn eye(&self, index: u32) -> Option<&[u8]> {
        ReceivedFrame::eye(self, index)
    }
}

/// What a [`FrameSource`] delivered.
#[derive(Debug)]
pub enum Incoming<F> {
    /// A frame.
    Frame(F),
    /// A frame refused for its header (dropped by the source).
    Rejected(FrameHeaderError),
}

/// The frame source failed for good (the transport), not a frame.
#[derive(Debug, thiserror::Error)]
#[error("frame source: {0}")]
pub struct SourceError(pub String);

/// Where frames come from.
pub trait FrameSource {
    /// The frame type.
    type Frame: LiveFrame;
    /// The next frame, waiting at most `timeout`; `None` when none came.
    fn wait(&mut self, timeout: Duration) -> Result<Option<Incoming<Self::Frame>>, SourceError>;
    /// The next buffered frame, at once.
    fn try_next(&mut self) -> Result<Option<Incoming<Self::Frame>>, SourceError>;
    /// Frames lost in the transport so far (sequence gaps).
    fn missed(&self) -> u64;
}

fn from_recv(r: Result<Option<ReceivedFrame>, FrameRecvError>) -> Result<Option<Incoming<ReceivedFrame>>, SourceError> {
    match r {
        Ok(f) => Ok(f.map(Incoming::Frame)),
        Err(FrameRecvError::Header(h)) => Ok(Some(Incoming::Rejected(h))),
        Err(e) => Err(SourceError(e.to_string())),
    }
}

impl FrameSource for FrameSubscriber {
    type Frame = ReceivedFrame;
    fn wait(&mut self, timeout: Duration) -> Result<Option<Incoming<ReceivedFrame>>, SourceError> {
        match FrameSubscriber::wait(self, timeout) {
            Ok(f) => Ok(f.map(Incoming::Frame)),
            Err(FrameWaitError::Recv(e)) => from_recv(Err(e)),
            Err(e) => Err(SourceError(e.to_string())),
        }
    }
    fn try_next(&mut self) -> Result<Option<Incoming<ReceivedFrame>>, SourceError> {
        from_recv(self.try_recv())
    }
    fn missed(&self) -> u64 {
        self.counters().missed
    }
}

/// An in-process frame: metadata and shared pixels.
#[derive(Clone, Debug)]
pub struct MemoryFrame {
    /// The metadata.
    pub meta: FrameMeta,
    /// Both eyes, one after the other.
    pub pixels: Arc<[u8]>,
}

impl LiveFrame for MemoryFrame {
    fn meta(&self) -> &FrameMeta {
        &self.meta
    }
    fn eye(&self, index: u32) -> Option<&[u8]> {
        if index >= self.meta.eyes {
            return None;
        }
        let n = self.meta.layout.eye_bytes();
        let start = index as usize * n;
        self.pixels.get(start..start + n)
    }
}

/// An in-process frame source over a list (tests, benchmarks): each `wait` delivers the next
/// item; `burst` items at a time become available (the others are "arriving while the tracker
/// works").
#[derive(Debug)]
pub struct MemoryFrames {
    items: Vec<Incoming<MemoryFrame>>,
    next: usize,
    available: usize,
    burst: usize,
}

impl MemoryFrames {
    /// Delivers `items` in order, `burst` (≥ 1) of them per [`FrameSource::wait`].
    pub fn new(items: Vec<Incoming<MemoryFrame>>, burst: usize) -> Self {
        Self { items, next: 0, available: 0, burst: burst.max(1) }
    }

    /// The first `n` items already waiting before the first [`FrameSource::wait`] (as frames
    /// published while the loop was busy), for [`FrameSource::try_next`] too.
    #[must_use]
    pub fn waiting(mut self, n: usize) -> Self {
        self.available = self.available.max(n);
        self
    }

    fn take(&mut self) -> Option<Incoming<MemoryFrame>> {
        if self.next >= self.available || self.next >= self.items.len() {
            return None;
        }
        let item = match self.items.get(self.next)? {
            Incoming::Frame(f) => Incoming::Frame(f.clone()),
            Incoming::Rejected(e) => Incoming::Rejected(*e),
        };
        self.next += 1;
        Some(item)
    }
}

impl FrameSource for MemoryFrames {
    type Frame = MemoryFrame;
    fn wait(&mut self, _timeout: Duration) -> Result<Option<Incoming<MemoryFrame>>, SourceError> {
        if self.next >= self.available {
            self.available = self.next + self.burst;
        }
        Ok(self.take())
    }
    fn try_next(&mut self) -> Result<Option<Incoming<MemoryFrame>>, SourceError> {
        Ok(self.take())
    }
    fn missed(&self) -> u64 {
        0
    }
}

/// What a calibration source had since the last poll.
#[derive(Clone, Copy, Debug, PartialEq)]
#[allow(clippy::large_enum_variant, reason = "a 432-byte copy per poll; boxing would allocate in the loop")]
pub enum CalibrationPoll {
    /// Nothing new.
    Nothing,
    /// The newest message.
    Sample(CalibrationSample),
    /// Only refused messages (another version, a broken invariant).
    Refused,
}

/// Where the calibration comes from.
pub trait CalibrationSource {
    /// The newest message since the last poll, at once. Allocation-free.
    fn poll(&mut self) -> CalibrationPoll;
}

/// No live calibration: the configuration's transform throughout.
#[derive(Clone, Copy, Debug, Default)]
pub struct NoCalibration;

impl CalibrationSource for NoCalibration {
    fn poll(&mut self) -> CalibrationPoll {
        CalibrationPoll::Nothing
    }
}

impl CalibrationSource for Subscriber<CalibrationSample> {
    fn poll(&mut self) -> CalibrationPoll {
        let mut out = CalibrationPoll::Nothing;
        loop {
            match self.try_recv() {
                Ok(Some(r)) => out = CalibrationPoll::Sample(r.sample),
                Ok(None) => return out,
                Err(RecvError::VersionMismatch { .. } | RecvError::Invalid { .. }) => {
                    if out == CalibrationPoll::Nothing {
                        out = CalibrationPoll::Refused;
                    }
                }
                Err(RecvError::Receive(e)) => {
                    tracing::warn!("calibration subscriber: {e}");
                    return out;
                }
            }
        }
    }
}

/// Where samples go.
pub trait TrackSink {
    /// Publishes one sample. Allocation-free once connected.
    fn publish(&mut self, sample: &TrackSample) -> Result<(), hw_io::ipc::PublishError>;
}

impl TrackSink for Publisher<TrackSample> {
    fn publish(&mut self, sample: &TrackSample) -> Result<(), hw_io::ipc::PublishError> {
        Publisher::publish(self, sample)
    }
}

impl TrackSink for Vec<TrackSample> {
    fn publish(&mut self, sample: &TrackSample) -> Result<(), hw_io::ipc::PublishError> {
        self.push(*sample);
        Ok(())
    }
}

/// The stereo rig: intrinsics, the eyes' relative pose, the hand-eye transform.
#[derive(Clone, Copy, Debug)]
pub struct Rig {
    /// Left and right intrinsics (measured pixels).
    pub intrinsics: [Intrinsics; 2],
    /// `T_cr_cl`, metres.
    pub right_from_left: Isometry3<f64>,
    /// `T_f_c` of the left eye on the endoscope arm, metres.
    pub hand_eye: Isometry3<f64>,
}

/// Frame counters of the live process.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct LiveCounters {
    /// Frames with a sample (tracked, or refused for their input).
    pub processed: u64,
    /// Frames dropped for a newer one, or lost in the transport.
    pub skipped: u64,
    /// Frames with a corrupt header.
    pub rejected: u64,
    /// Of `processed`, refused for their input (`Invalid`).
    pub invalid: u64,
    /// Samples by status: invalid, tracking, uncertain, lost.
    pub by_status: [u64; 4],
}

/// Why the live tracker could not be built.
#[derive(Debug, thiserror::Error)]
pub enum LiveBuildError {
    /// The tracker's configuration.
    #[error(transparent)]
    Config(#[from] track::ConfigError),
    /// A transform of the configuration is not finite.
    #[error("{0}: not a finite transform")]
    Transform(&'static str),
}

/// The live tracker's state: the tracker, the rig, the calibration in use, the counters.
#[derive(Debug)]
pub struct LiveTracker {
    tracker: Tracker,
    started: bool,
    rig: Rig,
    config_ecm_in_tool_base: Isometry3<f64>,
    /// `(T_b_e, sequence, run_id)` of the valid live calibration in use.
    live_calibration: Option<(Isometry3<f64>, u64, u64)>,
    calibration_flags: TrackReasons,
    counters: LiveCounters,
    sequence: u64,
    run_id: u64,
}

fn finite_iso(t: &Isometry3<f64>) -> bool {
    t.translation.vector.iter().all(|v| v.is_finite()) && t.rotation.coords.iter().all(|v| v.is_finite())
}

fn wxyz(q: &UnitQuaternion<f64>) -> [f64; 4] {
    [q.w, q.i, q.j, q.k]
}

impl LiveTracker {
    /// A tracker of `cfg` on `model`, for `rig`, starting from `ecm_in_tool_base` (`T_b_e`,
    /// metres: the configuration's calibration); `run_id` goes into every sample.
    pub fn new(
        cfg: TrackerConfig,
        model: ToolModel,
        rig: Rig,
        ecm_in_tool_base: Isometry3<f64>,
        run_id: u64,
    ) -> Result<Self, LiveBuildError> {
        for (name, t) in [
            ("rig.hand_eye", &rig.hand_eye),
            ("right_from_left", &rig.right_from_left),
            ("rig.endoscope_in_tool_base", &ecm_in_tool_base),
        ] {
            if !finite_iso(t) {
                return Err(LiveBuildError::Transform(name));
            }
        }
        Ok(Self {
            tracker: Tracker::new(cfg, model)?,
            started: false,
            rig,
            config_ecm_in_tool_base: ecm_in_tool_base,
            live_calibration: None,
            calibration_flags: TrackReasons::CALIBRATION_FROM_CONFIG,
            counters: LiveCounters::default(),
            sequence: 0,
            run_id,
        })
    }

    /// The counters so far.
    pub fn counters(&self) -> LiveCounters {
        self.counters
    }

    /// The tracker's configuration.
    pub fn config(&self) -> &TrackerConfig {
        self.tracker.config()
    }

    /// Takes a calibration poll into account: a valid calibration replaces the transform in
    /// use; drift drops it (back to the configuration's); a refused message is flagged.
    pub fn update_calibration(&mut self, poll: CalibrationPoll) {
        self.calibration_flags.remove(TrackReasons::CALIBRATION_REFUSED);
        match poll {
            CalibrationPoll::Nothing => {}
            CalibrationPoll::Refused => self.calibration_flags.insert(TrackReasons::CALIBRATION_REFUSED),
            CalibrationPoll::Sample(c) => match c.state() {
                Some(CalibrationState::Valid) => {
                    let [w, x, y, z] = c.quaternion_wxyz;
                    let t_e_t = Isometry3::from_parts(
                        Translation3::from(Vector3::from(c.translation_m)),
                        UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
                    );
                    let t_b_e = t_e_t.inverse();
                    if finite_iso(&t_b_e) {
                        self.live_calibration = Some((t_b_e, c.sequence, c.run_id));
                        self.calibration_flags = TrackReasons::empty();
                    } else {
                        self.calibration_flags.insert(TrackReasons::CALIBRATION_REFUSED);
                    }
                }
                Some(CalibrationState::Drift) => {
                    self.live_calibration = None;
                    self.calibration_flags = TrackReasons::CALIBRATION_FROM_CONFIG | TrackReasons::CALIBRATION_DRIFT;
                }
                Some(CalibrationState::Collecting) | None => {}
            },
        }
    }

    fn base_sample(&mut self, reasons: TrackReasons) -> TrackSample {
        let mut s = TrackSample::invalid(reasons | self.calibration_flags);
        s.sequence = self.sequence;
        s.run_id = self.run_id;
        self.sequence += 1;
        if let Some((_, seq, run)) = self.live_calibration {
            s.calibration_source = 1;
            s.calibration_sequence = seq;
            s.calibration_run_id = run;
        }
        s
    }

    fn finish(&mut self, mut s: TrackSample) -> TrackSample {
        s.frames_processed = self.counters.processed;
        s.frames_skipped = self.counters.skipped;
        s.frames_rejected = self.counters.rejected;
        s.frames_invalid = self.counters.invalid;
        let k = (s.status as usize).min(3);
        self.counters.by_status[k] += 1;
        s.published_ns = monotonic_now_ns();
        s
    }

    fn refuse(&mut self, meta: Option<&FrameMeta>, reasons: TrackReasons) -> TrackSample {
        let mut s = self.base_sample(reasons);
        if let Some(m) = meta {
            s.frame_timestamp_ns = m.timestamp_ns;
            s.frame_sequence = m.sequence;
            self.counters.processed += 1;
            self.counters.invalid += 1;
        }
        self.finish(s)
    }

    /// A frame with a corrupt header arrived: its `Invalid` sample (frame fields zero).
    pub fn rejected(&mut self) -> TrackSample {
        self.counters.rejected += 1;
        self.refuse(None, TrackReasons::FRAME_HEADER)
    }

    /// `n` frames were skipped (dropped for a newer one or lost in the transport).
    pub fn skipped(&mut self, n: u64) {
        self.counters.skipped += n;
    }

    /// Tracks one frame, its joints from `joints`; returns its sample (never a non-finite
    /// number; bad input gives an `Invalid` sample with its reasons).
    pub fn frame<F: LiveFrame, J: JointsAt>(&mut self, frame: &F, joints: &mut J, skipped_before: bool) -> TrackSample {
        let meta = *frame.meta();
        let extra = if skipped_before { TrackReasons::SKIPPED_BEFORE } else { TrackReasons::empty() };
        let cfg = self.tracker.config();
        let l = meta.layout;
        let packed = l.stride == l.width.saturating_mul(3);
        if meta.eyes != 2
            || l.format != PixelFormat::Rgb8
            || !packed
            || l.width as usize != cfg.width
            || l.height as usize != cfg.height
        {
            return self.refuse(Some(&meta), TrackReasons::FRAME_FORMAT | extra);
        }
        let (Some(left), Some(right)) = (frame.eye(0), frame.eye(1)) else {
            return self.refuse(Some(&meta), TrackReasons::FRAME_FORMAT | extra);
        };
        let arms = match joints.joints_at(&meta) {
            Ok(a) => a,
            Err(e) => return self.refuse(Some(&meta), e.reasons() | extra),
        };
        if !arms.tool_rad.iter().chain(&arms.endoscope).all(|v| v.is_finite()) {
            return self.refuse(Some(&meta), TrackReasons::NOT_FINITE | extra);
        }
        let t_b_e = self.live_calibration.map_or(self.config_ecm_in_tool_base, |c| c.0);
        let cams = StereoCameras {
            intrinsics: self.rig.intrinsics,
            left_from_base: left_from_base(&t_b_e, &self.rig.hand_eye, &arms.endoscope),
            right_from_left: self.rig.right_from_left,
        };
        if !cams.is_valid() {
            return self.refuse(Some(&meta), TrackReasons::NOT_FINITE | extra);
        }
        let first = !self.started;
        let est = match step_frame(
            &mut self.tracker,
            &mut self.started,
            None,
            arms.tool_rad,
            cams,
            [left, right],
            Some(meta.timestamp_ns.saturating_add(u64::from(meta.exposure_ns / 2))),
        ) {
            Ok(e) => e,
            Err(StepError::Encoder(_) | StepError::Cameras) => {
                return self.refuse(Some(&meta), TrackReasons::NOT_FINITE | extra);
            }
            Err(StepError::Image { .. }) => return self.refuse(Some(&meta), TrackReasons::FRAME_FORMAT | extra),
            Err(StepError::Kinematics) => return self.refuse(Some(&meta), TrackReasons::TRACKER_REFUSED | extra),
        };
        let mut reasons = extra;
        if est.reinitialised || first {
            reasons |= TrackReasons::REINITIALISED;
        }
        let mut s = self.base_sample(reasons);
        s.frame_timestamp_ns = meta.timestamp_ns;
        s.frame_sequence = meta.sequence;
        self.counters.processed += 1;
        s.spread_m = if est.spread_m.is_finite() { est.spread_m } else { -1.0 };
        s.best_cost_px = if est.best_cost_px.is_finite() { est.best_cost_px } else { -1.0 };
        s.status = match est.status {
            Status::Tracking => TrackStatus::Tracking,
            Status::Uncertain => TrackStatus::Uncertain,
            Status::Lost => TrackStatus::Lost,
        } as u32;
        match est.pose {
            Some(p) if est.status != Status::Lost => {
                s.tip_camera_m = p.tip_in_camera.translation.vector.into();
                s.tip_camera_wxyz = wxyz(&p.tip_in_camera.rotation);
                s.tip_base_m = p.tip_in_base.translation.vector.into();
                s.tip_base_wxyz = wxyz(&p.tip_in_base.rotation);
                s.jaw_rad = p.jaw_rad;
                s.camera_delta = p.camera_delta;
            }
            _ => s.status = TrackStatus::Lost as u32,
        }
        // The tracker guarantees finite poses; the message's own check is the last guard.
        if hw_io::ipc::Message::check(&s).is_err() {
            self.counters.invalid += 1;
            let mut bad = TrackSample::invalid(TrackReasons::NOT_FINITE | reasons | self.calibration_flags);
            bad.sequence = s.sequence;
            bad.run_id = s.run_id;
            bad.frame_timestamp_ns = s.frame_timestamp_ns;
            bad.frame_sequence = s.frame_sequence;
            bad.calibration_source = s.calibration_source;
            bad.calibration_sequence = s.calibration_sequence;
            bad.calibration_run_id = s.calibration_run_id;
            return self.finish(bad);
        }
        self.finish(s)
    }
}

/// When the loop stops.
#[derive(Clone, Copy, Debug)]
pub struct LoopOptions<'a> {
    /// Stop after this many frames handled (processed + rejected).
    pub max_frames: Option<u64>,
    /// Stop when no frame came for this long after the first one (`None`: never).
    pub idle_timeout: Option<Duration>,
    /// Stop when set (signal handlers).
    pub stop: &'a AtomicBool,
}

/// Why the loop stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    /// The frame source failed.
    #[error(transparent)]
    Source(#[from] SourceError),
    /// Publishing failed.
    #[error("cannot publish a track sample: {0}")]
    Publish(#[from] hw_io::ipc::PublishError),
}

/// The loop: wait for a frame, keep the newest of those buffered, poll the calibration, track,
/// publish; `on_sample` sees each sample with the `CLOCK_MONOTONIC` time its frame was taken
/// from the source (nanoseconds). Returns when a stop condition of `opts` holds.
pub fn run<S, J, C, P>(
    live: &mut LiveTracker,
    source: &mut S,
    joints: &mut J,
    calibration: &mut C,
    sink: &mut P,
    opts: &LoopOptions<'_>,
    on_sample: &mut dyn FnMut(&TrackSample, u64),
) -> Result<LiveCounters, LiveError>
where
    S: FrameSource,
    J: JointsAt,
    C: CalibrationSource,
    P: TrackSink,
{
    let mut handled = 0u64;
    let mut last_frame: Option<Instant> = None;
    let mut missed_seen = source.missed();
    while !opts.stop.load(Ordering::Relaxed) && opts.max_frames.is_none_or(|m| handled < m) {
        let Some(first) = source.wait(Duration::from_millis(100))? else {
            if let (Some(t), Some(idle)) = (last_frame, opts.idle_timeout)
                && t.elapsed() >= idle
            {
                break;
            }
            continue;
        };
        let received_ns = monotonic_now_ns();
        last_frame = Some(Instant::now());
        // Keep the newest frame; publish a refusal for each corrupt one at once.
        let mut current = None;
        let mut dropped = 0u64;
        let mut next = Some(first);
        while let Some(item) = next {
            match item {
                Incoming::Frame(f) => {
                    if current.replace(f).is_some() {
                        dropped += 1;
                    }
                }
                Incoming::Rejected(_) => {
                    let s = live.rejected();
                    sink.publish(&s)?;
                    on_sample(&s, received_ns);
                    handled += 1;
                }
            }
            next = source.try_next()?;
        }
        let missed = source.missed();
        let skipped = dropped + missed.saturating_sub(missed_seen);
        missed_seen = missed;
        live.skipped(skipped);
        let Some(frame) = current else { continue };
        live.update_calibration(calibration.poll());
        let s = live.frame(&frame, joints, skipped > 0);
        drop(frame);
        sink.publish(&s)?;
        on_sample(&s, received_ns);
        handled += 1;
    }
    // Stopping: the frames still waiting in the source (published before the stop, not taken
    // by the loop) are counted as skipped, and the transport's gap up to the newest of them
    // too, so that the counters account for every frame published up to the stop however far
    // behind the loop had fallen (a corrupt one is refused as in the loop). A source error
    // here ends the drain: the loop itself stopped cleanly.
    let mut dropped = 0u64;
    while let Ok(Some(item)) = source.try_next() {
        match item {
            Incoming::Frame(_) => dropped += 1,
            Incoming::Rejected(_) => {
                let s = live.rejected();
                sink.publish(&s)?;
                on_sample(&s, monotonic_now_ns());
            }
        }
    }
    live.skipped(dropped + source.missed().saturating_sub(missed_seen));
    Ok(live.counters())
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;
    use hw_io::frame::ImageLayout;

    fn meta(sequence: u64, timestamp_ns: u64) -> FrameMeta {
        FrameMeta {
            sequence,
            camera_id: 0,
            timestamp_ns,
            exposure_ns: 0,
            eyes: 2,
            layout: ImageLayout::packed(4, 3, PixelFormat::Rgb8).unwrap(),
        }
    }

    #[test]
    fn frame_clocks_map_frames_to_the_bus_clock() {
        // Live: a frame stamped now on CLOCK_MONOTONIC is now on CLOCK_REALTIME.
        let mut live = ClockMap::new(FrameClock::Monotonic);
        let bus = live.bus_time(&meta(0, monotonic_now_ns())).unwrap();
        let unix_ns = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos() as u64;
        assert!(unix_ns.abs_diff(bus) < 50_000_000, "{bus} vs {unix_ns}");
        let mut off = ClockMap::new(FrameClock::Offset(-5));
        assert_eq!(off.bus_time(&meta(0, 100)), Some(95));
        assert_eq!(off.bus_time(&meta(0, 2)), None, "before the clock's origin");
        let mut index = ClockMap::new(FrameClock::Index(vec![10, 20, 30]));
        assert_eq!(index.bus_time(&meta(1, 999)), Some(20));
        assert_eq!(index.bus_time(&meta(4, 999)), Some(20), "a repeated sequence wraps");
        assert_eq!(ClockMap::new(FrameClock::Index(Vec::new())).bus_time(&meta(0, 1)), None);
    }
}
