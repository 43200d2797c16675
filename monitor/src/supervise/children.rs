//! The stack's processes as children of the launcher: each is this same binary with its
//! role's sub-command, in a process group of its own (signals for the stack go to the
//! launcher), terminated and reaped on every exit path (drop guard), dying with the
//! launcher (PR_SET_PDEATHSIG). The scenario and deployment they read are files of the
//! run ([`RunFiles`]), removed as soon as every child has read them.

use anyhow::{Context, Result};
use std::io::{BufRead, BufReader};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use stepdrive_runtime::deploy::Deployment;
use stepdrive_runtime::rt::ordinarily;
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::stack::Role;
use stepdrive_shared::Scenario;

/// `child.try_wait()` that reaps at ordinary scheduling ([`ordinarily`] says why): a
/// child still running is told apart first without reaping (waitid with WNOWAIT), so the
/// launcher's real-time priority is given up only when there is a child to reap.
pub fn try_reap(child: &mut Child) -> std::io::Result<Option<ExitStatus>> {
    // SAFETY: waitid on our own child's pid into a zeroed siginfo_t.
    let exited = unsafe {
        let mut info: libc::siginfo_t = std::mem::zeroed();
        let rc = libc::waitid(
            libc::P_PID,
            child.id() as libc::id_t,
            &mut info,
            libc::WEXITED | libc::WNOHANG | libc::WNOWAIT,
        );
        // Not ours to peek at (reaped already, an error): std's wait says what it is.
        rc != 0 || info.si_pid() != 0
    };
    if exited {
        ordinarily(|| child.try_wait())
    } else {
        Ok(None)
    }
}

/// A child process that is terminated and reaped when dropped.
pub struct Supervised {
    role: Role,
    child: Child,
    last_error: Arc<Mutex<Option<String>>>,
    status: Option<ExitStatus>,
    forwarder: Option<std::thread::JoinHandle<()>>,
}

impl Supervised {
    /// Starts `role`'s process (its sub-command) with `args`.
    pub fn spawn(role: Role, args: &[String]) -> Result<Self> {
        let exe = std::env::current_exe().context("cannot locate the stepdrive executable")?;
        let command = role
            .command()
            .with_context(|| format!("the {role} has no process of its own"))?;
        let mut cmd = Command::new(exe);
        cmd.arg(command)
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped());
        if std::env::var_os("RUST_LOG").is_none() {
            cmd.env("RUST_LOG", "warn");
        }
        // Its own process group: a terminal's Ctrl-C goes to the launcher alone, which
        // brings the axes to a standstill before it stops the loops; sent to the loops too,
        // they would all stop at once and leave the motor to whatever the device does then.
        cmd.process_group(0);
        // SAFETY: prctl is async-signal-safe and touches no memory of the parent.
        unsafe {
            cmd.pre_exec(|| {
                // Die with the launcher even if it is SIGKILLed: no orphan loops.
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let mut child = cmd
            .spawn()
            .with_context(|| format!("cannot start the {} process", role.id()))?;
        let last_error = Arc::new(Mutex::new(None));
        let forwarder = child.stderr.take().map(|stderr| {
            let last_error = Arc::clone(&last_error);
            std::thread::spawn(move || {
                for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                    crate::supervise::supervisor::print_beside_progress(&format!(
                        "[{}] {line}",
                        role.id()
                    ));
                    if let Some(msg) = line.strip_prefix("error: ") {
                        if let Ok(mut slot) = last_error.lock() {
                            *slot = Some(msg.to_string());
                        }
                    }
                }
            })
        });
        tracing::debug!(role = %role, pid = child.id(), "started");
        Ok(Self {
            role,
            child,
            last_error,
            status: None,
            forwarder,
        })
    }

    pub fn poll_exit(&mut self) -> Result<Option<ExitStatus>> {
        if self.status.is_none() {
            self.status = try_reap(&mut self.child)
                .with_context(|| format!("cannot query the {} process", self.role.id()))?;
        }
        Ok(self.status)
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    pub fn role(&self) -> Role {
        self.role
    }

    pub fn signal(&self, sig: libc::c_int) {
        if self.status.is_none() {
            // SAFETY: plain kill(2) on our own, not yet reaped child.
            unsafe { libc::kill(self.child.id() as libc::pid_t, sig) };
        }
    }

    /// Waits up to `timeout` for a voluntary exit, then SIGTERM, then SIGKILL.
    pub fn finish(&mut self, timeout: Duration) -> ExitStatus {
        let exited = |c: &mut Child, within: Duration| -> Option<ExitStatus> {
            let deadline = Instant::now() + within;
            loop {
                match try_reap(c) {
                    Ok(Some(status)) => return Some(status),
                    Ok(None) if Instant::now() < deadline => {
                        std::thread::sleep(Duration::from_millis(2))
                    }
                    _ => return None,
                }
            }
        };
        if self.status.is_none() {
            self.status = exited(&mut self.child, timeout).or_else(|| {
                tracing::warn!(role = %self.role, "did not exit in time; sending SIGTERM");
                self.signal(libc::SIGTERM);
                exited(&mut self.child, Duration::from_secs(1)).or_else(|| {
                    let _ = self.child.kill();
                    ordinarily(|| self.child.wait()).ok()
                })
            });
        }
        if let Some(f) = self.forwarder.take() {
            let _ = f.join();
        }
        // Unknown only if the child could not be waited for: report failure, never guess success.
        self.status.unwrap_or_else(|| {
            use std::os::unix::process::ExitStatusExt;
            ExitStatus::from_raw(1 << 8)
        })
    }

    pub fn describe_failure(&self, status: ExitStatus) -> String {
        let detail = self
            .last_error
            .lock()
            .ok()
            .and_then(|e| e.clone())
            .unwrap_or_else(|| "no error message (see its log above)".to_string());
        format!(
            "the {} process exited with {status}: {detail}",
            self.role.id()
        )
    }
}

impl Drop for Supervised {
    fn drop(&mut self) {
        if self.status.is_none() {
            self.signal(libc::SIGTERM);
            let deadline = Instant::now() + Duration::from_secs(2);
            while Instant::now() < deadline {
                if let Ok(Some(_)) = try_reap(&mut self.child) {
                    return;
                }
                std::thread::sleep(Duration::from_millis(5));
            }
            let _ = self.child.kill();
            let _ = ordinarily(|| self.child.wait());
        }
    }
}

/// The scenario and deployment as the children read them: a private directory, removed as
/// soon as every child has read it (when the first sample arrives) and when dropped. A
/// launcher killed before then leaves it; the next launch removes such leftovers.
pub struct RunFiles {
    dir: PathBuf,
    /// The lockstep doorbells' page of the instance goes with the run.
    instance: String,
}

/// The prefix of a run's directory: `stepdrive-<launcher pid>-<instance>`.
const RUN_DIR_PREFIX: &str = "stepdrive-";

/// The emulated drive's truth file in the temporary directory: this, the launcher's pid, the
/// instance, `.csv`.
pub const TRUTH_PREFIX: &str = "stepdrive-truth-";

impl RunFiles {
    pub fn write(s: &Scenario, d: &Deployment, instance: &str) -> Result<Self> {
        Self::remove_leftovers();
        let dir =
            std::env::temp_dir().join(format!("{RUN_DIR_PREFIX}{}-{instance}", std::process::id()));
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create {}", dir.display()))?;
        let files = Self {
            dir,
            instance: instance.to_string(),
        };
        let write = |path: PathBuf, text: String| {
            std::fs::write(&path, text).with_context(|| format!("cannot write {}", path.display()))
        };
        write(files.scenario(), s.to_toml_string()?)?;
        write(files.deployment(), d.to_toml_string())?;
        Ok(files)
    }

    pub fn scenario(&self) -> PathBuf {
        self.dir.join("scenario.toml")
    }

    /// What every process of the stack is started with: mode, instance and these files.
    pub fn process_args(&self, mode: Mode, instance: &str) -> [String; 8] {
        [
            "--mode".to_string(),
            mode.as_str().to_string(),
            "--instance".to_string(),
            instance.to_string(),
            "--scenario".to_string(),
            path_arg(&self.scenario()),
            "--deploy".to_string(),
            path_arg(&self.deployment()),
        ]
    }

    pub fn deployment(&self) -> PathBuf {
        self.dir.join("deploy.toml")
    }

    /// Every child has read its files: they can go.
    pub fn remove(&self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }

    /// Removes the directories of launchers that no longer run.
    fn remove_leftovers() {
        let Ok(entries) = std::fs::read_dir(std::env::temp_dir()) else {
            return;
        };
        let pid_after = |name: &str, prefix: &str| {
            name.strip_prefix(prefix)
                .and_then(|rest| rest.split('-').next())
                .and_then(|pid| pid.parse::<u32>().ok())
        };
        let dead = |pid: u32| !Path::new(&format!("/proc/{pid}")).exists();
        for entry in entries.flatten() {
            let name = entry.file_name();
            let Some(name) = name.to_str() else { continue };
            if let Some(pid) = pid_after(name, RUN_DIR_PREFIX) {
                if dead(pid) && entry.path().join("deploy.toml").exists() {
                    let _ = std::fs::remove_dir_all(entry.path());
                }
            } else if let Some(pid) = pid_after(name, TRUTH_PREFIX) {
                // An emulated drive's truth file, left by a launcher that was killed.
                if dead(pid) && name.ends_with(".csv") {
                    let _ = std::fs::remove_file(entry.path());
                }
            }
        }
        stepdrive_runtime::doorbell::remove_stale(&stepdrive_runtime::ipc::live_instances());
    }
}

impl Drop for RunFiles {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
        stepdrive_runtime::doorbell::remove(&self.instance);
    }
}

/// An emulated drive on `addr` for a run's files. It stands for separate hardware: it
/// keeps the plant's CPU; the bridge shares the current loop's, one priority below it (see
/// docs/hardware.md). With `truth`, it writes the true rotor state there.
pub fn spawn_emulated_drive(
    addr: &str,
    files: &RunFiles,
    truth: Option<&Path>,
) -> Result<Supervised> {
    let mut args = vec![
        "--listen".to_string(),
        addr.to_string(),
        "--scenario".to_string(),
        path_arg(&files.scenario()),
        "--deploy".to_string(),
        path_arg(&files.deployment()),
    ];
    if let Some(p) = truth {
        args.extend(["--truth".to_string(), path_arg(p)]);
    }
    Supervised::spawn(Role::EmulatedDrive, &args)
}

pub fn path_arg(p: &Path) -> String {
    p.display().to_string()
}

/// `n` distinct loopback UDP addresses no one is using right now (the probes are held
/// until all are found, so no two are the same), for a multi-axis emulated drive.
pub fn free_loopback_ports(n: usize) -> Result<Vec<std::net::SocketAddr>> {
    let probes = (0..n)
        .map(|_| std::net::UdpSocket::bind("127.0.0.1:0").context("cannot find a free UDP port"))
        .collect::<Result<Vec<_>>>()?;
    probes.iter().map(|p| Ok(p.local_addr()?)).collect()
}
