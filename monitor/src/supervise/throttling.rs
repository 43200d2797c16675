//! RT throttling lifted for a run, and put back on every exit path. With the kernel's
//! default (`sched_rt_runtime_us = 950000`) a SCHED_FIFO loop loses its CPU for up to 50 ms
//! a second whenever an ordinary task wants it, which is five times the plant's watchdog:
//! a default realtime run would lose the motor. So a run with real-time priorities lifts it
//! (root only) and restores it when it ends.
//!
//! "Every exit path" includes a SIGKILL of the launcher, which runs no code. So the value is
//! held by a small guard process (`stepdrive rt-throttling-guard`): it lifts throttling,
//! says so on stdout, and restores the previous value when its stdin closes — which the
//! kernel does when the launcher exits, however it exits — or on SIGINT/SIGTERM.

use super::children::try_reap;
use anyhow::{bail, Context, Result};
use std::io::{BufRead, BufReader, Write};
use std::os::unix::process::CommandExt;
use std::process::{Child, Command, ExitStatus, Stdio};
use std::time::{Duration, Instant};
use stepdrive_runtime::poll::termination_requested;
use stepdrive_runtime::rt::ordinarily;
use stepdrive_runtime::rt::{RtThrottlingOff, RT_RUNTIME};

/// The launcher's end of a guard process: dropping it restores throttling.
pub struct ThrottlingLifted {
    child: Child,
    previous: i64,
}

impl ThrottlingLifted {
    /// Starts a guard that lifts RT throttling. `Ok(None)`: it was already off.
    pub fn engage() -> Result<Option<Self>> {
        let (child, said) = Self::spawn(None)?;
        match said {
            Said::Lifted(previous) => Ok(Some(Self { child, previous })),
            Said::Unchanged => Ok(None),
            Said::Refused(why) => bail!("cannot lift RT throttling: {why}"),
        }
    }

    /// A guard process; with `restore`, one that restores that value (it takes over from
    /// one that died) instead of the one it finds.
    fn spawn(restore: Option<i64>) -> Result<(Child, Said)> {
        let exe = std::env::current_exe().context("cannot locate the stepdrive executable")?;
        let mut cmd = Command::new(exe);
        cmd.arg("rt-throttling-guard");
        if let Some(v) = restore {
            cmd.args(["--restore", &v.to_string()]);
        }
        let mut child = cmd
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            // Its own process group: a terminal's Ctrl-C goes to the launcher, which stops
            // the axes before throttling is restored, not to the guard at the same time.
            .process_group(0)
            .spawn()
            .context("cannot start the RT throttling guard")?;
        let line = child
            .stdout
            .take()
            .map(|out| {
                let mut line = String::new();
                BufReader::new(out).read_line(&mut line).map(|_| line)
            })
            .transpose()
            .context("the RT throttling guard said nothing")?
            .unwrap_or_default();
        let mut words = line.split_whitespace();
        let said = match (words.next(), words.next().and_then(|v| v.parse().ok())) {
            (Some("lifted"), Some(previous)) => Said::Lifted(previous),
            (Some("unchanged"), _) => Said::Unchanged,
            _ => Said::Refused(line.trim().to_string()),
        };
        if !matches!(said, Said::Lifted(_)) {
            let _ = ordinarily(|| child.wait());
        }
        Ok((child, said))
    }

    pub fn previous(&self) -> i64 {
        self.previous
    }

    /// The guard's exit, if it has exited (it never does by itself while the launcher
    /// lives: its death is news).
    pub fn poll_exit(&mut self) -> Option<ExitStatus> {
        try_reap(&mut self.child).ok().flatten()
    }

    /// A guard in the place of one that died, holding the value that one saved: throttling
    /// stays lifted for the stack, and is restored however the launcher ends.
    pub fn restart(&mut self) -> Result<()> {
        let (child, said) = Self::spawn(Some(self.previous))?;
        match said {
            Said::Lifted(_) => {
                self.child = child;
                Ok(())
            }
            Said::Unchanged => bail!("the new guard found nothing to hold"),
            Said::Refused(why) => bail!("the new guard refused: {why}"),
        }
    }

    /// Puts the saved value back now (the guard is dead and no other can be started).
    pub fn restore_now(&self) {
        self.restore_if_left_lifted();
    }
}

/// What a guard said on its first line.
enum Said {
    Lifted(i64),
    Unchanged,
    Refused(String),
}

impl Drop for ThrottlingLifted {
    fn drop(&mut self) {
        // Closing its stdin is the signal to restore.
        drop(self.child.stdin.take());
        let deadline = Instant::now() + Duration::from_secs(5);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = try_reap(&mut self.child) {
                self.restore_if_left_lifted();
                return;
            }
            std::thread::sleep(Duration::from_millis(5));
        }
        tracing::error!(
            "the RT throttling guard did not exit: restore it with `sysctl kernel.sched_rt_runtime_us={}`",
            self.previous
        );
    }
}

impl ThrottlingLifted {
    /// A guard that was killed restored nothing: the launcher puts the value back itself,
    /// and says so.
    fn restore_if_left_lifted(&self) {
        let now = std::fs::read_to_string(RT_RUNTIME)
            .ok()
            .and_then(|t| t.trim().parse::<i64>().ok());
        if now == Some(self.previous) {
            return;
        }
        match std::fs::write(RT_RUNTIME, format!("{}\n", self.previous)) {
            Ok(()) => tracing::warn!(
                previous = self.previous,
                "the RT throttling guard had died without restoring throttling: restored here"
            ),
            Err(e) => tracing::error!(
                "the RT throttling guard died and throttling stays lifted ({RT_RUNTIME}: {e}): \
                 restore it with `sysctl kernel.sched_rt_runtime_us={}`",
                self.previous
            ),
        }
    }
}

/// The guard process's body: lift, report, hold until stdin closes or a termination signal,
/// restore (when the guard is dropped). With `restore`, it takes over from a guard that
/// died: it lifts throttling whatever it is now and restores that value.
pub fn guard(restore: Option<i64>) -> Result<()> {
    let engaged = match restore {
        Some(previous) => RtThrottlingOff::hold(previous).map(Some),
        None => RtThrottlingOff::engage(),
    };
    let lifted = match engaged {
        Ok(Some(g)) => g,
        Ok(None) => {
            println!("unchanged -1");
            return Ok(());
        }
        Err(e) => {
            println!("refused {}", e.describe());
            return Ok(());
        }
    };
    println!("lifted {}", lifted.previous());
    std::io::stdout().flush().ok();
    let stdin = libc::STDIN_FILENO;
    loop {
        if termination_requested() {
            break;
        }
        let mut pfd = libc::pollfd {
            fd: stdin,
            events: libc::POLLIN,
            revents: 0,
        };
        // SAFETY: one valid pollfd.
        let ready = unsafe { libc::poll(&mut pfd, 1, 100) };
        if ready > 0 {
            // Data or end of file: only the end matters (nothing is ever written to it).
            let mut buf = [0u8; 64];
            // SAFETY: reading into a valid buffer from our own stdin.
            let n = unsafe { libc::read(stdin, buf.as_mut_ptr().cast(), buf.len()) };
            if n <= 0 {
                break;
            }
        }
    }
    drop(lifted);
    tracing::info!("RT throttling restored ({RT_RUNTIME})");
    Ok(())
}
