//! The errors of a run: one variant per cause, the source kept.

use crate::node::Role;
use crate::port::{BoxedError, PortError};
use crate::rt::RtError;
use std::time::Duration;

#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// SIGINT or SIGTERM: the one "terminated" every process and the launcher share.
    #[error("terminated by signal")]
    Terminated,
    #[error("the {role} could not start within {timeout:?}: still waiting for {awaiting}")]
    Startup {
        role: Role,
        awaiting: String,
        timeout: Duration,
    },
    #[error("the {role} heard nothing for {timeout:?}: {awaiting} has gone silent")]
    PeerSilent {
        role: Role,
        awaiting: String,
        timeout: Duration,
    },
    #[error("the simulated stack cannot go on: {0}")]
    Deadlock(String),
    #[error(transparent)]
    Port(#[from] PortError),
    #[error(transparent)]
    Rt(#[from] RtError),
    /// A node's own failure (a protocol violation, a drive's refusal, ...).
    #[error("the {role} failed")]
    Node {
        role: Role,
        #[source]
        source: BoxedError,
    },
}

impl RunError {
    /// Wraps a node's own typed error.
    pub fn node(role: Role, source: impl std::error::Error + Send + Sync + 'static) -> Self {
        RunError::Node {
            role,
            source: Box::new(source),
        }
    }
}
