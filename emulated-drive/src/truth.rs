//! The rotor's true state, which only an emulated drive knows: its model's θ, ω and phase
//! currents at every sample of a run, beside what its sensors report. A thread writes them
//! as CSV so the drive's loop never waits on the file: the loop hands rows over a bounded
//! channel and counts the rows it could not hand over.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{sync_channel, SyncSender, TrySendError};
use std::thread::JoinHandle;

/// One sample, k counted from the run's first (the first after ENABLE), and the file's
/// header: the simulated drive's, which the firmware writes too.
pub use stepdrive_drive_core::simulated::{TruthRow, TRUTH_HEADER as HEADER};

/// Rows the channel holds: 3.3 s at 20 kHz, far more than a writer falls behind.
const QUEUE: usize = 1 << 16;

pub struct TruthWriter {
    tx: Option<SyncSender<TruthRow>>,
    thread: Option<JoinHandle<std::io::Result<u64>>>,
    path: PathBuf,
    /// Rows the channel was full for.
    pub dropped: u64,
}

impl TruthWriter {
    pub fn create(path: &Path) -> std::io::Result<Self> {
        let mut out = std::io::BufWriter::new(std::fs::File::create(path)?);
        writeln!(out, "{HEADER}")?;
        let (tx, rx) = sync_channel::<TruthRow>(QUEUE);
        let thread = std::thread::Builder::new()
            .name("truth-writer".into())
            .spawn(move || {
                let mut rows = 0;
                for r in rx {
                    writeln!(out, "{r}")?;
                    rows += 1;
                }
                out.flush()?;
                Ok(rows)
            })?;
        Ok(Self {
            tx: Some(tx),
            thread: Some(thread),
            path: path.to_path_buf(),
            dropped: 0,
        })
    }

    /// Hands a row to the writer; never blocks.
    pub fn push(&mut self, row: TruthRow) {
        if let Some(tx) = &self.tx {
            if let Err(TrySendError::Full(_)) = tx.try_send(row) {
                self.dropped += 1;
            }
        }
    }

    /// Closes the file; the rows written.
    pub fn finish(mut self) -> std::io::Result<u64> {
        self.close()
    }

    fn close(&mut self) -> std::io::Result<u64> {
        self.tx = None;
        match self.thread.take() {
            Some(t) => t
                .join()
                .unwrap_or_else(|_| Err(std::io::Error::other("the truth writer panicked"))),
            None => Ok(0),
        }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for TruthWriter {
    fn drop(&mut self) {
        let _ = self.close();
    }
}

/// Reads a truth file back: the rows of its last run (k restarts at 0 when a new run
/// starts on the same drive).
pub fn read(path: &Path) -> std::io::Result<Vec<TruthRow>> {
    let text = std::fs::read_to_string(path)?;
    let mut rows: Vec<TruthRow> = Vec::new();
    let bad = |n: usize| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("{}: line {} is not a truth row", path.display(), n + 1),
        )
    };
    for (n, line) in text.lines().enumerate().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        let [k, t, th, w, a, b] = f[..] else {
            return Err(bad(n));
        };
        let num = |s: &str| s.parse::<f64>().map_err(|_| bad(n));
        let row = TruthRow {
            k: k.parse().map_err(|_| bad(n))?,
            t_s: num(t)?,
            theta_rad: num(th)?,
            omega_rad_s: num(w)?,
            i_a_a: num(a)?,
            i_b_a: num(b)?,
        };
        if rows.last().is_some_and(|l| row.k <= l.k) {
            rows.clear();
        }
        rows.push(row);
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_round_trip_and_the_last_run_is_read() {
        let path = std::env::temp_dir().join(format!("truth-{}.csv", std::process::id()));
        let mut w = TruthWriter::create(&path).expect("create");
        let row = |k: u64| TruthRow {
            k,
            t_s: k as f64 * 5e-5,
            theta_rad: -4.0001e-4 + k as f64 * 1e-7,
            omega_rad_s: 0.1,
            i_a_a: 1.0,
            i_b_a: -0.25,
        };
        for k in [0, 1, 2, 0, 1] {
            w.push(row(k));
        }
        assert_eq!(w.finish().expect("written"), 5);
        let back = read(&path).expect("read");
        assert_eq!(back, vec![row(0), row(1)]);
        let _ = std::fs::remove_file(&path);
    }
}
