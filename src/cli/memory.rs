//! The binary's allocator: the system's, with a clear last word when memory
//! runs out. Rust's default answer to a failed allocation is "memory
//! allocation of N bytes failed" and an abort (exit 134, a core dump, no
//! file or phase named), which a build pipeline cannot tell from a crash.
//! Here the failure names the phase the bake was in (set by the progress
//! reporter as phases begin) and exits with status 1 like any other failed
//! bake. Outputs are never half-written: chunk files are replaced by
//! rename, and a later run removes the temporary files a stop leaves.

use shadowcull::progress::Phase;
use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicU8, Ordering};

pub struct PhaseNamingAllocator;

/// The phase in progress: 1 + its position in [`Phase::ALL`] (0: none
/// yet).
static CURRENT: AtomicU8 = AtomicU8::new(0);

/// Records the phase that has begun, for the out-of-memory message, and
/// hands the pages the last phase freed back to the system.
pub fn entering(phase: Phase) {
    if let Some(i) = Phase::ALL.iter().position(|p| *p == phase) {
        CURRENT.store(i as u8 + 1, Ordering::Relaxed);
    }
    release_free_pages();
}

/// glibc keeps freed memory mapped: the parse trees and decode buffers of
/// loading, a top level's build temporaries. Their pages sit between live
/// allocations, so they stay resident until `malloc_trim` gives back every
/// whole free page, which lowers the bake's peak resident memory.
fn release_free_pages() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only returns free pages to the system; every
    // live allocation stays where it is.
    unsafe {
        libc::malloc_trim(0);
    }
}

fn current() -> Option<Phase> {
    let slot = CURRENT.load(Ordering::Relaxed) as usize;
    slot.checked_sub(1).and_then(|i| Phase::ALL.get(i)).copied()
}

/// Writes the message (an `error` event with `--progress json`: nothing in
/// it needs escaping) and exits without allocating (the heap is what
/// failed) and without unwinding.
fn out_of_memory(bytes: usize) -> ! {
    let phase = current().map_or("starting", Phase::name);
    let json = super::messages::is_json();
    let mut buffer = [0u8; 400];
    let mut len = 0;
    for part in [
        if json {
            "{\"event\":\"error\",\"message\":\""
        } else {
            "error: "
        },
        "out of memory in phase `",
        phase,
        "`: could not allocate ",
    ] {
        len += copy(&mut buffer[len..], part.as_bytes());
    }
    len += copy(&mut buffer[len..], decimal(bytes, &mut [0u8; 20]));
    len += copy(
        &mut buffer[len..],
        b" bytes (chunk files are replaced whole or not at all). Run `shadowcull plan` for the \
estimate, then free memory, bake fewer lights at once (--light) or raise <texelSize>.",
    );
    let end: &[u8] = if json { b"\"}\n" } else { b"\n" };
    len += copy(&mut buffer[len..], end);
    // SAFETY: writing a byte buffer we own to stderr, then ending the
    // process without running anything that could allocate.
    unsafe {
        libc::write(2, buffer.as_ptr().cast(), len);
        libc::_exit(1)
    }
}

fn copy(to: &mut [u8], from: &[u8]) -> usize {
    let n = from.len().min(to.len());
    to[..n].copy_from_slice(&from[..n]);
    n
}

fn decimal(mut n: usize, digits: &mut [u8; 20]) -> &[u8] {
    let mut start = digits.len();
    loop {
        start -= 1;
        digits[start] = b'0' + (n % 10) as u8;
        n /= 10;
        if n == 0 {
            return &digits[start..];
        }
    }
}

// SAFETY: every call goes to the system allocator with the caller's
// arguments; only a null answer is turned into an exit.
unsafe impl GlobalAlloc for PhaseNamingAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc(layout) };
        if p.is_null() {
            out_of_memory(layout.size());
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        let p = unsafe { System.alloc_zeroed(layout) };
        if p.is_null() {
            out_of_memory(layout.size());
        }
        p
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if p.is_null() {
            out_of_memory(new_size);
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decimals_print_without_allocating() {
        let mut digits = [0u8; 20];
        assert_eq!(decimal(0, &mut digits), b"0");
        assert_eq!(decimal(4_317_058_280, &mut digits), b"4317058280");
        assert_eq!(
            decimal(usize::MAX, &mut digits),
            usize::MAX.to_string().as_bytes()
        );
    }

    #[test]
    fn every_phase_has_a_slot() {
        for phase in Phase::ALL {
            entering(phase);
            assert_eq!(current(), Some(phase));
        }
    }
}
