//! Seeing a run: MCAP recordings and their CSV export ([`recording`]), the paper's figures
//! drawn from a recording ([`plot`]), and the live terminal scope ([`scope`]).

pub mod plot;
pub mod recording;
pub mod scope;
