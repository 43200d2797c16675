//! A simulated drive (feature `simulated-stage`): the drive core over a simulated power
//! stage, the motor of eq. (1) (`stepdrive-motor`) behind two bridges, driven at the core's
//! duties and read back in drive units (encoder counts, ADC counts), with what a wiring
//! fault does to them, and the rotor's true state that only a simulation knows. The
//! emulated drive (`stepdrive emulate-drive`) and the emulated firmware run this one.

use crate::{DriveCore, Limits, Measurement, PowerStage};
use stepdrive_drive_protocol::units::{duty_for, round, volts_for, Scaling};
use stepdrive_drive_protocol::{Config, FaultReport, Frame};
use stepdrive_motor::{bus, Disturbance, Motor, MotorState, I_A, I_B, OMEGA, THETA};

/// What the stage simulates: the motor, its load, the bus and the sampling.
#[derive(Debug, Clone)]
pub struct StageParams {
    pub motor: Motor,
    pub load: Disturbance,
    pub sample_hz: f64,
    /// RK4 sub-steps per period.
    pub substeps: u32,
    pub bus_v: f64,
}

pub struct SimulatedStage {
    p: StageParams,
    /// The sample period, s: `1 / sample_hz`, as the plant's (`Scenario::sample_period_s`).
    period_s: f64,
    x: MotorState,
    /// Periods driven, and the one the load profile's time counts from (the run's start).
    k: u64,
    load_origin: u64,
    scaling: Scaling,
    /// Phase A's motor leads swapped at the terminals (fault injection): the winding
    /// carries the reverse of what the drive drives, while the drive's shunt, on its side
    /// of the leads, still reads what it drives.
    swapped_leads: bool,
}

impl SimulatedStage {
    /// `p`'s motor at rest at θ = 0, behind a drive that reports in `scaling`'s units.
    pub fn new(p: StageParams, scaling: Scaling) -> Self {
        Self {
            period_s: 1.0 / p.sample_hz,
            p,
            x: MotorState::zeros(),
            k: 0,
            load_origin: 0,
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
        self.p.motor.n_r
    }
}

impl PowerStage for SimulatedStage {
    fn drive(&mut self, duty: (i16, i16)) {
        let v_a = volts_for(duty.0, self.p.bus_v);
        let requested = [
            if self.swapped_leads { -v_a } else { v_a },
            volts_for(duty.1, self.p.bus_v),
        ];
        // A duty is within the bus by construction; the limit is the bridges' all the same.
        let (v, _) = bus::limit(requested, self.p.bus_v);
        let t = (self.k - self.load_origin) as f64 / self.p.sample_hz;
        self.x = self.p.motor.integrate_loaded(
            &self.x,
            v,
            &self.p.load,
            t,
            self.period_s,
            self.p.substeps,
        );
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
            adc_bus: self.scaling.bus_adc(self.p.bus_v),
        }
    }
}

/// The CSV header of a truth file; each [`TruthRow`] displays as one line of it.
pub const TRUTH_HEADER: &str = "k,t_s,theta_rad,omega_rad_s,i_a_a,i_b_a";

/// The rotor's true state at one sample, k counted from the run's first (the first after
/// ENABLE).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TruthRow {
    pub k: u64,
    pub t_s: f64,
    /// From the electrical zero the alignment found, rad.
    pub theta_rad: f64,
    pub omega_rad_s: f64,
    pub i_a_a: f64,
    pub i_b_a: f64,
}

/// One line of a truth file (without its newline): what `emulate-drive`'s file and the
/// firmware's UART2 carry, and `stepdrive run` reads back.
impl core::fmt::Display for TruthRow {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(
            f,
            "{},{},{:e},{:e},{:e},{:e}",
            self.k, self.t_s, self.theta_rad, self.omega_rad_s, self.i_a_a, self.i_b_a
        )
    }
}

/// A simulated board: the drive core (every rule of the drive's side of the protocol) over
/// the simulated stage, with the hooks of fault injection.
pub struct SimulatedDrive {
    core: DriveCore,
    stage: SimulatedStage,
    /// The electrical zero nearest to where the rotor was at the run's first sample: the
    /// truth's θ counts from it.
    zero_rad: f64,
    /// The winding resistance the drive's ALIGN duty is set for (its nominal motor's).
    align_r_ohm: f64,
    /// Fault injection: its ALIGN drives phase A the wrong way.
    align_reversed: bool,
}

impl SimulatedDrive {
    /// A drive announcing `config` over `stage`'s motor, whose ALIGN sets its duty for a
    /// winding of `align_r_ohm`. Its sensors never read beyond a limit: a simulated board's
    /// faults are injected, so that runs against it stay what they were.
    pub fn new(config: Config, stage: StageParams, align_r_ohm: f64) -> Self {
        let align_duty = align_duty(align_r_ohm, config.align_current_ma, stage.bus_v);
        Self {
            stage: SimulatedStage::new(stage, Scaling::new(&config)),
            core: DriveCore::new(config, align_duty, Limits::default()),
            zero_rad: 0.0,
            align_r_ohm,
            align_reversed: false,
        }
    }

    /// The rotor's true state at the sample about to be sent with wire seq `seq`, once a
    /// run has started.
    pub fn truth(&self, seq: u32) -> Option<TruthRow> {
        let first = self.core.run_start()?;
        let k = u64::from(seq.wrapping_sub(first));
        let x = self.stage.motor_state();
        Some(TruthRow {
            k,
            t_s: k as f64 * self.stage.period_s,
            theta_rad: x[THETA] - self.zero_rad,
            omega_rad_s: x[OMEGA],
            i_a_a: x[I_A],
            i_b_a: x[I_B],
        })
    }

    /// Its ALIGN: phase A at `current_ma` for `ms` (0: it does not align), announced in
    /// CONFIG.
    pub fn set_alignment(&mut self, current_ma: u16, ms: u16) {
        let duty = align_duty(self.align_r_ohm, current_ma, self.stage.p.bus_v);
        let duty = if self.align_reversed { -duty } else { duty };
        self.core.set_alignment(current_ma, ms, duty);
    }

    /// Fault injection: an alignment that never ends (`stuck`), phase A's leads swapped at
    /// the terminals (`swapped_leads`), an ALIGN that drives phase A the wrong way
    /// (`reversed`).
    pub fn break_alignment(&mut self, stuck: bool, swapped_leads: bool, reversed: bool) {
        self.core.set_align_stuck(stuck);
        self.stage.set_swapped_leads(swapped_leads);
        if reversed != self.align_reversed {
            self.align_reversed = reversed;
            let c = self.core.config;
            let duty = -self.core.align_duty();
            self.core
                .set_alignment(c.align_current_ma, c.align_ms, duty);
        }
    }

    /// The sample at the current instant, as a frame. At a run's first sample the load
    /// profile's time and the truth's angle start from where the motor is.
    pub fn sample_frame(&mut self, now_ns: u64) -> Frame {
        if self.core.run_starts_at_next_sample() {
            self.stage.restart_load_clock();
            let pitch = core::f64::consts::TAU / self.stage.rotor_teeth();
            self.zero_rad = round(self.stage.motor_state()[THETA] / pitch) * pitch;
        }
        self.core.sample_frame(now_ns, &mut self.stage)
    }

    /// The core's period: the duties for the period starting now, driven into the motor.
    pub fn run_period(&mut self, sample_seq: u32) -> Option<FaultReport> {
        self.core.run_period(sample_seq, &mut self.stage)
    }
}

/// The drive's state, counters and frame handling are the core's: a simulated drive is a
/// drive core whose sample and period also move the simulated motor.
impl core::ops::Deref for SimulatedDrive {
    type Target = DriveCore;

    fn deref(&self) -> &DriveCore {
        &self.core
    }
}

impl core::ops::DerefMut for SimulatedDrive {
    fn deref_mut(&mut self) -> &mut DriveCore {
        &mut self.core
    }
}

/// Phase A's duty for `current_ma` in the steady state (R·I), within the bus.
fn align_duty(r_ohm: f64, current_ma: u16, bus_v: f64) -> i16 {
    let v = r_ohm * f64::from(current_ma) * 1e-3;
    duty_for(v.clamp(0.0, bus_v), bus_v).unwrap_or(0)
}
