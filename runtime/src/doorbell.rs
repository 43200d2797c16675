//! Lockstep hand-offs that wake the waiting process when its input is published, not when a
//! sleep expires. Every lockstep process of an instance maps one shared page
//! (`/dev/shm/stepdrive-<instance>.doorbells`) holding a doorbell per role: a futex word the
//! publishers of the role's inputs bump, and the sequence number of the first state worth
//! waking the role for (0: awake). A waiting process spins a little, arms its doorbell,
//! polls once more and sleeps on the futex; a publisher rings after each message and makes
//! the `futex` call only when the reader sleeps for what it published.
//!
//! Why not iceoryx2's event service: a notify is a `sendto` and a listener wake-up ~15 µs
//! here, a futex wake ~3–8 µs (docs/measurements.md). Why not the old back-off (spin, yield,
//! sleep 200 µs): with one CPU hog per core every hand-off ended in the sleep, and a 0.18 s
//! run took 20–40 s.
//!
//! A reader may be woken by another reader instead of the publisher
//! ([`stepdrive_shared::stack::woken_by`]): the current loop rings the position loop's
//! doorbell for the state of its tick as it takes it, and the two share a CPU, the plant
//! has the other ([`placement`]). A wake-up on the waker's own CPU is one context switch,
//! ~4 µs here; woken by the plant, on a CPU where the plant or the current loop spins, it
//! was ~17 µs, and the current loop waits for that tick's setpoint (docs/measurements.md).
//!
//! Realtime and hardware stacks use one doorbell only: the position loop's, rung by a client
//! that sent it a command, so that the command is carried out between ticks instead of at
//! the next one (a tick waited up to a whole period: command latency p99 was one period plus
//! the wake-up, 563–945 µs at 2 kHz). Their loops are otherwise paced by the clock or by the
//! bridge's event, and no publisher rings.

use std::sync::atomic::{fence, AtomicU32, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;
use stepdrive_shared::services::Topic;
use stepdrive_shared::stack::{wakes_or_is_woken, woken_by, Role, NODES};

/// One role's doorbell, one cache line, so that ringing one reader does not bounce another's.
#[repr(C, align(64))]
struct Bell {
    /// The futex word: bumped by every ring.
    rung: AtomicU32,
    /// 0 while the role is awake; otherwise 1 + the first state sequence number it sleeps
    /// for (1: any message).
    wake_at: AtomicU64,
}

/// Doorbells, one per role code (`Role::code` is below this).
const BELLS: usize = 8;
const PAGE: usize = std::mem::size_of::<Bell>() * BELLS;

/// Why the doorbells could not be opened.
#[derive(Debug, thiserror::Error)]
#[error("cannot map the lockstep doorbells `{path}`")]
pub struct DoorbellError {
    pub path: String,
    #[source]
    pub source: std::io::Error,
}

/// The instance's doorbell page, mapped.
struct Page {
    bells: *const Bell,
}

// SAFETY: the page is only touched through atomics; the mapping lives as long as `Page`.
unsafe impl Send for Page {}
unsafe impl Sync for Page {}

impl Drop for Page {
    fn drop(&mut self) {
        // SAFETY: mapped by `Doorbells::open` with this length, unmapped once.
        unsafe {
            libc::munmap(self.bells as *mut libc::c_void, PAGE);
        }
    }
}

impl Page {
    fn bell(&self, code: u32) -> &Bell {
        let i = (code as usize).min(BELLS - 1);
        // SAFETY: `i < BELLS`, inside the mapping.
        unsafe { &*self.bells.add(i) }
    }
}

/// The path of an instance's doorbell page (the instance name is validated: letters,
/// digits, '.', '-', '_').
pub fn path(instance: &str) -> String {
    format!("/dev/shm/stepdrive-{instance}.doorbells")
}

/// Removes an instance's doorbell page once its stack has ended (the launcher's job; a file
/// left by a hand-started stack is reused by the next one of that instance).
pub fn remove(instance: &str) {
    let _ = std::fs::remove_file(path(instance));
}

/// Removes the doorbell pages of instances `live` says are gone (left by stacks started by
/// hand or launchers that were killed). A page is created after its process's iceoryx2
/// node, so a stack starting now is live already.
pub fn remove_stale(live: &std::collections::BTreeSet<String>) {
    remove_stale_in(std::path::Path::new("/dev/shm"), live);
}

fn remove_stale_in(dir: &std::path::Path, live: &std::collections::BTreeSet<String>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(instance) = name
            .to_str()
            .and_then(|n| n.strip_prefix("stepdrive-"))
            .and_then(|n| n.strip_suffix(".doorbells"))
        else {
            continue;
        };
        if !live.contains(instance) {
            let _ = std::fs::remove_file(entry.path());
        }
    }
}

/// Lockstep: the CPU `role` runs on, out of the `allowed` ones. The current loop and the
/// position loop it wakes ([`woken_by`]) share one: it waits for the setpoint anyway, so
/// its CPU is the one to lend, and a wake-up there is a context switch of its own CPU. The
/// plant has another to itself. Which two, the instance's name decides, so that parallel
/// stacks spread over the CPUs. Left to the scheduler, the three sometimes shared one CPU
/// beside a CPU hog for a whole run (1.7x real time, against 5-6x). None on one CPU, or
/// for a role in no pair (a tool, the identification).
pub fn placement(role: Role, instance: &str, allowed: &[usize]) -> Option<usize> {
    let n = allowed.len();
    if n < 2 {
        return None;
    }
    // The same instance gets the same CPUs in every process of its stack.
    let h = stepdrive_shared::fnv1a(instance.as_bytes());
    let device = (h % n as u64) as usize;
    match role {
        Role::Plant => Some(allowed[device]),
        _ if wakes_or_is_woken(role) => Some(allowed[(device + 1) % n]),
        _ => None,
    }
}

/// An instance's doorbells, shared by the ports and the runner of one process.
#[derive(Clone)]
pub struct Doorbells {
    page: Arc<Page>,
}

impl Doorbells {
    /// Maps the instance's page, creating it if this process is the first.
    pub fn open(instance: &str) -> Result<Self, DoorbellError> {
        Self::open_with(instance, true)?.ok_or_else(|| DoorbellError {
            path: path(instance),
            source: std::io::ErrorKind::NotFound.into(),
        })
    }

    /// Maps the instance's page if its stack made one (`None`: it did not; a client never
    /// leaves a page behind for a stack that is not there).
    pub fn open_existing(instance: &str) -> Result<Option<Self>, DoorbellError> {
        Self::open_with(instance, false)
    }

    fn open_with(instance: &str, create: bool) -> Result<Option<Self>, DoorbellError> {
        use std::os::unix::fs::OpenOptionsExt;
        use std::os::unix::io::AsRawFd;
        let path = path(instance);
        let error = |source| DoorbellError {
            path: path.clone(),
            source,
        };
        let file = match std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(create)
            .truncate(false)
            .mode(0o600)
            .open(&path)
        {
            Ok(file) => file,
            Err(e) if !create && e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(error(e)),
        };
        // Every opener sets the same length: the page is zeros until rung.
        file.set_len(PAGE as u64).map_err(error)?;
        // SAFETY: a shared mapping of a file of PAGE bytes; checked for MAP_FAILED.
        let p = unsafe {
            libc::mmap(
                std::ptr::null_mut(),
                PAGE,
                libc::PROT_READ | libc::PROT_WRITE,
                libc::MAP_SHARED,
                file.as_raw_fd(),
                0,
            )
        };
        if p == libc::MAP_FAILED {
            return Err(error(std::io::Error::last_os_error()));
        }
        Ok(Some(Self {
            page: Arc::new(Page {
                bells: p as *const Bell,
            }),
        }))
    }

    /// The ringer of `topic`'s readers (every role the stack's declaration says reads it),
    /// for its publisher: except those another reader wakes ([`Doorbells::relay`]).
    pub fn ringer(&self, topic: Topic) -> Ringer {
        self.ringer_of_all(
            NODES
                .iter()
                .filter(|n| n.reads(topic) && woken_by(n.role, topic).is_none())
                .map(|n| n.role),
        )
    }

    /// The ringer of the readers of `topic` that `reader` wakes as it takes each message
    /// ([`stepdrive_shared::stack::woken_by`]); `None` if it wakes none.
    pub fn relay(&self, reader: Role, topic: Topic) -> Option<Ringer> {
        let woken = NODES
            .iter()
            .map(|n| n.role)
            .filter(|&r| woken_by(r, topic) == Some(reader));
        let ringer = self.ringer_of_all(woken);
        (ringer.n > 0).then_some(ringer)
    }

    fn ringer_of_all(&self, roles: impl Iterator<Item = Role>) -> Ringer {
        let mut codes = [0u32; BELLS];
        let mut n = 0;
        for role in roles.take(BELLS) {
            codes[n] = role.code();
            n += 1;
        }
        Ringer {
            page: self.page.clone(),
            codes,
            n,
        }
    }

    /// The ringer of one role's doorbell (a client's command wakes the position loop).
    pub fn ringer_of(&self, role: Role) -> Ringer {
        self.ringer_of_all(std::iter::once(role))
    }

    /// `role`'s doorbell, to wait on. It starts awake (a process killed asleep left its
    /// doorbell armed).
    pub fn waiter(&self, role: Role) -> Waiter {
        let code = role.code();
        self.page.bell(code).wake_at.store(0, Ordering::SeqCst);
        Waiter {
            page: self.page.clone(),
            code,
        }
    }
}

/// Rings the doorbells of one topic's readers.
pub struct Ringer {
    page: Arc<Page>,
    codes: [u32; BELLS],
    n: usize,
}

impl Ringer {
    /// After a message is published: `key` is its state sequence number (None: any other
    /// message, which wakes every sleeping reader).
    pub fn ring(&self, key: Option<u64>) {
        // Orders the message before the loads of `wake_at` (pairs with the fence in
        // `Waiter::arm`): either the reader's last poll sees the message, or this sees the
        // reader asleep.
        fence(Ordering::SeqCst);
        for &code in &self.codes[..self.n] {
            let bell = self.page.bell(code);
            bell.rung.fetch_add(1, Ordering::SeqCst);
            let wake_at = bell.wake_at.load(Ordering::SeqCst);
            let wanted = match key {
                _ if wake_at == 0 => false,
                Some(k) => k.saturating_add(1) >= wake_at,
                None => true,
            };
            if wanted {
                futex_wake(&bell.rung);
            }
        }
    }
}

/// One role's side of its doorbell.
#[derive(Clone)]
pub struct Waiter {
    page: Arc<Page>,
    code: u32,
}

/// What the armed doorbell read: the sleep returns at once if it has been rung since.
#[derive(Debug, Clone, Copy)]
pub struct Armed(u32);

impl Waiter {
    /// Arms the doorbell for the state `key` (None: any message). Poll the inputs once more
    /// after this, then [`Waiter::sleep`].
    pub fn arm(&self, key: Option<u64>) -> Armed {
        let bell = self.page.bell(self.code);
        let wake_at = key.map_or(1, |k| k.saturating_add(1));
        bell.wake_at.store(wake_at, Ordering::SeqCst);
        fence(Ordering::SeqCst);
        Armed(bell.rung.load(Ordering::SeqCst))
    }

    /// Sleeps until rung (since `armed`) or `timeout`, then disarms. True if it was rung:
    /// the input is there, or a relayed ring's a moment ahead of it.
    pub fn sleep(&self, armed: Armed, timeout: Duration) -> bool {
        let bell = self.page.bell(self.code);
        futex_wait(&bell.rung, armed.0, timeout);
        self.disarm();
        bell.rung.load(Ordering::SeqCst) != armed.0
    }

    /// Sleeps until rung (since `armed`) or the absolute CLOCK_MONOTONIC time `t_ns` (as
    /// precisely as `clock_nanosleep`: both are the kernel's high-resolution timers), then
    /// disarms.
    pub fn sleep_until(&self, armed: Armed, t_ns: u64) {
        let bell = self.page.bell(self.code);
        let ts = crate::pacer::timespec(t_ns);
        // SAFETY: a shared futex on a word of a MAP_SHARED page; FUTEX_WAIT_BITSET takes an
        // absolute CLOCK_MONOTONIC timeout. A spurious or interrupted return is fine: the
        // caller looks at the time and polls again.
        unsafe {
            libc::syscall(
                libc::SYS_futex,
                bell.rung.as_ptr(),
                libc::FUTEX_WAIT_BITSET,
                armed.0,
                &ts as *const libc::timespec,
                std::ptr::null::<u32>(),
                libc::FUTEX_BITSET_MATCH_ANY,
            );
        }
        self.disarm();
    }

    /// Marks the role awake (its input came before it slept).
    pub fn disarm(&self) {
        self.page.bell(self.code).wake_at.store(0, Ordering::SeqCst);
    }
}

fn futex_wait(word: &AtomicU32, expected: u32, timeout: Duration) {
    let ts = libc::timespec {
        tv_sec: timeout.as_secs() as libc::time_t,
        tv_nsec: timeout.subsec_nanos() as libc::c_long,
    };
    // SAFETY: a shared (not private) futex on a word of a MAP_SHARED page, with a valid
    // relative timeout. A spurious or interrupted return is fine: the caller polls again.
    unsafe {
        libc::syscall(
            libc::SYS_futex,
            word.as_ptr(),
            libc::FUTEX_WAIT,
            expected,
            &ts as *const libc::timespec,
            std::ptr::null::<u32>(),
            0u32,
        );
    }
}

fn futex_wake(word: &AtomicU32) {
    // SAFETY: wakes the waiters of a futex word of a MAP_SHARED page.
    unsafe {
        libc::syscall(
            libc::SYS_futex,
            word.as_ptr(),
            libc::FUTEX_WAKE,
            i32::MAX,
            std::ptr::null::<libc::timespec>(),
            std::ptr::null::<u32>(),
            0u32,
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Instant;

    fn instance(name: &str) -> String {
        format!("doorbell-test-{name}-{}", std::process::id())
    }

    #[test]
    fn a_ring_wakes_a_sleeper_at_once_and_a_state_before_its_key_does_not() {
        let name = instance("wake");
        let bells = Doorbells::open(&name).expect("open");
        let position = bells.waiter(Role::PositionLoop);
        // The current loop wakes the position loop for its states.
        let states = bells
            .relay(Role::CurrentLoop, Topic::State)
            .expect("the current loop relays states");
        // Asleep for state 10: state 3 does not wake it, state 10 does.
        let sleeper = std::thread::spawn(move || {
            let armed = position.arm(Some(10));
            position.sleep(armed, Duration::from_secs(5));
            Instant::now()
        });
        std::thread::sleep(Duration::from_millis(50));
        states.ring(Some(3));
        std::thread::sleep(Duration::from_millis(100));
        assert!(
            !sleeper.is_finished(),
            "woken by a state it does not wait for"
        );
        // Times taken on both sides of the wake, not from the sleeper's start (a thread
        // may start late on a busy machine: once it measured 149.98 ms for "≥ 150 ms").
        let rung = Instant::now();
        states.ring(Some(10));
        let woke = sleeper.join().expect("sleeper");
        assert!(woke >= rung, "woke before the state it waits for was rung");
        let after = woke - rung;
        assert!(
            after < Duration::from_secs(4),
            "not woken: {after:?} after the ring"
        );
        remove(&name);
    }

    #[test]
    fn a_ring_between_arming_and_sleeping_is_not_lost() {
        let name = instance("race");
        let bells = Doorbells::open(&name).expect("open");
        let current = bells.waiter(Role::CurrentLoop);
        let setpoints = bells.ringer(Topic::Setpoint);
        let armed = current.arm(None);
        setpoints.ring(None);
        let t0 = Instant::now();
        current.sleep(armed, Duration::from_secs(5));
        assert!(t0.elapsed() < Duration::from_secs(1));
        // A role that does not read the topic is not rung: the plant reads no setpoints.
        let plant = bells.waiter(Role::Plant);
        let armed = plant.arm(None);
        setpoints.ring(None);
        let t0 = Instant::now();
        plant.sleep(armed, Duration::from_millis(100));
        assert!(t0.elapsed() >= Duration::from_millis(100));
        remove(&name);
    }

    #[test]
    fn the_current_loop_wakes_the_position_loop_for_a_state_and_the_plant_does_not() {
        let name = instance("relay");
        let bells = Doorbells::open(&name).expect("open");
        let position = bells.waiter(Role::PositionLoop);
        let published = bells.ringer(Topic::State);
        let relayed = bells
            .relay(Role::CurrentLoop, Topic::State)
            .expect("the current loop relays states");
        assert!(bells.relay(Role::Plant, Topic::State).is_none());
        assert!(bells.relay(Role::CurrentLoop, Topic::Setpoint).is_none());
        // The plant's ring of the awaited state leaves the position loop asleep.
        let armed = position.arm(Some(10));
        published.ring(Some(10));
        let t0 = Instant::now();
        assert!(!position.sleep(armed, Duration::from_millis(100)));
        assert!(t0.elapsed() >= Duration::from_millis(100));
        // The current loop's ring of it wakes it, and says so.
        let armed = position.arm(Some(10));
        relayed.ring(Some(10));
        let t0 = Instant::now();
        assert!(position.sleep(armed, Duration::from_secs(5)));
        assert!(t0.elapsed() < Duration::from_secs(1));
        // The plant still wakes the current loop.
        let current = bells.waiter(Role::CurrentLoop);
        let armed = current.arm(None);
        published.ring(Some(11));
        assert!(current.sleep(armed, Duration::from_secs(5)));
        remove(&name);
    }

    #[test]
    fn the_current_and_position_loops_share_a_cpu_the_plant_has_another_and_stacks_spread() {
        let mut layouts = std::collections::BTreeSet::new();
        for i in 0..16 {
            let name = format!("stack-{i}");
            let at = |role| placement(role, &name, &[2, 5, 7]);
            let (plant, current, position) = (
                at(Role::Plant),
                at(Role::CurrentLoop),
                at(Role::PositionLoop),
            );
            assert_eq!(current, position, "{name}");
            assert_ne!(plant, current, "{name}");
            assert!([plant, current]
                .iter()
                .all(|c| c.is_some_and(|c| [2, 5, 7].contains(&c))));
            assert_eq!(at(Role::Identify), None);
            assert_eq!(at(Role::Monitor), None);
            layouts.insert((plant, current));
        }
        assert!(
            layouts.len() > 1,
            "every stack on the same CPUs: {layouts:?}"
        );
        assert_eq!(placement(Role::Plant, "one", &[3]), None);
        assert_eq!(
            placement(Role::Plant, "x", &[1, 0]),
            placement(Role::Plant, "x", &[1, 0])
        );
    }

    #[test]
    fn the_pages_of_gone_instances_are_removed_and_live_ones_kept() {
        let dir = std::env::temp_dir().join(instance("stale"));
        std::fs::create_dir_all(&dir).expect("dir");
        for name in [
            "stepdrive-gone.doorbells",
            "stepdrive-live.x.doorbells",
            "stepdrive-gone.mcap",
        ] {
            std::fs::write(dir.join(name), b"").expect("file");
        }
        remove_stale_in(&dir, &["live.x".to_string()].into());
        let mut left: Vec<String> = std::fs::read_dir(&dir)
            .expect("read")
            .flatten()
            .filter_map(|e| e.file_name().to_str().map(String::from))
            .collect();
        left.sort();
        assert_eq!(left, ["stepdrive-gone.mcap", "stepdrive-live.x.doorbells"]);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn two_mappings_of_one_instance_share_the_bells() {
        let name = instance("shared");
        let a = Doorbells::open(&name).expect("open");
        let b = Doorbells::open(&name).expect("open again");
        let plant = a.waiter(Role::Plant);
        let commands = b.ringer(Topic::Command);
        let sleeper = std::thread::spawn(move || {
            let armed = plant.arm(None);
            let t0 = Instant::now();
            plant.sleep(armed, Duration::from_secs(5));
            t0.elapsed()
        });
        std::thread::sleep(Duration::from_millis(50));
        commands.ring(None);
        assert!(sleeper.join().expect("sleeper") < Duration::from_secs(4));
        remove(&name);
    }
}
