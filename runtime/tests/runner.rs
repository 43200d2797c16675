//! The runner and the simulation, driven with toy nodes over in-memory ports: what every
//! role gets from them without writing it (pacing, the last-sample rule, holds, deadlock
//! and silence detection, lateness policies, statistics, stopping on every exit path).

use std::cell::RefCell;
use std::rc::Rc;
use std::time::Duration;
use stepdrive_runtime::clock::monotonic_ns;
use stepdrive_runtime::memory::MemoryBus;
use stepdrive_runtime::node::{Cx, Flow, Late, Node, Pace, Poll, Role, Start};
use stepdrive_runtime::pacer::{sleep_until, WaitStrategy};
use stepdrive_runtime::port::{PortFactory, Publish, Subscribe};
use stepdrive_runtime::runner::{Runner, Settings};
use stepdrive_runtime::simulation::{self, Hold};
use stepdrive_runtime::RunError;
use stepdrive_shared::messages::{state_flags, DriveState};
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::stats::StatsReport;

const PERIOD: u64 = 1_000_000;

/// Publishes sample k at each deadline, the last one flagged; sleeps `work_ns` per cycle.
struct Source {
    period_ns: u64,
    samples: u64,
    next: u64,
    late: Late,
    work_ns: u64,
    stopped: Rc<RefCell<bool>>,
}

impl Node for Source {
    type Ports = Box<dyn Publish<DriveState>>;
    fn role(&self) -> Role {
        Role::Plant
    }
    fn pace(&self) -> Pace {
        Pace::Clock {
            period_ns: self.period_ns,
            late: self.late,
        }
    }
    fn rate_hz(&self) -> f64 {
        1e9 / self.period_ns as f64
    }
    fn awaiting(&self) -> String {
        "nothing".into()
    }
    fn start(&mut self, _: &mut Self::Ports, cx: &mut Cx) -> Result<Start, RunError> {
        Ok(Start::Ready {
            epoch_ns: Some(cx.now() + self.period_ns),
        })
    }
    fn poll(&mut self, _: &mut Self::Ports, _: &mut Cx) -> Result<Poll, RunError> {
        Ok(Poll::READY)
    }
    fn step(&mut self, out: &mut Self::Ports, cx: &mut Cx) -> Result<Flow, RunError> {
        let last = self.next + 1 == self.samples;
        out.publish(&DriveState {
            seq: self.next,
            deadline_ns: cx.deadline_ns,
            flags: if last { state_flags::LAST } else { 0 },
            ..Default::default()
        })?;
        self.next += 1;
        if self.work_ns > 0 {
            sleep_until(cx.now() + self.work_ns);
        }
        Ok(if last { Flow::Last } else { Flow::Continue })
    }
    fn stop(&mut self, _: &mut Self::Ports, _: &mut Cx) {
        *self.stopped.borrow_mut() = true;
    }
}

/// Takes states: lockstep, each in turn; realtime, the newest.
struct Sink {
    lockstep: bool,
    seen: Vec<u64>,
    taken: Option<DriveState>,
    fail_at: Option<u64>,
    stopped: Rc<RefCell<bool>>,
}

impl Node for Sink {
    type Ports = Box<dyn Subscribe<DriveState>>;
    fn role(&self) -> Role {
        Role::CurrentLoop
    }
    fn pace(&self) -> Pace {
        Pace::Input
    }
    fn rate_hz(&self) -> f64 {
        1e9 / PERIOD as f64
    }
    fn awaiting(&self) -> String {
        "drive/state from the source".into()
    }
    fn poll(&mut self, input: &mut Self::Ports, _: &mut Cx) -> Result<Poll, RunError> {
        let got = if self.lockstep {
            input.receive()?
        } else {
            input.newest()?
        };
        let Some(s) = got else {
            return Ok(Poll::Pending);
        };
        let skipped = self.seen.last().map_or(0, |&prev| s.seq - prev - 1);
        self.taken = Some(s);
        Ok(Poll::Ready {
            fresh: true,
            skipped,
        })
    }
    fn step(&mut self, _: &mut Self::Ports, _: &mut Cx) -> Result<Flow, RunError> {
        let s = self.taken.take().expect("polled");
        if self.fail_at == Some(s.seq) {
            return Err(RunError::Deadlock("injected".into()));
        }
        self.seen.push(s.seq);
        Ok(if s.flags & state_flags::LAST != 0 {
            Flow::Last
        } else {
            Flow::Continue
        })
    }
    fn stop(&mut self, _: &mut Self::Ports, _: &mut Cx) {
        *self.stopped.borrow_mut() = true;
    }
}

fn settings() -> Settings {
    Settings::lockstep(Duration::from_secs(1), Duration::from_secs(1))
}

fn flag() -> Rc<RefCell<bool>> {
    Rc::new(RefCell::new(false))
}

fn source(samples: u64, late: Late, work_ns: u64, stopped: &Rc<RefCell<bool>>) -> Source {
    Source {
        period_ns: PERIOD,
        samples,
        next: 0,
        late,
        work_ns,
        stopped: stopped.clone(),
    }
}

fn sink(lockstep: bool, fail_at: Option<u64>, stopped: &Rc<RefCell<bool>>) -> Sink {
    Sink {
        lockstep,
        seen: Vec::new(),
        taken: None,
        fail_at,
        stopped: stopped.clone(),
    }
}

/// A source and a sink joined by a queue, and the flags their `stop` sets.
type Pair = (
    Runner<Source>,
    Runner<Sink>,
    Rc<RefCell<bool>>,
    Rc<RefCell<bool>>,
);

fn pair(mode: Mode, samples: u64, fail_at: Option<u64>) -> Pair {
    let mut bus = MemoryBus::new(mode);
    let (a, b) = (flag(), flag());
    let source = source(samples, Late::Pause, 0, &a);
    let sink = sink(mode == Mode::Lockstep, fail_at, &b);
    let input = bus.subscriber::<DriveState>(4).expect("port");
    let output = bus.publisher::<DriveState>().expect("port");
    (
        Runner::new(source, output, settings(), None),
        Runner::new(sink, input, settings(), None),
        a,
        b,
    )
}

#[test]
fn lockstep_delivers_every_sample_in_order_and_ends_at_the_last() {
    let (mut source, mut sink, a, b) = pair(Mode::Lockstep, 50, None);
    simulation::run(&mut [&mut source, &mut sink], &[]).expect("runs");
    assert_eq!(sink.node().seen, (0..50).collect::<Vec<_>>());
    assert_eq!(sink.stats().cycles, 50);
    assert_eq!(sink.stats().lost, 0);
    assert!(*a.borrow() && *b.borrow(), "both stopped");
}

#[test]
fn a_held_member_does_nothing_then_takes_the_newest_and_counts_what_it_skipped() {
    let (mut source, mut sink, _, _) = pair(Mode::Realtime, 30, None);
    // The source's epoch is one period in: its sample k is due at (k + 1) periods, so the
    // hold covers samples 10 to 19.
    let hold = Hold {
        role: Role::CurrentLoop,
        during_ns: 10 * PERIOD + 1..20 * PERIOD + 1,
    };
    simulation::run(&mut [&mut source, &mut sink], &[hold]).expect("runs");
    let seen = &sink.node().seen;
    let expected: Vec<u64> = (0..10).chain(20..30).collect();
    assert_eq!(seen, &expected);
    assert_eq!(sink.stats().lost, 10);
}

#[test]
fn a_stack_that_cannot_go_on_is_a_deadlock_naming_who_waits_for_what() {
    let mut bus = MemoryBus::new(Mode::Lockstep);
    let input = bus.subscriber::<DriveState>(4).expect("port");
    let stopped = flag();
    let mut sink = Runner::new(sink(true, None, &stopped), input, settings(), None);
    let e = simulation::run(&mut [&mut sink], &[]).expect_err("nobody publishes");
    assert!(
        matches!(&e, RunError::Deadlock(why) if why.contains("drive/state from the source")),
        "{e}"
    );
    assert!(*stopped.borrow(), "stopped on the error path too");
}

#[test]
fn a_failing_node_stops_everyone_and_its_error_comes_out() {
    let (mut source, mut sink, a, b) = pair(Mode::Lockstep, 50, Some(7));
    let e = simulation::run(&mut [&mut source, &mut sink], &[]).expect_err("fails");
    assert!(
        matches!(e, RunError::Deadlock(ref m) if m == "injected"),
        "{e}"
    );
    assert_eq!(sink.node().seen, (0..7).collect::<Vec<_>>());
    assert!(*a.borrow() && *b.borrow(), "every member stopped");
}

/// Statistics go out once per second's worth of cycles and once more at the end.
#[test]
fn statistics_go_out_once_a_second_of_cycles_and_at_the_end() {
    let mut bus = MemoryBus::new(Mode::Realtime);
    let mut reports = bus.subscriber::<StatsReport>(64).expect("port");
    let stats_port = bus.publisher::<StatsReport>().expect("port");
    let output = bus.publisher::<DriveState>().expect("port");
    let source = source(2_500, Late::Pause, 0, &flag());
    let mut r = Runner::new(source, output, settings(), Some(stats_port));
    simulation::run(&mut [&mut r], &[]).expect("runs");
    let mut got = Vec::new();
    reports
        .drain(&mut |s| got.push((s.cycles, s.is_final)))
        .expect("drain");
    // 1 kHz: at cycles 1000 and 2000, then the final one.
    assert_eq!(got, [(1000, 0), (2000, 0), (2500, 1)]);
}

/// On the wall clock: a clock-paced node whose cycle takes three periods is held to its
/// lateness policy. `Pause` moves its schedule after each cycle (a device's time stops with
/// it), so it always wakes on time; `Skip` wakes late, runs, and drops the deadlines it
/// missed. Long periods (10 ms) keep the figures far from scheduling noise.
#[test]
fn overruns_pause_a_devices_time_and_skip_a_controllers_deadlines() {
    let period = 10_000_000;
    for late in [Late::Pause, Late::Skip] {
        let mut bus = MemoryBus::new(Mode::Realtime);
        let output = bus.publisher::<DriveState>().expect("port");
        let source = Source {
            period_ns: period,
            ..source(6, late, 3 * period, &flag())
        };
        let settings = Settings {
            wait: WaitStrategy::Sleep,
            ..settings()
        };
        let stats = Runner::new(source, output, settings, None)
            .run()
            .expect("runs")
            .stats;
        assert_eq!(stats.cycles, 6, "{late:?}");
        assert_eq!(
            stats.misses, 6,
            "{late:?}: every cycle ends past the next deadline"
        );
        // Every cycle but the last overruns: `Pause` counts it after the cycle, `Skip` at
        // the next wake-up.
        assert_eq!(stats.overruns, 5, "{late:?}");
        let median = stats.wakeup.quantile_ns(0.5).expect("wake-ups");
        match late {
            Late::Pause => assert!(median < period, "re-anchored: {median} ns late"),
            Late::Skip => assert!(median >= 2 * period, "woke two periods late: {median} ns"),
        }
    }
}

/// On the wall clock: an input-paced node whose peer never speaks stops after the
/// start-up timeout, naming what it waited for; and on SIGTERM-like termination the
/// runner would stop too (checked by the end-to-end tests).
#[test]
fn a_silent_peer_stops_the_node_naming_it() {
    let mut bus = MemoryBus::new(Mode::Realtime);
    let input = bus.subscriber::<DriveState>(4).expect("port");
    let stopped = flag();
    let sink = sink(false, None, &stopped);
    let settings = Settings {
        wait: WaitStrategy::Sleep,
        ..Settings::lockstep(Duration::from_millis(50), Duration::from_millis(50))
    };
    let t0 = monotonic_ns();
    let Err(e) = Runner::new(sink, input, settings, None).run() else {
        panic!("nobody speaks, yet the run ended");
    };
    assert!(monotonic_ns() - t0 >= 50_000_000);
    assert!(
        matches!(&e, RunError::PeerSilent { awaiting, .. } if awaiting.contains("the source")),
        "{e}"
    );
    assert!(*stopped.borrow());
}

/// A clock-paced node that counts its ticks and when it was rung.
struct Ringed {
    period_ns: u64,
    ticks: u64,
    done: u64,
    rungs: Rc<RefCell<Vec<(u64, u64)>>>,
}

impl Node for Ringed {
    type Ports = ();
    fn role(&self) -> Role {
        Role::PositionLoop
    }
    fn pace(&self) -> Pace {
        Pace::Clock {
            period_ns: self.period_ns,
            late: Late::Skip,
        }
    }
    fn rate_hz(&self) -> f64 {
        1e9 / self.period_ns as f64
    }
    fn awaiting(&self) -> String {
        "nothing".into()
    }
    fn start(&mut self, _: &mut (), cx: &mut Cx) -> Result<Start, RunError> {
        Ok(Start::Ready {
            epoch_ns: Some(cx.now() + self.period_ns),
        })
    }
    fn poll(&mut self, _: &mut (), _: &mut Cx) -> Result<Poll, RunError> {
        Ok(Poll::READY)
    }
    fn step(&mut self, _: &mut (), _: &mut Cx) -> Result<Flow, RunError> {
        self.done += 1;
        Ok(if self.done == self.ticks {
            Flow::Last
        } else {
            Flow::Continue
        })
    }
    fn rung(&mut self, _: &mut (), cx: &mut Cx) -> Result<(), RunError> {
        self.rungs.borrow_mut().push((self.done, cx.now()));
        Ok(())
    }
}

/// A clock-paced node given a doorbell (the position loop, rung by a client's command)
/// acts on a ring between its ticks at once, not at its next deadline; a burst of rings in
/// one period costs it at most `RINGS_PER_PERIOD` calls; its ticks keep their deadlines.
/// Periods of 20 ms keep the figures far from scheduling noise (a loaded CI host has held a
/// process for 20 ms).
#[test]
fn a_ring_between_ticks_is_acted_on_at_once_and_a_burst_costs_at_most_the_allowance() {
    use stepdrive_runtime::doorbell::{self, Doorbells};
    use stepdrive_runtime::runner::RINGS_PER_PERIOD;
    let name = format!("runner-rings-{}", std::process::id());
    let bells = Doorbells::open(&name).expect("doorbells");
    let waiter = bells.waiter(Role::PositionLoop);
    let ringer = bells.ringer_of(Role::PositionLoop);
    let period = 20_000_000;
    let rungs = Rc::new(RefCell::new(Vec::new()));
    let node = Ringed {
        period_ns: period,
        ticks: 20,
        done: 0,
        rungs: rungs.clone(),
    };
    let started = monotonic_ns();
    let rings = std::thread::spawn(move || {
        let at = |ms: u64| sleep_until(started + ms * 1_000_000);
        at(102);
        let one = monotonic_ns();
        ringer.ring(None);
        at(242);
        let burst = monotonic_ns();
        for _ in 0..5 {
            ringer.ring(None);
            std::thread::sleep(Duration::from_micros(300));
        }
        (one, burst)
    });
    let settings = Settings {
        wait: WaitStrategy::Sleep,
        ..settings()
    };
    let stats = Runner::new(node, (), settings, None)
        .with_doorbell(Some(waiter))
        .run()
        .expect("runs")
        .stats;
    let (one, burst) = rings.join().expect("the ringer");
    doorbell::remove(&name);
    assert_eq!(stats.cycles, 20, "the rings took no tick's place");
    let rungs = rungs.borrow();
    // The single ring: acted on within 10 ms (its tick was 18 ms away).
    let first = rungs
        .iter()
        .find(|&&(_, at)| at >= one && at < burst)
        .unwrap_or_else(|| panic!("the ring at {one} was not acted on: {rungs:?}"));
    assert!(
        first.1 - one < 10_000_000,
        "acted on {} µs after",
        (first.1 - one) / 1000
    );
    // The burst, within 1.5 ms: as many calls as allowed in its period and no more.
    let in_burst: Vec<_> = rungs.iter().filter(|&&(_, at)| at >= burst).collect();
    assert!(!in_burst.is_empty(), "{rungs:?}");
    let period_of_burst = in_burst[0].0;
    let calls = in_burst
        .iter()
        .filter(|&&&(tick, _)| tick == period_of_burst)
        .count();
    assert!(
        calls <= RINGS_PER_PERIOD,
        "{calls} calls in one period: {rungs:?}"
    );
    assert!(rungs.len() <= 1 + 2 * RINGS_PER_PERIOD, "{rungs:?}");
}
