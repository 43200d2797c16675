//! Drive protocol conformance (docs/drive-protocol.md §8 and §9), written from the document:
//! its test vectors are read from the file itself, and each numbered item of §9 is one
//! scripted exchange, played against the emulated drive's core (D1–D23) or the bridge's
//! link (H1–H8). No clock, no sockets: frames in, frames out.

use std::f64::consts::{FRAC_PI_2, TAU};
use stepdrive_bridge::core::holds_phase_a;
use stepdrive_bridge::link::{DriveLink, EncoderCalibration, Event, HeldLoad};
use stepdrive_drive_protocol::{
    crc32, decode, encode, faults, frame_bytes, reseal, status, Action, Command, Config,
    FaultReport, Frame, Message, Plan, Sample, MAX_FRAME, MAX_PLAN_ENTRIES,
};
use stepdrive_emulated_drive::{DriveCore, Reply};
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

fn drive() -> DriveCore {
    DriveCore::new(&Scenario::default(), WATCHDOG, 8)
}

/// The host's frames, numbered from 1 as a host process does.
struct Host(u32);

impl Host {
    fn send(&mut self, d: &mut DriveCore, m: Message) -> Option<Reply> {
        self.0 += 1;
        d.on_frame(&frame_bytes(self.0, m))
    }
    fn control(&mut self, d: &mut DriveCore, a: Action) {
        self.send(d, Message::Control(a));
    }
    /// C(s, duty) on both phases; returns its frame seq.
    fn command(&mut self, d: &mut DriveCore, answers: u32, duty: i16) -> u32 {
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
fn period_reporting(d: &mut DriveCore) -> (u32, Sample, Option<FaultReport>) {
    let f = d.sample_frame(0);
    let report = d.run_period(f.seq);
    let Message::Sample(s) = f.message else {
        panic!("a SAMPLE")
    };
    (f.seq, s, report)
}

fn period(d: &mut DriveCore) -> (u32, Sample) {
    let (k, s, _) = period_reporting(d);
    (k, s)
}

fn hello(h: &mut Host, d: &mut DriveCore) -> Config {
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
    let mut d = [[0i16; 2]; MAX_PLAN_ENTRIES];
    for (slot, &x) in d.iter_mut().zip(duties) {
        *slot = [x, x];
    }
    Message::Plan(Plan {
        answers_sample: answers,
        count: duties.len() as u16,
        duties: d,
    })
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
fn following(d: &mut DriveCore) -> Host {
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
fn until_aligned(d: &mut DriveCore) -> (u32, Sample) {
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

// ---- the host (H1–H8), against the bridge's link ----

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
    // Without an alignment there is no offset to take out.
    config.align_ms = 0;
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
