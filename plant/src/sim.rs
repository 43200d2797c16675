//! The simulated drive: the motor of eq. (1) sampled at the current-loop rate, phase voltages
//! limited to ±V_bus, and an explicit compute delay: the command computed from sample k is
//! applied over (t_{k+d}, t_{k+d+1}]. This is the plant's logic; [`crate::node`] runs it.

use stepdrive_motor::{bus, Disturbance, Motor, MotorState, I_A, I_B, OMEGA, THETA};
use stepdrive_runtime::cycle::MissRuns;
use stepdrive_shared::messages::{
    command_flags, fault_bits, state_flags, DriveCommand, DrivePlan, DriveState, NONE_SEQ,
};
use stepdrive_shared::stats::StatsReport;
use stepdrive_shared::Scenario;

#[derive(Debug, Clone)]
pub struct PlantSim {
    motor: Motor,
    load: Disturbance,
    bus_v: f64,
    period: f64,
    substeps: u32,
    delay: u64,
    sample_hz: f64,
    x: MotorState,
    k: u64,
    /// The sample the load profile's time counts from.
    load_origin: u64,
    applied: [f64; 2],
    applied_seq: u64,
    flags: u32,
    /// The last command came from a current loop stopping the motor on its own (stale
    /// setpoints); sticky until a command without it.
    stale: bool,
    fault: u32,
    /// The holding brake's torque, N·m, when one is fitted ([`Self::fit_brake`]), and
    /// whether the last command released it. Applied while a fault holds the outputs off.
    brake_nm: Option<f64>,
    brake_released: bool,
}

impl PlantSim {
    pub fn new(scenario: &Scenario) -> Self {
        Self {
            motor: Motor::from(&scenario.plant_motor()),
            load: scenario.disturbance(),
            bus_v: scenario.drive.bus_voltage_v,
            period: scenario.sample_period_s(),
            substeps: scenario.rates.plant_substeps,
            delay: u64::from(scenario.rates.compute_delay_periods),
            sample_hz: scenario.rates.current_loop_hz,
            x: MotorState::zeros(),
            k: 0,
            load_origin: 0,
            applied: [0.0; 2],
            applied_seq: NONE_SEQ,
            flags: 0,
            stale: false,
            fault: 0,
            brake_nm: None,
            brake_released: false,
        }
    }

    /// Fits the motor's holding brake, applied until a command releases it (the simulated
    /// plant of a commanded stack; a drive's motor is the drive's business).
    pub fn fit_brake(&mut self, holding_nm: f64) {
        self.brake_nm = (holding_nm > 0.0).then_some(holding_nm);
        self.brake_released = false;
    }

    /// Index of the current sample.
    pub fn sample_index(&self) -> u64 {
        self.k
    }

    pub fn motor_state(&self) -> MotorState {
        self.x
    }

    /// The rotor brought to rest at its nearest electrical zero (N_r θ a multiple of 2π),
    /// currents zero: where an alignment with phase A energized leaves it.
    pub fn align(&mut self) {
        let pitch = std::f64::consts::TAU / self.motor.n_r;
        self.x[THETA] = (self.x[THETA] / pitch).round() * pitch;
        self.x[OMEGA] = 0.0;
        self.x[I_A] = 0.0;
        self.x[I_B] = 0.0;
    }

    /// The load profile's time starts again at the current sample (a drive's ENABLE: its
    /// samples before that were not the run's).
    pub fn restart_load_clock(&mut self) {
        self.load_origin = self.k;
    }

    /// Clears the latched faults: the outputs follow the commands again from the next
    /// period.
    pub fn clear_faults(&mut self) {
        self.fault = 0;
    }

    /// The latched fault bits; zero when healthy.
    pub fn fault(&self) -> u32 {
        self.fault
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
            flags: self.flags
                | if last { state_flags::LAST } else { 0 }
                | if self.stale {
                    state_flags::SETPOINT_STALE
                } else {
                    0
                },
            fault: self.fault,
        }
    }

    /// Latches a fault: outputs are off from the next period on, until the process restarts.
    pub fn trip(&mut self, fault_bit: u32) {
        self.fault |= fault_bit;
    }

    /// Realtime: the command for this period is missing. Applies `planned` (the freshest
    /// plan's entry for this period, with the sequence number of the command it continues)
    /// if there is one, else holds the previous voltage; zero if faulted. Flags the sample
    /// either way.
    pub fn advance_missing(&mut self, planned: Option<([f64; 2], u64)>) {
        let (v, seq, flags) = match planned {
            Some((v, seq)) => (
                v,
                seq,
                state_flags::COMMAND_HELD | state_flags::COMMAND_PLANNED,
            ),
            None => (self.applied, self.applied_seq, state_flags::COMMAND_HELD),
        };
        self.apply(v, seq);
        self.flags |= flags;
    }

    /// Realtime: decides the period starting now by `slot`'s rules and integrates it. After
    /// `watchdog_periods` misses in a row the outputs go off and [`fault_bits::COMMAND_TIMEOUT`]
    /// latches; returns true in the period where that happens.
    pub fn advance_realtime(&mut self, slot: &mut CommandSlot, watchdog_periods: u32) -> bool {
        let Some(needed) = self.needed_command() else {
            self.advance(None);
            return false;
        };
        match slot.take(needed) {
            Selection::Apply(c) => {
                self.advance(Some(&c));
                false
            }
            Selection::Missing(planned) => {
                let timed_out = slot.runs.current >= watchdog_periods;
                let trips = timed_out && self.fault & fault_bits::COMMAND_TIMEOUT == 0;
                if timed_out {
                    self.trip(fault_bits::COMMAND_TIMEOUT);
                }
                self.advance_missing(planned);
                trips
            }
        }
    }

    /// Integrates over (t_k, t_{k+1}] with `command` (the one [`Self::needed_command`] named,
    /// or `None` for outputs off) and moves to sample k+1. A non-finite command turns the
    /// outputs off and latches [`fault_bits::BAD_COMMAND`]; from then on the outputs stay off.
    pub fn advance(&mut self, command: Option<&DriveCommand>) {
        match command {
            Some(c) => {
                self.stale = c.flags & command_flags::SETPOINT_STALE != 0;
                self.brake_released = c.flags & command_flags::BRAKE_RELEASED != 0;
                self.apply([c.v_a_v, c.v_b_v], c.seq)
            }
            None => self.apply([0.0; 2], NONE_SEQ),
        }
    }

    /// The one place a voltage reaches the motor: non-finite latches a fault, a fault turns
    /// the outputs off, anything beyond ±V_bus is clamped and flagged.
    fn apply(&mut self, requested: [f64; 2], seq: u64) {
        self.flags = 0;
        if !requested.iter().all(|v| v.is_finite()) {
            self.fault |= fault_bits::BAD_COMMAND;
        }
        let mut v = [0.0; 2];
        let mut seq = seq;
        if self.fault == 0 {
            let limited;
            (v, limited) = bus::limit(requested, self.bus_v);
            if limited {
                self.flags |= state_flags::VOLTAGE_LIMITED;
            }
        } else {
            seq = NONE_SEQ;
        }
        let t = (self.k - self.load_origin) as f64 / self.sample_hz;
        let braking = self
            .brake_nm
            .filter(|_| !self.brake_released || self.fault != 0);
        self.x = match braking {
            Some(holding) => self.motor.integrate_braked(
                &self.x,
                v,
                &self.load,
                t,
                self.period,
                self.substeps,
                holding,
            ),
            None => {
                self.motor
                    .integrate_loaded(&self.x, v, &self.load, t, self.period, self.substeps)
            }
        };
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
    /// It did not (a deadline miss): apply the freshest plan's entry for this period
    /// (voltage, the sequence number of the command that plan continues), or hold the
    /// previous voltage if no plan covers the period.
    Missing(Option<([f64; 2], u64)>),
}

/// Realtime command selection, kept apart from IPC so its rules are testable: the command
/// for period p is the one answering sample p − d; one that arrives after its period was
/// decided is discarded and counted, never applied to a later period. When the command for
/// a period is missing, the freshest plan received may cover it; every plan entry names
/// its period, so none lands on another one.
#[derive(Debug, Clone)]
pub struct CommandSlot {
    delay: u64,
    pending: [Option<DriveCommand>; 8],
    /// The plan continuing the newest command (~8 KB, kept in place).
    freshest: DrivePlan,
    /// Periods whose command was missing.
    pub misses: u64,
    /// Of those, periods covered by a plan entry (the rest held the previous voltage).
    pub planned: u64,
    /// Commands that arrived after their period and were dropped unapplied.
    pub late_discarded: u64,
    /// Misses in a row (the watchdog's count) and their runs.
    pub runs: MissRuns,
    /// The newest sample a command offered in time answers.
    newest: Option<u64>,
}

impl CommandSlot {
    /// `delay`: the compute delay d, periods.
    pub fn new(delay: u64) -> Self {
        Self {
            delay,
            pending: [None; 8],
            freshest: DrivePlan::default(),
            misses: 0,
            planned: 0,
            late_discarded: 0,
            runs: MissRuns::default(),
            newest: None,
        }
    }

    /// Puts the slot's counters into a stats report (its misses are the plant's).
    pub fn copy_counters(&self, stats: &mut StatsReport) {
        stats.misses = self.misses;
        stats.planned = self.planned;
        stats.late_discarded = self.late_discarded;
        self.runs.copy_to(stats);
    }

    /// Offers a received command. `next_needed` is the first sample whose command has not
    /// been decided yet; anything older is late.
    pub fn offer(&mut self, c: DriveCommand, next_needed: u64) {
        if c.answers_seq < next_needed {
            self.late_discarded += 1;
            return;
        }
        self.newest = self.newest.max(Some(c.answers_seq));
        let slot = &mut self.pending[(c.answers_seq % 8) as usize];
        if slot.is_some_and(|old| old.answers_seq >= c.answers_seq) {
            return;
        }
        *slot = Some(c);
    }

    /// The newest sample a command offered in time answers: the stream has reached it.
    pub fn newest(&self) -> Option<u64> {
        self.newest
    }

    /// Offers a received plan; the one continuing the newest command is kept.
    pub fn offer_plan(&mut self, plan: &DrivePlan) {
        if self.freshest.len == 0 || plan.answers_seq > self.freshest.answers_seq {
            self.freshest = *plan;
        }
    }

    /// Decides the period whose command answers sample `needed`.
    pub fn take(&mut self, needed: u64) -> Selection {
        let slot = &mut self.pending[(needed % 8) as usize];
        match slot.take() {
            Some(c) if c.answers_seq == needed => {
                self.runs.record(false);
                Selection::Apply(c)
            }
            other => {
                // A newer command parked in this slot stays for its own period.
                if other.is_some_and(|c| c.answers_seq > needed) {
                    *slot = other;
                }
                self.misses += 1;
                self.runs.record(true);
                let planned = self
                    .freshest
                    .voltage_for(needed + self.delay, self.delay)
                    .map(|v| (v, self.freshest.command_seq));
                self.planned += u64::from(planned.is_some());
                Selection::Missing(planned)
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
        let mut slot = CommandSlot::new(1);
        p.advance(None); // period (0,1]: delay line filling
                         // Period (1,2] needs cmd 0: it arrived in time.
        slot.offer(cmd(0, 1.0, 2.0), 0);
        let Selection::Apply(c) = slot.take(0) else {
            panic!("cmd 0 was on time")
        };
        p.advance(Some(&c));
        assert_eq!(p.state(false).applied_command_seq, 0);
        // Period (2,3] needs cmd 1: missing, so cmd 0's voltage is held and a miss counted.
        assert_eq!(slot.take(1), Selection::Missing(None));
        p.advance_missing(None);
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
        assert_eq!(slot.runs.current, 0);
        // Commands that arrive early wait for their own period.
        slot.offer(cmd(4, 5.0, 5.0), 3);
        assert_eq!(slot.take(3), Selection::Missing(None));
        assert!(matches!(slot.take(4), Selection::Apply(c) if c.answers_seq == 4));
    }

    fn plan(answers: u64, entries: &[f32]) -> DrivePlan {
        let mut p = DrivePlan {
            command_seq: answers,
            answers_seq: answers,
            len: entries.len() as u32,
            ..Default::default()
        };
        for (slot, &x) in p.v.iter_mut().zip(entries) {
            *slot = [x, -x];
        }
        p
    }

    /// On a miss the plant applies the freshest plan's entry for that very period; a late
    /// command's own voltage never; past the plan it holds the last voltage.
    #[test]
    fn misses_follow_the_freshest_plan_entry_for_their_own_period() {
        let mut p = PlantSim::new(&Scenario::default());
        let mut slot = CommandSlot::new(1);
        p.advance(None);
        // cmd 0 answers sample 0: period 1; its plan covers periods 2, 3, 4.
        slot.offer(cmd(0, 1.0, -1.0), 0);
        slot.offer_plan(&plan(0, &[2.0, 3.0, 4.0]));
        let Selection::Apply(c) = slot.take(0) else {
            panic!("cmd 0 was on time")
        };
        p.advance(Some(&c));
        let applied = |p: &PlantSim| {
            let st = p.state(false);
            (st.v_a_v, st.v_b_v, st.applied_command_seq, st.flags)
        };
        let planned = state_flags::COMMAND_HELD | state_flags::COMMAND_PLANNED;
        // Period 2: cmd 1 missing, plan 0's entry for period 2.
        let sel = slot.take(1);
        assert_eq!(sel, Selection::Missing(Some(([2.0, -2.0], 0))));
        let Selection::Missing(v) = sel else { panic!() };
        p.advance_missing(v);
        assert_eq!(applied(&p), (2.0, -2.0, 0, planned));
        // cmd 1 turns up late with its plan for periods 3 and 4: the command is discarded,
        // its 9 V never applied, but its plan is the freshest (an older one offered after
        // it does not replace it).
        slot.offer(cmd(1, 9.0, -9.0), 2);
        slot.offer_plan(&plan(1, &[5.0, 6.0]));
        slot.offer_plan(&plan(0, &[7.0, 7.0, 7.0, 7.0]));
        assert_eq!(slot.late_discarded, 1);
        for (needed, want) in [(2, 5.0), (3, 6.0)] {
            let Selection::Missing(v) = slot.take(needed) else {
                panic!("sample {needed}'s command never came")
            };
            p.advance_missing(v);
            assert_eq!(applied(&p), (want, -want, 1, planned));
        }
        // Period 5: past every plan, the last voltage is held.
        assert_eq!(slot.take(4), Selection::Missing(None));
        p.advance_missing(None);
        assert_eq!(applied(&p), (6.0, -6.0, 1, state_flags::COMMAND_HELD));
        assert_eq!(
            (slot.misses, slot.planned, slot.runs.runs, slot.runs.longest),
            (4, 3, 1, 4)
        );
        // A plan claiming more than MAX_PLAN entries covers nothing.
        let mut bad = plan(5, &[7.0]);
        bad.len = stepdrive_shared::messages::MAX_PLAN as u32 + 1;
        slot.offer_plan(&bad);
        assert_eq!(slot.take(6), Selection::Missing(None));
    }

    /// A non-finite plan entry is a bad command: outputs off, fault latched.
    #[test]
    fn non_finite_plan_entry_trips_the_plant() {
        let mut p = PlantSim::new(&Scenario::default());
        let mut slot = CommandSlot::new(1);
        p.advance(None);
        slot.offer(cmd(0, 1.0, 1.0), 0);
        slot.offer_plan(&plan(0, &[f32::NAN]));
        let Selection::Apply(c) = slot.take(0) else {
            panic!()
        };
        p.advance(Some(&c));
        let Selection::Missing(v) = slot.take(1) else {
            panic!()
        };
        p.advance_missing(v);
        let st = p.state(false);
        assert_eq!((st.v_a_v, st.v_b_v), (0.0, 0.0));
        assert_ne!(st.fault & fault_bits::BAD_COMMAND, 0);
    }

    #[test]
    fn tripped_plant_holds_zero() {
        let mut p = PlantSim::new(&Scenario::default());
        p.advance(None);
        p.advance(Some(&cmd(0, 5.0, 5.0)));
        p.trip(fault_bits::COMMAND_TIMEOUT);
        p.advance_missing(None);
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
