//! Steal: wall time in which a loop's thread neither ran, nor waited on the guest's run
//! queue, nor slept on purpose. On a virtual machine that is the hypervisor holding the
//! vCPU (the kernel's paravirtual steal clock keeps it out of the thread's CPU clock); on
//! bare metal it stays near zero. A loop measures it per cycle so that its deadline misses
//! can be split into those the host caused and those the guest did.
//!
//! The per-CPU `steal` column of `/proc/stat` has the same source but 10 ms resolution; a
//! cycle needs microseconds, hence the thread's own clocks.

use crate::clock::{monotonic_ns, thread_cpu_ns};
use std::fs::File;
use std::os::unix::fs::FileExt;

/// A cycle whose unaccounted time (or run-queue wait) reaches this counts as a host hold
/// (or a guest queueing). Below it are timer-interrupt delivery and clock-read noise (a
/// few µs per cycle here).
pub const HOST_HOLD_MIN_NS: u64 = 20_000;

/// Where a thread's time went, up to one instant.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct ThreadTimes {
    /// CLOCK_MONOTONIC.
    pub wall_ns: u64,
    /// The thread's CPU clock: time it ran (interrupts it took included; steal excluded).
    pub cpu_ns: u64,
    /// Time it was runnable but waited for the CPU in the guest (`/proc` schedstat).
    pub run_delay_ns: u64,
    /// Times it gave up the CPU itself: sleeps, but also blocking in a system call, a page
    /// fault or a stop signal. Read last.
    pub voluntary_switches: u64,
    /// The same count read first, before the wall clock: a stop that lands inside a
    /// reading is then counted by both windows that reading separates, whichever of them
    /// its time falls in.
    pub voluntary_switches_first: u64,
}

/// Reads [`ThreadTimes`] of the calling thread without allocating (`clock_gettime`,
/// `getrusage` and one `pread`, about 1.3 µs here). Open it on the thread it measures.
#[derive(Debug)]
pub struct ThreadClock {
    schedstat: File,
}

impl ThreadClock {
    /// `None` when the kernel has no per-thread schedstat (CONFIG_SCHED_INFO off).
    pub fn open() -> Option<Self> {
        File::open("/proc/thread-self/schedstat")
            .ok()
            .map(|schedstat| Self { schedstat })
    }

    pub fn read(&self) -> Option<ThreadTimes> {
        let voluntary_switches_first = voluntary_switches()?;
        let wall_ns = monotonic_ns();
        let cpu_ns = thread_cpu_ns()?;
        let mut buf = [0u8; 96];
        let n = self.schedstat.read_at(&mut buf, 0).ok()?;
        let (_, run_delay_ns) = parse_schedstat(&buf[..n])?;
        Some(ThreadTimes {
            wall_ns,
            cpu_ns,
            run_delay_ns,
            voluntary_switches: voluntary_switches()?,
            voluntary_switches_first,
        })
    }
}

fn voluntary_switches() -> Option<u64> {
    // SAFETY: a zeroed rusage is valid and getrusage only writes into it.
    let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: `ru` is a valid, writable rusage.
    let rc = unsafe { libc::getrusage(libc::RUSAGE_THREAD, &mut ru) };
    (rc == 0).then_some(ru.ru_nvcsw as u64)
}

/// Makes a stop of this process visible to [`StealMeter`]: blocks SIGCONT in the calling
/// thread and every thread it starts afterwards, so that a stop and continue (SIGSTOP,
/// Ctrl-Z, a debugger) leave a SIGCONT pending for the meter to take. A blocked SIGCONT
/// still continues the process; it only stays queued. Call it first in `main`, before any
/// thread exists: a thread that does not block it would take the signal and drop it.
pub fn notice_stops() -> bool {
    // SAFETY: the set is initialised by sigemptyset before use; a null old set is allowed.
    unsafe {
        let mut set: libc::sigset_t = std::mem::zeroed();
        libc::sigemptyset(&mut set);
        libc::sigaddset(&mut set, libc::SIGCONT);
        libc::pthread_sigmask(libc::SIG_BLOCK, &set, std::ptr::null_mut()) == 0
    }
}

/// Takes a pending SIGCONT (see [`notice_stops`]): true when the process was stopped and
/// continued since the last one was taken. Two system calls, made only for a cycle that
/// lost time or blocked.
fn take_continue() -> bool {
    // SAFETY: both sets are initialised (sigpending fills one, sigemptyset the other); a
    // zero timeout makes sigtimedwait a non-blocking take of an already pending signal.
    unsafe {
        let mut pending: libc::sigset_t = std::mem::zeroed();
        if libc::sigpending(&mut pending) != 0 || libc::sigismember(&pending, libc::SIGCONT) != 1 {
            return false;
        }
        let mut only: libc::sigset_t = std::mem::zeroed();
        libc::sigemptyset(&mut only);
        libc::sigaddset(&mut only, libc::SIGCONT);
        let now = libc::timespec {
            tv_sec: 0,
            tv_nsec: 0,
        };
        libc::sigtimedwait(&only, std::ptr::null_mut(), &now) == libc::SIGCONT
    }
}

/// The first two fields of a schedstat line: time on the CPU and time waiting for it, ns.
pub fn parse_schedstat(line: &[u8]) -> Option<(u64, u64)> {
    let text = std::str::from_utf8(line).ok()?;
    let mut fields = text.split_ascii_whitespace().map(str::parse::<u64>);
    let on_cpu = fields.next()?.ok()?;
    let run_delay = fields.next()?.ok()?;
    Some((on_cpu, run_delay))
}

/// The sleeps a loop asked for between two readings: their total up to the timers'
/// deadlines (not to the wake-ups, so a late wake-up stays unaccounted) and how many.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Slept {
    pub ns: u64,
    pub calls: u64,
}

impl std::ops::Add for Slept {
    type Output = Slept;
    fn add(self, other: Slept) -> Slept {
        Slept {
            ns: self.ns + other.ns,
            calls: self.calls + other.calls,
        }
    }
}

/// Where a cycle's wall time went beyond running and the sleeps it asked for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct CycleLoss {
    /// Neither running, nor queued, nor asleep as asked: the host held the vCPU.
    pub held_ns: u64,
    /// Runnable, waiting behind another task of the guest.
    pub queued_ns: u64,
    /// The thread gave up its CPU more often than it slept (it blocked in a system call or
    /// a page fault) or was stopped (a SIGCONT was pending), so its unaccounted time is its
    /// own, not the host's.
    pub blocked: bool,
}

impl CycleLoss {
    /// The thread was stopped (a signal, a debugger): its unaccounted time is the guest's.
    pub fn stopped(self) -> Self {
        Self {
            held_ns: 0,
            blocked: true,
            ..self
        }
    }

    pub fn between(before: &ThreadTimes, after: &ThreadTimes, slept: Slept) -> Self {
        let wall = after.wall_ns.saturating_sub(before.wall_ns);
        let ran = after.cpu_ns.saturating_sub(before.cpu_ns);
        let queued_ns = after.run_delay_ns.saturating_sub(before.run_delay_ns);
        let switches = after
            .voluntary_switches
            .saturating_sub(before.voluntary_switches_first);
        let blocked = switches > slept.calls;
        let unaccounted = wall.saturating_sub(ran + queued_ns + slept.ns);
        Self {
            held_ns: if blocked { 0 } else { unaccounted },
            queued_ns,
            blocked,
        }
    }
}

/// Of `missed` periods lost in one cycle, those `lost_ns` of lost time explains: one per
/// period (rounded), never more than were missed. Losses below [`HOST_HOLD_MIN_NS`]
/// explain nothing.
pub fn periods_explained(missed: u64, lost_ns: u64, period_ns: u64) -> u64 {
    if lost_ns < HOST_HOLD_MIN_NS || period_ns == 0 {
        return 0;
    }
    missed.min((lost_ns + period_ns / 2) / period_ns)
}

/// Splits the states a loop never saw into those host holds explain and those guest
/// queueing explains, cycle by cycle. A loss after a cycle took its sample shows up as
/// states skipped in the next cycle, so a cycle's loss not spent explaining its own misses
/// carries over to the next one (and no further).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MissAttribution {
    held_ns: u64,
    queued_ns: u64,
}

impl MissAttribution {
    /// `unseen` states skipped this cycle and the cycle's loss: returns (periods the host
    /// explains, periods guest queueing explains).
    pub fn explain(&mut self, unseen: u64, loss: &CycleLoss, period_ns: u64) -> (u64, u64) {
        let held = self.held_ns + loss.held_ns;
        let queued = self.queued_ns + loss.queued_ns;
        let by_host = periods_explained(unseen, held, period_ns);
        let by_queue = periods_explained(unseen - by_host, queued, period_ns);
        self.held_ns = held.saturating_sub(by_host * period_ns).min(loss.held_ns);
        self.queued_ns = queued
            .saturating_sub(by_queue * period_ns)
            .min(loss.queued_ns);
        (by_host, by_queue)
    }
}

/// One window of a [`StealMeter`]: from one wake-up to the next.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Window {
    pub wall_ns: u64,
    pub ran_ns: u64,
    pub loss: CycleLoss,
    /// States the loop skipped at the take inside the window, and how many of them the
    /// host and guest queueing explain.
    pub unseen: u64,
    pub by_host: u64,
    pub by_queue: u64,
}

/// A loop's steal accounting. It reads its thread's times once per cycle, right after the
/// wait's sleep, where the loop has slack (read after the answer, the ~1.5 µs it costs
/// would come out of the sleep before the next sample), and attributes the states skipped
/// at each take. The `sleep` strategy's polling sleeps are counted as asked, so there a
/// stop can hide behind a sleep that expired at once; `hybrid` checks its sleep.
#[derive(Debug)]
pub struct StealMeter {
    clock: Option<ThreadClock>,
    period_ns: u64,
    last: Option<ThreadTimes>,
    /// Sleeps since `last` that the next wake-up's own sleep does not include.
    sleeps: Slept,
    /// Voluntary switches just before the sleep that ends at the next wake-up.
    switches_before_sleep: Option<u64>,
    unseen: u64,
    attribution: MissAttribution,
}

impl StealMeter {
    pub fn new(period_ns: u64) -> Self {
        Self {
            clock: ThreadClock::open(),
            period_ns,
            last: None,
            sleeps: Slept::default(),
            switches_before_sleep: None,
            unseen: 0,
            attribution: MissAttribution::default(),
        }
    }

    /// False when the kernel has no per-thread schedstat: nothing is measured.
    pub fn available(&self) -> bool {
        self.clock.is_some()
    }

    /// Just before the wait's sleep: what the sleep itself switches is told apart from a
    /// stop or a block elsewhere in the cycle (a sleep that expires at once does not
    /// switch, and would otherwise cover for one).
    pub fn before_sleep(&mut self) {
        if self.clock.is_some() {
            self.switches_before_sleep = voluntary_switches();
        }
    }

    /// At a wake-up, after the wait's sleep `slept` (none if it did not sleep): closes the
    /// window since the previous wake-up.
    pub fn at_wake(&mut self, slept: Slept) -> Option<Window> {
        let now = self.clock.as_ref().and_then(ThreadClock::read);
        let before_sleep = self.switches_before_sleep.take();
        let window = match (self.last, now) {
            (Some(before), Some(after)) => {
                // The sleep accounts for one switch if it made any; more is a stop in it.
                let slept = match before_sleep {
                    Some(b) if slept.calls > 0 => Slept {
                        calls: after.voluntary_switches.saturating_sub(b).min(1),
                        ..slept
                    },
                    _ => slept,
                };
                let mut loss = CycleLoss::between(&before, &after, self.sleeps + slept);
                // A stop's switch can pass for the sleep's own when the sleep expired at
                // once; its SIGCONT cannot. A blocked cycle takes it too, so that it does
                // not excuse a later hold.
                if (loss.blocked || loss.held_ns >= HOST_HOLD_MIN_NS) && take_continue() {
                    loss = loss.stopped();
                }
                let (by_host, by_queue) =
                    self.attribution.explain(self.unseen, &loss, self.period_ns);
                Some(Window {
                    wall_ns: after.wall_ns.saturating_sub(before.wall_ns),
                    ran_ns: after.cpu_ns.saturating_sub(before.cpu_ns),
                    loss,
                    unseen: self.unseen,
                    by_host,
                    by_queue,
                })
            }
            _ => None,
        };
        self.last = now;
        self.sleeps = Slept::default();
        self.unseen = 0;
        window
    }

    /// After a take that skipped `unseen` states, having slept `slept` since the wake-up.
    pub fn after_take(&mut self, unseen: u64, slept: Slept) {
        self.unseen += unseen;
        self.sleeps = self.sleeps + slept;
    }

    /// A wait without a wake-up reading (start-up, a wait on another process's event):
    /// the next window starts afresh.
    pub fn restart(&mut self) {
        // A stop before the window opens is not this window's.
        take_continue();
        self.last = None;
        self.sleeps = Slept::default();
        self.switches_before_sleep = None;
        self.unseen = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn times(wall: u64, cpu: u64, queued: u64, switches: u64) -> ThreadTimes {
        ThreadTimes {
            wall_ns: wall,
            cpu_ns: cpu,
            run_delay_ns: queued,
            voluntary_switches: switches,
            voluntary_switches_first: switches,
        }
    }

    fn slept(ns: u64, calls: u64) -> Slept {
        Slept { ns, calls }
    }

    fn loss(held_ns: u64, queued_ns: u64) -> CycleLoss {
        CycleLoss {
            held_ns,
            queued_ns,
            blocked: false,
        }
    }

    #[test]
    fn schedstat_line_parses_and_garbage_does_not() {
        assert_eq!(parse_schedstat(b"416140 0 1\n"), Some((416140, 0)));
        assert_eq!(
            parse_schedstat(b"9000000000 123456 77\n"),
            Some((9_000_000_000, 123_456))
        );
        assert_eq!(parse_schedstat(b""), None);
        assert_eq!(parse_schedstat(b"12"), None);
        assert_eq!(parse_schedstat(b"12 x 3"), None);
        assert_eq!(parse_schedstat(&[0xff, b' ', b'1']), None);
    }

    #[test]
    fn held_time_is_what_running_queueing_and_sleeping_leave() {
        let a = times(1_000_000, 500_000, 7_000, 3);
        // 100 µs of wall: 30 ran, 20 queued, 10 slept in one sleep -> 40 held by the host.
        let b = times(1_100_000, 530_000, 27_000, 4);
        let l = CycleLoss::between(&a, &b, slept(10_000, 1));
        assert_eq!((l.held_ns, l.queued_ns, l.blocked), (40_000, 20_000, false));
        // More accounted than elapsed (clock granularity): zero, not an underflow.
        assert_eq!(CycleLoss::between(&a, &b, slept(90_000, 1)).held_ns, 0);
        assert_eq!(CycleLoss::between(&b, &a, slept(0, 0)).held_ns, 0);
        // Gave up the CPU once without a sleep asked: blocked, its own time.
        let l = CycleLoss::between(&a, &b, slept(0, 0));
        assert!(l.blocked);
        assert_eq!(l.held_ns, 0);
    }

    #[test]
    fn explained_periods_round_to_periods_and_never_exceed_the_misses() {
        let p = 50_000;
        assert_eq!(periods_explained(40, 2_000_000, p), 40);
        assert_eq!(periods_explained(40, 1_000_000, p), 20);
        assert_eq!(periods_explained(3, 2_000_000, p), 3);
        assert_eq!(periods_explained(1, 30_000, p), 1);
        assert_eq!(periods_explained(1, 24_000, p), 0);
        assert_eq!(periods_explained(5, HOST_HOLD_MIN_NS - 1, 10_000), 0);
        assert_eq!(periods_explained(5, 1_000_000, 0), 0);
    }

    #[test]
    fn a_loss_late_in_one_cycle_explains_the_next_cycles_misses_once() {
        let p = 50_000;
        let mut a = MissAttribution::default();
        // Held 100 µs after taking its sample: nothing missed yet.
        assert_eq!(a.explain(0, &loss(100_000, 0), p), (0, 0));
        // The next cycle finds 2 states skipped, and lost nothing itself.
        assert_eq!(a.explain(2, &loss(0, 0), p), (2, 0));
        // Spent: a third skip later is not explained by the same hold again.
        assert_eq!(a.explain(1, &loss(0, 0), p), (0, 0));
        // Carried one cycle only.
        assert_eq!(a.explain(0, &loss(0, 60_000), p), (0, 0));
        assert_eq!(a.explain(0, &loss(0, 0), p), (0, 0));
        assert_eq!(a.explain(1, &loss(0, 0), p), (0, 0));
        // Host first, then queueing, never more than were missed.
        assert_eq!(a.explain(5, &loss(100_000, 100_000), p), (2, 2));
        assert_eq!(a.explain(3, &loss(1_000_000, 1_000_000), p), (3, 0));
    }

    #[test]
    fn a_meter_closes_one_window_per_wake_up_with_the_skips_inside_it() {
        let mut m = StealMeter::new(50_000);
        if !m.available() {
            eprintln!("no /proc/thread-self/schedstat on this kernel: nothing to check");
            return;
        }
        assert_eq!(
            m.at_wake(Slept::default()),
            None,
            "no window before the first reading"
        );
        m.after_take(3, Slept::default());
        spin_for(1_000_000);
        let w = m.at_wake(Slept::default()).expect("a window");
        assert_eq!(w.unseen, 3);
        assert!(w.wall_ns >= 1_000_000 && w.ran_ns > 0, "{w:?}");
        assert!(!w.loss.blocked, "{w:?}");
        let w = m.at_wake(Slept::default()).expect("a window");
        assert_eq!(w.unseen, 0, "skips are counted in one window only");
        m.restart();
        assert_eq!(
            m.at_wake(Slept::default()),
            None,
            "a restart opens no window"
        );
    }

    /// A stop whose switch the meter cannot see (here: a sleep declared as the one switch it
    /// made, the way a stop at the entry of a sleep that expired at once looks) is still
    /// not the host's: its SIGCONT is pending, and the window is the guest's.
    #[test]
    fn a_continue_signal_takes_a_lost_window_from_the_host() {
        let mut m = StealMeter::new(50_000);
        if !m.available() {
            eprintln!("no /proc/thread-self/schedstat on this kernel: nothing to check");
            return;
        }
        // Only this test's thread blocks SIGCONT, and the signal goes to this thread only.
        assert!(notice_stops());
        let one_sleep = slept(0, 1);
        let lost_window = |m: &mut StealMeter, continued: bool| {
            m.restart();
            assert_eq!(m.at_wake(Slept::default()), None);
            crate::pacer::sleep_until(monotonic_ns() + 2_000_000);
            if continued {
                // SAFETY: signals this thread, which blocks SIGCONT: it only becomes pending.
                unsafe { libc::pthread_kill(libc::pthread_self(), libc::SIGCONT) };
            }
            m.at_wake(one_sleep).expect("a window")
        };
        let held = lost_window(&mut m, false);
        assert!(
            held.loss.held_ns >= 1_500_000 && !held.loss.blocked,
            "{held:?}"
        );
        let stopped = lost_window(&mut m, true);
        assert_eq!(stopped.loss.held_ns, 0, "{stopped:?}");
        assert!(stopped.loss.blocked, "{stopped:?}");
        // Taken once: the next loss is the host's again.
        let held = lost_window(&mut m, false);
        assert!(held.loss.held_ns >= 1_500_000, "{held:?}");
    }

    fn spin_for(ns: u64) {
        let end = monotonic_ns() + ns;
        while monotonic_ns() < end {
            std::hint::spin_loop();
        }
    }

    /// The identity behind the attribution: a thread sharing its CPU with a busy one
    /// waits about half the time, and all of that must show up as run-queue delay, not as
    /// host time; a sleep stops both clocks, so it is host time unless declared.
    #[test]
    fn waiting_for_the_cpu_and_sleeping_are_not_blamed_on_the_host() {
        let Some(probe) = ThreadClock::open() else {
            eprintln!("no /proc/thread-self/schedstat on this kernel: nothing to check");
            return;
        };
        let cpu = 0;
        if crate::rt::pin_to_cpu(cpu).is_err() {
            eprintln!("cannot pin to CPU {cpu}: nothing to check");
            return;
        }
        let rival = std::thread::spawn(move || {
            let _ = crate::rt::pin_to_cpu(cpu);
            spin_for(300_000_000);
        });
        let before = probe.read().expect("schedstat readable");
        spin_for(200_000_000);
        let after = probe.read().expect("schedstat readable");
        rival.join().expect("rival thread");
        let wall = after.wall_ns - before.wall_ns;
        let l = CycleLoss::between(&before, &after, Slept::default());
        assert!(
            l.queued_ns > wall / 5,
            "sharing a CPU must show as run-queue delay: {} ns of {wall} ns",
            l.queued_ns
        );
        assert!(
            l.held_ns < wall / 5,
            "waiting in the guest blamed on the host: {} ns of {wall} ns (queued {} ns)",
            l.held_ns,
            l.queued_ns
        );

        let before = probe.read().expect("schedstat readable");
        let wake = monotonic_ns() + 20_000_000;
        let asked = slept(wake - before.wall_ns, 1);
        crate::pacer::sleep_until(wake);
        let after = probe.read().expect("schedstat readable");
        let l = CycleLoss::between(&before, &after, asked);
        assert!(!l.blocked, "one sleep asked, one taken");
        assert!(
            l.held_ns < 2_000_000,
            "a 20 ms sleep left {} ns unaccounted",
            l.held_ns
        );
        // The same sleep, undeclared: the thread gave up its CPU on its own, and that is
        // not the host's doing either.
        let l = CycleLoss::between(&before, &after, Slept::default());
        assert!(l.blocked);
        assert_eq!(l.held_ns, 0);
    }
}
