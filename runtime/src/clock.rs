//! Time: CLOCK_MONOTONIC, the one time base all timestamps in messages use, and the clock a
//! runner injects into its nodes (the real one in a process, a virtual one in simulation).

use std::cell::Cell;

/// Nanoseconds on CLOCK_MONOTONIC. Comparable across processes on one host.
pub fn monotonic_ns() -> u64 {
    // CLOCK_MONOTONIC always exists on Linux.
    read_ns(libc::CLOCK_MONOTONIC).unwrap_or(0)
}

/// Nanoseconds the calling thread has run (its CPU clock; steal excluded where the kernel
/// has paravirtual steal accounting). `None` if the kernel refuses the clock.
pub fn thread_cpu_ns() -> Option<u64> {
    read_ns(libc::CLOCK_THREAD_CPUTIME_ID)
}

fn read_ns(clock: libc::clockid_t) -> Option<u64> {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec.
    let rc = unsafe { libc::clock_gettime(clock, &mut ts) };
    (rc == 0).then(|| ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64)
}

/// What a node reads the time from: it never calls the system clock itself, so the same
/// node runs on the wall clock in a process and on virtual time in a simulation.
pub trait Clock {
    fn now_ns(&self) -> u64;
}

/// CLOCK_MONOTONIC.
#[derive(Debug, Clone, Copy, Default)]
pub struct Monotonic;

impl Clock for Monotonic {
    fn now_ns(&self) -> u64 {
        monotonic_ns()
    }
}

/// Simulated time: it moves only when the simulation moves it.
#[derive(Debug, Default)]
pub struct VirtualClock {
    now: Cell<u64>,
}

impl VirtualClock {
    pub fn set(&self, ns: u64) {
        self.now.set(ns);
    }
}

impl Clock for VirtualClock {
    fn now_ns(&self) -> u64 {
        self.now.get()
    }
}
