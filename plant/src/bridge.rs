//! The hardware back-end of the plant process: a bridge between the stack's services and a
//! drive speaking `docs/drive-protocol.md` over UDP. Units and calibration live here and
//! only here; the current loop, position loop and monitor see the same `DriveState` and
//! `DriveCommand` as with the simulated plant. The drive's sample clock paces everything.

use crate::drive_protocol::{
    decode, encode, is_newer, status, Action, Command, Config, DecodeError, FaultReport, Frame,
    Message, Plan, MAX_FRAME, MAX_PLAN_ENTRIES,
};
use crate::drive_units::{duty_for, volts_for, Scaling, VelocityObserver};
use crate::process::{wait_for_stack, PlantError, PlantOptions};
use crate::wire::{enlarge_receive_buffer, SerialPort, Wire, RECEIVE_BUFFER_BYTES};
use std::net::{SocketAddr, UdpSocket};
use std::os::fd::RawFd;
use stepdrive_shared::clock::monotonic_ns;
use stepdrive_shared::messages::{fault_bits, state_flags, DriveCommand, DrivePlan, DriveState};
use stepdrive_shared::pacer::{sleep_until, WaitStrategy};
use stepdrive_shared::poll::termination_requested;
use stepdrive_shared::rt::RtOptions;
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::{
    connect, drain, notifier, notify, publish_stats, publisher, send, subscriber, try_receive, Sub,
    Topics, LOOP_BUFFER,
};
use stepdrive_shared::stats::{roles, MissRuns, StatsReport};

/// What one received datagram turned into.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Event {
    State(DriveState),
    Config(Config),
    Fault(FaultReport),
    /// Dropped: bad CRC, malformed, duplicate or out of order, or unexpected.
    Dropped,
}

/// Host-side encoder calibration, over what the drive's CONFIG says.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct EncoderCalibration {
    /// Encoder reading at θ = 0 (an absolute encoder's zero); `None` zeroes at the first
    /// sample.
    pub offset_counts: Option<i64>,
    /// Counts increase for negative θ, whatever CONFIG's `encoder_direction` says (an
    /// encoder or motor wired the other way round).
    pub reverse: bool,
}

/// Drive frames ↔ SI, without sockets or clocks.
pub struct DriveLink {
    scaling: Option<Scaling>,
    calibration: EncoderCalibration,
    /// PLAN entries the drive keeps (from CONFIG; 0: send none).
    plan_capacity: u16,
    observer: VelocityObserver,
    observer_hz: f64,
    sample_hz: f64,
    last_seq: Option<u32>,
    first_seq: Option<u32>,
    counts: i64,
    last_raw: Option<i32>,
    offset_counts: Option<i64>,
    tx_seq: u32,
    pub crc_errors: u64,
    pub bad_frames: u64,
    pub rejected_commands: u64,
    /// Periods the drive reported without their COMMAND, and of those the ones it covered
    /// with a PLAN entry; runs of such periods.
    pub held_periods: u64,
    pub planned_periods: u64,
    pub held_runs: MissRuns,
    /// Samples that never arrived: gaps in the drive's frame sequence.
    pub lost_on_wire: u64,
    /// The drive's timestamp of the last accepted sample, ns on the drive's clock.
    pub sample_timestamp_ns: u64,
}

impl DriveLink {
    pub fn new(sample_hz: f64, observer_hz: f64, calibration: EncoderCalibration) -> Self {
        Self {
            scaling: None,
            calibration,
            plan_capacity: 0,
            observer: VelocityObserver::new(observer_hz, 1.0 / sample_hz),
            observer_hz,
            sample_hz,
            last_seq: None,
            first_seq: None,
            counts: 0,
            last_raw: None,
            offset_counts: calibration.offset_counts,
            tx_seq: 1,
            crc_errors: 0,
            bad_frames: 0,
            rejected_commands: 0,
            held_periods: 0,
            planned_periods: 0,
            held_runs: MissRuns::default(),
            lost_on_wire: 0,
            sample_timestamp_ns: 0,
        }
    }

    pub fn configured(&self) -> bool {
        self.scaling.is_some()
    }

    /// Forgets the sample stream (index, position, velocity, counters) so that run starts
    /// at k = 0 with the next sample; the configuration is kept.
    pub fn restart(&mut self) {
        let (scaling, plan_capacity) = (self.scaling, self.plan_capacity);
        *self = Self {
            scaling,
            plan_capacity,
            tx_seq: self.tx_seq,
            ..Self::new(self.sample_hz, self.observer_hz, self.calibration)
        };
    }

    /// Index k of the drive sample with wire sequence `seq` (k = 0 at the first sample).
    fn index_of(&self, seq: u32) -> u64 {
        u64::from(seq.wrapping_sub(self.first_seq.unwrap_or(seq)))
    }

    pub fn on_frame(&mut self, bytes: &[u8], now_ns: u64) -> Event {
        let frame = match decode(bytes) {
            Ok(f) => f,
            Err(DecodeError::BadCrc { .. }) => {
                self.crc_errors += 1;
                return Event::Dropped;
            }
            Err(_) => {
                self.bad_frames += 1;
                return Event::Dropped;
            }
        };
        match frame.message {
            Message::Config(c) => {
                let mut c = c;
                if self.calibration.reverse {
                    c.encoder_direction = if c.encoder_direction < 0 { 1 } else { -1 };
                }
                self.scaling = Some(Scaling::new(&c));
                self.plan_capacity = c.plan_capacity.min(MAX_PLAN_ENTRIES as u16);
                Event::Config(c)
            }
            Message::FaultReport(f) => Event::Fault(f),
            Message::Sample(s) => {
                let Some(scaling) = self.scaling else {
                    self.bad_frames += 1;
                    return Event::Dropped;
                };
                if !is_newer(frame.seq, self.last_seq) {
                    self.bad_frames += 1;
                    return Event::Dropped;
                }
                if let Some(last) = self.last_seq {
                    self.lost_on_wire += u64::from(frame.seq.wrapping_sub(last) - 1);
                }
                self.last_seq = Some(frame.seq);
                self.sample_timestamp_ns = frame.timestamp_ns;
                self.first_seq.get_or_insert(frame.seq);
                // Unwrap the 32-bit counter into a 64-bit position.
                let step = match self.last_raw {
                    Some(prev) => i64::from(s.encoder_counts.wrapping_sub(prev)),
                    None => i64::from(s.encoder_counts),
                };
                self.last_raw = Some(s.encoder_counts);
                self.counts += step;
                let offset = *self.offset_counts.get_or_insert(self.counts);
                let theta = scaling.theta(self.counts - offset);
                let omega = self.observer.update(theta);
                let bus = scaling.bus_volts(s.adc_bus);
                let k = self.index_of(frame.seq);
                let mut fault = 0;
                if s.fault_bits != 0 {
                    fault = fault_bits::DRIVE_FAULT | (u32::from(s.fault_bits) << 16);
                }
                let mut flags = 0;
                let held = s.status & status::COMMAND_HELD != 0;
                self.held_runs.record(held);
                if held {
                    flags |= state_flags::COMMAND_HELD;
                    self.held_periods += 1;
                    if s.status & status::COMMAND_PLANNED != 0 {
                        flags |= state_flags::COMMAND_PLANNED;
                        self.planned_periods += 1;
                    }
                }
                Event::State(DriveState {
                    seq: k,
                    sample_time_s: k as f64 / self.sample_hz,
                    publish_time_ns: 0,
                    deadline_ns: now_ns,
                    applied_command_seq: u64::from(s.applied_command_seq),
                    theta_rad: theta,
                    omega_rad_s: omega,
                    i_a_a: scaling.amps(s.adc_a),
                    i_b_a: scaling.amps(s.adc_b),
                    v_a_v: volts_for(s.duty_a, bus),
                    v_b_v: volts_for(s.duty_b, bus),
                    bus_voltage_v: bus,
                    flags,
                    fault,
                })
            }
            _ => {
                self.bad_frames += 1;
                Event::Dropped
            }
        }
    }

    /// The frame carrying `c`, or `None` (counted) if it must not reach the drive: a
    /// non-finite voltage or one beyond the measured bus voltage.
    pub fn command_frame(&mut self, c: &DriveCommand, bus_v: f64, now_ns: u64) -> Option<Frame> {
        let (Some(a), Some(b)) = (duty_for(c.v_a_v, bus_v), duty_for(c.v_b_v, bus_v)) else {
            self.rejected_commands += 1;
            return None;
        };
        let first = self.first_seq?;
        let frame = Frame {
            seq: self.tx_seq,
            timestamp_ns: now_ns,
            message: Message::Command(Command {
                answers_sample: first.wrapping_add(c.answers_seq as u32),
                duty_a: a,
                duty_b: b,
            }),
        };
        self.tx_seq = self.tx_seq.wrapping_add(1);
        Some(frame)
    }

    /// The PLAN frame carrying `plan` (as many entries as the drive keeps), or `None` if the
    /// drive keeps none or any entry must not reach it (non-finite or beyond the measured
    /// bus: the whole plan is refused and counted with the rejected commands).
    pub fn plan_frame(&mut self, plan: &DrivePlan, bus_v: f64, now_ns: u64) -> Option<Frame> {
        let first = self.first_seq?;
        let count = plan.entries().len().min(usize::from(self.plan_capacity));
        if count == 0 {
            return None;
        }
        let mut duties = [[0i16; 2]; MAX_PLAN_ENTRIES];
        for (out, v) in duties.iter_mut().zip(&plan.entries()[..count]) {
            let (Some(a), Some(b)) = (
                duty_for(f64::from(v[0]), bus_v),
                duty_for(f64::from(v[1]), bus_v),
            ) else {
                self.rejected_commands += 1;
                return None;
            };
            *out = [a, b];
        }
        let frame = Frame {
            seq: self.tx_seq,
            timestamp_ns: now_ns,
            message: Message::Plan(Plan {
                answers_sample: first.wrapping_add(plan.answers_seq as u32),
                count: count as u16,
                duties,
            }),
        };
        self.tx_seq = self.tx_seq.wrapping_add(1);
        Some(frame)
    }

    /// Puts the link's counters into a stats report (drive-held periods are its misses).
    pub fn copy_counters(&self, stats: &mut StatsReport) {
        stats.lost = self.lost_on_wire;
        stats.crc_errors = self.crc_errors;
        stats.bad_frames = self.bad_frames;
        stats.rejected_commands = self.rejected_commands;
        stats.misses = self.held_periods;
        stats.planned = self.planned_periods;
        self.held_runs.copy_to(stats);
    }

    pub fn control_frame(&mut self, action: Action, now_ns: u64) -> Frame {
        let f = Frame {
            seq: self.tx_seq,
            timestamp_ns: now_ns,
            message: Message::Control(action),
        };
        self.tx_seq = self.tx_seq.wrapping_add(1);
        f
    }

    pub fn hello_frame(&mut self, now_ns: u64) -> Frame {
        let f = Frame {
            seq: self.tx_seq,
            timestamp_ns: now_ns,
            message: Message::Hello,
        };
        self.tx_seq = self.tx_seq.wrapping_add(1);
        f
    }
}

/// Where the drive is.
#[derive(Debug, Clone)]
pub enum DriveAddr {
    Udp(SocketAddr),
    /// A serial line: a UART (`/dev/ttyACM0`) or a pseudo-terminal.
    Serial(std::path::PathBuf),
}

impl std::fmt::Display for DriveAddr {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            DriveAddr::Udp(a) => write!(f, "udp://{a}"),
            DriveAddr::Serial(p) => write!(f, "serial:{}", p.display()),
        }
    }
}

#[derive(Debug, Clone)]
pub struct BridgeOptions {
    pub drive: DriveAddr,
    pub rt: RtOptions,
    /// How the bridge waits for the drive's next frame: `hybrid:N` sleeps until N before
    /// it is due, then polls the socket; `spin` polls throughout; `sleep` blocks in poll().
    pub wait: WaitStrategy,
    /// No valid sample for this many periods: publish a fault and stop forwarding.
    pub silence_periods: u32,
    /// Forward the current loop's plan when it is this many samples newer than the last
    /// one sent (a ~830-byte PLAN at 20 kHz would be 17 MB/s; every 10th period, ~1.7).
    pub plan_every: u32,
    pub observer_hz: f64,
    pub calibration: EncoderCalibration,
}

fn send_frame(wire: &mut Wire, f: &Frame) {
    let mut buf = [0u8; MAX_FRAME];
    let n = encode(f, &mut buf);
    wire.send(&buf[..n]);
}

/// How a bridge with a real-time priority waits for the drive's next frame: asleep until
/// 30 µs before it is due, then polling the socket. Periods without their own command,
/// 10 s runs at 20 kHz on this project's 2-core VM: margin 15 µs 5-6 %, 22 µs 1.6-1.8 %,
/// 30 µs 0.7-3.5 %, 40 µs 1.5-2.5 % (the spread between runs is as large as the
/// differences; polling longer crowds the current loop's CPU). Without a real-time
/// priority polling only takes the CPU from the processes the bridge waits for: `sleep`.
pub fn default_wait(realtime_priority: bool) -> WaitStrategy {
    if realtime_priority {
        WaitStrategy::Hybrid { margin_ns: 30_000 }
    } else {
        WaitStrategy::Sleep
    }
}

/// The longest the bridge polls its socket past a frame's due time before it blocks.
const MAX_SPIN_PAST_DUE_NS: u64 = 100_000;

/// Runs the bridge for the scenario's duration (hardware mode).
pub fn run_bridge(opts: &PlantOptions, b: &BridgeOptions) -> Result<StatsReport, PlantError> {
    let io = |e: std::io::Error| PlantError::Protocol(format!("drive socket: {e}"));
    let topics = Topics::open(&opts.instance, "plant", Mode::Hardware)?;
    let commands = subscriber(&topics.command, "drive/command", LOOP_BUFFER)?;
    let plans = subscriber(&topics.plan, "drive/plan", LOOP_BUFFER)?;
    let ready = notifier(&topics.state_ready()?)?;
    let states = publisher(&topics.state, "drive/state")?;
    let stats_pub = publisher(&topics.stats, "monitor/stats")?;
    b.rt.apply()
        .map_err(|e| PlantError::Protocol(e.to_string()))?;
    let mut wire = match &b.drive {
        DriveAddr::Udp(addr) => {
            let local = if addr.ip().is_loopback() {
                "127.0.0.1:0"
            } else {
                "0.0.0.0:0"
            };
            let sock = UdpSocket::bind(local).map_err(io)?;
            sock.connect(addr).map_err(io)?;
            sock.set_nonblocking(true).map_err(io)?;
            let got = enlarge_receive_buffer(&sock, RECEIVE_BUFFER_BYTES);
            tracing::debug!(bytes = got, "drive socket receive buffer");
            Wire::Udp { sock, peer: None }
        }
        DriveAddr::Serial(path) => Wire::Serial(SerialPort::open(path).map_err(|e| {
            PlantError::Protocol(format!("cannot open serial port {}: {e}", path.display()))
        })?),
    };

    let s = &opts.scenario;
    if s.rates.compute_delay_periods != 1 {
        return Err(PlantError::Protocol(format!(
            "a drive applies each COMMAND one period after its sample (docs/drive-protocol.md); \
             the scenario's rates.compute_delay_periods is {}, so the current loop would be \
             designed for another drive",
            s.rates.compute_delay_periods
        )));
    }
    let period_ns = s.sample_period_ns();
    let mut link = DriveLink::new(s.rates.current_loop_hz, b.observer_hz, b.calibration);
    let mut rx = [0u8; 2048];

    // Find the drive: HELLO until CONFIG.
    let start = monotonic_ns();
    let mut next_hello = start;
    while !link.configured() {
        if termination_requested() {
            return Err(PlantError::Terminated);
        }
        let now = monotonic_ns();
        if now - start > opts.startup_timeout.as_nanos() as u64 {
            return Err(PlantError::Startup(
                opts.startup_timeout,
                format!("no CONFIG from the drive at {}", b.drive),
            ));
        }
        if now >= next_hello {
            send_frame(&mut wire, &link.hello_frame(now));
            next_hello = now + 50_000_000;
        }
        wait_readable(wire.raw_fd(), 1);
        if let Some((n, _)) = wire.recv(&mut rx, 0) {
            if let Event::Config(c) = link.on_frame(&rx[..n], now) {
                tracing::info!(?c, "drive configuration");
                if f64::from(c.sample_rate_hz) != s.rates.current_loop_hz.round() {
                    return Err(PlantError::Protocol(format!(
                        "drive samples at {} Hz, the scenario expects {} Hz",
                        c.sample_rate_hz, s.rates.current_loop_hz
                    )));
                }
            }
        }
    }
    wait_for_stack(&topics, opts)?;
    connect(&states)?;
    // Samples queued while the loops came up are stale: drop them and start the stream
    // (k = 0) with the next one, then enable the drive.
    while wire.recv(&mut rx, 0).is_some() {}
    link.restart();
    let now = monotonic_ns();
    send_frame(&mut wire, &link.control_frame(Action::Reset, now));
    send_frame(&mut wire, &link.control_frame(Action::Enable, now));

    let n = s.sample_count();
    let mut stats = Box::new(StatsReport {
        role: roles::PLANT,
        ..Default::default()
    });
    let mut out = Box::new(Outbox {
        sent_at: [(0, 0); 64],
        answered: None,
        plan: DrivePlan::default(),
        plan_sent: None,
        plan_every: u64::from(b.plan_every.max(1)),
        silent: false,
        bus_v: 0.0,
    });
    let mut last_rx = monotonic_ns();
    let mut last_state: Option<DriveState> = None;
    let silence_ns = u64::from(b.silence_periods) * period_ns;
    // About once a second, for the monitor's progress line.
    let stats_every = (s.rates.current_loop_hz.round() as u64).max(1);
    let mut arrivals = ArrivalClock::new(period_ns);
    let mut due: Option<u64> = None;
    tracing::info!(samples = n, drive = %b.drive, wait = %b.wait, "bridge running");
    loop {
        if termination_requested() {
            return Err(PlantError::Terminated);
        }
        // Wait for the drive's next frame without a wake-up on the critical path: asleep
        // until the wait strategy's margin before it is due, then polling the socket (a
        // wake-up by the kernel would cost ~15 µs here: softirq, IPI, preemption). Without a
        // due time, or well past it (drive late or silent), block in poll() for up to 1 ms
        // so the silence watchdog keeps running.
        let spin_from = due.map(|d| match b.wait {
            WaitStrategy::Hybrid { margin_ns } => d.saturating_sub(margin_ns),
            WaitStrategy::Spin => 0,
            _ => u64::MAX,
        });
        if let Some(t) = spin_from.filter(|&t| t != u64::MAX && t > monotonic_ns()) {
            sleep_until(t);
        }
        // A frame this late means the drive or the host was held up: stop spinning.
        let give_up = due.map_or(0, |d| d + (2 * period_ns).min(MAX_SPIN_PAST_DUE_NS));
        let (mut st, rx_at) = loop {
            out.forward(&commands, &plans, &mut link, &mut wire, &mut stats)?;
            // Taken before the socket is read: if it holds nothing, nothing arrived up to
            // here, even if this process is held up before it checks for silence.
            let looked_at = monotonic_ns();
            let mut newest: Option<(DriveState, u64)> = None;
            while let Some((len, _)) = wire.recv(&mut rx, 0) {
                let now = monotonic_ns();
                match link.on_frame(&rx[..len], now) {
                    Event::State(st) => {
                        // The emulated drive shares this host's clock; for a real drive only
                        // the round trip is meaningful.
                        stats
                            .hop
                            .record(now.saturating_sub(link.sample_timestamp_ns));
                        out.round_trip(st.applied_command_seq as u32, now, &mut stats);
                        stats.superseded += u64::from(newest.is_some());
                        newest = Some((st, now));
                    }
                    Event::Fault(f) => {
                        tracing::error!(
                            faults = f.fault_bits,
                            at = f.at_sample,
                            "drive reports a latched fault"
                        );
                    }
                    Event::Config(_) | Event::Dropped => {}
                }
            }
            if let Some(taken) = newest {
                break taken;
            }
            let now = monotonic_ns();
            if looked_at.saturating_sub(last_rx) > silence_ns && !out.silent {
                out.silent = true;
                tracing::error!(
                    periods = b.silence_periods,
                    "no valid sample from the drive: fault published, no commands forwarded until it speaks again"
                );
                if let Some(mut st) = last_state {
                    st.seq += 1;
                    st.fault |= fault_bits::DRIVE_SILENT;
                    st.publish_time_ns = now;
                    st.deadline_ns = now;
                    send(&states, st)?;
                    notify(&ready)?;
                    last_state = Some(st);
                }
            }
            if looked_at.saturating_sub(last_rx) > opts.peer_timeout.as_nanos() as u64 {
                return Err(PlantError::Protocol(format!(
                    "the drive at {} has been silent for {:?}",
                    b.drive, opts.peer_timeout
                )));
            }
            if termination_requested() {
                return Err(PlantError::Terminated);
            }
            if spin_from.is_none_or(|t| t == u64::MAX) || now > give_up {
                wait_readable(wire.raw_fd(), 1);
            } else {
                std::hint::spin_loop();
            }
        };
        // The newest is the last sample accepted: its drive timestamp is the link's.
        let newest_stamp = link.sample_timestamp_ns;
        if last_state.is_some_and(|prev| st.seq <= prev.seq) {
            // The silence fault state took this index: a drive that resumes continues
            // after it, never publishing an index twice.
            stats.superseded += 1;
            continue;
        }
        if out.silent {
            // The drive speaks again. Forwarding resumes: the drive's own watchdog decides
            // whether its outputs come back (one that missed its commands has latched a
            // fault until RESET, and reports it in every sample). On this VM the emulated
            // drive is the one that goes quiet when the host stalls its CPU, and its time
            // pauses with it: nothing was missed.
            out.silent = false;
            tracing::warn!(
                silent_ms = (rx_at - last_rx) as f64 * 1e-6,
                drive_faults = st.fault >> 16,
                "the drive speaks again; forwarding commands again"
            );
        }
        if let Some(prev) = last_state {
            stats.period.record(rx_at.saturating_sub(prev.deadline_ns));
        }
        let last = st.seq + 1 >= n;
        if last {
            st.flags |= state_flags::LAST;
        }
        out.bus_v = st.bus_voltage_v;
        st.publish_time_ns = monotonic_ns();
        send(&states, st)?;
        // With real-time priorities the current loop, one above on this CPU, preempts us
        // here and has answered when notify returns.
        notify(&ready)?;
        stats.cycles += 1;
        stats.compute.record(monotonic_ns() - rx_at);
        out.forward(&commands, &plans, &mut link, &mut wire, &mut stats)?;
        if b.wait == WaitStrategy::Sleep {
            // Without them nothing orders its answer before our next wake-up: look for it
            // every ANSWER_CHECK_NS until it is out, a frame lands, or most of the period
            // has gone.
            let until = rx_at + period_ns * 8 / 10;
            while out.answered.is_none_or(|a| a < st.seq) {
                let now = monotonic_ns();
                if now >= until
                    || wait_readable_ns(wire.raw_fd(), (until - now).min(ANSWER_CHECK_NS))
                {
                    break;
                }
                out.forward(&commands, &plans, &mut link, &mut wire, &mut stats)?;
            }
        }
        if stats.cycles % stats_every == 0 {
            link.copy_counters(&mut stats);
            publish_stats(&stats_pub, &mut stats, false)?;
        }
        last_rx = rx_at;
        last_state = Some(st);
        due = Some(arrivals.next_due(newest_stamp, rx_at));
        if last {
            break;
        }
    }
    send_frame(
        &mut wire,
        &link.control_frame(Action::Disable, monotonic_ns()),
    );
    link.copy_counters(&mut stats);
    publish_stats(&stats_pub, &mut stats, true)?;
    tracing::info!(
        crc_errors = link.crc_errors,
        bad_frames = link.bad_frames,
        rejected = link.rejected_commands,
        lost = link.lost_on_wire,
        superseded = stats.superseded,
        "bridge done"
    );
    Ok(*stats)
}

/// When the drive's next sample is due, in host time. Every SAMPLE carries the drive's
/// timestamp, so the next one leaves one period after it (whatever the drive did before,
/// pauses included); it lands the transport delay later. That delay, which also absorbs the
/// offset between the two clocks, is the smallest seen: a sample can be held up on the way,
/// never sped up. The estimate may grow by `CREEP_NS` a period so that it follows a drive
/// clock running slow against the host's (up to 0.2 % at 20 kHz).
#[derive(Debug, Clone, Copy)]
pub struct ArrivalClock {
    period_ns: u64,
    /// Host time minus drive time of the fastest recent delivery, ns.
    delay_ns: Option<i64>,
}

/// How far a period the delay estimate may grow.
const CREEP_NS: i64 = 100;

impl ArrivalClock {
    pub fn new(period_ns: u64) -> Self {
        Self {
            period_ns,
            delay_ns: None,
        }
    }

    /// A sample stamped `drive_ns` by the drive arrived at host time `at`: returns when the
    /// next one is due.
    pub fn next_due(&mut self, drive_ns: u64, at: u64) -> u64 {
        let delay = at.wrapping_sub(drive_ns) as i64;
        let d = self.delay_ns.map_or(delay, |d| delay.min(d + CREEP_NS));
        self.delay_ns = Some(d);
        drive_ns.wrapping_add(self.period_ns).wrapping_add(d as u64)
    }
}

/// The host → drive side of the bridge: what the current loop publishes goes out as frames.
struct Outbox {
    /// (frame seq, send time) of recent COMMAND frames, for the round trip.
    sent_at: [(u32, u64); 64],
    /// The newest sample a command has answered.
    answered: Option<u64>,
    /// The newest plan received (~2 KB, kept in place), and the sample the last PLAN sent
    /// continued from.
    plan: DrivePlan,
    plan_sent: Option<u64>,
    plan_every: u64,
    /// While the drive is silent (no sample for its silence periods) nothing is forwarded.
    silent: bool,
    /// The measured bus voltage of the last sample (volts → duty).
    bus_v: f64,
}

impl Outbox {
    /// Forwards every command queued, then the newest plan if it is `plan_every` samples
    /// newer than the last one sent (nothing while silent).
    fn forward(
        &mut self,
        commands: &Sub<DriveCommand>,
        plans: &Sub<DrivePlan>,
        link: &mut DriveLink,
        wire: &mut Wire,
        stats: &mut StatsReport,
    ) -> Result<(), PlantError> {
        self.forward_commands(commands, link, wire, stats)?;
        drain(plans, |p| {
            if p.len > 0 && (self.plan.len == 0 || p.answers_seq > self.plan.answers_seq) {
                self.plan = *p;
            }
        })?;
        let due = self
            .plan_sent
            .is_none_or(|sent| self.plan.answers_seq >= sent + self.plan_every);
        if self.plan.len > 0 && due && !self.silent {
            if let Some(f) = link.plan_frame(&self.plan, self.bus_v, monotonic_ns()) {
                send_frame(wire, &f);
            }
            self.plan_sent = Some(self.plan.answers_seq);
        }
        Ok(())
    }

    fn forward_commands(
        &mut self,
        commands: &Sub<DriveCommand>,
        link: &mut DriveLink,
        wire: &mut Wire,
        stats: &mut StatsReport,
    ) -> Result<(), PlantError> {
        while let Some(c) = try_receive(commands)? {
            stats
                .sensor_to_actuator
                .record(c.publish_time_ns.saturating_sub(c.state_publish_time_ns));
            self.answered = self.answered.max(Some(c.answers_seq));
            if self.silent {
                continue;
            }
            if let Some(f) = link.command_frame(&c, self.bus_v, monotonic_ns()) {
                send_frame(wire, &f);
                self.sent_at[(f.seq % 64) as usize] = (f.seq, monotonic_ns());
            }
        }
        Ok(())
    }

    /// A sample reported command frame `seq` applied: records the round trip once.
    fn round_trip(&mut self, seq: u32, now: u64, stats: &mut StatsReport) {
        let slot = &mut self.sent_at[(seq % 64) as usize];
        if slot.0 == seq && slot.1 != 0 {
            stats.round_trip.record(now - slot.1);
            slot.1 = 0;
        }
    }
}

/// Sleeps until `fd` is readable or `timeout_ms` passes (EINTR just returns).
fn wait_readable(fd: RawFd, timeout_ms: i32) {
    wait_readable_ns(fd, timeout_ms as u64 * 1_000_000);
}

/// Sleeps until `fd` is readable (true) or `timeout_ns` passes (false; EINTR too).
fn wait_readable_ns(fd: RawFd, timeout_ns: u64) -> bool {
    let mut pfd = libc::pollfd {
        fd,
        events: libc::POLLIN,
        revents: 0,
    };
    let ts = libc::timespec {
        tv_sec: (timeout_ns / 1_000_000_000) as libc::time_t,
        tv_nsec: (timeout_ns % 1_000_000_000) as libc::c_long,
    };
    // SAFETY: one valid pollfd and timespec; no signal mask change.
    unsafe { libc::ppoll(&mut pfd, 1, &ts, std::ptr::null()) > 0 }
}

/// How often a bridge without real-time priority looks for the current loop's answer.
const ANSWER_CHECK_NS: u64 = 20_000;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::drive_protocol::{frame_bytes as bytes, Sample};
    use crate::drive_units::default_config;

    fn sample(counts: i32) -> Message {
        Message::Sample(Sample {
            encoder_counts: counts,
            adc_a: 32768 + 1510,
            adc_b: 32768,
            adc_bus: 2400,
            duty_a: 16384,
            duty_b: 0,
            applied_command_seq: 0,
            fault_bits: 0,
            status: 0,
        })
    }

    #[test]
    fn samples_become_si_states_and_bad_frames_are_dropped() {
        let mut l = DriveLink::new(20_000.0, 400.0, zero_offset());
        assert_eq!(
            l.on_frame(&bytes(9, sample(5)), 0),
            Event::Dropped,
            "no CONFIG yet"
        );
        let cfg = default_config(20_000.0, 200, 200);
        assert!(matches!(
            l.on_frame(&bytes(0, Message::Config(cfg)), 0),
            Event::Config(_)
        ));
        let Event::State(st) = l.on_frame(&bytes(100, sample(1 << 18)), 7) else {
            panic!()
        };
        assert_eq!(st.seq, 0);
        assert!((st.theta_rad - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        assert!((st.i_a_a - 0.151).abs() < 1e-9);
        assert!((st.bus_voltage_v - 24.0).abs() < 1e-9);
        assert!((st.v_a_v - 12.0).abs() < 1e-3);
        assert_eq!(st.deadline_ns, 7);
        // Corrupted: counted, no state.
        let mut bad = bytes(101, sample(0));
        bad[25] ^= 4;
        assert_eq!(l.on_frame(&bad, 0), Event::Dropped);
        assert_eq!(l.crc_errors, 1);
        // Duplicate and out of order: counted, no state.
        assert_eq!(l.on_frame(&bytes(100, sample(0)), 0), Event::Dropped);
        assert_eq!(l.on_frame(&bytes(99, sample(0)), 0), Event::Dropped);
        assert_eq!(l.bad_frames, 3);
        // A gap is visible in the index; counter wrap-around unwraps.
        let Event::State(st) = l.on_frame(&bytes(103, sample(i32::MAX)), 0) else {
            panic!()
        };
        assert_eq!(st.seq, 3);
        let Event::State(st2) = l.on_frame(&bytes(104, sample(i32::MIN)), 0) else {
            panic!()
        };
        assert!(st2.theta_rad > st.theta_rad);
    }

    /// The due time follows the drive's own timestamps (a pause of the drive moves it at
    /// once), plus the fastest delivery seen; a slower delivery does not move it, a steadily
    /// growing delay (a slow drive clock) is followed at CREEP_NS a period.
    #[test]
    fn arrival_clock_follows_the_drive_timestamps() {
        let mut c = ArrivalClock::new(50_000);
        // Drive clock 7 ms behind the host's, 3 µs on the way.
        let host = |drive: u64, on_the_way: u64| drive + 7_000_000 + on_the_way;
        assert_eq!(
            c.next_due(1_000_000, host(1_000_000, 3_000)),
            host(1_050_000, 3_000)
        );
        // Held up 20 µs on the way: the next is still due 3 µs after it leaves.
        assert_eq!(
            c.next_due(1_050_000, host(1_050_000, 23_000)),
            host(1_100_000, 3_000 + CREEP_NS as u64)
        );
        // The drive paused 400 µs: its timestamp says so.
        assert_eq!(
            c.next_due(1_500_000, host(1_500_000, 3_000)),
            host(1_550_000, 3_000)
        );
        // A drive clock 1 µs a period slower than the host's: the delay estimate follows.
        let mut due = 0;
        for k in 0..200u64 {
            let sent = 2_000_000 + k * 50_000;
            due = c.next_due(sent, host(sent, 3_000 + k * 1_000));
        }
        assert!(due >= host(2_000_000 + 200 * 50_000, 3_000 + 199 * CREEP_NS as u64 - 1));
    }

    fn zero_offset() -> EncoderCalibration {
        EncoderCalibration {
            offset_counts: Some(0),
            reverse: false,
        }
    }

    /// A configured offset is θ = 0 and `reverse` flips CONFIG's direction; without an
    /// offset the first sample is θ = 0.
    #[test]
    fn encoder_calibration_overrides() {
        let quarter: i32 = 1 << 18; // a quarter turn of the 20-bit encoder
        let theta_of = |cal: EncoderCalibration, counts: &[i32]| {
            let mut l = DriveLink::new(20_000.0, 400.0, cal);
            l.on_frame(
                &bytes(0, Message::Config(default_config(20_000.0, 200, 0))),
                0,
            );
            let mut theta = f64::NAN;
            for (i, &c) in counts.iter().enumerate() {
                if let Event::State(st) = l.on_frame(&bytes(10 + i as u32, sample(c)), 0) {
                    theta = st.theta_rad;
                }
            }
            theta
        };
        let half_pi = std::f64::consts::FRAC_PI_2;
        let offset = |o: i64, reverse| EncoderCalibration {
            offset_counts: Some(o),
            reverse,
        };
        let q = i64::from(quarter);
        assert!((theta_of(offset(q, false), &[2 * quarter]) - half_pi).abs() < 1e-12);
        assert!((theta_of(offset(q, true), &[2 * quarter]) + half_pi).abs() < 1e-12);
        let first = EncoderCalibration::default();
        assert!((theta_of(first, &[quarter, 2 * quarter]) - half_pi).abs() < 1e-12);
    }

    #[test]
    fn bad_commands_are_never_sent() {
        let mut l = DriveLink::new(20_000.0, 400.0, zero_offset());
        l.on_frame(
            &bytes(0, Message::Config(default_config(20_000.0, 200, 200))),
            0,
        );
        l.on_frame(&bytes(50, sample(0)), 0);
        let c = |va: f64| DriveCommand {
            answers_seq: 0,
            v_a_v: va,
            v_b_v: 0.0,
            ..Default::default()
        };
        assert!(l.command_frame(&c(f64::NAN), 24.0, 0).is_none());
        assert!(l.command_frame(&c(f64::INFINITY), 24.0, 0).is_none());
        assert!(l.command_frame(&c(30.0), 24.0, 0).is_none());
        assert_eq!(l.rejected_commands, 3);
        let f = l.command_frame(&c(-12.0), 24.0, 0).expect("valid");
        let Message::Command(cmd) = f.message else {
            panic!()
        };
        assert_eq!((cmd.answers_sample, cmd.duty_a), (50, -16384));
    }
}
