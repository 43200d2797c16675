//! Transport baselines for `stepdrive latency`: the stack's traffic pattern with the control
//! law taken out. The "ping" side is paced like the plant (a message every period on
//! absolute deadlines); the "pong" side waits like the current loop, records the one-way
//! publish → receive latency, and answers at once. Same payload size as `DriveState`. Both
//! sides are nodes of the same runner as the stack, so the baseline differs from the
//! current loop only in its transport (and in the current loop's host-hold accounting).

use crate::latency::histfile::SparseHistogram;
use anyhow::{Context, Result};
use std::os::unix::net::UnixDatagram;
use std::path::PathBuf;
use std::time::Duration;
use stepdrive_runtime::deploy::Deployment;
use stepdrive_runtime::ipc::{IpcBus, IpcPublisher, IpcSubscriber, Stamp};
use stepdrive_runtime::node::{Cx, Flow, Late, Node, Pace, Poll, Role, Start};
use stepdrive_runtime::pacer::WaitStrategy;
use stepdrive_runtime::port::{PortFactory, Presence, Publish, Subscribe};
use stepdrive_runtime::rt::RtOptions;
use stepdrive_runtime::runner::{Runner, Settings};
use stepdrive_runtime::RunError;
use stepdrive_shared::messages::{state_flags, DriveState};
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::{Topic, LOOP_BUFFER};

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Transport {
    Iceoryx2,
    Uds,
}

impl Transport {
    pub fn as_str(self) -> &'static str {
        match self {
            Transport::Iceoryx2 => "iceoryx2",
            Transport::Uds => "uds",
        }
    }
}

/// Both directions of a ping-pong link, sending and receiving `DriveState`-sized messages.
pub enum Link {
    /// The stack's own service settings (realtime QoS), under a private instance: pings go
    /// over `<endpoint>/drive/state`, replies over `<endpoint>.back/drive/state`.
    Iceoryx2 {
        tx: Box<IpcPublisher<DriveState>>,
        rx: Box<IpcSubscriber<DriveState>>,
        presence: Box<dyn Presence>,
        _buses: Box<[IpcBus; 2]>,
    },
    Uds {
        socket: UnixDatagram,
        peer: PathBuf,
        own: PathBuf,
    },
}

impl Drop for Link {
    fn drop(&mut self) {
        if let Link::Uds { own, .. } = self {
            let _ = std::fs::remove_file(own);
        }
    }
}

const MSG: usize = std::mem::size_of::<DriveState>();

fn encode(m: &DriveState) -> [u8; MSG] {
    let mut b = [0u8; MSG];
    b[0..8].copy_from_slice(&m.seq.to_le_bytes());
    b[8..16].copy_from_slice(&m.deadline_ns.to_le_bytes());
    b[16..24].copy_from_slice(&m.publish_time_ns.to_le_bytes());
    b[24..28].copy_from_slice(&m.flags.to_le_bytes());
    b
}

fn decode(b: &[u8]) -> Option<DriveState> {
    if b.len() != MSG {
        return None;
    }
    let u64_at = |i: usize| u64::from_le_bytes(b[i..i + 8].try_into().unwrap_or([0; 8]));
    Some(DriveState {
        seq: u64_at(0),
        deadline_ns: u64_at(8),
        publish_time_ns: u64_at(16),
        flags: u32::from_le_bytes(b[24..28].try_into().unwrap_or([0; 4])),
        ..Default::default()
    })
}

fn socket_path(endpoint: &str, role: &str) -> PathBuf {
    std::env::temp_dir().join(format!("stepdrive-{endpoint}-{role}.sock"))
}

impl Link {
    fn open(transport: Transport, endpoint: &str, ping: bool) -> Result<Self> {
        match transport {
            Transport::Iceoryx2 => {
                let role = if ping { "ping" } else { "pong" };
                // A private instance: the stack's realtime settings, no scenario.
                let stamp = Stamp {
                    mode: Mode::Realtime,
                    scenario: "ping-pong".to_string(),
                };
                let mut forward = IpcBus::open(endpoint, role, &stamp)?;
                let backward = IpcBus::open(&format!("{endpoint}.back"), role, &stamp)?;
                let (tx, rx) = if ping {
                    (
                        forward.publisher_of()?,
                        backward.subscriber_of(LOOP_BUFFER)?,
                    )
                } else {
                    (
                        backward.publisher_of()?,
                        forward.subscriber_of(LOOP_BUFFER)?,
                    )
                };
                let presence = forward.presence()?;
                Ok(Link::Iceoryx2 {
                    tx: Box::new(tx),
                    rx: Box::new(rx),
                    presence,
                    _buses: Box::new([forward, backward]),
                })
            }
            Transport::Uds => {
                let (me, peer) = if ping {
                    ("ping", "pong")
                } else {
                    ("pong", "ping")
                };
                let path = socket_path(endpoint, me);
                let _ = std::fs::remove_file(&path);
                let socket = UnixDatagram::bind(&path)
                    .with_context(|| format!("cannot bind {}", path.display()))?;
                socket.set_nonblocking(true)?;
                Ok(Link::Uds {
                    socket,
                    peer: socket_path(endpoint, peer),
                    own: path,
                })
            }
        }
    }

    fn send(&mut self, m: &DriveState) -> Result<bool> {
        match self {
            Link::Iceoryx2 { tx, .. } => {
                tx.publish(m)?;
                Ok(true)
            }
            Link::Uds { socket, peer, .. } => match socket.send_to(&encode(m), &*peer) {
                Ok(_) => Ok(true),
                // The peer is not bound yet, or its queue is full: the message is dropped,
                // as a realtime publisher would.
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::NotFound
                            | std::io::ErrorKind::ConnectionRefused
                            | std::io::ErrorKind::WouldBlock
                    ) =>
                {
                    Ok(false)
                }
                Err(e) => Err(e.into()),
            },
        }
    }

    fn try_recv(&mut self) -> Result<Option<DriveState>> {
        match self {
            Link::Iceoryx2 { rx, .. } => Ok(rx.receive()?),
            Link::Uds { socket, .. } => {
                let mut buf = [0u8; MSG + 1];
                match socket.recv(&mut buf) {
                    Ok(n) => Ok(decode(&buf[..n])),
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => Ok(None),
                    Err(e) => Err(e.into()),
                }
            }
        }
    }

    /// The ping side: the pong side is there to answer.
    fn peer_ready(&self) -> bool {
        match self {
            Link::Iceoryx2 { presence, .. } => presence.subscribers(Topic::State) >= 1,
            Link::Uds { peer, .. } => peer.exists(),
        }
    }

    fn connect(&mut self) -> Result<()> {
        if let Link::Iceoryx2 { tx, .. } = self {
            tx.connect()?;
        }
        Ok(())
    }
}

#[derive(Debug, Clone)]
pub struct PingPongOptions {
    pub transport: Transport,
    pub endpoint: String,
    pub ping: bool,
    pub period_ns: u64,
    pub duration: Duration,
    pub wait: WaitStrategy,
    pub rt: RtOptions,
    /// Pong: where to write the one-way latency histogram (JSON).
    pub out: Option<PathBuf>,
}

fn link_error(e: anyhow::Error) -> RunError {
    RunError::Node {
        role: Role::Tool("ping-pong"),
        source: e.into(),
    }
}

/// How long the ping side keeps offering its last ping to a full socket queue.
const LAST_PING_PATIENCE_NS: u64 = 2_000_000_000;

/// Pings at absolute deadlines, like the plant publishes its samples.
struct Ping {
    period_ns: u64,
    count: u64,
    sent: u64,
}

impl Node for Ping {
    type Ports = Link;

    fn role(&self) -> Role {
        Role::Tool("ping")
    }

    fn pace(&self) -> Pace {
        Pace::Clock {
            period_ns: self.period_ns,
            late: Late::Pause,
        }
    }

    fn rate_hz(&self) -> f64 {
        1e9 / self.period_ns as f64
    }

    fn awaiting(&self) -> String {
        "the pong side".to_string()
    }

    fn start(&mut self, link: &mut Link, cx: &mut Cx) -> Result<Start, RunError> {
        if !link.peer_ready() {
            return Ok(Start::Waiting);
        }
        Ok(Start::Ready {
            epoch_ns: Some(cx.now() + 20_000_000),
        })
    }

    fn connect(&mut self, link: &mut Link) -> Result<(), RunError> {
        link.connect().map_err(link_error)
    }

    fn poll(&mut self, link: &mut Link, _cx: &mut Cx) -> Result<Poll, RunError> {
        while link.try_recv().map_err(link_error)?.is_some() {}
        Ok(Poll::READY)
    }

    fn step(&mut self, link: &mut Link, cx: &mut Cx) -> Result<Flow, RunError> {
        let k = self.sent;
        let last = k + 1 == self.count;
        let m = DriveState {
            seq: k,
            deadline_ns: cx.deadline_ns,
            publish_time_ns: cx.now(),
            flags: if last { state_flags::LAST } else { 0 },
            ..Default::default()
        };
        let mut sent = link.send(&m).map_err(link_error)?;
        if last {
            // The last ping ends the pong side's run: dropped (a socket queue a loaded
            // pong had let fill), the pong waited out its peer timeout and the baseline was
            // lost. The measurement is over, so waiting here costs nothing.
            let deadline = cx.now() + LAST_PING_PATIENCE_NS;
            while !sent && cx.now() < deadline {
                std::thread::sleep(Duration::from_millis(1));
                sent = link.send(&m).map_err(link_error)?;
            }
        }
        self.sent += 1;
        Ok(if last { Flow::Last } else { Flow::Continue })
    }
}

/// Waits like the current loop, records the one-way latency as its input hop, answers.
struct Pong {
    period_ns: u64,
    message: Option<DriveState>,
    due_ns: Option<u64>,
}

impl Node for Pong {
    type Ports = Link;

    fn role(&self) -> Role {
        Role::Tool("pong")
    }

    fn pace(&self) -> Pace {
        Pace::Input
    }

    fn rate_hz(&self) -> f64 {
        1e9 / self.period_ns as f64
    }

    fn awaiting(&self) -> String {
        "pings".to_string()
    }

    fn poll(&mut self, link: &mut Link, _cx: &mut Cx) -> Result<Poll, RunError> {
        self.message = link.try_recv().map_err(link_error)?;
        Ok(if self.message.is_some() {
            Poll::READY
        } else {
            Poll::Pending
        })
    }

    fn step(&mut self, link: &mut Link, cx: &mut Cx) -> Result<Flow, RunError> {
        let Some(m) = self.message.take() else {
            return Ok(Flow::Continue);
        };
        // Measured exactly as the current loop measures its state hop.
        cx.stats
            .hop
            .record(cx.woke_ns.saturating_sub(m.publish_time_ns));
        let reply = DriveState {
            publish_time_ns: cx.now(),
            ..m
        };
        link.send(&reply).map_err(link_error)?;
        self.due_ns = Some(m.deadline_ns + self.period_ns);
        Ok(if m.flags & state_flags::LAST != 0 {
            Flow::Last
        } else {
            Flow::Continue
        })
    }

    fn due_ns(&self) -> Option<u64> {
        self.due_ns
    }
}

pub fn run(o: &PingPongOptions) -> Result<()> {
    o.rt.apply()?;
    let link = Link::open(o.transport, &o.endpoint, o.ping)?;
    let d = Deployment::default();
    let settings = Settings {
        wait: o.wait,
        startup_timeout: d.startup_timeout(),
        peer_timeout: d.peer_timeout(),
        account_host_holds: false,
        linger: Duration::ZERO,
        report_end: false,
    };
    if o.ping {
        let ping = Ping {
            period_ns: o.period_ns,
            count: (o.duration.as_nanos() as u64 / o.period_ns).max(1),
            sent: 0,
        };
        Runner::new(ping, link, settings, None).run()?;
        // Let the last pong arrive before our ports go away.
        std::thread::sleep(Duration::from_millis(100));
        return Ok(());
    }
    let pong = Pong {
        period_ns: o.period_ns,
        message: None,
        due_ns: None,
    };
    let stats = Runner::new(pong, link, settings, None).run()?.stats;
    if let Some(path) = &o.out {
        let text = serde_json::to_string(&SparseHistogram::from(&stats.hop))?;
        std::fs::write(path, text).with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(())
}
