//! Order-preserving maps over independent items (observations, candidates), on rayon's pool
//! with the `parallel` feature and in turn without it.
//!
//! Only the maps run in parallel: every sum over their results is taken afterwards by the
//! caller, in item order, so a solve's results are bit for bit those of the serial build,
//! whatever the thread count (rayon's global pool: one thread per core unless
//! `RAYON_NUM_THREADS` says otherwise, or the pool the caller runs in).

use std::vec::Vec;

/// Fewest items a parallel task takes (per-observation work is a few microseconds: smaller
/// tasks would cost more in scheduling than they save).
#[cfg(feature = "parallel")]
const MIN_ITEMS_PER_TASK: usize = 32;

/// `out` cleared and filled with `f` of each item, in order (its allocation reused).
#[cfg(feature = "parallel")]
pub(crate) fn map_into<T: Sync, U: Send>(items: &[T], out: &mut Vec<U>, f: impl Fn(&T) -> U + Sync + Send) {
    use rayon::prelude::*;
    items.par_iter().with_min_len(MIN_ITEMS_PER_TASK).map(f).collect_into_vec(out);
}

/// `out` cleared and filled with `f` of each item, in order (its allocation reused).
#[cfg(not(feature = "parallel"))]
pub(crate) fn map_into<T: Sync, U: Send>(items: &[T], out: &mut Vec<U>, f: impl Fn(&T) -> U + Sync + Send) {
    out.clear();
    out.extend(items.iter().map(f));
}

/// `f(i, &mut out[i])` for every slot of `out` (written in place: no result moved).
#[cfg(feature = "parallel")]
pub(crate) fn for_each_mut<U: Send>(out: &mut [U], f: impl Fn(usize, &mut U) + Sync + Send) {
    use rayon::prelude::*;
    out.par_iter_mut().with_min_len(MIN_ITEMS_PER_TASK).enumerate().for_each(|(i, x)| f(i, x));
}

/// `f(i, &mut out[i])` for every slot of `out` (written in place: no result moved).
#[cfg(not(feature = "parallel"))]
pub(crate) fn for_each_mut<U: Send>(out: &mut [U], f: impl Fn(usize, &mut U) + Sync + Send) {
    for (i, x) in out.iter_mut().enumerate() {
        f(i, x);
    }
}

/// `f()` run on one of the pool's threads, so that the maps inside it are split between the
/// pool's threads without a hand-over from an outside thread at each map (which costs a
/// sleep and a wake-up per map, thousands per solve); in place when already on one.
#[cfg(feature = "parallel")]
pub(crate) fn in_pool<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    rayon::scope(|_| f())
}

/// `f()` (in turn: no pool without the `parallel` feature).
#[cfg(not(feature = "parallel"))]
pub(crate) fn in_pool<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    f()
}

/// `f` of each item, in order.
pub(crate) fn map<T: Sync, U: Send>(items: &[T], f: impl Fn(&T) -> U + Sync + Send) -> Vec<U> {
    let mut out = Vec::with_capacity(items.len());
    map_into(items, &mut out, f);
    out
}

/// `f` of each item, in order, one task per item: for few items of much work each (the
/// candidates refined from the standing turns). The items are handed out interleaved (even
/// indices first, then odd), so that rayon's halving split gives each of two threads every
/// other item rather than a contiguous half: neighbouring turns tend to cost alike (on the
/// bench scene the first two run to the iteration cap, the last two converge in a quarter of
/// that).
#[cfg(feature = "parallel")]
pub(crate) fn map_each<T: Sync, U: Send>(items: &[T], f: impl Fn(&T) -> U + Sync + Send) -> Vec<U> {
    use rayon::prelude::*;
    let n = items.len();
    let order: Vec<usize> = (0..n).step_by(2).chain((1..n).step_by(2)).collect();
    let mut out: Vec<(usize, U)> = order.par_iter().with_max_len(1).map(|&i| (i, f(&items[i]))).collect();
    out.sort_by_key(|(i, _)| *i);
    out.into_iter().map(|(_, u)| u).collect()
}

/// `f` of each item, in order, one task per item: for few items of much work each (the
/// candidates refined from the standing turns).
#[cfg(not(feature = "parallel"))]
pub(crate) fn map_each<T: Sync, U: Send>(items: &[T], f: impl Fn(&T) -> U + Sync + Send) -> Vec<U> {
    items.iter().map(f).collect()
}

#[cfg(test)]
mod tests {
    use super::{for_each_mut, in_pool, map, map_each, map_into};
    use std::vec::Vec;

    /// Results come back in item order (with or without the `parallel` feature).
    #[test]
    fn maps_keep_item_order() {
        let items: Vec<u64> = (0..1000).collect();
        let squares: Vec<u64> = items.iter().map(|x| x * x).collect();
        assert_eq!(map(&items, |x| x * x), squares);
        assert_eq!(map_each(&items[..7], |x| x * x), squares[..7]);
        let mut out = vec![5u64; 3];
        map_into(&items, &mut out, |x| x * x);
        assert_eq!(out, squares);
        let mut slots = vec![0u64; 1000];
        in_pool(|| for_each_mut(&mut slots, |i, x| *x = items[i] * items[i]));
        assert_eq!(slots, squares);
    }
}
