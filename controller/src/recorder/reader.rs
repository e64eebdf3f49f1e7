//! Reading recordings back: one file or every file of a run, checking magic, version, CRC and
//! framing; a frame cut short by a crash is a [`Truncation`], not an error.

use std::collections::BTreeMap;
use std::fs;
use std::io;
use std::marker::PhantomData;
use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;

use super::header::{RecordingHeader, parse_file_name};
use super::{FORMAT_VERSION, FRAME_OVERHEAD_BYTES, MAGIC, MAX_FRAME_PAYLOAD_BYTES, PREAMBLE_BYTES};

#[cfg(doc)]
use super::header::file_name;

/// Why a recording could not be read.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    /// A file or directory could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// File or directory.
        path: PathBuf,
        /// OS error.
        source: io::Error,
    },
    /// The file does not start with the magic bytes `COMANIPREC`.
    #[error("{path} is not a comanip recording (bad magic bytes)")]
    NotARecording {
        /// The file.
        path: PathBuf,
    },
    /// The file's format version is not [`FORMAT_VERSION`].
    #[error("{path}: recording format version {found} is not supported (this reader reads version {supported})")]
    UnsupportedVersion {
        /// The file.
        path: PathBuf,
        /// Version in the file.
        found: u16,
        /// Version this reader reads.
        supported: u16,
    },
    /// A frame's CRC-32 does not match its payload.
    #[error("{path}: corrupt frame at byte {offset}: CRC-32 {stored:#010x} stored, {computed:#010x} computed")]
    CorruptFrame {
        /// The file.
        path: PathBuf,
        /// Offset of the frame (its length field) in the file, bytes.
        offset: u64,
        /// CRC in the file.
        stored: u32,
        /// CRC of the payload as read.
        computed: u32,
    },
    /// A frame announces an impossible length.
    #[error("{path}: corrupt frame at byte {offset}: length {length} exceeds {max} bytes", max = MAX_FRAME_PAYLOAD_BYTES)]
    BadFrameLength {
        /// The file.
        path: PathBuf,
        /// Offset of the frame in the file, bytes.
        offset: u64,
        /// Announced payload length, bytes.
        length: u32,
    },
    /// A frame passed its CRC but its payload is not a valid record (or header).
    #[error("{path}: frame at byte {offset} does not decode: {source}")]
    Decode {
        /// The file.
        path: PathBuf,
        /// Offset of the frame in the file, bytes.
        offset: u64,
        /// Postcard's error.
        source: postcard::Error,
    },
    /// A frame decoded but left bytes unread: the record type does not match the file.
    #[error("{path}: frame at byte {offset} decodes with {extra} bytes left over: wrong record type?")]
    TrailingBytes {
        /// The file.
        path: PathBuf,
        /// Offset of the frame in the file, bytes.
        offset: u64,
        /// Bytes left, bytes.
        extra: usize,
    },
    /// A file's header disagrees with the run's first file or with its own name.
    #[error("{path}: header field {field} does not match the run")]
    HeaderMismatch {
        /// The file.
        path: PathBuf,
        /// Which header field.
        field: &'static str,
    },
    /// The directory holds no recording file.
    #[error("no recording files (fulcrumd-*.rec) in {dir}")]
    NoRecordings {
        /// The directory.
        dir: PathBuf,
    },
    /// The directory holds several runs: pick one with [`RecordingReader::open_run`].
    #[error("{dir} holds {} runs ({}): open one with its run id", run_ids.len(), hex_list(run_ids))]
    MultipleRuns {
        /// The directory.
        dir: PathBuf,
        /// Run ids found.
        run_ids: Vec<u64>,
    },
}

fn hex_list(ids: &[u64]) -> String {
    ids.iter().map(|id| format!("{id:016x}")).collect::<Vec<_>>().join(", ")
}

/// An incomplete frame at the end of a file: what a crash (or a failed write) leaves. The reader
/// returns the records before it and goes on with the next file of the run.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Truncation {
    /// The file.
    pub path: PathBuf,
    /// Offset of the incomplete frame (or 0 for an incomplete magic/version), bytes.
    pub offset: u64,
    /// Bytes of the incomplete frame present in the file (ignored), bytes.
    pub partial_bytes: u64,
    /// Bytes missing to complete the frame, when its length field was complete, bytes.
    pub missing_bytes: Option<u64>,
}

/// The files of one run in a directory.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RunFiles {
    /// The run id, from the file names.
    pub run_id: u64,
    /// (file index, path), by increasing index.
    pub files: Vec<(u32, PathBuf)>,
}

/// Lists the runs in `dir` (files named like [`file_name`]), by increasing run id.
pub fn list_runs(dir: &Path) -> Result<Vec<RunFiles>, ReadError> {
    let io_err = |source| ReadError::Io { path: dir.to_owned(), source };
    let mut runs: BTreeMap<u64, Vec<(u32, PathBuf)>> = BTreeMap::new();
    for entry in fs::read_dir(dir).map_err(io_err)? {
        let entry = entry.map_err(io_err)?;
        let name = entry.file_name();
        if let Some((run, index)) = name.to_str().and_then(parse_file_name) {
            runs.entry(run).or_default().push((index, entry.path()));
        }
    }
    Ok(runs
        .into_iter()
        .map(|(run_id, mut files)| {
            files.sort();
            RunFiles { run_id, files }
        })
        .collect())
}

/// A whole recording read into memory by [`RecordingReader::read_all`].
#[derive(Clone, Debug, PartialEq)]
pub struct Recording<T> {
    /// Header of the first readable file.
    pub header: Option<RecordingHeader>,
    /// Every record, in order.
    pub records: Vec<T>,
    /// Incomplete frames met (normally at most one, at the end of the last file).
    pub truncations: Vec<Truncation>,
}

/// One file read into memory.
struct FileCursor {
    path: PathBuf,
    data: Vec<u8>,
    pos: usize,
}

enum Frame<'a> {
    End,
    Whole { payload: &'a [u8], next: usize },
    Cut(Truncation),
}

/// Iterates over the records of one file or of a run's files, in order. Yields `Err` once (at a
/// corrupt frame, a bad header...) and then ends: nothing is skipped silently.
pub struct RecordingReader<T> {
    files: Vec<PathBuf>,
    next_file: usize,
    current: Option<FileCursor>,
    header: Option<RecordingHeader>,
    truncations: Vec<Truncation>,
    failed: bool,
    _marker: PhantomData<fn() -> T>,
}

impl<T: DeserializeOwned> RecordingReader<T> {
    /// Reads one file.
    pub fn open(path: &Path) -> Result<Self, ReadError> {
        Self::from_files(vec![path.to_owned()])
    }

    /// Reads every file of the only run in `dir`, oldest first.
    pub fn open_dir(dir: &Path) -> Result<Self, ReadError> {
        let mut runs = list_runs(dir)?;
        match runs.len() {
            0 => Err(ReadError::NoRecordings { dir: dir.to_owned() }),
            1 => Self::from_run(runs.remove(0)),
            _ => Err(ReadError::MultipleRuns { dir: dir.to_owned(), run_ids: runs.iter().map(|r| r.run_id).collect() }),
        }
    }

    /// Reads every file of run `run_id` in `dir`, oldest first.
    pub fn open_run(dir: &Path, run_id: u64) -> Result<Self, ReadError> {
        let run = list_runs(dir)?
            .into_iter()
            .find(|r| r.run_id == run_id)
            .ok_or_else(|| ReadError::NoRecordings { dir: dir.to_owned() })?;
        Self::from_run(run)
    }

    fn from_run(run: RunFiles) -> Result<Self, ReadError> {
        Self::from_files(run.files.into_iter().map(|(_, p)| p).collect())
    }

    fn from_files(files: Vec<PathBuf>) -> Result<Self, ReadError> {
        let mut reader = Self {
            files,
            next_file: 0,
            current: None,
            header: None,
            truncations: Vec::new(),
            failed: false,
            _marker: PhantomData,
        };
        // Load the first file now, so that a bad magic or version is an error of `open`.
        reader.load_next()?;
        Ok(reader)
    }

    /// Header of the first file with a readable header (`None` if none had one yet).
    pub fn header(&self) -> Option<&RecordingHeader> {
        self.header.as_ref()
    }

    /// Incomplete frames met so far.
    pub fn truncations(&self) -> &[Truncation] {
        &self.truncations
    }

    /// Reads every remaining record.
    pub fn read_all(mut self) -> Result<Recording<T>, ReadError> {
        let mut records = Vec::new();
        for r in &mut self {
            records.push(r?);
        }
        Ok(Recording { header: self.header, records, truncations: self.truncations })
    }

    /// Opens the next file into `current` (or leaves it `None` when there is none, or when the
    /// file's preamble is cut: that is recorded as a truncation).
    fn load_next(&mut self) -> Result<(), ReadError> {
        self.current = None;
        let Some(path) = self.files.get(self.next_file).cloned() else { return Ok(()) };
        self.next_file += 1;
        let data = fs::read(&path).map_err(|source| ReadError::Io { path: path.clone(), source })?;
        if data.len() < PREAMBLE_BYTES {
            let n = data.len().min(MAGIC.len());
            if data[..n] != MAGIC[..n] {
                return Err(ReadError::NotARecording { path });
            }
            let missing = (PREAMBLE_BYTES - data.len()) as u64;
            self.truncations.push(Truncation {
                path,
                offset: 0,
                partial_bytes: data.len() as u64,
                missing_bytes: Some(missing),
            });
            return Ok(());
        }
        if data[..MAGIC.len()] != MAGIC[..] {
            return Err(ReadError::NotARecording { path });
        }
        let version = u16::from_le_bytes([data[MAGIC.len()], data[MAGIC.len() + 1]]);
        if version != FORMAT_VERSION {
            return Err(ReadError::UnsupportedVersion { path, found: version, supported: FORMAT_VERSION });
        }
        let (header, next) =
            match parse_frame(&path, &data, PREAMBLE_BYTES)? {
                Frame::End => {
                    let t = Truncation { path, offset: PREAMBLE_BYTES as u64, partial_bytes: 0, missing_bytes: None };
                    self.truncations.push(t);
                    return Ok(());
                }
                Frame::Cut(t) => {
                    self.truncations.push(t);
                    return Ok(());
                }
                Frame::Whole { payload, next } => {
                    let header = postcard::from_bytes::<RecordingHeader>(payload).map_err(|source| {
                        ReadError::Decode { path: path.clone(), offset: PREAMBLE_BYTES as u64, source }
                    })?;
                    (header, next)
                }
            };
        if let Some((run, index)) = path.file_name().and_then(|n| n.to_str()).and_then(parse_file_name) {
            if run != header.run_id {
                return Err(ReadError::HeaderMismatch { path, field: "run_id" });
            }
            if index != header.file_index {
                return Err(ReadError::HeaderMismatch { path, field: "file_index" });
            }
        }
        match &self.header {
            Some(first) if first.run_id != header.run_id => {
                return Err(ReadError::HeaderMismatch { path, field: "run_id" });
            }
            Some(first) if first.record_kind != header.record_kind => {
                return Err(ReadError::HeaderMismatch { path, field: "record_kind" });
            }
            Some(_) => {}
            None => self.header = Some(header),
        }
        self.current = Some(FileCursor { path, data, pos: next });
        Ok(())
    }

    fn next_record(&mut self) -> Option<Result<T, ReadError>> {
        loop {
            let Some(cur) = &mut self.current else {
                if self.next_file >= self.files.len() {
                    return None;
                }
                if let Err(e) = self.load_next() {
                    return Some(Err(e));
                }
                continue;
            };
            let offset = cur.pos;
            // Turn the borrowed frame into an owned outcome before touching `self`.
            let outcome = match parse_frame(&cur.path, &cur.data, offset) {
                Err(e) => return Some(Err(e)),
                Ok(Frame::End) => None,
                Ok(Frame::Cut(t)) => Some(Err(t)),
                Ok(Frame::Whole { payload, next }) => {
                    let result = match postcard::take_from_bytes::<T>(payload) {
                        Ok((rec, [])) => Ok(rec),
                        Ok((_, rest)) => Err(ReadError::TrailingBytes {
                            path: cur.path.clone(),
                            offset: offset as u64,
                            extra: rest.len(),
                        }),
                        Err(source) => Err(ReadError::Decode { path: cur.path.clone(), offset: offset as u64, source }),
                    };
                    Some(Ok((result, next)))
                }
            };
            match outcome {
                None => self.current = None,
                Some(Err(t)) => {
                    self.truncations.push(t);
                    self.current = None;
                }
                Some(Ok((result, next))) => {
                    cur.pos = next;
                    return Some(result);
                }
            }
        }
    }
}

impl<T: DeserializeOwned> Iterator for RecordingReader<T> {
    type Item = Result<T, ReadError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.failed {
            return None;
        }
        let item = self.next_record();
        if matches!(item, Some(Err(_))) {
            self.failed = true;
        }
        item
    }
}

/// Parses the frame at `pos` of `data`.
fn parse_frame<'a>(path: &Path, data: &'a [u8], pos: usize) -> Result<Frame<'a>, ReadError> {
    let rest = &data[pos.min(data.len())..];
    if rest.is_empty() {
        return Ok(Frame::End);
    }
    let cut = |missing: Option<usize>| {
        Frame::Cut(Truncation {
            path: path.to_owned(),
            offset: pos as u64,
            partial_bytes: rest.len() as u64,
            missing_bytes: missing.map(|m| m as u64),
        })
    };
    let Some((len_bytes, after_len)) = rest.split_first_chunk::<4>() else { return Ok(cut(None)) };
    let length = u32::from_le_bytes(*len_bytes);
    if length == 0 && after_len.iter().all(|&b| b == 0) {
        // A zero-filled tail: blocks allocated but never written before a power loss.
        return Ok(cut(None));
    }
    if length > MAX_FRAME_PAYLOAD_BYTES {
        return Err(ReadError::BadFrameLength { path: path.to_owned(), offset: pos as u64, length });
    }
    let need = length as usize + FRAME_OVERHEAD_BYTES;
    if rest.len() < need {
        return Ok(cut(Some(need - rest.len())));
    }
    let payload = &after_len[..length as usize];
    let mut crc_bytes = [0u8; 4];
    crc_bytes.copy_from_slice(&after_len[length as usize..length as usize + 4]);
    let stored = u32::from_le_bytes(crc_bytes);
    let computed = crc32fast::hash(payload);
    if stored != computed {
        return Err(ReadError::CorruptFrame { path: path.to_owned(), offset: pos as u64, stored, computed });
    }
    Ok(Frame::Whole { payload, next: pos + need })
}
