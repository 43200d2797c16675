//! Drive protocol conformance (docs/drive-protocol.md §8 and §9), written from the document:
//! its test vectors are read from the file itself, and each numbered item of §9 is one
//! scripted exchange, played against the emulated drive's core (D1–D23) or the bridge's
//! link and core (H1–H17; H11–H13 play the bridge's start-up against the emulated drive's
//! core). No clock, no sockets: frames in, frames out.

use std::f64::consts::{FRAC_PI_2, TAU};
use stepdrive_bridge::core::{
    holds_phase_a, BridgeCore, CoreSettings, Received, Refusal, StartStep, HANDSHAKE_NS,
};
use stepdrive_bridge::link::{DriveLink, EncoderCalibration, Event, HeldLoad, HOLD_SAMPLES};
use stepdrive_drive_protocol::{
    crc32, decode, encode, faults, frame_bytes, reseal, status, Action, Command, Config,
    FaultReport, Frame, Message, Plan, Sample, MAX_FRAME,
};
use stepdrive_emulated_drive::{emulated_drive, AlignFault, EmulatedDrive, Reply};
use stepdrive_shared::stats::StatsReport;
use stepdrive_shared::Scenario;

const SPEC: &str = include_str!("../docs/drive-protocol.md");

/// The fenced hex blocks of §8, in order.
fn vectors() -> Vec<Vec<u8>> {
    let section = &SPEC[SPEC.find("## 8. Test vectors").expect("§8")..];
    let section = &section[..section.find("## 9.").expect("§9")];
    section
        .split("```")
        .skip(1)
        .step_by(2)
        .map(|block| {
            block
                .split_whitespace()
                .map(|b| u8::from_str_radix(b, 16).expect("hex byte"))
                .collect()
        })
        .collect()
}

fn frame(bytes: &[u8]) -> Frame {
    let f = decode(bytes).expect("the vector decodes");
    let mut out = [0u8; MAX_FRAME];
    let n = encode(&f, &mut out);
    assert_eq!(&out[..n], bytes, "the vector re-encodes to itself");
    f
}

#[test]
fn the_documents_test_vectors_decode_to_what_the_document_says() {
    assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
    assert_eq!(crc32(&[0]), 0xD202_EF8D);
    let v = vectors();
    assert_eq!(v.len(), 4, "COMMAND, PLAN, CONFIG and SAMPLE vectors");
    let f = frame(&v[0]);
    assert_eq!((f.seq, f.timestamp_ns), (7, 1000));
    assert_eq!(
        f.message,
        Message::Command(Command {
            answers_sample: 6,
            duty_a: 1000,
            duty_b: -1000
        })
    );
    let f = frame(&v[1]);
    let Message::Plan(p) = f.message else {
        panic!("a PLAN")
    };
    assert_eq!((f.seq, p.answers_sample), (8, 6));
    assert_eq!(p.entries(), &[[1000, -1000], [2000, -2000]]);
    let Message::Config(c) = frame(&v[2]).message else {
        panic!("a CONFIG")
    };
    assert_eq!(
        (c.sample_rate_hz, c.counts_per_rev, c.watchdog_periods),
        (20_000, 1 << 20, 1000)
    );
    assert_eq!(
        (
            c.encoder_direction,
            c.plan_capacity,
            c.align_current_ma,
            c.align_ms
        ),
        (1, 200, 1000, 300)
    );
    c.check().expect("the vector's CONFIG is valid");
    // The SAMPLE in SI through the host's link with that CONFIG (zero at count 0).
    let mut link = DriveLink::new(
        20_000.0,
        400.0,
        EncoderCalibration {
            offset_counts: Some(0),
            reverse: false,
            held_load: None,
        },
    );
    assert!(matches!(link.on_frame(&v[2], 0), Event::Config(_)));
    let Event::State(st) = link.on_frame(&v[3], 0) else {
        panic!("a state")
    };
    assert!((st.theta_rad - FRAC_PI_2).abs() < 1e-12);
    assert!((st.i_a_a - 0.151).abs() < 1e-9 && st.i_b_a == 0.0);
    assert!((st.bus_voltage_v - 24.0).abs() < 1e-9);
    assert!((st.v_a_v - 12.0).abs() < 1e-3 && st.v_b_v == 0.0);
    assert_eq!(st.applied_command_seq, 17);
}

// ---- the drive (D1–D17), against the emulated drive's core ----

const WATCHDOG: u16 = 20;

fn drive() -> EmulatedDrive {
    emulated_drive(&Scenario::default(), WATCHDOG, 8)
}

/// The host's frames, numbered from 1 as a host process does.
struct Host(u32);

impl Host {
    fn send(&mut self, d: &mut EmulatedDrive, m: Message) -> Option<Reply> {
        self.0 += 1;
        d.on_frame(&frame_bytes(self.0, m))
    }
    fn control(&mut self, d: &mut EmulatedDrive, a: Action) {
        self.send(d, Message::Control(a));
    }
    /// C(s, duty) on both phases; returns its frame seq.
    fn command(&mut self, d: &mut EmulatedDrive, answers: u32, duty: i16) -> u32 {
        self.send(
            d,
            Message::Command(Command {
                answers_sample: answers,
                duty_a: duty,
                duty_b: duty,
            }),
        );
        self.0
    }
}

/// One period: the drive sends S(k) (which reports the period before) and runs the
/// period that starts there. Returns k and S(k).
/// One period, with the FAULT_REPORT the drive sends after S(k), if any.
fn period_reporting(d: &mut EmulatedDrive) -> (u32, Sample, Option<FaultReport>) {
    let f = d.sample_frame(0);
    let report = d.run_period(f.seq);
    let Message::Sample(s) = f.message else {
        panic!("a SAMPLE")
    };
    (f.seq, s, report)
}

fn period(d: &mut EmulatedDrive) -> (u32, Sample) {
    let (k, s, _) = period_reporting(d);
    (k, s)
}

fn hello(h: &mut Host, d: &mut EmulatedDrive) -> Config {
    match h.send(d, Message::Hello) {
        Some(Reply::Config(c)) => c,
        None => panic!("HELLO must be answered with CONFIG"),
    }
}

#[test]
fn d1_hello_is_answered_with_a_valid_config_and_starts_a_session() {
    let mut d = drive();
    let mut h = Host(0);
    hello(&mut h, &mut d).check().expect("valid CONFIG");
    h.control(&mut d, Action::Enable);
    for _ in 0..500 {
        let (k, _) = period(&mut d);
        h.command(&mut d, k, 100);
    }
    assert!(d.outputs_on());
    // A new host process numbers its frames from 1 again.
    let mut next = Host(0);
    hello(&mut next, &mut d);
    assert_eq!(d.counters.stale_frames, 0);
    assert!(!d.outputs_on(), "a new session starts with outputs off");
}

#[test]
fn d2_samples_are_numbered_by_period() {
    let mut d = drive();
    hello(&mut Host(0), &mut d);
    let (first, _) = period(&mut d);
    for i in 1..100 {
        assert_eq!(period(&mut d).0, first + i);
    }
    assert_eq!(
        d.report_seq(),
        first + 99,
        "a report carries the last SAMPLE's seq"
    );
}

#[test]
fn d3_a_command_is_applied_over_the_period_after_the_next_sample_only() {
    let mut d = drive();
    let mut h = Host(0);
    hello(&mut h, &mut d);
    h.control(&mut d, Action::Enable);
    let (s, _) = period(&mut d);
    let c = h.command(&mut d, s, 1000);
    period(&mut d); // S(s+1): C(s) applies over this period
    let (_, got) = period(&mut d); // S(s+2) reports it
    assert_eq!((got.duty_a, got.applied_command_seq), (1000, c));
    assert_eq!(got.status & status::COMMAND_HELD, 0);
    // C(s) again, now for a period that has passed: not applied, the period held.
    h.command(&mut d, s, 3000);
    period(&mut d);
    let (_, got) = period(&mut d);
    assert_eq!((got.duty_a, got.applied_command_seq), (1000, c));
    assert_ne!(got.status & status::COMMAND_HELD, 0);
}

#[test]
fn d4_frames_failing_validation_or_sequence_are_never_acted_upon() {
    let mut d = drive();
    let mut h = Host(0);
    hello(&mut h, &mut d);
    h.control(&mut d, Action::Enable);
    let (s, _) = period(&mut d);
    let command = |seq, duty| {
        frame_bytes(
            seq,
            Message::Command(Command {
                answers_sample: s,
                duty_a: duty,
                duty_b: duty,
            }),
        )
    };
    let mut flipped = command(h.0 + 1, 5000);
    flipped[19] ^= 0x04;
    assert!(d.on_frame(&flipped).is_none());
    let c = h.command(&mut d, s, 1000);
    // The same seq twice, and an older host seq.
    d.on_frame(&command(c, 9000));
    d.on_frame(&frame_bytes(c - 1, Message::Control(Action::Disable)));
    period(&mut d);
    let (_, got) = period(&mut d);
    assert_eq!((got.duty_a, got.applied_command_seq), (1000, c));
    assert!(d.outputs_on());
    assert_eq!((d.counters.crc_errors, d.counters.stale_frames), (1, 2));
}

#[test]
fn d5_every_state_reports_what_the_table_says() {
    let mut d = drive();
    let mut h = Host(0);
    let config = hello(&mut h, &mut d);
    assert!(config.align_ms > 0);
    period(&mut d);
    // Disabled.
    let (_, s) = period(&mut d);
    assert_eq!(
        (s.status, s.duty_a, s.duty_b, s.applied_command_seq),
        (0, 0, 0, 0)
    );
    // Aligning: phase A only, not enabled, no command.
    h.control(&mut d, Action::Align);
    period(&mut d);
    let (_, s) = period(&mut d);
    assert_eq!(s.status, status::ALIGNING);
    assert!(s.duty_a > 0 && s.duty_b == 0 && s.applied_command_seq == 0);
    while period(&mut d).1.status & status::ALIGNING != 0 {}
    // Holding: enabled, the align duties, no command yet.
    h.control(&mut d, Action::Enable);
    period(&mut d);
    let (k, s) = period(&mut d);
    assert_eq!(s.status, status::ENABLED | status::COMMAND_HELD);
    assert!(s.duty_a > 0 && s.duty_b == 0 && s.applied_command_seq == 0);
    // Following.
    let c = h.command(&mut d, k, -700);
    period(&mut d);
    let (_, s) = period(&mut d);
    assert_eq!(s.status, status::ENABLED);
    assert_eq!((s.duty_a, s.duty_b, s.applied_command_seq), (-700, -700, c));
    // Faulted.
    d.trip(faults::OVERCURRENT);
    period(&mut d);
    let (_, s) = period(&mut d);
    assert_eq!(
        (s.status, s.duty_a, s.duty_b, s.applied_command_seq),
        (0, 0, 0, 0)
    );
    assert_eq!(s.fault_bits, faults::OVERCURRENT);
}

#[test]
fn d6_the_watchdog_arms_at_the_first_command_after_enable() {
    let mut d = drive();
    let mut h = Host(0);
    hello(&mut h, &mut d);
    h.control(&mut d, Action::Enable);
    for _ in 0..3 * WATCHDOG {
        period(&mut d);
    }
    assert_eq!(d.latched_faults(), 0, "not armed before the first COMMAND");
    let (k, _) = period(&mut d);
    h.command(&mut d, k, 100);
    period(&mut d); // applied: armed
    let mut report: Option<FaultReport> = None;
    for _ in 0..WATCHDOG {
        let k = d.sample_frame(0).seq;
        report = report.or(d.run_period(k));
    }
    let r = report.expect("WATCHDOG latched after watchdog_periods without a COMMAND");
    assert_eq!(r.fault_bits, faults::WATCHDOG);
}

#[test]
fn d7_an_out_of_range_duty_latches_bad_command_and_applies_nothing() {
    let mut d = drive();
    let mut h = Host(0);
    hello(&mut h, &mut d);
    h.control(&mut d, Action::Enable);
    let (k, _) = period(&mut d);
    h.command(&mut d, k, i16::MIN);
    period(&mut d);
    let (_, s) = period(&mut d);
    assert_eq!(s.fault_bits, faults::BAD_COMMAND);
    assert_eq!((s.duty_a, s.duty_b), (0, 0));
}

#[test]
fn d8_faults_clear_only_on_reset_and_outputs_return_only_on_enable() {
    let mut d = drive();
    let mut h = Host(0);
    hello(&mut h, &mut d);
    h.control(&mut d, Action::Enable);
    d.trip(faults::OVERCURRENT);
    let (k, _) = period(&mut d);
    h.command(&mut d, k, 100);
    period(&mut d);
    assert_eq!(
        d.latched_faults(),
        faults::OVERCURRENT,
        "a COMMAND never clears"
    );
    h.control(&mut d, Action::Reset);
    assert_eq!(d.latched_faults(), 0);
    assert!(!d.outputs_on(), "off until ENABLE");
    h.control(&mut d, Action::Enable);
    let (k, _) = period(&mut d);
    let c = h.command(&mut d, k, 2500);
    period(&mut d);
    let (_, s) = period(&mut d);
    assert_eq!((s.duty_a, s.applied_command_seq), (2500, c));
}

#[test]
fn d9_align_brings_the_rotor_to_an_electrical_zero_from_wherever_it_was() {
    let mut d = drive();
    let mut h = Host(0);
    let config = hello(&mut h, &mut d);
    h.control(&mut d, Action::Enable);
    // Drive it somewhere else, as a previous session would.
    for _ in 0..400 {
        let (k, _) = period(&mut d);
        h.command(&mut d, k, 12_000);
    }
    let theta = |s: Sample| f64::from(s.encoder_counts) / f64::from(config.counts_per_rev) * TAU;
    let pitch = TAU / 50.0;
    let off_zero = |th: f64| (th / pitch - (th / pitch).round()) * pitch;
    let before = theta(period(&mut d).1);
    assert!(off_zero(before).abs() > 1e-2, "moved off a zero: {before}");
    h.control(&mut d, Action::Align);
    let mut flagged = 0;
    let after = loop {
        let (_, s) = period(&mut d);
        if s.status & status::ALIGNING == 0 {
            break theta(s);
        }
        flagged += 1;
        assert!(flagged < 100_000, "ALIGNING never cleared");
    };
    let expected = u32::from(config.align_ms) * config.sample_rate_hz / 1000;
    assert_eq!(flagged, expected, "ALIGNING for align_ms");
    // Within the load's offset at 1 A (0.01 N·m / 25 N·m/rad = 4e-4 rad).
    assert!(off_zero(after).abs() < 1e-3, "{after}");
    assert!((after - before).abs() <= pitch / 2.0 + 1e-3);
}

fn plan(answers: u32, duties: &[i16]) -> Message {
    Message::Plan(Plan::new(answers, duties.iter().map(|&x| [x, x])))
}

#[test]
fn d10_the_newest_plan_covers_missing_commands_and_an_equal_one_replaces_it() {
    let mut d = drive();
    let mut h = Host(0);
    hello(&mut h, &mut d);
    h.control(&mut d, Action::Enable);
    let (s, _) = period(&mut d);
    h.command(&mut d, s, 1000);
    h.send(&mut d, plan(s, &[2000, 3000]));
    h.send(&mut d, plan(s, &[4000, 5000])); // the same base: replaces
    h.send(&mut d, plan(s.wrapping_sub(1), &[9000, 9000])); // older: ignored
    period(&mut d); // s + 1: C(s)
    let planned = status::ENABLED | status::COMMAND_HELD | status::COMMAND_PLANNED;
    assert_eq!(period(&mut d).1.duty_a, 1000); // s + 2: entry 0 runs
    let (_, got) = period(&mut d); // s + 3: entry 1 runs
    assert_eq!((got.duty_a, got.status), (4000, planned));
    assert_eq!(period(&mut d).1.duty_a, 5000);
}

/// An enabled drive following C(k, 1000) for a few periods; returns the host.
fn following(d: &mut EmulatedDrive) -> Host {
    let mut h = Host(0);
    hello(&mut h, d);
    h.control(d, Action::Enable);
    for _ in 0..5 {
        let (k, _) = period(d);
        h.command(d, k, 1000);
    }
    h
}

#[test]
fn d11_a_sample_shows_state_changes_then_duties_one_period_later() {
    let mut d = drive();
    let mut h = following(&mut d);
    // A −32768 duty received between S(k − 1) and S(k).
    h.command(&mut d, 0, i16::MIN);
    let (k, s, report) = period_reporting(&mut d);
    assert_ne!(
        s.fault_bits & faults::BAD_COMMAND,
        0,
        "S(k) has the fault bit"
    );
    assert_eq!(s.status & status::ENABLED, 0, "and ENABLED clear");
    assert_eq!(s.duty_a, 1000, "with period k − 1's duties");
    assert_eq!(
        report.map(|r| r.at_sample),
        Some(k),
        "period k is the first off"
    );
    let (_, s, _) = period_reporting(&mut d);
    assert_eq!(
        (s.duty_a, s.applied_command_seq),
        (0, 0),
        "S(k + 1): duties 0"
    );
    // An ENABLE received between S(j − 1) and S(j): S(j) has ENABLED set.
    let mut d = drive();
    let mut h = Host(0);
    hello(&mut h, &mut d);
    period(&mut d);
    h.control(&mut d, Action::Enable);
    assert_ne!(period(&mut d).1.status & status::ENABLED, 0);
}

#[test]
fn d12_the_watchdog_latches_at_the_start_of_its_nth_period_without_a_command() {
    let mut d = drive();
    following(&mut d);
    // Period p had the last COMMAND; periods p + 1 … are without one.
    let (p, _) = period(&mut d);
    let mut held = 0;
    let (k, report) = loop {
        let (k, s, report) = period_reporting(&mut d);
        if let Some(r) = report {
            break (k, r);
        }
        assert_eq!(s.fault_bits, 0);
        if k > p + 1 {
            assert_eq!(s.duty_a, 1000, "the held duty, not yet off");
            held += 1;
        }
        assert!(k < p + 10 * u32::from(WATCHDOG), "no watchdog");
    };
    assert_eq!(k, p + u32::from(WATCHDOG), "the N-th period without is off");
    assert_eq!(
        held,
        u32::from(WATCHDOG) - 2,
        "N − 1 held, all reported so far"
    );
    assert_eq!((report.at_sample, report.fault_bits), (k, faults::WATCHDOG));
    let (_, s, _) = period_reporting(&mut d);
    assert_eq!(
        (s.fault_bits, s.duty_a),
        (faults::WATCHDOG, 0),
        "S(k + 1) shows it"
    );
}

#[test]
fn d13_before_a_hello_and_frames_of_drive_kinds_are_not_acted_upon() {
    let mut d = drive();
    let mut h = Host(0);
    h.control(&mut d, Action::Enable);
    assert!(!d.outputs_on(), "no session yet");
    assert_eq!(d.counters.foreign_frames, 1);
    hello(&mut h, &mut d);
    // A SAMPLE sent to the drive, numbered far ahead: dropped before the sequence rule,
    // so the host's next frame is still accepted.
    let bytes = frame_bytes(1000, Message::Sample(RESTING));
    assert!(d.on_frame(&bytes).is_none());
    assert_eq!(d.counters.bad_frames, 1);
    h.control(&mut d, Action::Enable);
    assert!(d.outputs_on());
    assert_eq!(d.counters.stale_frames, 0);
}

#[test]
fn d14_disable_and_reset_discard_the_plan_and_the_waiting_command() {
    for stop in [Action::Disable, Action::Reset] {
        let mut d = drive();
        let mut h = following(&mut d);
        let (s, _) = period(&mut d);
        h.command(&mut d, s, 7000);
        h.send(&mut d, plan(s, &[2000, 3000, 4000]));
        h.control(&mut d, stop);
        h.control(&mut d, Action::Enable);
        period(&mut d);
        period(&mut d);
        let (_, got) = period(&mut d);
        assert_eq!(
            got.status & (status::COMMAND_HELD | status::COMMAND_PLANNED),
            status::COMMAND_HELD,
            "{stop:?}: held, not from the discarded plan"
        );
        assert_eq!(
            got.duty_a, 0,
            "{stop:?}: the waiting COMMAND was discarded, nothing held from before"
        );
    }
}

#[test]
fn d15_enable_and_align_are_ignored_while_a_fault_is_latched() {
    let mut d = drive();
    let mut h = following(&mut d);
    h.command(&mut d, 0, i16::MIN);
    period(&mut d);
    h.control(&mut d, Action::Align);
    h.control(&mut d, Action::Enable);
    let (_, s) = period(&mut d);
    assert_eq!(s.status & (status::ALIGNING | status::ENABLED), 0);
    assert_eq!((s.duty_a, s.duty_b), (0, 0), "nothing energized");
    h.control(&mut d, Action::Reset);
    h.control(&mut d, Action::Enable);
    assert!(d.outputs_on());
}

#[test]
fn d16_one_fault_report_each_time_new_bits_latch() {
    let mut d = drive();
    let mut h = following(&mut d);
    h.command(&mut d, 0, i16::MIN);
    let reports: Vec<FaultReport> = (0..50).filter_map(|_| period_reporting(&mut d).2).collect();
    assert_eq!(reports.len(), 1, "{reports:?}");
    d.trip(faults::OVERCURRENT);
    let (_, s, report) = period_reporting(&mut d);
    assert_ne!(s.fault_bits & faults::OVERCURRENT, 0);
    assert_eq!(
        report.map(|r| r.fault_bits),
        Some(faults::BAD_COMMAND | faults::OVERCURRENT),
        "every latched bit"
    );
    h.control(&mut d, Action::Reset);
    h.command(&mut d, 0, i16::MIN);
    assert!(period_reporting(&mut d).2.is_some(), "again after RESET");
}

#[test]
fn d17_an_enable_during_align_waits_for_its_end_and_commands_are_not_applied() {
    let mut d = drive();
    let mut h = Host(0);
    let config = hello(&mut h, &mut d);
    h.control(&mut d, Action::Align);
    h.control(&mut d, Action::Enable);
    let n = u32::from(config.align_ms) * config.sample_rate_hz / 1000;
    for i in 0..n {
        let (k, s) = period(&mut d);
        let both = status::ALIGNING | status::ENABLED;
        assert_eq!(s.status & both, both, "sample {i}");
        assert_eq!(s.applied_command_seq, 0, "sample {i}: no COMMAND applied");
        h.command(&mut d, k, 5000);
    }
    let (_, s) = period(&mut d);
    assert_eq!(s.status & status::ALIGNING, 0, "clear after n samples");
}

/// Runs periods until the drive's SAMPLE shows ALIGNING clear; returns that SAMPLE.
fn until_aligned(d: &mut EmulatedDrive) -> (u32, Sample) {
    for _ in 0..100_000 {
        let (k, s) = period(d);
        if s.status & status::ALIGNING == 0 {
            return (k, s);
        }
    }
    panic!("ALIGNING never cleared")
}

#[test]
fn d18_the_run_starts_at_the_first_enabled_sample_with_aligning_clear() {
    let mut d = drive();
    let mut h = Host(0);
    let config = hello(&mut h, &mut d);
    h.control(&mut d, Action::Align);
    h.control(&mut d, Action::Enable);
    let n = u32::from(config.align_ms) * config.sample_rate_hz / 1000;
    for i in 0..n {
        let f = d.sample_frame(0);
        assert!(
            d.truth(f.seq).is_none(),
            "sample {i}: no run while aligning"
        );
        d.run_period(f.seq);
    }
    let f = d.sample_frame(0);
    let Message::Sample(s) = f.message else {
        panic!("a SAMPLE")
    };
    assert_eq!(
        s.status & (status::ENABLED | status::ALIGNING),
        status::ENABLED
    );
    assert_eq!(
        d.truth(f.seq).map(|t| t.k),
        Some(0),
        "the host's k = 0 is the drive's"
    );
}

#[test]
fn d19_no_plan_entry_applies_while_the_aligned_rotor_is_held() {
    let mut d = drive();
    let mut h = Host(0);
    hello(&mut h, &mut d);
    h.control(&mut d, Action::Align);
    until_aligned(&mut d);
    h.control(&mut d, Action::Enable);
    let (s, held) = period(&mut d);
    let align_duty = held.duty_a;
    assert!(align_duty > 0);
    // A PLAN without its COMMAND (lost on the way): entry 0 is for period s + 2.
    h.send(&mut d, plan(s, &[3000, 4000, 5000]));
    period(&mut d);
    period(&mut d);
    let (_, got) = period(&mut d); // reports period s + 2
    assert_eq!(
        got.status,
        status::ENABLED | status::COMMAND_HELD,
        "held, not planned"
    );
    assert_eq!(
        (got.duty_a, got.duty_b, got.applied_command_seq),
        (align_duty, 0, 0)
    );
}

#[test]
fn d20_disable_reset_and_hello_show_at_once_and_in_the_duties_a_period_later() {
    for stop in ["DISABLE", "RESET", "HELLO"] {
        let mut d = drive();
        let mut h = following(&mut d);
        let (k, _) = period(&mut d);
        let c = h.command(&mut d, k, 2000);
        period(&mut d); // S(k + 1): period k + 1 applies C(k)
        match stop {
            "DISABLE" => h.control(&mut d, Action::Disable),
            "RESET" => h.control(&mut d, Action::Reset),
            _ => {
                h.send(&mut d, Message::Hello);
            }
        }
        let (_, s) = period(&mut d); // S(k + 2) reports period k + 1
        assert_eq!(
            s.status & status::ENABLED,
            0,
            "{stop}: ENABLED clear at once"
        );
        assert_eq!(
            (s.duty_a, s.applied_command_seq),
            (2000, c),
            "{stop}: period k + 1 ran with C(k)"
        );
        let (_, s) = period(&mut d);
        assert_eq!(
            (s.duty_a, s.duty_b, s.applied_command_seq),
            (0, 0, 0),
            "{stop}: outputs off from period k + 2"
        );
    }
}

#[test]
fn d21_a_live_session_is_not_taken_over_by_another_address() {
    let mut d = drive();
    let mut h = following(&mut d);
    // Another host (its own frame numbers) says HELLO while this one commands the motor.
    assert!(d
        .on_frame_from(&frame_bytes(1, Message::Hello), false)
        .is_none());
    assert_eq!(d.counters.foreign_frames, 1);
    assert!(d.outputs_on(), "the motor is still this host's");
    let (k, _) = period(&mut d);
    let c = h.command(&mut d, k, 1500);
    period(&mut d);
    assert_eq!(period(&mut d).1.applied_command_seq, c);
    // Once this host lets go (DISABLE), the next one is taken.
    h.control(&mut d, Action::Disable);
    assert!(matches!(
        d.on_frame_from(&frame_bytes(1, Message::Hello), false),
        Some(Reply::Config(_))
    ));
    // A host gone silent while its drive holds the aligned rotor (the watchdog is not armed
    // before a COMMAND): after the watchdog's periods of silence, the next one is taken.
    let mut d = drive();
    let mut h = Host(0);
    hello(&mut h, &mut d);
    h.control(&mut d, Action::Align);
    until_aligned(&mut d);
    h.control(&mut d, Action::Enable);
    for _ in 0..WATCHDOG - 1 {
        period(&mut d);
    }
    assert!(d
        .on_frame_from(&frame_bytes(1, Message::Hello), false)
        .is_none());
    period(&mut d);
    assert!(matches!(
        d.on_frame_from(&frame_bytes(1, Message::Hello), false),
        Some(Reply::Config(_))
    ));
    assert!(!d.outputs_on(), "a new session starts with outputs off");
}

#[test]
fn d21_a_dead_hosts_session_passes_on_with_watchdog_latched() {
    // §2: a host gone silent leaves the drive to the next one after the watchdog, "which has
    // latched by then if a COMMAND had armed it". Another address says HELLO every period
    // after this host's last COMMAND.
    let mut d = drive();
    let mut h = following(&mut d);
    let (k, _) = period(&mut d);
    h.command(&mut d, k, 1500);
    let taken = (0..WATCHDOG + 10).find(|_| {
        period(&mut d);
        matches!(
            d.on_frame_from(&frame_bytes(1, Message::Hello), false),
            Some(Reply::Config(_))
        )
    });
    assert!(taken.is_some(), "never taken");
    assert_eq!(
        d.latched_faults(),
        faults::WATCHDOG,
        "taken {taken:?} periods after the last COMMAND, before the watchdog latched"
    );
}

#[test]
fn d22_hello_stops_an_align() {
    let mut d = drive();
    let mut h = Host(0);
    hello(&mut h, &mut d);
    h.control(&mut d, Action::Align);
    period(&mut d);
    assert_ne!(period(&mut d).1.status & status::ALIGNING, 0);
    h.send(&mut d, Message::Hello);
    let (_, s) = period(&mut d);
    assert_eq!(s.status & status::ALIGNING, 0, "ALIGNING clear at once");
    let (_, s) = period(&mut d);
    assert_eq!(
        (s.duty_a, s.duty_b),
        (0, 0),
        "phase A off from the next period"
    );
}

#[test]
fn d23_past_a_plans_end_the_last_duties_are_held_and_not_planned() {
    let mut d = drive();
    let mut h = following(&mut d);
    let (s, _) = period(&mut d);
    h.command(&mut d, s, 1000);
    h.send(&mut d, plan(s, &[2000, 3000]));
    let plan_seq = h.0;
    period(&mut d); // s + 1: C(s)
    period(&mut d); // s + 2: entry 0
    period(&mut d); // s + 3: entry 1
    period(&mut d); // s + 4: past the end
    let (_, got) = period(&mut d);
    assert_eq!(got.status, status::ENABLED | status::COMMAND_HELD);
    assert_eq!((got.duty_a, got.applied_command_seq), (3000, plan_seq));
}

#[test]
fn d23_a_shorter_plan_that_replaces_a_longer_one_ends_where_it_ends() {
    let mut d = drive();
    let mut h = following(&mut d);
    let (s, _) = period(&mut d);
    h.command(&mut d, s, 1000);
    h.send(&mut d, plan(s, &[2000, 3000, 4000]));
    h.send(&mut d, plan(s, &[5000])); // the same base: replaces, entries and length
    let plan_seq = h.0;
    period(&mut d); // s + 1: C(s)
    period(&mut d); // s + 2: entry 0
    let (_, got) = period(&mut d); // s + 3: past the new plan's end, not the old one's
    assert_eq!(got.duty_a, 5000);
    let (_, got) = period(&mut d);
    assert_eq!(got.status, status::ENABLED | status::COMMAND_HELD);
    assert_eq!((got.duty_a, got.applied_command_seq), (5000, plan_seq));
}

// ---- the host (H1–H17), against the bridge's link and core ----

fn configured_link() -> DriveLink {
    let mut l = DriveLink::new(
        20_000.0,
        400.0,
        EncoderCalibration {
            offset_counts: Some(0),
            reverse: false,
            held_load: None,
        },
    );
    let config = stepdrive_drive_protocol::units::default_config(20_000.0, 1000, 200);
    assert!(matches!(
        l.on_frame(&frame_bytes(0, Message::Config(config)), 0),
        Event::Config(_)
    ));
    l
}

/// An enabled drive at rest with the default CONFIG's scaling: 0 A, 24 V, duties 0.
const RESTING: Sample = Sample {
    encoder_counts: 0,
    adc_a: 32768,
    adc_b: 32768,
    adc_bus: 2400,
    duty_a: 0,
    duty_b: 0,
    applied_command_seq: 0,
    fault_bits: 0,
    status: status::ENABLED,
};

fn sample_at(seq: u32, counts: i32) -> Vec<u8> {
    let s = Sample {
        encoder_counts: counts,
        ..RESTING
    };
    frame_bytes(seq, Message::Sample(s))
}

#[test]
fn h1_a_lost_sample_advances_the_host_by_the_gap() {
    let mut l = configured_link();
    let w = 13.13;
    let counts =
        |k: u32| (w * f64::from(k) / 20_000.0 / TAU * f64::from(1u32 << 20)).round() as i32;
    let mut before = 0.0;
    for k in 1..=4000 {
        let Event::State(st) = l.on_frame(&sample_at(k, counts(k)), 0) else {
            panic!()
        };
        before = st.omega_rad_s;
    }
    let Event::State(st) = l.on_frame(&sample_at(4002, counts(4002)), 0) else {
        panic!()
    };
    assert_eq!(st.seq, 4001, "index k advances by the gap");
    assert_eq!(l.lost_on_wire, 1);
    // The encoder's 6 µrad quantum moves the 400 Hz estimate by ~2e-3 rad/s a sample;
    // stepped one period for the two, it would jump by β/T · ωT ≈ 0.18 rad/s.
    assert!(
        (st.omega_rad_s - w).abs() < 0.03 && (st.omega_rad_s - before).abs() < 0.03,
        "ω̂ {before} → {}",
        st.omega_rad_s
    );
}

#[test]
fn h2_a_reordered_sample_is_counted_once() {
    let mut l = configured_link();
    for seq in [1, 3, 2] {
        l.on_frame(&sample_at(seq, 0), 0);
    }
    assert_eq!((l.lost_on_wire, l.bad_frames), (0, 1));
    // A true duplicate is dropped and counted too, and never makes a loss negative.
    l.on_frame(&sample_at(2, 0), 0);
    assert_eq!((l.lost_on_wire, l.bad_frames), (0, 2));
}

#[test]
fn h3_a_stale_fault_report_is_dropped() {
    let mut l = configured_link();
    l.on_frame(&sample_at(2000, 0), 0);
    let report = |seq| {
        frame_bytes(
            seq,
            Message::FaultReport(FaultReport {
                fault_bits: faults::WATCHDOG,
                at_sample: seq,
            }),
        )
    };
    assert_eq!(l.on_frame(&report(5), 0), Event::Dropped);
    assert_eq!(l.stale_reports, 1);
    assert!(matches!(l.on_frame(&report(2000), 0), Event::Fault(_)));
    // Counted where the run's report shows the drive link's dropped frames (issue 24,
    // defect 3: it stayed in a counter nothing read).
    let mut stats = StatsReport::default();
    l.copy_counters(&mut stats);
    assert_eq!(stats.bad_frames, 1, "the stale report is a dropped frame");
}

#[test]
fn h4_an_invalid_config_is_refused_naming_the_field() {
    let good = stepdrive_drive_protocol::units::default_config(20_000.0, 1000, 200);
    let cases = [
        (
            Config {
                encoder_direction: 0,
                ..good
            },
            "encoder_direction",
        ),
        (
            Config {
                plan_capacity: 1025,
                ..good
            },
            "plan_capacity",
        ),
        (
            Config {
                watchdog_periods: 1,
                ..good
            },
            "watchdog_periods",
        ),
        (
            Config {
                counts_per_rev: 0,
                ..good
            },
            "counts_per_rev",
        ),
    ];
    for (config, field) in cases {
        let mut l = DriveLink::new(20_000.0, 400.0, EncoderCalibration::default());
        match l.on_frame(&frame_bytes(0, Message::Config(config)), 0) {
            Event::BadConfig(e) => {
                assert_eq!(e.field, field);
                assert!(e.to_string().contains(field), "{e}");
            }
            other => panic!("{field}: accepted as {other:?}"),
        }
        assert!(!l.configured());
    }
}

#[test]
fn h5_frames_of_another_version_are_counted_with_it() {
    let mut l = DriveLink::new(20_000.0, 400.0, EncoderCalibration::default());
    let config = stepdrive_drive_protocol::units::default_config(20_000.0, 1000, 200);
    let mut v2 = frame_bytes(0, Message::Config(config));
    v2[2] = 2;
    reseal(&mut v2);
    assert_eq!(l.on_frame(&v2, 0), Event::Dropped);
    assert_eq!(l.other_version, (1, 2));
}

fn sample_with_status(seq: u32, status_bits: u16) -> Vec<u8> {
    let s = Sample {
        status: status_bits,
        ..RESTING
    };
    frame_bytes(seq, Message::Sample(s))
}

#[test]
fn h6_the_run_starts_at_the_first_enabled_sample_after_enable() {
    let mut l = configured_link();
    // What the host does when it sends ENABLE: the stream starts again.
    l.restart();
    for seq in [100, 101] {
        assert!(matches!(
            l.on_frame(&sample_with_status(seq, status::ALIGNING), 0),
            Event::Dropped
        ));
    }
    let Event::State(st) = l.on_frame(&sample_with_status(102, status::ENABLED), 0) else {
        panic!("the enabled sample is a state")
    };
    assert_eq!(st.seq, 0, "k = 0");
    assert_eq!((l.before_enable, l.lost_on_wire), (2, 0));
}

#[test]
fn h7_theta_zero_is_the_electrical_zero_after_an_alignment_under_load() {
    let mut l = DriveLink::new(
        20_000.0,
        400.0,
        EncoderCalibration {
            offset_counts: None,
            reverse: false,
            held_load: Some(HeldLoad {
                torque_nm: 0.01,
                torque_constant_nm_per_a: 0.5,
                rotor_teeth: 50.0,
            }),
        },
    );
    let mut config = stepdrive_drive_protocol::units::default_config(20_000.0, 1000, 200);
    config.align_current_ma = 1000;
    config.align_ms = 300;
    assert!(matches!(
        l.on_frame(&frame_bytes(0, Message::Config(config)), 0),
        Event::Config(_)
    ));
    let Event::State(st) = l.on_frame(&sample_at(1, 0), 0) else {
        panic!("a state")
    };
    let expected = -(0.02f64).asin() / 50.0;
    assert!(
        (st.theta_rad - expected).abs() < 1e-12,
        "θ₀ {}",
        st.theta_rad
    );
    assert!((expected + 4.0003e-4).abs() < 1e-8);
    // Without an alignment there is no offset to take out. (A fresh link: a second CONFIG
    // is never applied, H10.)
    config.align_ms = 0;
    let mut l = DriveLink::new(
        20_000.0,
        400.0,
        EncoderCalibration {
            offset_counts: None,
            reverse: false,
            held_load: Some(HeldLoad {
                torque_nm: 0.01,
                torque_constant_nm_per_a: 0.5,
                rotor_teeth: 50.0,
            }),
        },
    );
    l.on_frame(&frame_bytes(2, Message::Config(config)), 0);
    l.restart();
    let Event::State(st) = l.on_frame(&sample_at(3, 0), 0) else {
        panic!("a state")
    };
    assert_eq!(st.theta_rad, 0.0);
}

#[test]
fn h8_a_drive_that_does_not_hold_phase_a_at_its_align_current_is_refused() {
    let mut l = configured_link();
    let config = stepdrive_drive_protocol::units::default_config(20_000.0, 1000, 200);
    let counts_per_amp = 1e6 / f64::from(config.current_ua_per_count);
    let adc = |amps: f64| (f64::from(config.current_zero_count) + amps * counts_per_amp) as u16;
    // The first sample with ALIGNING clear: aligned, not yet enabled, phase A holding.
    let held = |seq: u32, i_a: f64, i_b: f64| {
        let s = Sample {
            adc_a: adc(i_a),
            adc_b: adc(i_b),
            duty_a: 2048,
            status: 0,
            ..RESTING
        };
        frame_bytes(seq, Message::Sample(s))
    };
    let align_a = 1.0;
    for (seq, i_a, i_b, accepted) in [
        (1, -1.0, 0.0, false),
        (2, 0.0, 1.0, false),
        (3, 2.0, 0.0, false),
        (4, 1.0, 0.0, true),
    ] {
        let Event::State(st) = l.on_frame(&held(seq, i_a, i_b), 0) else {
            panic!("a state")
        };
        assert!((st.i_a_a - i_a).abs() < 1e-3 && (st.i_b_a - i_b).abs() < 1e-3);
        assert_eq!(
            holds_phase_a(st.i_a_a, st.i_b_a, align_a),
            accepted,
            "i_a {i_a} A, i_b {i_b} A"
        );
    }
}

#[test]
fn h9_an_encoder_offset_is_subtracted_modulo_2_32() {
    // An absolute encoder (no alignment) at 500 000 counts/rev counting the other way, its
    // zero 3 648 counts from the ±2^31 wrap.
    let offset: i64 = -2_147_480_000;
    let mut l = DriveLink::new(
        2000.0,
        400.0,
        EncoderCalibration {
            offset_counts: Some(offset),
            reverse: false,
            held_load: None,
        },
    );
    let mut config = stepdrive_drive_protocol::units::default_config(2000.0, 100, 99);
    config.counts_per_rev = 500_000;
    config.encoder_direction = -1;
    config.align_ms = 0;
    assert!(matches!(
        l.on_frame(&frame_bytes(0, Message::Config(config)), 0),
        Event::Config(_)
    ));
    // The first reading is 7 296 counts below the offset: across the wrap, a positive i32.
    let first = (offset as i32).wrapping_sub(7296);
    assert!(first > 2_147_000_000);
    let Event::State(st) = l.on_frame(&sample_at(1, first), 0) else {
        panic!("a state")
    };
    let rad = |counts: f64| -TAU * counts / 500_000.0;
    assert!(
        (st.theta_rad - rad(-7296.0)).abs() < 1e-12,
        "θ {} (2^32 counts are {} rad)",
        st.theta_rad,
        rad(4_294_967_296.0)
    );
    // Back across the wrap by differences.
    let Event::State(st) = l.on_frame(&sample_at(2, first.wrapping_add(7306)), 0) else {
        panic!("a state")
    };
    assert!(
        (st.theta_rad - rad(10.0)).abs() < 1e-12,
        "θ {}",
        st.theta_rad
    );
}

/// A link whose CONFIG (1 A / 300 ms alignment) was taken, with the Table I load, and whose
/// run started: θ at count 0 is θ₀ = −asin(0.02)/50.
fn running_link_under_load() -> DriveLink {
    let mut l = DriveLink::new(
        20_000.0,
        400.0,
        EncoderCalibration {
            offset_counts: None,
            reverse: false,
            held_load: Some(HeldLoad {
                torque_nm: 0.01,
                torque_constant_nm_per_a: 0.5,
                rotor_teeth: 50.0,
            }),
        },
    );
    let config = stepdrive_drive_protocol::units::default_config(20_000.0, 1000, 200);
    assert!(matches!(
        l.on_frame(&frame_bytes(0, Message::Config(config)), 0),
        Event::Config(_)
    ));
    l.restart();
    l
}

const THETA_0: f64 = -4.000_266_7e-4;

#[test]
fn h10_a_config_outside_the_handshake_is_never_applied() {
    let mut l = running_link_under_load();
    let theta =
        |l: &mut DriveLink, seq: u32, counts: i32| match l.on_frame(&sample_at(seq, counts), 0) {
            Event::State(st) => st.theta_rad,
            other => panic!("{other:?}"),
        };
    let theta_0 = theta(&mut l, 1, 0);
    assert!((theta_0 - THETA_0).abs() < 1e-9, "θ₀ {theta_0}");
    // The same CONFIG again (a late answer to a repeated HELLO): dropped and counted.
    let config = stepdrive_drive_protocol::units::default_config(20_000.0, 1000, 200);
    assert_eq!(
        l.on_frame(&frame_bytes(1, Message::Config(config)), 0),
        Event::Dropped
    );
    assert_eq!(theta(&mut l, 2, 0), theta_0, "θ₀ kept");
    let mut stats = StatsReport::default();
    l.copy_counters(&mut stats);
    assert_eq!(stats.bad_frames, 1);
    // A different one (half the counts per revolution): not applied; the session must end.
    let halved = Config {
        counts_per_rev: 1 << 19,
        ..config
    };
    let Event::ConfigChanged(change) = l.on_frame(&frame_bytes(2, Message::Config(halved)), 0)
    else {
        panic!("a changed CONFIG must end the session")
    };
    assert_eq!(
        (change.field, change.was, change.now),
        ("counts_per_rev", 1 << 20, 1 << 19)
    );
    assert!(Refusal::ConfigChanged(change)
        .to_string()
        .contains("counts_per_rev was 1048576, now 524288"));
    let quarter_turn = theta(&mut l, 3, 1 << 18);
    assert!(
        (quarter_turn - theta_0 - FRAC_PI_2).abs() < 1e-12,
        "still 2^20 counts/rev"
    );
}

/// The bridge core with the default scenario's motor (Table I) at `hz`, zeroing at the first
/// sample (or at `offset`).
fn bridge_core(hz: f64, offset: Option<i64>) -> BridgeCore {
    let s = Scenario::default();
    BridgeCore::new(CoreSettings {
        sample_hz: hz,
        samples: 1000,
        silence_periods: 200,
        plan_every: 1,
        observer_hz: 400.0,
        calibration: EncoderCalibration {
            offset_counts: offset,
            reverse: false,
            held_load: Some(HeldLoad {
                torque_nm: s.load.torque_nm,
                torque_constant_nm_per_a: s.motor.torque_constant_nm_per_a,
                rotor_teeth: s.motor.n_r(),
            }),
        },
        resistance_ohm: s.motor.resistance_ohm,
        rotor_teeth: s.motor.n_r(),
    })
}

fn wire(f: &Frame) -> Vec<u8> {
    let mut b = [0u8; MAX_FRAME];
    let n = encode(f, &mut b);
    b[..n].to_vec()
}

/// One look of the start-up at `now` (the stack there), with the frames it sent.
fn look(c: &mut BridgeCore, now: u64) -> (Result<StartStep, Refusal>, Vec<Frame>) {
    let mut sent = Vec::new();
    let step = c.startup(now, true, &mut |f| sent.push(*f));
    (step, sent)
}

#[test]
fn h11_every_exit_after_a_hello_sends_disable() {
    let mut c = bridge_core(20_000.0, None);
    assert!(
        c.farewell(0).is_none(),
        "before a HELLO there is nobody to tell"
    );
    let (step, sent) = look(&mut c, 0);
    assert_eq!(step, Ok(StartStep::Wait));
    assert_eq!(sent[0].message, Message::Hello);
    let bad = Config {
        encoder_direction: 0,
        ..stepdrive_drive_protocol::units::default_config(20_000.0, 1000, 200)
    };
    let mut stats = StatsReport::default();
    assert!(matches!(
        c.on_frame(&frame_bytes(0, Message::Config(bad)), 1, &mut stats),
        Received::BadConfig(_)
    ));
    // The node ends with the refusal; its exit path says goodbye.
    let f = c.farewell(2).expect("DISABLE after refusing a CONFIG");
    assert_eq!(f.message, Message::Control(Action::Disable));
}

#[test]
fn h12_a_drive_never_heard_is_named_within_the_handshake_time() {
    let ms = 1_000_000;
    // Nothing comes back (a drive sending from another port is heard as nothing: §2).
    let mut c = bridge_core(20_000.0, None);
    let mut hellos = 0;
    let mut t = 0;
    let report = loop {
        match look(&mut c, t) {
            (Ok(StartStep::Wait), sent) => hellos += sent.len(),
            (Err(Refusal::Handshake(r)), _) => break r,
            other => panic!("{other:?}"),
        }
        t += 10 * ms;
        assert!(
            t <= HANDSHAKE_NS + 100 * ms,
            "no verdict in the handshake time"
        );
    };
    assert!(t >= HANDSHAKE_NS && hellos >= 20, "{t} ns, {hellos} HELLOs");
    assert_eq!(report.frames, 0);
    let text = Refusal::Handshake(report).to_string();
    assert!(text.contains("no frame came"), "{text}");
    // A CONFIG with its reserved byte set: dropped, never read, and named.
    let mut c = bridge_core(20_000.0, None);
    assert_eq!(look(&mut c, 0).0, Ok(StartStep::Wait));
    let config = stepdrive_drive_protocol::units::default_config(20_000.0, 1000, 200);
    let mut bytes = frame_bytes(0, Message::Config(config));
    bytes[18 + 27] = 1;
    reseal(&mut bytes);
    let mut stats = StatsReport::default();
    for i in 0..30 {
        let now = i * 50 * ms;
        c.on_frame(&bytes, now, &mut stats);
        match look(&mut c, now) {
            (Ok(StartStep::Wait), _) => assert!(now < HANDSHAKE_NS),
            (Err(Refusal::Handshake(r)), _) => {
                assert_eq!(r.frames, i + 1);
                let text = Refusal::Handshake(r).to_string();
                assert!(
                    text.contains("CONFIG with its reserved byte (offset 27) set"),
                    "{text}"
                );
                return;
            }
            other => panic!("{other:?}"),
        }
    }
    panic!("no verdict")
}

/// The bridge's start-up (§7) against the emulated drive's core, period by period at
/// 20 kHz, frames both ways (the host's answer to S(k) reaches the drive before period
/// k + 1). Returns the verdict and every frame the host sent.
fn start_against(d: &mut EmulatedDrive, c: &mut BridgeCore) -> (Result<(), Refusal>, Vec<Frame>) {
    let mut stats = StatsReport::default();
    let mut all = Vec::new();
    for k in 0..100_000u64 {
        let now = k * 50_000;
        let f = d.sample_frame(now);
        let report = d.run_period(f.seq);
        c.on_frame(&wire(&f), now, &mut stats);
        if let Some(r) = report {
            let report = frame_bytes(d.report_seq(), Message::FaultReport(r));
            c.on_frame(&report, now, &mut stats);
        }
        let (step, sent) = look(c, now);
        for f in &sent {
            if let Some(Reply::Config(config)) = d.on_frame(&wire(f)) {
                let reply = frame_bytes(d.report_seq(), Message::Config(config));
                c.on_frame(&reply, now, &mut stats);
            }
        }
        all.extend(sent);
        match step {
            Ok(StartStep::Ready) => return (Ok(()), all),
            Err(e) => return (Err(e), all),
            Ok(_) => {}
        }
    }
    panic!("the start-up never ended")
}

#[test]
fn h13_a_swapped_phase_is_caught_before_the_run_by_the_phase_b_step() {
    // Wired as assumed: RESET, ALIGN, the hold, ENABLE and phase B alone (the rotor turns a
    // quarter electrical period towards +θ), ALIGN again; then the run starts with θ where
    // the rotor truly is.
    let mut d = drive();
    let mut c = bridge_core(20_000.0, None);
    let (verdict, sent) = start_against(&mut d, &mut c);
    verdict.expect("a drive wired as assumed passes");
    let controls: Vec<Action> = sent
        .iter()
        .filter_map(|f| match f.message {
            Message::Control(a) => Some(a),
            _ => None,
        })
        .collect();
    use Action::*;
    assert_eq!(controls, [Reset, Align, Enable, Align]);
    let commands = sent
        .iter()
        .filter(|f| matches!(f.message, Message::Command(c) if c.duty_a == 0 && c.duty_b > 0))
        .count();
    assert!(
        commands >= 6000,
        "phase B for align_ms: {commands} COMMANDs"
    );
    let enable = c.begin(0);
    d.on_frame(&wire(&enable));
    let f = d.sample_frame(0);
    let truth = d.truth(f.seq).expect("the run started");
    c.on_frame(&wire(&f), 0, &mut StatsReport::default());
    let st = *c.newest().expect("the run's first sample");
    assert_eq!(truth.k, 0);
    assert!(
        (st.theta_rad - truth.theta_rad).abs() < 1.2e-5,
        "host θ {} against the rotor's {} (2 counts)",
        st.theta_rad,
        truth.theta_rad
    );
    // Phase A's leads swapped: the drive's shunt still reads +1 A holding, the held-current
    // check passes, and the rotor rests half an electrical period off; driven on phase B it
    // turns a quarter period towards −θ. Refused before the run's ENABLE.
    let mut d = drive();
    AlignFault::SwappedLeads.apply(&mut d);
    let mut c = bridge_core(20_000.0, None);
    let (verdict, sent) = start_against(&mut d, &mut c);
    let Err(Refusal::PhaseStep { ratio, .. }) = verdict else {
        panic!("{verdict:?}")
    };
    assert!((ratio + 1.0).abs() < 0.05, "{ratio}");
    let enables = sent
        .iter()
        .filter(|f| f.message == Message::Control(Action::Enable))
        .count();
    assert_eq!(enables, 1, "only the step's ENABLE, never the run's");
}

/// A SAMPLE of a drive holding its aligned rotor, with the default CONFIG's scaling.
fn hold_sample(seq: u32, i_a: f64, i_b: f64, duty_a: i16, status_bits: u16) -> Vec<u8> {
    let config = stepdrive_drive_protocol::units::default_config(20_000.0, 1000, 200);
    let counts_per_amp = 1e6 / f64::from(config.current_ua_per_count);
    let adc =
        |amps: f64| (f64::from(config.current_zero_count) + amps * counts_per_amp).round() as u16;
    let s = Sample {
        adc_a: adc(i_a),
        adc_b: adc(i_b),
        duty_a,
        status: status_bits,
        ..RESTING
    };
    frame_bytes(seq, Message::Sample(s))
}

#[test]
fn h14_theta_zero_comes_from_the_held_current() {
    // The drive announced 1 A but holds 0.54 A: the load pulls the rotor further from the
    // electrical zero, −asin(0.01 / (0.5 × 0.54)) / 50.
    let mut l = DriveLink::new(
        20_000.0,
        400.0,
        EncoderCalibration {
            offset_counts: None,
            reverse: false,
            held_load: Some(HeldLoad {
                torque_nm: 0.01,
                torque_constant_nm_per_a: 0.5,
                rotor_teeth: 50.0,
            }),
        },
    );
    let config = stepdrive_drive_protocol::units::default_config(20_000.0, 1000, 200);
    l.on_frame(&frame_bytes(0, Message::Config(config)), 0);
    l.on_frame(&hold_sample(1, 0.54, 0.0, 11_000, status::ALIGNING), 0);
    for seq in 2..2 + HOLD_SAMPLES {
        l.on_frame(&hold_sample(seq, 0.54, 0.0, 11_000, 0), 0);
    }
    l.restart();
    let Event::State(st) = l.on_frame(&sample_at(100, 0), 0) else {
        panic!("a state")
    };
    let expected = -(0.01f64 / (0.5 * 0.54)).asin() / 50.0;
    assert!(
        (st.theta_rad - expected).abs() < 1e-6,
        "θ₀ {} against {expected} (from the announced 1 A: {THETA_0})",
        st.theta_rad
    );
}

/// The start-up, scripted up to the first hold's verdict: HELLO, `config`, the stack
/// ready, one SAMPLE aligning and then the hold, with phase A at `i_a` for a duty of
/// `duty_a`.
fn first_hold(
    c: &mut BridgeCore,
    config: Config,
    i_a: f64,
    duty_a: i16,
) -> Result<StartStep, Refusal> {
    let mut stats = StatsReport::default();
    look(c, 0).0?;
    c.on_frame(&frame_bytes(0, Message::Config(config)), 0, &mut stats);
    look(c, 1).0?;
    c.on_frame(
        &hold_sample(10, 1.0, 0.0, duty_a, status::ALIGNING),
        2,
        &mut stats,
    );
    look(c, 2).0?;
    for seq in 11..11 + HOLD_SAMPLES {
        c.on_frame(&hold_sample(seq, i_a, 0.0, duty_a, 0), 3, &mut stats);
    }
    look(c, 3).0
}

#[test]
fn h15_a_current_sense_off_scale_is_refused() {
    let config = stepdrive_drive_protocol::units::default_config(20_000.0, 1000, 200);
    // The duty that drives 1 A through the model's 14.8 Ω from 24 V.
    let duty = (14.8 / 24.0 * 32767.0_f64).round() as i16;
    for (i_a, accepted) in [(1.0, true), (0.74, true), (1.4, false), (0.55, false)] {
        let mut c = bridge_core(20_000.0, None);
        let verdict = first_hold(&mut c, config, i_a, duty);
        match (verdict, accepted) {
            (Ok(StartStep::Answer), true) => {}
            (Err(Refusal::CurrentScale { ratio, .. }), false) => {
                assert!((ratio - i_a).abs() < 1e-3, "{ratio}")
            }
            (other, _) => panic!("{i_a} A: {other:?}"),
        }
    }
}

#[test]
fn h16_a_drive_without_alignment_needs_an_encoder_offset() {
    let config = Config {
        align_ms: 0,
        ..stepdrive_drive_protocol::units::default_config(20_000.0, 1000, 200)
    };
    let mut stats = StatsReport::default();
    let mut c = bridge_core(20_000.0, None);
    assert_eq!(look(&mut c, 0).0, Ok(StartStep::Wait));
    c.on_frame(&frame_bytes(0, Message::Config(config)), 0, &mut stats);
    let (step, _) = look(&mut c, 1);
    assert_eq!(step, Err(Refusal::NoElectricalZero));
    // With the absolute encoder's offset: RESET, no ALIGN, and the run may begin.
    let mut c = bridge_core(20_000.0, Some(123));
    assert_eq!(look(&mut c, 0).0, Ok(StartStep::Wait));
    c.on_frame(&frame_bytes(0, Message::Config(config)), 0, &mut stats);
    let (step, sent) = look(&mut c, 1);
    assert_eq!(step, Ok(StartStep::Ready));
    let sent: Vec<Message> = sent.into_iter().map(|f| f.message).collect();
    assert_eq!(sent, [Message::Control(Action::Reset)]);
}

#[test]
fn h17_reserved_bits_of_status_and_fault_bits_are_read_not_dropped() {
    let mut l = configured_link();
    let s = Sample {
        status: status::ENABLED | 0x8000,
        fault_bits: 0x1000,
        ..RESTING
    };
    let Event::State(st) = l.on_frame(&frame_bytes(1, Message::Sample(s)), 0) else {
        panic!("a frame with reserved bits set is read (§4.1), not dropped as a reserved byte")
    };
    assert_eq!(
        st.fault >> 16,
        0x1000,
        "an unknown fault bit is still a fault"
    );
    assert_ne!(
        st.fault & stepdrive_shared::messages::fault_bits::DRIVE_FAULT,
        0
    );
}
