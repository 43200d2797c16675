//! The hardware back-end of the plant process: a bridge between the stack's services and a
//! drive speaking `docs/drive-protocol.md` over UDP. Units and calibration live here and
//! only here; the current loop, position loop and monitor see the same `DriveState` and
//! `DriveCommand` as with the simulated plant. The drive's sample clock paces everything.

use crate::drive_protocol::{
    decode, encode, is_newer, status, Action, Command, Config, DecodeError, FaultReport, Frame,
    Message, MAX_FRAME,
};
use crate::drive_units::{duty_for, volts_for, Scaling, VelocityObserver};
use crate::process::{wait_for_stack, PlantError, PlantOptions};
use crate::wire::{SerialPort, Wire};
use std::net::{SocketAddr, UdpSocket};
use std::time::Duration;
use stepdrive_shared::clock::monotonic_ns;
use stepdrive_shared::messages::{fault_bits, state_flags, DriveCommand, DriveState};
use stepdrive_shared::poll::termination_requested;
use stepdrive_shared::rt::RtOptions;
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::{
    connect, publish_stats, publisher, send, subscriber, try_receive, Topics, LOOP_BUFFER,
};
use stepdrive_shared::stats::{roles, StatsReport};

/// What one received datagram turned into.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Event {
    State(DriveState),
    Config(Config),
    Fault(FaultReport),
    /// Dropped: bad CRC, malformed, duplicate or out of order, or unexpected.
    Dropped,
}

/// Drive frames ↔ SI, without sockets or clocks.
pub struct DriveLink {
    scaling: Option<Scaling>,
    observer: VelocityObserver,
    observer_hz: f64,
    offset_counts_setting: Option<i64>,
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
    pub held_periods: u64,
    /// The drive's timestamp of the last accepted sample, ns on the drive's clock.
    pub sample_timestamp_ns: u64,
}

impl DriveLink {
    /// `offset_counts`: encoder reading at θ = 0; `None` zeroes at the first sample.
    pub fn new(sample_hz: f64, observer_hz: f64, offset_counts: Option<i64>) -> Self {
        Self {
            scaling: None,
            observer: VelocityObserver::new(observer_hz, 1.0 / sample_hz),
            observer_hz,
            offset_counts_setting: offset_counts,
            sample_hz,
            last_seq: None,
            first_seq: None,
            counts: 0,
            last_raw: None,
            offset_counts,
            tx_seq: 1,
            crc_errors: 0,
            bad_frames: 0,
            rejected_commands: 0,
            held_periods: 0,
            sample_timestamp_ns: 0,
        }
    }

    pub fn configured(&self) -> bool {
        self.scaling.is_some()
    }

    /// Forgets the sample stream (index, position, velocity, counters) so that run starts
    /// at k = 0 with the next sample; the configuration is kept.
    pub fn restart(&mut self) {
        let scaling = self.scaling;
        *self = Self {
            scaling,
            tx_seq: self.tx_seq,
            ..Self::new(self.sample_hz, self.observer_hz, self.offset_counts_setting)
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
                self.scaling = Some(Scaling::new(&c));
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
                if s.status & status::COMMAND_HELD != 0 {
                    flags |= state_flags::COMMAND_HELD;
                    self.held_periods += 1;
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

    /// Puts the link's counters into a stats report (drive-held periods are its misses).
    pub fn copy_counters(&self, stats: &mut StatsReport) {
        stats.crc_errors = self.crc_errors;
        stats.bad_frames = self.bad_frames;
        stats.rejected_commands = self.rejected_commands;
        stats.misses = self.held_periods;
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
    /// No valid sample for this many periods: publish a fault and stop forwarding.
    pub silence_periods: u32,
    pub observer_hz: f64,
    pub offset_counts: Option<i64>,
}

/// Receives one frame: the first of a batch waiting up to 1 ms (woken by the kernel when
/// it lands), the rest without waiting. `None` when nothing (more) is there.
fn recv_frame(wire: &mut Wire, buf: &mut [u8], first: &mut bool) -> Option<usize> {
    let wait = if *first { 1 } else { 0 };
    *first = false;
    wire.recv(buf, wait).map(|(n, _)| n)
}

fn send_frame(wire: &mut Wire, f: &Frame) {
    let mut buf = [0u8; MAX_FRAME];
    let n = encode(f, &mut buf);
    wire.send(&buf[..n]);
}

/// Runs the bridge for the scenario's duration (hardware mode).
pub fn run_bridge(opts: &PlantOptions, b: &BridgeOptions) -> Result<StatsReport, PlantError> {
    let io = |e: std::io::Error| PlantError::Protocol(format!("drive socket: {e}"));
    let topics = Topics::open(&opts.instance, "plant", Mode::Hardware)?;
    let commands = subscriber(&topics.command, "drive/command", LOOP_BUFFER)?;
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
            // Blocking with a short timeout: a waiting recv is woken when a datagram lands.
            sock.set_read_timeout(Some(Duration::from_millis(1)))
                .map_err(io)?;
            Wire::Udp { sock, peer: None }
        }
        DriveAddr::Serial(path) => Wire::Serial(SerialPort::open(path).map_err(|e| {
            PlantError::Protocol(format!("cannot open serial port {}: {e}", path.display()))
        })?),
    };

    let s = &opts.scenario;
    let period_ns = s.sample_period_ns();
    let mut link = DriveLink::new(s.rates.current_loop_hz, b.observer_hz, b.offset_counts);
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
        if let Some((n, _)) = wire.recv(&mut rx, 1) {
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
    let mut sent_at = [(0u32, 0u64); 64];
    let mut last_rx = monotonic_ns();
    let mut last_state: Option<DriveState> = None;
    let mut silent = false;
    let silence_ns = u64::from(b.silence_periods) * period_ns;
    tracing::info!(samples = n, drive = %b.drive, "bridge running");
    // Each period: wait (woken by the kernel when a frame lands: no timer, whose wake-up
    // costs ~25 µs here; at most 1 ms, so the silence watchdog keeps running), take everything queued, publish the
    // newest sample, then poll for the current loop's answer for up to `answer_window` and
    // forward it. Never a continuous spin: the bridge shares a CPU with the drive
    // (emulated) or with the loops.
    let answer_window = period_ns * 6 / 10;
    // About once a second, for the monitor's progress line.
    let stats_every = (s.rates.current_loop_hz.round() as u64).max(1);
    let mut first_wait = true;
    'run: loop {
        if termination_requested() {
            return Err(PlantError::Terminated);
        }
        // Take everything queued; only the newest sample is published (older ones would
        // only draw late commands) and the skipped ones show up as lost.
        let mut newest: Option<(DriveState, u64)> = None;
        loop {
            while let Some(len) = recv_frame(&mut wire, &mut rx, &mut first_wait) {
                let now = monotonic_ns();
                match link.on_frame(&rx[..len], now) {
                    Event::State(st) => {
                        // The emulated drive shares this host's clock; for a real drive
                        // only the round trip below is meaningful.
                        stats
                            .hop
                            .record(now.saturating_sub(link.sample_timestamp_ns));
                        let q = st.applied_command_seq as u32;
                        let slot = &mut sent_at[(q % 64) as usize];
                        if slot.0 == q && slot.1 != 0 {
                            stats.round_trip.record(now - slot.1);
                            slot.1 = 0;
                        }
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
            if newest.is_some() {
                break;
            }
            first_wait = true;
            {
                let now = monotonic_ns();
                if termination_requested() {
                    return Err(PlantError::Terminated);
                }
                if !silent && now - last_rx > silence_ns {
                    silent = true;
                    tracing::error!(
                        periods = b.silence_periods,
                        "no valid sample from the drive: fault published, commands no longer forwarded"
                    );
                    if let Some(mut st) = last_state {
                        st.seq += 1;
                        st.fault |= fault_bits::DRIVE_SILENT;
                        st.publish_time_ns = now;
                        st.deadline_ns = now;
                        send(&states, st)?;
                        last_state = Some(st);
                    }
                }
                if now - last_rx > opts.peer_timeout.as_nanos() as u64 {
                    return Err(PlantError::Protocol(format!(
                        "the drive at {} has been silent for {:?}",
                        b.drive, opts.peer_timeout
                    )));
                }
            }
        }
        if let Some((mut st, rx_at)) = newest {
            if silent {
                // Latched: once silent, the stack stays in fault for this run.
                st.fault |= fault_bits::DRIVE_SILENT;
            }
            if let Some(prev) = last_state {
                stats.lost += st.seq.saturating_sub(prev.seq + 1);
                stats.period.record(rx_at.saturating_sub(prev.deadline_ns));
            }
            let last = st.seq + 1 >= n;
            if last {
                st.flags |= state_flags::LAST;
            }
            st.publish_time_ns = monotonic_ns();
            send(&states, st)?;
            stats.cycles += 1;
            stats.compute.record(monotonic_ns() - rx_at);
            if stats.cycles % stats_every == 0 {
                link.copy_counters(&mut stats);
                publish_stats(&stats_pub, &mut stats, false)?;
            }
            last_rx = rx_at;
            last_state = Some(st);
            if last {
                break 'run;
            }
        }
        // The answer to the sample just published.
        let want = last_state.map_or(0, |st| st.seq);
        let until = monotonic_ns() + answer_window;
        loop {
            let mut answered = false;
            while let Some(c) = try_receive(&commands)? {
                let now = monotonic_ns();
                stats
                    .sensor_to_actuator
                    .record(c.publish_time_ns.saturating_sub(c.state_publish_time_ns));
                answered |= c.answers_seq >= want;
                if silent {
                    continue;
                }
                let bus = last_state.map_or(0.0, |st| st.bus_voltage_v);
                if let Some(f) = link.command_frame(&c, bus, now) {
                    send_frame(&mut wire, &f);
                    sent_at[(f.seq % 64) as usize] = (f.seq, monotonic_ns());
                }
            }
            if answered || monotonic_ns() > until {
                break;
            }
            std::hint::spin_loop();
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
        "bridge done"
    );
    Ok(*stats)
}

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
        let mut l = DriveLink::new(20_000.0, 400.0, Some(0));
        assert_eq!(
            l.on_frame(&bytes(9, sample(5)), 0),
            Event::Dropped,
            "no CONFIG yet"
        );
        let cfg = default_config(20_000.0, 200);
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

    #[test]
    fn bad_commands_are_never_sent() {
        let mut l = DriveLink::new(20_000.0, 400.0, Some(0));
        l.on_frame(&bytes(0, Message::Config(default_config(20_000.0, 200))), 0);
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
