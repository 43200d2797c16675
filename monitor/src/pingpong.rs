//! Transport baselines for `stepdrive latency`: the stack's traffic pattern with the control
//! law taken out. The "ping" side is paced like the plant (a message every period on
//! absolute deadlines); the "pong" side waits like the current loop, records the one-way
//! publish → receive latency, and answers at once. Same payload size as `DriveState`.

use anyhow::{bail, Context, Result};
use std::os::unix::net::UnixDatagram;
use std::path::PathBuf;
use std::time::Duration;
use stepdrive_shared::clock::monotonic_ns;
use stepdrive_shared::messages::{state_flags, DriveState};
use stepdrive_shared::pacer::{await_message, Pacer, WaitStrategy};
use stepdrive_shared::poll::{termination_requested, WaitError};
use stepdrive_shared::rt::RtOptions;
use stepdrive_shared::scenario::Mode;
use stepdrive_shared::services::{
    connect, publisher, send, subscriber, subscriber_count, try_receive, Pub, Sub, Topics,
    LOOP_BUFFER,
};
use stepdrive_shared::stats::{Histogram, SparseHistogram};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Transport {
    Iceoryx2,
    Uds,
}

impl std::str::FromStr for Transport {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "iceoryx2" => Ok(Self::Iceoryx2),
            "uds" => Ok(Self::Uds),
            o => Err(format!("unknown transport `{o}` (iceoryx2 or uds)")),
        }
    }
}

/// Both directions of a ping-pong link, sending and receiving `DriveState`-sized messages.
enum Link {
    /// The stack's own service settings (realtime QoS), under a private instance: pings go
    /// over `<endpoint>/drive/state`, replies over `<endpoint>.back/drive/state`.
    Iceoryx2 {
        tx: Box<Pub<DriveState>>,
        rx: Box<Sub<DriveState>>,
        forward: Box<Topics>,
        _backward: Box<Topics>,
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
                let forward = Box::new(Topics::open(endpoint, role, Mode::Realtime)?);
                let backward = Box::new(Topics::open(
                    &format!("{endpoint}.back"),
                    role,
                    Mode::Realtime,
                )?);
                let (tx, rx) = if ping {
                    (
                        publisher(&forward.state, "ping")?,
                        subscriber(&backward.state, "pong", LOOP_BUFFER)?,
                    )
                } else {
                    (
                        publisher(&backward.state, "pong")?,
                        subscriber(&forward.state, "ping", LOOP_BUFFER)?,
                    )
                };
                Ok(Link::Iceoryx2 {
                    tx: Box::new(tx),
                    rx: Box::new(rx),
                    forward,
                    _backward: backward,
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
                send(tx, *m)?;
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
            Link::Iceoryx2 { rx, .. } => Ok(try_receive(rx)?),
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

    fn peer_ready(&self) -> bool {
        match self {
            Link::Iceoryx2 { .. } => true,
            Link::Uds { peer, .. } => peer.exists(),
        }
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

pub fn run(o: &PingPongOptions) -> Result<()> {
    let mut link = Link::open(o.transport, &o.endpoint, o.ping)?;
    o.rt.apply()?;
    if o.ping {
        run_ping(o, &mut link)
    } else {
        run_pong(o, &mut link)
    }
}

fn run_ping(o: &PingPongOptions, link: &mut Link) -> Result<()> {
    // Wait for the pong side.
    let start = monotonic_ns();
    loop {
        let ready = match link {
            Link::Iceoryx2 { forward, .. } => subscriber_count(&forward.state) >= 1,
            Link::Uds { .. } => link.peer_ready(),
        };
        if ready {
            break;
        }
        if termination_requested() || monotonic_ns() - start > 30_000_000_000 {
            bail!("pong side did not come up");
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    if let Link::Iceoryx2 { tx, .. } = link {
        connect(tx)?;
    }
    let n = o.duration.as_nanos() as u64 / o.period_ns;
    let mut pacer = Pacer::new(
        monotonic_ns() + 20_000_000,
        o.period_ns,
        WaitStrategy::Sleep,
    );
    for k in 0..n {
        if termination_requested() {
            bail!("terminated");
        }
        let tick = pacer.wait();
        while link.try_recv()?.is_some() {}
        let m = DriveState {
            seq: k,
            deadline_ns: tick.deadline_ns,
            publish_time_ns: monotonic_ns(),
            flags: if k + 1 == n { state_flags::LAST } else { 0 },
            ..Default::default()
        };
        link.send(&m)?;
        pacer.pause_if_late(k + 1, monotonic_ns());
    }
    std::thread::sleep(Duration::from_millis(100));
    Ok(())
}

fn run_pong(o: &PingPongOptions, link: &mut Link) -> Result<()> {
    let mut hop = Box::<Histogram>::default();
    let mut expected = 0u64;
    loop {
        // The current loop's own wait, so the baseline differs from it only in transport
        // (and in the current loop's steal accounting, done while it has slack).
        let arrival = await_message(o.wait, expected, Duration::from_secs(5), &mut (), || {
            link.try_recv()
        })
        .map_err(|e| match e {
            WaitError::Source(e) => e,
            _ => anyhow::anyhow!("ping side went silent"),
        })?;
        let m = arrival.message;
        // Measured exactly as the current loop measures its state hop.
        hop.record(arrival.taken_ns.saturating_sub(m.publish_time_ns));
        let reply = DriveState {
            publish_time_ns: monotonic_ns(),
            ..m
        };
        link.send(&reply)?;
        expected = m.deadline_ns + o.period_ns;
        if m.flags & state_flags::LAST != 0 {
            break;
        }
    }
    if let Some(path) = &o.out {
        let text = serde_json::to_string(&SparseHistogram::from(&*hop))?;
        std::fs::write(path, text).with_context(|| format!("cannot write {}", path.display()))?;
    }
    Ok(())
}
