//! The real-time side: the lock-free queue's storage, the flags the three parties share, and
//! the [`RecorderProducer`] the 1 kHz thread pushes into.

use std::ptr::NonNull;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use heapless::spsc::{Consumer, Producer, Queue};

use super::stats::{RecorderStats, add};

/// Owns the heap block of the queue; the producer and consumer halves borrow it for `'static`
/// and each keeps an `Arc` to this owner, declared after the half so that it drops last.
pub(super) struct QueueStorage<T, const N: usize> {
    ptr: NonNull<Queue<T, N>>,
}

// SAFETY: the storage is only a heap block; access goes through the spsc halves, which are
// `Send` when `T: Send`. The block is freed only when the last `Arc` (held next to each half) drops.
unsafe impl<T: Send, const N: usize> Send for QueueStorage<T, N> {}
// SAFETY: as above; `&QueueStorage` gives no access to the queue.
unsafe impl<T: Send, const N: usize> Sync for QueueStorage<T, N> {}

impl<T, const N: usize> QueueStorage<T, N> {
    /// Allocates an empty queue directly on the heap (a `Box::new(Queue::new())` would build it
    /// on the stack first, which overflows for large `N * size_of::<T>()` in debug builds).
    pub(super) fn allocate() -> Option<Self> {
        let layout = std::alloc::Layout::new::<Queue<T, N>>();
        // SAFETY: the layout is not zero-sized (the queue holds two atomics). An all-zero
        // `heapless::spsc::Queue` (0.9) is exactly `Queue::new()`: head and tail are
        // `AtomicUsize(0)` and the buffer is `[UnsafeCell<MaybeUninit<T>>; N]`, for which any
        // bytes are valid. The block comes from the global allocator with the layout of the type,
        // as `Box::from_raw` in `Drop` requires.
        let raw = unsafe { std::alloc::alloc_zeroed(layout) };
        let ptr = NonNull::new(raw.cast::<Queue<T, N>>())?;
        // A large zeroed block is fresh mmap'd memory, not yet backed by pages: touch each page
        // now, so that the real-time thread takes no page fault on its first pushes.
        let mut offset = 0;
        while offset < layout.size() {
            // SAFETY: `offset < size`, inside the block; writing 0 keeps every byte as it is.
            unsafe { std::ptr::write_volatile(raw.add(offset), 0) };
            offset += 4096;
        }
        Some(Self { ptr })
    }

    /// Splits into the two halves, borrowed for `'static`.
    ///
    /// # Safety
    /// Call once; the halves must be dropped before the last `Arc` to `self`.
    pub(super) unsafe fn split(&self) -> (Producer<'static, T>, Consumer<'static, T>) {
        // SAFETY: the block is valid and initialised (see `allocate`); this is the only
        // `&mut` ever made to it, and it is not used after `split` returns.
        let queue: &'static mut Queue<T, N> = unsafe { &mut *self.ptr.as_ptr() };
        queue.split()
    }
}

impl<T, const N: usize> Drop for QueueStorage<T, N> {
    fn drop(&mut self) {
        // SAFETY: allocated in `allocate` with the layout of `Queue<T, N>`; both halves have been
        // dropped (they are declared before the `Arc` that owns `self`), so no reference remains.
        drop(unsafe { Box::from_raw(self.ptr.as_ptr()) });
    }
}

/// Flags shared by the producer, the writer and the handle.
#[derive(Debug, Default)]
pub(super) struct Control {
    /// Set by the producer around its enqueue (see `RecorderProducer::push`).
    pub(super) producer_busy: AtomicBool,
    /// Set by the writer before its final drain: the producer refuses records from then on.
    pub(super) closed: AtomicBool,
    /// Set by the handle to stop the writer.
    pub(super) shutdown: AtomicBool,
    /// Set by the handle to pause the writer.
    pub(super) pause_requested: AtomicBool,
    /// Set by the writer while paused.
    pub(super) paused: AtomicBool,
}

/// The real-time side of the recorder: owned by the 1 kHz thread.
pub struct RecorderProducer<T: 'static> {
    // Field order matters: the queue half must drop before `_storage`.
    pub(super) queue: Producer<'static, T>,
    pub(super) control: Arc<Control>,
    pub(super) stats: Arc<RecorderStats>,
    pub(super) capacity: usize,
    pub(super) _storage: Arc<dyn Send + Sync>,
}

impl<T: Copy + Send + 'static> RecorderProducer<T> {
    /// Queues one record for the writer.
    ///
    /// **Real-time (1 kHz loop):** called once a cycle; a few atomic operations and a copy,
    /// never blocks, allocates or does I/O.
    ///
    /// Returns false when the record was refused: the queue is full (counted in
    /// `dropped_queue_full`) or the recorder has shut down (counted in `dropped_closed`).
    #[inline]
    pub fn push(&mut self, rec: T) -> bool {
        // Dekker-style hand-shake with the writer's shutdown (both sides SeqCst): either this push
        // sees `closed` and refuses, or the writer sees `producer_busy` and waits for the enqueue to
        // finish before its final drain. No record is accepted and then left unwritten.
        self.control.producer_busy.store(true, Ordering::SeqCst);
        if self.control.closed.load(Ordering::SeqCst) {
            self.control.producer_busy.store(false, Ordering::Release);
            add(&self.stats.dropped_closed, 1);
            return false;
        }
        let accepted = self.queue.enqueue(rec).is_ok();
        if accepted {
            add(&self.stats.pushed, 1);
        } else {
            add(&self.stats.dropped_queue_full, 1);
        }
        self.control.producer_busy.store(false, Ordering::Release);
        accepted
    }

    /// Records the queue can hold (its const-generic size minus one).
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// The recorder's counters.
    pub fn stats(&self) -> &Arc<RecorderStats> {
        &self.stats
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn queue_layout_is_two_counters_and_the_buffer() {
        // `QueueStorage::allocate` relies on heapless 0.9's queue being exactly head, tail and
        // the slot array (all valid when zeroed): a new field would change the size.
        fn expected<T, const N: usize>() -> usize {
            let align = std::mem::align_of::<Queue<T, N>>();
            (2 * std::mem::size_of::<usize>() + N * std::mem::size_of::<T>()).next_multiple_of(align)
        }
        assert_eq!(std::mem::size_of::<Queue<u8, 5>>(), expected::<u8, 5>());
        assert_eq!(std::mem::size_of::<Queue<u64, 4096>>(), expected::<u64, 4096>());
        assert_eq!(std::mem::size_of::<Queue<[f64; 7], 64>>(), expected::<[f64; 7], 64>());
        assert_eq!(std::mem::size_of::<Queue<u128, 8>>(), expected::<u128, 8>());
    }

    #[test]
    fn zeroed_queue_behaves_like_a_new_one() {
        // The allocation trick of `QueueStorage`: an all-zero queue must be empty, hold N-1
        // items and wrap around correctly.
        let storage = Arc::new(QueueStorage::<u32, 4>::allocate().unwrap());
        // SAFETY: split once; both halves drop at the end of the test, before `storage`.
        let (mut p, mut c) = unsafe { storage.split() };
        assert_eq!(c.capacity(), 3);
        assert!(c.dequeue().is_none());
        for round in 0..10u32 {
            for i in 0..3 {
                assert!(p.enqueue(round * 10 + i).is_ok());
            }
            assert!(p.enqueue(99).is_err(), "a full queue refuses");
            for i in 0..3 {
                assert_eq!(c.dequeue(), Some(round * 10 + i));
            }
        }
    }
}
