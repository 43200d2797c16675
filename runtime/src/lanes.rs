//! Several axes in one process: [`Lanes`] is a node made of one node per axis, each on its
//! own axis's ports, all stepped in one cycle. A stack of N axes is still three loop
//! processes: the plant steps N motors, the current loop N current loops, the position loop
//! N axes, each process at its one rate with its one runner. Two cores cannot pace 3N
//! processes at 20 kHz; one wake-up a period for all axes they can.
//!
//! Paced by their input, in lockstep a cycle runs once every lane has its input; on the wall
//! clock the lanes that have theirs step at once and the others wait. The axes are
//! independent, so each one's results are those of a node of its own (in lockstep bit for
//! bit). On the clock every lane takes whatever is there at the deadline, as one node would.

use crate::error::RunError;
use crate::node::{Awaits, Cx, Flow, Node, Pace, Poll, Role, Start};
use stepdrive_shared::stats::StatsReport;

/// What the lanes of one role do as one machine in each cycle, around their own steps:
/// a multi-axis position loop's coordinated moves and stop policy. Nothing, by default.
pub trait Together: Node + Sized {
    /// Before the lanes step in a cycle in which all of them do (in lockstep, or on the
    /// clock).
    fn before_lanes(_lanes: &mut [Self], _ports: &mut [Self::Ports]) -> Result<(), RunError> {
        Ok(())
    }
    /// After they stepped, in such a cycle.
    fn after_lanes(_lanes: &mut [Self], _ports: &mut [Self::Ports]) -> Result<(), RunError> {
        Ok(())
    }

    /// Whether one lane's [`Node::block`] wakes on every lane's input (the current loop's
    /// state-ready event is one for all axes), so that several lanes waiting block on it.
    /// False by default: a lane blocked on its own input (a drive's socket) would hold up
    /// the others'.
    const BLOCKS_FOR_ALL: bool = false;
}

/// One node per axis, as one node. See the module documentation.
pub struct Lanes<N: Node> {
    nodes: Vec<N>,
    lanes: Vec<Lane>,
    together: bool,
}

struct Lane {
    /// Started ([`Node::start`] said `Ready`): its epoch.
    started: Option<Option<u64>>,
    /// Input-paced: this cycle's input taken.
    ready: bool,
    /// Its run's last sample handled (it takes no more cycles).
    finished: bool,
    /// Stepped, its [`Node::after_answers`] not yet run.
    owes: bool,
}

impl<N: Node> Lanes<N> {
    /// `nodes[n]` is axis n's. At least one. `together`: input-paced lanes step in one
    /// cycle once every one has its input (lockstep: one hand-off a sample for all axes);
    /// otherwise each as soon as it has it (realtime).
    pub fn new(nodes: Vec<N>, together: bool) -> Self {
        assert!(!nodes.is_empty(), "a stack has at least one axis");
        Self {
            together,
            lanes: nodes
                .iter()
                .map(|_| Lane {
                    started: None,
                    ready: false,
                    finished: false,
                    owes: false,
                })
                .collect(),
            nodes,
        }
    }

    fn first(&self) -> &N {
        &self.nodes[0]
    }

    /// The lanes with their nodes and ports.
    fn each<'a>(
        &'a mut self,
        ports: &'a mut [N::Ports],
    ) -> impl Iterator<Item = (&'a mut Lane, &'a mut N, &'a mut N::Ports)> {
        self.lanes
            .iter_mut()
            .zip(self.nodes.iter_mut())
            .zip(ports.iter_mut())
            .map(|((l, n), p)| (l, n, p))
    }

    /// Runs the [`Node::after_answers`] the lanes owe.
    fn pay_owed(&mut self, ports: &mut [N::Ports], cx: &mut Cx) -> Result<(), RunError> {
        for (lane, node, p) in self.each(ports) {
            if std::mem::take(&mut lane.owes) {
                node.after_answers(p, &mut lane_cx(cx))?;
            }
        }
        Ok(())
    }
}

/// What a lane sees of the cycle: the process's context, with its own answer time.
fn lane_cx<'a>(cx: &'a mut Cx<'_>) -> Cx<'a> {
    Cx {
        clock: cx.clock,
        stats: cx.stats,
        deadline_ns: cx.deadline_ns,
        woke_ns: cx.woke_ns,
        taken_ns: None,
        answered_ns: None,
    }
}

/// The counters a node's [`Node::report`] sets from what it keeps itself (the plant's
/// command record): each lane's are its axis's, and the process reports their sum.
const NOT_SET: u64 = u64::MAX;

#[derive(Clone, Copy, Default)]
struct Kept {
    misses: u64,
    planned: u64,
    late_discarded: u64,
    miss_runs: u64,
    longest_miss_run: u64,
}

impl Kept {
    fn of(s: &StatsReport) -> Self {
        Self {
            misses: s.misses,
            planned: s.planned,
            late_discarded: s.late_discarded,
            miss_runs: s.miss_runs,
            longest_miss_run: s.longest_miss_run,
        }
    }

    fn write(self, s: &mut StatsReport) {
        s.misses = self.misses;
        s.planned = self.planned;
        s.late_discarded = self.late_discarded;
        s.miss_runs = self.miss_runs;
        s.longest_miss_run = self.longest_miss_run;
    }

    const UNSET: Kept = Kept {
        misses: NOT_SET,
        planned: NOT_SET,
        late_discarded: NOT_SET,
        miss_runs: NOT_SET,
        longest_miss_run: NOT_SET,
    };

    /// Adds a lane's report: a counter it did not set keeps `before`'s (a counter the
    /// node accumulates in its cycles is already the process's total).
    fn add(&mut self, lane: Kept, before: Kept, first: bool) {
        let set = |total: &mut u64, v: u64, b: u64, sum: fn(u64, u64) -> u64| {
            *total = if v == NOT_SET {
                b
            } else if first {
                v
            } else {
                sum(*total, v)
            };
        };
        set(
            &mut self.misses,
            lane.misses,
            before.misses,
            u64::saturating_add,
        );
        set(
            &mut self.planned,
            lane.planned,
            before.planned,
            u64::saturating_add,
        );
        set(
            &mut self.late_discarded,
            lane.late_discarded,
            before.late_discarded,
            u64::saturating_add,
        );
        set(
            &mut self.miss_runs,
            lane.miss_runs,
            before.miss_runs,
            u64::saturating_add,
        );
        set(
            &mut self.longest_miss_run,
            lane.longest_miss_run,
            before.longest_miss_run,
            u64::max,
        );
    }
}

impl<N: Together> Node for Lanes<N> {
    type Ports = Vec<N::Ports>;

    fn role(&self) -> Role {
        self.first().role()
    }

    fn pace(&self) -> Pace {
        self.first().pace()
    }

    fn rate_hz(&self) -> f64 {
        self.first().rate_hz()
    }

    fn awaiting(&self) -> String {
        let lanes = || self.lanes.iter().enumerate();
        lanes()
            .find(|(_, l)| l.started.is_none())
            .or_else(|| lanes().find(|(_, l)| !l.finished && !l.ready))
            .map_or_else(
                || self.first().awaiting(),
                |(n, _)| format!("axis {n}: {}", self.nodes[n].awaiting()),
            )
    }

    fn start(&mut self, ports: &mut Self::Ports, cx: &mut Cx) -> Result<Start, RunError> {
        let mut all = true;
        for (lane, node, p) in self.each(ports) {
            if lane.started.is_some() {
                continue;
            }
            match node.start(p, &mut lane_cx(cx))? {
                Start::Waiting => all = false,
                Start::Ready { epoch_ns } => lane.started = Some(epoch_ns),
            }
        }
        Ok(if all {
            // Every axis on axis 0's deadline grid.
            Start::Ready {
                epoch_ns: self.lanes[0].started.flatten(),
            }
        } else {
            Start::Waiting
        })
    }

    fn connect(&mut self, ports: &mut Self::Ports) -> Result<(), RunError> {
        for node_ports in self.nodes.iter_mut().zip(ports.iter_mut()) {
            node_ports.0.connect(node_ports.1)?;
        }
        Ok(())
    }

    fn poll(&mut self, ports: &mut Self::Ports, cx: &mut Cx) -> Result<Poll, RunError> {
        let clock_paced = matches!(self.first().pace(), Pace::Clock { .. });
        let (mut pending, mut fresh, mut skipped) = (false, false, 0);
        for (lane, node, p) in self.each(ports) {
            if lane.finished || (lane.ready && !clock_paced) {
                continue;
            }
            match node.poll(p, &mut lane_cx(cx))? {
                Poll::Pending if clock_paced => lane.ready = true,
                Poll::Pending => pending = true,
                Poll::Finished => lane.finished = true,
                Poll::Ready {
                    fresh: f,
                    skipped: s,
                } => {
                    lane.ready = true;
                    fresh |= f;
                    skipped += s;
                }
            }
        }
        if self.lanes.iter().all(|l| l.finished) {
            return Ok(Poll::Finished);
        }
        // On the wall clock a lane whose input is there goes at once, whatever the others
        // wait for: waiting for all would let one axis's backlog stand, its answers a period
        // late ever after. In lockstep no axis falls behind, and one cycle for all costs
        // one hand-off instead of one per axis (3 axes: 0.5-1.1 s a run against 1.4-1.9 s).
        let any_ready = self.lanes.iter().any(|l| l.ready && !l.finished);
        if pending && (self.together || !any_ready) {
            return Ok(Poll::Pending);
        }
        Ok(Poll::Ready { fresh, skipped })
    }

    fn step(&mut self, ports: &mut Self::Ports, cx: &mut Cx) -> Result<Flow, RunError> {
        let all = self.lanes.iter().all(|l| l.ready && !l.finished);
        if all {
            N::before_lanes(&mut self.nodes, ports)?;
        }
        // A lane that steps again before every lane answered once owes its last cycle's
        // work still: it goes first (one silent axis holds the others' for one cycle).
        if self.lanes.iter().any(|l| l.owes && l.ready && !l.finished) {
            self.pay_owed(ports, cx)?;
        }
        let mut answered = None;
        for (lane, node, p) in self.each(ports) {
            if lane.finished || !lane.ready {
                continue;
            }
            lane.ready = false;
            lane.owes = true;
            let mut lcx = lane_cx(cx);
            let flow = node.step(p, &mut lcx)?;
            answered = lcx.answered_ns.or(answered);
            if flow == Flow::Last {
                lane.finished = true;
            }
        }
        // Every axis's answer first (on the clock their inputs come one after another),
        // then the work that follows them.
        if self.lanes.iter().all(|l| l.owes || l.finished) {
            self.pay_owed(ports, cx)?;
        }
        if all {
            N::after_lanes(&mut self.nodes, ports)?;
        }
        if answered.is_some() {
            cx.answered_ns = answered;
        }
        Ok(if self.lanes.iter().all(|l| l.finished) {
            Flow::Last
        } else {
            Flow::Continue
        })
    }

    fn due_ns(&self) -> Option<u64> {
        self.lanes
            .iter()
            .zip(&self.nodes)
            .filter(|(l, _)| !l.finished && !l.ready)
            .filter_map(|(_, n)| n.due_ns())
            .min()
    }

    fn spin_past_due_ns(&self) -> Option<u64> {
        self.first().spin_past_due_ns()
    }

    fn awaits(&self) -> Awaits {
        // The earliest any waiting lane needs: an answer within a hand-off, else a setpoint
        // from the position loop beside it, else the earliest state one sleeps for.
        let waiting = self
            .lanes
            .iter()
            .zip(&self.nodes)
            .filter(|(l, _)| !l.finished && !l.ready)
            .map(|(_, n)| n);
        let mut beside = false;
        // Until a lane sleeps for any message (None); u64::MAX: none sleeps at all.
        let mut earliest = Some(u64::MAX);
        for n in waiting {
            match n.awaits() {
                Awaits::Next => return Awaits::Next,
                Awaits::Beside => beside = true,
                Awaits::Later { state } => earliest = earliest.zip(state).map(|(a, b)| a.min(b)),
            }
        }
        if beside {
            return Awaits::Beside;
        }
        Awaits::Later {
            state: earliest.filter(|&s| s != u64::MAX),
        }
    }

    fn block(
        &mut self,
        ports: &mut Self::Ports,
        now_ns: u64,
        until_ns: u64,
    ) -> Result<bool, RunError> {
        // One lane waiting blocks on its input, and so do several whose block wakes on any
        // lane's ([`Together::BLOCKS_FOR_ALL`]). Otherwise none may block on its own (one
        // drive's socket would hold up another's frames), so the runner backs off between
        // polls.
        let mut waiting = self
            .lanes
            .iter()
            .enumerate()
            .filter(|(_, l)| !l.finished && !l.ready)
            .map(|(n, _)| n);
        match (waiting.next(), waiting.next()) {
            (Some(n), None) => self.nodes[n].block(&mut ports[n], now_ns, until_ns),
            (Some(n), Some(_)) if N::BLOCKS_FOR_ALL => {
                self.nodes[n].block(&mut ports[n], now_ns, until_ns)
            }
            _ => Ok(false),
        }
    }

    fn rung(&mut self, ports: &mut Self::Ports, cx: &mut Cx) -> Result<(), RunError> {
        for (lane, node, p) in self.each(ports) {
            if !lane.finished {
                node.rung(p, &mut lane_cx(cx))?;
            }
        }
        Ok(())
    }

    fn awaiting_rejoin(&self) -> bool {
        self.nodes.iter().any(Node::awaiting_rejoin)
    }

    fn latched_fault(&self) -> u32 {
        self.nodes.iter().fold(0, |f, n| f | n.latched_fault())
    }

    fn report(&self, stats: &mut StatsReport) {
        let before = Kept::of(stats);
        let mut total = before;
        for (n, node) in self.nodes.iter().enumerate() {
            Kept::UNSET.write(stats);
            node.report(stats);
            total.add(Kept::of(stats), before, n == 0);
        }
        total.write(stats);
    }

    fn stop(&mut self, ports: &mut Self::Ports, cx: &mut Cx) {
        for (node, p) in self.nodes.iter_mut().zip(ports.iter_mut()) {
            node.stop(p, &mut lane_cx(cx));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::clock::VirtualClock;
    use std::cell::Cell;
    use std::rc::Rc;

    /// What every test lane is: an input-paced current loop at 20 kHz.
    macro_rules! an_input_paced_lane {
        () => {
            type Ports = ();
            fn role(&self) -> Role {
                Role::CurrentLoop
            }
            fn pace(&self) -> Pace {
                Pace::Input
            }
            fn rate_hz(&self) -> f64 {
                20_000.0
            }
            fn awaiting(&self) -> String {
                String::new()
            }
        };
    }

    /// An input-paced lane that never has its input and counts the blocks asked of it.
    struct Waiting<const ALL: bool> {
        blocks: Rc<Cell<u32>>,
    }

    impl<const ALL: bool> Node for Waiting<ALL> {
        an_input_paced_lane!();
        fn poll(&mut self, _: &mut (), _: &mut Cx) -> Result<Poll, RunError> {
            Ok(Poll::Pending)
        }
        fn step(&mut self, _: &mut (), _: &mut Cx) -> Result<Flow, RunError> {
            Ok(Flow::Continue)
        }
        fn block(&mut self, _: &mut (), _: u64, _: u64) -> Result<bool, RunError> {
            self.blocks.set(self.blocks.get() + 1);
            Ok(true)
        }
    }

    impl<const ALL: bool> Together for Waiting<ALL> {
        const BLOCKS_FOR_ALL: bool = ALL;
    }

    /// Whether `lanes` lanes, all waiting, block, and how many blocks were asked.
    fn blocks<const ALL: bool>(lanes: usize) -> (bool, u32) {
        let counted = Rc::new(Cell::new(0));
        let nodes = (0..lanes)
            .map(|_| Waiting::<ALL> {
                blocks: counted.clone(),
            })
            .collect();
        let mut l = Lanes::new(nodes, false);
        let mut ports = vec![(); lanes];
        let clock = VirtualClock::default();
        let mut stats = StatsReport::default();
        let mut cx = Cx::new(&clock, &mut stats);
        assert_eq!(l.start(&mut ports, &mut cx).expect("starts"), Start::NOW);
        assert_eq!(l.poll(&mut ports, &mut cx).expect("polls"), Poll::Pending);
        let blocked = l.block(&mut ports, 0, 1_000).expect("blocks");
        (blocked, counted.get())
    }

    /// An input-paced lane whose input is its bit in `inputs`; it logs its answers and
    /// the work after them.
    struct Answering {
        axis: u32,
        inputs: Rc<Cell<u32>>,
        log: Rc<std::cell::RefCell<Vec<String>>>,
    }

    impl Node for Answering {
        an_input_paced_lane!();
        fn poll(&mut self, _: &mut (), _: &mut Cx) -> Result<Poll, RunError> {
            let bit = 1 << self.axis;
            if self.inputs.get() & bit == 0 {
                return Ok(Poll::Pending);
            }
            self.inputs.set(self.inputs.get() & !bit);
            Ok(Poll::READY)
        }
        fn step(&mut self, _: &mut (), _: &mut Cx) -> Result<Flow, RunError> {
            self.log.borrow_mut().push(format!("answer {}", self.axis));
            Ok(Flow::Continue)
        }
        fn after_answers(&mut self, _: &mut (), _: &mut Cx) -> Result<(), RunError> {
            self.log.borrow_mut().push(format!("after {}", self.axis));
            Ok(())
        }
    }

    impl Together for Answering {}

    #[test]
    fn the_work_after_the_answers_waits_for_every_axis_answer_or_a_lane_that_steps_again() {
        let inputs = Rc::new(Cell::new(0));
        let log = Rc::new(std::cell::RefCell::new(Vec::new()));
        let nodes = (0..3)
            .map(|axis| Answering {
                axis,
                inputs: inputs.clone(),
                log: log.clone(),
            })
            .collect();
        let mut l = Lanes::new(nodes, false);
        let mut ports = vec![(); 3];
        let clock = VirtualClock::default();
        let mut stats = StatsReport::default();
        let mut cx = Cx::new(&clock, &mut stats);
        assert_eq!(l.start(&mut ports, &mut cx).expect("starts"), Start::NOW);
        let mut cycle = |bits: u32| {
            inputs.set(bits);
            assert!(matches!(
                l.poll(&mut ports, &mut cx).expect("polls"),
                Poll::Ready { .. }
            ));
            l.step(&mut ports, &mut cx).expect("steps");
            log.borrow_mut().drain(..).collect::<Vec<_>>()
        };
        // On the clock the axes' inputs come one after another: the work after the
        // answers waits for the last axis's answer.
        assert_eq!(cycle(0b001), ["answer 0"]);
        assert_eq!(
            cycle(0b110),
            ["answer 1", "answer 2", "after 0", "after 1", "after 2"]
        );
        // Axes 1 and 2 silent: axis 0's work is done before it answers again, never lost.
        assert_eq!(cycle(0b001), ["answer 0"]);
        assert_eq!(cycle(0b001), ["after 0", "answer 0"]);
    }

    #[test]
    fn one_waiting_lane_blocks_on_its_input() {
        assert_eq!(blocks::<false>(1), (true, 1));
    }

    #[test]
    fn several_waiting_lanes_block_only_on_an_input_that_wakes_for_all() {
        // A drive's socket would hold up the other drives' frames: the runner backs off.
        assert_eq!(blocks::<false>(3), (false, 0));
        // The current loop's state-ready event wakes for every axis: one block for all.
        assert_eq!(blocks::<true>(3), (true, 1));
    }
}
