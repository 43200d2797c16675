//! `stepdrive gateway`: the stack's axes on Zenoh, for clients on other hosts
//! (docs/remote.md). Not a loop of the stack: an ordinary process beside it that is a client
//! of the stack's iceoryx2 services on one side and a Zenoh peer on the other.
//!
//! - commands: a queryable on `stepdrive/<instance>/axis/*/command`; each query's
//!   [`AxisRequest`] goes to the local command service and its [`AxisAck`] comes back as
//!   the reply, so a remote command is validated and answered exactly as a local one. A
//!   client over its rate limit is refused (`TooMany`) here, without reaching the axis.
//! - status: each axis's newest [`AxisStatus`] on `stepdrive/<instance>/axis/<n>/status`
//!   at the gateway's rate (100 Hz by default).
//! - streams: points on `stepdrive/<instance>/axis/*/stream` go to the named axis's local
//!   stream topic.
//!
//! A multi-axis stack (docs/axes.md) is served whole: every axis its command, status and
//! stream keys, each to its own local services (the axis count from the stack's announced
//! scenario). A command or point for an axis the stack lacks is refused (`UnknownAxis`).
//! - leases: every remote client holds a liveliness token; when one goes (its session
//!   closed, or its link silent for [`LEASE`](crate::remote::LEASE)) and the axis is still
//!   in a stream or jog that client started, the gateway quick-stops the axis. That is the
//!   fast path for a client that ends; safety does not rest on it: the axis itself stops a
//!   jog its client stops renewing, and a stream whose points stop or never come, whatever
//!   a client declares.
//! - a request is a remote client's or none: its client id odd and at least 2³¹, and the
//!   top 32 bits of its sequence number (refused `BadClient` otherwise, so that no remote
//!   client speaks, or renews a jog, as a local one). A stream start that names no lead
//!   gets the remote one, [`REMOTE_STREAM_LEAD_S`](crate::remote::REMOTE_STREAM_LEAD_S).

use crate::remote::{self, decode, encoding, Side};
use std::collections::HashMap;
use std::time::{Duration, Instant};
use stepdrive_runtime::ipc::{CommandClient, IpcBus, IpcPublisher, IpcSubscriber};
use stepdrive_runtime::port::{PortError, PortFactory, Publish, Subscribe};
use stepdrive_shared::axis::{
    request_flags, AxisAck, AxisMode, AxisRequest, AxisState, AxisStatus, AxisStreamPoint, Refusal,
    RequestKind,
};
use stepdrive_shared::services::remote as keys;
use stepdrive_shared::wire;
use zenoh::sample::SampleKind;
use zenoh::Wait;

/// What the gateway does.
#[derive(Debug, Clone)]
pub struct GatewayOptions {
    pub instance: String,
    /// `tcp/HOST:PORT`.
    pub endpoint: String,
    pub side: Side,
    /// Status messages per second on Zenoh.
    pub status_hz: f64,
    /// Commands per second one remote client may send (a burst of a tenth of a second of
    /// them is let through at once).
    pub max_commands_hz: f64,
    /// How long to wait for the stack to come up.
    pub attach_timeout: Duration,
}

/// The gateway's counts, when it stops.
#[derive(Debug, Default, Clone, Copy, PartialEq, Eq)]
pub struct GatewaySummary {
    pub commands: u64,
    pub rate_limited: u64,
    pub malformed: u64,
    pub statuses: u64,
    pub points: u64,
    pub leases_lost: u64,
    pub quick_stops: u64,
}

#[derive(Debug, thiserror::Error)]
pub enum GatewayError {
    #[error("no stack on instance `{instance}` (waited {waited:?}): start it with `stepdrive serve --instance {instance}`")]
    NoStack {
        instance: String,
        waited: Duration,
        #[source]
        source: PortError,
    },
    #[error(transparent)]
    Port(#[from] PortError),
    #[error("zenoh at {endpoint}: {message}")]
    Zenoh { endpoint: String, message: String },
    #[error("the stack on instance `{instance}` published no status for {silent:?}: it stopped")]
    StackGone { instance: String, silent: Duration },
}

/// A token bucket per remote client.
struct Bucket {
    tokens: f64,
    at: Instant,
}

/// How long a forwarded command waits for the axis: under a remote client's own wait (2 s
/// by default), so the client hears why rather than a timeout.
const LOCAL_ANSWER: Duration = Duration::from_secs(1);

/// The gateway's own client id (the top of its sequence numbers), an even number above any
/// pid: never a remote client's (odd) nor a local one's.
const GATEWAY_CLIENT: u32 = 0xfffe_0000;

/// Runs the gateway until SIGINT/SIGTERM or the stack stops.
pub fn run(o: &GatewayOptions) -> Result<GatewaySummary, GatewayError> {
    if !(o.status_hz.is_finite() && o.status_hz > 0.0) {
        return Err(GatewayError::Zenoh {
            endpoint: o.endpoint.clone(),
            message: format!("a status rate of {} Hz", o.status_hz),
        });
    }
    let no_stack = |source| GatewayError::NoStack {
        instance: o.instance.clone(),
        waited: o.attach_timeout,
        source,
    };
    let mut bus = IpcBus::attach(&o.instance, "gateway", o.attach_timeout).map_err(no_stack)?;
    let count = axis_count(&bus, o.attach_timeout);
    let mut locals = Vec::with_capacity(count);
    for axis in 0..count as u32 {
        bus.set_axis(axis);
        locals.push(Local {
            commands: bus.command_client().map_err(no_stack)?,
            status_in: bus.subscriber_of::<AxisStatus>(16)?,
            points_out: bus.publisher_of::<AxisStreamPoint>()?,
            newest: None,
            commanded_by: None,
        });
    }
    bus.set_axis(0);

    let zerr = |what: &str, e: &dyn std::fmt::Display| GatewayError::Zenoh {
        endpoint: o.endpoint.clone(),
        message: format!("{what}: {e}"),
    };
    // The answer to a command's query: the axis's acknowledgement.
    let reply_ack = |query: &zenoh::query::Query, ack: &AxisAck| {
        query
            .reply(query.key_expr().clone(), wire::bytes(ack).to_vec())
            .encoding(encoding::<AxisAck>())
            .wait()
            .map_err(|e| zerr("command reply", &e))
    };
    let config = remote::config(&o.endpoint, o.side).map_err(|e| zerr("configuration", &e))?;
    let session = zenoh::open(config)
        .wait()
        .map_err(|e| zerr("cannot open the session", &e))?;
    let any_axis = |leaf| keys::any_axis_key(&o.instance, leaf);
    let queries = session
        .declare_queryable(any_axis(keys::COMMAND))
        .wait()
        .map_err(|e| zerr("command queryable", &e))?;
    let points_in = session
        .declare_subscriber(any_axis(keys::STREAM))
        .wait()
        .map_err(|e| zerr("stream subscriber", &e))?;
    let status_out = (0..count as u32)
        .map(|axis| {
            session
                .declare_publisher(keys::axis_key(&o.instance, axis, keys::STATUS))
                .encoding(encoding::<AxisStatus>())
                .wait()
                .map_err(|e| zerr("status publisher", &e))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let leases = session
        .liveliness()
        .declare_subscriber(keys::client_tokens(&o.instance))
        .history(true)
        .wait()
        .map_err(|e| zerr("liveliness subscriber", &e))?;
    tracing::info!(
        "gateway for instance `{}` ({count} axis(es)) on {} ({}): commands, status at {} Hz, \
         streams, leases of {:?}",
        o.instance,
        o.endpoint,
        match o.side {
            Side::Listen => "listening",
            Side::Connect => "connected",
        },
        o.status_hz,
        remote::LEASE
    );

    let mut sum = GatewaySummary::default();
    let mut buckets: HashMap<u32, Bucket> = HashMap::new();
    let burst = (o.max_commands_hz / 10.0).max(1.0);
    let status_period = Duration::from_secs_f64(1.0 / o.status_hz);
    let mut next_status = Instant::now();
    let mut last_status_at = Instant::now();
    let mut own_seq = u64::from(GATEWAY_CLIENT) << 32;
    let silent_limit = Duration::from_secs(5);
    // Coordinated parts forwarded and not yet answered, with when each went.
    let mut parts = Vec::new();

    while !stepdrive_runtime::poll::termination_requested() {
        let mut idle = true;
        for local in &mut locals {
            while let Some(s) = local.status_in.newest()? {
                local.newest = Some(s);
                last_status_at = Instant::now();
            }
        }
        // Before the first status the stack is still starting: it has the attach time.
        let limit = if locals.iter().any(|l| l.newest.is_some()) {
            silent_limit
        } else {
            silent_limit.max(o.attach_timeout)
        };
        if last_status_at.elapsed() > limit {
            return Err(GatewayError::StackGone {
                instance: o.instance.clone(),
                silent: limit,
            });
        }
        let now = Instant::now();
        if now >= next_status {
            for (local, out) in locals.iter().zip(&status_out) {
                if let Some(s) = local.newest {
                    out.put(wire::bytes(&s).to_vec())
                        .wait()
                        .map_err(|e| zerr("status", &e))?;
                    sum.statuses += 1;
                }
            }
            // Paced from the schedule, not from now: the rate holds on average.
            next_status += status_period;
            if next_status < now {
                next_status = now + status_period;
            }
        }

        while let Ok(Some(query)) = queries.try_recv() {
            idle = false;
            let Some(payload) = query.payload() else {
                sum.malformed += 1;
                let _ = query
                    .reply_err("no payload: an AxisRequest was expected")
                    .wait();
                continue;
            };
            let request: AxisRequest = match decode(payload) {
                Ok(r) => r,
                Err(e) => {
                    sum.malformed += 1;
                    let _ = query.reply_err(e.to_string()).wait();
                    continue;
                }
            };
            let limited = over_rate(
                &mut buckets,
                request.client,
                (o.max_commands_hz, burst),
                Instant::now(),
            );
            let keyed = keys::axis_of_key(query.key_expr().as_str());
            let local = keyed.and_then(|n| locals.get_mut(n as usize));
            let state = local.as_ref().and_then(|l| l.newest).map_or(0, |s| s.state);
            let refused =
                refused_here(&request, keyed, limited, o.max_commands_hz, state).or_else(|| {
                    local
                        .is_none()
                        .then(|| unknown_axis(&request, count, state))
                });
            let ack = if let Some(ack) = refused {
                match ack.refusal == Refusal::TooMany as u32 {
                    true => sum.rate_limited += 1,
                    false => sum.malformed += 1,
                }
                ack
            } else if let Some(local) = local {
                sum.commands += 1;
                let mut r = with_remote_lead(request);
                r.publish_time_ns = stepdrive_runtime::clock::monotonic_ns();
                if r.flags & request_flags::COORDINATED != 0 {
                    // A coordinated part is answered once its partners, later queries,
                    // have come: it must not hold them up.
                    match local.commands.send(&r) {
                        Ok(pending) => parts.push((query, pending, Instant::now())),
                        Err(e) => {
                            let _ = query.reply_err(e.to_string()).wait();
                        }
                    }
                    continue;
                }
                match local.commands.request(&r, LOCAL_ANSWER) {
                    Ok(ack) => {
                        if ack.taken() && r.kind != RequestKind::Status as u32 {
                            local.commanded_by = Some(r.client);
                        }
                        ack
                    }
                    Err(e) => {
                        // The stack starting or stalled: this command fails, the gateway
                        // goes on (a stack that stopped shows as a silent status below).
                        let _ = query.reply_err(e.to_string()).wait();
                        continue;
                    }
                }
            } else {
                unreachable!("a request for an axis the stack lacks is refused above")
            };
            reply_ack(&query, &ack)?;
        }

        let mut k = 0;
        while k < parts.len() {
            let (_, pending, sent) = &parts[k];
            let reply = match pending.answer() {
                Ok(Some(ack)) => Ok(ack),
                Ok(None) if sent.elapsed() < LOCAL_ANSWER => {
                    k += 1;
                    continue;
                }
                Ok(None) => Err(pending.unanswered(LOCAL_ANSWER).to_string()),
                Err(e) => Err(e.to_string()),
            };
            let (query, _, _) = parts.swap_remove(k);
            idle = false;
            match reply {
                Ok(ack) => reply_ack(&query, &ack)?,
                Err(text) => {
                    let _ = query.reply_err(text).wait();
                }
            }
        }

        while let Ok(Some(sample)) = points_in.try_recv() {
            idle = false;
            match decode::<AxisStreamPoint>(sample.payload()) {
                Ok(p) if keys::axis_of_key(sample.key_expr().as_str()) != Some(p.axis) => {
                    sum.malformed += 1;
                    tracing::warn!(
                        "a stream point for axis {} on {}: dropped",
                        p.axis,
                        sample.key_expr()
                    );
                }
                Ok(mut p) => {
                    let Some(local) = locals.get_mut(p.axis as usize) else {
                        sum.malformed += 1;
                        tracing::warn!(
                            "a stream point for axis {} of a stack of {count}: dropped",
                            p.axis
                        );
                        continue;
                    };
                    // The stack's clock, for recorders: the client's is another host's.
                    p.publish_time_ns = stepdrive_runtime::clock::monotonic_ns();
                    local.points_out.publish(&p)?;
                    sum.points += 1;
                }
                Err(e) => {
                    sum.malformed += 1;
                    tracing::warn!("a stream point from {}: {e}", sample.key_expr());
                }
            }
        }

        while let Ok(Some(sample)) = leases.try_recv() {
            idle = false;
            let Some(client) = keys::client_of_token(sample.key_expr().as_str()) else {
                continue;
            };
            match sample.kind() {
                SampleKind::Put => tracing::info!("remote client {client} connected"),
                SampleKind::Delete => {
                    sum.leases_lost += 1;
                    buckets.remove(&client);
                    // Every axis still in a stream or jog the client started stops: told by
                    // the newest status, unless a later command of another client was taken.
                    let mut stopped = false;
                    for local in &mut locals {
                        while let Some(s) = local.status_in.newest()? {
                            local.newest = Some(s);
                        }
                        let Some(s) = local
                            .newest
                            .filter(|s| started_motion(s, client))
                            .filter(|_| local.commanded_by.is_none_or(|c| c == client))
                        else {
                            continue;
                        };
                        own_seq += 1;
                        let stop = AxisRequest {
                            axis: s.axis,
                            kind: RequestKind::QuickStop as u32,
                            seq: own_seq,
                            client: GATEWAY_CLIENT,
                            publish_time_ns: stepdrive_runtime::clock::monotonic_ns(),
                            ..Default::default()
                        };
                        let ack = local.commands.request(&stop, LOCAL_ANSWER)?;
                        sum.quick_stops += 1;
                        stopped = true;
                        tracing::warn!(
                            "remote client {client} went away (session closed or lease of {:?} \
                             expired) while its {} of axis {} ran: quick stop {}",
                            remote::LEASE,
                            AxisMode::from_u32(s.mode).map_or("motion", |m| m.name()),
                            s.axis,
                            if ack.taken() { "taken" } else { ack.text() }
                        );
                    }
                    if !stopped {
                        tracing::info!("remote client {client} went away");
                    }
                }
            }
        }
        if idle {
            std::thread::sleep(Duration::from_micros(200));
        }
    }
    drop(session);
    Ok(sum)
}

/// One axis's local side: its command client, status subscriber and stream publisher, and
/// its newest status.
struct Local {
    commands: CommandClient,
    status_in: IpcSubscriber<AxisStatus>,
    points_out: IpcPublisher<AxisStreamPoint>,
    newest: Option<AxisStatus>,
    /// The client of the newest remote command (a status request aside) this gateway saw
    /// the axis take: a lease lost after another client took the axis over stops nothing,
    /// even when the newest status still names the old one (statuses lag a command).
    commanded_by: Option<u32>,
}

/// The stack's axis count, from the scenario it announces (a gateway started with its
/// stack waits up to `wait` for the announcement; 1, with a warning, if none comes or it
/// does not parse: axis 0 is served all the same).
fn axis_count(bus: &IpcBus, wait: Duration) -> usize {
    let deadline = Instant::now() + wait;
    loop {
        match bus.announced_scenario() {
            Ok(Some(s)) => return s.axis_count(),
            Ok(None) => {}
            Err(e) => {
                tracing::warn!("{e}: axis 0 only");
                return 1;
            }
        }
        if Instant::now() >= deadline || stepdrive_runtime::poll::termination_requested() {
            tracing::warn!("the stack announced no scenario within {wait:?}: axis 0 only");
            return 1;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// The refusal of a request for an axis the stack lacks (`state`: for the answer).
fn unknown_axis(request: &AxisRequest, count: usize, state: u32) -> AxisAck {
    let mut ack = AxisAck {
        request: *request,
        refusal: Refusal::UnknownAxis as u32,
        state,
        ..Default::default()
    };
    ack.set_text(&format!(
        "the stack has {count} axis(es), 0..={}: there is no axis {}",
        count - 1,
        request.axis
    ));
    ack
}

/// Whether the axis is still in a stream or jog that `client`'s last command started: what
/// a client that went away leaves running. (A move ends by itself.)
fn started_motion(s: &AxisStatus, client: u32) -> bool {
    let mode = AxisMode::from_u32(s.mode);
    (s.last_seq >> 32) as u32 == client
        && s.axis_state() == Some(AxisState::OperationEnabled)
        && matches!(
            mode,
            Some(AxisMode::CyclicPosition | AxisMode::ProfileVelocity)
        )
}

/// A remote stream start that names no lead gets the remote one: points cross a network
/// and two processes the drive's host may hold off (docs/remote.md), and a client that
/// left the lead to the axis would get the local 50 ms and run dry.
fn with_remote_lead(mut r: AxisRequest) -> AxisRequest {
    if r.kind == RequestKind::StreamStart as u32 && r.flags & request_flags::HAS_LEAD == 0 {
        r.lead_s = remote::REMOTE_STREAM_LEAD_S;
        r.flags |= request_flags::HAS_LEAD;
    }
    r
}

/// Takes a token from `client`'s bucket at `now` (refilled at `rate`/s up to `burst`);
/// whether it was empty.
fn over_rate(
    buckets: &mut HashMap<u32, Bucket>,
    client: u32,
    (rate, burst): (f64, f64),
    now: Instant,
) -> bool {
    let b = buckets.entry(client).or_insert(Bucket {
        tokens: burst,
        at: now,
    });
    b.tokens = (b.tokens + rate * now.duration_since(b.at).as_secs_f64()).min(burst);
    b.at = now;
    if b.tokens < 1.0 {
        return true;
    }
    b.tokens -= 1.0;
    false
}

/// The gateway's own refusal of a request that came on the key naming axis `keyed`, if
/// any: a request for another axis than its key names (it must never reach another one),
/// or one over the client's rate (`limited`). `state` is the axis's, for the answer.
fn refused_here(
    request: &AxisRequest,
    keyed: Option<u32>,
    limited: bool,
    max_commands_hz: f64,
    state: u32,
) -> Option<AxisAck> {
    let (refusal, text) = if !request.from_remote_client() {
        (
            Refusal::BadClient,
            format!(
                "client id {:#x} with sequence number {:#x}: a remote client's id is odd, at least 2^31, and the top 32 bits of its sequence numbers",
                request.client, request.seq
            ),
        )
    } else if keyed != Some(request.axis) {
        (
            Refusal::UnknownAxis,
            format!(
                "the key names axis {} but the request axis {}",
                keyed.map_or("?".to_string(), |a| a.to_string()),
                request.axis
            ),
        )
    } else if limited {
        (
            Refusal::TooMany,
            format!(
                "over the gateway's limit of {max_commands_hz} commands/s for one remote client"
            ),
        )
    } else {
        return None;
    };
    let mut ack = AxisAck {
        request: *request,
        refusal: refusal as u32,
        state,
        ..Default::default()
    };
    ack.set_text(&text);
    Some(ack)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_client_over_its_rate_is_limited_after_its_burst() {
        let mut buckets = HashMap::new();
        let limits = (100.0, 10.0);
        let t0 = Instant::now();
        // 50 at once: the burst of 10 passes.
        let limited = (0..50)
            .filter(|_| over_rate(&mut buckets, 7, limits, t0))
            .count();
        assert_eq!(limited, 40);
        // Another client has its own bucket.
        assert!(!over_rate(&mut buckets, 8, limits, t0));
        // 50 ms later at 100/s: 5 more, and never more than the burst after a long pause.
        let t1 = t0 + Duration::from_millis(50);
        let passed = (0..20)
            .filter(|_| !over_rate(&mut buckets, 7, limits, t1))
            .count();
        assert_eq!(passed, 5);
        let t2 = t1 + Duration::from_secs(60);
        let passed = (0..20)
            .filter(|_| !over_rate(&mut buckets, 7, limits, t2))
            .count();
        assert_eq!(passed, 10);
    }

    #[test]
    fn only_a_stream_or_jog_the_client_started_is_left_running() {
        let client = 0x8000_1235;
        let mut s = AxisStatus {
            state: AxisState::OperationEnabled as u32,
            mode: AxisMode::CyclicPosition as u32,
            last_seq: (u64::from(client) << 32) + 9,
            ..Default::default()
        };
        assert!(started_motion(&s, client));
        assert!(!started_motion(&s, client + 2));
        s.mode = AxisMode::ProfileVelocity as u32;
        assert!(started_motion(&s, client));
        s.mode = AxisMode::ProfilePosition as u32;
        assert!(!started_motion(&s, client));
        s.mode = AxisMode::CyclicPosition as u32;
        s.state = AxisState::QuickStopActive as u32;
        assert!(!started_motion(&s, client));
    }

    /// A request whose key names another axis is refused there, whatever its rate; one
    /// over the rate is refused `too many`; others go on to the stack.
    #[test]
    fn a_request_for_another_axis_than_its_key_names_is_refused() {
        let client = 0x8000_1235u32;
        let request = AxisRequest {
            axis: 0,
            client,
            seq: (u64::from(client) << 32) + 1,
            ..Default::default()
        };
        let ack = refused_here(&request, Some(3), false, 500.0, 7).expect("refused");
        assert_eq!(ack.refusal, Refusal::UnknownAxis as u32);
        assert_eq!(ack.state, 7);
        assert!(ack
            .text()
            .contains("key names axis 3 but the request axis 0"));
        let ack = refused_here(&request, None, true, 500.0, 7).expect("refused");
        assert_eq!(ack.refusal, Refusal::UnknownAxis as u32);
        let ack = refused_here(&request, Some(0), true, 500.0, 7).expect("refused");
        assert_eq!(ack.refusal, Refusal::TooMany as u32);
        assert!(ack.text().contains("500 commands/s"));
        assert!(refused_here(&request, Some(0), false, 500.0, 7).is_none());
    }

    /// A local client's id (a pid), the gateway's own, or an id its sequence numbers do not
    /// carry are refused before anything else: no remote client speaks as another.
    #[test]
    fn a_request_that_is_not_a_remote_clients_is_refused() {
        let remote = 0x8000_1235u32;
        for (client, seq_top) in [
            (4242u32, 4242u32),
            (GATEWAY_CLIENT, GATEWAY_CLIENT),
            (remote, remote + 2),
            (0x8000_1234, 0x8000_1234),
            (0, 0),
        ] {
            let request = AxisRequest {
                client,
                seq: (u64::from(seq_top) << 32) + 1,
                ..Default::default()
            };
            let ack = refused_here(&request, Some(0), false, 500.0, 7).expect("refused");
            assert_eq!(ack.refusal, Refusal::BadClient as u32, "{client:#x}");
        }
    }

    /// A remote stream start without a lead gets the remote one; one with a lead keeps it;
    /// other requests pass unchanged.
    #[test]
    fn a_remote_stream_without_a_lead_gets_the_remote_lead() {
        let start = AxisRequest {
            kind: RequestKind::StreamStart as u32,
            ..Default::default()
        };
        let r = with_remote_lead(start);
        assert_eq!(r.lead_s, remote::REMOTE_STREAM_LEAD_S);
        assert!(r.flags & request_flags::HAS_LEAD != 0);
        let own = AxisRequest {
            lead_s: 0.2,
            flags: request_flags::HAS_LEAD,
            ..start
        };
        assert_eq!(with_remote_lead(own), own);
        let jog = AxisRequest {
            kind: RequestKind::Jog as u32,
            ..Default::default()
        };
        assert_eq!(with_remote_lead(jog), jog);
    }

    /// What the gateway declares matches the key every client names, for any axis and
    /// leaf, and no other instance's.
    #[test]
    fn the_gateways_keys_match_the_clients_of_its_instance_only() {
        use zenoh::key_expr::KeyExpr;
        let key = |k: String| KeyExpr::new(k).expect("a valid key expression");
        for leaf in [keys::COMMAND, keys::STREAM, keys::STATUS] {
            let served = key(keys::any_axis_key("cell-1", leaf));
            for axis in [0, 1, 7] {
                assert!(served.intersects(&key(keys::axis_key("cell-1", axis, leaf))));
                let named = keys::axis_key("cell-1", axis, leaf);
                assert_eq!(keys::axis_of_key(&named), Some(axis));
                assert!(!served.intersects(&key(keys::axis_key("cell-2", axis, leaf))));
            }
            assert!(!served.intersects(&key(keys::client_token("cell-1", 3))));
            assert_eq!(keys::axis_of_key(&keys::client_token("cell-1", 3)), None);
            assert_eq!(keys::axis_of_key("stepdrive/cell-1/axis/x/command"), None);
        }
    }
}
