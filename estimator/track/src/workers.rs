//! The tracker's worker threads: a fixed set of threads started once, to which each parallel
//! loop over the particles is handed without allocating (issue 18: "0 allocations per frame
//! after start-up", docs/tracking.md "Threads without a job queue").
//!
//! Why not rayon: each parallel loop rayon starts from a thread outside its pool pushes a job
//! onto its shared injector queue, which allocates a new block every few dozen jobs (about one
//! allocation every six frames of the tracker); inside its pool the work-stealing deques grow
//! with the load. Here nothing is queued:
//! - the caller publishes one job, a borrowed `&dyn Fn()`, under a [`Mutex`] and wakes the
//!   workers with a [`Condvar`] (on Linux both are a futex word: locking, waiting and waking
//!   never allocate);
//! - every thread, the caller included, claims fixed-size chunks of the index range from one
//!   [`AtomicUsize`] until none is left (a descheduled worker delays the loop by one chunk at
//!   most; a worker that wakes after the last chunk was claimed does nothing);
//! - the caller then withdraws the job and waits until every worker that took it has finished,
//!   so the borrow never outlives the call (also when a chunk panics: the panic is carried to
//!   the caller once every worker has let go).
//!
//! Each index is handled exactly once, by one thread, with the same arguments whatever the
//! thread count or the chunk order: results that depend only on the index (the tracker's noise
//! is seeded per particle) are bit-identical for any number of threads.

use std::ops::Range;
use std::panic::{AssertUnwindSafe, catch_unwind, resume_unwind};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::thread::JoinHandle;

/// Chunks per thread of one loop (smaller chunks balance a descheduled thread better; each
/// claim is one atomic add).
const CHUNKS_PER_THREAD: usize = 8;

/// A published job: a borrowed closure whose lifetime was erased (see [`Workers::run`]).
#[derive(Clone, Copy)]
struct Job(*const (dyn Fn() + Sync + 'static));

// SAFETY: the pointee is `Sync` (so calling it from another thread through a shared reference is
// sound) and `Workers::run` keeps it alive for as long as any worker can reach the pointer: it
// withdraws the job and waits for every worker that took it before returning.
unsafe impl Send for Job {}

struct State {
    /// Incremented at each published job; a worker runs each generation at most once.
    generation: u64,
    /// The current job; `None` once the caller has withdrawn it.
    job: Option<Job>,
    /// Workers running the current job.
    active: usize,
    /// Set by `Drop`.
    shutdown: bool,
}

struct Shared {
    state: Mutex<State>,
    /// Workers wait here for a new generation (or the shutdown).
    start: Condvar,
    /// The caller waits here for `active == 0`.
    done: Condvar,
    /// A worker's chunk panicked during the current job.
    panicked: AtomicBool,
}

impl Shared {
    fn lock(&self) -> MutexGuard<'_, State> {
        // No code panics while holding the lock (jobs run unlocked), so a poisoned lock still
        // holds a consistent state.
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// The worker threads of one tracker: `threads − 1` threads started by [`Workers::new`], plus
/// the calling thread, which takes part in every loop. Dropping it stops and joins them.
pub struct Workers {
    /// `None`: no worker thread ([`Workers::serial`], or one thread asked for).
    shared: Option<Arc<Shared>>,
    handles: Vec<JoinHandle<()>>,
}

impl std::fmt::Debug for Workers {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Workers").field("threads", &self.threads()).finish()
    }
}

/// The machine's processors available to this process (its CPU affinity and cgroup quota
/// respected, `std::thread::available_parallelism`); 1 when unknown.
pub fn available_threads() -> usize {
    std::thread::available_parallelism().map_or(1, usize::from)
}

impl Workers {
    /// No worker thread: every loop runs on the caller (no allocation, nothing started).
    pub const fn serial() -> Self {
        Self { shared: None, handles: Vec::new() }
    }

    /// Starts `threads − 1` worker threads (`threads` counts the caller; 0: the machine's
    /// processors, [`available_threads`]) named `track-1`, `track-2`, …. They are created by the
    /// calling thread and so inherit its scheduling priority (nice value). A thread that cannot
    /// be started is left out (fewer threads, same results); with one thread every loop runs
    /// on the caller alone.
    pub fn new(threads: usize) -> Self {
        let threads = if threads == 0 { available_threads() } else { threads };
        if threads <= 1 {
            return Self::serial();
        }
        let shared = Arc::new(Shared {
            state: Mutex::new(State { generation: 0, job: None, active: 0, shutdown: false }),
            start: Condvar::new(),
            done: Condvar::new(),
            panicked: AtomicBool::new(false),
        });
        let mut handles = Vec::with_capacity(threads.saturating_sub(1));
        for i in 1..threads {
            let s = Arc::clone(&shared);
            match std::thread::Builder::new().name(format!("track-{i}")).spawn(move || worker(&s)) {
                Ok(h) => handles.push(h),
                Err(_) => break,
            }
        }
        Self { shared: Some(shared), handles }
    }

    /// Threads taking part in a loop, the caller included (≥ 1).
    pub fn threads(&self) -> usize {
        self.handles.len() + 1
    }

    /// Calls `f` on every chunk of `0..len` (disjoint ranges covering it, each exactly once)
    /// from the caller and the workers; returns when all are done. Allocation-free. A panic in
    /// `f` is resumed here, after every thread has stopped using `f`.
    pub fn for_each_range<F: Fn(Range<usize>) + Sync>(&self, len: usize, f: F) {
        if len == 0 {
            return;
        }
        let chunk = len.div_ceil(self.threads() * CHUNKS_PER_THREAD).max(1);
        let next = AtomicUsize::new(0);
        let body = || {
            loop {
                let start = next.fetch_add(chunk, Ordering::Relaxed);
                if start >= len {
                    break;
                }
                f(start..(start + chunk).min(len));
            }
        };
        if self.handles.is_empty() || len <= chunk {
            body();
        } else {
            self.run(&body);
        }
    }

    /// Calls `f(i, &mut a[i])` for every index of `a`, in parallel (see
    /// [`Workers::for_each_range`]).
    pub fn for_each_mut<A: Send, F: Fn(usize, &mut A) + Sync>(&self, a: &mut [A], f: F) {
        let pa = RawSlice::new(a);
        self.for_each_range(pa.len, |r| {
            // SAFETY: the ranges handed out by `for_each_range` are disjoint and within
            // `0..a.len()`, and `a` is borrowed mutably for the whole call.
            let sa = unsafe { pa.range(r.clone()) };
            for (k, x) in sa.iter_mut().enumerate() {
                f(r.start + k, x);
            }
        });
    }

    /// Calls `f(i, &mut a[i], &mut b[i])` for every index `i < min(a.len(), b.len())`, in
    /// parallel (see [`Workers::for_each_range`]).
    pub fn for_each_mut2<A: Send, B: Send, F: Fn(usize, &mut A, &mut B) + Sync>(&self, a: &mut [A], b: &mut [B], f: F) {
        let n = a.len().min(b.len());
        let (pa, pb) = (RawSlice::new(&mut a[..n]), RawSlice::new(&mut b[..n]));
        self.for_each_range(n, |r| {
            // SAFETY: as in `for_each_mut`, for each of the two slices (both of length `n`).
            let (sa, sb) = unsafe { (pa.range(r.clone()), pb.range(r.clone())) };
            for (k, (x, y)) in sa.iter_mut().zip(sb).enumerate() {
                f(r.start + k, x, y);
            }
        });
    }

    /// Calls `f(i, &mut a[i], &mut b[i], &mut c[i])` for every index `i` of the shortest slice,
    /// in parallel (see [`Workers::for_each_range`]).
    pub fn for_each_mut3<A: Send, B: Send, C: Send, F: Fn(usize, &mut A, &mut B, &mut C) + Sync>(
        &self,
        a: &mut [A],
        b: &mut [B],
        c: &mut [C],
        f: F,
    ) {
        let n = a.len().min(b.len()).min(c.len());
        let (pa, pb, pc) = (RawSlice::new(&mut a[..n]), RawSlice::new(&mut b[..n]), RawSlice::new(&mut c[..n]));
        self.for_each_range(n, |r| {
            // SAFETY: as in `for_each_mut`, for each of the three slices (all of length `n`).
            let (sa, sb, sc) = unsafe { (pa.range(r.clone()), pb.range(r.clone()), pc.range(r.clone())) };
            for (k, ((x, y), z)) in sa.iter_mut().zip(sb).zip(sc).enumerate() {
                f(r.start + k, x, y, z);
            }
        });
    }

    /// Runs `body` on the caller and on every worker that wakes while the job is published;
    /// returns once no worker runs it any more.
    fn run(&self, body: &(dyn Fn() + Sync)) {
        let Some(sh) = self.shared.as_deref() else {
            body();
            return;
        };
        // SAFETY: only the lifetime is erased (same fat-pointer layout). The pointer is
        // published below and withdrawn before this function returns, after which no worker
        // can reach it; every worker that copied it has decremented `active` after its last
        // use, and this function waits for `active == 0` before returning (unwinding included:
        // the caller's own part runs under `catch_unwind`).
        let job = Job(unsafe {
            std::mem::transmute::<*const (dyn Fn() + Sync + '_), *const (dyn Fn() + Sync + 'static)>(body)
        });
        sh.panicked.store(false, Ordering::Relaxed);
        {
            let mut st = sh.lock();
            st.generation = st.generation.wrapping_add(1);
            st.job = Some(job);
        }
        sh.start.notify_all();
        let mine = catch_unwind(AssertUnwindSafe(body));
        {
            let mut st = sh.lock();
            st.job = None;
            while st.active > 0 {
                st = sh.done.wait(st).unwrap_or_else(PoisonError::into_inner);
            }
        }
        if let Err(p) = mine {
            resume_unwind(p);
        }
        if sh.panicked.load(Ordering::Acquire) {
            panic!("a tracker worker thread panicked in a parallel loop");
        }
    }
}

impl Drop for Workers {
    fn drop(&mut self) {
        let Some(sh) = self.shared.as_deref() else { return };
        sh.lock().shutdown = true;
        sh.start.notify_all();
        for h in self.handles.drain(..) {
            // A worker never panics outside `catch_unwind`; nothing to report.
            let _ = h.join();
        }
    }
}

fn worker(sh: &Shared) {
    let mut seen = 0u64;
    let mut st = sh.lock();
    loop {
        if st.shutdown {
            return;
        }
        if st.generation != seen {
            seen = st.generation;
            if let Some(job) = st.job {
                st.active += 1;
                drop(st);
                // SAFETY: the job was published and not yet withdrawn when it was copied under
                // the lock, and `active` (incremented under that same lock) keeps the caller
                // from returning, so the closure it points to is alive until the decrement
                // below.
                let f = unsafe { &*job.0 };
                if catch_unwind(AssertUnwindSafe(f)).is_err() {
                    sh.panicked.store(true, Ordering::Release);
                }
                st = sh.lock();
                st.active -= 1;
                if st.active == 0 {
                    sh.done.notify_all();
                }
            }
            continue;
        }
        st = sh.start.wait(st).unwrap_or_else(PoisonError::into_inner);
    }
}

/// A mutable slice (borrowed for `'a`) shared between threads, each of which takes disjoint
/// ranges of it.
struct RawSlice<'a, T> {
    ptr: *mut T,
    len: usize,
    _borrow: std::marker::PhantomData<&'a mut [T]>,
}

impl<T> Clone for RawSlice<'_, T> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<T> Copy for RawSlice<'_, T> {}

// SAFETY: a `RawSlice` only hands out disjoint `&mut [T]` ranges (the callers' contract), each
// used by one thread, which is what `&mut [T]: Send` needs: `T: Send`.
unsafe impl<T: Send> Sync for RawSlice<'_, T> {}

impl<'a, T> RawSlice<'a, T> {
    fn new(s: &'a mut [T]) -> Self {
        Self { ptr: s.as_mut_ptr(), len: s.len(), _borrow: std::marker::PhantomData }
    }

    /// # Safety
    /// `r` lies within `0..len`, and no other range overlapping `r` is in use at the same time
    /// (the slice stays borrowed for `'a`).
    unsafe fn range(self, r: Range<usize>) -> &'a mut [T] {
        debug_assert!(r.start <= r.end && r.end <= self.len);
        // SAFETY: the caller's contract (within bounds of a live, exclusively borrowed slice;
        // no overlapping range in use).
        unsafe { std::slice::from_raw_parts_mut(self.ptr.add(r.start), r.end - r.start) }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, reason = "test code")]
    use super::*;

    #[test]
    fn every_index_once_for_any_thread_count() {
        for threads in [1, 2, 3, 7] {
            let w = Workers::new(threads);
            assert_eq!(w.threads(), threads);
            assert_eq!(w.shared.is_some(), threads > 1);
            for len in [0, 1, 2, 5, 63, 64, 65, 1000] {
                let mut v = vec![0u32; len];
                let mut idx = vec![usize::MAX; len];
                for _ in 0..3 {
                    w.for_each_mut2(&mut v, &mut idx, |i, x, j| {
                        *x += 1;
                        *j = i;
                    });
                }
                assert!(v.iter().all(|&x| x == 3), "{threads} threads, {len}: {v:?}");
                assert!(idx.iter().enumerate().all(|(i, &j)| i == j));
            }
        }
    }

    #[test]
    fn results_do_not_depend_on_the_thread_count() {
        let f = |i: usize, x: &mut u64, y: &mut f64, z: &mut u8| {
            *x = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
            *y = (i as f64).sqrt();
            *z = (i % 251) as u8;
        };
        let run = |threads| {
            let w = Workers::new(threads);
            let (mut a, mut b, mut c) = (vec![0u64; 777], vec![0.0; 777], vec![0u8; 777]);
            w.for_each_mut3(&mut a, &mut b, &mut c, f);
            (a, b, c)
        };
        assert_eq!(run(1), run(4));
    }

    #[test]
    fn a_panic_reaches_the_caller_and_the_workers_keep_working() {
        let w = Workers::new(3);
        let mut v = vec![0u32; 100];
        let r = catch_unwind(AssertUnwindSafe(|| {
            w.for_each_mut(&mut v, |i, _| assert!(i != 57, "index 57"));
        }));
        assert!(r.is_err());
        w.for_each_mut(&mut v, |i, x| *x = i as u32);
        assert!(v.iter().enumerate().all(|(i, &x)| x == i as u32));
    }
}
