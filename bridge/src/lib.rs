//! The bridge: the plant's place in the stack taken by a drive speaking
//! `docs/drive-protocol.md`. [`link`] converts frames to SI and back (units and calibration
//! live there and only there), [`observer`] estimates velocity from the encoder, [`core`] holds
//! the bridge's rules as a pure state machine, and [`node`] runs it in the stack over UDP or a
//! serial line.

pub mod core;
pub mod link;
pub mod node;
pub mod observer;

pub use node::{BridgeNode, BridgePorts, BridgeSettings, DriveAddr};
