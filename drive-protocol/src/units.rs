//! Drive units and their calibration, as a CONFIG defines them: encoder counts, ADC counts,
//! duties. Used by the simulated drive (SI → counts: the emulated drive, the firmware in
//! QEMU) and by the bridge (counts → SI).

use crate::{Config, MAX_DUTY};
use core::f64::consts::TAU;

/// `x.round()`: the host's, or libm's where there is no `std` (a firmware build); both
/// round exactly, half away from zero, so the two agree bit for bit.
#[cfg(feature = "std")]
pub fn round(x: f64) -> f64 {
    x.round()
}

#[cfg(not(feature = "std"))]
pub fn round(x: f64) -> f64 {
    libm::round(x)
}

/// The emulated drive's scaling (a real drive reports its own in CONFIG).
pub fn default_config(sample_rate_hz: f64, watchdog_periods: u16, plan_capacity: u16) -> Config {
    Config {
        sample_rate_hz: round(sample_rate_hz) as u32,
        // A 20-bit encoder: 6 µrad per count, far below the errors being measured.
        counts_per_rev: 1 << 20,
        // 16-bit current ADC, ±3.28 A.
        current_ua_per_count: 100,
        current_zero_count: 32768,
        // 10 mV per count.
        bus_uv_per_count: 10_000,
        watchdog_periods,
        encoder_direction: 1,
        plan_capacity,
        // 1 A holds the rotor at 25 N·m/rad (Table I motor); settled well within 300 ms.
        align_current_ma: 1000,
        align_ms: 300,
        reserved: [0; 1],
    }
}

/// Conversions between drive units and SI for one drive's [`Config`].
#[derive(Debug, Clone, Copy)]
pub struct Scaling {
    rad_per_count: f64,
    amp_per_count: f64,
    zero: f64,
    volt_per_count: f64,
}

impl Scaling {
    pub fn new(c: &Config) -> Self {
        let dir = if c.encoder_direction < 0 { -1.0 } else { 1.0 };
        Self {
            rad_per_count: dir * TAU / f64::from(c.counts_per_rev.max(1)),
            amp_per_count: f64::from(c.current_ua_per_count) * 1e-6,
            zero: f64::from(c.current_zero_count),
            volt_per_count: f64::from(c.bus_uv_per_count) * 1e-6,
        }
    }

    pub fn theta(&self, counts: i64) -> f64 {
        counts as f64 * self.rad_per_count
    }
    pub fn counts(&self, theta: f64) -> i64 {
        round(theta / self.rad_per_count) as i64
    }
    pub fn amps(&self, adc: u16) -> f64 {
        (f64::from(adc) - self.zero) * self.amp_per_count
    }
    pub fn adc(&self, amps: f64) -> u16 {
        round(amps / self.amp_per_count + self.zero).clamp(0.0, 65535.0) as u16
    }
    pub fn bus_volts(&self, adc: u16) -> f64 {
        f64::from(adc) * self.volt_per_count
    }
    pub fn bus_adc(&self, volts: f64) -> u16 {
        round(volts / self.volt_per_count).clamp(0.0, 65535.0) as u16
    }
}

/// Duty for phase voltage `v` on a bus of `bus` volts, or `None` if `v` is not finite or
/// needs more than the bus can give (never sent to a drive).
pub fn duty_for(v: f64, bus: f64) -> Option<i16> {
    if !v.is_finite() || !bus.is_finite() || bus <= 0.0 || v.abs() > bus {
        return None;
    }
    Some(round_half_away(v / bus * f64::from(MAX_DUTY)))
}

/// `x.round() as i16` for |x| ≤ [`MAX_DUTY`], without libm's `round`: a PLAN converts
/// 2000 voltages, and the call was a twentieth of the bridge's time. Exact: the truncation
/// and the fraction left are both exact below 2^31.
fn round_half_away(x: f64) -> i16 {
    let t = x as i32;
    let f = x - f64::from(t);
    (t + i32::from(f >= 0.5) - i32::from(f <= -0.5)) as i16
}

/// Phase voltage of `duty` on a bus of `bus` volts.
pub fn volts_for(duty: i16, bus: f64) -> f64 {
    f64::from(duty.clamp(-MAX_DUTY, MAX_DUTY)) / f64::from(MAX_DUTY) * bus
}

#[cfg(test)]
mod tests {
    use super::*;

    proptest::proptest! {
        /// The fast rounding is `f64::round` over the whole duty range, halves included.
        #[test]
        fn duties_round_half_away_from_zero(x in -32767.0f64..=32767.0, half in -32767i32..=32766) {
            proptest::prop_assert_eq!(round_half_away(x), x.round() as i16);
            let h = f64::from(half) + 0.5;
            proptest::prop_assert_eq!(round_half_away(h), h.round() as i16);
            proptest::prop_assert_eq!(round_half_away(-h), (-h).round() as i16);
        }
    }

    #[test]
    fn unit_round_trips() {
        let s = Scaling::new(&default_config(20_000.0, 200, 200));
        for theta in [-3.0, 0.0, 1e-3, 19.7] {
            assert!((s.theta(s.counts(theta)) - theta).abs() <= TAU / f64::from(1u32 << 20));
        }
        for amps in [-0.44, 0.0, 0.151] {
            assert!((s.amps(s.adc(amps)) - amps).abs() <= 50e-6);
        }
        assert!((s.bus_volts(s.bus_adc(24.0)) - 24.0).abs() < 0.006);
        assert_eq!(duty_for(12.0, 24.0), Some(16384));
        assert_eq!(duty_for(f64::NAN, 24.0), None);
        assert_eq!(duty_for(25.0, 24.0), None);
        assert!((volts_for(16384, 24.0) - 12.0).abs() < 1e-3);
    }
}
