//! Processes beside a stack that are not its loops but must not be lost silently: the
//! gateway `serve --gateway` starts, and the RT-throttling guard. The supervisor watches them
//! with the loops: a death is logged at once and answered ([`Helpers`]), and each is
//! restarted at most [`MAX_RESTARTS`] times.

use super::children::try_reap;
use crate::supervise::throttling::ThrottlingLifted;
use anyhow::{Context, Result};
use std::os::unix::process::CommandExt;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};
use stepdrive_runtime::rt::ordinarily;

/// Restarts of one helper in a launcher's life; its next death stops the stack. A helper
/// that keeps dying (a crash its input triggers, a port taken) is not restarted for ever.
pub const MAX_RESTARTS: u32 = 3;

/// A helper process: this binary with `args`, in its own process group (a terminal's
/// Ctrl-C goes to the launcher, which stops the axes first), dying with the launcher.
pub struct Helper {
    name: &'static str,
    args: Vec<String>,
    child: Child,
    restarts: u32,
}

impl Helper {
    pub fn spawn(name: &'static str, args: Vec<String>) -> Result<Self> {
        let child = Self::start(name, &args)?;
        Ok(Self {
            name,
            args,
            child,
            restarts: 0,
        })
    }

    fn start(name: &str, args: &[String]) -> Result<Child> {
        let exe = std::env::current_exe().context("cannot locate the stepdrive executable")?;
        let mut cmd = Command::new(exe);
        cmd.args(args).stdin(Stdio::null()).process_group(0);
        // SAFETY: prctl is async-signal-safe and touches no memory of the parent.
        unsafe {
            cmd.pre_exec(|| {
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        cmd.spawn()
            .with_context(|| format!("cannot start the {name}"))
    }

    pub fn name(&self) -> &'static str {
        self.name
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Its exit, if it has exited.
    pub fn poll_exit(&mut self) -> Result<Option<ExitStatus>> {
        try_reap(&mut self.child).with_context(|| format!("cannot query the {}", self.name))
    }

    /// Starts it again with the same arguments; the restarts so far.
    pub fn restart(&mut self) -> Result<u32> {
        self.child = Self::start(self.name, &self.args)?;
        self.restarts += 1;
        Ok(self.restarts)
    }

    pub fn restarts(&self) -> u32 {
        self.restarts
    }

    /// SIGTERM, then SIGKILL if it has not exited within 5 s.
    pub fn stop(&mut self) -> Option<ExitStatus> {
        if let Ok(Some(status)) = try_reap(&mut self.child) {
            return Some(status);
        }
        // SAFETY: signalling our own, not yet reaped child by its pid.
        unsafe { libc::kill(self.child.id() as libc::pid_t, libc::SIGTERM) };
        let deadline = Instant::now() + Duration::from_secs(5);
        while Instant::now() < deadline {
            if let Ok(Some(status)) = try_reap(&mut self.child) {
                return Some(status);
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        let _ = self.child.kill();
        ordinarily(|| self.child.wait()).ok()
    }
}

impl Drop for Helper {
    fn drop(&mut self) {
        self.stop();
    }
}

/// The helpers of one launcher. Dropped after the stack, in this order: the gateway is
/// stopped, then RT throttling restored (the guard's own drop), when no loop runs any more.
#[derive(Default)]
pub struct Helpers {
    pub gateway: Option<Helper>,
    pub guard: Option<ThrottlingLifted>,
    /// Restarts of the guard so far.
    pub guard_restarts: u32,
    /// What happened to them, for the launcher's last line ("the gateway was restarted
    /// after it was killed by signal 9").
    pub events: Vec<String>,
}

impl Helpers {
    /// The gateway's death, if it has died since the last look.
    pub fn gateway_died(&mut self) -> Result<Option<ExitStatus>> {
        match self.gateway.as_mut() {
            Some(g) => g.poll_exit(),
            None => Ok(None),
        }
    }

    /// The guard's death, if it has died since the last look.
    pub fn guard_died(&mut self) -> Option<ExitStatus> {
        self.guard.as_mut().and_then(ThrottlingLifted::poll_exit)
    }
}
