//! `stepdrive emulate-drive`: a stand-in driver board. The drive's logic is
//! `stepdrive-drive-core`'s [`DriveCore`] (the one copy a firmware runs too), its power
//! stage the motor model of eq. (1) in drive units (encoder counts, ADC counts, duties:
//! [`stage`]); it runs on the stack's runner on its own sample clock ([`node`]), with fault
//! injection for tests as a type of its own ([`inject`]).

pub mod inject;
pub mod node;
pub mod stage;
pub mod truth;

pub use inject::{AlignFault, FaultInjection, Injector};
pub use stepdrive_drive_core::{DriveCore, DriveCounters, Limits, Reply};

use std::net::SocketAddr;
use std::time::Duration;
use stepdrive_drive_protocol::transport::Wire;
use stepdrive_drive_protocol::units::default_config;
use stepdrive_drive_protocol::MAX_PLAN_ENTRIES;
use stepdrive_runtime::pacer::WaitStrategy;
use stepdrive_runtime::rt::RtOptions;
use stepdrive_runtime::runner::{Runner, Settings};
use stepdrive_runtime::RunError;
use stepdrive_shared::Scenario;

/// The emulated board: the drive core (every rule of the drive's side of the protocol)
/// over the simulated power stage (the motor model), with the fault injection's hooks; the
/// emulated firmware runs the same one.
pub use stepdrive_drive_core::simulated::SimulatedDrive as EmulatedDrive;

/// The emulated board for `s`: its rate, the default scaling, the scenario's `[plant]`
/// motor and load; `plan_capacity`: PLAN entries kept (0: PLAN frames are not wanted, and
/// dropped). Its ALIGN is set for the nominal motor's winding (`[motor]`), as a drive is
/// configured for the motor it is sold with.
pub fn emulated_drive(s: &Scenario, watchdog_periods: u16, plan_capacity: u16) -> EmulatedDrive {
    let capacity = plan_capacity.min(MAX_PLAN_ENTRIES as u16);
    let config = default_config(s.rates.current_loop_hz, watchdog_periods, capacity);
    EmulatedDrive::new(config, stage::params(s), s.motor.resistance_ohm)
}

#[derive(Debug, Clone)]
pub struct EmulatorOptions {
    /// UDP address to listen on, one per axis of the scenario (a multi-axis scenario's
    /// drives are one process, a drive per address); ignored when `serial` is given.
    pub listen: Vec<SocketAddr>,
    /// The axis whose drive the fault injection acts on (the others run clean).
    pub inject_axis: usize,
    /// Serial line (UART or pseudo-terminal) to use instead of UDP.
    pub serial: Option<std::path::PathBuf>,
    pub scenario: Scenario,
    pub wait: WaitStrategy,
    pub rt: RtOptions,
    pub watchdog_periods: u16,
    /// PLAN entries the drive keeps (announced in CONFIG; 0: none).
    pub plan_capacity: u16,
    /// ALIGN current, mA, and time, ms (0 ms: no alignment).
    pub align_ma: u16,
    pub align_ms: u16,
    pub inject: FaultInjection,
    /// Stop after this long (None: until SIGTERM/SIGINT).
    pub duration: Option<Duration>,
    /// Write the rotor's true state of every sample of a run to this CSV file.
    pub truth: Option<std::path::PathBuf>,
}

#[derive(Debug, thiserror::Error)]
pub enum EmulatorError {
    #[error("cannot open the drive's {what}")]
    Open {
        what: String,
        #[source]
        source: std::io::Error,
    },
    #[error(transparent)]
    Rt(#[from] stepdrive_runtime::rt::RtError),
    #[error(transparent)]
    Run(stepdrive_runtime::RunError),
    #[error("the scenario has {axes} axes and {given} drive addresses were given (--listen A,B,...: one per axis{serial})")]
    Axes {
        axes: usize,
        given: usize,
        serial: &'static str,
    },
    #[error("cannot write the truth file {path}")]
    Truth {
        path: std::path::PathBuf,
        #[source]
        source: std::io::Error,
    },
}

pub fn run_emulator(o: &EmulatorOptions) -> Result<(), EmulatorError> {
    let axes = o.scenario.axis_count();
    if axes > 1 || o.listen.len() != 1 {
        return run_emulators(o);
    }
    let wire = match &o.serial {
        Some(path) => Wire::open_serial(path).map_err(|source| EmulatorError::Open {
            what: format!("serial line {}", path.display()),
            source,
        })?,
        None => Wire::bind_udp(o.listen[0]).map_err(|source| EmulatorError::Open {
            what: format!("UDP socket on {}", o.listen[0]),
            source,
        })?,
    };
    let truth = match &o.truth {
        Some(p) => Some(
            truth::TruthWriter::create(p).map_err(|source| EmulatorError::Truth {
                path: p.clone(),
                source,
            })?,
        ),
        None => None,
    };
    o.rt.apply()?;
    let mut core = emulated_drive(&o.scenario, o.watchdog_periods, o.plan_capacity);
    core.set_alignment(o.align_ma, o.align_ms);
    o.inject.align.apply(&mut core);
    tracing::info!(listen = %o.listen[0], serial = ?o.serial, "emulated drive up; waiting for HELLO");
    let node = node::DriveNode::new(&o.scenario, core, Injector::new(o.inject.clone()), truth)
        .lasting(o.duration);
    run_drive(node, wire, o.wait)
}

/// A drive on the runner until it is switched off.
fn run_drive<N: stepdrive_runtime::Node>(
    node: N,
    ports: N::Ports,
    wait: WaitStrategy,
) -> Result<(), EmulatorError> {
    // A drive has no peer to time out: it waits for a host as long as it runs.
    let forever = Duration::from_secs(1_000_000_000);
    let settings = Settings {
        wait,
        startup_timeout: forever,
        peer_timeout: forever,
        account_host_holds: false,
        linger: Duration::ZERO,
        report_end: true,
    };
    match Runner::new(node, ports, settings, None).run() {
        // SIGINT/SIGTERM is how a drive is switched off.
        Ok(_) | Err(RunError::Terminated) => Ok(()),
        Err(e) => Err(EmulatorError::Run(e)),
    }
}

/// A multi-axis scenario's drives in one process: a drive per axis, each its own UDP
/// address, session, clock and motor (its axis's scenario), stepped on one deadline grid
/// (`stepdrive_runtime::lanes`); the truth is axis 0's, the fault injection
/// `inject_axis`'s.
fn run_emulators(o: &EmulatorOptions) -> Result<(), EmulatorError> {
    let axes = o.scenario.axis_count();
    if o.listen.len() != axes || o.serial.is_some() {
        return Err(EmulatorError::Axes {
            axes,
            given: if o.serial.is_some() {
                0
            } else {
                o.listen.len()
            },
            serial: if o.serial.is_some() {
                "; a serial line is one drive"
            } else {
                ""
            },
        });
    }
    o.rt.apply()?;
    let (mut nodes, mut wires) = (Vec::with_capacity(axes), Vec::with_capacity(axes));
    for (axis, &listen) in o.listen.iter().enumerate() {
        let Some(s) = o.scenario.for_axis(axis) else {
            unreachable!("axis {axis} is below the axis count")
        };
        wires.push(
            Wire::bind_udp(listen).map_err(|source| EmulatorError::Open {
                what: format!("UDP socket on {listen} (axis {axis})"),
                source,
            })?,
        );
        let truth = match (&o.truth, axis) {
            (Some(p), 0) => {
                Some(
                    truth::TruthWriter::create(p).map_err(|source| EmulatorError::Truth {
                        path: p.clone(),
                        source,
                    })?,
                )
            }
            _ => None,
        };
        let mut core = emulated_drive(s, o.watchdog_periods, o.plan_capacity);
        core.set_alignment(o.align_ma, o.align_ms);
        let inject = if axis == o.inject_axis {
            o.inject.align.apply(&mut core);
            o.inject.clone()
        } else {
            FaultInjection::default()
        };
        nodes.push(node::DriveNode::new(s, core, Injector::new(inject), truth).lasting(o.duration));
    }
    tracing::info!(listen = ?o.listen, "emulated drives up, one per axis; waiting for HELLO");
    run_drive(
        stepdrive_runtime::lanes::Lanes::new(nodes, false),
        wires,
        o.wait,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use stepdrive_drive_protocol::{faults, frame_bytes, status, Action, Command, Message, Plan};

    /// A drive a host has said HELLO to (frame seq 0).
    fn in_session(mut d: EmulatedDrive) -> EmulatedDrive {
        assert!(matches!(
            d.on_frame(&frame_bytes(0, Message::Hello)),
            Some(Reply::Config(_))
        ));
        d
    }

    fn cmd(answers: u32, d: i16) -> Message {
        Message::Command(Command {
            answers_sample: answers,
            duty_a: d,
            duty_b: d,
        })
    }

    #[test]
    fn corrupt_stale_and_late_frames_are_never_applied() {
        let mut d = emulated_drive(&Scenario::default(), 20, 8);
        assert!(matches!(
            d.on_frame(&frame_bytes(1, Message::Hello)),
            Some(Reply::Config(_))
        ));
        d.on_frame(&frame_bytes(2, Message::Control(Action::Enable)));
        let _ = d.sample_frame(0);
        d.run_period(0);
        // A corrupted command: counted, not applied.
        let mut bad = frame_bytes(3, cmd(0, 1000));
        bad[20] ^= 1;
        assert!(d.on_frame(&bad).is_none());
        assert_eq!(d.counters.crc_errors, 1);
        d.run_period(1);
        assert_eq!(d.counters.commands_applied, 0);
        // A good one for sample 1, applied in the period after sample 2.
        d.on_frame(&frame_bytes(4, cmd(1, 2000)));
        // The same frame again (duplicate) and an older one (out of order): dropped.
        d.on_frame(&frame_bytes(4, cmd(1, 9000)));
        d.on_frame(&frame_bytes(3, cmd(1, 9000)));
        assert_eq!(d.counters.stale_frames, 2);
        d.run_period(2);
        assert_eq!(d.counters.commands_applied, 1);
        let Message::Sample(s) = d.sample_frame(0).message else {
            panic!()
        };
        assert_eq!((s.duty_a, s.applied_command_seq), (2000, 4));
        // A command that answers an old sample arrives late: held, not applied.
        d.on_frame(&frame_bytes(5, cmd(1, 3000)));
        d.run_period(3);
        let Message::Sample(s) = d.sample_frame(0).message else {
            panic!()
        };
        assert_eq!(s.duty_a, 2000);
        assert_ne!(s.status & status::COMMAND_HELD, 0);
    }

    fn plan(answers: u32, duties: &[i16]) -> Message {
        Message::Plan(Plan::new(answers, duties.iter().map(|&x| [x, -x])))
    }

    fn applied(d: &mut EmulatedDrive) -> (i16, u32, u16) {
        let Message::Sample(s) = d.sample_frame(0).message else {
            panic!()
        };
        (s.duty_a, s.applied_command_seq, s.status)
    }

    /// A period without its COMMAND gets the freshest PLAN's entry for that very period
    /// (flagged, and still counted for the watchdog); past the plan the duty is held; an
    /// older PLAN never replaces a newer one; a PLAN longer than the announced capacity is
    /// dropped; one with a −32768 duty latches BAD_COMMAND like such a COMMAND.
    #[test]
    fn missing_commands_take_the_freshest_plan_entry_for_their_period() {
        let mut d = in_session(emulated_drive(&Scenario::default(), 20, 8));
        assert_eq!(d.config.plan_capacity, 8);
        d.on_frame(&frame_bytes(1, Message::Control(Action::Enable)));
        d.run_period(0);
        // Sample 0 answered in time: applied over the period starting at sample 1. Its plan
        // covers the periods starting at samples 2, 3 and 4.
        d.on_frame(&frame_bytes(2, cmd(0, 1000)));
        d.on_frame(&frame_bytes(3, plan(0, &[2000, 3000, 4000])));
        d.run_period(1);
        assert_eq!(applied(&mut d), (1000, 2, status::ENABLED));
        let planned = status::ENABLED | status::COMMAND_HELD | status::COMMAND_PLANNED;
        d.run_period(2);
        assert_eq!(applied(&mut d), (2000, 3, planned));
        // A newer plan (continuing a command that never arrived) takes over; an older one
        // offered after it does not.
        d.on_frame(&frame_bytes(4, plan(1, &[5000, 6000])));
        d.on_frame(&frame_bytes(5, plan(0, &[7000, 7000, 7000])));
        d.run_period(3);
        assert_eq!(applied(&mut d), (5000, 4, planned));
        d.run_period(4);
        assert_eq!(applied(&mut d), (6000, 4, planned));
        // Past the plan: held, not planned.
        d.run_period(5);
        assert_eq!(
            applied(&mut d),
            (6000, 4, status::ENABLED | status::COMMAND_HELD)
        );
        // Held: period 0 (nothing can answer the sample before the first) and 2 to 5.
        assert_eq!(
            (d.counters.periods_held, d.counters.periods_planned),
            (5, 3)
        );
        // Longer than the capacity of 8: dropped, counted.
        d.on_frame(&frame_bytes(6, plan(5, &[1; 9])));
        assert_eq!(d.counters.bad_frames, 1);
        // A −32768 duty: rejected, fault latched, outputs off.
        d.on_frame(&frame_bytes(7, plan(6, &[1, i16::MIN])));
        d.run_period(6);
        assert_ne!(d.latched_faults() & faults::BAD_COMMAND, 0);
        assert_eq!(applied(&mut d).0, 0);
    }

    #[test]
    fn watchdog_turns_outputs_off_and_latches_until_reset() {
        let mut d = in_session(emulated_drive(&Scenario::default(), 20, 8));
        d.on_frame(&frame_bytes(1, Message::Control(Action::Enable)));
        d.run_period(0);
        d.on_frame(&frame_bytes(2, cmd(0, 5000)));
        d.run_period(1);
        let mut report = None;
        for k in 2..=21 {
            report = report.or(d.run_period(k));
        }
        let r = report.expect("watchdog fault reported");
        assert_eq!(r.fault_bits & faults::WATCHDOG, faults::WATCHDOG);
        assert_eq!(r.at_sample, 21);
        let Message::Sample(s) = d.sample_frame(0).message else {
            panic!()
        };
        assert_eq!((s.duty_a, s.duty_b), (0, 0));
        // A good command does not clear the latch; RESET + ENABLE does.
        d.on_frame(&frame_bytes(3, cmd(21, 5000)));
        d.run_period(22);
        assert!(!d.outputs_on());
        d.on_frame(&frame_bytes(4, Message::Control(Action::Reset)));
        assert!(!d.outputs_on(), "off until ENABLE");
        d.on_frame(&frame_bytes(5, Message::Control(Action::Enable)));
        d.on_frame(&frame_bytes(6, cmd(22, 5000)));
        d.run_period(23);
        assert!(d.outputs_on());
        let Message::Sample(s) = d.sample_frame(0).message else {
            panic!()
        };
        assert_eq!(s.duty_a, 5000);
    }

    /// A second host (a new run) says HELLO with its own frame numbers, lower than the
    /// first host's last: it gets its CONFIG and a new session, not a "stale frame".
    #[test]
    fn a_hello_starts_a_new_session() {
        let mut d = emulated_drive(&Scenario::default(), 20, 8);
        assert!(matches!(
            d.on_frame(&frame_bytes(1, Message::Hello)),
            Some(Reply::Config(_))
        ));
        d.on_frame(&frame_bytes(2, Message::Control(Action::Enable)));
        for seq in 3..500 {
            d.on_frame(&frame_bytes(seq, cmd(seq, 100)));
        }
        assert!(d.outputs_on());
        // The next host.
        assert!(matches!(
            d.on_frame(&frame_bytes(1, Message::Hello)),
            Some(Reply::Config(_))
        ));
        assert!(!d.outputs_on(), "off until the new host enables them");
        d.on_frame(&frame_bytes(2, Message::Control(Action::Reset)));
        d.on_frame(&frame_bytes(3, Message::Control(Action::Enable)));
        assert!(d.outputs_on());
        assert_eq!(d.counters.stale_frames, 0);
    }

    /// ALIGN brings the rotor to an electrical zero, physically (phase A at the align
    /// current for align_ms, ALIGNING set meanwhile), whatever a previous session left it
    /// at; it rests there within the load's offset (0.01 N·m / 25 N·m/rad = 4e-4 rad).
    #[test]
    fn align_leaves_the_rotor_at_an_electrical_zero() {
        let mut d = in_session(emulated_drive(&Scenario::default(), 2000, 8));
        d.on_frame(&frame_bytes(1, Message::Control(Action::Enable)));
        for k in 0..400u32 {
            d.on_frame(&frame_bytes(2 + k, cmd(k.wrapping_sub(1), 12_000)));
            d.run_period(k);
        }
        let theta = |d: &mut EmulatedDrive| {
            let Message::Sample(s) = d.sample_frame(0).message else {
                panic!()
            };
            f64::from(s.encoder_counts) / f64::from(1u32 << 20) * std::f64::consts::TAU
        };
        let pitch = std::f64::consts::TAU / 50.0;
        let before = theta(&mut d);
        assert!(
            (before / pitch - (before / pitch).round()).abs() > 1e-3,
            "moved off a zero"
        );
        d.on_frame(&frame_bytes(500, Message::Control(Action::Align)));
        let periods = 300 * 20_000 / 1000;
        for k in 0..periods - 1 {
            d.run_period(400 + k);
            let Message::Sample(s) = d.sample_frame(0).message else {
                panic!()
            };
            assert_ne!(s.status & status::ALIGNING, 0, "aligning at {k}");
            assert_eq!((s.status & status::ENABLED, s.duty_b), (0, 0));
        }
        d.run_period(400 + periods - 1);
        let after = theta(&mut d);
        let Message::Sample(s) = d.sample_frame(0).message else {
            panic!()
        };
        assert_eq!(s.status & status::ALIGNING, 0, "done");
        let off = (after / pitch - (after / pitch).round()) * pitch;
        assert!(off.abs() < 1e-3, "{off} rad from the nearest zero");
        assert!((after - before).abs() <= pitch / 2.0 + 1e-3);
    }

    /// Arbitrary frames, valid and corrupted with a matching CRC, at a drive between its
    /// periods: it never panics, and its outputs stay within the bus.
    #[test]
    fn arbitrary_frames_never_break_the_drive() {
        use proptest::prelude::*;
        let frame = (
            any::<u32>(),
            any::<u8>(),
            proptest::collection::vec(any::<u8>(), 0..64),
        );
        proptest!(|(frames in proptest::collection::vec(frame, 1..100))| {
            let mut d = emulated_drive(&Scenario::default(), 20, 8);
            for (k, (seq, kind, payload)) in frames.into_iter().enumerate() {
                let bytes = stepdrive_drive_protocol::raw_frame(seq, kind % 9, &payload);
                d.on_frame(&bytes);
                d.run_period(k as u32);
                let Message::Sample(s) = d.sample_frame(0).message else {
                    panic!("a sample frame")
                };
                prop_assert!(s.duty_a != i16::MIN && s.duty_b != i16::MIN);
            }
        });
    }
}
