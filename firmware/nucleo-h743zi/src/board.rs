//! What a user edits for their hardware: the drive's address, its rates, and the analog
//! front end, encoder and limits of the power stage wired to the board (README.md beside
//! this crate shows the wiring these values describe). Everything the host learns of the
//! drive (CONFIG, docs/drive-protocol.md §4.5) is derived here.

use crate::convert;
use stepdrive_drive_core::Limits;
use stepdrive_drive_protocol::units::default_config;
use stepdrive_drive_protocol::Config;

// ---- The link -------------------------------------------------------------------------

/// The drive's Ethernet address (locally administered: bit 1 of the first byte set) and
/// static IPv4 address; the host's `--drive` names this address and `DRIVE_PORT`.
pub const MAC: [u8; 6] = [0x02, 0x00, 0x5d, 0x00, 0x00, 0x02];
pub const IP: [u8; 4] = [192, 168, 1, 50];
pub const PREFIX_LEN: u8 = 24;
/// Only needed if the host is on another subnet; `None`: the host is on this one.
pub const GATEWAY: Option<[u8; 4]> = None;
pub const DRIVE_PORT: u16 = 5555;

// ---- Rates ----------------------------------------------------------------------------

/// The bridges' PWM rate (TIM1, centre-aligned): above hearing, within what a DRV8412's
/// switching losses allow at a stepper's currents.
pub const PWM_HZ: u32 = 20_000;
/// PWM periods a sample period: the sample rate is `PWM_HZ / SAMPLE_DIV`. 1 (20 kHz) by
/// default, the stack's default rate: the link carries it, and the drive core is estimated
/// at ~10 % of the period on this core (README.md, "Rates"). If the log's sample interrupt
/// cycles come near the 12 000 it has (25 µs), 2 (10 kHz, with scenario-10khz.toml).
pub const SAMPLE_DIV: u32 = 1;
pub const SAMPLE_HZ: u32 = PWM_HZ / SAMPLE_DIV;
const _: () = assert!(SAMPLE_DIV >= 1 && PWM_HZ % SAMPLE_DIV == 0);

/// TIM1's kernel clock with main.rs's clock tree (APB2 at 120 MHz, timers at twice that).
pub const TIM1_CLOCK_HZ: u32 = 240_000_000;

// ---- The encoder (TIM4, quadrature) ----------------------------------------------------

/// Counts a revolution: four edges a line (a 1000-line encoder: 4000).
pub const COUNTS_PER_REV: u32 = 4000;
/// +1 if counting up is positive θ (phase A leading B, with the wiring in README.md).
pub const ENCODER_DIRECTION: i8 = 1;

// ---- Current sense (INA240 on an inline shunt per phase) --------------------------------

/// The shunt in each phase, µΩ.
pub const SHUNT_UOHM: u32 = 10_000;
/// The amplifier's gain, V/V (INA240A2: 50).
pub const AMP_GAIN: u32 = 50;
/// Its output at 0 A, mV: REF1 and REF2 split between 3.3 V and ground (mid-supply).
pub const AMP_ZERO_MV: u32 = 1650;
/// The ADC's reference (the Nucleo's VREF+ is its 3.3 V supply).
pub const VREF_MV: u32 = 3300;

// ---- Bus voltage (a divider into an ADC pin) -------------------------------------------

pub const BUS_TOP_OHM: u32 = 100_000;
pub const BUS_BOTTOM_OHM: u32 = 4_700;

// ---- Limits and the alignment ----------------------------------------------------------

/// A phase current beyond this latches OVERCURRENT (the check is on each SAMPLE's
/// readings, §5; a DRV8412's own cycle-by-cycle limit acts faster).
pub const OVERCURRENT_MA: u32 = 3_000;
/// The bus outside this range latches BUS_VOLTAGE.
pub const BUS_MIN_MV: u32 = 10_000;
pub const BUS_MAX_MV: u32 = 40_000;
/// Periods without a COMMAND before the outputs go off (17.6 ms at 20 kHz), and PLAN entries
/// kept: 360, the most one UDP datagram carries unfragmented on a 1500-byte MTU (the IP
/// stack here does not reassemble fragments); watchdog = capacity − 8, so that a plan
/// covers every period until the watchdog trips (docs/drive-protocol.md §4.7).
pub const PLAN_CAPACITY: u16 = 360;
pub const WATCHDOG_PERIODS: u16 = PLAN_CAPACITY - 8;
/// ALIGN: phase A at this current for this long, held in voltage mode from the winding's
/// resistance at the nominal bus (§4.3).
pub const ALIGN_MA: u16 = 1000;
pub const ALIGN_MS: u16 = 300;
pub const WINDING_MOHM: u32 = 1_200;
pub const NOMINAL_BUS_MV: u32 = 24_000;

// ---- Derived -------------------------------------------------------------------------

/// The CONFIG the drive announces.
pub fn config() -> Config {
    let mut c = default_config(f64::from(SAMPLE_HZ), WATCHDOG_PERIODS, PLAN_CAPACITY);
    let (ua, zero) = convert::current_scale(SHUNT_UOHM, AMP_GAIN, AMP_ZERO_MV, VREF_MV);
    c.counts_per_rev = COUNTS_PER_REV;
    c.encoder_direction = ENCODER_DIRECTION;
    c.current_ua_per_count = ua;
    c.current_zero_count = zero;
    c.bus_uv_per_count = convert::bus_scale(BUS_TOP_OHM, BUS_BOTTOM_OHM, VREF_MV);
    c.align_current_ma = ALIGN_MA;
    c.align_ms = ALIGN_MS;
    c
}

/// The limits in ADC counts, for `config`'s scales.
pub fn limits(config: &Config) -> Limits {
    Limits {
        overcurrent_counts: Some(convert::current_counts(
            OVERCURRENT_MA,
            config.current_ua_per_count,
        )),
        bus_counts: Some((
            convert::bus_counts(BUS_MIN_MV, config.bus_uv_per_count),
            convert::bus_counts(BUS_MAX_MV, config.bus_uv_per_count),
        )),
    }
}

/// Phase A's duty during ALIGN and the hold after it.
pub fn align_duty() -> i16 {
    convert::hold_duty(u32::from(ALIGN_MA), WINDING_MOHM, NOMINAL_BUS_MV)
}
