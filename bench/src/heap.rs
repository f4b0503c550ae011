//! Peak heap in use, for `bench inolf`'s runtime-memory column.
//!
//! With the `heap-peak` feature this crate installs the system allocator with a peak counter
//! (`peakmem-alloc`: two atomic updates per allocation) as the process's global allocator;
//! without it (the default, and what the services run) there is nothing to read and
//! [`peak`] says so with `None`.

#[cfg(feature = "heap-peak")]
#[global_allocator]
static ALLOCATOR: &peakmem_alloc::PeakMemAlloc<std::alloc::System> = &peakmem_alloc::INSTRUMENTED_SYSTEM;

/// Restarts the peak count of heap bytes (net of frees) from now (a no-op without the
/// counting allocator).
pub fn reset_peak() {
    #[cfg(feature = "heap-peak")]
    {
        use peakmem_alloc::PeakMemAllocTrait;
        ALLOCATOR.reset_peak_memory();
    }
}

/// Most heap bytes in use at once (net of frees) since [`reset_peak`]; `None` when this
/// build has no counting allocator.
pub fn peak() -> Option<usize> {
    #[cfg(feature = "heap-peak")]
    {
        use peakmem_alloc::PeakMemAllocTrait;
        Some(ALLOCATOR.get_peak_memory())
    }
    #[cfg(not(feature = "heap-peak"))]
    None
}
