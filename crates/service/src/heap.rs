//! glibc malloc: its own view of the heap, and the arena setting of the service.
//!
//! RSS alone cannot tell a growing live heap (a leak, an unbounded structure) from
//! memory that malloc holds free (fragmentation): [`stats`] gives both, and the
//! metrics export them. [`use_one_arena`] is what keeps the service's RSS flat. Off
//! glibc (musl, other allocators) there are no figures and no setting.
//!
//! This is the one module with `unsafe`: glibc calls (`mallinfo2` found by `dlsym`,
//! `mallinfo`, `mallopt`, `malloc_trim`) through `libc`.
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
///
/// `mallinfo2` (glibc 2.33) is looked up when the process runs, not linked: linked, it
/// kept the gateway from building or starting on glibc 2.31 (Debian 11, the base of
/// several ARM gateway boxes' images). There the older `mallinfo` serves, whose `int`
/// fields, read unsigned, wrap past 4 GiB, far above this service's heap.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
pub fn stats() -> Option<HeapStats> {
    use std::sync::OnceLock;
    type Mallinfo2 = unsafe extern "C" fn() -> libc::mallinfo2;
    static MALLINFO2: OnceLock<Option<Mallinfo2>> = OnceLock::new();
    let mallinfo2 = MALLINFO2.get_or_init(|| {
        // SAFETY: dlsym with RTLD_DEFAULT and a NUL-terminated name only looks the
        // symbol up; a non-null result is glibc's mallinfo2, whose signature
        // `struct mallinfo2 mallinfo2(void)` is the type it is turned into.
        unsafe {
            let f = libc::dlsym(libc::RTLD_DEFAULT, c"mallinfo2".as_ptr());
            (!f.is_null()).then(|| std::mem::transmute::<*mut libc::c_void, Mallinfo2>(f))
        }
    });
    if let Some(mallinfo2) = mallinfo2 {
        // SAFETY: mallinfo2 takes no arguments, returns a plain struct by value and
        // only reads malloc's state under the arenas' own locks.
        let mi = unsafe { mallinfo2() };
        return Some(HeapStats {
            in_use_bytes: (mi.uordblks + mi.hblkhd) as u64,
            free_bytes: mi.fordblks as u64,
        });
    }
    Some(stats_before_2_33())
}

/// [`stats`] from glibc's older `mallinfo`.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn stats_before_2_33() -> HeapStats {
    // SAFETY: as mallinfo2, with `int` fields (read as unsigned: they wrap at 4 GiB).
    #[allow(deprecated)]
    let mi = unsafe { libc::mallinfo() };
    HeapStats {
        in_use_bytes: u64::from(mi.uordblks as u32) + u64::from(mi.hblkhd as u32),
        free_bytes: u64::from(mi.fordblks as u32),
    }
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

    // Both ways to the figures: mallinfo2 (glibc 2.33 on), mallinfo before.
    #[test]
    fn stats_see_a_live_allocation_come_and_go() {
        let reads: [fn() -> HeapStats; 2] = [|| stats().expect("glibc"), stats_before_2_33];
        for read in reads {
            let before = read();
            // Zeroed, so calloc maps it without touching it; far larger than anything
            // the other test threads allocate or free meanwhile.
            let block = vec![0u8; 256 << 20];
            let during = read();
            assert!(
                during.in_use_bytes >= before.in_use_bytes + (128 << 20),
                "{before:?} -> {during:?}"
            );
            drop(std::hint::black_box(block));
            let after = read();
            assert!(
                after.in_use_bytes + (128 << 20) <= during.in_use_bytes,
                "{during:?} -> {after:?}"
            );
        }
    }
}
