//! The MCAP file, written on a thread of its own.
//!
//! The monitor's thread drains the stack's queues and must not stop to encode: JSON and
//! zstd cost ~20 µs a sample beside a 20 kHz stack on two cores, more than the share of CPU
//! the realtime loops leave an ordinary reader, so a monitor that wrote the file itself fell
//! behind its queue and lost samples of the run, not just of the file. Here the monitor
//! hands each record over a bounded queue allocated at start; the writer thread encodes and
//! compresses at ordinary priority, catching up after the run if it must. In realtime a full
//! queue drops the record from the file (counted: the file and the report say so), never
//! the sample from the run's figures; in lockstep, where nothing waits on the clock, the
//! monitor waits for room instead.

use super::recording::{
    AckRecord, CommandRecord, FaultRecord, PlanRecord, SetpointRecord, StateRecord, StatsRecord,
    StatusRecord, TruthRecord,
};
use mcap::records::{MessageHeader, Metadata};
use serde::Serialize;
use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::sync::mpsc::{self, Receiver, SyncSender, TrySendError};
use std::thread::JoinHandle;

/// Records the queue holds: ~2.5 s of the default run's messages (state, setpoint, command
/// and status at 20 kHz, plans at 2 kHz), ~27 MB.
pub const QUEUE: usize = 1 << 17;

/// One message for the file, as the monitor derived it.
#[derive(Debug, Clone, Serialize)]
#[serde(untagged)]
pub enum Record {
    State(StateRecord),
    Fault(FaultRecord),
    Setpoint(SetpointRecord),
    Command(CommandRecord),
    Plan(PlanRecord),
    Truth(TruthRecord),
    Status(StatusRecord),
    // Rare (a command's answer, a loop's report about once a second): boxed, so that the
    // queue's slots stay the size of a state.
    Ack(Box<AckRecord>),
    Stats(Box<StatsRecord>),
}

enum ToFile {
    Message {
        header: MessageHeader,
        record: Record,
    },
    Channel {
        schema: u16,
        topic: String,
        id: mpsc::Sender<Result<u16, mcap::McapError>>,
    },
    Metadata(Metadata),
}

/// Whether a record reached the writer's queue.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Queued {
    Yes,
    /// The queue was full: the record is not in the file.
    Dropped,
}

/// The writer thread and the queue to it.
pub struct FileWriter {
    to_file: Option<SyncSender<ToFile>>,
    thread: Option<JoinHandle<Result<(), mcap::McapError>>>,
    /// Wait for room rather than drop (lockstep).
    lossless: bool,
}

impl FileWriter {
    /// Starts the thread that writes `writer` (its header and schemas already written).
    pub fn start(writer: mcap::Writer<BufWriter<File>>) -> std::io::Result<Self> {
        let (to_file, from_monitor) = mpsc::sync_channel(QUEUE);
        let thread = std::thread::Builder::new()
            .name("recording".into())
            .spawn(move || {
                // A writer at the monitor's real-time priority would keep the monitor's own
                // thread (same priority, first in first out) off its CPU while it catches up.
                stepdrive_runtime::rt::ordinarily(|| write(writer, from_monitor))
            })?;
        Ok(Self {
            to_file: Some(to_file),
            thread: Some(thread),
            lossless: false,
        })
    }

    /// Whether a full queue makes [`Self::message`] wait (true) or drop the record; what
    /// it was.
    pub fn set_lossless(&mut self, lossless: bool) -> bool {
        std::mem::replace(&mut self.lossless, lossless)
    }

    /// Queues a message; an error is the writer's (it stopped on a failed write).
    pub fn message(
        &mut self,
        header: MessageHeader,
        record: Record,
    ) -> Result<Queued, mcap::McapError> {
        let msg = ToFile::Message { header, record };
        let Some(to_file) = self.to_file.as_ref() else {
            return Err(stopped());
        };
        let sent = match self.lossless {
            true => to_file.send(msg).map_err(|_| ()),
            false => match to_file.try_send(msg) {
                Ok(()) => Ok(()),
                Err(TrySendError::Full(_)) => return Ok(Queued::Dropped),
                Err(TrySendError::Disconnected(_)) => Err(()),
            },
        };
        match sent {
            Ok(()) => Ok(Queued::Yes),
            Err(()) => Err(self.stop().err().unwrap_or_else(stopped)),
        }
    }

    /// A channel for `topic`'s messages of `schema`: waits until the writer has written
    /// what came before.
    pub fn add_channel(&mut self, schema: u16, topic: &str) -> Result<u16, mcap::McapError> {
        let (id, answer) = mpsc::channel();
        let asked = self.to_file.as_ref().is_some_and(|to_file| {
            to_file
                .send(ToFile::Channel {
                    schema,
                    topic: topic.to_string(),
                    id,
                })
                .is_ok()
        });
        match asked.then(|| answer.recv().ok()).flatten() {
            Some(id) => id,
            None => Err(self.stop().err().unwrap_or_else(stopped)),
        }
    }

    /// Writes `metadata` after what came before, then the summary, and waits for the file
    /// to be complete.
    pub fn finish(&mut self, metadata: Metadata) -> Result<(), mcap::McapError> {
        if let Some(to_file) = self.to_file.as_ref() {
            // A writer that stopped already tells why at the join.
            let _ = to_file.send(ToFile::Metadata(metadata));
        }
        self.stop()
    }

    /// Closes the queue and waits for the writer: its result.
    fn stop(&mut self) -> Result<(), mcap::McapError> {
        self.to_file = None;
        match self.thread.take().map(JoinHandle::join) {
            None => Ok(()),
            Some(Ok(result)) => result,
            Some(Err(_)) => Err(mcap::McapError::Io(std::io::Error::other(
                "the recording's writer thread panicked",
            ))),
        }
    }
}

impl Drop for FileWriter {
    fn drop(&mut self) {
        if let Err(e) = self.stop() {
            tracing::error!("the recording could not be finished: {e}");
        }
    }
}

fn stopped() -> mcap::McapError {
    mcap::McapError::Io(std::io::Error::other("the recording's writer has stopped"))
}

/// The writer thread: every message in order, then the summary when the queue closes.
fn write(
    mut writer: mcap::Writer<BufWriter<File>>,
    from_monitor: Receiver<ToFile>,
) -> Result<(), mcap::McapError> {
    let mut buf = Vec::with_capacity(512);
    for msg in from_monitor {
        match msg {
            ToFile::Message { header, record } => {
                buf.clear();
                // Serialising plain numbers and text into a Vec cannot fail.
                let _ = serde_json::to_writer(&mut buf, &record);
                writer.write_to_known_channel(&header, &buf)?;
            }
            ToFile::Channel { schema, topic, id } => {
                let added = writer.add_channel(schema, &topic, "json", &BTreeMap::new());
                let failed = added.is_err();
                // The monitor waits for the answer; it is gone only if it gave up.
                let _ = id.send(added);
                if failed {
                    return Err(stopped());
                }
            }
            ToFile::Metadata(m) => writer.write_metadata(&m)?,
        }
    }
    writer.finish()?;
    Ok(())
}
