//! The CLI's integration tests, as one test binary: each file beside this one is a module
//! of it, so the release test build compiles and links these tests once instead of once per
//! file (docs/measurements.md, "Building it"). `cargo test --release --test stack axis::`
//! runs one file's tests, `cargo test --release --test stack NAME` one test.
//!
//! Tests that start a whole stack take turns through [`common::one_stack_at_a_time`], now
//! across all the files (before, each file was its own process and the files ran one after
//! the other). A test's instance name and temporary directory carry this process's id and
//! a name no other test's starts with.

// What the tests share: the binary, temporary files, instance names, processes, results.
mod common;

// The axis through processes: `serve`, and `stepdrive axis` from other processes.
mod axis;
// Issue 44 on a served axis: nothing moves unasked, everything stops when its client does.
mod axis_safety;
// The drive protocol's conformance cases (docs/drive-protocol.md §9), played against the
// emulated drive's core and the bridge's link.
mod conformance;
// End-to-end runs: the real `stepdrive` binary, its processes talking through iceoryx2.
mod end_to_end;
// The drive firmware in QEMU over the wire (ignored unless asked for: it must be built).
mod firmware;
// A plant that is not the model through the processes; the robustness command's document.
mod real_motors;
// A run recorded, read back, drawn and exported; recordings cut short are finished.
mod recording;
// Faults, failures and bad input: every way a run can go wrong, and what it must say.
mod reliability;
// The axis from another network namespace, through the Zenoh gateway.
mod remote;
// Reliability, round 3: one test per finding of that issue.
mod round3;
// A stack that stops, or loses a process, stops the motor first (issue 44, items 4 and 5).
mod standstill;
// The stack against a drive written from docs/drive-protocol.md alone.
mod stranger_drive;
// Figures from the stack's timeline: reports and recordings that do not depend on the
// order the monitor met the stack's messages in.
mod timeline;
