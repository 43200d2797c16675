//! Recording a run to MCAP: what the motor did, sample by sample, in a file that Foxglove,
//! Lichtblick and PlotJuggler open as is.
//!
//! It runs in the monitor, outside every loop: the monitor already drains the state stream
//! for its metrics, and records each sample it sees; [`super::file`] writes them on a thread
//! of its own. A sample it never saw (it is the one reader allowed to fall behind) is
//! counted, and the file says how many.
//!
//! Layout: one channel per method and kind, `/<method>/state` (every sample, SI units, with
//! the reference and the derived d/q currents and torque), `/<method>/stats` (each loop's
//! counters as they are published) and `/<method>/fault` (each change of the fault bits);
//! JSON messages, each channel with its JSON Schema. Times are **simulated** time in ns
//! (log time = publish time, so PlotJuggler, which plots by publish time, overlays the
//! methods from t = 0). Metadata: `scenario` (the scenario as TOML, so the file explains
//! itself) and, when the file is finished, `recording` (samples written and lost per
//! method).
//!
//! A multi-axis stack's axes each have their channels: axis 0 the names above, axis n
//! (n ≥ 1) the same under `/<method>/axis/<n>/` (`/proposed/axis/2/state`, ...). The
//! loops' statistics are per process, on axis 0's `stats`. [`Recorded::axes`] reads the
//! other axes back, each as a recording of its own.

use super::file::{FileWriter, Queued, Record};
use super::live::{Every, LiveView};
use crate::report::setpoints::SetpointHistory;
use mcap::records::{MessageHeader, Metadata};
use serde::Serialize;
use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use stepdrive_emulated_drive::truth::TruthRow;
use stepdrive_shared::axis::{AxisAck, AxisState, AxisStatus, Refusal, RequestKind};
use stepdrive_shared::frames::dq_currents;
use stepdrive_shared::messages::{DriveCommand, DrivePlan, DriveState, TorqueSetpoint};
use stepdrive_shared::stats::StatsReport;
use stepdrive_shared::trajectory::{Reference, Trapezoid};
use stepdrive_shared::{Method, Scenario};

#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    #[error("cannot create the recording {path}")]
    Create {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A file the export writes (a CSV file, or its directory).
    #[error("cannot write {path}")]
    Export {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot write the recording {path}")]
    Write {
        path: PathBuf,
        #[source]
        source: mcap::McapError,
    },
    #[error("cannot read the recording {path}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path} is not a readable MCAP recording")]
    Parse {
        path: PathBuf,
        #[source]
        source: mcap::McapError,
    },
    #[error("{path}: message on {topic} is not a stepdrive record")]
    Message {
        path: PathBuf,
        topic: String,
        #[source]
        source: serde_json::Error,
    },
}

/// A number read back: JSON has no NaN, so serde_json writes one as `null` (a refused
/// `move --to nan` is recorded with its target, a plan shorter than four entries with NaN
/// for the rest, a drive may report a non-finite reading), and this reads it back as NaN.
/// Every number of every record takes it: one such value made a whole recording unreadable.
fn nan_from_null<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    <Option<f64> as serde::Deserialize>::deserialize(d).map(|x| x.unwrap_or(f64::NAN))
}

/// One state sample as recorded (SI units; angles in rad, currents in A, volts in V).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
pub struct StateRecord {
    #[serde(deserialize_with = "nan_from_null")]
    pub t: f64,
    pub seq: u64,
    #[serde(deserialize_with = "nan_from_null")]
    pub theta: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub theta_d: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub error: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub omega: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub omega_d: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub i_a: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub i_b: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub i_d: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub i_q: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub v_a: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub v_b: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub bus: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub torque: f64,
    pub flags: u32,
    pub fault: u32,
}

/// The fields of [`StateRecord`], in order, with their units (the schema and CSV header).
pub const STATE_FIELDS: [(&str, &str); 17] = [
    ("t", "s"),
    ("seq", ""),
    ("theta", "rad"),
    ("theta_d", "rad"),
    ("error", "rad"),
    ("omega", "rad/s"),
    ("omega_d", "rad/s"),
    ("i_a", "A"),
    ("i_b", "A"),
    ("i_d", "A"),
    ("i_q", "A"),
    ("v_a", "V"),
    ("v_b", "V"),
    ("bus", "V"),
    ("torque", "N·m"),
    ("flags", ""),
    ("fault", ""),
];

#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct StatsRecord {
    #[serde(deserialize_with = "nan_from_null")]
    pub t: f64,
    pub role: String,
    pub cycles: u64,
    pub misses: u64,
    pub planned: u64,
    pub overruns: u64,
    pub lost: u64,
    pub longest_miss_run: u64,
}

const STATS_FIELDS: [&str; 8] = [
    "t",
    "role",
    "cycles",
    "misses",
    "planned",
    "overruns",
    "lost",
    "longest_miss_run",
];

#[derive(Debug, Clone, Serialize, serde::Deserialize)]
pub struct FaultRecord {
    #[serde(deserialize_with = "nan_from_null")]
    pub t: f64,
    pub seq: u64,
    pub fault: u32,
}

const FAULT_FIELDS: [&str; 3] = ["t", "seq", "fault"];

/// A position-loop setpoint as recorded: the torque (12) asked for and the load it used.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
pub struct SetpointRecord {
    #[serde(deserialize_with = "nan_from_null")]
    pub t: f64,
    pub seq: u64,
    #[serde(deserialize_with = "nan_from_null")]
    pub theta_d: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub omega_d: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub alpha_d: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub torque: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub load_estimate: f64,
}

const SETPOINT_FIELDS: [&str; 7] = [
    "t",
    "seq",
    "theta_d",
    "omega_d",
    "alpha_d",
    "torque",
    "load_estimate",
];

/// A current-loop command as recorded: the voltages it asked for and its current
/// references (what the phase-current plot draws the currents against).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
pub struct CommandRecord {
    #[serde(deserialize_with = "nan_from_null")]
    pub t: f64,
    /// The instant the references are for: the first sample the voltage reaches.
    #[serde(deserialize_with = "nan_from_null")]
    pub t_ref: f64,
    pub seq: u64,
    pub answers_seq: u64,
    #[serde(deserialize_with = "nan_from_null")]
    pub v_a: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub v_b: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub i_a_ref: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub i_b_ref: f64,
}

const COMMAND_FIELDS: [&str; 8] = [
    "t",
    "t_ref",
    "seq",
    "answers_seq",
    "v_a",
    "v_b",
    "i_a_ref",
    "i_b_ref",
];

/// A voltage plan as recorded: its first entries (entry j is for the period that ends at
/// sample answers_seq + compute delay + 2 + j).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
pub struct PlanRecord {
    #[serde(deserialize_with = "nan_from_null")]
    pub t: f64,
    pub command_seq: u64,
    pub answers_seq: u64,
    pub len: u32,
    #[serde(deserialize_with = "nan_from_null")]
    pub v_a_0: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub v_b_0: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub v_a_1: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub v_b_1: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub v_a_2: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub v_b_2: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub v_a_3: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub v_b_3: f64,
}

const PLAN_FIELDS: [&str; 12] = [
    "t",
    "command_seq",
    "answers_seq",
    "len",
    "v_a_0",
    "v_b_0",
    "v_a_1",
    "v_b_1",
    "v_a_2",
    "v_b_2",
    "v_a_3",
    "v_b_3",
];

/// The emulated drive's true rotor state, beside the measured one.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, serde::Deserialize)]
pub struct TruthRecord {
    #[serde(deserialize_with = "nan_from_null")]
    pub t: f64,
    pub seq: u64,
    #[serde(deserialize_with = "nan_from_null")]
    pub theta: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub error: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub omega: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub i_a: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub i_b: f64,
}

const TRUTH_FIELDS: [&str; 7] = ["t", "seq", "theta", "error", "omega", "i_a", "i_b"];

/// A JSON Schema of an object whose fields are all numbers (but `role`).
/// Fields recorded as text (the rest are numbers).
const STRING_FIELDS: [&str; 6] = ["role", "kind", "refusal", "text", "state", "mode"];

/// An axis command's answer as recorded: the command, and whether it was taken.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
pub struct AckRecord {
    #[serde(deserialize_with = "nan_from_null")]
    pub t: f64,
    pub tick: u64,
    pub kind: String,
    pub seq: u64,
    pub client: u32,
    /// The command's as sent (NaN when it was, and refused for it).
    #[serde(deserialize_with = "nan_from_null")]
    pub target: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub velocity: f64,
    pub flags: u32,
    /// `taken`, or why not.
    pub refusal: String,
    pub text: String,
    /// The axis's state after it.
    pub state: String,
}

const ACK_FIELDS: [&str; 11] = [
    "t", "tick", "kind", "seq", "client", "target", "velocity", "flags", "refusal", "text", "state",
];

/// The axis's status as recorded, every tick.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, serde::Deserialize)]
pub struct StatusRecord {
    #[serde(deserialize_with = "nan_from_null")]
    pub t: f64,
    pub tick: u64,
    /// The CiA 402 state (numbered as `stepdrive_shared::axis::AxisState`) and the status
    /// word.
    pub state_code: u32,
    pub statusword: u32,
    pub mode_code: u32,
    #[serde(deserialize_with = "nan_from_null")]
    pub theta: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub omega: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub torque: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub following_error: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub theta_d: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub omega_d: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub alpha_d: f64,
    #[serde(deserialize_with = "nan_from_null")]
    pub target: f64,
    pub fault: u32,
    pub warning: u32,
    pub move_id: u64,
    pub last_seq: u64,
    /// The stream time played at this tick (absent when no stream plays, and in
    /// recordings made before it was recorded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stream_time: Option<f64>,
}

const STATUS_FIELDS: [&str; 18] = [
    "t",
    "tick",
    "state_code",
    "statusword",
    "mode_code",
    "theta",
    "omega",
    "torque",
    "following_error",
    "theta_d",
    "omega_d",
    "alpha_d",
    "target",
    "fault",
    "warning",
    "move_id",
    "last_seq",
    "stream_time",
];

/// Every message type's name and JSON Schema, in the order of [`Recording`]'s `schemas`.
fn schema_texts() -> [(&'static str, String); 9] {
    let named = |name: &'static str, fields: &[&str]| (name, schema(name, fields));
    [
        named("stepdrive.State", &STATE_FIELDS.map(|f| f.0)),
        named("stepdrive.Stats", &STATS_FIELDS),
        named("stepdrive.Fault", &FAULT_FIELDS),
        named("stepdrive.Setpoint", &SETPOINT_FIELDS),
        named("stepdrive.Truth", &TRUTH_FIELDS),
        named("stepdrive.Command", &COMMAND_FIELDS),
        named("stepdrive.Plan", &PLAN_FIELDS),
        named("stepdrive.AxisAck", &ACK_FIELDS),
        named("stepdrive.AxisStatus", &STATUS_FIELDS),
    ]
}

fn schema(title: &str, fields: &[&str]) -> String {
    let props: Vec<String> = fields
        .iter()
        .map(|f| {
            let ty = if STRING_FIELDS.contains(f) {
                "string"
            } else {
                "number"
            };
            format!("\"{f}\":{{\"type\":\"{ty}\"}}")
        })
        .collect();
    format!(
        "{{\"title\":\"{title}\",\"type\":\"object\",\"properties\":{{{}}},\"required\":[{}]}}",
        props.join(","),
        fields
            .iter()
            .map(|f| format!("\"{f}\""))
            .collect::<Vec<_>>()
            .join(",")
    )
}

struct Channels {
    method: Method,
    axis: u32,
    state: u16,
    stats: u16,
    fault: u16,
    setpoint: u16,
    command: u16,
    plan: u16,
    ack: u16,
    status: u16,
    /// Made when the first truth arrives (only an emulated drive has one).
    truth: Option<u16>,
    written: u64,
    lost: u64,
    /// Messages of any kind the writer's full queue dropped.
    dropped: u64,
    last_fault: u32,
    last_t: f64,
}

impl Channels {
    fn has_channel(&self, id: u16) -> bool {
        [
            self.state,
            self.stats,
            self.fault,
            self.setpoint,
            self.command,
            self.plan,
            self.ack,
            self.status,
        ]
        .contains(&id)
            || self.truth == Some(id)
    }
}

/// An MCAP file being written. Finished (summary and indexes written) by [`Self::finish`],
/// or when dropped on any other path.
pub struct Recording {
    /// The file's writer thread (none once finished, or for a live view alone).
    writer: Option<FileWriter>,
    /// The Foxglove live view the same messages go to, decimated.
    live: Option<LiveView>,
    /// The channel ids of a live view without a file.
    next_channel: u16,
    path: PathBuf,
    schemas: [u16; 9],
    /// Every run's channels, a set per axis; the current run's are the last `tracks.len()`.
    channels: Vec<Channels>,
    /// Each axis's reference and motor.
    tracks: Vec<Track>,
    sequence: u32,
    buf: Vec<u8>,
}

/// What the recording derives an axis's records with.
struct Track {
    /// θ_d at a sample's time: the scenario's profile when the axis runs it, else the
    /// last setpoint carried on along its ω_d and α_d.
    trajectory: Option<Trapezoid>,
    setpoints: SetpointHistory,
    n_r: f64,
    k_m: f64,
    /// (compute delay + 1) periods: how far ahead of its sample a command's references are.
    ref_lead_s: f64,
    period_s: f64,
}

impl Track {
    fn of(s: &Scenario) -> Self {
        Self {
            trajectory: s.runs_profile().then(|| Trapezoid::new(&s.trajectory)),
            setpoints: SetpointHistory::for_scenario(s),
            n_r: f64::from(s.motor.rotor_teeth),
            k_m: s.plant_motor().torque_constant_nm_per_a,
            ref_lead_s: f64::from(s.rates.compute_delay_periods + 1) * s.sample_period_s(),
            period_s: s.sample_period_s(),
        }
    }

    /// The setpoint at time `t` (see `trajectory`): the last one taken at or before `t`
    /// carried on to `t`; before the oldest kept, the rotor's `theta` at rest.
    fn reference_at(&self, t: f64, theta: f64) -> Reference {
        if let Some(profile) = &self.trajectory {
            return profile.at(t);
        }
        self.setpoints.at(t).unwrap_or(Reference {
            theta,
            omega: 0.0,
            alpha: 0.0,
        })
    }
}

/// zstd's level for recordings: on a recording of the default run, level 1 compresses 3.9×
/// in 0.49 s of CPU per 140 MB, level 3 4.4× in 0.82 s (the `zstd` tool on the whole file);
/// the monitor shares two cores with the realtime loops, so the cheaper level.
const ZSTD_LEVEL: u32 = 1;

/// What a failed write of the recording at `path` is.
fn write_error(path: &Path) -> impl Fn(mcap::McapError) -> RecordError + Copy + '_ {
    move |source| RecordError::Write {
        path: path.to_path_buf(),
        source,
    }
}

/// Axis 0's channels keep the one-axis names; axis n's are under `axis/<n>/`.
fn topic(method: Method, axis: u32, kind: &str) -> String {
    match axis {
        0 => format!("/{}/{kind}", method.as_str()),
        n => format!("/{}/axis/{n}/{kind}", method.as_str()),
    }
}

/// How a recording's chunks are written.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Chunks {
    /// zstd level 1, on the recording's one writer thread: 3.8× smaller than the messages
    /// (a minute of the default run's topics, 840 MB, becomes 221 MB; docs/recording.md has
    /// the figures); zstd's own worker threads cost more CPU than they save.
    #[default]
    Zstd,
    /// As the messages are: for tools that read MCAP but not its compression.
    Uncompressed,
}

impl Recording {
    /// Creates `path` (refusing at once if it cannot be written) with the scenario as
    /// metadata, its chunks written as `chunks` says.
    pub fn create(path: &Path, s: &Scenario, chunks: Chunks) -> Result<Self, RecordError> {
        let file = File::create(path).map_err(|source| RecordError::Create {
            path: path.to_path_buf(),
            source,
        })?;
        let wrap = write_error(path);
        let compression = match chunks {
            Chunks::Zstd => Some(mcap::Compression::Zstd),
            Chunks::Uncompressed => None,
        };
        let mut writer = mcap::WriteOptions::new()
            .compression(compression)
            .compression_level(ZSTD_LEVEL)
            .compression_threads(0)
            .profile("")
            .create(BufWriter::new(file))
            .map_err(wrap)?;
        let mut schemas = [0u16; 9];
        for (id, (name, text)) in schemas.iter_mut().zip(schema_texts()) {
            *id = writer
                .add_schema(name, "jsonschema", text.as_bytes())
                .map_err(wrap)?;
        }
        let toml = s.to_toml_string().unwrap_or_default();
        writer
            .write_metadata(&Metadata {
                name: "scenario".into(),
                metadata: BTreeMap::from([("toml".to_string(), toml)]),
            })
            .map_err(wrap)?;
        let writer = FileWriter::start(writer).map_err(|source| RecordError::Create {
            path: path.to_path_buf(),
            source,
        })?;
        Ok(Self::new(Some(writer), path, schemas, s))
    }

    /// No file: the messages go to `live` alone (decimated there; a message the view does
    /// not take is not even encoded).
    pub fn live_only(live: LiveView, s: &Scenario) -> Self {
        Self::new(None, Path::new(""), [0; 9], s).with_live(live)
    }

    /// The same messages to `live` too.
    pub fn with_live(mut self, live: LiveView) -> Self {
        self.live = Some(live);
        self
    }

    fn new(writer: Option<FileWriter>, path: &Path, schemas: [u16; 9], s: &Scenario) -> Self {
        Self {
            writer,
            live: None,
            next_channel: 0,
            path: path.to_path_buf(),
            schemas,
            channels: Vec::new(),
            tracks: (0..s.axis_count())
                .map(|n| Track::of(s.for_axis(n).unwrap_or(s)))
                .collect(),
            sequence: 0,
            buf: Vec::with_capacity(512),
        }
    }

    /// Whether a full queue to the file's writer makes the monitor wait (lockstep: nothing
    /// waits on the clock) or drops the message from the file (the default: the monitor's
    /// draining of the stack comes first).
    pub fn set_lossless(&mut self, lossless: bool) {
        if let Some(w) = self.writer.as_mut() {
            w.set_lossless(lossless);
        }
    }

    /// Messages the file lacks because its writer fell behind, over every run so far.
    pub fn dropped(&self) -> u64 {
        self.channels.iter().map(|c| c.dropped).sum()
    }

    /// Whether it writes a file (not a live view alone).
    pub fn has_file(&self) -> bool {
        self.writer.is_some()
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The channels of `method`'s run, every axis's; what follows is recorded on them.
    pub fn begin(&mut self, method: Method) -> Result<(), RecordError> {
        for axis in 0..self.tracks.len() as u32 {
            self.begin_axis(method, axis)?;
        }
        Ok(())
    }

    fn begin_axis(&mut self, method: Method, axis: u32) -> Result<(), RecordError> {
        if let Some(t) = self.tracks.get_mut(axis as usize) {
            t.setpoints.clear();
        }
        let stats = match axis {
            // The loops' statistics are per process: axis 0's run has them.
            0 => self.channel(1, method, axis, "stats", Every::Message)?,
            _ => u16::MAX,
        };
        let state = self.channel(0, method, axis, "state", Every::Period)?;
        let fault = self.channel(2, method, axis, "fault", Every::Message)?;
        let setpoint = self.channel(3, method, axis, "setpoint", Every::Period)?;
        let command = self.channel(5, method, axis, "command", Every::Period)?;
        let plan = self.channel(6, method, axis, "plan", Every::Period)?;
        let ack = self.channel(7, method, axis, "axis/ack", Every::Message)?;
        let status = self.channel(8, method, axis, "axis/status", Every::Period)?;
        self.channels.push(Channels {
            method,
            axis,
            state,
            stats,
            fault,
            setpoint,
            command,
            plan,
            ack,
            status,
            truth: None,
            written: 0,
            lost: 0,
            dropped: 0,
            last_fault: 0,
            last_t: 0.0,
        });
        Ok(())
    }

    /// A channel of `method`'s run for messages of `schema` (its index in `schemas`): in
    /// the file, and in the live view, which takes each message or one a period (`every`).
    fn channel(
        &mut self,
        schema: usize,
        method: Method,
        axis: u32,
        kind: &str,
        every: Every,
    ) -> Result<u16, RecordError> {
        let name = topic(method, axis, kind);
        let id = match self.writer.as_mut() {
            Some(w) => w
                .add_channel(self.schemas[schema], &name)
                .map_err(write_error(&self.path))?,
            None => {
                self.next_channel += 1;
                self.next_channel
            }
        };
        if let Some(live) = self.live.as_mut() {
            let (schema_name, text) = schema_texts()[schema].clone();
            live.add_channel(id, &name, schema_name, text, every);
        }
        Ok(id)
    }

    /// The current run's channels of `axis` (none before [`Self::begin`], or for an axis
    /// the scenario lacks).
    /// Where the current run's channels start: they are the last, one per track.
    fn run_start(&self) -> usize {
        self.channels.len().saturating_sub(self.tracks.len())
    }

    fn current(&self, axis: u32) -> Option<&Channels> {
        self.channels[self.run_start()..]
            .iter()
            .find(|c| c.axis == axis)
    }

    fn current_mut(&mut self, axis: u32) -> Option<&mut Channels> {
        let start = self.run_start();
        self.channels[start..].iter_mut().find(|c| c.axis == axis)
    }

    fn track(&self, axis: u32) -> Option<&Track> {
        self.tracks.get(axis as usize)
    }

    /// Sends a message to the live view (when due there) and to the file's writer: whether
    /// the file will have it.
    fn put(&mut self, channel: u16, t: f64, record: Record) -> Result<Queued, RecordError> {
        let ns = (t.max(0.0) * 1e9).round() as u64;
        if let Some(live) = self.live.as_mut().filter(|l| l.due(channel, ns)) {
            self.buf.clear();
            // Serialising plain numbers and text into a Vec cannot fail.
            let _ = serde_json::to_writer(&mut self.buf, &record);
            live.put(channel, ns, &self.buf);
        }
        let Some(w) = self.writer.as_mut() else {
            return Ok(Queued::Yes);
        };
        self.sequence = self.sequence.wrapping_add(1);
        let header = MessageHeader {
            channel_id: channel,
            sequence: self.sequence,
            log_time: ns,
            publish_time: ns,
        };
        let queued = w.message(header, record).map_err(write_error(&self.path))?;
        if queued == Queued::Dropped {
            let start = self.run_start();
            if let Some(ch) = self.channels[start..]
                .iter_mut()
                .find(|c| c.has_channel(channel))
            {
                ch.dropped += 1;
            }
        }
        Ok(queued)
    }

    /// One state sample of `axis` in the current method's run, with the θ_d, ω_d, α_d the
    /// run's figures graded it against (`None`: this recording's own, see
    /// [`Track::reference_at`]).
    pub fn state(
        &mut self,
        axis: u32,
        st: &DriveState,
        reference: Option<Reference>,
    ) -> Result<(), RecordError> {
        let (Some(ch), Some(track)) = (self.current(axis), self.track(axis)) else {
            return Ok(());
        };
        let (state_ch, fault_ch, last_fault) = (ch.state, ch.fault, ch.last_fault);
        let t = st.sample_time_s;
        let r = reference.unwrap_or_else(|| track.reference_at(t, st.theta_rad));
        let (i_d, i_q) = dq_currents(st.theta_rad, track.n_r, st.i_a_a, st.i_b_a);
        let k_m = track.k_m;
        let rec = StateRecord {
            t,
            seq: st.seq,
            theta: st.theta_rad,
            theta_d: r.theta,
            error: r.theta - st.theta_rad,
            omega: st.omega_rad_s,
            omega_d: r.omega,
            i_a: st.i_a_a,
            i_b: st.i_b_a,
            i_d,
            i_q,
            v_a: st.v_a_v,
            v_b: st.v_b_v,
            bus: st.bus_voltage_v,
            torque: k_m * i_q,
            flags: st.flags,
            fault: st.fault,
        };
        let queued = self.put(state_ch, t, Record::State(rec))?;
        if st.fault != last_fault {
            let f = FaultRecord {
                t,
                seq: st.seq,
                fault: st.fault,
            };
            self.put(fault_ch, t, Record::Fault(f))?;
        }
        if let Some(ch) = self.current_mut(axis) {
            match queued {
                Queued::Yes => ch.written += 1,
                Queued::Dropped => ch.lost += 1,
            }
            ch.last_fault = st.fault;
            ch.last_t = t;
        }
        Ok(())
    }

    /// A setpoint of `axis` in the current method's run, at its sample's time.
    pub fn setpoint(&mut self, axis: u32, sp: &TorqueSetpoint) -> Result<(), RecordError> {
        if let Some(t) = self.tracks.get_mut(axis as usize) {
            t.setpoints.push(sp);
        }
        let Some(ch) = self.current(axis) else {
            return Ok(());
        };
        let rec = SetpointRecord {
            t: sp.sample_time_s,
            seq: sp.seq,
            theta_d: sp.theta_d_rad,
            omega_d: sp.omega_d_rad_s,
            alpha_d: sp.alpha_d_rad_s2,
            torque: sp.torque_nm,
            load_estimate: sp.load_estimate_nm,
        };
        self.put(ch.setpoint, sp.sample_time_s, Record::Setpoint(rec))
            .map(drop)
    }

    /// An answer to a command to `axis`, at the tick that took it.
    pub fn ack(&mut self, axis: u32, a: &AxisAck) -> Result<(), RecordError> {
        let Some(ch) = self.current(axis) else {
            return Ok(());
        };
        let r = &a.request;
        let rec = AckRecord {
            t: a.t_s,
            tick: a.tick,
            kind: RequestKind::from_u32(r.kind)
                .map_or("?", |k| k.name())
                .to_string(),
            seq: r.seq,
            client: r.client,
            target: r.target_rad,
            velocity: r.velocity_rad_s,
            flags: r.flags,
            refusal: Refusal::from_u32(a.refusal)
                .map_or("?", |x| x.name())
                .to_string(),
            text: a.text().to_string(),
            state: AxisState::from_u32(a.state)
                .map_or("?", |x| x.name())
                .to_string(),
        };
        self.put(ch.ack, a.t_s, Record::Ack(Box::new(rec)))
            .map(drop)
    }

    /// `axis`'s status at a tick.
    pub fn status(&mut self, axis: u32, st: &AxisStatus) -> Result<(), RecordError> {
        let Some(ch) = self.current(axis) else {
            return Ok(());
        };
        let rec = StatusRecord {
            t: st.t_s,
            tick: st.tick,
            state_code: st.state,
            statusword: st.statusword,
            mode_code: st.mode,
            theta: st.theta_rad,
            omega: st.omega_rad_s,
            torque: st.torque_nm,
            following_error: st.following_error_rad,
            theta_d: st.theta_d_rad,
            omega_d: st.omega_d_rad_s,
            alpha_d: st.alpha_d_rad_s2,
            target: st.target_rad,
            fault: st.fault,
            warning: st.warning,
            move_id: st.move_id,
            last_seq: st.last_seq,
            stream_time: st.stream_time_s.is_finite().then_some(st.stream_time_s),
        };
        self.put(ch.status, st.t_s, Record::Status(rec)).map(drop)
    }

    /// A command to `axis` in the current method's run, at the time of the sample it
    /// answers.
    pub fn command(&mut self, axis: u32, c: &DriveCommand) -> Result<(), RecordError> {
        let (Some(ch), Some(track)) = (self.current(axis), self.track(axis)) else {
            return Ok(());
        };
        let rec = CommandRecord {
            t: c.sample_time_s,
            t_ref: c.sample_time_s + track.ref_lead_s,
            seq: c.seq,
            answers_seq: c.answers_seq,
            v_a: c.v_a_v,
            v_b: c.v_b_v,
            i_a_ref: c.i_a_ref_a,
            i_b_ref: c.i_b_ref_a,
        };
        self.put(ch.command, c.sample_time_s, Record::Command(rec))
            .map(drop)
    }

    /// A voltage plan for `axis` in the current method's run (its first four entries), at
    /// the time of the sample its command answers.
    pub fn plan(&mut self, axis: u32, p: &DrivePlan) -> Result<(), RecordError> {
        let (Some(ch), Some(track)) = (self.current(axis), self.track(axis)) else {
            return Ok(());
        };
        let t = p.answers_seq as f64 * track.period_s;
        let e =
            |j: usize, phase: usize| p.entries().get(j).map_or(f64::NAN, |v| f64::from(v[phase]));
        let rec = PlanRecord {
            t,
            command_seq: p.command_seq,
            answers_seq: p.answers_seq,
            len: p.len,
            v_a_0: e(0, 0),
            v_b_0: e(0, 1),
            v_a_1: e(1, 0),
            v_b_1: e(1, 1),
            v_a_2: e(2, 0),
            v_b_2: e(2, 1),
            v_a_3: e(3, 0),
            v_b_3: e(3, 1),
        };
        self.put(ch.plan, t, Record::Plan(rec)).map(drop)
    }

    /// The emulated drive's true rotor state over the current method's run (axis 0's).
    pub fn truth(&mut self, rows: &[TruthRow]) -> Result<(), RecordError> {
        let wrap = write_error(&self.path);
        let start = self.run_start();
        let ch = self.channels[start..].iter_mut().find(|c| c.axis == 0);
        let (Some(ch), Some(w)) = (ch, self.writer.as_mut()) else {
            return Ok(());
        };
        let channel = match ch.truth {
            Some(c) => c,
            None => {
                let name = topic(ch.method, 0, "truth");
                let c = w.add_channel(self.schemas[4], &name).map_err(wrap)?;
                ch.truth = Some(c);
                c
            }
        };
        // Written after the run: nothing waits on the clock, so every row goes in.
        let realtime = w.set_lossless(true);
        let written = self.truth_rows(channel, rows);
        if let Some(w) = self.writer.as_mut() {
            w.set_lossless(realtime);
        }
        written
    }

    fn truth_rows(&mut self, channel: u16, rows: &[TruthRow]) -> Result<(), RecordError> {
        for r in rows {
            let rec = TruthRecord {
                t: r.t_s,
                seq: r.k,
                theta: r.theta_rad,
                error: self
                    .track(0)
                    .map_or(f64::NAN, |t| t.reference_at(r.t_s, r.theta_rad).theta)
                    - r.theta_rad,
                omega: r.omega_rad_s,
                i_a: r.i_a_a,
                i_b: r.i_b_a,
            };
            self.put(channel, r.t_s, Record::Truth(rec))?;
        }
        Ok(())
    }

    /// Samples of `axis` in the current run the monitor never saw.
    pub fn lost(&mut self, axis: u32, n: u64) {
        if let Some(ch) = self.current_mut(axis) {
            ch.lost += n;
        }
    }

    /// A loop's statistics report, at the latest sample's time.
    pub fn stats(&mut self, r: &StatsReport) -> Result<(), RecordError> {
        let Some(ch) = self.current(0) else {
            return Ok(());
        };
        let (channel, t) = (ch.stats, ch.last_t);
        let role = stepdrive_shared::stack::Role::from_code(r.role).map_or("other", |r| r.id());
        let rec = StatsRecord {
            t,
            role: role.to_string(),
            cycles: r.cycles,
            misses: r.misses,
            planned: r.planned,
            overruns: r.overruns,
            lost: r.lost,
            longest_miss_run: r.longest_miss_run,
        };
        self.put(channel, t, Record::Stats(Box::new(rec))).map(drop)
    }

    /// Writes what was recorded and lost, then the summary: the file is complete.
    pub fn finish(mut self) -> Result<(), RecordError> {
        self.close()
    }

    fn close(&mut self) -> Result<(), RecordError> {
        let Some(mut w) = self.writer.take() else {
            return Ok(());
        };
        let dropped = self.dropped();
        if dropped > 0 {
            tracing::warn!(
                "the recording {} lacks {dropped} messages: its writer fell behind the stack \
                 (the run's figures are the monitor's, from every sample it saw)",
                self.path.display()
            );
        }
        let mut counts = BTreeMap::new();
        for ch in &self.channels {
            let m = match ch.axis {
                0 => ch.method.as_str().to_string(),
                n => format!("{}.axis{n}", ch.method.as_str()),
            };
            counts.insert(format!("{m}.samples_recorded"), ch.written.to_string());
            counts.insert(format!("{m}.samples_lost"), ch.lost.to_string());
            counts.insert(format!("{m}.messages_dropped"), ch.dropped.to_string());
        }
        w.finish(Metadata {
            name: "recording".into(),
            metadata: counts,
        })
        .map_err(write_error(&self.path))
    }
}

impl Drop for Recording {
    fn drop(&mut self) {
        if let Err(e) = self.close() {
            tracing::error!("{e:#}");
        }
    }
}

/// A recording read back: per method, its states in order, and the file's metadata.
#[derive(Debug, Default)]
pub struct Recorded {
    pub runs: Vec<(String, Vec<StateRecord>)>,
    pub stats: Vec<(String, Vec<StatsRecord>)>,
    pub faults: Vec<(String, Vec<FaultRecord>)>,
    pub setpoints: Vec<(String, Vec<SetpointRecord>)>,
    pub commands: Vec<(String, Vec<CommandRecord>)>,
    pub plans: Vec<(String, Vec<PlanRecord>)>,
    pub truth: Vec<(String, Vec<TruthRecord>)>,
    pub acks: Vec<(String, Vec<AckRecord>)>,
    pub statuses: Vec<(String, Vec<StatusRecord>)>,
    pub metadata: BTreeMap<String, BTreeMap<String, String>>,
    /// A multi-axis recording's other axes, by index, each read as a recording of its own
    /// (without metadata: the file's is axis 0's, above).
    pub axes: BTreeMap<u32, Recorded>,
}

impl Recorded {
    pub fn read(path: &Path) -> Result<Self, RecordError> {
        let bytes = std::fs::read(path).map_err(|source| RecordError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let parse = |source| RecordError::Parse {
            path: path.to_path_buf(),
            source,
        };
        let mut out = Recorded::default();
        for m in mcap::MessageStream::new(&bytes).map_err(parse)? {
            let m = m.map_err(parse)?;
            let topic = m.channel.topic.clone();
            let bad = |source| RecordError::Message {
                path: path.to_path_buf(),
                topic: topic.clone(),
                source,
            };
            let Some((method, kind)) = topic.trim_start_matches('/').split_once('/') else {
                continue;
            };
            // Another axis's: `axis/<n>/<kind>` (axis 0's own `axis/ack` is a kind).
            let other = kind.strip_prefix("axis/").and_then(|rest| {
                let (n, kind) = rest.split_once('/')?;
                Some((n.parse::<u32>().ok()?, kind))
            });
            let (into, kind) = match other {
                Some((n, kind)) if n > 0 => (out.axes.entry(n).or_default(), kind),
                _ => (&mut out, kind),
            };
            into.take(method, kind, &m.data).map_err(bad)?;
        }
        let summary = mcap::Summary::read(&bytes).map_err(parse)?;
        if let Some(summary) = summary {
            for index in &summary.metadata_indexes {
                let meta = mcap::read::metadata(&bytes, index).map_err(parse)?;
                out.metadata.insert(meta.name, meta.metadata);
            }
        }
        Ok(out)
    }

    /// One message of `method`'s run on a channel of `kind` (unknown kinds are skipped).
    fn take(&mut self, method: &str, kind: &str, data: &[u8]) -> Result<(), serde_json::Error> {
        match kind {
            "state" => push(&mut self.runs, method, serde_json::from_slice(data)?),
            "stats" => push(&mut self.stats, method, serde_json::from_slice(data)?),
            "fault" => push(&mut self.faults, method, serde_json::from_slice(data)?),
            "setpoint" => push(&mut self.setpoints, method, serde_json::from_slice(data)?),
            "plan" => push(&mut self.plans, method, serde_json::from_slice(data)?),
            "command" => push(&mut self.commands, method, serde_json::from_slice(data)?),
            "truth" => push(&mut self.truth, method, serde_json::from_slice(data)?),
            "axis/ack" => push(&mut self.acks, method, serde_json::from_slice(data)?),
            "axis/status" => push(&mut self.statuses, method, serde_json::from_slice(data)?),
            _ => {}
        }
        Ok(())
    }

    /// The scenario the recording was made with.
    pub fn scenario(&self) -> Option<Scenario> {
        let text = self.metadata.get("scenario")?.get("toml")?;
        Scenario::from_toml_str(text).ok()
    }
}

fn push<T>(list: &mut Vec<(String, Vec<T>)>, method: &str, item: T) {
    match list.iter_mut().find(|(m, _)| m == method) {
        Some((_, v)) => v.push(item),
        None => list.push((method.to_string(), vec![item])),
    }
}

/// Writes each topic of the recording at `path` as a CSV file in `dir` (a header of field
/// names with units, then one row per message); returns the files and their row counts.
pub fn export_csv(path: &Path, dir: &Path) -> Result<Vec<(PathBuf, usize)>, RecordError> {
    let rec = Recorded::read(path)?;
    std::fs::create_dir_all(dir).map_err(|source| RecordError::Export {
        path: dir.to_path_buf(),
        source,
    })?;
    let state_header: Vec<String> = STATE_FIELDS
        .iter()
        .map(|(n, u)| {
            if u.is_empty() {
                n.to_string()
            } else {
                format!("{n} [{u}]")
            }
        })
        .collect();
    let mut written = Vec::new();
    export_axis(&rec, dir, "", &state_header, &mut written)?;
    // Another axis's files: `axis<n>_<method>_<kind>.csv`.
    for (n, axis) in &rec.axes {
        export_axis(axis, dir, &format!("axis{n}_"), &state_header, &mut written)?;
    }
    Ok(written)
}

/// One axis's topics of an export, as [`export_csv`] says, their names led by `prefix`.
fn export_axis(
    rec: &Recorded,
    dir: &Path,
    prefix: &str,
    state_header: &[String],
    written: &mut Vec<(PathBuf, usize)>,
) -> Result<(), RecordError> {
    for (method, states) in &rec.runs {
        let p = dir.join(format!("{prefix}{method}_state.csv"));
        write_csv(&p, &state_header.join(","), states, |s| {
            format!(
                "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
                s.t,
                s.seq,
                s.theta,
                s.theta_d,
                s.error,
                s.omega,
                s.omega_d,
                s.i_a,
                s.i_b,
                s.i_d,
                s.i_q,
                s.v_a,
                s.v_b,
                s.bus,
                s.torque,
                s.flags,
                s.fault
            )
        })?;
        written.push((p, states.len()));
    }
    for (method, stats) in &rec.stats {
        let p = dir.join(format!("{prefix}{method}_stats.csv"));
        let header = "t [s],role,cycles,misses,planned,overruns,lost,longest_miss_run";
        write_csv(&p, header, stats, |s| {
            format!(
                "{},{},{},{},{},{},{},{}",
                s.t, s.role, s.cycles, s.misses, s.planned, s.overruns, s.lost, s.longest_miss_run
            )
        })?;
        written.push((p, stats.len()));
    }
    for (method, faults) in &rec.faults {
        let p = dir.join(format!("{prefix}{method}_fault.csv"));
        write_csv(&p, "t [s],seq,fault", faults, |s| {
            format!("{},{},{}", s.t, s.seq, s.fault)
        })?;
        written.push((p, faults.len()));
    }
    for (method, setpoints) in &rec.setpoints {
        let p = dir.join(format!("{prefix}{method}_setpoint.csv"));
        let header = "t [s],seq,theta_d [rad],omega_d [rad/s],alpha_d [rad/s²],torque [N·m],load_estimate [N·m]";
        write_csv(&p, header, setpoints, |s| {
            format!(
                "{},{},{},{},{},{},{}",
                s.t, s.seq, s.theta_d, s.omega_d, s.alpha_d, s.torque, s.load_estimate
            )
        })?;
        written.push((p, setpoints.len()));
    }
    for (method, commands) in &rec.commands {
        let p = dir.join(format!("{prefix}{method}_command.csv"));
        let header = "t [s],t_ref [s],seq,answers_seq,v_a [V],v_b [V],i_a_ref [A],i_b_ref [A]";
        write_csv(&p, header, commands, |c| {
            format!(
                "{},{},{},{},{},{},{},{}",
                c.t, c.t_ref, c.seq, c.answers_seq, c.v_a, c.v_b, c.i_a_ref, c.i_b_ref
            )
        })?;
        written.push((p, commands.len()));
    }
    for (method, plans) in &rec.plans {
        let p = dir.join(format!("{prefix}{method}_plan.csv"));
        let header = "t [s],command_seq,answers_seq,len,v_a_0 [V],v_b_0 [V],v_a_1 [V],v_b_1 [V],v_a_2 [V],v_b_2 [V],v_a_3 [V],v_b_3 [V]";
        write_csv(&p, header, plans, |r| {
            format!(
                "{},{},{},{},{},{},{},{},{},{},{},{}",
                r.t,
                r.command_seq,
                r.answers_seq,
                r.len,
                r.v_a_0,
                r.v_b_0,
                r.v_a_1,
                r.v_b_1,
                r.v_a_2,
                r.v_b_2,
                r.v_a_3,
                r.v_b_3
            )
        })?;
        written.push((p, plans.len()));
    }
    for (method, truth) in &rec.truth {
        let p = dir.join(format!("{prefix}{method}_truth.csv"));
        let header = "t [s],seq,theta [rad],error [rad],omega [rad/s],i_a [A],i_b [A]";
        write_csv(&p, header, truth, |s| {
            format!(
                "{},{},{},{},{},{},{}",
                s.t, s.seq, s.theta, s.error, s.omega, s.i_a, s.i_b
            )
        })?;
        written.push((p, truth.len()));
    }
    for (method, acks) in &rec.acks {
        let p = dir.join(format!("{prefix}{method}_axis_ack.csv"));
        let header =
            "t [s],tick,kind,seq,client,target [rad],velocity [rad/s],flags,refusal,text,state";
        write_csv(&p, header, acks, |a| {
            format!(
                "{},{},{},{},{},{},{},{},{},{},{}",
                a.t,
                a.tick,
                a.kind,
                a.seq,
                a.client,
                a.target,
                a.velocity,
                a.flags,
                a.refusal,
                csv_text(&a.text),
                csv_text(&a.state)
            )
        })?;
        written.push((p, acks.len()));
    }
    for (method, statuses) in &rec.statuses {
        let p = dir.join(format!("{prefix}{method}_axis_status.csv"));
        let header = "t [s],tick,state,statusword,mode,theta [rad],omega [rad/s],torque [N·m],\
                      following_error [rad],theta_d [rad],omega_d [rad/s],alpha_d [rad/s²],\
                      target [rad],fault,warning,move_id,last_seq,stream_time [s]";
        write_csv(&p, header, statuses, |s| {
            let state = AxisState::from_u32(s.state_code).map_or("?", |x| x.name());
            let mode =
                stepdrive_shared::axis::AxisMode::from_u32(s.mode_code).map_or("?", |m| m.name());
            format!(
                "{},{},{},{:#06x},{},{},{},{},{},{},{},{},{},{:#x},{:#x},{},{},{}",
                s.t,
                s.tick,
                csv_text(state),
                s.statusword,
                csv_text(mode),
                s.theta,
                s.omega,
                s.torque,
                s.following_error,
                s.theta_d,
                s.omega_d,
                s.alpha_d,
                s.target,
                s.fault,
                s.warning,
                s.move_id,
                s.last_seq,
                s.stream_time.map_or(String::new(), |t| t.to_string())
            )
        })?;
        written.push((p, statuses.len()));
    }
    Ok(())
}

/// A text field for CSV: quoted, its quotes doubled.
fn csv_text(t: &str) -> String {
    format!("\"{}\"", t.replace('"', "\"\""))
}

/// One CSV file: `header`, then `row` of each item.
fn write_csv<T>(
    path: &Path,
    header: &str,
    items: &[T],
    row: impl Fn(&T) -> String,
) -> Result<(), RecordError> {
    use std::io::Write;
    let io = |source| RecordError::Export {
        path: path.to_path_buf(),
        source,
    };
    let mut f = BufWriter::new(File::create(path).map_err(io)?);
    writeln!(f, "{header}").map_err(io)?;
    for item in items {
        writeln!(f, "{}", row(item)).map_err(io)?;
    }
    f.flush().map_err(io)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// JSON has no NaN: a record holding one is written with `null` there, and reads back
    /// with NaN (a short plan's missing entries, a refused NaN target), not as an error that
    /// makes the whole recording unreadable.
    #[test]
    fn a_nan_in_a_record_reads_back_as_nan() {
        let plan = PlanRecord {
            t: 0.5,
            command_seq: 3,
            answers_seq: 10,
            len: 1,
            v_a_0: 1.5,
            v_b_0: -2.0,
            v_a_1: f64::NAN,
            v_b_1: f64::NAN,
            v_a_2: f64::NAN,
            v_b_2: f64::NAN,
            v_a_3: f64::NAN,
            v_b_3: f64::NAN,
        };
        let text = serde_json::to_string(&plan).expect("serialise");
        assert!(text.contains("\"v_a_1\":null"), "{text}");
        let back: PlanRecord = serde_json::from_str(&text).expect("reads back");
        assert_eq!((back.v_a_0, back.v_b_0, back.len), (1.5, -2.0, 1));
        assert!(back.v_a_1.is_nan() && back.v_b_3.is_nan());
        let ack = r#"{"t":1.0,"tick":2,"kind":"move","seq":7,"client":1,"target":null,"velocity":0.0,"flags":0,"refusal":"not_finite","text":"target NaN","state":"Operation enabled"}"#;
        let back: AckRecord = serde_json::from_str(ack).expect("reads back");
        assert!(back.target.is_nan());
        assert_eq!(back.velocity, 0.0);
    }
}
