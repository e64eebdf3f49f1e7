//! A global allocator that serves small allocations of real-time threads from a fixed pool.
//!
//! ## Why
//! iceoryx2 0.10 makes one heap allocation (and one free) of 48 bytes, alignment 8, per
//! published sample: `Publisher::loan_uninit`, `loan` and `send_copy` each wrap the loaned chunk
//! in an `Rc` (`ChunkMutSharedState`). There is no allocation-free publish path in that version.
//! At 1 kHz that is a `malloc`/`free` pair per cycle inside the control loop: glibc's allocator
//! can take a lock, `brk`/`mmap` and page-fault, which is unbounded latency for a real-time
//! thread. Everything else on the publish path ([`crate::ipc::FulcrumPublisher::publish`]:
//! the copy into shared memory, `send`, the event `notify`) allocates nothing.
//!
//! ## What
//! [`RtPoolAllocator`] wraps [`std::alloc::System`]. A thread that called [`enter_realtime`]
//! (until [`leave_realtime`]) gets every allocation of at most [`BLOCK_SIZE`] bytes with an
//! alignment of at most [`BLOCK_ALIGN`] bytes from a static pool of [`POOL_BLOCKS`] blocks
//! (16 KiB, in the binary's `.bss`, written once by [`prefault_pool`]). Allocation and release
//! are lock-free: one bit per block in atomic 64-bit words, claimed with `fetch_or` and released
//! with `fetch_and` (a bitmap has no ABA problem: a claim succeeds only if this very `fetch_or`
//! turned the bit from 0 to 1). A pointer inside the pool is returned to the pool whichever
//! thread frees it. Every other allocation, and every allocation of a thread that is not marked,
//! goes to `System` unchanged. When the pool is exhausted a marked thread falls back to `System`
//! and the fallback is counted.
//!
//! ```no_run
//! #[global_allocator]
//! static ALLOC: hw_io::rt_alloc::RtPoolAllocator = hw_io::rt_alloc::RtPoolAllocator::new();
//!
//! fn main() {
//!     // In the 1 kHz thread, after creating the publisher and a few warm-up cycles:
//!     hw_io::rt_alloc::prefault_pool();
//!     hw_io::rt_alloc::enter_realtime();
//!     // ... periodic loop; check hw_io::rt_alloc::stats().realtime_system_allocs == 0
//! }
//! ```
//!
//! The marker is a `const`-initialised thread-local `Cell<bool>` without destructor: reading it
//! from inside the allocator never allocates and never fails, also while a thread exits.
//!
//! Counters ([`stats`]) are process-wide atomics (relaxed ordering; for monitoring and tests);
//! [`thread_system_allocs`] counts the calling thread's `System` allocations, marked or not.
//! None of this counts anything unless [`RtPoolAllocator`] is the `#[global_allocator]`.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::{Cell, UnsafeCell};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

/// Size of one pool block, bytes. Allocations of a marked thread up to this size use the pool.
pub const BLOCK_SIZE: usize = 64;
/// Alignment of every pool block, bytes (one cache line). Allocations with a larger alignment
/// go to `System`.
pub const BLOCK_ALIGN: usize = 64;
/// Number of blocks in the pool.
pub const POOL_BLOCKS: usize = 256;

const WORDS: usize = POOL_BLOCKS / 64;
const _: () = assert!(POOL_BLOCKS.is_multiple_of(64));

thread_local! {
    static REALTIME: Cell<bool> = const { Cell::new(false) };
    static THREAD_SYSTEM_ALLOCS: Cell<u64> = const { Cell::new(0) };
}

/// Marks the calling thread real-time: from now on its small allocations come from the pool
/// (see the [module documentation](self)). Call it after the thread's set-up (port creation,
/// warm-up cycles), before its periodic loop. Allocates nothing.
pub fn enter_realtime() {
    let _ = REALTIME.try_with(|r| r.set(true));
}

/// Unmarks the calling thread: its allocations go to `System` again. Blocks it took from the
/// pool still return to the pool when freed.
pub fn leave_realtime() {
    let _ = REALTIME.try_with(|r| r.set(false));
}

/// True between [`enter_realtime`] and [`leave_realtime`] on the calling thread.
pub fn is_realtime() -> bool {
    REALTIME.try_with(Cell::get).unwrap_or(false)
}

/// Allocations (`alloc`, `alloc_zeroed`, `realloc`) the calling thread made through `System`
/// since it started, whether it is marked real-time or not. Always 0 unless [`RtPoolAllocator`]
/// is the global allocator.
pub fn thread_system_allocs() -> u64 {
    THREAD_SYSTEM_ALLOCS.try_with(Cell::get).unwrap_or(0)
}

/// Runs `f` and returns the system-allocator calls (alloc, alloc_zeroed, realloc) it made on
/// the calling thread, with its result. Needs [`RtPoolAllocator`] as the `#[global_allocator]`
/// (otherwise it always reports 0): the allocation tests of every crate use this one counter.
pub fn count_thread_allocs<T>(f: impl FnOnce() -> T) -> (u64, T) {
    let before = thread_system_allocs();
    let out = f();
    (thread_system_allocs().wrapping_sub(before), out)
}

/// A snapshot of the allocator's process-wide counters (see [`stats`]). Counts since the process
/// started; `pool_in_use` and `pool_high_water` are block counts.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RtAllocStats {
    /// Allocations (`alloc`, `alloc_zeroed`, `realloc`) made by real-time-marked threads that
    /// went to `System`: too large, too strongly aligned, or a pool fallback. Zero is the goal.
    pub realtime_system_allocs: u64,
    /// Frees of `System` memory made by real-time-marked threads.
    pub realtime_system_frees: u64,
    /// Allocations served by the pool.
    pub pool_allocs: u64,
    /// Blocks returned to the pool (by any thread).
    pub pool_frees: u64,
    /// Pool-eligible allocations of real-time-marked threads that found the pool exhausted and
    /// went to `System` (also counted in `realtime_system_allocs`).
    pub pool_fallbacks: u64,
    /// Pool blocks currently allocated.
    pub pool_in_use: usize,
    /// Largest `pool_in_use` seen.
    pub pool_high_water: usize,
}

/// The process-wide counters of [`RtPoolAllocator`].
pub fn stats() -> RtAllocStats {
    POOL.stats()
}

/// Writes to every page of the pool once, so that the first pool allocations of a real-time
/// thread do not page-fault. Optional (the pool is 16 KiB; `mlockall` does the same); call it
/// during set-up: while it runs (microseconds) pool allocations may fall back to `System`.
/// Allocates nothing.
pub fn prefault_pool() {
    POOL.prefault();
}

/// The global allocator: [`std::alloc::System`] plus the real-time pool (module documentation).
///
/// Use it as `#[global_allocator] static A: RtPoolAllocator = RtPoolAllocator::new();`. Every
/// instance shares the one static pool and the one set of counters.
#[derive(Debug, Default)]
pub struct RtPoolAllocator {
    _private: (),
}

impl RtPoolAllocator {
    /// The allocator (a `const fn`, for a `static`).
    pub const fn new() -> Self {
        Self { _private: () }
    }
}

fn fits_pool(layout: &Layout) -> bool {
    layout.size() <= BLOCK_SIZE && layout.align() <= BLOCK_ALIGN
}

fn count_system_alloc(realtime: bool) {
    let _ = THREAD_SYSTEM_ALLOCS.try_with(|c| c.set(c.get().wrapping_add(1)));
    if realtime {
        POOL.realtime_system_allocs.fetch_add(1, Ordering::Relaxed);
    }
}

// SAFETY: every pointer handed out is either from `System` with the caller's layout, or a pool
// block of BLOCK_SIZE bytes aligned to BLOCK_ALIGN, handed out only for layouts that fit it and
// owned exclusively until freed (one bit per block, claimed atomically). Pool pointers are
// recognised by address on free/realloc and never passed to `System`.
unsafe impl GlobalAlloc for RtPoolAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let realtime = is_realtime();
        if realtime && fits_pool(&layout) {
            if let Some(p) = POOL.alloc() {
                return p;
            }
            POOL.pool_fallbacks.fetch_add(1, Ordering::Relaxed);
        }
        count_system_alloc(realtime);
        // SAFETY: forwarded contract of `GlobalAlloc::alloc`.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let realtime = is_realtime();
        if realtime && fits_pool(&layout) {
            if let Some(p) = POOL.alloc() {
                // SAFETY: `p` is an exclusively owned block of BLOCK_SIZE >= layout.size() bytes.
                unsafe { p.write_bytes(0, layout.size()) };
                return p;
            }
            POOL.pool_fallbacks.fetch_add(1, Ordering::Relaxed);
        }
        count_system_alloc(realtime);
        // SAFETY: forwarded contract of `GlobalAlloc::alloc_zeroed`.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        if POOL.contains(ptr) {
            POOL.free(ptr);
            return;
        }
        if is_realtime() {
            POOL.realtime_system_frees.fetch_add(1, Ordering::Relaxed);
        }
        // SAFETY: not a pool pointer, hence allocated by `System` with this layout.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if POOL.contains(ptr) {
            if new_size <= BLOCK_SIZE {
                return ptr; // the block already holds BLOCK_SIZE bytes with this alignment
            }
            // SAFETY: the caller guarantees that `new_size` rounded up to `layout.align()` does
            // not overflow `isize` (contract of `GlobalAlloc::realloc`).
            let new_layout = unsafe { Layout::from_size_align_unchecked(new_size, layout.align()) };
            // SAFETY: new_size > BLOCK_SIZE > 0.
            let new = unsafe { self.alloc(new_layout) };
            if !new.is_null() {
                // SAFETY: both regions are valid for layout.size() bytes (< new_size) and distinct.
                unsafe { std::ptr::copy_nonoverlapping(ptr, new, layout.size()) };
                POOL.free(ptr);
            }
            return new;
        }
        count_system_alloc(is_realtime());
        // SAFETY: not a pool pointer, hence allocated by `System` with `layout`.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[repr(C, align(64))]
struct Storage(UnsafeCell<[[u8; BLOCK_SIZE]; POOL_BLOCKS]>);

const _: () = assert!(std::mem::align_of::<Storage>() == BLOCK_ALIGN);

/// The fixed block pool: storage, a bitmap of used blocks, counters.
struct Pool {
    storage: Storage,
    used: [AtomicU64; WORDS],
    in_use: AtomicUsize,
    high_water: AtomicUsize,
    pool_allocs: AtomicU64,
    pool_frees: AtomicU64,
    pool_fallbacks: AtomicU64,
    realtime_system_allocs: AtomicU64,
    realtime_system_frees: AtomicU64,
}

// SAFETY: the storage is only accessed through blocks whose exclusive ownership is arbitrated by
// the atomic bitmap; everything else is atomic.
unsafe impl Sync for Pool {}

static POOL: Pool = Pool::new();

impl Pool {
    const fn new() -> Self {
        Self {
            storage: Storage(UnsafeCell::new([[0; BLOCK_SIZE]; POOL_BLOCKS])),
            used: [const { AtomicU64::new(0) }; WORDS],
            in_use: AtomicUsize::new(0),
            high_water: AtomicUsize::new(0),
            pool_allocs: AtomicU64::new(0),
            pool_frees: AtomicU64::new(0),
            pool_fallbacks: AtomicU64::new(0),
            realtime_system_allocs: AtomicU64::new(0),
            realtime_system_frees: AtomicU64::new(0),
        }
    }

    fn base(&self) -> *mut u8 {
        self.storage.0.get().cast()
    }

    fn contains(&self, p: *mut u8) -> bool {
        let base = self.base() as usize;
        let addr = p as usize;
        addr >= base && addr < base + BLOCK_SIZE * POOL_BLOCKS
    }

    /// Claims a free block; `None` when all are in use. Lock-free.
    fn alloc(&self) -> Option<*mut u8> {
        for (w, word) in self.used.iter().enumerate() {
            let mut seen = word.load(Ordering::Relaxed);
            while seen != u64::MAX {
                let bit = (!seen).trailing_zeros() as usize;
                let mask = 1u64 << bit;
                // Acquire: the previous owner's writes to the block (before its Release free)
                // happen before ours.
                let before = word.fetch_or(mask, Ordering::Acquire);
                if before & mask == 0 {
                    let n = self.in_use.fetch_add(1, Ordering::Relaxed) + 1;
                    self.high_water.fetch_max(n, Ordering::Relaxed);
                    self.pool_allocs.fetch_add(1, Ordering::Relaxed);
                    // SAFETY: w * 64 + bit < POOL_BLOCKS, so the offset stays inside the storage.
                    return Some(unsafe { self.base().add((w * 64 + bit) * BLOCK_SIZE) });
                }
                seen = before | mask;
            }
        }
        None
    }

    /// Returns the block at `p` (which must be inside the pool) to the pool.
    fn free(&self, p: *mut u8) {
        let index = (p as usize - self.base() as usize) / BLOCK_SIZE;
        let mask = 1u64 << (index % 64);
        // Release: our writes to the block happen before the next owner's Acquire claim.
        let before = self.used[index / 64].fetch_and(!mask, Ordering::Release);
        // A double free (undefined behaviour of the caller) must not corrupt the counters; an
        // allocator must not panic either.
        if before & mask != 0 {
            self.in_use.fetch_sub(1, Ordering::Relaxed);
            self.pool_frees.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Writes one byte of every free block, so that each page of the pool is backed by memory
    /// of its own (a page of `.bss` that was only read maps the shared zero page, and the first
    /// write would fault). The free blocks of a word are claimed for the duration (allocations
    /// meanwhile look elsewhere or fall back), so no block owned by another thread is touched.
    fn prefault(&self) {
        for (w, word) in self.used.iter().enumerate() {
            let before = word.fetch_or(u64::MAX, Ordering::Acquire);
            let claimed = !before;
            for bit in 0..64 {
                if claimed & (1u64 << bit) != 0 {
                    // SAFETY: in bounds (w * 64 + bit < POOL_BLOCKS), and the block is ours
                    // until the release below.
                    unsafe { std::ptr::write_volatile(self.base().add((w * 64 + bit) * BLOCK_SIZE), 0) };
                }
            }
            word.fetch_and(!claimed, Ordering::Release);
        }
    }

    fn stats(&self) -> RtAllocStats {
        RtAllocStats {
            realtime_system_allocs: self.realtime_system_allocs.load(Ordering::Relaxed),
            realtime_system_frees: self.realtime_system_frees.load(Ordering::Relaxed),
            pool_allocs: self.pool_allocs.load(Ordering::Relaxed),
            pool_frees: self.pool_frees.load(Ordering::Relaxed),
            pool_fallbacks: self.pool_fallbacks.load(Ordering::Relaxed),
            pool_in_use: self.in_use.load(Ordering::Relaxed),
            pool_high_water: self.high_water.load(Ordering::Relaxed),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashSet;

    fn layout(size: usize, align: usize) -> Layout {
        Layout::from_size_align(size, align).unwrap()
    }

    #[test]
    fn pool_blocks_are_distinct_aligned_and_exhaust_at_capacity() {
        let pool = Box::new(Pool::new());
        let mut got = HashSet::new();
        for _ in 0..POOL_BLOCKS {
            let p = pool.alloc().expect("pool has room");
            assert_eq!(p as usize % BLOCK_ALIGN, 0);
            assert!(pool.contains(p));
            assert!(got.insert(p as usize), "block handed out twice");
        }
        assert_eq!(pool.alloc(), None, "pool must be exhausted after POOL_BLOCKS claims");
        let s = pool.stats();
        assert_eq!((s.pool_in_use, s.pool_high_water, s.pool_allocs), (POOL_BLOCKS, POOL_BLOCKS, POOL_BLOCKS as u64));
        let one = *got.iter().next().unwrap() as *mut u8;
        pool.free(one);
        assert_eq!(pool.alloc(), Some(one), "a freed block is reusable");
        for p in got {
            pool.free(p as *mut u8);
        }
        assert_eq!(pool.stats().pool_in_use, 0);
        assert!(!pool.contains(std::ptr::null_mut()));
    }

    #[test]
    fn prefault_leaves_owned_blocks_and_the_bitmap_as_they_were() {
        let pool = Box::new(Pool::new());
        let owned: Vec<*mut u8> = (0..3).map(|_| pool.alloc().unwrap()).collect();
        for &p in &owned {
            // SAFETY: exclusively owned blocks.
            unsafe { p.write_bytes(0xAB, BLOCK_SIZE) };
        }
        pool.prefault();
        for &p in &owned {
            // SAFETY: still owned.
            let block = unsafe { std::slice::from_raw_parts(p, BLOCK_SIZE) };
            assert!(block.iter().all(|&b| b == 0xAB), "prefault wrote into an owned block");
        }
        assert_eq!(pool.stats().pool_in_use, 3);
        let rest: Vec<*mut u8> = std::iter::from_fn(|| pool.alloc()).collect();
        assert_eq!(rest.len(), POOL_BLOCKS - 3, "prefault released every block it claimed");
        assert!(rest.iter().all(|p| !owned.contains(p)));
    }

    #[test]
    fn concurrent_alloc_free_from_two_threads_never_shares_a_block() {
        let pool: &'static Pool = Box::leak(Box::new(Pool::new()));
        let worker = |tag: u8| {
            move || {
                let mut held = Vec::with_capacity(64);
                for round in 0..20_000usize {
                    let p = pool.alloc().expect("two threads hold at most 2 * 64 blocks");
                    // SAFETY: an exclusively owned block of BLOCK_SIZE bytes.
                    unsafe { p.write_bytes(tag, BLOCK_SIZE) };
                    held.push(p as usize);
                    if held.len() == 64 || round % 7 == 0 {
                        for q in held.drain(..) {
                            let q = q as *mut u8;
                            // SAFETY: still exclusively owned: any sharing would show another tag.
                            let block = unsafe { std::slice::from_raw_parts(q, BLOCK_SIZE) };
                            assert!(block.iter().all(|&b| b == tag), "block shared between threads");
                            pool.free(q);
                        }
                    }
                }
                for q in held {
                    pool.free(q as *mut u8);
                }
            }
        };
        let a = std::thread::spawn(worker(0xA5));
        let b = std::thread::spawn(worker(0x5A));
        a.join().unwrap();
        b.join().unwrap();
        let s = pool.stats();
        assert_eq!(s.pool_in_use, 0);
        assert_eq!(s.pool_allocs, 40_000);
        assert_eq!(s.pool_frees, 40_000);
        assert!(s.pool_high_water <= 128);
    }

    // The only test touching the process-wide POOL (the unit-test binary's global allocator is
    // `System`, so nothing else uses it).
    #[test]
    fn allocator_serves_marked_threads_from_the_pool_and_falls_back_when_exhausted() {
        std::thread::spawn(|| {
            let a = RtPoolAllocator::new();
            let small = layout(48, 8);
            // Unmarked: System, even for small layouts.
            assert!(!is_realtime());
            // SAFETY: valid non-zero layouts; every pointer is freed with its layout.
            unsafe {
                let p = a.alloc(small);
                assert!(!POOL.contains(p));
                a.dealloc(p, small);

                // (Vec and friends of this test use the test binary's global allocator, System.)
                let mut held: Vec<*mut u8> = Vec::with_capacity(POOL_BLOCKS);
                let before = stats();
                enter_realtime();
                assert!(is_realtime());
                for _ in 0..POOL_BLOCKS {
                    let p = a.alloc(small);
                    assert!(POOL.contains(p) && (p as usize).is_multiple_of(8));
                    held.push(p);
                }
                let mid = stats();
                assert_eq!(mid.pool_allocs - before.pool_allocs, POOL_BLOCKS as u64);
                assert_eq!(mid.realtime_system_allocs, before.realtime_system_allocs);
                // Exhausted: falls back to System and counts it.
                let p = a.alloc(small);
                assert!(!p.is_null() && !POOL.contains(p));
                let after = stats();
                assert_eq!(after.pool_fallbacks - mid.pool_fallbacks, 1);
                assert_eq!(after.realtime_system_allocs - mid.realtime_system_allocs, 1);
                a.dealloc(p, small);
                // Too large or too aligned: System even with room in the pool.
                a.dealloc(held.pop().unwrap(), small);
                let big = layout(BLOCK_SIZE + 1, 8);
                let q = a.alloc(big);
                assert!(!POOL.contains(q));
                a.dealloc(q, big);
                let aligned = layout(16, 128);
                let q = a.alloc(aligned);
                assert!(!POOL.contains(q) && (q as usize).is_multiple_of(128));
                a.dealloc(q, aligned);
                // Zeroed allocations from the pool are zeroed.
                let z = a.alloc_zeroed(layout(BLOCK_SIZE, 64));
                assert!(POOL.contains(z));
                assert!(std::slice::from_raw_parts(z, BLOCK_SIZE).iter().all(|&b| b == 0));
                // Growing a pool block moves it to System and keeps the content.
                z.write_bytes(7, BLOCK_SIZE);
                let g = a.realloc(z, layout(BLOCK_SIZE, 64), 4 * BLOCK_SIZE);
                assert!(!POOL.contains(g));
                assert!(std::slice::from_raw_parts(g, BLOCK_SIZE).iter().all(|&b| b == 7));
                a.dealloc(g, layout(4 * BLOCK_SIZE, 64));
                leave_realtime();
                // Blocks return to the pool from an unmarked thread too.
                for p in held.drain(..) {
                    a.dealloc(p, small);
                }
                assert_eq!(stats().pool_in_use, before.pool_in_use);
            }
        })
        .join()
        .unwrap();
    }
}
