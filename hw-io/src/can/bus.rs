//! The one trait every bus backend implements.

use std::time::Duration;

use super::frame::{CanFrame, TimedFrame};

/// Why a frame could not be sent.
#[derive(Debug, thiserror::Error)]
pub enum SendError {
    /// The driver's transmit queue is full (`ENOBUFS`/`EAGAIN`): the bus is overloaded or
    /// nobody acknowledges. The frame was not sent; retrying later may succeed.
    #[error("CAN transmit queue full (bus overloaded or no node acknowledging)")]
    TxQueueFull,
    /// The interface is down (`ENETDOWN`) or gone (`ENODEV`, `ENXIO`).
    #[error("CAN interface is down or gone: {0}")]
    InterfaceDown(#[source] std::io::Error),
    /// Any other operating-system error.
    #[error("CAN send failed: {0}")]
    Io(#[source] std::io::Error),
}

/// Why no frame could be received.
#[derive(Debug, thiserror::Error)]
pub enum RecvError {
    /// A replayed log has no more frames.
    #[error("end of the replayed CAN log")]
    EndOfReplay,
    /// The controller reported a bus error (a SocketCAN error frame); the `u32` is the
    /// `can_id` with the error-class bits (`CAN_ERR_*` in `linux/can/error.h`).
    #[error("CAN error frame, error class 0x{0:08X}")]
    ErrorFrame(u32),
    /// A frame that is not classic CAN (e.g. CAN FD) arrived.
    #[error("received a frame that is not classic CAN")]
    NotClassicCan,
    /// The interface is down (`ENETDOWN`) or gone (`ENODEV`, `ENXIO`).
    #[error("CAN interface is down or gone: {0}")]
    InterfaceDown(#[source] std::io::Error),
    /// Any other operating-system error.
    #[error("CAN receive failed: {0}")]
    Io(#[source] std::io::Error),
}

/// A CAN bus as the controller and the simulator see it, whatever is behind it
/// (SocketCAN, the in-process bus, a replayed candump log).
///
/// Like a real CAN socket, an endpoint does not receive its own frames back.
pub trait CanBus {
    /// Queue one frame for transmission. Does not wait for the bus.
    ///
    /// **Real-time (1 kHz loop):** the loop sends its SYNC through this once a cycle;
    /// implementations must not block on the bus nor allocate.
    fn send(&mut self, frame: &CanFrame) -> Result<(), SendError>;

    /// Wait at most `timeout` for the next frame; `Ok(None)` when the time ran out.
    /// A zero `timeout` polls without blocking. Never busy-polls.
    ///
    /// **Real-time (1 kHz loop):** the loop's only wait, bounded by `timeout`; implementations
    /// must not allocate.
    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<TimedFrame>, RecvError>;

    /// Frames this endpoint lost because its receive queue was full, since it was opened
    /// (0 where the backend cannot tell).
    ///
    /// **Real-time (1 kHz loop):** read once a cycle; a counter, no system call.
    fn dropped_rx_frames(&self) -> u64 {
        0
    }
}

impl<B: CanBus + ?Sized> CanBus for &mut B {
    fn send(&mut self, frame: &CanFrame) -> Result<(), SendError> {
        (**self).send(frame)
    }
    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<TimedFrame>, RecvError> {
        (**self).recv_timeout(timeout)
    }
    fn dropped_rx_frames(&self) -> u64 {
        (**self).dropped_rx_frames()
    }
}

impl<B: CanBus + ?Sized> CanBus for Box<B> {
    fn send(&mut self, frame: &CanFrame) -> Result<(), SendError> {
        (**self).send(frame)
    }
    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<TimedFrame>, RecvError> {
        (**self).recv_timeout(timeout)
    }
    fn dropped_rx_frames(&self) -> u64 {
        (**self).dropped_rx_frames()
    }
}
