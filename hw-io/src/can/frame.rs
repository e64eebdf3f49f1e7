//! Our own classic-CAN frame: fixed size, `Copy`, no heap.
//!
//! [`CanFrame`] is what every backend hands out and takes in. Its invariants hold by
//! construction: a standard identifier fits in 11 bits, an extended one in 29 bits, the
//! data length code (DLC) is 0..=8 and the data bytes beyond the DLC are zero, so two
//! frames with the same content compare equal.

/// Largest 11-bit (standard) identifier, `0x7FF`.
pub const MAX_STANDARD_ID: u16 = 0x7FF;
/// Largest 29-bit (extended) identifier, `0x1FFF_FFFF`.
pub const MAX_EXTENDED_ID: u32 = 0x1FFF_FFFF;
/// Largest classic-CAN payload, bytes.
pub const MAX_DLC: u8 = 8;

/// A CAN identifier: standard (11-bit) or extended (29-bit).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum CanId {
    /// 11-bit base-format identifier, `0x000..=0x7FF`.
    Standard(u16),
    /// 29-bit extended-format identifier, `0x0000_0000..=0x1FFF_FFFF`.
    Extended(u32),
}

impl CanId {
    /// The identifier as a plain number (11 or 29 significant bits).
    pub const fn raw(self) -> u32 {
        match self {
            CanId::Standard(id) => id as u32,
            CanId::Extended(id) => id,
        }
    }

    /// `true` for a 29-bit extended identifier.
    pub const fn is_extended(self) -> bool {
        matches!(self, CanId::Extended(_))
    }
}

/// Why a [`CanFrame`] could not be built.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// A standard identifier above `0x7FF` (11 bits).
    #[error("standard CAN identifier 0x{id:X} does not fit in 11 bits (max 0x7FF)")]
    StandardIdTooLarge {
        /// The identifier given.
        id: u32,
    },
    /// An extended identifier above `0x1FFF_FFFF` (29 bits).
    #[error("extended CAN identifier 0x{id:X} does not fit in 29 bits (max 0x1FFFFFFF)")]
    ExtendedIdTooLarge {
        /// The identifier given.
        id: u32,
    },
    /// More than 8 data bytes, or a DLC above 8 (classic CAN only; no CAN FD).
    #[error("data length {len} bytes exceeds the classic CAN maximum of 8")]
    TooLong {
        /// Length or DLC given, bytes.
        len: usize,
    },
}

/// One classic CAN 2.0 frame (data or remote), 16 bytes, `Copy`, no heap.
///
/// ```
/// use hw_io::can::{CanFrame, CanId};
/// let f = CanFrame::new_standard(0x181, &[1, 2, 3]).unwrap();
/// assert_eq!(f.id(), CanId::Standard(0x181));
/// assert_eq!(f.dlc(), 3);
/// assert_eq!(f.data(), &[1, 2, 3]);
/// assert!(CanFrame::new_standard(0x800, &[]).is_err());
/// ```
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct CanFrame {
    id: CanId,
    remote: bool,
    dlc: u8,
    data: [u8; 8],
}

impl CanFrame {
    /// A data frame with an 11-bit identifier and 0..=8 data bytes.
    pub fn new_standard(id: u16, data: &[u8]) -> Result<Self, FrameError> {
        Self::new_data(CanId::Standard(id), data)
    }

    /// A data frame with a 29-bit identifier and 0..=8 data bytes.
    pub fn new_extended(id: u32, data: &[u8]) -> Result<Self, FrameError> {
        Self::new_data(CanId::Extended(id), data)
    }

    /// A data frame with the given identifier and 0..=8 data bytes.
    pub fn new_data(id: CanId, data: &[u8]) -> Result<Self, FrameError> {
        check_id(id)?;
        if data.len() > usize::from(MAX_DLC) {
            return Err(FrameError::TooLong { len: data.len() });
        }
        let mut bytes = [0u8; 8];
        bytes[..data.len()].copy_from_slice(data);
        Ok(Self { id, remote: false, dlc: data.len() as u8, data: bytes })
    }

    /// A remote (RTR) frame: no data bytes, but a DLC of 0..=8 requested bytes.
    pub fn new_remote(id: CanId, dlc: u8) -> Result<Self, FrameError> {
        check_id(id)?;
        if dlc > MAX_DLC {
            return Err(FrameError::TooLong { len: usize::from(dlc) });
        }
        Ok(Self { id, remote: true, dlc, data: [0; 8] })
    }

    /// Build a frame from raw fields as a driver or a file presents them.
    ///
    /// `id` is 11 bits when `extended` is false, else 29 bits; `dlc` is 0..=8 bytes.
    /// Data bytes at and beyond `dlc` (and all bytes of a remote frame) are ignored and
    /// stored as zero.
    pub fn from_parts(id: u32, extended: bool, remote: bool, dlc: u8, data: [u8; 8]) -> Result<Self, FrameError> {
        let id = if extended {
            CanId::Extended(id)
        } else {
            let standard = u16::try_from(id)
                .ok()
                .filter(|id| *id <= MAX_STANDARD_ID)
                .ok_or(FrameError::StandardIdTooLarge { id })?;
            CanId::Standard(standard)
        };
        if remote {
            return Self::new_remote(id, dlc);
        }
        if dlc > MAX_DLC {
            return Err(FrameError::TooLong { len: usize::from(dlc) });
        }
        Self::new_data(id, &data[..usize::from(dlc)])
    }

    /// A standard data frame from a COB-ID and bytes already known to be in range: the
    /// identifier is masked to 11 bits and the DLC clamped to 8, bytes beyond it zeroed.
    pub(crate) fn standard_masked(id: u16, dlc: u8, data: [u8; 8]) -> Self {
        let dlc = dlc.min(MAX_DLC);
        let mut bytes = [0u8; 8];
        bytes[..usize::from(dlc)].copy_from_slice(&data[..usize::from(dlc)]);
        Self { id: CanId::Standard(id & MAX_STANDARD_ID), remote: false, dlc, data: bytes }
    }

    /// The identifier (standard 11-bit or extended 29-bit).
    pub const fn id(&self) -> CanId {
        self.id
    }

    /// `true` for a 29-bit extended identifier.
    pub const fn is_extended(&self) -> bool {
        self.id.is_extended()
    }

    /// `true` for a remote transmission request (RTR) frame.
    pub const fn is_remote(&self) -> bool {
        self.remote
    }

    /// Data length code, bytes (0..=8). For a remote frame: the requested length.
    pub const fn dlc(&self) -> u8 {
        self.dlc
    }

    /// The data bytes (`dlc` of them; empty for a remote frame).
    pub fn data(&self) -> &[u8] {
        if self.remote { &[] } else { &self.data[..usize::from(self.dlc.min(MAX_DLC))] }
    }

    /// All 8 data bytes; bytes beyond the DLC are zero.
    pub const fn data_padded(&self) -> [u8; 8] {
        self.data
    }
}

impl core::fmt::Debug for CanFrame {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        // candump-like: 181#0102 / 1234ABCD#R2
        write!(f, "CanFrame(")?;
        match self.id {
            CanId::Standard(id) => write!(f, "{id:03X}#")?,
            CanId::Extended(id) => write!(f, "{id:08X}#")?,
        }
        if self.remote {
            write!(f, "R{}", self.dlc)?;
        } else {
            for b in self.data() {
                write!(f, "{b:02X}")?;
            }
        }
        write!(f, ")")
    }
}

fn check_id(id: CanId) -> Result<(), FrameError> {
    match id {
        CanId::Standard(id) if id > MAX_STANDARD_ID => Err(FrameError::StandardIdTooLarge { id: u32::from(id) }),
        CanId::Extended(id) if id > MAX_EXTENDED_ID => Err(FrameError::ExtendedIdTooLarge { id }),
        _ => Ok(()),
    }
}

/// A frame with the time it was received (or, for a sender, sent).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TimedFrame {
    /// The frame.
    pub frame: CanFrame,
    /// Reception time, microseconds since the Unix epoch (UTC wall clock, as in candump
    /// logs and SocketCAN `SO_TIMESTAMPNS`). Not monotonic: use it for logs and replay,
    /// not for control deadlines.
    pub unix_time_us: u64,
}

/// The wall-clock time now, microseconds since the Unix epoch (0 if the clock is before it).
pub fn unix_time_now_us() -> u64 {
    system_time_to_unix_us(std::time::SystemTime::now())
}

/// A `SystemTime` as microseconds since the Unix epoch (0 before the epoch, saturating
/// at `u64::MAX`).
pub fn system_time_to_unix_us(t: std::time::SystemTime) -> u64 {
    t.duration_since(std::time::UNIX_EPOCH).map(|d| u64::try_from(d.as_micros()).unwrap_or(u64::MAX)).unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_are_range_checked() {
        assert!(CanFrame::new_standard(0x7FF, &[]).is_ok());
        assert_eq!(CanFrame::new_standard(0x800, &[]), Err(FrameError::StandardIdTooLarge { id: 0x800 }));
        assert!(CanFrame::new_extended(0x1FFF_FFFF, &[]).is_ok());
        assert_eq!(CanFrame::new_extended(0x2000_0000, &[]), Err(FrameError::ExtendedIdTooLarge { id: 0x2000_0000 }));
        assert_eq!(
            CanFrame::from_parts(0x1_0000, false, false, 0, [0; 8]),
            Err(FrameError::StandardIdTooLarge { id: 0x1_0000 })
        );
    }

    #[test]
    fn dlc_is_limited_and_padding_is_zero() {
        assert_eq!(CanFrame::new_standard(1, &[0; 9]), Err(FrameError::TooLong { len: 9 }));
        assert_eq!(CanFrame::from_parts(1, false, false, 9, [0; 8]), Err(FrameError::TooLong { len: 9 }));
        let a = CanFrame::from_parts(1, false, false, 2, [1, 2, 3, 4, 5, 6, 7, 8]).unwrap();
        let b = CanFrame::new_standard(1, &[1, 2]).unwrap();
        assert_eq!(a, b);
        assert_eq!(a.data_padded(), [1, 2, 0, 0, 0, 0, 0, 0]);
    }

    #[test]
    fn remote_frames_have_no_data() {
        let f = CanFrame::new_remote(CanId::Extended(0x1234_5678), 4).unwrap();
        assert!(f.is_remote() && f.is_extended());
        assert_eq!(f.dlc(), 4);
        assert!(f.data().is_empty());
        assert_eq!(format!("{f:?}"), "CanFrame(12345678#R4)");
    }
}
