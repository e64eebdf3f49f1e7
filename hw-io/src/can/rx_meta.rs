//! Receiving one datagram with what the kernel knows about it: its arrival time
//! (`SO_TIMESTAMPNS`) and how many datagrams the socket's receive queue has dropped so far
//! (`SO_RXQ_OVFL`). Used by the SocketCAN backend; works on any datagram socket (the unit
//! tests use UDP on the loopback interface, which needs no CAN in the kernel).
//!
//! # The kernel's drop counter
//! With `SO_RXQ_OVFL` on, the kernel attaches to a received datagram a `u32` control message:
//! the number of datagrams dropped on this socket's receive queue since the socket was created
//! (queue full), as it was **when that datagram was queued**. It is cumulative and wraps at
//! 2³²; the kernel leaves it out while it is 0. So drops are learnt from the next datagram
//! queued after them (a drop after the last datagram ever received stays unknown), and the
//! difference between two successive values (modulo 2³²) is what was lost between them:
//! [`RxDropCounter`] keeps that sum in 64 bits.
//!
//! Allocation-free after [`MsgReceiver::new`]: the control-message buffer is allocated once.

use std::io;
use std::io::IoSliceMut;
use std::os::fd::{AsFd, AsRawFd, BorrowedFd};

use nix::sys::socket::{ControlMessageOwned, MsgFlags, recvmsg, setsockopt, sockopt};
use nix::sys::time::TimeSpec;

/// The total of datagrams a socket's receive queue dropped, from the kernel's cumulative,
/// wrapping 32-bit counter (`SO_RXQ_OVFL`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RxDropCounter {
    last: u32,
    total: u64,
}

impl RxDropCounter {
    /// A counter at zero (the kernel's counter starts at 0 when the socket is created).
    pub const fn new() -> Self {
        Self { last: 0, total: 0 }
    }

    /// Takes the kernel's value attached to a received datagram; returns the datagrams
    /// dropped since the previous value (wrapping difference, frames).
    ///
    /// **Real-time (1 kHz loop):** called for every received frame; allocation-free.
    pub fn observe(&mut self, kernel_count: u32) -> u32 {
        let new = kernel_count.wrapping_sub(self.last);
        self.last = kernel_count;
        self.total = self.total.saturating_add(u64::from(new));
        new
    }

    /// Datagrams dropped since the socket was created, as far as the datagrams received so
    /// far tell (frames).
    pub const fn total(&self) -> u64 {
        self.total
    }
}

/// What [`MsgReceiver::recv`] got.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Received {
    /// The datagram's length, bytes (larger than the buffer when it was truncated).
    pub len: usize,
    /// The kernel's arrival timestamp, microseconds since the Unix epoch (`None` when the
    /// kernel attached none).
    pub unix_time_us: Option<u64>,
    /// Datagrams the receive queue dropped between the previous received datagram and this
    /// one (frames).
    pub newly_dropped: u32,
}

/// `recvmsg` with a preallocated control-message buffer, reading `SCM_TIMESTAMPNS` and
/// `SO_RXQ_OVFL`, and keeping the socket's drop total.
#[derive(Debug)]
pub struct MsgReceiver {
    cmsg: Vec<u8>,
    drops: RxDropCounter,
}

impl Default for MsgReceiver {
    fn default() -> Self {
        Self::new()
    }
}

impl MsgReceiver {
    /// A receiver; allocates its control-message buffer (room for a timestamp, the drop
    /// counter, and a `SO_TIMESTAMPING` triple should someone enable that too).
    pub fn new() -> Self {
        Self { cmsg: nix::cmsg_space!(TimeSpec, u32, [TimeSpec; 3]), drops: RxDropCounter::new() }
    }

    /// Turns on, for `fd`, the kernel's arrival timestamps (`SO_TIMESTAMPNS`) and drop counter
    /// (`SO_RXQ_OVFL`) on every received datagram.
    ///
    /// **Not for the real-time loop:** socket options, set once when the socket opens.
    pub fn enable(fd: BorrowedFd<'_>) -> io::Result<()> {
        setsockopt(&fd, sockopt::ReceiveTimestampns, &true).map_err(io::Error::from)?;
        setsockopt(&fd, sockopt::RxqOvfl, &1).map_err(io::Error::from)?;
        Ok(())
    }

    /// Receives one datagram into `buf` (blocking unless the socket is non-blocking; errors as
    /// `recvmsg(2)` gives them). Does not allocate.
    ///
    /// **Real-time (1 kHz loop):** called by `SocketCanBus::recv_timeout` for every frame; one
    /// `recvmsg(2)`, no allocation.
    pub fn recv(&mut self, fd: impl AsFd, buf: &mut [u8]) -> io::Result<Received> {
        let fd = fd.as_fd();
        let mut iov = [IoSliceMut::new(buf)];
        // MSG_TRUNC: the datagram's real length, so that a longer one (a CAN FD frame) is told
        // apart from a frame that fits.
        let msg = recvmsg::<()>(fd.as_raw_fd(), &mut iov, Some(&mut self.cmsg), MsgFlags::MSG_TRUNC)
            .map_err(io::Error::from)?;
        let mut out = Received { len: msg.bytes, unix_time_us: None, newly_dropped: 0 };
        // A truncated control area (MSG_CTRUNC, not expected with the buffer above) leaves the
        // datagram without its metadata; the datagram itself is still good.
        if let Ok(cmsgs) = msg.cmsgs() {
            for c in cmsgs {
                match c {
                    ControlMessageOwned::ScmTimestampns(ts) => out.unix_time_us = Some(timespec_to_unix_us(&ts)),
                    ControlMessageOwned::RxqOvfl(count) => out.newly_dropped = self.drops.observe(count),
                    _ => {}
                }
            }
        }
        Ok(out)
    }

    /// Datagrams the socket's receive queue dropped so far (see [`RxDropCounter::total`]).
    pub fn dropped(&self) -> u64 {
        self.drops.total()
    }
}

/// A kernel timestamp as microseconds since the Unix epoch (truncated; 0 before the epoch).
fn timespec_to_unix_us(ts: &TimeSpec) -> u64 {
    let secs = u64::try_from(ts.tv_sec()).unwrap_or(0);
    let micros = u64::try_from(ts.tv_nsec()).unwrap_or(0) / 1000;
    secs.saturating_mul(1_000_000).saturating_add(micros)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::net::UdpSocket;

    #[test]
    fn the_drop_counter_sums_wrapping_differences() {
        let mut c = RxDropCounter::new();
        assert_eq!(c.total(), 0);
        assert_eq!(c.observe(5), 5);
        assert_eq!(c.observe(5), 0, "the same value again: nothing new");
        assert_eq!(c.observe(12), 7);
        assert_eq!(c.total(), 12);
        // Across the kernel counter's wrap: u32::MAX - 2 → 4 is 7 drops.
        let mut c = RxDropCounter::new();
        c.observe(u32::MAX - 2);
        assert_eq!(c.observe(4), 7);
        assert_eq!(c.total(), u64::from(u32::MAX - 2) + 7);
        // Several wraps keep counting past 2^32 in the 64-bit total.
        let mut c = RxDropCounter::new();
        for k in 1..=6u64 {
            c.observe(((k * (1 << 31)) % (1 << 32)) as u32);
        }
        assert_eq!(c.total(), 6 * (1 << 31));
    }

    #[test]
    fn timestamps_convert_to_unix_microseconds() {
        assert_eq!(timespec_to_unix_us(&TimeSpec::new(1_700_000_000, 123_456_789)), 1_700_000_000_123_456);
        assert_eq!(timespec_to_unix_us(&TimeSpec::new(-1, 0)), 0);
    }

    /// On the real kernel (UDP on loopback: no CAN needed): a receiver whose queue is too
    /// small for a burst learns exactly how many datagrams the kernel dropped, and gets a
    /// kernel timestamp on each datagram.
    #[test]
    fn the_kernel_drop_counter_counts_exactly_what_a_full_queue_lost() {
        let rx = UdpSocket::bind("127.0.0.1:0").unwrap();
        let tx = UdpSocket::bind("127.0.0.1:0").unwrap();
        setsockopt(&rx, sockopt::RcvBuf, &4096).unwrap();
        MsgReceiver::enable(rx.as_fd()).unwrap();
        rx.set_nonblocking(true).unwrap();
        let before = std::time::SystemTime::now();
        const SENT: u32 = 500;
        for i in 0..SENT {
            tx.send_to(&i.to_le_bytes(), rx.local_addr().unwrap()).unwrap();
        }
        let mut r = MsgReceiver::new();
        let mut buf = [0u8; 16];
        let mut got = 0u32;
        let mut last_seq = None;
        loop {
            match r.recv(&rx, &mut buf) {
                Ok(m) => {
                    assert_eq!(m.len, 4);
                    assert!(m.unix_time_us.unwrap() >= crate::can::system_time_to_unix_us(before) - 1);
                    last_seq = Some(u32::from_le_bytes(buf[..4].try_into().unwrap()));
                    got += 1;
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => break,
                Err(e) => panic!("{e}"),
            }
        }
        assert!(got < SENT, "the small queue must have overflowed ({got} received)");
        // The drops are learnt from a datagram queued after them: one more, read now.
        tx.send_to(&SENT.to_le_bytes(), rx.local_addr().unwrap()).unwrap();
        loop {
            match r.recv(&rx, &mut buf) {
                Ok(_) => break,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => std::thread::yield_now(),
                Err(e) => panic!("{e}"),
            }
        }
        assert!(last_seq.is_some());
        assert_eq!(u64::from(got) + r.dropped(), u64::from(SENT), "received + dropped = sent");
    }
}
