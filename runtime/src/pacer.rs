//! The one clock every periodic loop uses: absolute deadlines on CLOCK_MONOTONIC,
//! reached by `clock_nanosleep(TIMER_ABSTIME)`, by spinning, or by sleeping to a margin
//! before the deadline and spinning the rest (iceoryx2's timers are jiffy-grained here).

use crate::clock::monotonic_ns;
use serde::{Deserialize, Deserializer, Serialize, Serializer};
use std::str::FromStr;

/// How a loop waits for its next deadline or message. Written `sleep`, `spin`,
/// `hybrid:<µs>` or `event` on the command line and in deployment files.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WaitStrategy {
    /// clock_nanosleep to the deadline: no CPU burnt, the kernel timer's wake-up latency
    /// (tens of µs on a VM; see docs/design.md's wait strategies).
    Sleep,
    /// Busy-wait: microsecond-exact, one whole core. On 2 cores only one process can.
    Spin,
    /// Sleep until `margin_ns` before the deadline, then spin. An input-paced loop whose
    /// margin is already past when it is done rests a few µs all the same, if its next
    /// input is still far enough off ([`crate::runner::hybrid_sleep_target`]).
    Hybrid { margin_ns: u64 },
    /// Block until the input's producer raises an event (hardware mode: the current loop,
    /// woken by the bridge). A clock-paced loop treats it as `Sleep`.
    Event,
}

impl FromStr for WaitStrategy {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "sleep" => Ok(Self::Sleep),
            "spin" => Ok(Self::Spin),
            // The current loop's margin: a larger one leaves sleeps too short to give the
            // CPU away (crate::deploy::CURRENT_LOOP_MARGIN_NS).
            "hybrid" => Ok(Self::Hybrid {
                margin_ns: crate::deploy::CURRENT_LOOP_MARGIN_NS,
            }),
            "event" => Ok(Self::Event),
            other => match other.strip_prefix("hybrid:") {
                Some(us) => us
                    .parse::<u64>()
                    .map(|us| Self::Hybrid {
                        margin_ns: us * 1000,
                    })
                    .map_err(|_| format!("bad hybrid margin `{us}` (µs expected)")),
                None => Err(format!(
                    "unknown wait strategy `{other}` (sleep, spin, hybrid, hybrid:<µs> or event)"
                )),
            },
        }
    }
}

impl std::fmt::Display for WaitStrategy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Sleep => f.write_str("sleep"),
            Self::Spin => f.write_str("spin"),
            Self::Hybrid { margin_ns } => write!(f, "hybrid:{}", margin_ns / 1000),
            Self::Event => f.write_str("event"),
        }
    }
}

impl Serialize for WaitStrategy {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for WaitStrategy {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let text = String::deserialize(d)?;
        text.parse().map_err(serde::de::Error::custom)
    }
}

/// `t_ns` as a `timespec` (an absolute CLOCK_MONOTONIC time for the kernel's sleeps).
pub(crate) fn timespec(t_ns: u64) -> libc::timespec {
    libc::timespec {
        tv_sec: (t_ns / 1_000_000_000) as libc::time_t,
        tv_nsec: (t_ns % 1_000_000_000) as libc::c_long,
    }
}

/// Sleeps until the absolute CLOCK_MONOTONIC time `t_ns`.
pub fn sleep_until(t_ns: u64) {
    let ts = timespec(t_ns);
    // EINTR (a signal) just returns early; callers re-check the time and the stop flag.
    // SAFETY: valid timespec, null remainder is allowed with TIMER_ABSTIME.
    unsafe {
        libc::clock_nanosleep(
            libc::CLOCK_MONOTONIC,
            libc::TIMER_ABSTIME,
            &ts,
            std::ptr::null_mut(),
        );
    }
}

/// Waits until `t_ns` with the given strategy; returns the wake-up time.
pub fn wait_until(t_ns: u64, strategy: WaitStrategy) -> u64 {
    match strategy {
        WaitStrategy::Sleep | WaitStrategy::Event => sleep_until(t_ns),
        WaitStrategy::Spin => {}
        WaitStrategy::Hybrid { margin_ns } => {
            if t_ns > margin_ns {
                sleep_until(t_ns - margin_ns)
            }
        }
    }
    loop {
        let now = monotonic_ns();
        if now >= t_ns {
            return now;
        }
        std::hint::spin_loop();
    }
}

/// One wake-up of a [`Pacer`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Tick {
    /// Index of the deadline (0, 1, 2, ...).
    pub index: u64,
    pub deadline_ns: u64,
    pub woke_ns: u64,
}

impl Tick {
    pub fn latency_ns(&self) -> u64 {
        self.woke_ns.saturating_sub(self.deadline_ns)
    }
}

/// Absolute-deadline clock: deadline k is `epoch + k·period`, never accumulated from wake
/// times, so lateness never drifts the schedule.
#[derive(Debug, Clone)]
pub struct Pacer {
    epoch_ns: u64,
    period_ns: u64,
    next: u64,
    strategy: WaitStrategy,
}

impl Pacer {
    pub fn new(epoch_ns: u64, period_ns: u64, strategy: WaitStrategy) -> Self {
        Self {
            epoch_ns,
            period_ns,
            next: 0,
            strategy,
        }
    }

    pub fn deadline(&self, index: u64) -> u64 {
        self.epoch_ns + index * self.period_ns
    }

    /// Waits for the next deadline. If already past it, returns at once (the caller sees
    /// the lateness in the tick and decides what a missed period means for it).
    pub fn wait(&mut self) -> Tick {
        let woke_ns = wait_until(self.next_deadline(), self.strategy);
        self.tick_at(woke_ns)
    }

    /// The deadline the next tick is for.
    pub fn next_deadline(&self) -> u64 {
        self.deadline(self.next)
    }

    /// Takes the next tick as woken at `woke_ns`, without waiting (a virtual clock, or a
    /// caller that waited itself).
    pub fn tick_at(&mut self, woke_ns: u64) -> Tick {
        let index = self.next;
        self.next += 1;
        Tick {
            index,
            deadline_ns: self.deadline(index),
            woke_ns,
        }
    }

    /// Moves the schedule so that deadline `index` falls at `at_ns` (after a stall the
    /// caller chose to absorb rather than catch up).
    pub fn reanchor(&mut self, index: u64, at_ns: u64) {
        self.epoch_ns = at_ns.saturating_sub(index * self.period_ns);
        self.next = index;
    }

    /// For a simulated device whose time must not run while its process is held up: if
    /// deadline `index` is already past at `now_ns`, moves it one period after `now_ns` and
    /// returns by how much it was late (the time paused).
    pub fn pause_if_late(&mut self, index: u64, now_ns: u64) -> Option<u64> {
        let due = self.deadline(index);
        (now_ns > due).then(|| {
            self.reanchor(index, now_ns + self.period_ns);
            now_ns - due
        })
    }

    pub fn epoch_ns(&self) -> u64 {
        self.epoch_ns
    }

    /// Skips ahead so the next deadline is the first one after `now_ns`; returns how many
    /// deadlines were skipped.
    pub fn skip_to(&mut self, now_ns: u64) -> u64 {
        let target = now_ns.saturating_sub(self.epoch_ns) / self.period_ns + 1;
        let skipped = target.saturating_sub(self.next);
        self.next = self.next.max(target);
        skipped
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deadlines_are_absolute_and_never_early() {
        let start = monotonic_ns() + 1_000_000;
        let mut p = Pacer::new(start, 200_000, WaitStrategy::Hybrid { margin_ns: 100_000 });
        for k in 0..20 {
            let t = p.wait();
            assert_eq!(t.index, k);
            assert_eq!(t.deadline_ns, start + k * 200_000);
            assert!(t.woke_ns >= t.deadline_ns);
        }
        let mut late = Pacer::new(monotonic_ns() - 10_000_000, 1_000_000, WaitStrategy::Spin);
        assert!(late.skip_to(monotonic_ns()) >= 10);
        assert!(late.wait().woke_ns >= late.deadline(0));
    }

    #[test]
    fn a_late_deadline_is_paused_not_caught_up() {
        let mut p = Pacer::new(1_000, 100, WaitStrategy::Spin);
        assert_eq!(
            p.pause_if_late(3, 1_250),
            None,
            "deadline 3 is 1_300, not past"
        );
        assert_eq!(p.deadline(3), 1_300);
        assert_eq!(p.pause_if_late(3, 1_450), Some(150));
        assert_eq!(p.deadline(3), 1_550);
        assert_eq!(p.deadline(4), 1_650);
    }

    #[test]
    fn strategies_parse() {
        assert_eq!("sleep".parse(), Ok(WaitStrategy::Sleep));
        assert_eq!(
            "hybrid:15".parse(),
            Ok(WaitStrategy::Hybrid { margin_ns: 15_000 })
        );
        assert_eq!("event".parse(), Ok(WaitStrategy::Event));
        assert!("nap".parse::<WaitStrategy>().is_err());
        // A bare `hybrid` is the current loop's default, whose margin leaves its sleeps
        // long enough to give the CPU away.
        assert_eq!(
            "hybrid".parse(),
            Ok(crate::deploy::Deployment::default().wait(
                stepdrive_shared::stack::Role::CurrentLoop,
                stepdrive_shared::scenario::Mode::Realtime
            ))
        );
    }
}
