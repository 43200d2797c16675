//! The axis over Zenoh: a client on another host talks to the `stepdrive gateway` on the
//! stack's host (docs/remote.md). The gateway answers commands with the local command
//! service's acknowledgements, publishes the axis's status at its rate, and forwards stream
//! points; the client holds a liveliness token, and when it goes away (its process ends,
//! or its link is silent for a lease) the gateway quick-stops the stream or jog it started
//! (the axis itself stops a jog its client stops renewing, and a stream whose points stop,
//! whatever the client declares: docs/remote.md).

use crate::ClientError;
use std::time::Duration;
use stepdrive_shared::axis::{AxisAck, AxisRequest, AxisStatus, AxisStreamPoint};
use stepdrive_shared::services::remote as keys;
use stepdrive_shared::wire::{self, Wire};
use zenoh::handlers::{FifoChannelHandler, RingChannel, RingChannelHandler};
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::query::{Querier, Reply};
use zenoh::sample::Sample;
use zenoh::Wait;

/// The link lease, both ends: a link silent this long is declared dead (and the client's
/// token with it). Zenoh's default is 10 s; shorter than ~2 s has given false expiries
/// under load (rmw_zenoh #734).
pub const LEASE: Duration = Duration::from_secs(3);

/// The lead of a stream sent over the network when the client names none, s: the status
/// the client paces by comes at the gateway's rate (100 Hz: 10 ms apart) and crosses the
/// link, and the client and the gateway are ordinary network processes that a drive host
/// can hold off for a while. Measured on two cores beside the 20 kHz loops (docs/remote.md):
/// points were held up to 270 ms; a 0.1 s lead ran dry in 4 of 4 runs (peaks 8.5e-3 …
/// 1.8e-2 rad, or quick-stopped), 0.5 s kept at least 238 ms in hand and every run within
/// 3.0e-5 rad.
pub const REMOTE_STREAM_LEAD_S: f64 = 0.5;

/// Which side of a link a session is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    /// Listens on the endpoint (the gateway, by default).
    Listen,
    /// Connects to the endpoint (a remote client; a gateway with `--connect`).
    Connect,
}

/// A Zenoh configuration for one endpoint (`tcp/HOST:PORT`): TCP only, no scouting (nothing
/// is sent to a multicast group or gossiped: the endpoint is the whole network), the
/// lease above. A client connects once and fails at once if nobody answers.
pub fn config(endpoint: &str, side: Side) -> Result<zenoh::Config, String> {
    if !endpoint.starts_with("tcp/") {
        return Err(format!(
            "endpoint {endpoint:?}: give tcp/HOST:PORT (TCP is the one transport built in)"
        ));
    }
    let mut c = zenoh::Config::default();
    let mut set = |key: &str, value: String| {
        c.insert_json5(key, &value)
            .map_err(|e| format!("zenoh setting {key} = {value}: {e}"))
    };
    let quoted = json5_string(endpoint);
    match side {
        Side::Listen => {
            set("mode", "\"peer\"".into())?;
            set("listen/endpoints", format!("[{quoted}]"))?;
        }
        Side::Connect => {
            set("mode", "\"client\"".into())?;
            set("connect/endpoints", format!("[{quoted}]"))?;
        }
    }
    set("scouting/multicast/enabled", "false".into())?;
    set("scouting/gossip/enabled", "false".into())?;
    set("transport/link/tx/lease", LEASE.as_millis().to_string())?;
    set("transport/link/tx/keep_alive", "4".into())?;
    Ok(c)
}

/// `s` as a JSON5 string literal.
fn json5_string(s: &str) -> String {
    let mut out = String::with_capacity(s.len() + 2);
    out.push('"');
    for ch in s.chars() {
        if ch == '"' || ch == '\\' {
            out.push('\\');
        }
        out.push(ch);
    }
    out.push('"');
    out
}

/// An encoding naming the message's type, so a reader can tell a stepdrive message from
/// anything else on the key.
pub fn encoding<T: Wire>() -> zenoh::bytes::Encoding {
    zenoh::bytes::Encoding::APPLICATION_OCTET_STREAM.with_schema(T::TYPE)
}

/// The message in a sample's payload.
pub fn decode<T: Wire>(payload: &zenoh::bytes::ZBytes) -> Result<T, wire::WrongSize> {
    wire::from_bytes(&payload.to_bytes())
}

fn remote_error(endpoint: &str, what: &str, e: impl std::fmt::Display) -> ClientError {
    ClientError::Remote {
        endpoint: endpoint.to_string(),
        message: format!("{what}: {e}"),
    }
}

/// An axis's link through a gateway.
pub(crate) struct RemoteLink {
    endpoint: String,
    instance: String,
    axis: u32,
    querier: Querier<'static>,
    status: Subscriber<RingChannelHandler<Sample>>,
    stream: Publisher<'static>,
    _token: LivelinessToken,
    // Dropped last: the declarations above belong to it.
    _session: zenoh::Session,
}

impl RemoteLink {
    pub(crate) fn open(
        endpoint: &str,
        instance: &str,
        axis: u32,
        client: u32,
    ) -> Result<Self, ClientError> {
        let err = |what: &str, e: &dyn std::fmt::Display| remote_error(endpoint, what, e);
        let config = config(endpoint, Side::Connect).map_err(|e| err("configuration", &e))?;
        let session = zenoh::open(config)
            .wait()
            .map_err(|e| err("no gateway answers there", &e))?;
        let key = |leaf| keys::axis_key(instance, axis, leaf);
        let querier = session
            .declare_querier(key(keys::COMMAND))
            .wait()
            .map_err(|e| err("command querier", &e))?;
        let status = session
            .declare_subscriber(key(keys::STATUS))
            .with(RingChannel::new(1))
            .wait()
            .map_err(|e| err("status subscriber", &e))?;
        let stream = session
            .declare_publisher(key(keys::STREAM))
            .encoding(encoding::<AxisStreamPoint>())
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .wait()
            .map_err(|e| err("stream publisher", &e))?;
        let token = session
            .liveliness()
            .declare_token(keys::client_token(instance, client))
            .wait()
            .map_err(|e| err("liveliness token", &e))?;
        Ok(Self {
            endpoint: endpoint.to_string(),
            instance: instance.to_string(),
            axis,
            querier,
            status,
            stream,
            _token: token,
            _session: session,
        })
    }

    pub(crate) fn endpoint(&self) -> &str {
        &self.endpoint
    }

    /// Sends `r` without waiting: the gateway's answer (the axis's ack) is the
    /// [`RemotePending`]'s to wait for.
    pub(crate) fn send(&mut self, r: &AxisRequest) -> Result<RemotePending, ClientError> {
        let replies: FifoChannelHandler<Reply> = self
            .querier
            .get()
            .payload(wire::bytes(r).to_vec())
            .encoding(encoding::<AxisRequest>())
            .wait()
            .map_err(|e| remote_error(&self.endpoint, "command", e))?;
        Ok(RemotePending {
            replies,
            endpoint: self.endpoint.clone(),
            instance: self.instance.clone(),
        })
    }

    /// The newest status the gateway published since the last call, if any.
    pub(crate) fn newest_status(&mut self) -> Result<Option<AxisStatus>, ClientError> {
        let Some(sample) = self
            .status
            .try_recv()
            .map_err(|e| remote_error(&self.endpoint, "status", e))?
        else {
            return Ok(None);
        };
        let s: AxisStatus =
            decode(sample.payload()).map_err(|e| remote_error(&self.endpoint, "a status", e))?;
        Ok((s.axis == self.axis).then_some(s))
    }

    pub(crate) fn publish_point(&mut self, p: &AxisStreamPoint) -> Result<(), ClientError> {
        self.stream
            .put(wire::bytes(p).to_vec())
            .wait()
            .map_err(|e| remote_error(&self.endpoint, "stream point", e))
    }
}

/// A request sent to the gateway and not yet answered ([`RemoteLink::send`]).
pub(crate) struct RemotePending {
    replies: FifoChannelHandler<Reply>,
    endpoint: String,
    instance: String,
}

impl RemotePending {
    /// Waits until `deadline` for the answer.
    pub(crate) fn wait(self, deadline: std::time::Instant) -> Result<AxisAck, ClientError> {
        let timeout = deadline.saturating_duration_since(std::time::Instant::now());
        let no_answer = || ClientError::Timeout {
            what: format!(
                "an answer from the gateway of instance `{}` at {}",
                self.instance, self.endpoint
            ),
            timeout,
        };
        let reply = self
            .replies
            .recv_timeout(timeout)
            .map_err(|_| no_answer())?
            .ok_or_else(no_answer)?;
        match reply.into_result() {
            Ok(sample) => decode::<AxisAck>(sample.payload())
                .map_err(|e| remote_error(&self.endpoint, "the gateway's answer", e)),
            Err(e) => {
                let text = e.payload().try_to_string().unwrap_or_default().into_owned();
                Err(remote_error(&self.endpoint, "the gateway refused", text))
            }
        }
    }
}
