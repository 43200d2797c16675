//! The position loop as a node of the runner: each tick it takes the axis's commands (the
//! command service's, a stream's points, or the scenario's program at their times), runs
//! the axis and torque modulation (12) on the newest state, publishes the setpoint, then
//! answers the commands (so that an answer's time is the first setpoint that carries the
//! command out) and publishes the axis's status. On the wall clock a client's command also
//! rings its doorbell, and the tick comes at once. Its ports take the states by the stack's
//! policy (in lockstep every one in order); its ticks come from its input (every N-th
//! state) or from its own clock at the position rate, on the plant's deadline grid.

use crate::program::Program;
use stepdrive_control::axis::gather::{check_part, gather, missing, Part};
use stepdrive_control::axis::group::{newest_time, Axes, Coordinator, StopPolicy};
use stepdrive_control::axis::{Axis, Measured};
use stepdrive_control::position_loop::{measured, PositionLoop};
use stepdrive_runtime::inbox::Inbox;
use stepdrive_runtime::ipc::COMMANDS_PER_CYCLE;
use stepdrive_runtime::lanes::Together;
use stepdrive_runtime::node::{Awaits, Cx, Flow, Late, Node, Pace, Poll, Role, Start};
use stepdrive_runtime::port::{AxisServer, PortError, PortFactory, Presence, Publish, Subscribe};
use stepdrive_runtime::RunError;
use stepdrive_shared::axis::request_flags;
use stepdrive_shared::axis::{
    AxisAck, AxisRequest, AxisStatus, AxisStreamPoint, Refusal, RequestKind,
};
use stepdrive_shared::messages::{state_flags, DriveState, ResetRequest, TorqueSetpoint};
use stepdrive_shared::scenario::{GroupStop, Mode};
use stepdrive_shared::services::Topic;
use stepdrive_shared::stack::POSITION_LOOP;
use stepdrive_shared::Scenario;

/// Commands applied in one tick; more in the same tick are refused (a flood must not take
/// the loop's time). Each costs a few µs at most (a re-plan of the trajectory).
const APPLIED_PER_TICK: usize = 8;
/// A fault reset asks the device to reset at most this often, s.
const RESET_EVERY_S: f64 = 0.1;
/// How long a client's coordinated part waits for its partners, s (a client sends them
/// back to back, within a millisecond).
const PARTS_WAIT_S: f64 = 0.05;

/// What the position loop reads and writes.
pub struct PositionLoopPorts {
    pub states: Inbox<DriveState>,
    pub setpoints: Box<dyn Publish<TorqueSetpoint>>,
    pub status: Box<dyn Publish<AxisStatus>>,
    pub acks: Box<dyn Publish<AxisAck>>,
    pub stream: Box<dyn Subscribe<AxisStreamPoint>>,
    /// The command service (on the wall clock; a lockstep stack runs its program only).
    pub commands: Option<AxisServer>,
    /// A fault reset asks the device to clear its own latched fault too.
    pub resets: Box<dyn Publish<ResetRequest>>,
    pub presence: Box<dyn Presence>,
}

/// Lockstep: the queue of states between two ticks. Deep enough that the position loop
/// sleeps from tick to tick: at 16 it was woken every 8 samples to drain it, each time a
/// futex call in the plant's hand-off and a CPU taken from a spinning peer (the default
/// run 0.26-0.46 -> 0.15-0.33 s). The plant would wait on a full one.
const LOCKSTEP_STATE_QUEUE: usize = 1024;

impl PositionLoopPorts {
    pub fn open(f: &mut impl PortFactory, mode: Mode) -> Result<Self, PortError> {
        Ok(Self {
            // On the clock a tick wants the newest state only: a queue of one spares it
            // draining the ten that came since the last (4 axes: tick p50 13 -> 8 us).
            states: Inbox::open(
                f,
                &POSITION_LOOP,
                mode,
                match mode {
                    Mode::Lockstep => LOCKSTEP_STATE_QUEUE,
                    Mode::Realtime | Mode::Hardware => 1,
                },
            )?,
            setpoints: f.publisher()?,
            status: f.publisher()?,
            acks: f.publisher()?,
            stream: f.subscriber(256)?,
            commands: match mode {
                Mode::Lockstep => None,
                _ => f.command_server()?,
            },
            resets: f.publisher()?,
            presence: f.presence()?,
        })
    }
}

pub struct PositionLoopNode {
    /// The axis it serves (its index in a multi-axis stack).
    axis: u32,
    body: PositionLoop,
    program: Program,
    pace: Pace,
    ratio: u64,
    period_ns: u64,
    phase_ns: u64,
    rate_hz: f64,
    /// The newest state taken, whether it is news, and the sample the last tick used.
    latest: Option<DriveState>,
    fresh: bool,
    last_used: Option<u64>,
    setpoint_subscribers: usize,
    /// Commands taken this tick and their answers (pre-allocated).
    requests: [AxisRequest; COMMANDS_PER_CYCLE],
    acks: [AxisAck; COMMANDS_PER_CYCLE],
    /// When the device was last asked to reset, s.
    reset_asked_s: Option<f64>,
    ticks: u64,
    /// The axes of its stack (a coordinated part names them).
    axes: usize,
    /// Axis 0's lane: the axes of a stream of several axes whose origin is not yet set.
    stream_group: u32,
    /// A multi-axis stack: this axis's part of a coordinated move, due and not yet
    /// started (the lanes start it together at their next tick).
    coordinated: Option<AxisRequest>,
    /// A client's coordinated part, waiting for its partners unanswered, and its answer
    /// once the lanes have started (or refused) the move: sent after this lane's next
    /// setpoint, the first to carry it out.
    part: Option<(Part, AxisRequest)>,
    part_answer: Option<AxisAck>,
    /// Which of this tick's requests wait (their answers are not sent with the others').
    deferred: [bool; COMMANDS_PER_CYCLE],
    /// A multi-axis stack's coordination, kept by axis 0's lane, and whether the lanes
    /// tick in this cycle.
    /// Boxed: the cycle takes it out of the lane and puts it back (a move of a pointer,
    /// not of the coordinator's plans).
    group: Option<Box<Coordinator>>,
    group_ticks: bool,
    /// Its newest coordinated move's peak contour error, rad (NaN: it has been in none).
    contour_rad: f64,
}

impl PositionLoopNode {
    /// In lockstep a tick is every N-th state, taken in order; otherwise its own clock at
    /// the position rate, on the plant's deadline grid shifted by `phase_ns` (processes use
    /// half a current period, so that the sample is out when the tick reads it; a
    /// simulation, 0: same instant, the plant first). The scenario's program, if any, is
    /// read now (its stream files too).
    /// `axis`: the axis it serves, whose index its commands, setpoints and status carry
    /// (`s` is that axis's scenario).
    pub fn new(s: &Scenario, axis: u32, mode: Mode, phase_ns: u64) -> Result<Self, RunError> {
        let period_ns = s.sample_period_ns();
        let ratio = s.rate_ratio();
        let stop_policy = match s.group.stop {
            GroupStop::All => StopPolicy::All,
            GroupStop::Own => StopPolicy::Own,
        };
        Ok(Self {
            axis,
            body: PositionLoop::new(s),
            program: Program::new(s, axis).map_err(|e| RunError::node(Role::PositionLoop, e))?,
            pace: match mode {
                Mode::Lockstep => Pace::Input,
                _ => Pace::Clock {
                    period_ns: period_ns * ratio,
                    late: Late::Skip,
                },
            },
            ratio,
            period_ns,
            phase_ns,
            rate_hz: s.rates.position_loop_hz,
            latest: None,
            fresh: false,
            last_used: None,
            setpoint_subscribers: 0,
            requests: [AxisRequest::default(); COMMANDS_PER_CYCLE],
            acks: [AxisAck::default(); COMMANDS_PER_CYCLE],
            reset_asked_s: None,
            ticks: 0,
            axes: 1,
            stream_group: 0,
            coordinated: None,
            part: None,
            part_answer: None,
            deferred: [false; COMMANDS_PER_CYCLE],
            group: Some(Box::new(coordinator(
                s.rates.position_loop_hz,
                stop_policy,
                mode,
            ))),
            group_ticks: false,
            contour_rad: f64::NAN,
        })
    }

    /// One of a stack of `axes` (1 by default).
    pub fn in_stack_of(mut self, axes: usize) -> Self {
        self.axes = axes.max(1);
        self
    }

    /// Whether `state` starts a tick: on the clock, any state the last tick did not use;
    /// paced by its input, every N-th.
    fn ticks_on(&self, state: &DriveState) -> bool {
        match self.pace {
            Pace::Input => state.seq.is_multiple_of(self.ratio),
            Pace::Clock { .. } => self.last_used != Some(state.seq),
        }
    }

    /// Applies a client's `request` to the axis at `state`, returning its answer.
    fn apply(&mut self, request: &AxisRequest, state: &DriveState) -> AxisAck {
        self.apply_from(request, state, false)
    }

    /// [`Self::apply`]; `scripted`: a step of the scenario's program (a jog it starts needs
    /// no renewal from a client).
    fn apply_from(&mut self, request: &AxisRequest, state: &DriveState, scripted: bool) -> AxisAck {
        let m = measured(state);
        let result = if request.axis != self.axis {
            Err((
                Refusal::UnknownAxis,
                format!(
                    "axis {} (this is axis {}'s command service)",
                    request.axis, self.axis
                ),
            ))
        } else {
            let axis = self.body.axis();
            match scripted {
                true => axis.request_scripted(request, &m),
                false => axis.request(request, &m),
            }
            .map_err(|r| (r.refusal, r.text))
        };
        self.answer_of(request, state.sample_time_s, result)
    }

    /// The answer to `request` at this tick (at time `t_s`): taken, or refused and why.
    fn answer_of(
        &mut self,
        request: &AxisRequest,
        t_s: f64,
        result: Result<(), (Refusal, String)>,
    ) -> AxisAck {
        let mut ack = AxisAck {
            request: *request,
            tick: self.ticks,
            t_s,
            ..Default::default()
        };
        if let Err((refusal, text)) = result {
            ack.refusal = refusal as u32;
            ack.set_text(&text);
            tracing::debug!(
                kind = request.kind,
                seq = request.seq,
                client = request.client,
                "command refused: {text}"
            );
        }
        ack.state = self.body.axis().state() as u32;
        ack
    }

    /// A client's coordinated part: checked, then kept to wait for its partners (`None`:
    /// its answer comes when the lanes start the move), or answered now. A one-axis
    /// stack's part of a move of its one axis is a plain move.
    fn take_part(
        &mut self,
        request: &AxisRequest,
        index: usize,
        server: &mut AxisServer,
        state: &DriveState,
    ) -> Option<AxisAck> {
        let t = state.sample_time_s;
        let part = match check_part(request, self.axis, self.axes, t) {
            Err(e) => return Some(self.answer_of(request, t, Err((e.refusal, e.text)))),
            Ok(part) => part,
        };
        if self.axes == 1 {
            let mut plain = *request;
            plain.flags &= !(request_flags::COORDINATED | request_flags::GROUP_MASK);
            let mut ack = self.apply(&plain, state);
            ack.request = *request;
            return Some(ack);
        }
        if let Some((waiting, _)) = self.part {
            let text = format!(
                "axis {}'s part of another coordinated move (client {}, seq {}) waits for its partners",
                self.axis, waiting.client, waiting.seq
            );
            return Some(self.answer_of(request, t, Err((Refusal::Moving, text))));
        }
        if !server.defer(index) {
            let text = "the command service cannot keep a part unanswered".to_string();
            return Some(self.answer_of(request, t, Err((Refusal::WrongState, text))));
        }
        self.part = Some((part, *request));
        None
    }

    /// One tick: the commands, the axis and (12), the setpoint, the answers, the status.
    fn tick(
        &mut self,
        ports: &mut PositionLoopPorts,
        cx: &mut Cx,
        state: &DriveState,
    ) -> Result<(), RunError> {
        let m = measured(state);
        // The program's commands due by now (and their answers, for the recorders).
        while let Some(request) = self.program.due(state.sample_time_s) {
            if request.flags & request_flags::COORDINATED != 0 {
                // Started with the other axes' parts by the lanes (`Together`).
                self.coordinated = Some(request);
                continue;
            }
            let ack = self.apply_from(&request, state, true);
            if !ack.taken() {
                tracing::warn!(
                    "program step {} ({}) at {:.4} s refused: {}",
                    request.seq,
                    RequestKind::from_u32(request.kind).map_or("?", |k| k.name()),
                    state.sample_time_s,
                    ack.text()
                );
            }
            self.program.answered(&ack);
            ports.acks.publish(&ack)?;
        }
        for p in self.program.points_due(state.sample_time_s) {
            // A point the axis refuses is counted in its status.
            let _ = self.body.axis().stream_point(p, &m);
        }
        let mut n = 0;
        if let Some(server) = &mut ports.commands {
            n = server.take(&mut self.requests)?;
            for i in 0..n {
                let request = self.requests[i];
                self.deferred[i] = false;
                self.acks[i] = if i >= APPLIED_PER_TICK {
                    let text = format!(
                        "more than {APPLIED_PER_TICK} commands in one tick ({} µs)",
                        1_000_000 / self.rate_hz.max(1.0) as u64
                    );
                    self.answer_of(&request, state.sample_time_s, Err((Refusal::TooMany, text)))
                } else if request.flags & request_flags::COORDINATED != 0 {
                    match self.take_part(&request, i, server, state) {
                        Some(ack) => ack,
                        None => {
                            self.deferred[i] = true;
                            continue;
                        }
                    }
                } else {
                    self.apply(&request, state)
                };
            }
        }
        while let Some(p) = ports.stream.receive()? {
            let _ = self.body.axis().stream_point(&p, &m);
        }
        let mut sp = self.body.on_tick(state);
        sp.axis = self.axis;
        sp.publish_time_ns = cx.now();
        ports.setpoints.publish(&sp)?;
        if n > 0 {
            for ack in &mut self.acks[..n] {
                ack.publish_time_ns = sp.publish_time_ns;
            }
            if let Some(server) = &mut ports.commands {
                server.answer(&self.acks[..n])?;
            }
            for (ack, _) in self.acks[..n]
                .iter()
                .zip(&self.deferred[..n])
                .filter(|(_, deferred)| !**deferred)
            {
                ports.acks.publish(ack)?;
            }
        }
        if let Some(mut ack) = self.part_answer.take() {
            ack.publish_time_ns = sp.publish_time_ns;
            if let Some(server) = &mut ports.commands {
                server.answer_deferred(&ack)?;
            }
            ports.acks.publish(&ack)?;
        }
        let mut status = self.body.status(state);
        status.axis = self.axis;
        status.contour_rad = self.contour_rad;
        status.publish_time_ns = cx.now();
        ports.status.publish(&status)?;
        if self.body.axis().device_reset_wanted() && state.fault != 0 {
            let due = self
                .reset_asked_s
                .is_none_or(|t| state.sample_time_s - t >= RESET_EVERY_S);
            if due {
                self.reset_asked_s = Some(state.sample_time_s);
                ports.resets.publish(&ResetRequest {
                    seq: self.ticks,
                    publish_time_ns: cx.now(),
                    pid: std::process::id(),
                    _reserved: 0,
                })?;
            }
        }
        self.ticks += 1;
        Ok(())
    }
}

impl Node for PositionLoopNode {
    type Ports = PositionLoopPorts;

    fn role(&self) -> Role {
        Role::PositionLoop
    }

    fn pace(&self) -> Pace {
        self.pace
    }

    fn rate_hz(&self) -> f64 {
        self.rate_hz
    }

    fn awaiting(&self) -> String {
        if self.pace == Pace::Input && self.latest.is_none() {
            "a current loop subscribed to control/setpoint".to_string()
        } else {
            "drive/state from the plant".to_string()
        }
    }

    /// Paced by its input, it sleeps until its next tick's state, or until its queue is
    /// half full (the plant would wait on a full one).
    fn awaits(&self) -> Awaits {
        if self.pace != Pace::Input {
            return Awaits::Next;
        }
        let next = self.latest.map_or(0, |s| s.seq + 1);
        let tick = next.div_ceil(self.ratio) * self.ratio;
        Awaits::Later {
            state: Some(tick.min(next + LOCKSTEP_STATE_QUEUE as u64 / 2)),
        }
    }

    fn start(&mut self, ports: &mut PositionLoopPorts, _cx: &mut Cx) -> Result<Start, RunError> {
        if self.pace == Pace::Input {
            let ready = ports.presence.subscribers(Topic::Setpoint) >= 1;
            return Ok(if ready { Start::NOW } else { Start::Waiting });
        }
        // On its own clock: the first state tells where the plant's deadline grid is.
        let Some(first) = ports.states.take()? else {
            return Ok(Start::Waiting);
        };
        let first = first.message;
        self.latest = Some(first);
        self.fresh = true;
        let epoch = (first.deadline_ns + self.phase_ns).saturating_sub(first.seq * self.period_ns);
        Ok(Start::Ready {
            epoch_ns: Some(epoch),
        })
    }

    fn connect(&mut self, ports: &mut PositionLoopPorts) -> Result<(), RunError> {
        ports.setpoints.connect()?;
        ports.status.connect()?;
        Ok(())
    }

    fn poll(&mut self, ports: &mut PositionLoopPorts, cx: &mut Cx) -> Result<Poll, RunError> {
        let fresh = std::mem::take(&mut self.fresh);
        let Some(mut taken) = ports.states.take()? else {
            if self.pace == Pace::Input {
                // A current loop that rejoins gets the newest setpoint from the topic's
                // history, delivered when the publisher updates its connections.
                let subscribers = ports.presence.subscribers(Topic::Setpoint);
                if subscribers != self.setpoint_subscribers {
                    self.setpoint_subscribers = subscribers;
                    ports.setpoints.connect()?;
                }
                return Ok(Poll::Pending);
            }
            return Ok(Poll::Ready { fresh, skipped: 0 });
        };
        // Lockstep, one axis: the states between two ticks only pass through, so they are
        // taken in one cycle. Woken at its tick, the loop found ten queued and ran a cycle
        // for each while the current loop waited for the setpoint. The lanes of several
        // axes step state by state together.
        let mut skipped = taken.skipped;
        if self.pace == Pace::Input && self.axes == 1 {
            while !self.ticks_on(&taken.message) && taken.message.flags & state_flags::LAST == 0 {
                let Some(next) = ports.states.take()? else {
                    break;
                };
                skipped += next.skipped;
                taken = next;
            }
        }
        cx.stats
            .hop
            .record(cx.now().saturating_sub(taken.message.publish_time_ns));
        self.latest = Some(taken.message);
        Ok(Poll::Ready {
            fresh: true,
            skipped,
        })
    }

    /// A client's command, between ticks: a tick at once on the newest state, so that the
    /// command is carried out now and not up to a period later. On the state the last tick
    /// used, if no newer one has come (one comes every current-loop period): the setpoint of
    /// that sample again, decided with the command (waiting for the next tick instead left
    /// one command in ten a whole period late).
    fn rung(&mut self, ports: &mut PositionLoopPorts, cx: &mut Cx) -> Result<(), RunError> {
        if !ports
            .commands
            .as_ref()
            .is_some_and(|server| server.pending())
        {
            return Ok(());
        }
        if let Some(taken) = ports.states.take()? {
            cx.stats
                .hop
                .record(cx.now().saturating_sub(taken.message.publish_time_ns));
            cx.stats.lost += taken.skipped;
            self.latest = Some(taken.message);
            // The next poll tells the runner the plant was heard.
            self.fresh = true;
        }
        let Some(state) = self.latest else {
            return Ok(());
        };
        self.tick(ports, cx, &state)?;
        self.last_used = Some(state.seq);
        Ok(())
    }

    fn step(&mut self, ports: &mut PositionLoopPorts, cx: &mut Cx) -> Result<Flow, RunError> {
        let Some(state) = self.latest else {
            return Ok(Flow::Continue);
        };
        if self.ticks_on(&state) {
            self.tick(ports, cx, &state)?;
            self.last_used = Some(state.seq);
        }
        Ok(if state.flags & state_flags::LAST != 0 {
            Flow::Last
        } else {
            Flow::Continue
        })
    }
}

/// A multi-axis position loop's axes, one per lane, as the coordination reaches them.
struct LaneAxes<'a>(&'a mut [PositionLoopNode]);

impl Axes for LaneAxes<'_> {
    fn count(&self) -> usize {
        self.0.len()
    }
    fn axis_ref(&self, i: usize) -> &Axis {
        self.0[i].body.axis_ref()
    }
    fn axis_mut(&mut self, i: usize) -> &mut Axis {
        self.0[i].body.axis()
    }
}

/// The lanes of a multi-axis position loop tick as one machine: the coordinated moves due
/// (every axis's part, started on one tick and answered), the running one's next states,
/// and after the axes' ticks the contour error and the stop policy
/// (`stepdrive_control::axis::group`).
impl Together for PositionLoopNode {
    fn before_lanes(lanes: &mut [Self], ports: &mut [PositionLoopPorts]) -> Result<(), RunError> {
        // The lanes step at every state; they tick (and the coordination with them) at
        // their ticks only.
        let ticking = lanes[0].latest.is_some_and(|s| lanes[0].ticks_on(&s));
        lanes[0].group_ticks = ticking;
        let Some((m, n)) = lanes_measured(lanes).filter(|_| ticking) else {
            return Ok(());
        };
        let Some(mut group) = lanes[0].group.take() else {
            return Ok(());
        };
        start_client_parts(lanes, &mut group, &m[..n]);
        align_stream_origins(lanes, &m[..n]);
        // The program's parts due (a program's parts have no group bits: their partners are
        // the parts due at the same time).
        let due = (0..lanes.len())
            .filter(|&i| lanes[i].coordinated.is_some())
            .fold(0u32, |g, i| g | (1 << i));
        if due != 0 {
            let (targets, k) = targets_of(lanes, due, |l| l.coordinated);
            let result =
                start_coordinated(lanes, &mut group, &targets[..k], &m[..n], |l| l.coordinated);
            for (i, lane) in lanes.iter_mut().enumerate() {
                if let Some(request) = lane.coordinated.take() {
                    let ack = lane.answer_of(&request, m[i].t, result.clone());
                    lane.program.answered(&ack);
                    ports[i].acks.publish(&ack)?;
                }
            }
        }
        group.before_tick(&mut LaneAxes(lanes), &m[..n]);
        lanes[0].group = Some(group);
        Ok(())
    }

    fn after_lanes(lanes: &mut [Self], _ports: &mut [PositionLoopPorts]) -> Result<(), RunError> {
        let Some((m, n)) = lanes_measured(lanes).filter(|_| lanes[0].group_ticks) else {
            return Ok(());
        };
        let Some(mut group) = lanes[0].group.take() else {
            return Ok(());
        };
        let was = group.coordinated_running();
        let stopped_by = group.stopped_by();
        group.after_tick(&mut LaneAxes(lanes), &m[..n]);
        if was {
            for lane in lanes.iter_mut().filter(|l| !l.contour_rad.is_nan()) {
                lane.contour_rad = group.contour_peak();
            }
        }
        if group.stopped_by() != stopped_by {
            if let Some(by) = group.stopped_by() {
                tracing::warn!(
                    "axis {by} stopped (fault or quick stop): every other enabled axis quick-stops ([group] stop = \"all\")"
                );
            }
        }
        if was && !group.coordinated_running() {
            tracing::info!(
                contour_peak_rad = group.contour_peak(),
                "coordinated move ended"
            );
        }
        lanes[0].group = Some(group);
        Ok(())
    }
}

/// A multi-axis stack's coordination (kept by axis 0's lane). In hardware mode each
/// axis's samples come from its own drive's clock.
fn coordinator(rate_hz: f64, policy: StopPolicy, mode: Mode) -> Coordinator {
    let group = Coordinator::new(1.0 / rate_hz, policy);
    match mode {
        Mode::Hardware => group.separate_clocks(),
        Mode::Lockstep | Mode::Realtime => group,
    }
}

/// Clients' coordinated parts: a move whose parts are all in starts now (or is refused),
/// a part that waited too long for its partners is refused; each lane answers its part
/// after its next setpoint.
fn start_client_parts(lanes: &mut [PositionLoopNode], group: &mut Coordinator, m: &[Measured]) {
    let mut parts = [None; MAX_LANES];
    for (i, lane) in lanes.iter().enumerate().take(MAX_LANES) {
        parts[i] = lane.part.map(|(p, _)| p);
    }
    let parts = &parts[..lanes.len().min(MAX_LANES)];
    let g = gather(parts, m[0].t, PARTS_WAIT_S);
    let streams = parts
        .iter()
        .flatten()
        .any(|p| g.start & p.group != 0 && p.kind == RequestKind::StreamStart as u32);
    // Every part is answered with the cycle's time: on the wall clock the lanes' newest
    // samples can be one apart, and the parts started in one cycle all the same.
    let t = newest_time((0..parts.len()).filter(|i| g.start & (1 << i) != 0), m);
    if g.start != 0 && streams {
        let result = start_streams(lanes, g.start, m);
        if let Err((_, text)) = &result {
            tracing::warn!("a client's stream of several axes refused: {text}");
        }
        for (i, lane) in lanes.iter_mut().enumerate() {
            if let Some((_, r)) = lane.part.filter(|_| g.start & (1 << i) != 0) {
                lane.part = None;
                lane.part_answer = Some(lane.answer_of(&r, t, result.clone()));
            }
        }
    } else if g.start != 0 {
        let request_of = |l: &PositionLoopNode| l.part.map(|(_, r)| r);
        let (targets, k) = targets_of(lanes, g.start, request_of);
        if Coordinator::brakes_hold(&LaneAxes(lanes), &targets[..k], m) {
            // Enabled a moment ago: the parts wait for the brakes, then leave together.
            return;
        }
        let result = start_coordinated(lanes, group, &targets[..k], m, request_of);
        for (i, lane) in lanes.iter_mut().enumerate() {
            if let Some((_, r)) = lane.part.filter(|_| g.start & (1 << i) != 0) {
                lane.part = None;
                lane.part_answer = Some(lane.answer_of(&r, t, result.clone()));
            }
        }
    }
    for (i, lane) in lanes.iter_mut().enumerate() {
        if g.expired & (1 << i) == 0 {
            continue;
        }
        if let Some((p, r)) = lane.part.take() {
            let text = format!(
                "axes {:?} sent no part of this coordinated move within {} ms",
                missing(parts, &p),
                PARTS_WAIT_S * 1e3
            );
            lane.part_answer =
                Some(lane.answer_of(&r, m[i].t, Err((Refusal::GroupIncomplete, text))));
        }
    }
}

/// The targets of the lanes in `members` (bit per lane) that hold a request
/// (`request_of`), and how many.
fn targets_of(
    lanes: &[PositionLoopNode],
    members: u32,
    request_of: impl Fn(&PositionLoopNode) -> Option<AxisRequest>,
) -> ([(usize, f64); MAX_LANES], usize) {
    let mut targets = [(0usize, 0.0f64); MAX_LANES];
    let mut k = 0;
    for (i, lane) in lanes.iter().enumerate().take(MAX_LANES) {
        if let Some(r) = request_of(lane).filter(|_| members & (1 << i) != 0) {
            targets[k] = (i, r.target_rad);
            k += 1;
        }
    }
    (targets, k)
}

/// Starts a coordinated move of the lanes to `targets` on this tick, or refuses it as a
/// whole. Started, each lane's contour error restarts (those not in the move have none)
/// and its request (`request_of`) is its last command.
fn start_coordinated(
    lanes: &mut [PositionLoopNode],
    group: &mut Coordinator,
    targets: &[(usize, f64)],
    m: &[Measured],
    request_of: impl Fn(&PositionLoopNode) -> Option<AxisRequest>,
) -> Result<(), (Refusal, String)> {
    let result = group
        .move_together(&mut LaneAxes(lanes), targets, m)
        .map_err(|e| (e.refusal, e.text));
    match &result {
        Err((_, text)) => tracing::warn!("coordinated move refused: {text}"),
        Ok(()) => {
            for (i, lane) in lanes.iter_mut().enumerate() {
                let in_move = targets.iter().any(|&(j, _)| j == i);
                lane.contour_rad = if in_move { 0.0 } else { f64::NAN };
                if let Some(r) = request_of(lane).filter(|_| in_move) {
                    lane.body.axis().took_part(&r);
                }
            }
        }
    }
    result
}

/// A client's stream of several axes: every axis of `axes` starts its stream on this tick,
/// or none does (an axis not enabled, a lead out of range: `Axis::stream_start`).
fn start_streams(
    lanes: &mut [PositionLoopNode],
    axes: u32,
    m: &[Measured],
) -> Result<(), (Refusal, String)> {
    let members = || (0..lanes.len()).filter(move |i| axes & (1 << i) != 0);
    // Every axis is asked before any starts.
    for i in members() {
        if let Some((_, r)) = lanes[i].part {
            lanes[i]
                .body
                .axis_ref()
                .stream_start(&r)
                .map_err(|e| (e.refusal, format!("axis {i}: {}", e.text)))?;
        }
    }
    for i in members() {
        let lane = &mut lanes[i];
        if let Some((_, r)) = lane.part {
            lane.body
                .axis()
                .request(&r, &m[i])
                .map_err(|e| (e.refusal, format!("axis {i}: {}", e.text)))?;
            lane.body.axis().stream_in_group();
        }
    }
    lanes[0].stream_group = axes;
    Ok(())
}

/// A stream of several axes plays from one origin: once every axis of it has its first
/// point, each plays stream time `first` (the earliest of their first points) a lead after
/// this tick, so that one stream time is one instant on every axis. An axis that left the
/// stream before releases the others to their own first points.
fn align_stream_origins(lanes: &mut [PositionLoopNode], m: &[Measured]) {
    let axes = lanes[0].stream_group;
    if axes == 0 {
        return;
    }
    let members = || (0..lanes.len()).filter(move |i| axes & (1 << i) != 0);
    let left = members().any(|i| !lanes[i].body.axis_ref().stream_awaits_origin());
    let mut first = f64::INFINITY;
    for i in members() {
        match lanes[i].body.axis_ref().stream_first_point() {
            Some(t) => first = first.min(t),
            None if !left => return,
            None => {}
        }
    }
    for i in members() {
        let axis = lanes[i].body.axis();
        match axis.stream_first_point() {
            Some(own) if left => axis.start_stream_at(m[i].t, own),
            Some(_) => axis.start_stream_at(m[i].t, first),
            None => axis.stream_alone(),
        }
    }
    if left {
        tracing::warn!("an axis left the stream of axes {axes:#b} before it began: the others play from their own first points");
    }
    lanes[0].stream_group = 0;
}

/// The most lanes a position loop serves (`stepdrive_shared::scenario::MAX_AXES`).
const MAX_LANES: usize = stepdrive_shared::scenario::MAX_AXES;

/// Every lane's measured state at this tick, when every lane has one.
fn lanes_measured(lanes: &[PositionLoopNode]) -> Option<([Measured; MAX_LANES], usize)> {
    let mut m = [Measured::default(); MAX_LANES];
    for (i, lane) in lanes.iter().enumerate().take(MAX_LANES) {
        m[i] = measured(&lane.latest?);
    }
    Some((m, lanes.len().min(MAX_LANES)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What a lockstep position loop that has taken state `seq` sleeps for, at `hz`.
    fn sleeps_for(hz: f64, seq: u64) -> Awaits {
        let mut s = Scenario::default();
        s.rates.position_loop_hz = hz;
        let mut node = PositionLoopNode::new(&s, 0, Mode::Lockstep, 0).expect("node");
        node.latest = Some(DriveState {
            seq,
            ..DriveState::default()
        });
        node.awaits()
    }

    /// Lockstep: the states of a tick in one cycle for one axis, one by one for the lanes
    /// of several (which step together); a setpoint at each tick either way.
    #[test]
    fn a_lockstep_position_loop_takes_the_states_between_ticks_in_one_cycle() {
        use stepdrive_runtime::clock::VirtualClock;
        use stepdrive_runtime::memory::MemoryBus;
        use stepdrive_runtime::runner::{Runner, Settings, Wake};
        let s = Scenario::default();
        let ratio = (s.rates.current_loop_hz / s.rates.position_loop_hz).round() as u64;
        for (axes, cycles) in [(1, 3), (2, 2 * ratio + 1)] {
            let mut bus = MemoryBus::new(Mode::Lockstep);
            let ports = PositionLoopPorts::open(&mut bus, Mode::Lockstep).expect("ports");
            let mut states = bus.publisher::<DriveState>().expect("states");
            let mut setpoints = bus.subscriber::<TorqueSetpoint>(16).expect("setpoints");
            let node = PositionLoopNode::new(&s, 0, Mode::Lockstep, 0)
                .expect("node")
                .in_stack_of(axes);
            let timeout = std::time::Duration::from_secs(1);
            let settings = Settings::lockstep(timeout, timeout);
            let mut runner = Runner::new(node, ports, settings, None);
            let clock = VirtualClock::default();
            assert!(runner.try_start(&clock).expect("start"));
            for seq in 0..=2 * ratio {
                let state = DriveState {
                    seq,
                    ..DriveState::default()
                };
                states.publish(&state).expect("publish");
            }
            while runner
                .try_input_cycle(&clock, Wake::default())
                .expect("cycle")
                .is_some()
            {}
            assert_eq!(runner.stats().cycles, cycles, "{axes} axes");
            let mut ticks = Vec::new();
            setpoints
                .drain(&mut |sp| ticks.push(sp.from_state_seq))
                .expect("setpoints");
            assert_eq!(ticks, [0, ratio, 2 * ratio], "{axes} axes");
        }
    }

    #[test]
    fn a_lockstep_position_loop_sleeps_from_tick_to_tick_not_queue_to_queue() {
        let at = |state| Awaits::Later { state: Some(state) };
        // 20 kHz samples: a tick every 10 states at 2 kHz, every 100 at 200 Hz (a queue of
        // 16 had it woken every 8 states to drain it).
        assert_eq!(sleeps_for(2_000.0, 0), at(10));
        assert_eq!(sleeps_for(2_000.0, 10), at(20));
        assert_eq!(sleeps_for(200.0, 0), at(100));
        assert_eq!(sleeps_for(200.0, 99), at(100));
        // Ticks further apart than half its queue: woken to drain it, so the plant never
        // waits on a full one.
        assert_eq!(sleeps_for(20.0, 0), at(1 + LOCKSTEP_STATE_QUEUE as u64 / 2));
    }
}
