//! The bridges' supply: a phase voltage beyond ±V_bus is not available.

/// `requested` limited to ±`bus_v`, and whether either phase was limited.
pub fn limit(requested: [f64; 2], bus_v: f64) -> ([f64; 2], bool) {
    let mut limited = false;
    let v = requested.map(|raw| {
        let clamped = raw.clamp(-bus_v, bus_v);
        limited |= clamped != raw;
        clamped
    });
    (v, limited)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn beyond_the_bus_is_clamped_and_said() {
        assert_eq!(limit([3.0, -24.0], 24.0), ([3.0, -24.0], false));
        assert_eq!(limit([30.0, -1.0], 24.0), ([24.0, -1.0], true));
        assert_eq!(limit([0.5, -25.0], 24.0), ([0.5, -24.0], true));
    }
}
