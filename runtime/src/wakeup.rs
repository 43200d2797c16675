//! Fast wake-ups for lockstep hand-offs: while a lockstep stack runs, its launcher asks the
//! kernel's power management for a CPU wake-up latency of 0 µs (`/dev/cpu_dma_latency`, the
//! request `cyclictest` makes), so that an idle CPU polls instead of halting. Every
//! lockstep hand-off that sleeps on a doorbell is a wake-up of a process on the other CPU;
//! from a halted virtual CPU that costs a VM exit and an interrupt, ~9 µs one way here.
//! Measured on this project's machine (docs/measurements.md): the default scenario's
//! lockstep run 0.479 → 0.345 s (medians of 10, interleaved with the build before).
//!
//! The request lasts while the file stays open: the kernel drops it when the holder exits,
//! killed or not. Opening it needs root; without, runs are as they were (said at debug).

use std::io::Write;

const PATH: &str = "/dev/cpu_dma_latency";

/// The held request; dropping it ends it.
#[derive(Debug)]
pub struct WakeupLatencyHold {
    _file: std::fs::File,
}

/// Asks for 0 µs wake-up latency for as long as the returned hold lives; `None` if the
/// request could not be made (not root, no such device).
pub fn hold_zero_wakeup_latency() -> Option<WakeupLatencyHold> {
    let attempt = || -> std::io::Result<WakeupLatencyHold> {
        let mut file = std::fs::OpenOptions::new().write(true).open(PATH)?;
        // The kernel takes a 32-bit binary value (or a hex string).
        file.write_all(&0i32.to_ne_bytes())?;
        Ok(WakeupLatencyHold { _file: file })
    };
    match attempt() {
        Ok(hold) => Some(hold),
        Err(e) => {
            tracing::debug!("no 0 µs CPU wake-up latency request ({PATH}: {e}): lockstep hand-offs wake halted CPUs");
            None
        }
    }
}
