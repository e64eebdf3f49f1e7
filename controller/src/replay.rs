//! `fulcrumd replay`: rerun the estimation over a flight recording or a candump log.
//!
//! - A **flight recording** holds each cycle's [`CycleInput`] (raw counts, received nodes,
//!   health flags) and the published [`CycleOutput`]; its header holds the configuration.
//!   Replay rebuilds the [`Estimation`] from that configuration, feeds the inputs in order
//!   and checks every output **bit for bit**. It needs the run from its first cycle: a run
//!   whose oldest files were deleted (bounded disk) or with dropped records cannot be
//!   reproduced past the gap, and the report says so instead of comparing.
//! - A **candump log** (`candump -l`, from can-utils or our simulator) is cut into cycles
//!   the way the live loop cuts the bus: a SYNC opens a cycle; TPDOs are taken until all
//!   nodes have answered or `loop.frame_deadline_us` after the SYNC (by the log's
//!   timestamps); later frames are "between cycles" (late TPDOs counted, EMCY and
//!   heartbeats applied). The resulting outputs can be scored against a ground-truth file
//!   or compared with a flight recording of the same run.

use std::io::BufRead;
use std::path::{Path, PathBuf};

use hw_io::can::candump::{CandumpReadError, CandumpReader};
use hw_io::ipc::HealthFlags;
use serde::Serialize;

use crate::bus_listen::{CutCycle, CycleCutter, EndoscopeDecoder};
use crate::config::{Config, LoadError};
use crate::cycle::{AcquisitionError, AcquisitionStats, CycleInput, CycleOutput, Estimation, EstimationError};
use crate::recorder::{ReadError, RecordingReader, parse_file_name};
use crate::rt_loop::{CycleRecord, RECORD_KIND};

/// Why a replay could not run.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    /// The recording could not be read.
    #[error(transparent)]
    Read(#[from] ReadError),
    /// The recording holds something other than fulcrumd cycle records.
    #[error("{path}: records of kind {found:?}, expected {RECORD_KIND:?}")]
    WrongKind {
        /// File.
        path: PathBuf,
        /// Kind found in the header.
        found: String,
    },
    /// The recording has no header (an empty or truncated first file).
    #[error("{0}: no recording header (empty or truncated file)")]
    NoHeader(PathBuf),
    /// The configuration stored in the recording (or given) is invalid.
    #[error("configuration: {0}")]
    Config(#[from] LoadError),
    /// The configuration cannot build acquisition (encoders, health).
    #[error("configuration: {0}")]
    Acquisition(#[from] AcquisitionError),
    /// The configuration cannot build estimation (encoders, kinematics, detector).
    #[error("configuration: {0}")]
    Estimation(#[from] EstimationError),
    /// The candump log could not be opened.
    #[error("cannot open {path}: {source}")]
    Open {
        /// File.
        path: PathBuf,
        /// OS error.
        source: std::io::Error,
    },
    /// The candump log is malformed.
    #[error("{path}: {source}")]
    Candump {
        /// File.
        path: PathBuf,
        /// Which line, and why.
        source: CandumpReadError,
    },
}

/// Result of replaying a flight recording.
#[derive(Clone, Debug, Default, Serialize)]
pub struct RecordingReplay {
    /// Run identifier from the header.
    pub run_id: u64,
    /// Records read.
    pub records: u64,
    /// Records whose output was reproduced bit for bit.
    pub identical: u64,
    /// Records whose replayed output differs.
    pub mismatches: u64,
    /// Sequence number of the first mismatch.
    pub first_mismatch: Option<u64>,
    /// Sequence of the first record when it is not 0 (older files deleted): nothing compared.
    pub starts_at: Option<u64>,
    /// Sequence at which a gap (dropped records) stopped the comparison.
    pub gap_at: Option<u64>,
    /// Truncated frames at file ends (a crash or a kill), as "file @ offset".
    pub truncations: Vec<String>,
}

impl RecordingReplay {
    /// True when every record read was compared and reproduced exactly.
    pub fn reproduced(&self) -> bool {
        self.records > 0 && self.identical == self.records && self.starts_at.is_none() && self.gap_at.is_none()
    }
}

/// Opens a recording given as a directory (one run in it) or as one of its files (the whole
/// run that file belongs to).
pub fn open_recording(path: &Path) -> Result<RecordingReader<CycleRecord>, ReadError> {
    if path.is_dir() {
        return RecordingReader::open_dir(path);
    }
    let run = path.file_name().and_then(|n| n.to_str()).and_then(parse_file_name);
    match (run, path.parent()) {
        (Some((run_id, _)), Some(dir)) => RecordingReader::open_run(dir, run_id),
        _ => RecordingReader::open(path),
    }
}

/// Reads a whole recording: its configuration and records.
pub fn load_recording(path: &Path) -> Result<(Config, u64, Vec<CycleRecord>, Vec<String>), ReplayError> {
    let rec = open_recording(path)?.read_all()?;
    let header = rec.header.ok_or_else(|| ReplayError::NoHeader(path.to_owned()))?;
    if header.record_kind != RECORD_KIND {
        return Err(ReplayError::WrongKind { path: path.to_owned(), found: header.record_kind });
    }
    let cfg = Config::from_toml(&header.config_toml, path)?;
    let truncations =
        rec.truncations.iter().map(|t| format!("{} @ byte {}", t.path.display(), t.offset)).collect::<Vec<_>>();
    Ok((cfg, header.run_id, rec.records, truncations))
}

fn estimation(cfg: &Config) -> Result<Estimation, ReplayError> {
    Ok(Estimation::new(&cfg.bus.encoder, &cfg.kinematics, &cfg.detector)?)
}

/// Replays a flight recording and checks every output bit for bit.
pub fn replay_recording(path: &Path) -> Result<RecordingReplay, ReplayError> {
    let (cfg, run_id, records, truncations) = load_recording(path)?;
    let mut est = estimation(&cfg)?;
    let mut out = RecordingReplay { run_id, truncations, ..Default::default() };
    out.records = records.len() as u64;
    if let Some(first) = records.first()
        && first.sequence != 0
    {
        out.starts_at = Some(first.sequence);
        return Ok(out);
    }
    for (i, r) in records.iter().enumerate() {
        if r.sequence != i as u64 {
            out.gap_at = Some(i as u64);
            break;
        }
        if est.process(&r.input).bit_identical(&r.output) {
            out.identical += 1;
        } else {
            out.mismatches += 1;
            out.first_mismatch.get_or_insert(r.sequence);
        }
    }
    Ok(out)
}

/// One cycle cut from a candump log.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LogCycle {
    /// Timestamp of the cycle's SYNC in the log, microseconds since the Unix epoch.
    pub sync_unix_us: u64,
    /// What acquisition made of the cycle's frames.
    pub input: CycleInput,
    /// The estimate.
    pub output: CycleOutput,
}

/// Result of running a candump log through acquisition and estimation.
#[derive(Clone, Debug, Default)]
pub struct LogReplay {
    /// One entry per SYNC in the log.
    pub cycles: Vec<LogCycle>,
    /// Acquisition counters over the log.
    pub acquisition: AcquisitionStats,
    /// Lines of the log that were not frames (comments, blank) and skipped.
    pub lines: u64,
}

/// Cuts a candump log into cycles and runs them through the pipeline of `cfg`.
pub fn replay_candump(path: &Path, cfg: &Config) -> Result<LogReplay, ReplayError> {
    let file = std::fs::File::open(path).map_err(|source| ReplayError::Open { path: path.to_owned(), source })?;
    replay_candump_reader(std::io::BufReader::new(file), cfg).map_err(|e| match e {
        ReplayError::Candump { source, .. } => ReplayError::Candump { path: path.to_owned(), source },
        other => other,
    })
}

/// [`replay_candump`] on any reader. Times past the year 2554 (nanoseconds beyond `u64`) saturate.
/// The log is cut into cycles by [`crate::bus_listen::CycleCutter`], the same cutter the live
/// bus listener runs.
pub fn replay_candump_reader(reader: impl BufRead, cfg: &Config) -> Result<LogReplay, ReplayError> {
    let mut cutter = CycleCutter::from_config(cfg)?;
    let mut est = estimation(cfg)?;
    let mut reader = CandumpReader::new(reader);
    let mut out = LogReplay::default();
    let push = |c: CutCycle, est: &mut Estimation, cycles: &mut Vec<LogCycle>| {
        let output = est.process(&c.input);
        cycles.push(LogCycle { sync_unix_us: c.sync_us, input: c.input, output });
    };
    loop {
        let rec = match reader.next_record() {
            Ok(Some(r)) => r,
            Ok(None) => break,
            Err(source) => return Err(ReplayError::Candump { path: PathBuf::new(), source }),
        };
        if let Some(c) = cutter.on_frame(&rec.timed.frame, rec.timed.unix_time_us) {
            push(c, &mut est, &mut out.cycles);
        }
    }
    if let Some(c) = cutter.finish() {
        push(c, &mut est, &mut out.cycles);
    }
    out.acquisition = *cutter.stats();
    out.lines = reader.line_number();
    Ok(out)
}

/// The endoscope-holder arm's joints `[yaw rad, pitch rad, insertion m, roll rad]` from a
/// candump log: each pair of its two nodes' TPDOs (less than 1 ms apart) decoded with the
/// arm's encoder model `arm`, stamped with the later one's time (nanoseconds on the log's
/// clock, Unix microseconds × 1000), in log order. Used by `comanip-calib from-run` and
/// `comanip-track run`; the decoding is [`crate::bus_listen::EndoscopeDecoder`], the same the
/// live bus listener runs.
pub fn endoscope_joints(
    path: &Path,
    arm: &sim::endoscope_arm::EndoscopeArmConfig,
) -> Result<Vec<(u64, [f64; 4])>, ReplayError> {
    let file = std::fs::File::open(path).map_err(|source| ReplayError::Open { path: path.to_owned(), source })?;
    let mut reader = CandumpReader::new(std::io::BufReader::new(file));
    let mut decoder = EndoscopeDecoder::new(arm);
    let mut ecm: Vec<(u64, [f64; 4])> = Vec::new();
    loop {
        let rec = match reader.next_record() {
            Ok(Some(r)) => r,
            Ok(None) => break,
            Err(source) => return Err(ReplayError::Candump { path: path.to_owned(), source }),
        };
        if let Some(s) = decoder.on_frame(&rec.timed.frame, rec.timed.unix_time_us.saturating_mul(1000)) {
            ecm.push(s);
        }
    }
    Ok(ecm)
}

/// Comparison of a candump replay with a flight recording of the same run.
#[derive(Clone, Debug, Default, Serialize)]
pub struct LogVsRecording {
    /// Index of the log cycle matched with the recording's sequence 0 (log cycles may start
    /// before the daemon's, e.g. when candump ran first), or None when no alignment found.
    pub offset: Option<usize>,
    /// Cycles compared.
    pub compared: u64,
    /// Cycles whose inputs (counts, received nodes, flags but OVERRUN) are identical.
    pub identical_inputs: u64,
    /// Cycles whose outputs are bit-identical.
    pub identical_outputs: u64,
    /// Sequence of the first output mismatch.
    pub first_mismatch: Option<u64>,
}

/// Health flags the loop adds from its own timing, which a bus log cannot know (`OVERRUN`):
/// left out when inputs are compared, and taken from the recording when a log cycle is
/// replayed against it.
pub const LOOP_ONLY_FLAGS: HealthFlags = HealthFlags::OVERRUN;

/// The same bus input: counts, received nodes and flags other than [`LOOP_ONLY_FLAGS`].
pub fn same_bus_input(a: &CycleInput, b: &CycleInput) -> bool {
    a.counts == b.counts && a.received_mask == b.received_mask && a.flags - LOOP_ONLY_FLAGS == b.flags - LOOP_ONLY_FLAGS
}

/// Aligns the log's cycles with the recording (first 1000 candidate offsets, by inputs),
/// reruns the estimation of `cfg` from the aligned cycle (as the daemon started there) and
/// compares outputs.
pub fn compare_with_recording(
    log: &LogReplay,
    records: &[CycleRecord],
    cfg: &Config,
) -> Result<LogVsRecording, ReplayError> {
    let mut r = LogVsRecording::default();
    let window = records.len().min(50);
    if window == 0 {
        return Ok(r);
    }
    let offset = (0..log.cycles.len().min(1000)).find(|&k| {
        log.cycles.len() >= k + window
            && (0..window).all(|i| same_bus_input(&log.cycles[k + i].input, &records[i].input))
    });
    r.offset = offset;
    let Some(k) = offset else { return Ok(r) };
    let mut est = estimation(cfg)?;
    for (c, rec) in log.cycles[k..].iter().zip(records) {
        r.compared += 1;
        if same_bus_input(&c.input, &rec.input) {
            r.identical_inputs += 1;
        }
        let mut input = c.input;
        input.flags |= rec.input.flags & LOOP_ONLY_FLAGS;
        if est.process(&input).bit_identical(&rec.output) {
            r.identical_outputs += 1;
        } else {
            r.first_mismatch.get_or_insert(rec.sequence);
        }
    }
    Ok(r)
}
