//! The position/torque loop body, one tick per position-loop period: the axis
//! ([`crate::axis`]: its state machine, its source — a command, a stream, or the scenario's
//! profile — and its envelope) gives θ_d, ω_d, α_d; torque modulation (12) turns them into
//! the torque, within the axis's torque limit. Pure: the node supplies state and commands.

use crate::axis::{Axis, Measured};
use crate::laws::load_observer::LoadObserver;
use crate::laws::torque_modulation::TorqueModulation;
use stepdrive_shared::axis::AxisStatus;
use stepdrive_shared::messages::{
    fault_bits, setpoint_flags, state_flags, DriveState, TorqueSetpoint,
};
use stepdrive_shared::scenario::LoadCompensation;
use stepdrive_shared::trajectory::Trapezoid;
use stepdrive_shared::Scenario;

#[derive(Debug)]
pub struct PositionLoop {
    law: TorqueModulation,
    /// With `load_compensation = "observer"`: what stands in for τ_L.
    observer: Option<LoadObserver>,
    axis: Axis,
    ticks: u64,
    /// The torque the last tick asked for, N·m.
    torque: f64,
}

/// What the axis sees of a state sample.
pub fn measured(state: &DriveState) -> Measured {
    Measured {
        t: state.sample_time_s,
        theta: state.theta_rad,
        omega: state.omega_rad_s,
        device_fault: state.fault & LATCHED_FAULTS,
        setpoint_stale: state.flags & state_flags::SETPOINT_STALE != 0,
    }
}

/// The device's fault bits that turn its outputs off.
const LATCHED_FAULTS: u32 =
    fault_bits::BAD_COMMAND | fault_bits::COMMAND_TIMEOUT | fault_bits::DRIVE_FAULT | 0xFFFF_0000;

impl PositionLoop {
    /// Without a program, and unless the stack serves commands, the axis runs the
    /// scenario's profile from the first tick (the paper's experiment); otherwise it starts
    /// disabled and waits for its commands.
    pub fn new(s: &Scenario) -> Self {
        let c = &s.control;
        let tau_l = match c.load_compensation {
            LoadCompensation::Known => s.load.torque_nm,
            LoadCompensation::Observer | LoadCompensation::None => 0.0,
        };
        // A command reaches the winding one compute delay after its sample and the current
        // follows it within about 1/k_3.
        let delay_s =
            s.sample_period_s() * f64::from(s.rates.compute_delay_periods) + 1.0 / s.gains.k3_per_s;
        let observer = (c.load_compensation == LoadCompensation::Observer).then(|| {
            LoadObserver::new(
                s.motor.inertia_kg_m2,
                s.motor.viscous_friction_nm_s_per_rad,
                delay_s,
                s.observer_bandwidth_rad_s(),
            )
            .starting_at(s.load.torque_nm)
        });
        let period = 1.0 / s.rates.position_loop_hz;
        let axis = if s.runs_profile() {
            Axis::running_profile(&s.axis, period, Trapezoid::new(&s.trajectory))
        } else {
            Axis::new(&s.axis, period)
        };
        Self {
            law: TorqueModulation {
                k1: s.gains.k1,
                k2: s.gains.k2,
                j: s.motor.inertia_kg_m2,
                b: s.motor.viscous_friction_nm_s_per_rad,
                tau_l,
            },
            observer,
            axis,
            ticks: 0,
            torque: 0.0,
        }
    }

    pub fn axis(&mut self) -> &mut Axis {
        &mut self.axis
    }

    pub fn axis_ref(&self) -> &Axis {
        &self.axis
    }

    /// One tick from the state sample `state`. `publish_time_ns` is left for the caller.
    pub fn on_tick(&mut self, state: &DriveState) -> TorqueSetpoint {
        let sp = self.axis.tick(&measured(state));
        let r = sp.reference;
        let (t, omega) = (state.sample_time_s, state.omega_rad_s);
        if let Some(obs) = self.observer.as_mut() {
            self.law.tau_l = obs.update(t, omega);
        }
        let mut torque = 0.0;
        let mut torque_rate = 0.0;
        if sp.outputs_on {
            torque = self.law.torque(&r, state.theta_rad, omega);
            if sp.torque_ff != 0.0 {
                torque += sp.torque_ff;
            }
            let max = self.axis.torque_max();
            let limited = torque.abs() > max;
            if limited {
                torque = torque.clamp(-max, max);
            }
            self.axis.torque_limited(limited);
            if sp.smooth && !limited {
                // Along a jerk-limited segment (12) changes at B α_d + J jerk_d while the
                // rotor tracks: the viscous term alone, held over a 500 µs tick while
                // accelerating at 50 rad/s², left the torque 8e-5 N·m short (8e-5 rad).
                torque_rate = self.law.b * r.alpha + self.law.j * sp.jerk;
            }
        }
        if let Some(obs) = self.observer.as_mut() {
            obs.commanded(t, omega, torque);
        }
        self.torque = torque;
        let sp = TorqueSetpoint {
            seq: self.ticks,
            from_state_seq: state.seq,
            sample_time_s: state.sample_time_s,
            publish_time_ns: 0,
            theta_d_rad: r.theta,
            omega_d_rad_s: r.omega,
            alpha_d_rad_s2: r.alpha,
            torque_nm: torque,
            load_estimate_nm: self.law.tau_l,
            torque_rate_nm_s: torque_rate,
            axis: 0,
            flags: if sp.outputs_on {
                setpoint_flags::OUTPUTS_ON
            } else {
                0
            } | if sp.smooth {
                setpoint_flags::ACCELERATION_AHEAD
            } else {
                0
            } | if sp.brake_released {
                setpoint_flags::BRAKE_RELEASED
            } else {
                0
            },
            epoch: sp.epoch,
            _reserved: 0,
        };
        self.ticks += 1;
        sp
    }

    /// The axis's status after the tick on `state`.
    pub fn status(&mut self, state: &DriveState) -> AxisStatus {
        let mut st = self.axis.status(&measured(state), self.torque);
        st.tick = self.ticks.saturating_sub(1);
        st
    }
}
