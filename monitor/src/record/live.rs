//! The live view: the recording's channels served to Foxglove (or Lichtblick) over the
//! Foxglove WebSocket protocol while the stack runs, each with its JSON Schema, decimated.
//!
//! The monitor already turns every sample it reads into the recording's JSON messages; the
//! live view takes the same messages ([`crate::record::recording::Recording::with_live`]),
//! at most one per channel per period of the configured rate for the streams (state,
//! setpoint, command, plan, axis status), every one for the events (faults, axis
//! acknowledgements, statistics). A message the view does not take costs a comparison: a
//! live view without a file does not even encode it. The server runs on a tokio runtime of
//! one worker thread of its own, outside every loop; a client that cannot keep up loses
//! messages in the server's queue, never slows the monitor.

use foxglove::{
    ChannelBuilder, Context, PartialMetadata, RawChannel, Schema, WebSocketServer,
    WebSocketServerHandle,
};
use std::net::SocketAddr;
use std::sync::Arc;

/// The live view's default rate for the streams, Hz: a plot in Foxglove redraws at 60 Hz.
pub const DEFAULT_RATE_HZ: f64 = 100.0;

/// Highest rate the live view takes, Hz: the state stream's own (20 kHz).
pub const MAX_RATE_HZ: f64 = 20_000.0;

#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    #[error("the live view's rate {0} Hz is not in (0, {MAX_RATE_HZ}]")]
    Rate(f64),
    #[error("cannot start the live view's runtime")]
    Runtime(#[source] std::io::Error),
    #[error("cannot serve the live view on {addr}")]
    Bind {
        addr: SocketAddr,
        #[source]
        source: foxglove::FoxgloveError,
    },
}

/// How often a channel's messages go out.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Every {
    /// One a period of the view's rate: a stream.
    Period,
    /// Each one: an event.
    Message,
}

struct LiveChannel {
    raw: Arc<RawChannel>,
    every: Every,
    /// The log time from which the next message is taken, ns.
    next_ns: u64,
}

/// A Foxglove WebSocket server and the channels it offers.
pub struct LiveView {
    context: Arc<Context>,
    server: Option<WebSocketServerHandle>,
    /// Kept for the server's lifetime; dropped after it stops.
    runtime: Option<tokio::runtime::Runtime>,
    /// By the recording's channel id.
    channels: Vec<Option<LiveChannel>>,
    period_ns: u64,
    addr: SocketAddr,
}

impl LiveView {
    /// Serves on `addr` (port 0: one the system picks, see [`Self::addr`]), the streams at
    /// `rate_hz`.
    pub fn start(addr: SocketAddr, rate_hz: f64) -> Result<Self, LiveError> {
        if !(rate_hz > 0.0 && rate_hz <= MAX_RATE_HZ) {
            return Err(LiveError::Rate(rate_hz));
        }
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("live-view")
            .enable_all()
            .build()
            .map_err(LiveError::Runtime)?;
        let context = Context::new();
        let server = WebSocketServer::new()
            .name("stepdrive")
            .bind(addr.ip().to_string(), addr.port())
            .context(&context)
            .tokio_runtime(runtime.handle())
            .start_blocking()
            .map_err(|source| LiveError::Bind { addr, source })?;
        let addr = SocketAddr::new(addr.ip(), server.port());
        Ok(Self {
            context,
            server: Some(server),
            runtime: Some(runtime),
            channels: Vec::new(),
            period_ns: (1e9 / rate_hz).round() as u64,
            addr,
        })
    }

    /// Where it serves (the port the system picked for port 0).
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Offers the recording's channel `id` as `topic`, JSON with `schema_name`'s schema.
    pub(crate) fn add_channel(
        &mut self,
        id: u16,
        topic: &str,
        schema_name: &str,
        schema: String,
        every: Every,
    ) {
        let built = ChannelBuilder::new(topic)
            .message_encoding("json")
            .schema(Schema::new(schema_name, "jsonschema", schema.into_bytes()))
            .context(&self.context)
            .build_raw();
        let raw = match built {
            Ok(raw) => raw,
            Err(e) => {
                tracing::warn!("the live view does not offer {topic}: {e}");
                return;
            }
        };
        let i = usize::from(id);
        if self.channels.len() <= i {
            self.channels.resize_with(i + 1, || None);
        }
        self.channels[i] = Some(LiveChannel {
            raw,
            every,
            next_ns: 0,
        });
    }

    /// Whether channel `id` takes a message logged at `ns`.
    pub(crate) fn due(&self, id: u16, ns: u64) -> bool {
        match self.channels.get(usize::from(id)) {
            Some(Some(c)) => c.every == Every::Message || ns >= c.next_ns,
            _ => false,
        }
    }

    /// The message `json` of channel `id` at log time `ns`, if the channel takes it.
    pub(crate) fn put(&mut self, id: u16, ns: u64, json: &[u8]) {
        if !self.due(id, ns) {
            return;
        }
        let period = self.period_ns;
        let Some(Some(c)) = self.channels.get_mut(usize::from(id)) else {
            return;
        };
        c.next_ns = ns.saturating_add(period);
        c.raw
            .log_with_meta(json, PartialMetadata { log_time: Some(ns) });
    }
}

impl Drop for LiveView {
    fn drop(&mut self) {
        if let Some(server) = self.server.take() {
            // Closes the clients' connections before the runtime goes.
            if let Some(rt) = self.runtime.as_ref() {
                rt.block_on(server.stop().wait());
            }
        }
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_background();
        }
    }
}
