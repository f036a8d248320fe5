//! glibc malloc: its own view of the heap, and the arena setting of the service.
//!
//! RSS alone cannot tell a growing live heap (a leak, an unbounded structure) from
//! memory that malloc holds free (fragmentation): [`stats`] gives both, and the
//! metrics export them. [`use_one_arena`] is what keeps the service's RSS flat. Off
//! glibc (musl, other allocators) there are no figures and no setting.
//!
//! This is the one module with `unsafe`: two glibc calls (`mallinfo2`, `mallopt`)
//! through `libc`.
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

/// Makes every thread allocate from the one main arena (`M_ARENA_MAX` = 1). Call
/// before any thread starts; returns whether glibc took it (a no-op off glibc).
///
/// Why: glibc gives each new thread an arena of its own. In the soak (8 x 64
/// channels at 10 Hz) the tokio worker's arena kept extending its top (1.86 to
/// 2.02 MB in 6 minutes) while the process' live heap stayed flat at about 3.6 MB,
/// and RSS crept up in steps (+0.4 to +0.75 MB in 30 minutes). With one arena the
/// same churn reuses the free space the main arena holds from start-up (the
/// configuration is parsed there), and RSS stays flat (README, soak benchmark).
/// Four threads at a few thousand allocations a second do not contend for its lock
/// measurably.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
pub fn use_one_arena() -> bool {
    // SAFETY: mallopt only sets a malloc parameter (under malloc's lock); M_ARENA_MAX
    // with a positive value is a valid setting.
    unsafe { libc::mallopt(libc::M_ARENA_MAX, 1) == 1 }
}

/// Makes every thread allocate from the one main arena (`M_ARENA_MAX` = 1). Call
/// before any thread starts; returns whether glibc took it (a no-op off glibc).
#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
pub fn use_one_arena() -> bool {
    false
}

/// Gives the free heap back to the system (`malloc_trim(0)`: the top of the heap and
/// whole free pages inside it). Called once after start-up: parsing a large
/// configuration peaks far above what the running gateway keeps, and with one arena
/// that peak would otherwise stay resident. Returns whether anything was released.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
pub fn release_free() -> bool {
    // SAFETY: malloc_trim only walks and shrinks malloc's own free lists under its
    // locks; 0 asks for no padding to be kept.
    unsafe { libc::malloc_trim(0) == 1 }
}

/// Gives the free heap back to the system; a no-op off glibc.
#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
pub fn release_free() -> bool {
    false
}

#[cfg(all(test, target_os = "linux", target_env = "gnu"))]
mod tests {
    use super::*;

    #[test]
    fn stats_see_a_live_allocation_come_and_go() {
        let before = stats().expect("glibc");
        // Zeroed, so calloc maps it without touching it; far larger than anything the
        // other test threads allocate or free meanwhile.
        let block = vec![0u8; 256 << 20];
        let during = stats().expect("glibc");
        assert!(
            during.in_use_bytes >= before.in_use_bytes + (128 << 20),
            "{before:?} -> {during:?}"
        );
        drop(std::hint::black_box(block));
        let after = stats().expect("glibc");
        assert!(
            after.in_use_bytes + (128 << 20) <= during.in_use_bytes,
            "{during:?} -> {after:?}"
        );
    }
}
