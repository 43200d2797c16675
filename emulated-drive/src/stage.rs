//! The emulated board's bridges and sensors: the drive core's simulated stage
//! (`stepdrive_drive_core::simulated`, the one the emulated firmware drives too) over the
//! scenario's `[plant]` motor and load.

use stepdrive_drive_core::simulated::StageParams;
use stepdrive_motor::Motor;
use stepdrive_shared::Scenario;

/// The scenario's plant (its `[plant]` motor and load) at its sample rate and bus.
pub fn params(s: &Scenario) -> StageParams {
    StageParams {
        motor: Motor::from(&s.plant_motor()),
        load: s.disturbance(),
        sample_hz: s.rates.current_loop_hz,
        substeps: s.rates.plant_substeps,
        bus_v: s.drive.bus_voltage_v,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use stepdrive_drive_core::simulated::SimulatedStage;
    use stepdrive_drive_core::PowerStage;
    use stepdrive_drive_protocol::units::default_config;
    use stepdrive_drive_protocol::units::volts_for;
    use stepdrive_drive_protocol::units::Scaling;
    use stepdrive_motor::THETA;
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
        let mut stage = SimulatedStage::new(params(&s), scaling);
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
