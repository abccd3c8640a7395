//! The allocator of the fuzz binary: the system allocator, counting the bytes live now and the
//! most live at once, and refusing any allocation that would bring the live bytes past
//! [`HARD_LIMIT`] (the process then aborts with "memory allocation of N bytes failed": a reader
//! that sizes an allocation from a file's claims fails loudly and at once, instead of driving the
//! machine into swap or being killed without a word).

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

/// The most bytes live at once that an allocation may bring about: 3 GiB, several times
/// [`crate::engine::PEAK_LIVE_LIMIT`], so a breach of that bound is measured and reported
/// before this one ends the process.
pub const HARD_LIMIT: usize = 3 << 30;

static LIVE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

/// The counting allocator (see the module docs).
#[derive(Debug)]
pub struct Counting;

/// Bytes live now.
pub fn live() -> usize {
    LIVE.load(Ordering::Relaxed)
}

/// The most bytes live at once since the last [`reset_peak`].
pub fn peak() -> usize {
    PEAK.load(Ordering::Relaxed)
}

/// Starts a new peak at the bytes live now.
pub fn reset_peak() {
    PEAK.store(live(), Ordering::Relaxed);
}

/// Counts `size` more live bytes, or refuses them when they would pass [`HARD_LIMIT`].
fn grow(size: usize) -> bool {
    let before = LIVE.fetch_add(size, Ordering::Relaxed);
    match before.checked_add(size) {
        Some(now) if now <= HARD_LIMIT => {
            PEAK.fetch_max(now, Ordering::Relaxed);
            true
        }
        _ => {
            LIVE.fetch_sub(size, Ordering::Relaxed);
            false
        }
    }
}

fn shrink(size: usize) {
    LIVE.fetch_sub(size, Ordering::Relaxed);
}

// SAFETY: every method forwards to `System` with the caller's layout and pointer unchanged (its
// contract is the caller's); the counters are plain atomics. A refused allocation returns null,
// which `GlobalAlloc` allows (the caller's allocation-error handler then aborts).
#[allow(unsafe_code)]
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if !grow(layout.size()) {
            return std::ptr::null_mut();
        }
        // SAFETY: forwarded as given
        let p = unsafe { System.alloc(layout) };
        if p.is_null() {
            shrink(layout.size());
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if !grow(layout.size()) {
            return std::ptr::null_mut();
        }
        // SAFETY: forwarded as given
        let p = unsafe { System.alloc_zeroed(layout) };
        if p.is_null() {
            shrink(layout.size());
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: forwarded as given
        unsafe { System.dealloc(ptr, layout) };
        shrink(layout.size());
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let old = layout.size();
        if new_size > old && !grow(new_size - old) {
            return std::ptr::null_mut();
        }
        // SAFETY: forwarded as given
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if p.is_null() {
            if new_size > old {
                shrink(new_size - old);
            }
        } else if new_size < old {
            shrink(old - new_size);
        }
        p
    }
}
