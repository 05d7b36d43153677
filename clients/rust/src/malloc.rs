//! How the tools (`esrp-bench`, `esrp-eval`) keep the memory they free for their next
//! allocations: [`keep_freed_memory`].
//!
//! A client's step receives answers of tens of kilobytes to megabytes (a 128×128 image is 49 KiB,
//! a StepBatch of 64 episodes 3 MiB) and frees each soon after. With glibc's defaults a process
//! gives freed memory at the top of its heaps back to the system and faults it in again, page by
//! page, for the next answer: `esrp-bench` driving 64 episodes took 2 to 4 minor page faults a
//! step and spent most of its CPU time in the kernel (docs/performance.md). The Python client
//! makes the same settings (`esrp._malloc_setup`).

/// Allocations below this many bytes come from the heap rather than from fresh mappings.
pub const MMAP_THRESHOLD: i32 = 32 << 20;

/// Free memory at the top of a heap beyond this many bytes goes back to the system.
pub const TRIM_THRESHOLD: i32 = 64 << 20;

/// The environment variables by which a user makes the choice instead: glibc's own, and
/// `ESRP_KEEP_MALLOC_DEFAULTS` (to anything) for glibc's defaults.
pub const USER_VARIABLES: [&str; 4] =
    ["MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_", "ESRP_KEEP_MALLOC_DEFAULTS"];

/// Whether `lookup` (an environment: a variable's value, if set) chooses malloc's thresholds
/// already: one of [`USER_VARIABLES`], or a `glibc.malloc.` tunable in `GLIBC_TUNABLES`.
pub fn users_choice(lookup: impl Fn(&str) -> Option<String>) -> bool {
    USER_VARIABLES.iter().any(|name| lookup(name).is_some())
        || lookup("GLIBC_TUNABLES").is_some_and(|tunables| tunables.contains("glibc.malloc."))
}

/// Raises glibc malloc's mmap threshold to [`MMAP_THRESHOLD`] and its trim threshold to
/// [`TRIM_THRESHOLD`], so that this process keeps up to that much freed memory for its next
/// allocations. Returns whether both were set: not where the C library is not glibc, nor when the
/// environment makes the choice ([`users_choice`]). Affects this process only (child processes
/// make their own call). Call it early in `main`; it takes effect for the allocations after it.
pub fn keep_freed_memory() -> bool {
    if users_choice(|name| std::env::var(name).ok()) {
        return false;
    }
    set_thresholds()
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
#[allow(unsafe_code)] // Audited: two libc calls on plain integers, see the SAFETY note.
fn set_thresholds() -> bool {
    // SAFETY: mallopt changes two of malloc's parameters under malloc's own lock; it reads and
    // writes no memory of ours.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1
            && libc::mallopt(libc::M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn set_thresholds() -> bool {
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    fn environment(pairs: &[(&str, &str)]) -> impl Fn(&str) -> Option<String> {
        let pairs: Vec<(String, String)> = pairs.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect();
        move |name| pairs.iter().find(|(k, _)| k == name).map(|(_, v)| v.clone())
    }

    #[test]
    fn the_users_variables_and_malloc_tunables_are_their_choice() {
        assert!(!users_choice(environment(&[])));
        assert!(!users_choice(environment(&[("GLIBC_TUNABLES", "glibc.pthread.rseq=0"), ("PATH", "/bin")])));
        for name in USER_VARIABLES {
            assert!(users_choice(environment(&[(name, "")])), "{name}");
        }
        assert!(users_choice(environment(&[("GLIBC_TUNABLES", "glibc.pthread.rseq=0:glibc.malloc.trim_threshold=1")])));
    }

    #[test]
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    fn the_thresholds_are_set_on_glibc() {
        assert!(set_thresholds());
    }
}
