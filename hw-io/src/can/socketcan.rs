//! Linux SocketCAN backend (raw `AF_CAN` socket, classic CAN frames).
//!
//! Receive waits in `ppoll` (nanosecond timeout, no busy-polling), then reads one frame with
//! its kernel arrival time (`SO_TIMESTAMPNS`); neither allocates.
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
use super::frame::{CanFrame, CanId, TimedFrame, system_time_to_unix_us, unix_time_now_us};

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
}

impl SocketCanBus {
    /// Open `interface` and enable kernel receive timestamps.
    pub fn open(interface: &str) -> Result<Self, OpenError> {
        let socket =
            socketcan::CanSocket::open(interface).map_err(|e| classify_open_error(interface, e, kernel_lacks_can))?;
        socket.set_recv_timestamp(true).map_err(|source| OpenError::Io { interface: interface.to_owned(), source })?;
        Ok(Self { socket, interface: interface.to_owned() })
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
        let (frame, stamps) = self.socket.read_frame_with_timestamps().map_err(recv_error)?;
        let unix_time_us = stamps.socket.map(system_time_to_unix_us).unwrap_or_else(unix_time_now_us);
        Ok(Some(TimedFrame { frame: from_socketcan(&frame)?, unix_time_us }))
    }
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
}
