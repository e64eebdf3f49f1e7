//! Linux SocketCAN backend (raw `AF_CAN` socket, classic CAN frames).
//!
//! Receive waits in `ppoll` (nanosecond timeout, no busy-polling), then reads one frame with
//! `recvmsg` and its two control messages: the kernel arrival time (`SO_TIMESTAMPNS`) and the
//! socket's receive-queue drop counter (`SO_RXQ_OVFL`), which [`CanBus::dropped_rx_frames`]
//! reports (frames the kernel dropped because this socket's receive queue was full, learnt from
//! the next frame queued after them: see [`super::rx_meta`]). Neither allocates after
//! [`SocketCanBus::open`].
//!
//! On a machine whose kernel has no CAN support, [`SocketCanBus::open`] fails with
//! [`OpenError::NoKernelCan`]; with CAN support but no such interface, with
//! [`OpenError::NoSuchInterface`].

use std::io;
use std::os::fd::AsFd;
use std::time::{Duration, Instant};

use nix::errno::Errno;
use nix::poll::{PollFd, PollFlags, ppoll};
use nix::sys::time::TimeSpec;
use socketcan::{EmbeddedFrame, ExtendedId, Frame, Id, Socket, SocketOptions, StandardId};

use super::bus::{CanBus, RecvError, SendError};
use super::frame::{CanFrame, CanId, TimedFrame, unix_time_now_us};
use super::rx_meta::MsgReceiver;

/// Bytes of a classic CAN frame on a raw socket (`struct can_frame`, `CAN_MTU`).
const CAN_MTU: usize = 16;

/// Why a SocketCAN interface could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    /// The running kernel has no CAN support: creating an `AF_CAN` socket fails with
    /// `EAFNOSUPPORT`.
    #[error(
        "cannot open CAN interface {interface:?}: the kernel has no CAN support \
         (socket(AF_CAN) failed: {source}); load the CAN modules \
         (`modprobe can can-raw vcan`, or the adapter's driver) or run on a kernel built \
         with CONFIG_CAN"
    )]
    NoKernelCan {
        /// The interface asked for.
        interface: String,
        /// The operating-system error.
        #[source]
        source: io::Error,
    },
    /// The kernel has CAN support but there is no interface of that name.
    #[error(
        "no CAN interface {interface:?} ({source}); for a virtual bus: \
         `ip link add dev {interface} type vcan && ip link set up {interface}`"
    )]
    NoSuchInterface {
        /// The interface asked for.
        interface: String,
        /// The operating-system error.
        #[source]
        source: io::Error,
    },
    /// Any other operating-system error while opening or configuring the socket.
    #[error("cannot open CAN interface {interface:?}: {source}")]
    Io {
        /// The interface asked for.
        interface: String,
        /// The operating-system error.
        #[source]
        source: io::Error,
    },
}

/// A raw SocketCAN socket bound to one interface (`can0`, `vcan0`, ...).
#[derive(Debug)]
pub struct SocketCanBus {
    socket: socketcan::CanSocket,
    interface: String,
    /// `recvmsg` with its preallocated control-message buffer and the drop total.
    rx: MsgReceiver,
}

impl SocketCanBus {
    /// Open `interface` and enable kernel receive timestamps (`SO_TIMESTAMPNS`) and the
    /// receive-queue drop counter (`SO_RXQ_OVFL`).
    ///
    /// **Not for the real-time loop:** opens and configures a socket (system calls,
    /// allocation); call it at start-up.
    pub fn open(interface: &str) -> Result<Self, OpenError> {
        let socket =
            socketcan::CanSocket::open(interface).map_err(|e| classify_open_error(interface, e, kernel_lacks_can))?;
        MsgReceiver::enable(socket.as_fd())
            .map_err(|source| OpenError::Io { interface: interface.to_owned(), source })?;
        Ok(Self { socket, interface: interface.to_owned(), rx: MsgReceiver::new() })
    }

    /// Receive only the standard-identifier frames whose 11-bit identifier is in `ids` (kernel
    /// filters, `CAN_RAW_FILTER`: the others never reach this socket's queue, so a reader that
    /// needs a few identifiers of a busy bus does not pay for the rest). Error frames still
    /// arrive. An empty list receives nothing.
    ///
    /// **Not for the real-time loop:** a socket option, set once at start-up.
    pub fn set_receive_filter(&mut self, ids: &[u16]) -> io::Result<()> {
        const CAN_SFF_MASK: u32 = 0x7FF;
        const CAN_EFF_FLAG: u32 = 0x8000_0000;
        const CAN_RTR_FLAG: u32 = 0x4000_0000;
        let filters: Vec<(u32, u32)> =
            ids.iter().map(|&id| (u32::from(id) & CAN_SFF_MASK, CAN_SFF_MASK | CAN_EFF_FLAG | CAN_RTR_FLAG)).collect();
        self.socket.set_filters(&filters)
    }

    /// The interface name this socket is bound to.
    pub fn interface(&self) -> &str {
        &self.interface
    }

    /// Also receive the frames this socket sends (`CAN_RAW_RECV_OWN_MSGS`), stamped by the
    /// kernel like every other frame: the same timestamp every other socket on the interface
    /// (e.g. candump) sees for that frame. fulcrumd uses its own SYNC's echo as the time
    /// reference of the cycle's collection window (docs/daemon.md).
    pub fn receive_own_frames(&mut self, on: bool) -> io::Result<()> {
        self.socket.set_recv_own_msgs(on)
    }

    /// Asks for a kernel receive queue of `bytes` bytes for this socket (`SO_RCVBUFFORCE`
    /// when the process may, else `SO_RCVBUF`, which the kernel caps at
    /// `net.core.rmem_max`) and returns the size the kernel granted, bytes. The kernel counts
    /// its bookkeeping in it (about 1 KiB per classic CAN frame) and doubles the request. A
    /// frame arriving at a full queue is dropped by the kernel.
    ///
    /// **Not for the real-time loop:** a socket option, set once at start-up.
    pub fn set_receive_buffer(&mut self, bytes: usize) -> io::Result<usize> {
        use nix::sys::socket::{getsockopt, setsockopt, sockopt};
        let fd = self.socket.as_fd();
        if setsockopt(&fd, sockopt::RcvBufForce, &bytes).is_err() {
            setsockopt(&fd, sockopt::RcvBuf, &bytes).map_err(io::Error::from)?;
        }
        getsockopt(&fd, sockopt::RcvBuf).map_err(io::Error::from)
    }

    /// The underlying `socketcan` socket, e.g. to set filters.
    pub fn socket(&self) -> &socketcan::CanSocket {
        &self.socket
    }
}

/// The error of creating an `AF_CAN` socket, if that fails with `EAFNOSUPPORT`.
fn kernel_lacks_can() -> Option<io::Error> {
    // Interface index 0 binds a raw socket to all CAN interfaces; only the socket() call
    // matters here.
    socketcan::CanSocket::open_iface(0).err().filter(is_no_can)
}

fn is_no_can(e: &io::Error) -> bool {
    matches!(e.raw_os_error(), Some(c) if c == Errno::EAFNOSUPPORT as i32 || c == Errno::EPROTONOSUPPORT as i32)
}

/// Map an error of `CanSocket::open` to an [`OpenError`]. An unknown interface name
/// (`ENODEV`) is looked at twice: on a kernel without CAN there cannot be a CAN interface,
/// and "no kernel support" is the useful message. `kernel_lacks_can` returns the
/// `EAFNOSUPPORT` error of a probe socket, or `None` if the kernel has CAN.
pub(crate) fn classify_open_error(
    interface: &str,
    source: io::Error,
    kernel_lacks_can: impl FnOnce() -> Option<io::Error>,
) -> OpenError {
    let interface = interface.to_owned();
    if is_no_can(&source) {
        return OpenError::NoKernelCan { interface, source };
    }
    match source.raw_os_error() {
        Some(c) if c == Errno::ENODEV as i32 || c == Errno::ENXIO as i32 => match kernel_lacks_can() {
            Some(probe) => OpenError::NoKernelCan { interface, source: probe },
            None => OpenError::NoSuchInterface { interface, source },
        },
        _ => OpenError::Io { interface, source },
    }
}

fn is_interface_down(e: &io::Error) -> bool {
    matches!(e.raw_os_error(), Some(c) if c == Errno::ENETDOWN as i32 || c == Errno::ENODEV as i32 || c == Errno::ENXIO as i32)
}

fn send_error(e: io::Error) -> SendError {
    if e.raw_os_error() == Some(Errno::ENOBUFS as i32) || e.kind() == io::ErrorKind::WouldBlock {
        SendError::TxQueueFull
    } else if is_interface_down(&e) {
        SendError::InterfaceDown(e)
    } else {
        SendError::Io(e)
    }
}

fn recv_error(e: io::Error) -> RecvError {
    if is_interface_down(&e) { RecvError::InterfaceDown(e) } else { RecvError::Io(e) }
}

/// Our frame as a `socketcan` frame (`None` only for an ID out of range, which our
/// constructors make impossible).
pub(crate) fn to_socketcan(f: &CanFrame) -> Option<socketcan::CanFrame> {
    let id: Id = match f.id() {
        CanId::Standard(id) => Id::Standard(StandardId::new(id)?),
        CanId::Extended(id) => Id::Extended(ExtendedId::new(id)?),
    };
    if f.is_remote() {
        socketcan::CanFrame::new_remote(id, usize::from(f.dlc()))
    } else {
        socketcan::CanFrame::new(id, f.data())
    }
}

/// A `socketcan` frame as ours; an error frame or an impossible length is an error.
pub(crate) fn from_socketcan(f: &socketcan::CanFrame) -> Result<CanFrame, RecvError> {
    if let socketcan::CanFrame::Error(e) = f {
        return Err(RecvError::ErrorFrame(e.id_word()));
    }
    let id = match f.id() {
        Id::Standard(id) => CanId::Standard(id.as_raw()),
        Id::Extended(id) => CanId::Extended(id.as_raw()),
    };
    let frame = if f.is_remote_frame() {
        let dlc = u8::try_from(f.dlc()).map_err(|_| RecvError::NotClassicCan)?;
        CanFrame::new_remote(id, dlc)
    } else {
        CanFrame::new_data(id, f.data())
    };
    frame.map_err(|_| RecvError::NotClassicCan)
}

impl CanBus for SocketCanBus {
    fn send(&mut self, frame: &CanFrame) -> Result<(), SendError> {
        let f = to_socketcan(frame)
            .ok_or_else(|| SendError::Io(io::Error::new(io::ErrorKind::InvalidInput, "CAN identifier out of range")))?;
        self.socket.write_frame(&f).map_err(send_error)
    }

    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<TimedFrame>, RecvError> {
        let start = Instant::now();
        loop {
            let remaining = timeout.saturating_sub(start.elapsed());
            let mut fds = [PollFd::new(self.socket.as_fd(), PollFlags::POLLIN)];
            match ppoll(&mut fds, Some(TimeSpec::from(remaining)), None) {
                Ok(0) => return Ok(None),
                Ok(_) => break,
                Err(Errno::EINTR) if start.elapsed() < timeout => continue,
                Err(Errno::EINTR) => return Ok(None),
                Err(e) => return Err(recv_error(io::Error::from(e))),
            }
        }
        let mut buf = [0u8; CAN_MTU];
        let got = self.rx.recv(&self.socket, &mut buf).map_err(recv_error)?;
        if got.len != CAN_MTU {
            return Err(RecvError::NotClassicCan);
        }
        let unix_time_us = got.unix_time_us.unwrap_or_else(unix_time_now_us);
        Ok(Some(TimedFrame { frame: from_socketcan(&raw_to_socketcan(&buf))?, unix_time_us }))
    }

    fn dropped_rx_frames(&self) -> u64 {
        self.rx.dropped()
    }
}

/// The bytes of a `struct can_frame` as a `socketcan` frame: `can_id` (native-endian `u32`
/// with the EFF/RTR/ERR flags), `len` at byte 4, `len8_dlc` at byte 7, the data at 8..16.
fn raw_to_socketcan(buf: &[u8; CAN_MTU]) -> socketcan::CanFrame {
    let mut raw = socketcan::frame::can_frame_default();
    raw.can_id = u32::from_ne_bytes([buf[0], buf[1], buf[2], buf[3]]);
    raw.can_dlc = buf[4];
    raw.len8_dlc = buf[7];
    raw.data.copy_from_slice(&buf[8..CAN_MTU]);
    // `From` clamps the length to 8 and picks data, remote or error frame from the flags.
    socketcan::CanFrame::from(raw)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn os_err(e: Errno) -> io::Error {
        io::Error::from_raw_os_error(e as i32)
    }

    #[test]
    fn eafnosupport_means_no_kernel_can() {
        let e = classify_open_error("can0", os_err(Errno::EAFNOSUPPORT), || unreachable!());
        assert!(matches!(e, OpenError::NoKernelCan { .. }));
        let msg = e.to_string();
        assert!(msg.contains("kernel has no CAN support") && msg.contains("modprobe"), "{msg}");
    }

    #[test]
    fn enodev_is_classified_by_probing_the_kernel() {
        let e = classify_open_error("vcan9", os_err(Errno::ENODEV), || Some(os_err(Errno::EAFNOSUPPORT)));
        assert!(
            matches!(&e, OpenError::NoKernelCan { source, .. } if source.raw_os_error() == Some(Errno::EAFNOSUPPORT as i32))
        );
        let e = classify_open_error("vcan9", os_err(Errno::ENODEV), || None);
        assert!(matches!(e, OpenError::NoSuchInterface { .. }));
        assert!(e.to_string().contains("ip link add dev vcan9 type vcan"));
        let e = classify_open_error("vcan9", os_err(Errno::EPERM), || None);
        assert!(matches!(e, OpenError::Io { .. }));
    }

    #[test]
    fn send_and_recv_errors_are_classified() {
        assert!(matches!(send_error(os_err(Errno::ENOBUFS)), SendError::TxQueueFull));
        assert!(matches!(send_error(os_err(Errno::EAGAIN)), SendError::TxQueueFull));
        assert!(matches!(send_error(os_err(Errno::ENETDOWN)), SendError::InterfaceDown(_)));
        assert!(matches!(send_error(os_err(Errno::EIO)), SendError::Io(_)));
        assert!(matches!(recv_error(os_err(Errno::ENETDOWN)), RecvError::InterfaceDown(_)));
        assert!(matches!(recv_error(os_err(Errno::EIO)), RecvError::Io(_)));
    }

    #[test]
    fn frames_convert_both_ways() {
        let frames = [
            CanFrame::new_standard(0x181, &[1, 2, 3, 4, 5, 6, 7, 8]).unwrap(),
            CanFrame::new_standard(0x080, &[]).unwrap(),
            CanFrame::new_extended(0x1FFF_FFFF, &[9]).unwrap(),
            CanFrame::new_remote(CanId::Standard(0x7FF), 8).unwrap(),
            CanFrame::new_remote(CanId::Extended(0x1234_5678), 0).unwrap(),
        ];
        for f in frames {
            let s = to_socketcan(&f).unwrap();
            assert_eq!(from_socketcan(&s).unwrap(), f);
        }
        let err = socketcan::CanFrame::Error(socketcan::CanErrorFrame::new_error(0x0000_0040, &[0; 8]).unwrap());
        assert!(matches!(from_socketcan(&err), Err(RecvError::ErrorFrame(w)) if w & 0x40 != 0));
    }

    /// `struct can_frame` bytes as the kernel hands them over.
    fn raw(can_id: u32, len: u8, data: &[u8]) -> [u8; CAN_MTU] {
        let mut b = [0u8; CAN_MTU];
        b[..4].copy_from_slice(&can_id.to_ne_bytes());
        b[4] = len;
        b[8..8 + data.len()].copy_from_slice(data);
        b
    }

    #[test]
    fn raw_kernel_frames_convert() {
        let f = from_socketcan(&raw_to_socketcan(&raw(0x181, 8, &[1, 2, 3, 4, 5, 6, 7, 8]))).unwrap();
        assert_eq!(f, CanFrame::new_standard(0x181, &[1, 2, 3, 4, 5, 6, 7, 8]).unwrap());
        let f = from_socketcan(&raw_to_socketcan(&raw(0x701, 1, &[0x05, 0xEE]))).unwrap();
        assert_eq!(f, CanFrame::new_standard(0x701, &[0x05]).unwrap(), "bytes past len are not data");
        let f = from_socketcan(&raw_to_socketcan(&raw(0x8000_0181, 1, &[9]))).unwrap();
        assert_eq!(f, CanFrame::new_extended(0x181, &[9]).unwrap());
        let f = from_socketcan(&raw_to_socketcan(&raw(0x4000_07FF, 8, &[]))).unwrap();
        assert_eq!(f, CanFrame::new_remote(CanId::Standard(0x7FF), 8).unwrap());
        assert!(matches!(
            from_socketcan(&raw_to_socketcan(&raw(0x2000_0040, 8, &[0; 8]))),
            Err(RecvError::ErrorFrame(w)) if w & 0x40 != 0
        ));
    }
}
