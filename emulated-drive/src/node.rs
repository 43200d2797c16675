//! The emulated drive as a node of the runner, on its own clock (a drive's sample clock;
//! when the host holds the process its time pauses, [`Late::Pause`]): each period it takes
//! the frames that arrived, sends its SAMPLE (through the [`Injector`]'s faults), and applies
//! the period's duties. Its port is its wire.

use crate::inject::{send_frame, Before, Injector};
use crate::truth::TruthWriter;
use crate::{EmulatedDrive, Reply};
use std::time::Duration;
use stepdrive_drive_protocol::transport::Wire;
use stepdrive_drive_protocol::{faults, Message, MAX_FRAME};
use stepdrive_runtime::node::{Cx, Flow, Late, Node, Pace, Poll, Role, Start};
use stepdrive_runtime::pacer::sleep_until;
use stepdrive_runtime::RunError;
use stepdrive_shared::Scenario;

pub struct DriveNode {
    core: EmulatedDrive,
    inject: Injector,
    truth: Option<TruthWriter>,
    period_ns: u64,
    rate_hz: f64,
    /// Stop after this long from the start (None: until SIGINT/SIGTERM).
    duration: Option<Duration>,
    started_ns: u64,
    /// Samples sent since start-up (the SAMPLE's index).
    sample_seq: u32,
    /// The session's ENABLE: injection times count from it.
    running_since: Option<u64>,
    tx: [u8; MAX_FRAME],
    /// One byte more than the largest frame: a longer datagram arrives truncated to a
    /// length the decoder rejects, instead of fitting by accident.
    rx: [u8; MAX_FRAME + 1],
}

impl DriveNode {
    pub fn new(
        s: &Scenario,
        core: EmulatedDrive,
        inject: Injector,
        truth: Option<TruthWriter>,
    ) -> Self {
        Self {
            core,
            inject,
            truth,
            period_ns: s.sample_period_ns(),
            rate_hz: s.rates.current_loop_hz,
            duration: None,
            started_ns: 0,
            sample_seq: 0,
            running_since: None,
            tx: [0; MAX_FRAME],
            rx: [0; MAX_FRAME + 1],
        }
    }

    /// Stops after `d` (None: runs until SIGINT/SIGTERM).
    pub fn lasting(mut self, d: Option<Duration>) -> Self {
        self.duration = d;
        self
    }

    pub fn core(&self) -> &EmulatedDrive {
        &self.core
    }
}

/// Each axis's drive is on its own in a multi-axis emulator.
impl stepdrive_runtime::lanes::Together for DriveNode {}

impl Node for DriveNode {
    type Ports = Wire;

    fn role(&self) -> Role {
        Role::EmulatedDrive
    }

    fn pace(&self) -> Pace {
        Pace::Clock {
            period_ns: self.period_ns,
            // Like the simulated plant: a host stall pauses the drive's time.
            late: Late::Pause,
        }
    }

    fn rate_hz(&self) -> f64 {
        self.rate_hz
    }

    fn awaiting(&self) -> String {
        "a host's HELLO".to_string()
    }

    fn start(&mut self, _wire: &mut Wire, cx: &mut Cx) -> Result<Start, RunError> {
        self.started_ns = cx.now();
        Ok(Start::Ready {
            epoch_ns: Some(self.started_ns + self.period_ns),
        })
    }

    /// Takes the frames that arrived. A host that went away is no error for a drive: it
    /// waits for the next HELLO, so it is never waiting on a peer.
    fn poll(&mut self, wire: &mut Wire, cx: &mut Cx) -> Result<Poll, RunError> {
        while let Ok(Some((n, from))) = wire.recv(&mut self.rx, 0) {
            let bytes = &self.rx[..n];
            let config = match (&mut *wire, from) {
                (Wire::Udp { peer, .. }, Some(from)) => self.core.on_datagram(bytes, from, peer),
                _ => self.core.on_frame(bytes).map(|Reply::Config(c)| c),
            };
            if let Some(c) = config {
                self.running_since = None;
                let f = self.core.report_frame(Message::Config(c), cx.now());
                send_frame(wire, &f, &mut self.tx);
            }
        }
        Ok(Poll::READY)
    }

    /// One period: the SAMPLE out (as the injected faults have it), the period's duties
    /// applied, a FAULT_REPORT for newly latched faults.
    fn step(&mut self, wire: &mut Wire, cx: &mut Cx) -> Result<Flow, RunError> {
        if let Some(d) = self.duration {
            if cx.woke_ns.saturating_sub(self.started_ns) > d.as_nanos() as u64 {
                return Ok(Flow::Last);
            }
        }
        if !self.core.in_session() {
            return Ok(Flow::Continue);
        }
        // Injection times count from the run's first sample (after the host's alignment
        // checks), not from the HELLO: the alignment and the stack's start-up before it
        // take varying time.
        if !self.core.in_run() {
            self.running_since = None;
        } else if self.running_since.is_none() {
            self.running_since = Some(cx.woke_ns);
        }
        let t_s = self
            .running_since
            .map_or(-1.0, |since| (cx.woke_ns - since) as f64 * 1e-9);
        match self.inject.before(t_s) {
            Before::Go => {}
            Before::Overcurrent => {
                if self.core.latched_faults() & faults::OVERCURRENT == 0 {
                    self.core.trip(faults::OVERCURRENT);
                    tracing::warn!("injected over-current: outputs off, fault latched");
                }
            }
            Before::Freeze { ns } => {
                tracing::warn!(ms = ns as f64 * 1e-6, "injected freeze");
                // Its time pauses with it, as after any host stall (`Late::Pause`).
                sleep_until(cx.now() + ns);
                return Ok(Flow::Continue);
            }
        }
        let now = cx.now();
        let frame = self.core.sample_frame(now);
        if let (Some(w), Some(row)) = (self.truth.as_mut(), self.core.truth(frame.seq)) {
            w.push(row);
        }
        let k = u64::from(self.sample_seq) + 1;
        self.inject
            .send_sample(wire, &frame, k, t_s, now, &mut self.tx);
        if let Some(report) = self.core.run_period(frame.seq) {
            tracing::warn!(
                faults = report.fault_bits,
                "drive fault latched: outputs off until RESET"
            );
            let f = self
                .core
                .report_frame(Message::FaultReport(report), cx.now());
            send_frame(wire, &f, &mut self.tx);
        }
        self.sample_seq = self.sample_seq.wrapping_add(1);
        if let Some(at) = self.inject.delayed_due(cx.deadline_ns + self.period_ns) {
            sleep_until(at);
            self.inject.send_delayed(wire, &mut self.tx);
        }
        Ok(Flow::Continue)
    }

    fn latched_fault(&self) -> u32 {
        u32::from(self.core.latched_faults())
    }

    fn stop(&mut self, _wire: &mut Wire, _cx: &mut Cx) {
        let c = self.core.counters;
        tracing::info!(
            ?c,
            faults = self.core.latched_faults(),
            "emulated drive stopped"
        );
        if let Some(w) = self.truth.take() {
            let (path, dropped) = (w.path().to_path_buf(), w.dropped);
            match w.finish() {
                Ok(rows) => tracing::info!(rows, dropped, path = %path.display(), "truth written"),
                Err(e) => {
                    tracing::error!(path = %path.display(), "cannot write the truth file: {e}")
                }
            }
        }
        eprintln!(
            "drive: frames ok {}, CRC errors {}, bad {}, stale {}, foreign {}, commands applied {}, late commands discarded {}, periods without their command {} (PLAN entry applied in {}), controls ignored {}, latched faults {:#06x}",
            c.frames_ok, c.crc_errors, c.bad_frames, c.stale_frames, c.foreign_frames, c.commands_applied, c.commands_late, c.periods_held, c.periods_planned, c.ignored_controls, self.core.latched_faults()
        );
    }
}
