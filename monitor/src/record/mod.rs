//! Seeing a run: MCAP recordings and their CSV export ([`recording`]), the paper's figures
//! drawn from a recording ([`plot`]), the live terminal scope ([`scope`]) and the live view
//! in Foxglove ([`live`]).

pub mod file;
pub mod live;
pub mod plot;
pub mod recording;
pub mod scope;
