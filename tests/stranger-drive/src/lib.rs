//! A drive for stepdrive's wire protocol version 3 (3.1 since issue 24), written from
//! `docs/drive-protocol.md` alone: a simulated Table I stepper behind a UDP endpoint.

#[cfg(test)]
mod conformance;
pub mod core;
pub mod crc;
pub mod frame;
pub mod motor;
pub mod net;

pub use crate::core::DriveCore;
pub use crate::net::serve;

use std::fmt;

/// Everything the drive can be told at start-up.
#[derive(Debug, Clone)]
pub struct DriveOptions {
    pub listen: String,
    pub rate_hz: u32,
    pub load_nm: f64,
    pub bus_v: f64,
    pub plan_capacity: u16,
    pub watchdog_periods: u16,
    pub align_ma: u16,
    pub align_ms: u16,
    pub counts_per_rev: u32,
    pub reverse_encoder: bool,
    pub initial_angle: f64,
    /// Our own ADC scalings (deliberately not the spec's example values).
    pub current_ua_per_count: u32,
    pub current_zero_count: u16,
    pub bus_uv_per_count: u32,
    pub overcurrent_a: f64,
    pub bus_min_v: f64,
    pub bus_max_v: f64,
    pub substeps: u32,
    pub drop_pct: f64,
    pub corrupt_pct: f64,
    pub seed: u64,
    pub dropout_at: Option<u64>,
    pub dropout_samples: u64,
    /// Stop after this many periods (None: until `stop`).
    pub stop_after: Option<u64>,
    /// Spin (instead of sleeping) for this long before each deadline, µs.
    pub spin_us: u64,
    pub verbose: bool,
    /// Fault injection: phase A's motor leads swapped at the drive's terminals.
    pub swap_phase_a: bool,
}

impl Default for DriveOptions {
    fn default() -> Self {
        DriveOptions {
            listen: "127.0.0.1:47701".to_string(),
            rate_hz: 20_000,
            load_nm: 0.01,
            bus_v: 24.0,
            // §4.7: at least watchdog_periods entries, so that a plan covers every
            // period until the watchdog trips
            plan_capacity: 800,
            watchdog_periods: 800,
            align_ma: 800,
            align_ms: 250,
            counts_per_rev: 400_000,
            reverse_encoder: false,
            initial_angle: 0.0,
            current_ua_per_count: 153,
            current_zero_count: 31_744,
            bus_uv_per_count: 7_000,
            overcurrent_a: 4.0,
            bus_min_v: 18.0,
            bus_max_v: 30.0,
            substeps: 4,
            drop_pct: 0.0,
            corrupt_pct: 0.0,
            seed: 0x5EED_1234_ABCD_0001,
            dropout_at: None,
            dropout_samples: 0,
            stop_after: None,
            spin_us: 60,
            verbose: false,
            swap_phase_a: false,
        }
    }
}

/// Counters the drive keeps; printed at exit.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct DriveStats {
    pub frames_received: u64,
    pub frames_accepted: u64,
    pub dropped_too_short: u64,
    pub dropped_length: u64,
    pub dropped_crc: u64,
    pub dropped_magic: u64,
    pub dropped_version: u64,
    pub dropped_unknown_kind: u64,
    pub dropped_payload_len: u64,
    pub dropped_bad_field: u64,
    pub dropped_reserved: u64,
    pub dropped_wrong_direction: u64,
    pub dropped_sequence: u64,
    pub dropped_wrong_source: u64,
    pub dropped_no_session: u64,
    pub dropped_plan_capacity: u64,
    pub sessions: u64,
    pub configs_sent: u64,
    pub samples_sent: u64,
    pub samples_dropped_injected: u64,
    pub samples_corrupted_injected: u64,
    pub samples_dropout: u64,
    pub fault_reports_sent: u64,
    pub faults_latched: u64,
    pub commands_received: u64,
    pub commands_applied: u64,
    pub commands_late: u64,
    /// COMMANDs for a period with the outputs off or aligning (§4.3).
    pub commands_discarded_off: u64,
    pub commands_bad: u64,
    pub controls_ignored: u64,
    pub plans_stored: u64,
    pub plans_ignored_older: u64,
    pub periods: u64,
    pub periods_enabled: u64,
    pub periods_held: u64,
    pub periods_planned: u64,
    pub overruns: u64,
    pub send_errors: u64,
    pub runs_started: u64,
}

impl fmt::Display for DriveStats {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s = format!("{self:#?}");
        // one "name: value" per line, without the struct braces
        for line in s.lines() {
            let t = line.trim().trim_end_matches(',');
            if t.ends_with('{') || t == "}" {
                continue;
            }
            writeln!(f, "  {t}")?;
        }
        Ok(())
    }
}

#[derive(Debug)]
pub enum DriveError {
    Io(std::io::Error),
    Options(String),
}

impl fmt::Display for DriveError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            DriveError::Io(e) => write!(f, "i/o error: {e}"),
            DriveError::Options(s) => write!(f, "invalid options: {s}"),
        }
    }
}

impl std::error::Error for DriveError {}

impl From<std::io::Error> for DriveError {
    fn from(e: std::io::Error) -> Self {
        DriveError::Io(e)
    }
}

impl DriveOptions {
    /// Checks the options against CONFIG's valid values (§4.5) and the model.
    pub fn validate(&self) -> Result<(), DriveError> {
        let bad = |s: &str| Err(DriveError::Options(s.to_string()));
        if !(100..=100_000).contains(&self.rate_hz) {
            return bad("--rate must be 100..100000 Hz");
        }
        if !(4..=(1 << 30)).contains(&self.counts_per_rev) {
            return bad("--counts-per-rev must be 4..2^30");
        }
        if self.watchdog_periods < 2 {
            return bad("--watchdog-periods must be >= 2");
        }
        if self.plan_capacity > 1024 {
            return bad("--plan-capacity must be <= 1024");
        }
        if self.align_ms > 0 && self.align_ma == 0 {
            return bad("--align-ma must be > 0 when --align-ms > 0");
        }
        if self.align_ms > 0 && (self.align_ms as u64 * self.rate_hz as u64) < 1000 {
            // floor(align_ms × rate / 1000) = 0: no SAMPLE would ever show ALIGNING
            return bad("--align-ms × --rate must be >= 1000 (at least one ALIGNING period)");
        }
        if self.current_ua_per_count == 0 || self.bus_uv_per_count == 0 {
            return bad("ADC scales must be > 0");
        }
        if !(self.bus_v > 0.0 && self.bus_v.is_finite()) {
            return bad("--bus-v must be > 0");
        }
        if !self.load_nm.is_finite() || !self.initial_angle.is_finite() {
            return bad("--load and --initial-angle must be finite");
        }
        if !(0.0..=100.0).contains(&self.drop_pct) || !(0.0..=100.0).contains(&self.corrupt_pct) {
            return bad("--drop-pct and --corrupt-pct must be 0..100");
        }
        Ok(())
    }
}
