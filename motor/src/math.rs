//! The transcendental functions the model needs: the host's (`std`), so that the plant's
//! figures stay bit for bit what they were, or libm's on a target without `std`.

#[cfg(feature = "std")]
pub fn sin_cos(x: f64) -> (f64, f64) {
    x.sin_cos()
}

#[cfg(not(feature = "std"))]
pub fn sin_cos(x: f64) -> (f64, f64) {
    libm::sincos(x)
}

#[cfg(feature = "std")]
pub fn sin(x: f64) -> f64 {
    x.sin()
}

#[cfg(not(feature = "std"))]
pub fn sin(x: f64) -> f64 {
    libm::sin(x)
}

#[cfg(feature = "std")]
pub fn tanh(x: f64) -> f64 {
    x.tanh()
}

#[cfg(not(feature = "std"))]
pub fn tanh(x: f64) -> f64 {
    libm::tanh(x)
}

#[cfg(test)]
mod tests {
    /// libm's functions (a firmware's) agree with the host's to within a few ulps over the
    /// angles and speeds the model meets.
    #[test]
    fn libm_agrees_with_the_host() {
        for k in -2000..=2000 {
            let x = f64::from(k) * 0.0371;
            let (s, c) = libm::sincos(x);
            assert!((s - x.sin()).abs() <= 4.0 * f64::EPSILON, "sin {x}");
            assert!((c - x.cos()).abs() <= 4.0 * f64::EPSILON, "cos {x}");
            assert!(
                (libm::tanh(x) - x.tanh()).abs() <= 4.0 * f64::EPSILON,
                "tanh {x}"
            );
        }
    }
}
