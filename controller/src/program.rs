//! A scenario's program (`[[program]]`): its timed commands turned into the command
//! service's requests at their times, and the points of its streams, sent as a client
//! would send them (each at its own time, the stream played its lead behind). Everything is
//! read and built at start-up; on virtual time the program runs the same in every run.

use stepdrive_shared::axis::{
    parse_stream, request_flags, AxisAck, AxisRequest, AxisStreamPoint, ProgramCommand,
    RequestKind, StreamFileError,
};
use stepdrive_shared::Scenario;

/// A program that cannot run: a stream file it names.
#[derive(Debug, thiserror::Error)]
pub enum ProgramError {
    #[error("program step {step}: cannot read the stream file {file}")]
    Read {
        step: usize,
        file: String,
        #[source]
        source: std::io::Error,
    },
    #[error("program step {step}: stream file {file}")]
    Stream {
        step: usize,
        file: String,
        #[source]
        source: StreamFileError,
    },
}

/// A stream being sent: its points, the next, and the time its first went out.
struct Sending {
    points: Vec<AxisStreamPoint>,
    next: usize,
    started_s: f64,
}

/// See the module documentation.
#[derive(Default)]
pub struct Program {
    /// (time, request), in time order.
    steps: Vec<(f64, AxisRequest)>,
    next: usize,
    /// Each stream step's points, by the step's request seq.
    streams: Vec<(u64, Vec<AxisStreamPoint>)>,
    sending: Option<Sending>,
    /// Points handed out, a scratch buffer reused every tick.
    due: Vec<AxisStreamPoint>,
}

impl Program {
    /// `axis`: the index its requests carry (a multi-axis stack's position loop serves
    /// each axis's own steps).
    pub fn new(s: &Scenario, axis: u32) -> Result<Self, ProgramError> {
        let mut p = Program::default();
        for (i, step) in s.program.iter().enumerate() {
            // The request's seq is the step's number, from 1.
            let seq = i as u64 + 1;
            let mut r = AxisRequest {
                seq,
                axis,
                ..Default::default()
            };
            let kind = match step.command {
                ProgramCommand::Enable => RequestKind::Enable,
                ProgramCommand::Disable => RequestKind::DisableVoltage,
                ProgramCommand::QuickStop => RequestKind::QuickStop,
                ProgramCommand::Reset => RequestKind::FaultReset,
                ProgramCommand::Stop => RequestKind::Stop,
                ProgramCommand::Move => RequestKind::Move,
                ProgramCommand::Jog => RequestKind::Jog,
                ProgramCommand::SetPosition => RequestKind::SetPosition,
                ProgramCommand::Stream => RequestKind::StreamStart,
            };
            r.kind = kind as u32;
            r.target_rad = step.to.unwrap_or(0.0);
            r.velocity_rad_s = step.velocity.unwrap_or(0.0);
            if step.relative {
                r.flags |= request_flags::RELATIVE;
            }
            if step.after_current {
                r.flags |= request_flags::AFTER_CURRENT;
            }
            if step.coordinated {
                r.flags |= request_flags::COORDINATED;
            }
            for (value, flag, field) in [
                (step.vmax, request_flags::HAS_V, &mut r.v_max_rad_s),
                (step.amax, request_flags::HAS_A, &mut r.a_max_rad_s2),
                (step.jmax, request_flags::HAS_J, &mut r.j_max_rad_s3),
                (step.lead_s, request_flags::HAS_LEAD, &mut r.lead_s),
            ] {
                if let Some(v) = value {
                    *field = v;
                    r.flags |= flag;
                }
            }
            if let (ProgramCommand::Stream, Some(file)) = (step.command, &step.file) {
                let text = std::fs::read_to_string(file).map_err(|source| ProgramError::Read {
                    step: i,
                    file: file.clone(),
                    source,
                })?;
                let rows = parse_stream(&text).map_err(|source| ProgramError::Stream {
                    step: i,
                    file: file.clone(),
                    source,
                })?;
                let points = rows
                    .iter()
                    .enumerate()
                    .map(|(k, row)| row.point(0, seq, k as u64))
                    .collect();
                p.streams.push((seq, points));
            }
            p.steps.push((step.at_s, r));
        }
        // Stable: steps at the same time keep their order.
        p.steps.sort_by(|a, b| a.0.total_cmp(&b.0));
        let longest = p.streams.iter().map(|(_, v)| v.len()).max().unwrap_or(0);
        p.due = Vec::with_capacity(longest);
        Ok(p)
    }

    /// The next request due at time `t`, s.
    pub fn due(&mut self, t: f64) -> Option<AxisRequest> {
        let (at, r) = *self.steps.get(self.next)?;
        if at > t {
            return None;
        }
        self.next += 1;
        Some(r)
    }

    /// A request's answer: a stream taken starts sending its points.
    pub fn answered(&mut self, ack: &AxisAck) {
        if !ack.taken() || ack.request.kind != RequestKind::StreamStart as u32 {
            return;
        }
        if let Some(i) = self
            .streams
            .iter()
            .position(|(seq, _)| *seq == ack.request.seq)
        {
            let points = std::mem::take(&mut self.streams[i].1);
            self.sending = Some(Sending {
                points,
                next: 0,
                started_s: ack.t_s,
            });
        }
    }

    /// The points of the stream being sent whose time has come by `t` (a point goes out
    /// at its own time after the first).
    pub fn points_due(&mut self, t: f64) -> std::slice::Iter<'_, AxisStreamPoint> {
        self.due.clear();
        if let Some(s) = &mut self.sending {
            let origin = s.points.first().map_or(0.0, |p| p.t_s);
            while let Some(p) = s.points.get(s.next) {
                if p.t_s - origin > t - s.started_s {
                    break;
                }
                self.due.push(*p);
                s.next += 1;
            }
            if s.next == s.points.len() {
                self.sending = None;
            }
        }
        self.due.iter()
    }
}
