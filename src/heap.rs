//! glibc malloc's own view of the heap, for the service's memory figures.
//!
//! RSS alone cannot tell a growing live heap (a leak, an unbounded structure) from
//! memory that malloc holds free (fragmentation): [`stats`] gives both, and the
//! metrics export them. Off glibc (musl, other allocators) there are no figures.
//!
//! This is the one module with `unsafe`: the glibc call `mallinfo2` through `libc`.
#![allow(unsafe_code)]

/// The heap as glibc's malloc sees it, bytes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HeapStats {
    /// Bytes in chunks handed out and not yet freed (including large chunks malloc
    /// mapped on their own): the live heap.
    pub in_use_bytes: u64,
    /// Bytes malloc holds in free chunks of its arenas.
    pub free_bytes: u64,
}

/// The heap now; `None` where the allocator is not glibc's.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
pub fn stats() -> Option<HeapStats> {
    // SAFETY: mallinfo2 takes no arguments, returns a plain struct by value and only
    // reads malloc's state under the arenas' own locks.
    let mi = unsafe { libc::mallinfo2() };
    Some(HeapStats {
        in_use_bytes: (mi.uordblks + mi.hblkhd) as u64,
        free_bytes: mi.fordblks as u64,
    })
}

/// The heap now; `None` where the allocator is not glibc's.
#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
pub fn stats() -> Option<HeapStats> {
    None
}

#[cfg(all(test, target_os = "linux", target_env = "gnu"))]
mod tests {
    use super::*;

    #[test]
    fn stats_see_a_live_allocation_come_and_go() {
        let before = stats().expect("glibc");
        // Large enough to stand out from what other test threads allocate meanwhile.
        let block = vec![1u8; 64 << 20];
        let during = stats().expect("glibc");
        assert!(
            during.in_use_bytes >= before.in_use_bytes + (60 << 20),
            "{before:?} -> {during:?}"
        );
        drop(std::hint::black_box(block));
        let after = stats().expect("glibc");
        assert!(
            after.in_use_bytes + (60 << 20) <= during.in_use_bytes,
            "{during:?} -> {after:?}"
        );
    }
}
