//! Real-time setup in cyclictest's spirit (`-p`, `-a`, `-m`): SCHED_FIFO priority, CPU
//! affinity, mlockall with a prefaulted stack, timer slack. A refusal is reported once,
//! clearly, and the process goes on, unless `require` is set.

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RtOptions {
    /// SCHED_FIFO priority 1..=99; `None` keeps SCHED_OTHER.
    pub priority: Option<u8>,
    /// Pin to this CPU.
    pub cpu: Option<usize>,
    /// A helper of the stack (`cpu` unset): every thread of the process on these CPUs, so
    /// that neither it nor the network traffic it handles lands on a loop's CPU (see
    /// `Deployment::helper_cpus`). Empty: its affinity is left alone.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub helper_cpus: Vec<usize>,
    /// mlockall(MCL_CURRENT | MCL_FUTURE) and prefault 512 KiB of stack.
    pub lock_memory: bool,
    /// prctl(PR_SET_TIMERSLACK) in ns (the kernel default is 50 µs, a whole period here).
    pub timer_slack_ns: Option<u64>,
    /// This nice value (ordinary scheduling), for the calling thread and what it starts
    /// afterwards. A refusal (not root) is noted at debug level only, even with `require`:
    /// the run is the same, only slower on a busy machine.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub nice: Option<i32>,
    /// Fail instead of warning when the system refuses a setting.
    pub require: bool,
}

/// A real-time setting the system refused, with the system's reason.
#[derive(Debug, thiserror::Error)]
pub enum RtError {
    #[error("timer slack of {ns} ns refused")]
    TimerSlack {
        ns: u64,
        #[source]
        source: std::io::Error,
    },
    #[error("mlockall refused")]
    LockMemory(#[source] std::io::Error),
    #[error("SCHED_FIFO priority {priority} refused")]
    Priority {
        priority: u8,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot pin to CPU {cpus}")]
    Affinity {
        cpus: String,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot read {RT_RUNTIME}")]
    ReadThrottling(#[source] std::io::Error),
    #[error("cannot write -1 to {RT_RUNTIME} (RT throttling stays on)")]
    WriteThrottling(#[source] std::io::Error),
}

impl RtError {
    /// The refusal with its cause, on one line.
    pub fn describe(&self) -> String {
        match std::error::Error::source(self) {
            Some(cause) => format!("{self}: {cause}"),
            None => self.to_string(),
        }
    }
}

#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct RtApplied {
    pub fifo: bool,
    pub pinned: bool,
    pub locked: bool,
    pub slack: bool,
    pub niced: bool,
}

fn refuse(require: bool, error: RtError) -> Result<(), RtError> {
    if require {
        Err(error)
    } else {
        tracing::warn!(
            "{}; continuing without it (use --require-rt to make this fatal)",
            error.describe()
        );
        Ok(())
    }
}

#[inline(never)]
fn prefault_stack() {
    let mut buf = [0u8; 512 * 1024];
    for i in (0..buf.len()).step_by(4096) {
        // SAFETY: in-bounds volatile write keeps the touch from being optimised away.
        unsafe { std::ptr::write_volatile(buf.as_mut_ptr().add(i), 1) };
    }
    std::hint::black_box(&buf);
}

impl RtOptions {
    /// Applies the settings to the calling thread/process.
    pub fn apply(&self) -> Result<RtApplied, RtError> {
        let mut applied = RtApplied::default();
        if let Some(ns) = self.timer_slack_ns {
            // SAFETY: plain prctl with integer arguments.
            let rc = unsafe { libc::prctl(libc::PR_SET_TIMERSLACK, ns.max(1) as libc::c_ulong) };
            if rc == 0 {
                applied.slack = true;
            } else {
                let source = std::io::Error::last_os_error();
                refuse(self.require, RtError::TimerSlack { ns, source })?;
            }
        }
        if self.lock_memory {
            // SAFETY: mlockall has no memory-safety preconditions.
            let rc = unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) };
            if rc == 0 {
                prefault_stack();
                applied.locked = true;
            } else {
                let source = std::io::Error::last_os_error();
                refuse(self.require, RtError::LockMemory(source))?;
            }
        }
        if let Some(nice) = self.nice {
            // SAFETY: plain setpriority on the calling thread (who = 0).
            let rc = unsafe { libc::setpriority(libc::PRIO_PROCESS, 0, nice) };
            if rc == 0 {
                applied.niced = true;
            } else {
                tracing::debug!(
                    nice,
                    error = %std::io::Error::last_os_error(),
                    "nice value refused: this process competes with ordinary tasks as an equal"
                );
            }
        }
        // Priority before affinity: a process that moves to a CPU where a SCHED_FIFO loop
        // is busy must arrive with its own priority, or it never runs there.
        if let Some(prio) = self.priority {
            let param = libc::sched_param {
                sched_priority: i32::from(prio.clamp(1, 99)),
            };
            // SAFETY: valid sched_param for the calling process.
            let rc = unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) };
            if rc == 0 {
                applied.fifo = true;
            } else {
                let source = std::io::Error::last_os_error();
                refuse(
                    self.require,
                    RtError::Priority {
                        priority: prio,
                        source,
                    },
                )?;
            }
        }
        if let Some(cpu) = self.cpu {
            match pin_to_cpu(cpu) {
                Ok(()) => applied.pinned = true,
                Err(source) => refuse(
                    self.require,
                    RtError::Affinity {
                        cpus: cpu.to_string(),
                        source,
                    },
                )?,
            }
        } else if !self.helper_cpus.is_empty() {
            match pin_process_to(&self.helper_cpus) {
                Ok(()) => applied.pinned = true,
                Err(source) => refuse(
                    self.require,
                    RtError::Affinity {
                        cpus: cpu_list(&self.helper_cpus),
                        source,
                    },
                )?,
            }
        }
        Ok(applied)
    }
}

/// `/proc/sys/kernel/sched_rt_runtime_us`: −1 means no RT throttling.
pub fn rt_runtime_us() -> Option<i64> {
    std::fs::read_to_string(RT_RUNTIME)
        .ok()
        .and_then(|s| s.trim().parse().ok())
}

pub const RT_RUNTIME: &str = "/proc/sys/kernel/sched_rt_runtime_us";

/// Turns RT throttling off (`sched_rt_runtime_us = -1`) until dropped, then restores the
/// previous value. Needs root; the caller decides whether a refusal is fatal.
pub struct RtThrottlingOff {
    previous: i64,
}

impl RtThrottlingOff {
    pub fn engage() -> Result<Option<Self>, RtError> {
        let previous = std::fs::read_to_string(RT_RUNTIME)
            .map_err(RtError::ReadThrottling)?
            .trim()
            .parse::<i64>()
            .map_err(|e| {
                RtError::ReadThrottling(std::io::Error::new(std::io::ErrorKind::InvalidData, e))
            })?;
        if previous == -1 {
            return Ok(None);
        }
        std::fs::write(RT_RUNTIME, "-1").map_err(RtError::WriteThrottling)?;
        tracing::info!("RT throttling off for this run (was {previous} µs); restored at exit");
        Ok(Some(Self { previous }))
    }

    /// Turns RT throttling off (whatever it is now) until dropped, then sets `previous`:
    /// a guard that takes over from one that died, and restores the value that one saved.
    pub fn hold(previous: i64) -> Result<Self, RtError> {
        if rt_runtime_us() != Some(-1) {
            std::fs::write(RT_RUNTIME, "-1").map_err(RtError::WriteThrottling)?;
        }
        Ok(Self { previous })
    }

    /// The value restored when dropped.
    pub fn previous(&self) -> i64 {
        self.previous
    }
}

impl Drop for RtThrottlingOff {
    fn drop(&mut self) {
        if let Err(e) = std::fs::write(RT_RUNTIME, self.previous.to_string()) {
            tracing::error!("could not restore {RT_RUNTIME} to {}: {e}", self.previous);
        }
    }
}

/// Pins the calling thread to one CPU.
pub fn pin_to_cpu(cpu: usize) -> std::io::Result<()> {
    set_affinity(0, &[cpu])
}

/// Pins every thread of the calling process to `cpus`. Threads started before this (a
/// live view's, a runtime's) are moved too; those started after inherit it.
pub fn pin_process_to(cpus: &[usize]) -> std::io::Result<()> {
    for entry in std::fs::read_dir("/proc/self/task")? {
        let Some(tid) = entry?
            .file_name()
            .to_str()
            .and_then(|s| s.parse::<libc::pid_t>().ok())
        else {
            continue;
        };
        match set_affinity(tid, cpus) {
            // A thread that ended since the directory was read.
            Err(e) if e.raw_os_error() == Some(libc::ESRCH) => {}
            other => other?,
        }
    }
    Ok(())
}

const CPU_SET_SIZE: usize = 8 * std::mem::size_of::<libc::cpu_set_t>();

fn set_affinity(tid: libc::pid_t, cpus: &[usize]) -> std::io::Result<()> {
    if cpus.is_empty() || cpus.iter().any(|&c| c >= CPU_SET_SIZE) {
        return Err(std::io::Error::from_raw_os_error(libc::EINVAL));
    }
    // SAFETY: cpu_set_t is plain data; every CPU is within its size (checked above).
    let rc = unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        for &cpu in cpus {
            libc::CPU_SET(cpu, &mut set);
        }
        libc::sched_setaffinity(tid, std::mem::size_of::<libc::cpu_set_t>(), &set)
    };
    if rc == 0 {
        Ok(())
    } else {
        Err(std::io::Error::last_os_error())
    }
}

/// The CPUs the calling thread may run on (all configured ones if the kernel will not say).
pub fn allowed_cpus() -> Vec<usize> {
    // SAFETY: cpu_set_t is plain data, filled by the kernel; CPU_ISSET reads within it.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        if libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &mut set) == 0 {
            return (0..CPU_SET_SIZE)
                .filter(|&c| libc::CPU_ISSET(c, &set))
                .collect();
        }
    }
    (0..configured_cpus()).collect()
}

/// The CPUs this machine has (configured, online or not).
pub fn configured_cpus() -> usize {
    // SAFETY: sysconf only reads a system constant.
    unsafe { libc::sysconf(libc::_SC_NPROCESSORS_CONF) }.max(1) as usize
}

/// Refuses a CPU this machine does not have, naming the ones it has.
pub fn cpu_exists(cpu: usize) -> Result<(), String> {
    let n = configured_cpus();
    if cpu < n {
        Ok(())
    } else {
        Err(format!(
            "CPU {cpu} does not exist (this machine has CPUs 0-{})",
            n - 1
        ))
    }
}

/// `0,2,3` for [0, 2, 3].
pub fn cpu_list(cpus: &[usize]) -> String {
    cpus.iter()
        .map(usize::to_string)
        .collect::<Vec<_>>()
        .join(",")
}

/// Runs `f` with the calling thread at ordinary scheduling (SCHED_OTHER, nice unchanged),
/// then gives it back its real-time policy. For reaping children: wait4 of a zombie
/// releases its /proc entries and can spin in the kernel until a task on the same CPU has
/// run; a launcher at SCHED_FIFO 1 with RT throttling lifted starves that task, and spun
/// so for minutes, unkillable, until it was made ordinary by hand (three runs of three whose
/// bridge was killed, 2026-11-28).
pub fn ordinarily<T>(f: impl FnOnce() -> T) -> T {
    // SAFETY: sched_getscheduler/sched_getparam/sched_setscheduler on the calling thread
    // (pid 0) with a valid sched_param.
    let policy = unsafe { libc::sched_getscheduler(0) };
    let mut param = libc::sched_param { sched_priority: 0 };
    let realtime = matches!(policy, libc::SCHED_FIFO | libc::SCHED_RR)
        && unsafe { libc::sched_getparam(0, &mut param) } == 0;
    let ordinary = libc::sched_param { sched_priority: 0 };
    let lowered =
        realtime && unsafe { libc::sched_setscheduler(0, libc::SCHED_OTHER, &ordinary) } == 0;
    let out = f();
    if lowered && unsafe { libc::sched_setscheduler(0, policy, &param) } != 0 {
        tracing::warn!(
            priority = param.sched_priority,
            error = %std::io::Error::last_os_error(),
            "could not take back the real-time priority after reaping a child"
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Inside, the thread is ordinary; after, it has its real-time priority back. Needs the
    /// right to SCHED_FIFO (root): without it there is nothing to give up, and `f` runs as is.
    #[test]
    fn a_reaping_thread_is_ordinary_and_gets_its_priority_back() {
        let policy = || unsafe { libc::sched_getscheduler(0) };
        let fifo = libc::sched_param { sched_priority: 1 };
        // SAFETY: sched_setscheduler on the calling thread with a valid sched_param.
        if unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &fifo) } != 0 {
            assert_eq!(ordinarily(policy), policy());
            return;
        }
        assert_eq!(ordinarily(policy), libc::SCHED_OTHER);
        assert_eq!(policy(), libc::SCHED_FIFO);
        let mut p = libc::sched_param { sched_priority: 0 };
        assert_eq!(unsafe { libc::sched_getparam(0, &mut p) }, 0);
        assert_eq!(p.sched_priority, 1);
        let other = libc::sched_param { sched_priority: 0 };
        assert_eq!(
            unsafe { libc::sched_setscheduler(0, libc::SCHED_OTHER, &other) },
            0
        );
    }

    fn own_nice() -> i32 {
        // SAFETY: getpriority of the calling thread; errno is not needed (-1 is a valid
        // nice, and the values asserted here are not -1).
        unsafe { libc::getpriority(libc::PRIO_PROCESS, 0) }
    }

    #[test]
    fn a_cpu_past_the_last_is_refused_naming_the_ones_there_are() {
        let n = configured_cpus();
        assert!(cpu_exists(0).is_ok());
        assert!(cpu_exists(n - 1).is_ok());
        let e = cpu_exists(n).expect_err("one past the last");
        assert_eq!(
            e,
            format!("CPU {n} does not exist (this machine has CPUs 0-{})", n - 1)
        );
        // What the thread may use is among what the machine has.
        assert!(allowed_cpus().iter().all(|&c| c < n));
    }

    #[test]
    fn a_nice_value_is_applied_to_the_calling_thread_and_inherited_by_its_threads() {
        std::thread::spawn(|| {
            let before = own_nice();
            // Raising the nice value to the top needs no privilege.
            let applied = RtOptions {
                nice: Some(19),
                ..RtOptions::default()
            }
            .apply()
            .expect("apply");
            assert!(applied.niced);
            assert_eq!(own_nice(), 19, "was {before}");
            let child = std::thread::spawn(own_nice).join().expect("child");
            assert_eq!(child, 19, "a thread started afterwards inherits it");
            // Lowering it again without privilege is refused, quietly, and the run goes on.
            let again = RtOptions {
                nice: Some(-20),
                require: true,
                ..RtOptions::default()
            }
            .apply()
            .expect("a refused nice value is not an error");
            // SAFETY: geteuid has no preconditions.
            let root = unsafe { libc::geteuid() } == 0;
            assert_eq!(again.niced, root);
            assert_eq!(own_nice(), if root { -20 } else { 19 });
        })
        .join()
        .expect("thread");
    }
}
