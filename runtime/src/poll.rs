//! Waiting without the kernel's help: iceoryx2's timed waits are jiffy-grained here, so
//! loops poll non-blocking `receive()` with a spin → yield → sleep back-off, and watch a
//! termination flag set by SIGINT/SIGTERM.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

static TERMINATE: AtomicBool = AtomicBool::new(false);

extern "C" fn on_termination_signal(_: libc::c_int) {
    TERMINATE.store(true, Ordering::Relaxed);
}

/// Installs SIGINT/SIGTERM handlers that set the termination flag (async-signal-safe: they
/// only store an atomic). Call once at process start.
pub fn install_termination_handler() {
    for sig in [libc::SIGINT, libc::SIGTERM] {
        // SAFETY: the handler only touches an atomic; sigaction is given a zeroed, valid struct.
        unsafe {
            let mut action: libc::sigaction = std::mem::zeroed();
            action.sa_sigaction = on_termination_signal as *const () as usize;
            libc::sigemptyset(&mut action.sa_mask);
            libc::sigaction(sig, &action, std::ptr::null_mut());
        }
    }
}

/// True once SIGINT or SIGTERM arrived.
pub fn termination_requested() -> bool {
    TERMINATE.load(Ordering::Relaxed)
}

#[derive(Debug, thiserror::Error)]
pub enum WaitError<E> {
    #[error("timed out after {0:?}")]
    Timeout(Duration),
    #[error("termination requested")]
    Terminated,
    #[error(transparent)]
    Source(E),
}

/// Spin this many polls before yielding the CPU. In lockstep three processes wait on each
/// other, on two cores in this project's target, so a long spin starves the very peer being
/// waited for (docs/measurements.md has the measurement).
const SPIN_POLLS: u32 = 16;
/// Yield for this long before falling back to short sleeps, so an idle process does not
/// burn a core that its peers need.
const YIELD_PHASE: Duration = Duration::from_millis(2);
const SLEEP_STEP: Duration = Duration::from_micros(200);

/// The waiting of a loop that does not know when its input comes: spin a little, then
/// yield the CPU, then take short sleeps.
#[derive(Debug, Clone, Default)]
pub struct Backoff {
    polls: u32,
    since: Option<Instant>,
}

impl Backoff {
    /// Call after each empty poll: spins, yields or sleeps, by how long the wait has been.
    /// Returns false while still in the spin phase (no need to check the clock yet).
    pub fn pause(&mut self) -> bool {
        self.polls = self.polls.saturating_add(1);
        if self.polls < SPIN_POLLS {
            std::hint::spin_loop();
            return false;
        }
        let since = *self.since.get_or_insert_with(Instant::now);
        if since.elapsed() < YIELD_PHASE {
            std::thread::yield_now();
        } else {
            std::thread::sleep(SLEEP_STEP);
        }
        true
    }
}

/// Polls `f` until it yields a value, the timeout passes, or termination is requested.
/// No allocation, no blocking system call other than `sched_yield` and short sleeps.
pub fn poll_until<T, E>(
    timeout: Duration,
    mut f: impl FnMut() -> Result<Option<T>, E>,
) -> Result<T, WaitError<E>> {
    let start = Instant::now();
    let mut backoff = Backoff::default();
    loop {
        if let Some(v) = f().map_err(WaitError::Source)? {
            return Ok(v);
        }
        if termination_requested() {
            return Err(WaitError::Terminated);
        }
        if start.elapsed() >= timeout {
            return Err(WaitError::Timeout(timeout));
        }
        backoff.pause();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn returns_value_when_ready_and_times_out_otherwise() {
        let mut n = 0;
        let v: Result<u32, WaitError<()>> = poll_until(Duration::from_secs(1), || {
            n += 1;
            Ok((n == 500).then_some(n))
        });
        assert_eq!(v.ok(), Some(500));
        let t0 = Instant::now();
        let r: Result<(), WaitError<()>> = poll_until(Duration::from_millis(20), || Ok(None));
        assert!(matches!(r, Err(WaitError::Timeout(_))));
        assert!(t0.elapsed() >= Duration::from_millis(20));
        let e: Result<(), WaitError<&str>> = poll_until(Duration::from_secs(1), || Err("boom"));
        assert!(matches!(e, Err(WaitError::Source("boom"))));
    }
}
