//! Two-phase PM stepper, eq. (1) of the paper (docs/paper.md) with Table I, integrated with RK4.
//!
//! Each phase is driven by an H-bridge: `Drive::Volts(v)` (duty × bus; duty 0 shorts the
//! winding) or `Drive::Off` (every switch open: the current freewheels into the bus through
//! the diodes, i.e. −sign(i)·V_bus across the winding, until it reaches zero and stays there).

#[derive(Debug, Clone, Copy)]
pub struct MotorParams {
    pub l: f64,
    pub r: f64,
    pub j: f64,
    pub km: f64,
    pub nr: f64,
    pub b: f64,
    pub load: f64,
}

impl Default for MotorParams {
    fn default() -> Self {
        MotorParams {
            l: 0.04,
            r: 14.8,
            j: 8e-5,
            km: 0.5,
            nr: 50.0,
            b: 5e-3,
            load: 0.01,
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Drive {
    Volts(f64),
    Off,
}

#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct MotorState {
    /// Rotor angle from the electrical zero (N_r θ ≡ 0 is phase A's axis), rad, unwrapped.
    pub theta: f64,
    pub omega: f64,
    pub ia: f64,
    pub ib: f64,
}

#[derive(Debug, Clone)]
pub struct Motor {
    pub p: MotorParams,
    pub s: MotorState,
}

impl Motor {
    pub fn new(p: MotorParams, theta0: f64) -> Self {
        Motor {
            p,
            s: MotorState {
                theta: theta0,
                ..MotorState::default()
            },
        }
    }

    fn deriv(&self, x: &MotorState, va: f64, vb: f64, fix_a: bool, fix_b: bool) -> MotorState {
        let p = &self.p;
        let (s, c) = (p.nr * x.theta).sin_cos();
        let torque = p.km * (-x.ia * s + x.ib * c);
        let dia = if fix_a {
            0.0
        } else {
            (va - p.r * x.ia + p.km * x.omega * s) / p.l
        };
        let dib = if fix_b {
            0.0
        } else {
            (vb - p.r * x.ib - p.km * x.omega * c) / p.l
        };
        MotorState {
            theta: x.omega,
            omega: (torque - p.b * x.omega - p.load) / p.j,
            ia: dia,
            ib: dib,
        }
    }

    /// Advances the state by `dt` in `substeps` RK4 steps with the phases driven as given.
    pub fn step(&mut self, a: Drive, b: Drive, vbus: f64, dt: f64, substeps: u32) {
        let n = substeps.max(1);
        let h = dt / n as f64;
        for _ in 0..n {
            let x = self.s;
            // outputs off: the diodes put −sign(i)·V_bus across a winding that carries a
            // current; a winding at zero current stays there (back-EMF < V_bus here)
            let phase = |d: Drive, i: f64| -> (f64, bool) {
                match d {
                    Drive::Volts(v) => (v, false),
                    Drive::Off if i == 0.0 => (0.0, true),
                    Drive::Off => (-i.signum() * vbus, false),
                }
            };
            let (va, fa) = phase(a, x.ia);
            let (vb, fb) = phase(b, x.ib);
            let k1 = self.deriv(&x, va, vb, fa, fb);
            let add = |x: &MotorState, k: &MotorState, f: f64| MotorState {
                theta: x.theta + k.theta * f,
                omega: x.omega + k.omega * f,
                ia: x.ia + k.ia * f,
                ib: x.ib + k.ib * f,
            };
            let k2 = self.deriv(&add(&x, &k1, h / 2.0), va, vb, fa, fb);
            let k3 = self.deriv(&add(&x, &k2, h / 2.0), va, vb, fa, fb);
            let k4 = self.deriv(&add(&x, &k3, h), va, vb, fa, fb);
            let mut y = MotorState {
                theta: x.theta + h / 6.0 * (k1.theta + 2.0 * k2.theta + 2.0 * k3.theta + k4.theta),
                omega: x.omega + h / 6.0 * (k1.omega + 2.0 * k2.omega + 2.0 * k3.omega + k4.omega),
                ia: x.ia + h / 6.0 * (k1.ia + 2.0 * k2.ia + 2.0 * k3.ia + k4.ia),
                ib: x.ib + h / 6.0 * (k1.ib + 2.0 * k2.ib + 2.0 * k3.ib + k4.ib),
            };
            // a freewheeling current stops at zero (the diode blocks)
            if a == Drive::Off && (x.ia == 0.0 || y.ia.signum() != x.ia.signum()) {
                y.ia = 0.0;
            }
            if b == Drive::Off && (x.ib == 0.0 || y.ib.signum() != x.ib.signum()) {
                y.ib = 0.0;
            }
            self.s = y;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn steady_current_under_constant_voltage() {
        let mut m = Motor::new(MotorParams::default(), 0.0);
        for _ in 0..20000 {
            m.step(Drive::Volts(14.8), Drive::Volts(0.0), 24.0, 50e-6, 4);
        }
        assert!((m.s.ia - 1.0).abs() < 1e-3, "{:?}", m.s);
        let e = -(0.01f64 / 0.5).asin() / 50.0;
        assert!((m.s.theta - e).abs() < 1e-6, "{:?}", m.s);
    }

    #[test]
    fn outputs_off_current_dies() {
        let mut m = Motor::new(MotorParams::default(), 0.0);
        m.s.ia = 1.0;
        m.s.ib = -0.5;
        for _ in 0..200 {
            m.step(Drive::Off, Drive::Off, 24.0, 50e-6, 4);
        }
        assert_eq!(m.s.ia, 0.0);
        assert_eq!(m.s.ib, 0.0);
    }
}
