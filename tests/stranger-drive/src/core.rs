//! The drive's protocol state machine and motor, steppable without clock or socket:
//! `on_frame(bytes, from, now_ns)` for every datagram received, `period(now_ns)` once per
//! sample period (returns the SAMPLE's bytes); CONFIG and FAULT_REPORT frames wait in an
//! outbox for the session's host (`take_outbox`, `session_host`).
//!
//! Timing follows §4.1's "When a SAMPLE shows a change" (spec revision after eeec02a).
//! A frame takes effect when it is received. Period k (t_k, t_{k+1}] is handled at tick
//! k, in this order:
//! 1. measure at t_k; an over-current or bus fault found here latches now (`at_sample` k)
//!    so that SAMPLE k shows it;
//! 2. build and send SAMPLE k: `fault_bits`, ENABLED and ALIGNING as the state stands now
//!    (what holds for period k), duties, `applied_command_seq`, COMMAND_HELD and
//!    COMMAND_PLANNED of period k − 1;
//! 3. choose period k's duties (the waiting COMMAND answering k − 1, else the PLAN entry
//!    for period k, else the previous duties); the watchdog latches here, at the start of
//!    the `watchdog_periods`-th period in a row without its COMMAND (`at_sample` k, so
//!    SAMPLE k + 1 is the first to show it); then integrate the motor over period k.
//!
//! BAD_COMMAND latches on receipt of the frame (`at_sample` = the next period to start).

use std::net::SocketAddr;

use crate::frame::{self, Config, DecodeError, Payload, Sample};
use crate::motor::{Drive, Motor, MotorParams};
use crate::{DriveOptions, DriveStats};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Mode {
    /// Outputs off (after start-up, HELLO, DISABLE, RESET, a fault).
    Disabled,
    /// ALIGN in progress: `remaining` periods of phase A at the align current.
    Aligning { remaining: u32 },
    /// Aligned, not enabled: phase A keeps holding the rotor.
    AlignHold,
    /// Enabled. `hold_align`: hold phase A until the first COMMAND; `aligning`: periods of
    /// an ALIGN still to run (an ENABLE taken during an ALIGN); `commanded`: a COMMAND has
    /// been applied since the ENABLE.
    Enabled {
        hold_align: bool,
        aligning: u32,
        commanded: bool,
    },
}

#[derive(Debug, Clone, Copy)]
struct Waiting {
    answers: u32,
    duty_a: i16,
    duty_b: i16,
    seq: u32,
}

#[derive(Debug, Clone)]
struct StoredPlan {
    answers: u32,
    seq: u32,
    entries: Vec<(i16, i16)>,
}

/// What the SAMPLE at the end of a period reports about it (§4.1: duties,
/// `applied_command_seq`, COMMAND_HELD and COMMAND_PLANNED are the ended period's).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PeriodRecord {
    pub duty_a: i16,
    pub duty_b: i16,
    pub applied_command_seq: u32,
    /// COMMAND_HELD / COMMAND_PLANNED only.
    pub status: u16,
}

pub struct DriveCore {
    config: Config,
    motor: Motor,
    bus_v: f64,
    period_s: f64,
    substeps: u32,
    overcurrent_a: f64,
    bus_range: (f64, f64),
    enc_origin: f64,
    enc_dir: f64,
    align_duty: i16,
    align_periods: u32,

    next_seq: u32,
    last_sent: Option<u32>,
    last_ts: u64,
    session: Option<SocketAddr>,
    host_last_seq: u32,
    mode: Mode,
    faults: u16,
    /// Bits some FAULT_REPORT has carried since the last RESET (§4.4).
    reported: u16,
    waiting: Option<Waiting>,
    plan: Option<StoredPlan>,
    record: PeriodRecord,
    last_duty: (i16, i16),
    last_applied: u32,
    wd_armed: bool,
    wd_missing: u32,
    run_started: bool,
    run_start_pending: bool,
    run_start_seq: u32,
    /// v3.1 §4.6: periods since the last frame accepted from the session's host; while it
    /// is heard and the motor energized, a HELLO from elsewhere is dropped.
    since_host: u32,
    /// Fault injection: phase A's motor leads swapped (the shunt reads the drive's side).
    swap_phase_a: bool,
    outbox: Vec<Vec<u8>>,
    pub stats: DriveStats,
}

impl DriveCore {
    pub fn new(o: &DriveOptions) -> Self {
        let p = MotorParams {
            load: o.load_nm,
            ..MotorParams::default()
        };
        let align_v = o.align_ma as f64 * 1e-3 * p.r;
        let align_duty = (align_v / o.bus_v * 32767.0).round().clamp(0.0, 32767.0) as i16;
        // §4.3 ALIGN: floor(align_ms × sample_rate_hz / 1000) periods
        let align_periods = (o.align_ms as u64 * o.rate_hz as u64 / 1000) as u32;
        DriveCore {
            config: Config {
                sample_rate_hz: o.rate_hz,
                counts_per_rev: o.counts_per_rev,
                current_ua_per_count: o.current_ua_per_count,
                current_zero_count: o.current_zero_count,
                bus_uv_per_count: o.bus_uv_per_count,
                watchdog_periods: o.watchdog_periods,
                encoder_direction: if o.reverse_encoder { -1 } else { 1 },
                plan_capacity: o.plan_capacity,
                align_current_ma: o.align_ma,
                align_ms: o.align_ms,
            },
            motor: Motor::new(p, o.initial_angle),
            bus_v: o.bus_v,
            period_s: 1.0 / o.rate_hz as f64,
            substeps: o.substeps,
            overcurrent_a: o.overcurrent_a,
            bus_range: (o.bus_min_v, o.bus_max_v),
            enc_origin: o.initial_angle,
            enc_dir: if o.reverse_encoder { -1.0 } else { 1.0 },
            align_duty,
            align_periods,
            next_seq: 0,
            last_sent: None,
            last_ts: 0,
            session: None,
            host_last_seq: 0,
            mode: Mode::Disabled,
            faults: 0,
            reported: 0,
            waiting: None,
            plan: None,
            record: PeriodRecord::default(),
            last_duty: (0, 0),
            last_applied: 0,
            wd_armed: false,
            wd_missing: 0,
            run_started: false,
            run_start_pending: false,
            run_start_seq: 0,
            since_host: 0,
            swap_phase_a: o.swap_phase_a,
            outbox: Vec::new(),
            stats: DriveStats::default(),
        }
    }

    pub fn config(&self) -> &Config {
        &self.config
    }
    pub fn session_host(&self) -> Option<SocketAddr> {
        self.session
    }
    pub fn take_outbox(&mut self) -> Vec<Vec<u8>> {
        std::mem::take(&mut self.outbox)
    }
    pub fn motor(&self) -> &Motor {
        &self.motor
    }
    pub fn motor_mut(&mut self) -> &mut Motor {
        &mut self.motor
    }
    pub fn fault_bits(&self) -> u16 {
        self.faults
    }
    /// Index of sample `seq` within the current run (0 = the run's first ENABLED SAMPLE).
    pub fn run_index(&self, seq: u32) -> Option<u64> {
        if self.run_started {
            Some(seq.wrapping_sub(self.run_start_seq) as u64)
        } else {
            None
        }
    }
    /// The SAMPLE seq the next `period` will send.
    pub fn next_seq(&self) -> u32 {
        self.next_seq
    }

    fn stamp(&mut self, now_ns: u64) -> u64 {
        self.last_ts = self.last_ts.max(now_ns);
        self.last_ts
    }

    fn count_decode_error(&mut self, e: DecodeError) {
        let s = &mut self.stats;
        match e {
            DecodeError::TooShort => s.dropped_too_short += 1,
            DecodeError::LengthMismatch => s.dropped_length += 1,
            DecodeError::Crc => s.dropped_crc += 1,
            DecodeError::Magic => s.dropped_magic += 1,
            DecodeError::Version(_) => s.dropped_version += 1,
            DecodeError::UnknownKind(_) => s.dropped_unknown_kind += 1,
            DecodeError::PayloadLen => s.dropped_payload_len += 1,
            DecodeError::BadField => s.dropped_bad_field += 1,
            DecodeError::Reserved => s.dropped_reserved += 1,
        }
    }

    /// Outputs off, nothing waiting, watchdog disarmed (DISABLE, RESET, ALIGN, HELLO, a
    /// fault latching).
    fn outputs_off(&mut self) {
        self.mode = Mode::Disabled;
        self.waiting = None;
        self.plan = None;
        self.wd_armed = false;
        self.wd_missing = 0;
        self.last_duty = (0, 0);
        self.last_applied = 0;
    }

    /// Latches `bits`: outputs off from the period that starts at `at_sample`, watchdog
    /// disarmed, and one FAULT_REPORT (with every latched bit) if some bit is one no
    /// FAULT_REPORT has carried since the last RESET. Returns whether a bit was new.
    fn latch(&mut self, bits: u16, at_sample: u32, report_seq: u32, ts: u64) -> bool {
        let new = bits & !self.faults;
        if new == 0 {
            return false;
        }
        self.faults |= new;
        self.stats.faults_latched += 1;
        self.outputs_off();
        if self.faults & !self.reported != 0 {
            self.reported |= self.faults;
            self.outbox.push(frame::encode(
                report_seq,
                ts,
                &Payload::FaultReport {
                    fault_bits: self.faults,
                    at_sample,
                },
            ));
            self.stats.fault_reports_sent += 1;
        }
        true
    }

    /// BAD_COMMAND, latched on receipt (§5): the period that starts next is the first off.
    fn latch_bad_command(&mut self, now_ns: u64) {
        self.stats.commands_bad += 1;
        let ts = self.stamp(now_ns);
        let seq = self.last_sent.unwrap_or(0);
        self.latch(frame::FAULT_BAD_COMMAND, self.next_seq, seq, ts);
    }

    /// One datagram from `from`. Never panics, whatever the bytes.
    pub fn on_frame(&mut self, bytes: &[u8], from: SocketAddr, now_ns: u64) {
        self.stats.frames_received += 1;
        let f = match frame::decode(bytes) {
            Ok(f) => f,
            Err(e) => {
                self.count_decode_error(e);
                return;
            }
        };
        // §2: a frame of a kind only a drive sends, before the sequence rule
        if matches!(
            f.payload,
            Payload::Sample(_) | Payload::Config(_) | Payload::FaultReport { .. }
        ) {
            self.stats.dropped_wrong_direction += 1;
            return;
        }
        if let Payload::Hello { .. } = f.payload {
            // v3.1 §4.6: not from another address while this session is live
            if self.session.is_some_and(|h| h != from) && self.live() {
                self.stats.dropped_wrong_source += 1;
                return;
            }
            self.since_host = 0;
            // a new session, whatever its seq (§3.1, §4.6)
            self.stats.frames_accepted += 1;
            self.stats.sessions += 1;
            self.session = Some(from);
            self.host_last_seq = f.seq;
            self.outputs_off();
            self.run_started = false;
            self.run_start_pending = false;
            let seq = self.last_sent.unwrap_or(0);
            let ts = self.stamp(now_ns);
            self.outbox
                .push(frame::encode(seq, ts, &Payload::Config(self.config)));
            self.stats.configs_sent += 1;
            return;
        }
        // §2 "No session yet": every frame but HELLO is dropped and counted
        let Some(host) = self.session else {
            self.stats.dropped_no_session += 1;
            return;
        };
        if from != host {
            self.stats.dropped_wrong_source += 1;
            return;
        }
        if let Payload::Plan { entries, .. } = &f.payload {
            if entries.len() > self.config.plan_capacity as usize {
                self.stats.dropped_plan_capacity += 1;
                return;
            }
        }
        if !frame::is_newer(f.seq, self.host_last_seq) {
            self.stats.dropped_sequence += 1;
            return;
        }
        self.host_last_seq = f.seq;
        self.stats.frames_accepted += 1;
        self.since_host = 0;
        match f.payload {
            Payload::Command {
                answers_sample,
                duty_a,
                duty_b,
            } => {
                self.stats.commands_received += 1;
                if duty_a == i16::MIN || duty_b == i16::MIN {
                    self.latch_bad_command(now_ns);
                    return;
                }
                // waits, in every state (§4.3 "Frames while the outputs are off")
                self.waiting = Some(Waiting {
                    answers: answers_sample,
                    duty_a,
                    duty_b,
                    seq: f.seq,
                });
            }
            Payload::Plan {
                answers_sample,
                entries,
            } => {
                if entries.iter().any(|&(a, b)| a == i16::MIN || b == i16::MIN) {
                    self.latch_bad_command(now_ns);
                    return;
                }
                let take = match &self.plan {
                    None => true,
                    Some(p) => {
                        p.answers == answers_sample || frame::is_newer(answers_sample, p.answers)
                    }
                };
                if take {
                    self.stats.plans_stored += 1;
                    self.plan = Some(StoredPlan {
                        answers: answers_sample,
                        seq: f.seq,
                        entries,
                    });
                } else {
                    self.stats.plans_ignored_older += 1;
                }
            }
            Payload::Control { action } => self.on_control(action),
            _ => {}
        }
    }

    fn on_control(&mut self, action: u8) {
        match action {
            frame::ACTION_ENABLE => {
                if self.faults != 0 {
                    // §4.3: ignored while a fault is latched
                    self.stats.controls_ignored += 1;
                    return;
                }
                let new = match self.mode {
                    Mode::Disabled => Mode::Enabled {
                        hold_align: false,
                        aligning: 0,
                        commanded: false,
                    },
                    Mode::Aligning { remaining } => Mode::Enabled {
                        hold_align: true,
                        aligning: remaining,
                        commanded: false,
                    },
                    Mode::AlignHold => Mode::Enabled {
                        hold_align: true,
                        aligning: 0,
                        commanded: false,
                    },
                    m @ Mode::Enabled { .. } => m,
                };
                if !matches!(self.mode, Mode::Enabled { .. }) && !self.run_started {
                    self.run_start_pending = true;
                }
                self.mode = new;
            }
            frame::ACTION_DISABLE => {
                self.outputs_off();
                self.run_started = false;
                self.run_start_pending = false;
            }
            frame::ACTION_RESET => {
                self.faults = 0;
                self.reported = 0;
                self.outputs_off();
            }
            _ => {
                // ALIGN: ignored while faulted and without alignment (§4.3)
                if self.config.align_ms == 0 || self.align_periods == 0 || self.faults != 0 {
                    self.stats.controls_ignored += 1;
                    return;
                }
                self.outputs_off();
                self.run_started = false;
                self.run_start_pending = false;
                self.mode = Mode::Aligning {
                    remaining: self.align_periods,
                };
            }
        }
    }

    /// v3.1 §4.6: the session's host is heard (within the watchdog's periods) and the motor
    /// is energized (aligning, holding, enabled).
    fn live(&self) -> bool {
        self.faults == 0
            && self.mode != Mode::Disabled
            && self.since_host < self.config.watchdog_periods as u32
    }

    fn adc_current(&self, i: f64) -> u16 {
        let c = (i * 1e6 / self.config.current_ua_per_count as f64).round()
            + self.config.current_zero_count as f64;
        c.clamp(0.0, 65535.0) as u16
    }
    fn current_of(&self, adc: u16) -> f64 {
        (adc as f64 - self.config.current_zero_count as f64)
            * self.config.current_ua_per_count as f64
            * 1e-6
    }

    fn encoder(&self) -> i32 {
        let counts = (self.enc_dir
            * (self.motor.s.theta - self.enc_origin)
            * self.config.counts_per_rev as f64
            / std::f64::consts::TAU)
            .floor();
        // multi-turn count, wrapping at ±2^31
        (counts as i64) as i32
    }

    fn plan_entry(&self, k: u32) -> Option<(u32, (i16, i16))> {
        let p = self.plan.as_ref()?;
        let j = k.wrapping_sub(p.answers.wrapping_add(2)) as usize;
        p.entries.get(j).map(|&e| (p.seq, e))
    }

    /// State bits of a SAMPLE taken now: what holds for the period about to start.
    fn state_bits(&self) -> u16 {
        if self.faults != 0 {
            return 0;
        }
        match self.mode {
            Mode::Disabled | Mode::AlignHold => 0,
            Mode::Aligning { .. } => frame::STATUS_ALIGNING,
            Mode::Enabled { aligning, .. } => {
                frame::STATUS_ENABLED
                    | if aligning > 0 {
                        frame::STATUS_ALIGNING
                    } else {
                        0
                    }
            }
        }
    }

    /// One sample period: returns SAMPLE k's bytes and runs period k.
    pub fn period(&mut self, now_ns: u64) -> Vec<u8> {
        let k = self.next_seq;
        let ts = self.stamp(now_ns);

        // 1. measure at t_k; over-current and bus faults found here show in SAMPLE k
        self.since_host = self.since_host.saturating_add(1);
        let s = &self.motor.s;
        // swapped leads: the shunt sits on the drive's side of them
        let ia_sensed = if self.swap_phase_a { -s.ia } else { s.ia };
        let (adc_a, adc_b) = (self.adc_current(ia_sensed), self.adc_current(s.ib));
        let adc_bus = (self.bus_v * 1e6 / self.config.bus_uv_per_count as f64)
            .round()
            .clamp(0.0, 65535.0) as u16;
        let ia = self.current_of(adc_a);
        let ib = self.current_of(adc_b);
        let mut found = 0u16;
        if ia.abs() > self.overcurrent_a || ib.abs() > self.overcurrent_a {
            found |= frame::FAULT_OVERCURRENT;
        }
        let vbus = adc_bus as f64 * self.config.bus_uv_per_count as f64 * 1e-6;
        if vbus < self.bus_range.0 || vbus > self.bus_range.1 {
            found |= frame::FAULT_BUS_VOLTAGE;
        }
        // latched before SAMPLE k is built; its FAULT_REPORT follows SAMPLE k (seq k)
        self.latch(found, k, k, ts);

        // 2. SAMPLE k
        let sample = Sample {
            encoder_counts: self.encoder(),
            adc_a,
            adc_b,
            adc_bus,
            duty_a: self.record.duty_a,
            duty_b: self.record.duty_b,
            applied_command_seq: self.record.applied_command_seq,
            fault_bits: self.faults,
            status: self.state_bits() | self.record.status,
        };
        let bytes = frame::encode(k, ts, &Payload::Sample(sample));
        self.last_sent = Some(k);
        self.next_seq = k.wrapping_add(1);
        self.stats.samples_sent += 1;
        self.stats.periods += 1;
        // v3.1 §7 step 5: the run starts where the host's k = 0 is, the first SAMPLE with
        // ENABLED set and ALIGNING clear (or a fault bit), not inside an alignment
        let run_sample = sample.status & (frame::STATUS_ENABLED | frame::STATUS_ALIGNING)
            == frame::STATUS_ENABLED
            || sample.fault_bits != 0;
        if run_sample && self.run_start_pending {
            self.run_start_pending = false;
            self.run_started = true;
            self.run_start_seq = k;
            self.stats.runs_started += 1;
        }

        // 3. period k: the waiting COMMAND is for it if it answers k − 1
        let prev = k.wrapping_sub(1);
        let cmd = match self.waiting {
            Some(w) if w.answers == prev => {
                self.waiting = None;
                Some(w)
            }
            Some(w) if frame::is_newer(prev, w.answers) => {
                self.waiting = None;
                self.stats.commands_late += 1;
                None
            }
            _ => None,
        };
        let align = (self.align_duty, 0i16);
        let off = PeriodRecord::default();
        let aligned = |st: u16| PeriodRecord {
            duty_a: align.0,
            duty_b: align.1,
            applied_command_seq: 0,
            status: st,
        };
        let mut rec = off;
        let mut on = true;
        if self.faults != 0 {
            on = false;
            if cmd.is_some() {
                self.stats.commands_discarded_off += 1;
            }
        } else {
            match self.mode {
                Mode::Disabled => {
                    on = false;
                    if cmd.is_some() {
                        self.stats.commands_discarded_off += 1;
                    }
                }
                Mode::Aligning { remaining } => {
                    if cmd.is_some() {
                        self.stats.commands_discarded_off += 1;
                    }
                    self.mode = if remaining <= 1 {
                        Mode::AlignHold
                    } else {
                        Mode::Aligning {
                            remaining: remaining - 1,
                        }
                    };
                    rec = aligned(0);
                }
                Mode::AlignHold => {
                    if cmd.is_some() {
                        self.stats.commands_discarded_off += 1;
                    }
                    rec = aligned(0);
                }
                Mode::Enabled {
                    hold_align,
                    aligning,
                    commanded,
                } => {
                    self.stats.periods_enabled += 1;
                    if aligning > 0 {
                        // §4.3: nothing is applied while aligning, a COMMAND for an
                        // aligning period is discarded; the alignment runs to its end
                        if cmd.is_some() {
                            self.stats.commands_discarded_off += 1;
                        }
                        self.stats.periods_held += 1;
                        self.mode = Mode::Enabled {
                            hold_align,
                            aligning: aligning - 1,
                            commanded,
                        };
                        rec = aligned(frame::STATUS_COMMAND_HELD);
                    } else if let Some(c) = cmd {
                        self.stats.commands_applied += 1;
                        self.mode = Mode::Enabled {
                            hold_align: false,
                            aligning: 0,
                            commanded: true,
                        };
                        self.wd_armed = true;
                        self.wd_missing = 0;
                        self.last_duty = (c.duty_a, c.duty_b);
                        self.last_applied = c.seq;
                        rec = PeriodRecord {
                            duty_a: c.duty_a,
                            duty_b: c.duty_b,
                            applied_command_seq: c.seq,
                            status: 0,
                        };
                    } else {
                        if self.wd_armed {
                            self.wd_missing += 1;
                        }
                        if self.wd_armed && self.wd_missing >= self.config.watchdog_periods as u32 {
                            // §5: latches at the start of the N-th period in a row without
                            // its COMMAND, which is the first with the outputs off
                            self.latch(frame::FAULT_WATCHDOG, k, k, ts);
                            on = false;
                        } else if hold_align && !commanded {
                            self.stats.periods_held += 1;
                            self.last_duty = align;
                            self.last_applied = 0;
                            rec = aligned(frame::STATUS_COMMAND_HELD);
                        } else {
                            self.stats.periods_held += 1;
                            let mut st = frame::STATUS_COMMAND_HELD;
                            if let Some((seq, e)) = self.plan_entry(k) {
                                self.stats.periods_planned += 1;
                                st |= frame::STATUS_COMMAND_PLANNED;
                                self.last_duty = e;
                                self.last_applied = seq;
                            }
                            rec = PeriodRecord {
                                duty_a: self.last_duty.0,
                                duty_b: self.last_duty.1,
                                applied_command_seq: self.last_applied,
                                status: st,
                            };
                        }
                    }
                }
            }
        }
        self.record = if on { rec } else { off };

        // 4. the motor over period k
        let sign_a = if self.swap_phase_a { -1.0 } else { 1.0 };
        let (da, db) = if on {
            (
                Drive::Volts(sign_a * rec.duty_a as f64 / 32767.0 * self.bus_v),
                Drive::Volts(rec.duty_b as f64 / 32767.0 * self.bus_v),
            )
        } else {
            (Drive::Off, Drive::Off)
        };
        self.motor
            .step(da, db, self.bus_v, self.period_s, self.substeps);
        bytes
    }
}
