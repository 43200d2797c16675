//! Several axes of one stack moved as one machine: a coordinated move, in which every axis
//! leaves on the same position-loop tick and arrives on the same tick (the slowest axis,
//! within its move limits, sets the duration; the others are stretched within theirs), and
//! a stream of several axes, in which one stream time is one instant on every axis
//! ([`Group::stream`]).
//!
//! ```no_run
//! use stepdrive_client::Group;
//! use std::time::Duration;
//!
//! # fn main() -> Result<(), stepdrive_client::ClientError> {
//! let mut xyz = Group::connect("stepdrive", &[0, 1, 2])?;
//! xyz.enable()?;
//! let mv = xyz.move_together(&[1.0, -6.0, 12.0])?;
//! println!("all three left at t = {:.4} s", mv.acks[0].t_s);
//! let arrived = xyz.wait_arrived(&mv, Duration::from_secs(10))?;
//! println!("peak contour error {:.2e} rad", arrived[0].contour_rad);
//! # Ok(())
//! # }
//! ```
//!
//! The move goes as one request per axis, each on its axis's command service and each
//! naming every axis of the move. The stack's position loop keeps each part unanswered
//! until all have come (50 ms at most), then starts the move and answers every part on one
//! tick, or refuses every part with one reason (an axis not enabled, a target outside its
//! soft limits, a coordinated move already running). Through a gateway too
//! ([`Group::connect_remote`]): it forwards the parts without waiting for their answers.

use crate::{Axis, ClientError, Move, Stream, REQUEST_TIMEOUT};
use std::time::{Duration, Instant};
use stepdrive_shared::axis::{request_flags, AxisRequest};
pub use stepdrive_shared::axis::{AxisAck, AxisStatus, Refusal, RequestKind};

/// The most axes a stack has, and a coordinated move moves.
pub const MAX_AXES: usize = stepdrive_shared::scenario::MAX_AXES;

/// Some axes of one served stack (see the module documentation).
pub struct Group {
    /// In the order given to [`Group::connect`].
    axes: Vec<Axis>,
    indices: Vec<u32>,
}

/// A coordinated move that was taken: every part's answer, in the group's order.
#[derive(Debug, Clone, PartialEq)]
pub struct GroupMove {
    /// The sequence number every part carries (each axis's status `last_seq` while it is
    /// its newest command).
    pub seq: u64,
    pub acks: Vec<AxisAck>,
}

impl Group {
    /// Connects to axes `indices` (each once, 1 … 8 of them) of the stack on `instance`, as
    /// [`Axis::connect`] does each.
    pub fn connect(instance: &str, indices: &[u32]) -> Result<Self, ClientError> {
        Self::of(indices, |i| Axis::connect(instance, i))
    }

    /// The same through the `stepdrive gateway` at `endpoint`, as
    /// [`Axis::connect_remote`] does each axis.
    pub fn connect_remote(
        endpoint: &str,
        instance: &str,
        indices: &[u32],
    ) -> Result<Self, ClientError> {
        Self::of(indices, |i| Axis::connect_remote(endpoint, instance, i))
    }

    fn of(
        indices: &[u32],
        connect: impl Fn(u32) -> Result<Axis, ClientError>,
    ) -> Result<Self, ClientError> {
        if indices.is_empty() || indices.len() > MAX_AXES {
            return Err(ClientError::BadGroup(format!(
                "a group has 1 … {MAX_AXES} axes, not {}",
                indices.len()
            )));
        }
        for (k, i) in indices.iter().enumerate() {
            if *i as usize >= MAX_AXES {
                return Err(ClientError::BadGroup(format!(
                    "no axis {i}: a stack has axes 0 … {}",
                    MAX_AXES - 1
                )));
            }
            if indices[..k].contains(i) {
                return Err(ClientError::BadGroup(format!("axis {i} is named twice")));
            }
        }
        let axes = indices
            .iter()
            .map(|&i| connect(i))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(Self {
            axes,
            indices: indices.to_vec(),
        })
    }

    /// The group's axes' indices in the stack, in the group's order.
    pub fn indices(&self) -> &[u32] {
        &self.indices
    }

    /// The group's axes, in the group's order.
    pub fn axes_mut(&mut self) -> &mut [Axis] {
        &mut self.axes
    }

    /// The group's `k`-th axis, to command on its own.
    pub fn axis(&mut self, k: usize) -> Option<&mut Axis> {
        self.axes.get_mut(k)
    }

    /// Enables every axis of the group, one after the other.
    pub fn enable(&mut self) -> Result<(), ClientError> {
        for axis in &mut self.axes {
            axis.enable()?;
        }
        Ok(())
    }

    /// Moves every axis to its target (`targets[k]` for the group's `k`-th axis, rad,
    /// absolute) at its move limits (`[axis] move_*`), all leaving on one tick and arriving
    /// on one tick. Refused as a whole, with nothing applied to any axis, if any axis
    /// cannot take its part.
    pub fn move_together(&mut self, targets: &[f64]) -> Result<GroupMove, ClientError> {
        one_per_axis(
            "a coordinated move",
            "targets",
            self.axes.len(),
            targets.len(),
        )?;
        let (seq, acks) = self.send_parts("coordinated move", |r, k| {
            r.kind = RequestKind::Move as u32;
            r.target_rad = targets[k];
        })?;
        Ok(GroupMove { seq, acks })
    }

    /// Starts a stream on every axis of the group, all on one tick and all played from one
    /// origin, so that one stream time is one instant on every axis: each axis plays stream
    /// time `t` at the same tick, `lead` s (default: each axis's `[axis] stream_lead_s`, or
    /// through a gateway [`crate::remote::REMOTE_STREAM_LEAD_S`]) after the tick by which
    /// every axis had its first point. Refused as a whole if any axis cannot stream (not
    /// enabled, a lead out of range).
    pub fn stream(&mut self, lead: Option<f64>) -> Result<GroupStream<'_>, ClientError> {
        let mut refused_before = Vec::with_capacity(self.axes.len());
        for axis in &mut self.axes {
            axis.link.open_stream()?;
            refused_before.push(axis.status()?.refused_points);
        }
        let remote = self.axes.iter().any(|a| a.endpoint().is_some());
        let lead = lead.or(remote.then_some(crate::remote::REMOTE_STREAM_LEAD_S));
        let (seq, acks) = self.send_parts("stream of several axes", |r, _| {
            r.kind = RequestKind::StreamStart as u32;
            if let Some(l) = lead {
                r.lead_s = l;
                r.flags |= request_flags::HAS_LEAD;
            }
        })?;
        let streams = self
            .axes
            .iter_mut()
            .zip(&acks)
            .zip(refused_before)
            .map(|((axis, ack), refused)| Stream::new(axis, seq, ack.tick, refused))
            .collect();
        Ok(GroupStream { streams })
    }

    /// Sends one part to every axis of the group (`part` fills axis `k`'s request), all
    /// with one sequence number, and waits for every answer; any part refused is an error.
    fn send_parts(
        &mut self,
        what: &'static str,
        part: impl Fn(&mut AxisRequest, usize),
    ) -> Result<(u64, Vec<AxisAck>), ClientError> {
        let group = self.indices.iter().fold(0u32, |g, &i| g | (1 << i));
        // One sequence number for every part: the stack matches them by it.
        let seq = self.axes.iter().map(|a| a.next_seq).max().unwrap_or(0) + 1;
        let mut sent = Vec::with_capacity(self.axes.len());
        for (k, axis) in self.axes.iter_mut().enumerate() {
            let mut r = axis.request(RequestKind::Move);
            axis.next_seq = seq;
            // The stack matches the parts by client and sequence number: through a gateway
            // each axis has its own client id, so the group's is the sequence number's.
            r.seq = seq;
            r.client = (seq >> 32) as u32;
            part(&mut r, k);
            r.flags = request_flags::with_group(r.flags, group);
            r.publish_time_ns = stepdrive_runtime::clock::monotonic_ns();
            sent.push(axis.link.send(&r)?);
        }
        let deadline = Instant::now() + REQUEST_TIMEOUT;
        let mut acks = Vec::with_capacity(sent.len());
        for pending in sent {
            acks.push(pending.wait(deadline)?);
        }
        if let Some((k, ack)) = acks.iter().enumerate().find(|(_, a)| !a.taken()) {
            // The stack's reason names the axis when the axis is the cause.
            let reason = if ack.text().starts_with("axis ") {
                ack.text().to_string()
            } else {
                format!("axis {}'s part: {}", self.indices[k], ack.text())
            };
            return Err(ClientError::Refused {
                kind: what,
                refusal: Refusal::from_u32(ack.refusal).unwrap_or(Refusal::UnknownCommand),
                reason,
            });
        }
        Ok((seq, acks))
    }

    /// Waits until every axis of `mv` has reached its target; fails if one faults or
    /// another command takes one over. Each axis's status at its arrival, in the group's
    /// order.
    pub fn wait_arrived(
        &mut self,
        mv: &GroupMove,
        timeout: Duration,
    ) -> Result<Vec<AxisStatus>, ClientError> {
        let deadline = Instant::now() + timeout;
        self.axes
            .iter_mut()
            .zip(&mv.acks)
            .map(|(axis, ack)| {
                let part = Move {
                    seq: mv.seq,
                    ack: *ack,
                };
                axis.wait_target_reached(&part, deadline.saturating_duration_since(Instant::now()))
            })
            .collect()
    }
}

/// `given` values for `what` of `axes` axes: one per axis, or the error that says so.
fn one_per_axis(what: &str, values: &str, axes: usize, given: usize) -> Result<(), ClientError> {
    if given == axes {
        return Ok(());
    }
    Err(ClientError::BadGroup(format!(
        "{what} of {axes} axes takes {axes} {values}, not {given}"
    )))
}

/// A stream of several axes in progress ([`Group::stream`]): one stream time, a position
/// for each axis.
pub struct GroupStream<'a> {
    streams: Vec<Stream<'a>>,
}

impl GroupStream<'_> {
    /// Sends the points at stream time `t` s: `thetas[k]` rad for the group's `k`-th axis.
    /// Time must increase and every value be finite: otherwise nothing is sent.
    pub fn push(&mut self, t: f64, thetas: &[f64]) -> Result<(), ClientError> {
        one_per_axis(
            "a stream",
            "positions a point",
            self.streams.len(),
            thetas.len(),
        )?;
        if !thetas.iter().all(|v| v.is_finite()) {
            return Err(ClientError::BadPoint {
                t,
                why: "not finite",
            });
        }
        for (stream, &theta) in self.streams.iter_mut().zip(thetas) {
            stream.push(t, theta, None, None)?;
        }
        Ok(())
    }

    /// Waits until every axis is ready for the point at stream time `t` ([`Stream::pace`]).
    pub fn pace(&mut self, t: f64) -> Result<(), ClientError> {
        for stream in &mut self.streams {
            stream.pace(t)?;
        }
        Ok(())
    }

    /// [`Self::pace`], then [`Self::push`].
    pub fn push_paced(&mut self, t: f64, thetas: &[f64]) -> Result<(), ClientError> {
        self.pace(t)?;
        self.push(t, thetas)
    }

    /// Each axis's newest status read while pacing, in the group's order.
    pub fn last_statuses(&self) -> Vec<Option<&AxisStatus>> {
        self.streams.iter().map(|s| s.last_status()).collect()
    }

    /// Fails with [`ClientError::StreamLimited`] if any axis could not follow its part of
    /// the stream within its limits so far ([`Stream::followed`]).
    pub fn followed(&self) -> Result<(), ClientError> {
        self.streams.iter().try_for_each(Stream::followed)
    }

    /// Whether any axis's part ran dry at some status read ([`Stream::ran_dry`]).
    pub fn ran_dry(&self) -> bool {
        self.streams.iter().any(Stream::ran_dry)
    }

    /// Waits until every axis has played every point sent ([`Stream::played_out`]).
    pub fn played_out(&mut self) -> Result<(), ClientError> {
        for stream in &mut self.streams {
            stream.played_out()?;
        }
        Ok(())
    }

    /// Ends every axis's stream at once: each decelerates to rest and holds (call
    /// [`Self::played_out`] first to have the whole path played).
    pub fn end(self) -> Result<Vec<AxisAck>, ClientError> {
        self.streams.into_iter().map(|s| s.end()).collect()
    }
}
