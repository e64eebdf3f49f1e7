//! The ground-truth file of a simulated run (`truth.jsonl`): JSON Lines, written next to the
//! CAN log, read back to score a detector. The format is documented in `docs/simulator.md`.
//!
//! One JSON object per line, told apart by `"type"`:
//! - `header` (always line 1): format name and version, the time base (`t0_unix_time_us`:
//!   Unix time of the SYNC of sample 0, as in the CAN log), the sample period, the state-line
//!   decimation, the trocar positions (metres, robot base frame), the scenario parameters
//!   and, from `simrobot`, the whole twin configuration;
//! - `event`: a true insertion or extraction ([`TwinEvent`]); its `sample` is the first
//!   sample of the new state: the sample at which the tip has crossed the trocar point;
//! - `state`: the true state, pivot and instrument line of one sample ([`TruthRecord`]).
//!   Written every `state_every` samples and, whatever the decimation, at the first and the
//!   last sample of every stretch of constant state (so every state change is between two
//!   adjacent state lines);
//! - `scenario`: a scenario starts (endless mode: seed and the run sample of its sample 0);
//! - `endoscope`: the endoscope-holder arm's true joints at a sample where its nodes sent
//!   their TPDOs (every 10th SYNC by default; [`EndoscopeRecord`]);
//! - `end` (always last): number of samples and events, so a truncated file is detected.
//!
//! Lines are in the order they happen. The state is piecewise constant between events, so
//! the state of every sample is exact; the pivot and the line between two state lines are
//! interpolated linearly: exact at the state lines, so everywhere at full rate
//! (`state_every = 1`); at the default 10 ms the pivot is off by up to about 10 µm where its
//! path has a kink (start and end of the manipulation), the wrist by up to millimetres where
//! the free motion has one.

use std::fs::File;
use std::io::{self, BufRead, BufReader, Write};
use std::path::Path;

use estimator::trocar::LineSample;
use nalgebra::Vector3;
use serde::{Deserialize, Serialize};

use crate::scenario::{Scenario, ScenarioConfig, TrueEvent, Truth, TruthState};
use crate::score::{Detected, GroundTruth, Score, score_against};
use crate::twin::{TwinConfig, TwinEvent};

/// Value of the header's `format` field.
pub const FORMAT: &str = "comanip-truth";

/// Version of the format this module writes and reads.
pub const VERSION: u32 = 1;

/// Default decimation of the state lines: one every 10 samples (10 ms).
pub const DEFAULT_STATE_EVERY: u64 = 10;

/// The first line of a truth file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TruthHeader {
    /// Always [`FORMAT`].
    pub format: String,
    /// Format version, [`VERSION`].
    pub version: u32,
    /// Sample period, seconds (one sample per SYNC: 0.001).
    pub sample_period_s: f64,
    /// Time of the SYNC of sample 0, microseconds since the Unix epoch, the time base of the
    /// CAN log written with this file.
    pub t0_unix_time_us: u64,
    /// A state line is written every `state_every` samples (and at every state change).
    pub state_every: u64,
    /// Trocar positions, metres, robot base frame (nominal; the trocar index of the events
    /// and states refers to this list).
    pub trocars_base_m: Vec<[f64; 3]>,
    /// Parameters of the (first) scenario.
    pub scenario: ScenarioConfig,
    /// The twin's whole configuration, when written by `simrobot`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub twin: Option<TwinConfig>,
}

impl TruthHeader {
    /// A header for `scenario` with sample 0 at `t0_unix_time_us` (microseconds since the
    /// Unix epoch) and a state line every `state_every` samples.
    pub fn new(scenario: &ScenarioConfig, t0_unix_time_us: u64, state_every: u64) -> Self {
        Self {
            format: FORMAT.to_owned(),
            version: VERSION,
            sample_period_s: scenario.sample_period_s,
            t0_unix_time_us,
            state_every,
            trocars_base_m: scenario.trocars_base_m.clone(),
            scenario: scenario.clone(),
            twin: None,
        }
    }
}

/// The true state of one sample, as in a `state` line.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TruthRecord {
    /// Sample index from the start of the run.
    pub sample: u64,
    /// Time, seconds since sample 0.
    pub t_s: f64,
    /// Time of the sample's SYNC, microseconds since the Unix epoch.
    pub unix_time_us: u64,
    /// True state.
    pub state: TruthState,
    /// True pivot while inside, metres, robot base frame.
    pub fulcrum_base_m: Option<Vector3<f64>>,
    /// True (noise-free) instrument line, metres and unit axis, robot base frame.
    pub line: LineSample,
}

/// The endoscope-holder arm's true joints at one sample, as in an `endoscope` line.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EndoscopeRecord {
    /// Sample index from the start of the run.
    pub sample: u64,
    /// Time of the sample's SYNC, microseconds since the Unix epoch (the CAN log's clock).
    pub unix_time_us: u64,
    /// `[yaw rad, pitch rad, insertion m, roll rad]` (ECM model, `docs/calibration.md`).
    pub joints: [f64; 4],
}

/// A scenario start (endless mode), as in a `scenario` line.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScenarioStart {
    /// Run sample index of the scenario's sample 0.
    pub sample: u64,
    /// Seed of the scenario.
    pub seed: u64,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum EventKind {
    Insertion,
    Extraction,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum StateKind {
    Outside,
    Inside,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct EventLine {
    event: EventKind,
    trocar: usize,
    sample: u64,
    t_s: f64,
    unix_time_us: u64,
}

#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct StateLine {
    sample: u64,
    t_s: f64,
    unix_time_us: u64,
    state: StateKind,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    trocar: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    fulcrum_base_m: Option<[f64; 3]>,
    wrist_base_m: [f64; 3],
    axis_base: [f64; 3],
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct EndLine {
    samples: u64,
    events: u64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case")]
enum Line {
    Header(Box<TruthHeader>),
    Event(EventLine),
    State(StateLine),
    Scenario(ScenarioStart),
    Endoscope(EndoscopeRecord),
    End(EndLine),
}

fn arr(v: &Vector3<f64>) -> [f64; 3] {
    [v.x, v.y, v.z]
}

fn vec3(a: &[f64; 3]) -> Vector3<f64> {
    Vector3::new(a[0], a[1], a[2])
}

impl From<&TruthRecord> for StateLine {
    fn from(r: &TruthRecord) -> Self {
        let (state, trocar) = match r.state {
            TruthState::Outside => (StateKind::Outside, None),
            TruthState::Inside { index } => (StateKind::Inside, Some(index)),
        };
        StateLine {
            sample: r.sample,
            t_s: r.t_s,
            unix_time_us: r.unix_time_us,
            state,
            trocar,
            fulcrum_base_m: r.fulcrum_base_m.as_ref().map(arr),
            wrist_base_m: arr(&r.line.wrist_base_m),
            axis_base: arr(&r.line.axis_base),
        }
    }
}

impl From<&TwinEvent> for EventLine {
    fn from(e: &TwinEvent) -> Self {
        EventLine {
            event: if e.insertion { EventKind::Insertion } else { EventKind::Extraction },
            trocar: e.trocar,
            sample: e.sample,
            t_s: e.t_s,
            unix_time_us: e.unix_time_us,
        }
    }
}

// ----------------------------------------------------------------------------------------
// Writing

/// Why a truth file could not be written.
#[derive(Debug, thiserror::Error)]
pub enum TruthWriteError {
    /// The underlying writer failed.
    #[error("writing truth file: {0}")]
    Io(#[from] io::Error),
    /// JSON serialisation failed.
    #[error("writing truth file: {0}")]
    Json(#[from] serde_json::Error),
    /// An event given with a sample that is not the one being written.
    #[error("truth file: event for sample {got} given with sample {expected}")]
    EventSample {
        /// The sample being written.
        expected: u64,
        /// The event's sample.
        got: u64,
    },
    /// A non-finite time, position or axis (JSON has no NaN).
    #[error("truth file: sample {sample} has a non-finite value")]
    NonFinite {
        /// The sample.
        sample: u64,
    },
    /// A header with `state_every = 0`.
    #[error("truth file: state_every must be at least 1")]
    ZeroStateEvery,
}

/// Writes a truth file sample by sample (streaming: nothing is kept but the previous sample).
#[derive(Debug)]
pub struct TruthWriter<W: Write> {
    inner: W,
    state_every: u64,
    samples: u64,
    events: u64,
    /// The previous sample and whether its state line was written.
    prev: Option<(TruthRecord, bool)>,
}

impl<W: Write> TruthWriter<W> {
    /// Writes the header line. Wrap files in a `BufWriter`.
    pub fn new(mut inner: W, header: &TruthHeader) -> Result<Self, TruthWriteError> {
        if header.state_every == 0 {
            return Err(TruthWriteError::ZeroStateEvery);
        }
        serde_json::to_writer(&mut inner, &Line::Header(Box::new(header.clone())))?;
        inner.write_all(b"\n")?;
        Ok(Self { inner, state_every: header.state_every, samples: 0, events: 0, prev: None })
    }

    fn write_line(&mut self, line: &Line) -> Result<(), TruthWriteError> {
        serde_json::to_writer(&mut self.inner, line)?;
        self.inner.write_all(b"\n")?;
        Ok(())
    }

    /// Samples written so far (the index of the next one).
    pub fn samples(&self) -> u64 {
        self.samples
    }

    /// Notes that a scenario starts with `seed`, its sample 0 being run sample `sample`.
    pub fn scenario(&mut self, start: ScenarioStart) -> Result<(), TruthWriteError> {
        self.write_line(&Line::Scenario(start))
    }

    /// Writes the next sample: its SYNC time (microseconds since the Unix epoch), its truth
    /// (`t_s` in seconds since sample 0, positions in metres, robot base frame) and the true
    /// events at this sample (each with `sample` equal to this sample's index).
    pub fn sample(&mut self, unix_time_us: u64, truth: &Truth, events: &[TwinEvent]) -> Result<(), TruthWriteError> {
        let i = self.samples;
        if let Some(e) = events.iter().find(|e| e.sample != i) {
            return Err(TruthWriteError::EventSample { expected: i, got: e.sample });
        }
        let finite = truth.t_s.is_finite()
            && truth.line.wrist_base_m.iter().chain(truth.line.axis_base.iter()).all(|v| v.is_finite())
            && truth.fulcrum_base_m.is_none_or(|f| f.iter().all(|v| v.is_finite()))
            && events.iter().all(|e| e.t_s.is_finite());
        if !finite {
            return Err(TruthWriteError::NonFinite { sample: i });
        }
        let rec = TruthRecord {
            sample: i,
            t_s: truth.t_s,
            unix_time_us,
            state: truth.state,
            fulcrum_base_m: truth.fulcrum_base_m,
            line: truth.line,
        };
        let changed = self.prev.is_none_or(|(p, _)| p.state != rec.state);
        if let Some((p, false)) = self.prev.filter(|_| changed) {
            // The last sample of the previous state.
            self.write_line(&Line::State(StateLine::from(&p)))?;
        }
        for e in events {
            self.write_line(&Line::Event(EventLine::from(e)))?;
            self.events += 1;
        }
        let write_now = changed || i.is_multiple_of(self.state_every);
        if write_now {
            self.write_line(&Line::State(StateLine::from(&rec)))?;
        }
        self.prev = Some((rec, write_now));
        self.samples += 1;
        Ok(())
    }

    /// Writes an `endoscope` line: the endoscope arm's true joints at `record.sample` (a
    /// sample already given to [`TruthWriter::sample`]).
    pub fn endoscope(&mut self, record: &EndoscopeRecord) -> Result<(), TruthWriteError> {
        if !record.joints.iter().all(|v| v.is_finite()) {
            return Err(TruthWriteError::NonFinite { sample: record.sample });
        }
        self.write_line(&Line::Endoscope(*record))
    }

    /// Writes the last sample's state line (if not yet written) and the end line, flushes,
    /// and gives back the writer.
    pub fn finish(mut self) -> Result<W, TruthWriteError> {
        if let Some((p, false)) = self.prev {
            self.write_line(&Line::State(StateLine::from(&p)))?;
        }
        let end = EndLine { samples: self.samples, events: self.events };
        self.write_line(&Line::End(end))?;
        self.inner.flush()?;
        Ok(self.inner)
    }
}

/// Writes a whole in-memory scenario as a truth file: sample `i` at
/// `t0_unix_time_us + i · sample period` (microseconds since the Unix epoch), a state line
/// every `state_every` samples. Event times are the sample times (`i · sample period`).
pub fn write_scenario<W: Write>(
    inner: W,
    scenario: &Scenario,
    t0_unix_time_us: u64,
    state_every: u64,
) -> Result<W, TruthWriteError> {
    let mut w = TruthWriter::new(inner, &TruthHeader::new(&scenario.config, t0_unix_time_us, state_every))?;
    let period_us = period_us(scenario.config.sample_period_s);
    let mut next_event = 0;
    let mut events: Vec<TwinEvent> = Vec::new();
    for (i, truth) in scenario.truth.iter().enumerate() {
        let t_us = t0_unix_time_us.saturating_add((i as u64).saturating_mul(period_us));
        events.clear();
        while let Some(e) = scenario.events.get(next_event).filter(|e| e.sample == i) {
            events.push(TwinEvent {
                sample: i as u64,
                t_s: truth.t_s,
                unix_time_us: t_us,
                trocar: e.trocar,
                insertion: e.insertion,
            });
            next_event += 1;
        }
        w.sample(t_us, truth, &events)?;
    }
    w.finish()
}

/// A sample period in whole microseconds (at least 1).
fn period_us(sample_period_s: f64) -> u64 {
    let us = (sample_period_s * 1e6).round();
    if us.is_finite() && us >= 1.0 { us as u64 } else { 1 }
}

// ----------------------------------------------------------------------------------------
// Reading

/// What is wrong with one line of a truth file.
#[derive(Debug, thiserror::Error)]
pub enum TruthLineError {
    /// Not valid UTF-8.
    #[error("not UTF-8")]
    NotUtf8,
    /// Not JSON, or not one of the known line types with its fields.
    #[error("{0}")]
    Json(#[source] serde_json::Error),
    /// The first line is not a header, or a header after the first line.
    #[error("the header must be line 1, and only line 1")]
    HeaderPlacement,
    /// Another format.
    #[error("format {found:?} is not {FORMAT:?}")]
    Format {
        /// The format found.
        found: String,
    },
    /// Another version.
    #[error("format version {found} is not supported (this reader reads version {VERSION})")]
    Version {
        /// The version found.
        found: u32,
    },
    /// A header value out of range.
    #[error("header: {0}")]
    BadHeader(&'static str),
    /// A sample index or time goes backwards, or the first state line is not sample 0.
    #[error("out of order: {0}")]
    Order(&'static str),
    /// A trocar index beyond the header's list.
    #[error("trocar {index} does not exist (the header lists {trocars})")]
    Trocar {
        /// The index.
        index: usize,
        /// Trocars in the header.
        trocars: usize,
    },
    /// A state line with a fulcrum while outside, or none while inside.
    #[error("a state line has a fulcrum exactly while inside")]
    Fulcrum,
    /// The line contradicts the events before it.
    #[error("inconsistent with the events: {0}")]
    Inconsistent(&'static str),
    /// The end line's counts do not match the file.
    #[error("end line says {said_samples} samples and {said_events} events, the file has {samples} and {events}")]
    EndCounts {
        /// Samples in the end line.
        said_samples: u64,
        /// Events in the end line.
        said_events: u64,
        /// Samples in the file (last state line + 1).
        samples: u64,
        /// Events in the file.
        events: u64,
    },
    /// Text after the end line.
    #[error("text after the end line")]
    AfterEnd,
}

/// Why a truth file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum TruthReadError {
    /// The underlying reader failed.
    #[error("reading truth file: {0}")]
    Io(#[from] io::Error),
    /// A line is malformed or inconsistent.
    #[error("truth file line {line}: {kind}")]
    Line {
        /// Line number, 1-based.
        line: u64,
        /// What is wrong.
        kind: TruthLineError,
    },
    /// No line at all.
    #[error("truth file is empty")]
    Empty,
    /// No end line: the file is truncated.
    #[error("truth file has no end line after line {last_line} (truncated?)")]
    MissingEnd {
        /// Number of the last line read.
        last_line: u64,
    },
}

impl TruthReadError {
    /// The 1-based line number, for a line-level error.
    pub fn line(&self) -> Option<u64> {
        match self {
            TruthReadError::Line { line, .. } => Some(*line),
            _ => None,
        }
    }
}

/// A truth file read back and checked: header, events, state lines, scenario starts.
#[derive(Clone, Debug, PartialEq)]
pub struct TruthFile {
    header: TruthHeader,
    events: Vec<TwinEvent>,
    states: Vec<TruthRecord>,
    scenarios: Vec<ScenarioStart>,
    endoscope: Vec<EndoscopeRecord>,
    samples: u64,
}

/// Reading state: everything checked line by line.
struct Parser {
    header: Option<TruthHeader>,
    file: Vec<TruthRecord>,
    events: Vec<TwinEvent>,
    scenarios: Vec<ScenarioStart>,
    endoscope: Vec<EndoscopeRecord>,
    /// State after every event read so far.
    state: TruthState,
    /// Sample of the last event not yet followed by its state line.
    pending_event: Option<u64>,
    last_time_us: u64,
    end: Option<EndLine>,
}

impl Parser {
    fn trocar(&self, index: usize) -> Result<(), TruthLineError> {
        let trocars = self.header.as_ref().map_or(0, |h| h.trocars_base_m.len());
        if index < trocars { Ok(()) } else { Err(TruthLineError::Trocar { index, trocars }) }
    }

    fn time(&mut self, t: u64) -> Result<(), TruthLineError> {
        if t < self.last_time_us {
            return Err(TruthLineError::Order("unix_time_us goes backwards"));
        }
        self.last_time_us = t;
        Ok(())
    }

    fn line(&mut self, line: Line) -> Result<(), TruthLineError> {
        if self.end.is_some() {
            return Err(TruthLineError::AfterEnd);
        }
        match line {
            Line::Header(h) => {
                if self.header.is_some() {
                    return Err(TruthLineError::HeaderPlacement);
                }
                if h.format != FORMAT {
                    return Err(TruthLineError::Format { found: h.format });
                }
                if h.version != VERSION {
                    return Err(TruthLineError::Version { found: h.version });
                }
                if !(h.sample_period_s.is_finite() && h.sample_period_s > 0.0) {
                    return Err(TruthLineError::BadHeader("sample_period_s must be positive"));
                }
                if h.state_every == 0 {
                    return Err(TruthLineError::BadHeader("state_every must be at least 1"));
                }
                if h.trocars_base_m.is_empty() {
                    return Err(TruthLineError::BadHeader("trocars_base_m is empty"));
                }
                self.last_time_us = h.t0_unix_time_us;
                self.header = Some(*h);
            }
            _ if self.header.is_none() => return Err(TruthLineError::HeaderPlacement),
            Line::Event(e) => {
                self.trocar(e.trocar)?;
                if let Some(last) = self.file.last()
                    && e.sample <= last.sample
                {
                    return Err(TruthLineError::Order("event at or before the last state line"));
                }
                if self.events.last().is_some_and(|p| p.sample > e.sample) {
                    return Err(TruthLineError::Order("event before the previous event"));
                }
                if self.pending_event.is_some_and(|p| p != e.sample) {
                    return Err(TruthLineError::Inconsistent("an event has no state line at its sample"));
                }
                self.time(e.unix_time_us)?;
                self.state = match (e.event, self.state) {
                    (EventKind::Insertion, TruthState::Outside) => TruthState::Inside { index: e.trocar },
                    (EventKind::Extraction, TruthState::Inside { index }) if index == e.trocar => TruthState::Outside,
                    (EventKind::Insertion, _) => return Err(TruthLineError::Inconsistent("insertion while inside")),
                    (EventKind::Extraction, _) => {
                        return Err(TruthLineError::Inconsistent("extraction from a trocar the tip is not in"));
                    }
                };
                self.pending_event = Some(e.sample);
                self.events.push(TwinEvent {
                    sample: e.sample,
                    t_s: e.t_s,
                    unix_time_us: e.unix_time_us,
                    trocar: e.trocar,
                    insertion: e.event == EventKind::Insertion,
                });
            }
            Line::State(s) => {
                let state = match (s.state, s.trocar) {
                    (StateKind::Outside, None) => TruthState::Outside,
                    (StateKind::Inside, Some(index)) => {
                        self.trocar(index)?;
                        TruthState::Inside { index }
                    }
                    (StateKind::Outside, Some(_)) => return Err(TruthLineError::Inconsistent("outside with a trocar")),
                    (StateKind::Inside, None) => return Err(TruthLineError::Inconsistent("inside without a trocar")),
                };
                if s.fulcrum_base_m.is_some() != (s.state == StateKind::Inside) {
                    return Err(TruthLineError::Fulcrum);
                }
                match self.file.last() {
                    None if s.sample != 0 => return Err(TruthLineError::Order("the first state line is not sample 0")),
                    Some(p) if s.sample <= p.sample => {
                        return Err(TruthLineError::Order("sample index goes backwards"));
                    }
                    Some(p) if p.state != state && s.sample != p.sample.saturating_add(1) => {
                        return Err(TruthLineError::Inconsistent(
                            "the state changes between two state lines that are not adjacent samples",
                        ));
                    }
                    _ => {}
                }
                if self.pending_event.is_some_and(|p| p != s.sample) {
                    return Err(TruthLineError::Inconsistent("an event has no state line at its sample"));
                }
                if state != self.state {
                    return Err(TruthLineError::Inconsistent("the state is not the one the events lead to"));
                }
                self.time(s.unix_time_us)?;
                self.pending_event = None;
                self.file.push(TruthRecord {
                    sample: s.sample,
                    t_s: s.t_s,
                    unix_time_us: s.unix_time_us,
                    state,
                    fulcrum_base_m: s.fulcrum_base_m.as_ref().map(vec3),
                    line: LineSample::new(vec3(&s.wrist_base_m), vec3(&s.axis_base)),
                });
            }
            Line::Scenario(start) => {
                if self.scenarios.last().is_some_and(|p| p.sample > start.sample) {
                    return Err(TruthLineError::Order("scenario starts go backwards"));
                }
                self.scenarios.push(start);
            }
            Line::Endoscope(e) => {
                if self.endoscope.last().is_some_and(|p| p.sample >= e.sample) {
                    return Err(TruthLineError::Order("endoscope lines go backwards"));
                }
                self.endoscope.push(e);
            }
            Line::End(end) => {
                if self.pending_event.is_some() {
                    return Err(TruthLineError::Inconsistent("an event has no state line at its sample"));
                }
                let samples = self.file.last().map_or(0, |r| r.sample.saturating_add(1));
                let events = self.events.len() as u64;
                if end.samples != samples || end.events != events {
                    return Err(TruthLineError::EndCounts {
                        said_samples: end.samples,
                        said_events: end.events,
                        samples,
                        events,
                    });
                }
                self.end = Some(end);
            }
        }
        Ok(())
    }
}

impl TruthFile {
    /// Reads and checks a whole truth file. Blank lines are skipped; every error names its
    /// 1-based line number.
    pub fn read(mut input: impl BufRead) -> Result<Self, TruthReadError> {
        let mut p = Parser {
            header: None,
            file: Vec::new(),
            events: Vec::new(),
            scenarios: Vec::new(),
            endoscope: Vec::new(),
            state: TruthState::Outside,
            pending_event: None,
            last_time_us: 0,
            end: None,
        };
        let mut buf = Vec::with_capacity(512);
        let mut line_no = 0u64;
        loop {
            buf.clear();
            if input.read_until(b'\n', &mut buf)? == 0 {
                break;
            }
            line_no += 1;
            if buf.iter().all(u8::is_ascii_whitespace) {
                continue;
            }
            let err = |kind| TruthReadError::Line { line: line_no, kind };
            let text = std::str::from_utf8(&buf).map_err(|_| err(TruthLineError::NotUtf8))?;
            let line: Line = serde_json::from_str(text).map_err(|e| err(TruthLineError::Json(e)))?;
            p.line(line).map_err(err)?;
        }
        let Some(header) = p.header else {
            return Err(TruthReadError::Empty);
        };
        let Some(end) = p.end else {
            return Err(TruthReadError::MissingEnd { last_line: line_no });
        };
        Ok(Self {
            header,
            events: p.events,
            states: p.file,
            scenarios: p.scenarios,
            endoscope: p.endoscope,
            samples: end.samples,
        })
    }

    /// Opens and reads the truth file at `path`.
    pub fn open(path: &Path) -> Result<Self, TruthReadError> {
        Self::read(BufReader::new(File::open(path)?))
    }

    /// The header.
    pub fn header(&self) -> &TruthHeader {
        &self.header
    }

    /// The true events, in time order.
    pub fn events(&self) -> &[TwinEvent] {
        &self.events
    }

    /// The state lines, in sample order.
    pub fn states(&self) -> &[TruthRecord] {
        &self.states
    }

    /// The scenario starts.
    pub fn scenarios(&self) -> &[ScenarioStart] {
        &self.scenarios
    }

    /// The endoscope arm's true joints, in sample order (empty when the arm was off).
    pub fn endoscope(&self) -> &[EndoscopeRecord] {
        &self.endoscope
    }

    /// Number of samples of the run.
    pub fn samples(&self) -> u64 {
        self.samples
    }

    /// The truth of `sample` (`None` past the end): exact at a state line, else the state
    /// (exact) with the pivot and the line interpolated linearly between the neighbouring
    /// state lines (metres, robot base frame; the axis renormalised; `t_s` and
    /// `unix_time_us` interpolated too).
    pub fn record_at(&self, sample: u64) -> Option<TruthRecord> {
        if sample >= self.samples {
            return None;
        }
        let k = self.states.partition_point(|r| r.sample <= sample).checked_sub(1)?;
        let a = &self.states[k];
        if a.sample == sample {
            return Some(*a);
        }
        // The last sample always has a state line, so there is a next one.
        let b = self.states.get(k + 1)?;
        let u = (sample - a.sample) as f64 / (b.sample - a.sample) as f64;
        let lerp = |x: &Vector3<f64>, y: &Vector3<f64>| x + (y - x) * u;
        let axis = lerp(&a.line.axis_base, &b.line.axis_base);
        Some(TruthRecord {
            sample,
            t_s: a.t_s + (b.t_s - a.t_s) * u,
            unix_time_us: a.unix_time_us + ((b.unix_time_us - a.unix_time_us) as f64 * u) as u64,
            state: a.state,
            fulcrum_base_m: match (&a.fulcrum_base_m, &b.fulcrum_base_m) {
                (Some(x), Some(y)) => Some(lerp(x, y)),
                _ => a.fulcrum_base_m,
            },
            line: LineSample::new(lerp(&a.line.wrist_base_m, &b.line.wrist_base_m), axis.normalize()),
        })
    }

    /// The true state of `sample` (exact), `None` past the end.
    pub fn state_at(&self, sample: u64) -> Option<TruthState> {
        if sample >= self.samples {
            return None;
        }
        let k = self.states.partition_point(|r| r.sample <= sample).checked_sub(1)?;
        Some(self.states[k].state)
    }

    /// The sample whose SYNC is the last one at or before `unix_time_us` (microseconds since
    /// the Unix epoch): exact where the file has a state line, nominal sample periods in
    /// between. `None` before sample 0; the last sample after the end.
    pub fn sample_at_unix_time_us(&self, unix_time_us: u64) -> Option<u64> {
        let first = self.states.first()?;
        if unix_time_us < first.unix_time_us {
            return None;
        }
        let k = self.states.partition_point(|r| r.unix_time_us <= unix_time_us).checked_sub(1)?;
        let a = &self.states[k];
        let mut s = a.sample + (unix_time_us - a.unix_time_us) / period_us(self.header.sample_period_s);
        if let Some(b) = self.states.get(k + 1) {
            s = s.min(b.sample - 1);
        }
        Some(s.min(self.samples.saturating_sub(1)))
    }
}

impl GroundTruth for TruthFile {
    fn sample_period_s(&self) -> f64 {
        self.header.sample_period_s
    }
    fn samples(&self) -> usize {
        usize::try_from(self.samples).unwrap_or(usize::MAX)
    }
    fn truth_at(&self, i: usize) -> (TruthState, Option<Vector3<f64>>) {
        self.record_at(i as u64).map_or((TruthState::Outside, None), |r| (r.state, r.fulcrum_base_m))
    }
    fn trocars_base_m(&self) -> &[[f64; 3]] {
        &self.header.trocars_base_m
    }
    fn event_count(&self) -> usize {
        self.events.len()
    }
    fn event(&self, k: usize) -> Option<TrueEvent> {
        self.events.get(k).map(|e| TrueEvent {
            t_s: e.t_s,
            sample: usize::try_from(e.sample).unwrap_or(usize::MAX),
            trocar: e.trocar,
            insertion: e.insertion,
        })
    }
}

// ----------------------------------------------------------------------------------------
// Scoring

/// When a detector's output holds: a sample index, or a time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum At {
    /// Sample index from the start of the run (the n-th SYNC, from 0).
    Sample(u64),
    /// Microseconds since the Unix epoch, in the time base of the CAN log; mapped to the
    /// last sample whose SYNC is at or before it ([`TruthFile::sample_at_unix_time_us`]).
    UnixTimeUs(u64),
}

/// Why a detector's output could not be scored against a truth file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum ScoreInputError {
    /// A time before sample 0.
    #[error("detection {index}: time before sample 0 of the truth file")]
    BeforeStart {
        /// Index of the detection in the input.
        index: usize,
    },
    /// A detection for an earlier sample than the one before it.
    #[error("detection {index}: sample {sample} comes after sample {previous}")]
    OutOfOrder {
        /// Index of the detection in the input.
        index: usize,
        /// Its sample.
        sample: u64,
        /// The previous detection's sample.
        previous: u64,
    },
}

/// Scores a detector's output against a truth file with the same definitions and code as
/// [`crate::score::score`]. `detections`: what the detector said, in time order, each
/// holding from its sample until the next detection (a later one for the same sample
/// replaces it; before the first one the detector counts as outside). Samples after the
/// last detection are not scored; detections past the end of the truth are ignored.
/// `wrong_trocar_m`: a fulcrum farther than this (metres) from the true pivot counts as a
/// wrong trocar.
pub fn score_detections(
    truth: &TruthFile,
    detections: impl IntoIterator<Item = (At, Detected)>,
    wrong_trocar_m: f64,
) -> Result<Score, ScoreInputError> {
    let mut dense: Vec<Detected> = Vec::new();
    let mut hold = Detected { inside: false, fulcrum_base_m: None };
    for (index, (at, d)) in detections.into_iter().enumerate() {
        let sample = match at {
            At::Sample(s) => s,
            At::UnixTimeUs(t) => truth.sample_at_unix_time_us(t).ok_or(ScoreInputError::BeforeStart { index })?,
        };
        let len = dense.len() as u64;
        if len > 0 && sample.saturating_add(1) < len {
            return Err(ScoreInputError::OutOfOrder { index, sample, previous: len - 1 });
        }
        if sample >= truth.samples {
            break;
        }
        if len > 0 && sample.saturating_add(1) == len {
            if let Some(last) = dense.last_mut() {
                *last = d;
            }
        } else {
            let fill = usize::try_from(sample).unwrap_or(usize::MAX);
            dense.resize(fill, hold);
            dense.push(d);
        }
        hold = d;
    }
    Ok(score_against(truth, &dense, wrong_trocar_m))
}
