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

use anyhow::{bail, Context, Result};
use std::io::{BufRead, BufReader, Write};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use stepdrive_runtime::poll::termination_requested;
use stepdrive_runtime::rt::{RtThrottlingOff, RT_RUNTIME};

/// The launcher's end of a guard process: dropping it restores throttling.
pub struct ThrottlingLifted {
    child: Child,
    previous: i64,
}

impl ThrottlingLifted {
    /// Starts a guard that lifts RT throttling. `Ok(None)`: it was already off.
    pub fn engage() -> Result<Option<Self>> {
        let exe = std::env::current_exe().context("cannot locate the stepdrive executable")?;
        let mut child = Command::new(exe)
            .arg("rt-throttling-guard")
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
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
        match (words.next(), words.next().and_then(|v| v.parse().ok())) {
            (Some("lifted"), Some(previous)) => Ok(Some(Self { child, previous })),
            (Some("unchanged"), _) => {
                let _ = child.wait();
                Ok(None)
            }
            _ => {
                let _ = child.wait();
                bail!("cannot lift RT throttling: {}", line.trim())
            }
        }
    }

    pub fn previous(&self) -> i64 {
        self.previous
    }
}

impl Drop for ThrottlingLifted {
    fn drop(&mut self) {
        // Closing its stdin is the signal to restore.
        drop(self.child.stdin.take());
        let deadline = Instant::now() + Duration::from_secs(5);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
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
/// restore (when the guard is dropped).
pub fn guard() -> Result<()> {
    let lifted = match RtThrottlingOff::engage() {
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
