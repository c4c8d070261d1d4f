//! A counting global allocator: the evidence behind "no allocation per cycle".
//!
//! A binary (test or benchmark) installs it with
//! `#[global_allocator] static GLOBAL: CountingAlloc = CountingAlloc;` and wraps the code under
//! test in [`counted`]; only allocations made by that thread inside [`counted`] are counted,
//! so the simulator, the bus and the harness around the measured calls do not disturb it.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicU64, Ordering};

/// Forwards to the system allocator and counts allocations made inside [`counted`].
pub struct CountingAlloc;

static ALLOCS: AtomicU64 = AtomicU64::new(0);
thread_local! {
    static COUNTING: Cell<bool> = const { Cell::new(false) };
    static MINE: Cell<u64> = const { Cell::new(0) };
}

fn count() {
    if COUNTING.with(|c| c.get()) {
        ALLOCS.fetch_add(1, Ordering::Relaxed);
        MINE.with(|m| m.set(m.get() + 1));
    }
}

// SAFETY: forwards every call to the system allocator unchanged; only counts.
unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        count();
        // SAFETY: same contract as the caller's.
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: same contract as the caller's.
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        count();
        // SAFETY: same contract as the caller's.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

/// Runs `f`, counting the allocations this thread makes meanwhile.
pub fn counted<T>(f: impl FnOnce() -> T) -> T {
    COUNTING.with(|c| c.set(true));
    let r = f();
    COUNTING.with(|c| c.set(false));
    r
}

/// Turns counting on or off for this thread (for code that cannot be wrapped in [`counted`]).
pub fn set_counting(on: bool) {
    COUNTING.with(|c| c.set(on));
}

/// Allocations counted so far (all threads' [`counted`] sections).
pub fn allocations() -> u64 {
    ALLOCS.load(Ordering::Relaxed)
}

/// Allocations counted so far on this thread (its [`counted`] sections): independent of
/// other tests of the same binary running on their own threads.
pub fn thread_allocations() -> u64 {
    MINE.with(|m| m.get())
}

/// Resets the count to zero.
pub fn reset() {
    ALLOCS.store(0, Ordering::Relaxed);
}
