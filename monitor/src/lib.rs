//! The operator's console, one folder per job (and [`assemble`]: the stack's nodes built
//! from its declaration, for processes and simulations alike):
//! - [`supervise`]: launches the stack's processes, supervises them, attaches to a running
//!   stack;
//! - [`report`]: the metrics, the timing, the outcome (exit codes and headlines), the table
//!   and JSON;
//! - [`record`]: MCAP recordings, CSV export, plots, the live scope;
//! - [`latency`]: latency sessions and their baselines;
//! - [`studies`]: in-process simulations, the robustness table, identification.

pub mod assemble;
pub mod latency;
pub mod record;
pub mod report;
pub mod studies;
pub mod supervise;
