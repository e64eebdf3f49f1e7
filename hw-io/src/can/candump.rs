//! candump log files (can-utils `candump -l` / `candump -L`), read and written.
//!
//! One frame per line:
//!
//! ```text
//! (1699999999.123456) vcan0 181#0102030405060708
//! (1699999999.124000) vcan0 080#01
//! (1699999999.125000) vcan0 12345678#DEAD      <- 29-bit ID: 8 hex digits
//! (1699999999.126000) vcan0 701#R1             <- remote frame, DLC 1
//! ```
//!
//! The timestamp is seconds.microseconds since the Unix epoch. python-can's writer may add
//! a direction token (` R` received, ` T` transmitted), which is accepted. CAN FD frames
//! (`123##1...`) and error frames (8-digit IDs with the `0x20000000` flag) are reported as
//! [`LineError::CanFd`] and [`LineError::ErrorFrame`]; the reader then goes on with the
//! next line, so a caller can skip them.
//!
//! Reading reuses one line buffer: after the longest line has been seen, reading a record
//! allocates nothing.
//!
//! ```
//! use hw_io::can::candump::{CandumpReader, CandumpWriter};
//! use hw_io::can::{CanFrame, TimedFrame};
//! let frame = CanFrame::new_standard(0x181, &[1, 2, 3, 4, 5, 6, 7, 8]).unwrap();
//! let mut w = CandumpWriter::new(Vec::new(), "vcan0").unwrap();
//! w.write(&TimedFrame { frame, unix_time_us: 1_699_999_999_123_456 }).unwrap();
//! let text = w.into_inner();
//! assert_eq!(text, b"(1699999999.123456) vcan0 181#0102030405060708\n");
//! let mut r = CandumpReader::new(&text[..]);
//! let rec = r.next_record().unwrap().unwrap();
//! assert_eq!((rec.interface, rec.timed.frame), ("vcan0", frame));
//! ```

use std::io::{self, BufRead, Write};

use super::frame::{CanFrame, CanId, MAX_DLC, MAX_EXTENDED_ID, MAX_STANDARD_ID, TimedFrame};

/// Error-frame flag in a candump 8-digit identifier (`CAN_ERR_FLAG`).
const CAN_ERR_FLAG: u32 = 0x2000_0000;

/// Direction token some writers (python-can) append to a line.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Direction {
    /// ` R`: received by the logging interface.
    Rx,
    /// ` T`: transmitted by the logging interface.
    Tx,
}

/// One parsed log line, borrowing the interface name from the reader's line buffer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CandumpRecord<'a> {
    /// The frame and its time, microseconds since the Unix epoch.
    pub timed: TimedFrame,
    /// The interface name (`can0`, `vcan0`, ...).
    pub interface: &'a str,
    /// The direction token, if the line had one.
    pub direction: Option<Direction>,
}

/// What is wrong with one line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum LineError {
    /// The line has fewer than three fields (timestamp, interface, frame).
    #[error("missing {field}")]
    MissingField {
        /// The first missing field: `"interface"` or `"frame"`.
        field: &'static str,
    },
    /// The timestamp is not `(seconds.fraction)` with decimal digits.
    #[error("timestamp is not (seconds.fraction)")]
    BadTimestamp,
    /// The frame has no `#` between identifier and data.
    #[error("frame has no '#' between identifier and data")]
    MissingHash,
    /// The identifier is not 3 hex digits (≤ 7FF) or 8 hex digits (≤ 1FFFFFFF).
    #[error("identifier is not 3 hex digits (max 7FF) or 8 hex digits (max 1FFFFFFF)")]
    BadId,
    /// The data is not pairs of hex digits (optionally separated by `.`).
    #[error("data is not pairs of hex digits")]
    BadData,
    /// More than 8 data bytes.
    #[error("{bytes} data bytes: classic CAN has at most 8")]
    TooManyBytes {
        /// Bytes found.
        bytes: usize,
    },
    /// A remote frame whose length after `R` is not one digit 0..8.
    #[error("remote frame length after 'R' is not a digit 0..8")]
    BadRemoteDlc,
    /// A CAN FD frame (`ID##flags data`): not supported.
    #[error("CAN FD frame: not supported (classic CAN only)")]
    CanFd,
    /// An error frame (identifier with the 0x20000000 error flag).
    #[error("CAN error frame (class 0x{class:08X})")]
    ErrorFrame {
        /// The identifier with the error-class bits.
        class: u32,
    },
    /// Text after the frame (and the optional direction token).
    #[error("unexpected text after the frame")]
    TrailingText,
}

/// Why reading a candump log failed.
#[derive(Debug, thiserror::Error)]
pub enum CandumpReadError {
    /// The underlying reader failed.
    #[error("reading candump log: {0}")]
    Io(#[source] io::Error),
    /// A line is not valid UTF-8.
    #[error("candump log line {line}: not UTF-8")]
    NotUtf8 {
        /// Line number, 1-based.
        line: u64,
    },
    /// A line is not a candump record.
    #[error("candump log line {line}: {kind}")]
    Malformed {
        /// Line number, 1-based.
        line: u64,
        /// What is wrong.
        kind: LineError,
    },
}

impl CandumpReadError {
    /// The 1-based line number, for a line-level error.
    pub fn line(&self) -> Option<u64> {
        match self {
            CandumpReadError::Io(_) => None,
            CandumpReadError::NotUtf8 { line } | CandumpReadError::Malformed { line, .. } => Some(*line),
        }
    }
}

fn hex_digit(b: u8) -> Option<u8> {
    match b {
        b'0'..=b'9' => Some(b - b'0'),
        b'a'..=b'f' => Some(b - b'a' + 10),
        b'A'..=b'F' => Some(b - b'A' + 10),
        _ => None,
    }
}

fn parse_hex_u32(s: &str) -> Option<u32> {
    if s.is_empty() || s.len() > 8 {
        return None;
    }
    s.bytes().try_fold(0u32, |acc, b| Some((acc << 4) | u32::from(hex_digit(b)?)))
}

/// `(seconds.fraction)` as microseconds since the epoch (fraction truncated to µs).
fn parse_timestamp(s: &str) -> Option<u64> {
    let inner = s.strip_prefix('(')?.strip_suffix(')')?;
    let (secs, frac) = match inner.split_once('.') {
        Some((s, f)) => (s, f),
        None => (inner, ""),
    };
    if secs.is_empty() || !secs.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    if !frac.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let secs: u64 = secs.parse().ok()?;
    let mut micros = 0u64;
    for i in 0..6 {
        let d = frac.as_bytes().get(i).map_or(0, |b| u64::from(b - b'0'));
        micros = micros * 10 + d;
    }
    secs.checked_mul(1_000_000)?.checked_add(micros)
}

fn parse_frame(s: &str) -> Result<CanFrame, LineError> {
    let (id_text, rest) = s.split_once('#').ok_or(LineError::MissingHash)?;
    let raw = parse_hex_u32(id_text).ok_or(LineError::BadId)?;
    let id = match id_text.len() {
        3 if raw <= u32::from(MAX_STANDARD_ID) => CanId::Standard(raw as u16),
        8 if raw & CAN_ERR_FLAG != 0 => return Err(LineError::ErrorFrame { class: raw }),
        8 if raw <= MAX_EXTENDED_ID => CanId::Extended(raw),
        _ => return Err(LineError::BadId),
    };
    if rest.starts_with('#') {
        return Err(LineError::CanFd);
    }
    if let Some(r) = rest.strip_prefix(['R', 'r']) {
        // `R`, `R4`, and can-utils' raw-DLC suffix `R8_D` (the suffix is ignored).
        let r = strip_raw_dlc_suffix(r);
        let dlc = match r.as_bytes() {
            [] => 0,
            [d] if d.is_ascii_digit() && *d - b'0' <= MAX_DLC => *d - b'0',
            _ => return Err(LineError::BadRemoteDlc),
        };
        return CanFrame::new_remote(id, dlc).map_err(|_| LineError::BadRemoteDlc);
    }
    let rest = strip_raw_dlc_suffix(rest);
    let mut data = [0u8; 8];
    let mut len = 0usize;
    let mut bytes = rest.bytes().filter(|&b| b != b'.');
    while let Some(hi) = bytes.next() {
        let lo = bytes.next().ok_or(LineError::BadData)?;
        let byte = (hex_digit(hi).ok_or(LineError::BadData)? << 4) | hex_digit(lo).ok_or(LineError::BadData)?;
        if len < data.len() {
            data[len] = byte;
        }
        len += 1;
    }
    if len > usize::from(MAX_DLC) {
        return Err(LineError::TooManyBytes { bytes: len });
    }
    CanFrame::new_data(id, &data[..len]).map_err(|_| LineError::BadId)
}

/// can-utils writes a raw DLC 9..F of an 8-byte frame as a `_X` suffix; we keep 8 bytes.
fn strip_raw_dlc_suffix(s: &str) -> &str {
    match s.as_bytes() {
        [.., b'_', d] if hex_digit(*d).is_some() => &s[..s.len() - 2],
        _ => s,
    }
}

/// Parse one line (without its newline). `Ok(None)` for a blank line. Allocation-free.
pub fn parse_line(line: &str) -> Result<Option<CandumpRecord<'_>>, LineError> {
    let mut fields = line.split_ascii_whitespace();
    let Some(ts) = fields.next() else {
        return Ok(None);
    };
    let unix_time_us = parse_timestamp(ts).ok_or(LineError::BadTimestamp)?;
    let interface = fields.next().ok_or(LineError::MissingField { field: "interface" })?;
    let frame_text = fields.next().ok_or(LineError::MissingField { field: "frame" })?;
    let direction = match fields.next() {
        None => None,
        Some("R" | "r") => Some(Direction::Rx),
        Some("T" | "t") => Some(Direction::Tx),
        Some(_) => return Err(LineError::TrailingText),
    };
    if fields.next().is_some() {
        return Err(LineError::TrailingText);
    }
    let frame = parse_frame(frame_text)?;
    Ok(Some(CandumpRecord { timed: TimedFrame { frame, unix_time_us }, interface, direction }))
}

/// Reads a candump log record by record.
#[derive(Debug)]
pub struct CandumpReader<R> {
    inner: R,
    buf: Vec<u8>,
    line: u64,
}

impl<R: BufRead> CandumpReader<R> {
    /// A reader over `inner` (e.g. a `BufReader<File>` or a byte slice).
    pub fn new(inner: R) -> Self {
        Self { inner, buf: Vec::with_capacity(128), line: 0 }
    }

    /// Number of lines read so far (the line number of the last record or error).
    pub fn line_number(&self) -> u64 {
        self.line
    }

    /// The next record; `Ok(None)` at the end of the input. Blank lines are skipped. After a
    /// [`CandumpReadError::Malformed`] or [`CandumpReadError::NotUtf8`], the next call
    /// continues with the following line.
    pub fn next_record(&mut self) -> Result<Option<CandumpRecord<'_>>, CandumpReadError> {
        loop {
            self.buf.clear();
            let n = self.inner.read_until(b'\n', &mut self.buf).map_err(CandumpReadError::Io)?;
            if n == 0 {
                return Ok(None);
            }
            self.line += 1;
            let blank = self.buf.iter().all(u8::is_ascii_whitespace);
            if !blank {
                break;
            }
        }
        let line = self.line;
        let text = std::str::from_utf8(&self.buf).map_err(|_| CandumpReadError::NotUtf8 { line })?;
        match parse_line(text) {
            Ok(Some(rec)) => Ok(Some(rec)),
            // Blank lines were skipped above; unreachable, but harmless.
            Ok(None) => Err(CandumpReadError::Malformed { line, kind: LineError::MissingField { field: "frame" } }),
            Err(kind) => Err(CandumpReadError::Malformed { line, kind }),
        }
    }

    /// Give back the underlying reader.
    pub fn into_inner(self) -> R {
        self.inner
    }
}

impl<R: BufRead> Iterator for CandumpReader<R> {
    type Item = Result<TimedFrame, CandumpReadError>;

    fn next(&mut self) -> Option<Self::Item> {
        self.next_record().map(|r| r.map(|rec| rec.timed)).transpose()
    }
}

/// An interface name that cannot be written into a candump line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum InterfaceNameError {
    /// Empty, or containing whitespace or a non-printable character.
    #[error("interface name must be non-empty printable text without whitespace")]
    Invalid,
}

/// Writes frames as candump log lines (`candump -l` format).
#[derive(Debug)]
pub struct CandumpWriter<W> {
    inner: W,
    interface: String,
}

impl<W: Write> CandumpWriter<W> {
    /// A writer that labels every line with `interface` (e.g. `"vcan0"`).
    pub fn new(inner: W, interface: &str) -> Result<Self, InterfaceNameError> {
        if interface.is_empty() || !interface.chars().all(|c| c.is_ascii_graphic()) {
            return Err(InterfaceNameError::Invalid);
        }
        Ok(Self { inner, interface: interface.to_owned() })
    }

    /// Write one line: `(seconds.micros) interface ID#DATA`. Allocation-free.
    pub fn write(&mut self, f: &TimedFrame) -> io::Result<()> {
        let secs = f.unix_time_us / 1_000_000;
        let micros = f.unix_time_us % 1_000_000;
        write!(self.inner, "({secs:010}.{micros:06}) {} ", self.interface)?;
        let frame = &f.frame;
        match frame.id() {
            CanId::Standard(id) => write!(self.inner, "{id:03X}#")?,
            CanId::Extended(id) => write!(self.inner, "{id:08X}#")?,
        }
        if frame.is_remote() {
            self.inner.write_all(b"R")?;
            if frame.dlc() > 0 {
                write!(self.inner, "{}", frame.dlc())?;
            }
        } else {
            for b in frame.data() {
                write!(self.inner, "{b:02X}")?;
            }
        }
        self.inner.write_all(b"\n")
    }

    /// Flush the underlying writer.
    pub fn flush(&mut self) -> io::Result<()> {
        self.inner.flush()
    }

    /// Give back the underlying writer.
    pub fn into_inner(self) -> W {
        self.inner
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(line: &str) -> Result<TimedFrame, LineError> {
        parse_line(line).map(|r| r.map(|r| r.timed).unwrap())
    }

    #[test]
    fn parses_the_documented_forms() {
        let t = parse("(1699999999.123456) vcan0 181#0102030405060708").unwrap();
        assert_eq!(t.unix_time_us, 1_699_999_999_123_456);
        assert_eq!(t.frame, CanFrame::new_standard(0x181, &[1, 2, 3, 4, 5, 6, 7, 8]).unwrap());
        let t = parse("(0.0) can1 12345678#DEAD").unwrap();
        assert_eq!(t.unix_time_us, 0);
        assert_eq!(t.frame, CanFrame::new_extended(0x1234_5678, &[0xDE, 0xAD]).unwrap());
        let t = parse("(5.5) can0 00000080#").unwrap();
        assert_eq!(t.frame, CanFrame::new_extended(0x80, &[]).unwrap());
        assert_eq!(t.unix_time_us, 5_500_000);
        let t = parse("(1.000001) can0 701#R1").unwrap();
        assert_eq!(t.frame, CanFrame::new_remote(CanId::Standard(0x701), 1).unwrap());
        let t = parse("(1.000001) can0 1FFFFFFF#r").unwrap();
        assert_eq!(t.frame, CanFrame::new_remote(CanId::Extended(0x1FFF_FFFF), 0).unwrap());
        let t = parse("(1.1234567) can0 123#11.22.33").unwrap();
        assert_eq!((t.unix_time_us, t.frame.data()), (1_123_456, &[0x11, 0x22, 0x33][..]));
        let t = parse("(1) can0 123#1122334455667788_E").unwrap();
        assert_eq!(t.frame.dlc(), 8);
        let r = parse_line("  (1.5) vcan0 080#01 R  ").unwrap().unwrap();
        assert_eq!((r.interface, r.direction), ("vcan0", Some(Direction::Rx)));
        assert_eq!(parse_line("(1.5) vcan0 080#01 T").unwrap().unwrap().direction, Some(Direction::Tx));
        assert_eq!(parse_line("   "), Ok(None));
    }

    #[test]
    fn malformed_lines_give_typed_errors() {
        let cases: &[(&str, LineError)] = &[
            ("1.5 can0 123#00", LineError::BadTimestamp),
            ("(1.5 can0 123#00", LineError::BadTimestamp),
            ("(-1.5) can0 123#00", LineError::BadTimestamp),
            ("(1.x) can0 123#00", LineError::BadTimestamp),
            ("(1.5)", LineError::MissingField { field: "interface" }),
            ("(1.5) can0", LineError::MissingField { field: "frame" }),
            ("(1.5) can0 12300", LineError::MissingHash),
            ("(1.5) can0 800#00", LineError::BadId),
            ("(1.5) can0 12#00", LineError::BadId),
            ("(1.5) can0 1234#00", LineError::BadId),
            ("(1.5) can0 G23#00", LineError::BadId),
            ("(1.5) can0 40000000#00", LineError::BadId),
            ("(1.5) can0 123#0", LineError::BadData),
            ("(1.5) can0 123#0G", LineError::BadData),
            ("(1.5) can0 123#001122334455667788", LineError::TooManyBytes { bytes: 9 }),
            ("(1.5) can0 123#R9", LineError::BadRemoteDlc),
            ("(1.5) can0 123#R12", LineError::BadRemoteDlc),
            ("(1.5) can0 123##1AABB", LineError::CanFd),
            ("(1.5) can0 20000080#0000000000000000", LineError::ErrorFrame { class: 0x2000_0080 }),
            ("(1.5) can0 123#00 X", LineError::TrailingText),
            ("(1.5) can0 123#00 R extra", LineError::TrailingText),
        ];
        for (line, kind) in cases {
            assert_eq!(parse(line), Err(*kind), "{line}");
        }
    }

    #[test]
    fn reader_reports_line_numbers_and_continues() {
        let text = b"(1.000000) can0 080#01\n\ngarbage\n(2.000000) can0 123##1AA\n\xff\xfe\n(3.000000) can0 080#02";
        let mut r = CandumpReader::new(&text[..]);
        assert_eq!(r.next_record().unwrap().unwrap().timed.frame.data(), &[1]);
        let e = r.next_record().unwrap_err();
        assert_eq!(e.line(), Some(3));
        assert!(e.to_string().starts_with("candump log line 3: "), "{e}");
        match r.next_record() {
            Err(CandumpReadError::Malformed { line: 4, kind: LineError::CanFd }) => {}
            other => panic!("{other:?}"),
        }
        assert!(matches!(r.next_record(), Err(CandumpReadError::NotUtf8 { line: 5 })));
        let last = r.next_record().unwrap().unwrap();
        assert_eq!(last.timed.unix_time_us, 3_000_000);
        assert!(r.next_record().unwrap().is_none());
        assert_eq!(r.line_number(), 6);
    }

    #[test]
    fn writer_uses_candump_formatting() {
        let mut w = CandumpWriter::new(Vec::new(), "can0").unwrap();
        let frames = [
            CanFrame::new_standard(0x80, &[1]).unwrap(),
            CanFrame::new_standard(0x7, &[]).unwrap(),
            CanFrame::new_extended(0xABC, &[0xFF, 0]).unwrap(),
            CanFrame::new_remote(CanId::Standard(0x701), 0).unwrap(),
            CanFrame::new_remote(CanId::Extended(0x10), 8).unwrap(),
        ];
        for (i, frame) in frames.into_iter().enumerate() {
            w.write(&TimedFrame { frame, unix_time_us: 1_000_000 + i as u64 }).unwrap();
        }
        let text = String::from_utf8(w.into_inner()).unwrap();
        assert_eq!(
            text,
            "(0000000001.000000) can0 080#01\n\
             (0000000001.000001) can0 007#\n\
             (0000000001.000002) can0 00000ABC#FF00\n\
             (0000000001.000003) can0 701#R\n\
             (0000000001.000004) can0 00000010#R8\n"
        );
        assert_eq!(CandumpWriter::new(Vec::new(), "").unwrap_err(), InterfaceNameError::Invalid);
        assert!(CandumpWriter::new(Vec::new(), "can 0").is_err());
    }
}
