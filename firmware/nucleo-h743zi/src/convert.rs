//! The board's pure conversions: duties to timer compare values, the 16-bit encoder timer
//! to the protocol's 32-bit count, the analog front end's gains to CONFIG's scale factors
//! and the drive's limits in ADC counts. Nothing here touches hardware or any crate but
//! `core`, so the host's compiler tests it as it is (`build` runs
//! `rustc --test src/convert.rs` before the firmware build).

/// The protocol's full-scale duty (drive-protocol's `MAX_DUTY`; ±this is ±100 % of the bus).
pub const MAX_DUTY: i32 = 32767;

/// The two legs' compare values for a full bridge at `duty` (−MAX_DUTY … MAX_DUTY), on a
/// centre-aligned timer counting 0 … `arr` in PWM mode 1 (a leg is high while the counter
/// is below its compare value).
///
/// Both legs are compared with the same carrier at +d/2 and −d/2 about half the period
/// (three-level modulation): leg 1 is high for (1 + d)/2 of the period, leg 2 for
/// (1 − d)/2, so the winding sees d × V_bus on average, its ripple at twice the PWM rate;
/// duty 0 has both legs switching together (0 V across the winding: shorted, as the
/// protocol says duty 0 is, §4.1). i16::MIN (never applied by the drive core) counts as
/// −MAX_DUTY.
pub fn bridge_compares(duty: i16, arr: u16) -> (u16, u16) {
    let d = i32::from(duty).clamp(-MAX_DUTY, MAX_DUTY);
    let arr = i32::from(arr);
    // round(arr × (MAX + d) / (2 MAX)), in integers: exact and symmetric about arr/2.
    let leg = |d: i32| ((arr * (MAX_DUTY + d) + MAX_DUTY) / (2 * MAX_DUTY)) as u16;
    (leg(d), leg(-d))
}

/// Whether the bridges' drivers are enabled: the drive core's outputs are on, or it drives
/// duties while they are off (its ALIGN and the aligned rotor's hold drive phase A before
/// an ENABLE). Otherwise every switch is open (high impedance), which is what the protocol
/// calls outputs off (§4.1), different from duty 0.
pub fn bridges_enabled(duty: (i16, i16), outputs_on: bool) -> bool {
    outputs_on || duty != (0, 0)
}

/// The encoder timer's 16-bit count extended to the protocol's 32-bit multi-turn count
/// (which wraps at ±2^31; the host unwraps it by differences, §4.1).
///
/// Correct as long as the rotor turns fewer than 32768 counts between two readings (one
/// sample period): 6.6e8 counts/s at 20 kHz, far beyond any encoder here.
#[derive(Debug, Clone, Copy, Default)]
pub struct EncoderCount {
    last: u16,
    count: i32,
}

impl EncoderCount {
    /// Counting from the timer's reading `raw` now, as count 0.
    pub fn new(raw: u16) -> Self {
        Self {
            last: raw,
            count: 0,
        }
    }

    /// The count at the timer's reading `raw`.
    pub fn update(&mut self, raw: u16) -> i32 {
        // The difference as a signed 16-bit step: the shorter way round the timer's wrap.
        let step = raw.wrapping_sub(self.last) as i16;
        self.last = raw;
        self.count = self.count.wrapping_add(i32::from(step));
        self.count
    }
}

/// The current sense front end: a shunt of `shunt_uohm` µΩ into an amplifier of gain
/// `gain` (V/V) whose output sits at `zero_mv` at 0 A, into a `bits`-bit ADC of reference
/// `vref_mv`. Returns CONFIG's `current_ua_per_count` (rounded) and
/// `current_zero_count`, as left-aligned 16-bit counts (the drive reports 16-bit
/// readings whatever the ADC's resolution).
pub fn current_scale(shunt_uohm: u32, gain: u32, zero_mv: u32, vref_mv: u32) -> (u32, u16) {
    // One count is vref / 65536 V at the ADC, vref / 65536 / gain V across the shunt,
    // vref / 65536 / gain / shunt A: in µA, vref_mv × 1e3 / 65536 / gain / (shunt_uohm × 1e-6).
    let num = u64::from(vref_mv) * 1_000_000_000;
    let den = 65_536 * u64::from(gain) * u64::from(shunt_uohm);
    let ua = ((num + den / 2) / den) as u32;
    let zero = (u64::from(zero_mv) * 65_536 + u64::from(vref_mv) / 2) / u64::from(vref_mv);
    (ua, zero.min(65_535) as u16)
}

/// The bus divider: `top_ohm` from the bus to the ADC pin, `bottom_ohm` from it to ground,
/// into the ADC of reference `vref_mv`. Returns CONFIG's `bus_uv_per_count` (rounded) for
/// 16-bit counts.
pub fn bus_scale(top_ohm: u32, bottom_ohm: u32, vref_mv: u32) -> u32 {
    let num = u64::from(vref_mv) * 1_000 * (u64::from(top_ohm) + u64::from(bottom_ohm));
    let den = 65_536 * u64::from(bottom_ohm);
    ((num + den / 2) / den) as u32
}

/// `ma` milliamps as ADC counts off the zero, at `ua_per_count` (rounded down: a limit in
/// counts never above the one asked for).
pub fn current_counts(ma: u32, ua_per_count: u32) -> u16 {
    (u64::from(ma) * 1000 / u64::from(ua_per_count.max(1))).min(65_535) as u16
}

/// `mv` millivolts of bus as ADC counts at `uv_per_count` (rounded down).
pub fn bus_counts(mv: u32, uv_per_count: u32) -> u16 {
    (u64::from(mv) * 1000 / u64::from(uv_per_count.max(1))).min(65_535) as u16
}

/// Phase A's duty that holds `ma` through a winding of `mohm` on a bus of `bus_mv`
/// (voltage mode: round(R × I / V_bus × MAX_DUTY), docs/drive-protocol.md §4.3), at most
/// MAX_DUTY.
pub fn hold_duty(ma: u32, mohm: u32, bus_mv: u32) -> i16 {
    let v_uv = u64::from(ma) * u64::from(mohm); // mA × mΩ = µV
    let bus_uv = u64::from(bus_mv.max(1)) * 1000;
    let d = (v_uv * MAX_DUTY as u64 + bus_uv / 2) / bus_uv;
    d.min(MAX_DUTY as u64) as i16
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn duty_zero_is_both_legs_at_half() {
        assert_eq!(bridge_compares(0, 6000), (3000, 3000));
    }

    #[test]
    fn full_duty_is_one_leg_always_high_and_the_other_always_low() {
        assert_eq!(bridge_compares(32767, 6000), (6000, 0));
        assert_eq!(bridge_compares(-32767, 6000), (0, 6000));
        // The value the core never applies is clamped, not wrapped.
        assert_eq!(bridge_compares(i16::MIN, 6000), (0, 6000));
    }

    #[test]
    fn legs_are_symmetric_and_their_difference_is_the_duty() {
        let arr = 6000u16;
        for duty in (-32767i32..=32767).step_by(97) {
            let d = duty as i16;
            let (a, b) = bridge_compares(d, arr);
            let (na, nb) = bridge_compares(-d, arr);
            assert_eq!((a, b), (nb, na), "duty {d}");
            // The winding's mean voltage (a − b)/arr of the bus, within one count of d.
            let want = f64::from(duty) / 32767.0 * f64::from(arr);
            let got = f64::from(a) - f64::from(b);
            assert!((got - want).abs() <= 1.0, "duty {d}: {got} vs {want}");
            assert!(a <= arr && b <= arr);
        }
    }

    #[test]
    fn bridges_are_enabled_when_driven_or_on() {
        assert!(!bridges_enabled((0, 0), false));
        assert!(bridges_enabled((0, 0), true));
        // Aligning or holding: duties before an ENABLE.
        assert!(bridges_enabled((1200, 0), false));
    }

    #[test]
    fn encoder_counts_through_the_timer_wrap_both_ways() {
        let mut e = EncoderCount::new(65_530);
        assert_eq!(e.update(65_535), 5);
        assert_eq!(e.update(4), 10);
        assert_eq!(e.update(65_534), 4);
        assert_eq!(e.update(65_534), 4);
        // A long way forward, in steps below half the timer's range.
        let mut raw = 65_534u16;
        for _ in 0..10 {
            raw = raw.wrapping_add(30_000);
            e.update(raw);
        }
        assert_eq!(e.update(raw), 300_004);
        for _ in 0..20 {
            raw = raw.wrapping_sub(30_000);
            e.update(raw);
        }
        assert_eq!(e.update(raw), -299_996);
    }

    #[test]
    fn encoder_count_wraps_as_the_protocol_says() {
        let mut e = EncoderCount {
            last: 0,
            count: i32::MAX,
        };
        assert_eq!(e.update(1), i32::MIN);
    }

    #[test]
    fn the_default_front_end_scales() {
        // 10 mΩ shunt, INA240A2 (gain 50), reference at half of 3.3 V: 0.5 V/A at the
        // pin, 3.3 V / 65536 per count = 50.35 µV = 100.7 µA.
        let (ua, zero) = current_scale(10_000, 50, 1650, 3300);
        assert_eq!((ua, zero), (101, 32768));
        // ±3.3 A full scale: 32768 counts either side.
        assert_eq!(current_counts(3000, ua), 29_702);
        // 100 kΩ over 4.7 kΩ: 3.3 V at the pin is 73.5 V of bus, 1121 µV a count.
        let uv = bus_scale(100_000, 4_700, 3300);
        assert_eq!(uv, 1122);
        assert_eq!(bus_counts(24_000, uv), 21_390);
    }

    #[test]
    fn hold_duty_is_r_i_over_the_bus() {
        // 1 A through 1.2 Ω on 24 V: 1.2 / 24 of full scale.
        assert_eq!(hold_duty(1000, 1200, 24_000), 1638);
        assert_eq!(hold_duty(100_000, 100_000, 1000), 32767);
    }
}
