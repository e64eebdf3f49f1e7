//! An in-process CAN bus: a hub and endpoints, for unit tests, the simulator and the demo.
//!
//! Every frame sent by one endpoint is delivered to every other endpoint (not back to the
//! sender), in the same order for all of them, like a real CAN bus. Each endpoint has a
//! bounded receive queue fixed at construction; when it is full the frame is dropped for
//! that endpoint and counted ([`InProcessEndpoint::dropped_rx_frames`],
//! [`InProcessBus::dropped_frames`]), never silently.
//!
//! All memory is allocated when the hub is built; `send` and `recv_timeout` allocate
//! nothing. `recv_timeout` blocks on a condition variable (no busy-polling).
//!
//! ```
//! use std::time::Duration;
//! use hw_io::can::{CanBus, CanFrame, InProcessBus};
//! let bus = InProcessBus::new();
//! let mut controller = bus.endpoint().unwrap();
//! let mut node = bus.endpoint().unwrap();
//! controller.send(&CanFrame::new_standard(0x080, &[1]).unwrap()).unwrap();
//! let got = node.recv_timeout(Duration::from_millis(10)).unwrap().unwrap();
//! assert_eq!(got.frame.data(), &[1]);
//! assert!(controller.recv_timeout(Duration::ZERO).unwrap().is_none()); // no echo
//! ```

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

use super::bus::{CanBus, RecvError, SendError};
use super::frame::{CanFrame, TimedFrame, unix_time_now_us};

/// Default number of endpoints of [`InProcessBus::new`].
pub const DEFAULT_MAX_ENDPOINTS: usize = 8;
/// Default receive-queue length of each endpoint of [`InProcessBus::new`], frames.
pub const DEFAULT_QUEUE_FRAMES: usize = 256;

/// Why no endpoint could be created.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
pub enum EndpointError {
    /// Every endpoint slot of the hub is in use.
    #[error("all {max} endpoints of the in-process CAN bus are in use")]
    TooManyEndpoints {
        /// Endpoints the hub was built for.
        max: usize,
    },
}

/// Fixed-capacity FIFO of frames.
struct Ring {
    buf: Box<[TimedFrame]>,
    head: usize,
    len: usize,
}

impl Ring {
    fn new(capacity: usize) -> Self {
        let empty = TimedFrame { frame: CanFrame::standard_masked(0, 0, [0; 8]), unix_time_us: 0 };
        Self { buf: vec![empty; capacity.max(1)].into_boxed_slice(), head: 0, len: 0 }
    }

    fn push(&mut self, f: TimedFrame) -> bool {
        if self.len == self.buf.len() {
            return false;
        }
        let tail = (self.head + self.len) % self.buf.len();
        self.buf[tail] = f;
        self.len += 1;
        true
    }

    fn pop(&mut self) -> Option<TimedFrame> {
        if self.len == 0 {
            return None;
        }
        let f = self.buf[self.head];
        self.head = (self.head + 1) % self.buf.len();
        self.len -= 1;
        Some(f)
    }

    fn clear(&mut self) {
        self.head = 0;
        self.len = 0;
    }
}

struct Port {
    in_use: AtomicBool,
    queue: Mutex<Ring>,
    ready: Condvar,
    dropped: AtomicU64,
}

struct Shared {
    ports: Box<[Port]>,
    /// Held while one frame is delivered to every port, so all see the same order.
    send_order: Mutex<()>,
    dropped_total: AtomicU64,
    queue_frames: usize,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // No code here panics while holding a lock; should a caller's panic poison one anyway,
    // the queue is still consistent (every update completes before unlocking).
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// The hub of an in-process CAN bus. Cheap to clone (all clones are the same bus).
#[derive(Clone)]
pub struct InProcessBus {
    shared: Arc<Shared>,
}

impl Default for InProcessBus {
    fn default() -> Self {
        Self::new()
    }
}

impl core::fmt::Debug for InProcessBus {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("InProcessBus")
            .field("max_endpoints", &self.max_endpoints())
            .field("queue_frames", &self.shared.queue_frames)
            .field("dropped_frames", &self.dropped_frames())
            .finish()
    }
}

impl InProcessBus {
    /// A bus for up to 8 endpoints with 256-frame receive queues.
    pub fn new() -> Self {
        Self::with_capacity(DEFAULT_MAX_ENDPOINTS, DEFAULT_QUEUE_FRAMES)
    }

    /// A bus for up to `max_endpoints` endpoints, each with a receive queue of
    /// `queue_frames` frames (both at least 1). All memory is allocated here.
    pub fn with_capacity(max_endpoints: usize, queue_frames: usize) -> Self {
        let queue_frames = queue_frames.max(1);
        let ports = (0..max_endpoints.max(1))
            .map(|_| Port {
                in_use: AtomicBool::new(false),
                queue: Mutex::new(Ring::new(queue_frames)),
                ready: Condvar::new(),
                dropped: AtomicU64::new(0),
            })
            .collect();
        Self {
            shared: Arc::new(Shared {
                ports,
                send_order: Mutex::new(()),
                dropped_total: AtomicU64::new(0),
                queue_frames,
            }),
        }
    }

    /// Endpoints this bus was built for.
    pub fn max_endpoints(&self) -> usize {
        self.shared.ports.len()
    }

    /// Attach a new endpoint; its receive queue starts empty. A dropped endpoint frees its
    /// slot.
    pub fn endpoint(&self) -> Result<InProcessEndpoint, EndpointError> {
        for (index, port) in self.shared.ports.iter().enumerate() {
            if port.in_use.compare_exchange(false, true, Ordering::AcqRel, Ordering::Acquire).is_ok() {
                lock(&port.queue).clear();
                port.dropped.store(0, Ordering::Relaxed);
                return Ok(InProcessEndpoint { shared: Arc::clone(&self.shared), index });
            }
        }
        Err(EndpointError::TooManyEndpoints { max: self.shared.ports.len() })
    }

    /// Frames dropped on this bus because a receive queue was full, all endpoints together,
    /// since the bus was built.
    pub fn dropped_frames(&self) -> u64 {
        self.shared.dropped_total.load(Ordering::Relaxed)
    }
}

/// One node's connection to an [`InProcessBus`]. `Send`: move it to the thread that uses it.
pub struct InProcessEndpoint {
    shared: Arc<Shared>,
    index: usize,
}

impl core::fmt::Debug for InProcessEndpoint {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("InProcessEndpoint")
            .field("index", &self.index)
            .field("dropped_rx_frames", &self.dropped_rx_frames())
            .finish()
    }
}

impl InProcessEndpoint {
    /// Send a frame stamped with `unix_time_us` (microseconds since the Unix epoch) instead of
    /// the wall clock: for a simulator running on virtual time. Never fails.
    pub fn send_at(&mut self, frame: &CanFrame, unix_time_us: u64) {
        let timed = TimedFrame { frame: *frame, unix_time_us };
        let _order = lock(&self.shared.send_order);
        for (i, port) in self.shared.ports.iter().enumerate() {
            if i == self.index || !port.in_use.load(Ordering::Acquire) {
                continue;
            }
            let delivered = lock(&port.queue).push(timed);
            if delivered {
                port.ready.notify_one();
            } else {
                port.dropped.fetch_add(1, Ordering::Relaxed);
                self.shared.dropped_total.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    /// Frames waiting in this endpoint's receive queue.
    pub fn pending(&self) -> usize {
        lock(&self.port().queue).len
    }

    /// Frames this endpoint lost because its receive queue was full.
    pub fn dropped_rx_frames(&self) -> u64 {
        self.port().dropped.load(Ordering::Relaxed)
    }

    fn port(&self) -> &Port {
        &self.shared.ports[self.index]
    }
}

impl CanBus for InProcessEndpoint {
    fn send(&mut self, frame: &CanFrame) -> Result<(), SendError> {
        self.send_at(frame, unix_time_now_us());
        Ok(())
    }

    fn recv_timeout(&mut self, timeout: Duration) -> Result<Option<TimedFrame>, RecvError> {
        let port = self.port();
        let mut queue = lock(&port.queue);
        if let Some(f) = queue.pop() {
            return Ok(Some(f));
        }
        if timeout.is_zero() {
            return Ok(None);
        }
        let deadline = Instant::now().checked_add(timeout);
        loop {
            queue = match deadline {
                None => port.ready.wait(queue).unwrap_or_else(PoisonError::into_inner),
                Some(deadline) => {
                    let now = Instant::now();
                    if now >= deadline {
                        return Ok(None);
                    }
                    port.ready.wait_timeout(queue, deadline - now).unwrap_or_else(PoisonError::into_inner).0
                }
            };
            if let Some(f) = queue.pop() {
                return Ok(Some(f));
            }
        }
    }

    fn dropped_rx_frames(&self) -> u64 {
        InProcessEndpoint::dropped_rx_frames(self)
    }
}

impl Drop for InProcessEndpoint {
    fn drop(&mut self) {
        let port = self.port();
        lock(&port.queue).clear();
        port.in_use.store(false, Ordering::Release);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(id: u16, b: u8) -> CanFrame {
        CanFrame::new_standard(id, &[b]).unwrap()
    }

    #[test]
    fn broadcasts_to_all_others_in_order() {
        let bus = InProcessBus::new();
        let mut a = bus.endpoint().unwrap();
        let mut b = bus.endpoint().unwrap();
        let mut c = bus.endpoint().unwrap();
        for i in 0..10 {
            a.send(&frame(0x100, i)).unwrap();
        }
        c.send(&frame(0x200, 99)).unwrap();
        for ep in [&mut b, &mut c] {
            for i in 0..10 {
                let f = ep.recv_timeout(Duration::ZERO).unwrap().unwrap();
                assert_eq!(f.frame, frame(0x100, i));
            }
        }
        assert_eq!(b.recv_timeout(Duration::ZERO).unwrap().unwrap().frame, frame(0x200, 99));
        assert_eq!(a.recv_timeout(Duration::ZERO).unwrap().unwrap().frame, frame(0x200, 99));
        for ep in [&mut a, &mut b, &mut c] {
            assert!(ep.recv_timeout(Duration::ZERO).unwrap().is_none());
        }
    }

    #[test]
    fn full_queue_drops_and_counts() {
        let bus = InProcessBus::with_capacity(3, 4);
        let mut tx = bus.endpoint().unwrap();
        let mut slow = bus.endpoint().unwrap();
        let mut fast = bus.endpoint().unwrap();
        for i in 0..6 {
            tx.send(&frame(0x181, i)).unwrap();
            fast.recv_timeout(Duration::ZERO).unwrap().unwrap();
        }
        assert_eq!(slow.pending(), 4);
        assert_eq!(slow.dropped_rx_frames(), 2);
        assert_eq!(CanBus::dropped_rx_frames(&slow), 2);
        assert_eq!(fast.dropped_rx_frames(), 0);
        assert_eq!(bus.dropped_frames(), 2);
        // The oldest four were kept.
        for i in 0..4 {
            assert_eq!(slow.recv_timeout(Duration::ZERO).unwrap().unwrap().frame, frame(0x181, i));
        }
    }

    #[test]
    fn endpoint_slots_are_bounded_and_reused() {
        let bus = InProcessBus::with_capacity(2, 4);
        let a = bus.endpoint().unwrap();
        let mut b = bus.endpoint().unwrap();
        assert_eq!(bus.endpoint().unwrap_err(), EndpointError::TooManyEndpoints { max: 2 });
        b.send(&frame(1, 1)).unwrap();
        drop(a);
        let c = bus.endpoint().unwrap();
        assert_eq!(c.pending(), 0, "a new endpoint must not see its predecessor's frames");
    }

    #[test]
    fn recv_times_out_and_wakes_on_send() {
        let bus = InProcessBus::new();
        let mut rx = bus.endpoint().unwrap();
        let mut tx = bus.endpoint().unwrap();
        let t0 = Instant::now();
        assert!(rx.recv_timeout(Duration::from_millis(20)).unwrap().is_none());
        assert!(t0.elapsed() >= Duration::from_millis(20));

        let sender = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(30));
            tx.send_at(&frame(0x080, 7), 42);
        });
        let t0 = Instant::now();
        let got = rx.recv_timeout(Duration::from_secs(5)).unwrap().unwrap();
        let waited = t0.elapsed();
        sender.join().unwrap();
        assert_eq!(got, TimedFrame { frame: frame(0x080, 7), unix_time_us: 42 });
        assert!(waited >= Duration::from_millis(25) && waited < Duration::from_secs(4), "{waited:?}");
    }

    #[test]
    fn timestamps_are_wall_clock_microseconds() {
        let bus = InProcessBus::new();
        let mut rx = bus.endpoint().unwrap();
        let mut tx = bus.endpoint().unwrap();
        let before = unix_time_now_us();
        tx.send(&frame(1, 1)).unwrap();
        let after = unix_time_now_us();
        let t = rx.recv_timeout(Duration::ZERO).unwrap().unwrap().unix_time_us;
        assert!(before <= t && t <= after);
    }
}
