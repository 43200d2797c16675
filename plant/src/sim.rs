//! The simulated drive: the motor of eq. (1) sampled at the current-loop rate, phase voltages
//! limited to ±V_bus, and an explicit compute delay: the command computed from sample k is
//! applied over (t_{k+d}, t_{k+d+1}]. This is the loop body; [`crate::process`] wraps it in IPC.

use crate::model::{Motor, MotorState, I_A, I_B, OMEGA, THETA};
use stepdrive_shared::messages::{fault_bits, state_flags, DriveCommand, DriveState, NONE_SEQ};
use stepdrive_shared::Scenario;

#[derive(Debug, Clone)]
pub struct PlantSim {
    motor: Motor,
    tau_l: f64,
    bus_v: f64,
    period: f64,
    substeps: u32,
    delay: u64,
    sample_hz: f64,
    x: MotorState,
    k: u64,
    applied: [f64; 2],
    applied_seq: u64,
    flags: u32,
    fault: u32,
}

impl PlantSim {
    pub fn new(scenario: &Scenario) -> Self {
        Self {
            motor: Motor::from(&scenario.motor),
            tau_l: scenario.load.torque_nm,
            bus_v: scenario.drive.bus_voltage_v,
            period: scenario.sample_period_s(),
            substeps: scenario.rates.plant_substeps,
            delay: u64::from(scenario.rates.compute_delay_periods),
            sample_hz: scenario.rates.current_loop_hz,
            x: MotorState::zeros(),
            k: 0,
            applied: [0.0; 2],
            applied_seq: NONE_SEQ,
            flags: 0,
            fault: 0,
        }
    }

    /// Index of the current sample.
    pub fn sample_index(&self) -> u64 {
        self.k
    }

    pub fn motor_state(&self) -> MotorState {
        self.x
    }

    /// The command whose voltage belongs to the next interval (t_k, t_{k+1}], or `None`
    /// while the delay line is still filling (outputs off).
    pub fn needed_command(&self) -> Option<u64> {
        self.k.checked_sub(self.delay)
    }

    /// The measured state at the current sample. `publish_time_ns` is left for the caller.
    pub fn state(&self, last: bool) -> DriveState {
        DriveState {
            seq: self.k,
            sample_time_s: self.k as f64 / self.sample_hz,
            publish_time_ns: 0,
            applied_command_seq: self.applied_seq,
            theta_rad: self.x[THETA],
            omega_rad_s: self.x[OMEGA],
            i_a_a: self.x[I_A],
            i_b_a: self.x[I_B],
            v_a_v: self.applied[0],
            v_b_v: self.applied[1],
            bus_voltage_v: self.bus_v,
            deadline_ns: 0,
            flags: self.flags | if last { state_flags::LAST } else { 0 },
            fault: self.fault,
        }
    }

    /// Latches a fault: outputs are off from the next period on, until the process restarts.
    pub fn trip(&mut self, fault_bit: u32) {
        self.fault |= fault_bit;
    }

    /// Realtime: the command for this period is missing. Holds the previous voltage (zero if
    /// faulted) over (t_k, t_{k+1}] and flags the sample.
    pub fn advance_hold(&mut self) {
        let v = if self.fault == 0 {
            self.applied
        } else {
            [0.0; 2]
        };
        let seq = if self.fault == 0 {
            self.applied_seq
        } else {
            NONE_SEQ
        };
        self.x = self
            .motor
            .integrate(&self.x, v, self.tau_l, self.period, self.substeps);
        self.applied = v;
        self.applied_seq = seq;
        self.flags = state_flags::COMMAND_HELD;
        self.k += 1;
    }

    /// Integrates over (t_k, t_{k+1}] with `command` (the one [`Self::needed_command`] named,
    /// or `None` for outputs off) and moves to sample k+1. A non-finite command turns the
    /// outputs off and latches [`fault_bits::BAD_COMMAND`]; from then on the outputs stay off.
    pub fn advance(&mut self, command: Option<&DriveCommand>) {
        self.flags = 0;
        let mut v = [0.0; 2];
        let mut seq = NONE_SEQ;
        if let Some(c) = command {
            if !(c.v_a_v.is_finite() && c.v_b_v.is_finite()) {
                self.fault |= fault_bits::BAD_COMMAND;
            }
            if self.fault == 0 {
                for (out, raw) in v.iter_mut().zip([c.v_a_v, c.v_b_v]) {
                    let clamped = raw.clamp(-self.bus_v, self.bus_v);
                    if clamped != raw {
                        self.flags |= state_flags::VOLTAGE_LIMITED;
                    }
                    *out = clamped;
                }
                seq = c.seq;
            }
        }
        self.x = self
            .motor
            .integrate(&self.x, v, self.tau_l, self.period, self.substeps);
        self.applied = v;
        self.applied_seq = seq;
        self.k += 1;
    }
}

/// What the realtime plant does for one period.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Selection {
    /// The command computed for this period arrived in time.
    Apply(DriveCommand),
    /// It did not: hold the previous voltage (a deadline miss).
    Hold,
}

/// Realtime command selection, kept apart from IPC so its rules are testable: the command
/// for a period is the one answering sample k − d; one that arrives after its period was
/// decided is discarded and counted, never applied to a later period.
#[derive(Debug, Clone, Default)]
pub struct CommandSlot {
    pending: [Option<DriveCommand>; 8],
    /// Periods whose command was missing (previous voltage held).
    pub misses: u64,
    /// Commands that arrived after their period and were dropped unapplied.
    pub late_discarded: u64,
    /// Misses in a row, for the watchdog.
    pub consecutive_misses: u32,
}

impl CommandSlot {
    /// Offers a received command. `next_needed` is the first sample whose command has not
    /// been decided yet; anything older is late.
    pub fn offer(&mut self, c: DriveCommand, next_needed: u64) {
        if c.answers_seq < next_needed {
            self.late_discarded += 1;
            return;
        }
        let slot = &mut self.pending[(c.answers_seq % 8) as usize];
        if slot.is_some_and(|old| old.answers_seq >= c.answers_seq) {
            return;
        }
        *slot = Some(c);
    }

    /// Decides the period whose command answers sample `needed`.
    pub fn take(&mut self, needed: u64) -> Selection {
        let slot = &mut self.pending[(needed % 8) as usize];
        match slot.take() {
            Some(c) if c.answers_seq == needed => {
                self.consecutive_misses = 0;
                Selection::Apply(c)
            }
            other => {
                // A newer command parked in this slot stays for its own period.
                if other.is_some_and(|c| c.answers_seq > needed) {
                    *slot = other;
                }
                self.misses += 1;
                self.consecutive_misses = self.consecutive_misses.saturating_add(1);
                Selection::Hold
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cmd(seq: u64, va: f64, vb: f64) -> DriveCommand {
        DriveCommand {
            seq,
            answers_seq: seq,
            v_a_v: va,
            v_b_v: vb,
            ..Default::default()
        }
    }

    #[test]
    fn delay_line_and_bus_limit() {
        let s = Scenario::default();
        let mut p = PlantSim::new(&s);
        // One period of delay: nothing to apply over the first interval.
        assert_eq!(p.needed_command(), None);
        p.advance(None);
        assert_eq!(p.state(false).applied_command_seq, NONE_SEQ);
        assert_eq!(p.needed_command(), Some(0));
        p.advance(Some(&cmd(0, 100.0, -3.0)));
        let st = p.state(false);
        assert_eq!(st.applied_command_seq, 0);
        assert_eq!((st.v_a_v, st.v_b_v), (24.0, -3.0));
        assert_ne!(st.flags & state_flags::VOLTAGE_LIMITED, 0);
        assert_eq!(st.seq, 2);
    }

    /// A late command is held and counted, never applied to the wrong period.
    #[test]
    fn late_command_is_held_counted_and_never_applied() {
        let s = Scenario::default();
        let mut p = PlantSim::new(&s);
        let mut slot = CommandSlot::default();
        p.advance(None); // period (0,1]: delay line filling
                         // Period (1,2] needs cmd 0: it arrived in time.
        slot.offer(cmd(0, 1.0, 2.0), 0);
        let Selection::Apply(c) = slot.take(0) else {
            panic!("cmd 0 was on time")
        };
        p.advance(Some(&c));
        assert_eq!(p.state(false).applied_command_seq, 0);
        // Period (2,3] needs cmd 1: missing, so cmd 0's voltage is held and a miss counted.
        assert_eq!(slot.take(1), Selection::Hold);
        p.advance_hold();
        let st = p.state(false);
        assert_eq!((st.v_a_v, st.v_b_v, st.applied_command_seq), (1.0, 2.0, 0));
        assert_ne!(st.flags & state_flags::COMMAND_HELD, 0);
        assert_eq!(slot.misses, 1);
        // cmd 1 shows up now, late: discarded. cmd 2 is on time and is what period (3,4] gets.
        slot.offer(cmd(1, 9.0, 9.0), 2);
        slot.offer(cmd(2, 3.0, 4.0), 2);
        assert_eq!(slot.late_discarded, 1);
        let Selection::Apply(c) = slot.take(2) else {
            panic!("cmd 2 was on time")
        };
        assert_eq!(c.answers_seq, 2);
        p.advance(Some(&c));
        let st = p.state(false);
        assert_eq!((st.v_a_v, st.v_b_v, st.applied_command_seq), (3.0, 4.0, 2));
        assert_eq!(slot.consecutive_misses, 0);
        // Commands that arrive early wait for their own period.
        slot.offer(cmd(4, 5.0, 5.0), 3);
        assert_eq!(slot.take(3), Selection::Hold);
        assert!(matches!(slot.take(4), Selection::Apply(c) if c.answers_seq == 4));
    }

    #[test]
    fn tripped_plant_holds_zero() {
        let mut p = PlantSim::new(&Scenario::default());
        p.advance(None);
        p.advance(Some(&cmd(0, 5.0, 5.0)));
        p.trip(fault_bits::COMMAND_TIMEOUT);
        p.advance_hold();
        let st = p.state(false);
        assert_eq!((st.v_a_v, st.v_b_v), (0.0, 0.0));
        assert_eq!(st.fault, fault_bits::COMMAND_TIMEOUT);
        p.advance(Some(&cmd(2, 5.0, 5.0)));
        assert_eq!(p.state(false).v_a_v, 0.0);
    }

    #[test]
    fn non_finite_command_turns_outputs_off_and_latches() {
        let mut p = PlantSim::new(&Scenario::default());
        p.advance(None);
        p.advance(Some(&cmd(0, f64::NAN, 1.0)));
        let st = p.state(false);
        assert_eq!((st.v_a_v, st.v_b_v), (0.0, 0.0));
        assert_ne!(st.fault & fault_bits::BAD_COMMAND, 0);
        // Latched: a good command afterwards is not applied.
        p.advance(Some(&cmd(1, 5.0, 5.0)));
        let st = p.state(false);
        assert_eq!((st.v_a_v, st.v_b_v), (0.0, 0.0));
        assert_ne!(st.fault, 0);
    }
}
