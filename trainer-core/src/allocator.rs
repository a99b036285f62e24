//! Tuning the system allocator for training loops.
//!
//! burn's CPU backend allocates a fresh buffer for nearly every tensor op. With glibc's defaults,
//! every buffer above 128 KiB is a new `mmap` whose pages are faulted in and zeroed, then
//! `munmap`ed (with a TLB shoot-down across threads) when freed: on the benchmark step this was
//! over 10% of the time. Keeping freed memory in the heap for reuse removes that churn.

/// What [`keep_freed_memory`] asked of the allocator and what it accepted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AllocatorTuning {
    /// Whether large allocations now come from the heap instead of fresh mappings.
    pub heap_for_large_blocks: bool,
    /// Whether freed memory at the top of the heap is now kept instead of returned.
    pub keep_freed_top: bool,
}

/// Makes glibc serve large blocks from its heaps and keep freed memory for reuse (at most a
/// few GiB stay reserved after peaks). Call once at process start, before worker threads exist.
/// On other allocators it does nothing and reports so.
pub fn keep_freed_memory() -> AllocatorTuning {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // Constants from glibc's <malloc.h>; the libc crate does not export them.
        const M_TRIM_THRESHOLD: libc::c_int = -1;
        const M_TOP_PAD: libc::c_int = -2;
        const M_MMAP_THRESHOLD: libc::c_int = -3;
        // SAFETY: mallopt only adjusts allocator parameters; it is called before the
        // allocation-heavy work and takes plain integers.
        unsafe {
            let heap_for_large_blocks = libc::mallopt(M_MMAP_THRESHOLD, 1 << 30) == 1;
            let keep_freed_top = libc::mallopt(M_TRIM_THRESHOLD, i32::MAX) == 1
                && libc::mallopt(M_TOP_PAD, 256 << 20) == 1;
            AllocatorTuning {
                heap_for_large_blocks,
                keep_freed_top,
            }
        }
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        AllocatorTuning {
            heap_for_large_blocks: false,
            keep_freed_top: false,
        }
    }
}
