//! How a run ended, as the user must learn it: a class, an exit code, and for anything but
//! success a headline that says what happened, when, in which process, and what to do.
//!
//! | outcome | exit code | meaning |
//! |---|---|---|
//! | ok | 0 | every method ran to the end, no fault, the motor followed |
//! | unobserved | 6 | the run ended, but the monitor saw too little of it (of the run, its cruise window or its final window) for its figures to stand |
//! | error | 1 | the run could not start: bad input, a refused setting (before any motion) |
//! | usage | 2 | the command line itself is wrong (clap) |
//! | fault | 3 | the plant, the bridge or the drive latched a fault (watchdog, bad command, over-current, ...): outputs went off |
//! | stepped out | 4 | the motor lost track: |θ_d − θ| exceeded one electrical period (2π/N_r, four full steps) |
//! | process died | 5 | a process of the stack died, hung, or broke the protocol; the run is incomplete |
//! | interrupted | 130 | SIGINT or SIGTERM; the run is incomplete |
//!
//! The most severe outcome of a run's methods decides its exit code; the results gathered
//! so far are printed and written either way, marked incomplete where they are.

use serde::Serialize;
use stepdrive_shared::messages::fault_bits;
use stepdrive_shared::Scenario;

/// A command that did not go well: its headline is printed, the process exits with `code`.
#[derive(Debug, thiserror::Error)]
#[error("{headline}")]
pub struct Exit {
    pub code: u8,
    pub headline: String,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    Ok,
    /// The figures do not stand: the monitor saw less than [`MIN_SEEN_FRACTION`] of the
    /// samples of the run, of its cruise window or of its final window, or missed more than
    /// [`MAX_UNSEEN_S`] in a row (lost on the wire, skipped by the bridge, or overwritten in
    /// the monitor's queue while it had no CPU).
    /// Below the outcomes that say what the motor did: evidence of those wins.
    Unobserved,
    SteppedOut,
    Fault,
    ProcessDied,
    Interrupted,
}

impl Outcome {
    pub fn exit_code(self) -> u8 {
        match self {
            Outcome::Ok => 0,
            Outcome::Unobserved => 6,
            Outcome::Fault => 3,
            Outcome::SteppedOut => 4,
            Outcome::ProcessDied => 5,
            Outcome::Interrupted => 130,
        }
    }

    pub fn title(self) -> &'static str {
        match self {
            Outcome::Ok => "OK",
            Outcome::Unobserved => "UNOBSERVED",
            Outcome::Fault => "FAULT",
            Outcome::SteppedOut => "STEPPED OUT",
            Outcome::ProcessDied => "PROCESS DIED",
            Outcome::Interrupted => "INTERRUPTED",
        }
    }
}

/// The least share of a window's samples (the whole run up to its last sample, the cruise
/// window, the final window) the monitor must have seen for the run's figures to stand. A
/// lossy link passes (one frame in ten corrupted: ~88 % seen; 1 % dropped at 2 kHz without
/// real-time priorities, the bridge superseding queued samples: 74 % of a 101-sample final
/// window, its longest gap 5 ms); a monitor that lost its CPU for longer than its queue
/// (8192 samples, 0.41 s at 20 kHz) saw 0–58 %.
pub const MIN_SEEN_FRACTION: f64 = 0.5;

/// The longest stretch of samples the monitor may miss, s: longer, and a transient (a load
/// step, a stall, the start of the cruise) can pass unseen. An emulated drive paused with its
/// host does not count (its sample index pauses too); a host stall that makes the bridge
/// supersede samples lasts 1–25 ms here; a starved monitor missed 0.4–1.1 s.
pub const MAX_UNSEEN_S: f64 = 0.1;

/// Faults that stay until a reset: the outputs are off. `DRIVE_SILENT` is the bridge's
/// report of a silent drive and ends when the drive speaks again.
pub const LATCHED: u32 =
    fault_bits::BAD_COMMAND | fault_bits::COMMAND_TIMEOUT | fault_bits::DRIVE_FAULT;

/// The drive's own fault bits (the upper 16 of `DriveState::fault`, see
/// `docs/drive-protocol.md`).
const DRIVE_FAULTS: [(u32, &str); 4] = [
    (
        1 << 0,
        "WATCHDOG (no valid COMMAND for its watchdog periods)",
    ),
    (1 << 1, "OVERCURRENT"),
    (1 << 2, "BUS_VOLTAGE (outside the drive's range)"),
    (1 << 3, "BAD_COMMAND (a duty outside ±32767)"),
];

/// The fault bits of a state, named.
pub fn fault_names(bits: u32) -> Vec<String> {
    let mut names = Vec::new();
    if bits & fault_bits::COMMAND_TIMEOUT != 0 {
        names.push("COMMAND_TIMEOUT (no command for the watchdog's periods)".to_string());
    }
    if bits & fault_bits::BAD_COMMAND != 0 {
        names.push("BAD_COMMAND (a non-finite voltage)".to_string());
    }
    if bits & fault_bits::DRIVE_SILENT != 0 {
        names.push("DRIVE_SILENT (no sample from the drive)".to_string());
    }
    if bits & fault_bits::DRIVE_FAULT != 0 {
        let drive = bits >> 16;
        let named: Vec<&str> = DRIVE_FAULTS
            .iter()
            .filter(|(bit, _)| drive & bit != 0)
            .map(|(_, name)| *name)
            .collect();
        if named.is_empty() {
            names.push(format!("DRIVE_FAULT (drive bits {drive:#06x})"));
        } else {
            names.push(format!("DRIVE_FAULT: {}", named.join(", ")));
        }
    }
    names
}

/// The first latched fault of a run.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FaultEvent {
    pub sample: u64,
    /// Simulated (sample) time, s.
    pub sim_time_s: f64,
    /// Wall-clock time the monitor saw it, s since the Unix epoch.
    pub seen_unix_s: f64,
    pub bits: u32,
    pub faults: Vec<String>,
}

impl FaultEvent {
    /// Which process latched it.
    pub fn latched_by(&self, mode: &str) -> &'static str {
        if self.bits & fault_bits::DRIVE_FAULT != 0 {
            "the drive"
        } else if mode == "hardware" {
            "the bridge"
        } else {
            "the plant"
        }
    }

    /// What a user can do about it.
    pub fn advice(&self) -> &'static str {
        let drive = self.bits >> 16;
        if self.bits & fault_bits::COMMAND_TIMEOUT != 0 || drive & 1 != 0 {
            "the current loop's commands stopped for the watchdog's periods: it died, was \
             stopped, or the host held its CPU. Keep the machine otherwise idle, keep RT \
             throttling lifted (the default when run as root), check the log above for a \
             dead process; --watchdog-periods trades this protection for tolerance of stalls. \
             A stack started by hand can be reset: `stepdrive reset --instance NAME`"
        } else if self.bits & fault_bits::BAD_COMMAND != 0 || drive & 8 != 0 {
            "a command was not a number a drive can apply: this is a controller bug, please \
             report it with the scenario"
        } else if drive & 2 != 0 {
            "the phase current exceeded the drive's limit: check the motor parameters and \
             the bus voltage against the drive's rating"
        } else {
            "check the drive and its supply"
        }
    }
}

/// One electrical period (four full steps): a microstepped rotor that loses synchronism
/// settles a whole period off, so an error this large means it slipped; a field-oriented
/// controller recovers from smaller transients.
pub fn step_out_threshold_rad(s: &Scenario) -> f64 {
    std::f64::consts::TAU / s.motor.n_r()
}

/// When a wall-clock instant (s since the Unix epoch) was, as UTC `HH:MM:SS.mmm`.
pub fn utc_time_of_day(unix_s: f64) -> String {
    let ms = (unix_s * 1000.0).round() as u64;
    let (s, ms) = (ms / 1000, ms % 1000);
    format!(
        "{:02}:{:02}:{:02}.{ms:03} UTC",
        (s / 3600) % 24,
        (s / 60) % 60,
        s % 60
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn severity_orders_the_outcomes_and_codes_are_distinct() {
        let all = [
            Outcome::Ok,
            Outcome::Unobserved,
            Outcome::SteppedOut,
            Outcome::Fault,
            Outcome::ProcessDied,
            Outcome::Interrupted,
        ];
        assert!(all.windows(2).all(|w| w[0] < w[1]));
        let mut codes: Vec<u8> = all.iter().map(|o| o.exit_code()).collect();
        codes.sort_unstable();
        codes.dedup();
        assert_eq!(codes, [0, 3, 4, 5, 6, 130]);
    }

    #[test]
    fn faults_are_named_with_the_drives_own_bits() {
        assert!(fault_names(fault_bits::COMMAND_TIMEOUT)[0].starts_with("COMMAND_TIMEOUT"));
        let drive = fault_names(fault_bits::DRIVE_FAULT | (3 << 16));
        assert_eq!(drive.len(), 1);
        assert!(
            drive[0].contains("WATCHDOG") && drive[0].contains("OVERCURRENT"),
            "{drive:?}"
        );
        assert_eq!(
            LATCHED & fault_bits::DRIVE_SILENT,
            0,
            "silence is not latched"
        );
        assert_eq!(
            utc_time_of_day(86_400.0 * 3.0 + 3_723.456),
            "01:02:03.456 UTC"
        );
    }
}
