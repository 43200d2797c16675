//! The emulated board's bridges and sensors: the motor of eq. (1) (`stepdrive-motor`) driven
//! at the core's duties and read back in drive units (encoder counts, ADC counts), with what
//! a wiring fault does to them.

use stepdrive_drive_core::{Measurement, PowerStage};
use stepdrive_drive_protocol::units::{volts_for, Scaling};
use stepdrive_motor::{bus, Disturbance, Motor, MotorState, I_A, I_B, THETA};
use stepdrive_shared::Scenario;

pub struct SimulatedStage {
    motor: Motor,
    load: Disturbance,
    x: MotorState,
    /// Periods driven, and the one the load profile's time counts from (the run's start).
    k: u64,
    load_origin: u64,
    sample_hz: f64,
    period_s: f64,
    substeps: u32,
    bus_v: f64,
    scaling: Scaling,
    /// Phase A's motor leads swapped at the terminals (fault injection): the winding
    /// carries the reverse of what the drive drives, while the drive's shunt, on its side
    /// of the leads, still reads what it drives.
    swapped_leads: bool,
}

impl SimulatedStage {
    /// The scenario's plant (its `[plant]` motor and load) behind a drive that reports in
    /// `scaling`'s units.
    pub fn new(s: &Scenario, scaling: Scaling) -> Self {
        Self {
            motor: Motor::from(&s.plant_motor()),
            load: s.disturbance(),
            x: MotorState::zeros(),
            k: 0,
            load_origin: 0,
            sample_hz: s.rates.current_loop_hz,
            period_s: s.sample_period_s(),
            substeps: s.rates.plant_substeps,
            bus_v: s.drive.bus_voltage_v,
            scaling,
            swapped_leads: false,
        }
    }

    pub fn set_swapped_leads(&mut self, swapped: bool) {
        self.swapped_leads = swapped;
    }

    /// The motor's true state, (θ, ω, i_a, i_b).
    pub fn motor_state(&self) -> MotorState {
        self.x
    }

    /// The load profile's time starts again at the current period (a run's first sample).
    pub fn restart_load_clock(&mut self) {
        self.load_origin = self.k;
    }

    pub fn rotor_teeth(&self) -> f64 {
        self.motor.n_r
    }
}

impl PowerStage for SimulatedStage {
    fn drive(&mut self, duty: (i16, i16)) {
        let v_a = volts_for(duty.0, self.bus_v);
        let requested = [
            if self.swapped_leads { -v_a } else { v_a },
            volts_for(duty.1, self.bus_v),
        ];
        // A duty is within the bus by construction; the limit is the bridges' all the same.
        let (v, _) = bus::limit(requested, self.bus_v);
        let t = (self.k - self.load_origin) as f64 / self.sample_hz;
        self.x =
            self.motor
                .integrate_loaded(&self.x, v, &self.load, t, self.period_s, self.substeps);
        self.k += 1;
    }

    fn measure(&mut self) -> Measurement {
        let i_a = match self.swapped_leads {
            true => -self.x[I_A],
            false => self.x[I_A],
        };
        Measurement {
            // A multi-turn count wraps at ±2^31 (§3.2).
            encoder_counts: self.scaling.counts(self.x[THETA]) as i32,
            adc_a: self.scaling.adc(i_a),
            adc_b: self.scaling.adc(self.x[I_B]),
            adc_bus: self.scaling.bus_adc(self.bus_v),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use stepdrive_drive_protocol::units::default_config;
    use stepdrive_plant::sim::PlantSim;
    use stepdrive_shared::messages::DriveCommand;

    /// The emulated board's motor is the plant process's, bit for bit: the same duties as
    /// voltages into both, through a load profile with every term and a restart of its
    /// clock, give the same states.
    #[test]
    fn the_stage_moves_the_motor_as_the_plant_does() {
        let s = Scenario::from_toml_str(
            "[plant.load]\ntorque_nm = 0.005\ncoulomb_nm = 0.003\ncoulomb_smoothing_rad_s = 0.2\n\
             steps = [{ at_s = 0.02, torque_nm = 0.02 }]\n\
             ramps = [{ start_s = 0.05, end_s = 0.08, torque_nm = 0.015 }]\n\
             [plant.detent]\namplitude_nm = 0.02\n",
        )
        .expect("valid");
        let scaling = Scaling::new(&default_config(s.rates.current_loop_hz, 20, 8));
        let mut stage = SimulatedStage::new(&s, scaling);
        let mut plant = PlantSim::new(&s);
        let bus = s.drive.bus_voltage_v;
        for k in 0..4000u32 {
            if k == 500 {
                stage.restart_load_clock();
                plant.restart_load_clock();
            }
            // A sweep of duties through both signs, full scale included.
            let duty = |phase: f64| {
                let x = (f64::from(k) * 0.0123 + phase).sin();
                (x * f64::from(stepdrive_drive_protocol::MAX_DUTY)) as i16
            };
            let d = (duty(0.0), duty(1.3));
            stage.drive(d);
            plant.advance(Some(&DriveCommand {
                v_a_v: volts_for(d.0, bus),
                v_b_v: volts_for(d.1, bus),
                ..Default::default()
            }));
            let (a, b) = (stage.motor_state(), plant.motor_state());
            assert!(
                a.iter()
                    .zip(b.iter())
                    .all(|(x, y)| x.to_bits() == y.to_bits()),
                "period {k}: {a:?} against {b:?}"
            );
        }
        assert!(stage.motor_state()[THETA].abs() > 0.01, "the motor moved");
    }
}
