//! §9's drive cases D1–D17, scripted against the core: no clock, no socket.
//! Written from the spec's table; `S(k)` is SAMPLE k, `C(s, d)` a COMMAND answering s.
//! In the scripts a frame sent before `tick` arrives between S(k − 1) and S(k), k being
//! the seq that tick returns.

use std::net::SocketAddr;

use crate::core::DriveCore;
use crate::frame::{self, *};
use crate::DriveOptions;

const T_NS: u64 = 50_000;

struct Host {
    seq: u32,
    addr: SocketAddr,
    now: u64,
}

impl Host {
    fn new() -> Self {
        Host {
            seq: 0,
            addr: "127.0.0.1:50001".parse().expect("addr"),
            now: 0,
        }
    }
    fn send(&mut self, d: &mut DriveCore, p: Payload) -> u32 {
        self.seq += 1;
        let b = encode(self.seq, self.now, &p);
        d.on_frame(&b, self.addr, self.now);
        self.seq
    }
    fn hello(&mut self, d: &mut DriveCore) -> u32 {
        self.send(
            d,
            Payload::Hello {
                requested_version: 3,
            },
        )
    }
    fn control(&mut self, d: &mut DriveCore, action: u8) -> u32 {
        self.send(d, Payload::Control { action })
    }
    fn cmd(&mut self, d: &mut DriveCore, s: u32, duty: i16) -> u32 {
        self.send(
            d,
            Payload::Command {
                answers_sample: s,
                duty_a: duty,
                duty_b: duty,
            },
        )
    }
    /// One period: the SAMPLE it sends, decoded.
    fn tick(&mut self, d: &mut DriveCore) -> (u32, Sample) {
        self.now += T_NS;
        let b = d.period(self.now);
        let f = decode(&b).expect("the drive's SAMPLE decodes");
        match f.payload {
            Payload::Sample(s) => (f.seq, s),
            other => panic!("not a SAMPLE: {other:?}"),
        }
    }
}

fn opts() -> DriveOptions {
    DriveOptions {
        align_ms: 20,
        align_ma: 1000,
        watchdog_periods: 50,
        plan_capacity: 100,
        ..DriveOptions::default()
    }
}

fn configs(d: &mut DriveCore) -> Vec<Frame> {
    d.take_outbox()
        .iter()
        .map(|b| decode(b).expect("outbox frame decodes"))
        .collect()
}

/// Session, RESET, ALIGN to the end, ENABLE: returns the last sample's seq.
fn start(d: &mut DriveCore, h: &mut Host) -> u32 {
    h.hello(d);
    h.control(d, ACTION_RESET);
    h.control(d, ACTION_ALIGN);
    let mut last = 0;
    for _ in 0..(20 * 20 + 1) {
        last = h.tick(d).0;
    }
    h.control(d, ACTION_ENABLE);
    last
}

#[test]
fn d1_hello_config_new_session() {
    let mut d = DriveCore::new(&opts());
    let mut h = Host::new();
    h.hello(&mut d);
    let out = configs(&mut d);
    assert_eq!(out.len(), 1);
    let Payload::Config(c) = out[0].payload else {
        panic!("no CONFIG")
    };
    assert!(config_valid(&c));
    assert_eq!(c.sample_rate_hz, 20_000);
    assert_eq!(out[0].seq, 0, "CONFIG before the first SAMPLE has seq 0");
    for _ in 0..3 {
        h.tick(&mut d);
    }
    for _ in 0..499 {
        h.control(&mut d, ACTION_DISABLE);
    }
    assert_eq!(h.seq, 500);
    // a restarted host: seq 1 again
    let mut h2 = Host::new();
    h2.hello(&mut d);
    let out = configs(&mut d);
    assert_eq!(out.len(), 1);
    assert_eq!(out[0].seq, 2, "CONFIG carries the last SAMPLE's seq");
    h2.control(&mut d, ACTION_RESET);
    assert_eq!(d.stats.dropped_sequence, 0);
    assert_eq!(d.stats.sessions, 2);
}

#[test]
fn d2_samples_numbered_by_period() {
    let mut d = DriveCore::new(&opts());
    let mut h = Host::new();
    h.hello(&mut d);
    let first = h.tick(&mut d).0;
    for i in 1..100u32 {
        assert_eq!(h.tick(&mut d).0, first + i);
    }
}

#[test]
fn d3_command_applied_in_its_period_only() {
    let mut d = DriveCore::new(&opts());
    let mut h = Host::new();
    h.hello(&mut d);
    h.control(&mut d, ACTION_ENABLE);
    let (s, _) = h.tick(&mut d);
    let c = h.cmd(&mut d, s, 1000);
    let (s1, x1) = h.tick(&mut d); // S(s+1): the period before it had no COMMAND
    assert_eq!(s1, s + 1);
    assert_ne!(x1.applied_command_seq, c);
    let (_, x2) = h.tick(&mut d); // S(s+2) reports period s+1
    assert_eq!(x2.applied_command_seq, c);
    assert_eq!((x2.duty_a, x2.duty_b), (1000, 1000));
    assert_eq!(x2.status, STATUS_ENABLED);
    // C(s'−1) in period s'+1: too late
    let late = h.cmd(&mut d, s + 1, 2000); // answers S(s+1), arrives in period s+2
    let (_, x3) = h.tick(&mut d); // S(s+3): period s+2 had no COMMAND
    assert_eq!(x3.status, STATUS_ENABLED | STATUS_COMMAND_HELD);
    assert_eq!(x3.applied_command_seq, c);
    assert_ne!(x3.applied_command_seq, late);
    assert_eq!(d.stats.commands_late, 1);
    // a COMMAND for a newer sample keeps waiting
    let early = h.cmd(&mut d, s + 4, 3000);
    let (_, x4) = h.tick(&mut d);
    assert_eq!(x4.status & STATUS_COMMAND_HELD, STATUS_COMMAND_HELD);
    let (_, x5) = h.tick(&mut d);
    let (_, x6) = h.tick(&mut d);
    assert_eq!(x5.status & STATUS_COMMAND_HELD, STATUS_COMMAND_HELD);
    assert_eq!(x6.applied_command_seq, early);
}

#[test]
fn d4_invalid_and_out_of_sequence_frames_have_no_effect() {
    let mut d = DriveCore::new(&opts());
    let mut h = Host::new();
    h.hello(&mut d);
    // a bit flip of an ENABLE
    h.seq += 1;
    let mut b = encode(h.seq, 0, &Payload::Control { action: 1 });
    b[5] ^= 0x10;
    d.on_frame(&b, h.addr, 0);
    assert_eq!(d.stats.dropped_crc, 1);
    let (_, x) = h.tick(&mut d);
    let (_, x) = if x.status == 0 {
        h.tick(&mut d)
    } else {
        (0, x)
    };
    assert_eq!(x.status & STATUS_ENABLED, 0);
    // a duplicate and an older seq
    let en = encode(h.seq + 5, 0, &Payload::Control { action: 1 });
    d.on_frame(&en, h.addr, 0);
    let dis = encode(h.seq + 5, 0, &Payload::Control { action: 2 });
    d.on_frame(&dis, h.addr, 0);
    let dis_old = encode(h.seq + 4, 0, &Payload::Control { action: 2 });
    d.on_frame(&dis_old, h.addr, 0);
    assert_eq!(d.stats.dropped_sequence, 2);
    h.tick(&mut d);
    let (_, x) = h.tick(&mut d);
    assert_eq!(
        x.status & STATUS_ENABLED,
        STATUS_ENABLED,
        "DISABLEs were dropped"
    );
    // another source
    let other: SocketAddr = "127.0.0.1:50002".parse().expect("addr");
    let dis = encode(h.seq + 100, 0, &Payload::Control { action: 2 });
    d.on_frame(&dis, other, 0);
    assert_eq!(d.stats.dropped_wrong_source, 1);
    // garbage of every length
    for n in 0..64 {
        d.on_frame(&vec![0x44; n], h.addr, 0);
    }
    let (_, x) = h.tick(&mut d);
    assert_eq!(x.status & STATUS_ENABLED, STATUS_ENABLED);
}

#[test]
fn d5_every_state_as_the_table_says() {
    let mut d = DriveCore::new(&opts());
    let mut h = Host::new();
    h.hello(&mut d);
    h.tick(&mut d);
    // disabled
    let (_, x) = h.tick(&mut d);
    assert_eq!(
        (x.status, x.duty_a, x.duty_b, x.applied_command_seq),
        (0, 0, 0, 0)
    );
    // aligning
    h.control(&mut d, ACTION_ALIGN);
    h.tick(&mut d);
    let (_, x) = h.tick(&mut d);
    assert_eq!(x.status, STATUS_ALIGNING);
    assert!(x.duty_a > 0);
    assert_eq!((x.duty_b, x.applied_command_seq), (0, 0));
    let align_duty = x.duty_a;
    for _ in 0..400 {
        h.tick(&mut d);
    }
    // aligned, not enabled
    let (_, x) = h.tick(&mut d);
    assert_eq!(
        (x.status, x.duty_a, x.duty_b, x.applied_command_seq),
        (0, align_duty, 0, 0)
    );
    // aligned and enabled, holding
    h.control(&mut d, ACTION_ENABLE);
    h.tick(&mut d);
    let (s, x) = h.tick(&mut d);
    assert_eq!(
        (x.status, x.duty_a, x.duty_b, x.applied_command_seq),
        (STATUS_ENABLED | STATUS_COMMAND_HELD, align_duty, 0, 0)
    );
    // following
    let c = h.cmd(&mut d, s, 500);
    h.tick(&mut d);
    let (s, x) = h.tick(&mut d);
    assert_eq!(
        (x.status, x.duty_a, x.duty_b, x.applied_command_seq),
        (STATUS_ENABLED, 500, 500, c)
    );
    // faulted
    h.cmd(&mut d, s, i16::MIN);
    h.tick(&mut d);
    let (_, x) = h.tick(&mut d);
    assert_eq!(
        (x.status, x.duty_a, x.duty_b, x.applied_command_seq),
        (0, 0, 0, 0)
    );
    assert_eq!(x.fault_bits, FAULT_BAD_COMMAND);
}

#[test]
fn d6_watchdog_arms_at_first_command() {
    let o = opts();
    let n = o.watchdog_periods as u32;
    let mut d = DriveCore::new(&o);
    let mut h = Host::new();
    h.hello(&mut d);
    h.control(&mut d, ACTION_ENABLE);
    for _ in 0..3 * n {
        let (_, x) = h.tick(&mut d);
        assert_eq!(x.fault_bits, 0);
    }
    let s = d.next_seq() - 1;
    let c = h.cmd(&mut d, s, 100);
    h.tick(&mut d); // period s+1 gets the COMMAND
    let _ = c;
    let mut faulted_at = None;
    for i in 0..n + 3 {
        let (k, x) = h.tick(&mut d);
        if x.fault_bits != 0 {
            faulted_at = Some((i, k));
            break;
        }
    }
    let (i, _) = faulted_at.expect("WATCHDOG latched");
    // S(p+1) is i = 0; the N-th period without a COMMAND (p + N) is the first off, and
    // S(p + N + 1) the first SAMPLE with the bit (§5)
    assert_eq!(i, n);
    let reports = configs(&mut d);
    assert!(reports.iter().any(|f| matches!(
        f.payload,
        Payload::FaultReport {
            fault_bits: FAULT_WATCHDOG,
            ..
        }
    )));
}

#[test]
fn d7_bad_command_latches_and_applies_nothing() {
    let mut d = DriveCore::new(&opts());
    let mut h = Host::new();
    h.hello(&mut d);
    h.control(&mut d, ACTION_ENABLE);
    let (s, _) = h.tick(&mut d);
    h.cmd(&mut d, s, 700);
    let (s, _) = h.tick(&mut d);
    h.send(
        &mut d,
        Payload::Command {
            answers_sample: s,
            duty_a: 100,
            duty_b: i16::MIN,
        },
    );
    let (_, x) = h.tick(&mut d);
    assert_eq!(x.duty_a, 700, "the period before the latch ran on");
    let (_, x) = h.tick(&mut d);
    assert_eq!(x.fault_bits, FAULT_BAD_COMMAND);
    assert_eq!((x.duty_a, x.duty_b, x.status), (0, 0, 0));
    assert_eq!(d.stats.commands_applied, 1);
    // the same from a PLAN
    let mut d = DriveCore::new(&opts());
    let mut h = Host::new();
    h.hello(&mut d);
    h.control(&mut d, ACTION_ENABLE);
    let (s, _) = h.tick(&mut d);
    h.send(
        &mut d,
        Payload::Plan {
            answers_sample: s,
            entries: vec![(1, 1), (i16::MIN, 0)],
        },
    );
    h.tick(&mut d);
    let (_, x) = h.tick(&mut d);
    assert_eq!(x.fault_bits, FAULT_BAD_COMMAND);
}

#[test]
fn d8_faults_clear_only_on_reset_outputs_only_on_enable() {
    let mut d = DriveCore::new(&opts());
    let mut h = Host::new();
    h.hello(&mut d);
    h.control(&mut d, ACTION_ENABLE);
    let (s, _) = h.tick(&mut d);
    h.cmd(&mut d, s, i16::MIN);
    h.tick(&mut d);
    let (s, x) = h.tick(&mut d);
    assert_ne!(x.fault_bits, 0);
    h.cmd(&mut d, s, 100);
    h.tick(&mut d);
    let (_, x) = h.tick(&mut d);
    assert_ne!(x.fault_bits, 0, "a valid COMMAND never clears a fault");
    h.control(&mut d, ACTION_ENABLE);
    h.tick(&mut d);
    let (_, x) = h.tick(&mut d);
    assert_ne!(x.fault_bits, 0, "ENABLE does not clear a fault");
    h.control(&mut d, ACTION_RESET);
    h.tick(&mut d);
    let (s, x) = h.tick(&mut d);
    assert_eq!(
        (x.fault_bits, x.status, x.duty_a),
        (0, 0, 0),
        "RESET: still off"
    );
    h.cmd(&mut d, s, 100);
    h.tick(&mut d);
    let (_, x) = h.tick(&mut d);
    assert_eq!(x.status, 0, "no ENABLE yet");
    h.control(&mut d, ACTION_ENABLE);
    let (s, _) = h.tick(&mut d);
    let c = h.cmd(&mut d, s, 321);
    h.tick(&mut d);
    let (_, x) = h.tick(&mut d);
    assert_eq!(
        (x.status, x.duty_a, x.applied_command_seq),
        (STATUS_ENABLED, 321, c)
    );
}

#[test]
fn d9_align_from_anywhere() {
    for theta0 in [0.0, 0.01, -0.031, 0.0628 * 0.5 - 1e-3, 3.0, -7.77] {
        let o = DriveOptions {
            initial_angle: theta0,
            ..opts()
        };
        let mut d = DriveCore::new(&o);
        let mut h = Host::new();
        h.hello(&mut d);
        // a while with outputs off first (the load turns the rotor)
        for _ in 0..2000 {
            h.tick(&mut d);
        }
        h.control(&mut d, ACTION_RESET);
        h.control(&mut d, ACTION_ALIGN);
        let mut aligning = 0;
        let mut seen = false;
        let mut first_clear = None;
        for _ in 0..20 * 20 + 50 {
            let (_, x) = h.tick(&mut d);
            if x.status & STATUS_ALIGNING != 0 {
                aligning += 1;
                seen = true;
            } else if seen && first_clear.is_none() {
                first_clear = Some(x);
            }
        }
        assert_eq!(
            aligning,
            20 * 20_000 / 1000,
            "ALIGNING for align_ms × rate / 1000"
        );
        // §7 step 4's check on the first clear SAMPLE
        let x = first_clear.expect("ALIGNING cleared");
        let c = d.config();
        let ia = (x.adc_a as f64 - c.current_zero_count as f64) * c.current_ua_per_count as f64;
        let ib = (x.adc_b as f64 - c.current_zero_count as f64) * c.current_ua_per_count as f64;
        let i_align = c.align_current_ma as f64 * 1000.0;
        assert!(ia > 0.5 * i_align && ia < 1.5 * i_align, "i_a {ia} µA");
        assert!(ib.abs() <= 0.25 * i_align, "i_b {ib} µA");
        // hold a while longer, then the rotor is at an electrical zero, less the load's
        for _ in 0..4000 {
            h.tick(&mut d);
        }
        let m = d.motor();
        let e = m.s.theta * m.p.nr;
        let off = (e - (e / std::f64::consts::TAU).round() * std::f64::consts::TAU) / m.p.nr;
        let load_off = -(m.p.load / (m.p.km * 1.0)).asin() / m.p.nr;
        assert!(
            (off - load_off).abs() < 1e-6,
            "θ0 {theta0}: {off} from the zero, expected {load_off}"
        );
    }
}

#[test]
fn d10_newest_plan_fills_missing_commands() {
    let mut d = DriveCore::new(&opts());
    let mut h = Host::new();
    h.hello(&mut d);
    h.control(&mut d, ACTION_ENABLE);
    let (s, _) = h.tick(&mut d);
    h.cmd(&mut d, s, 10);
    let p = h.send(
        &mut d,
        Payload::Plan {
            answers_sample: s,
            entries: vec![(20, 21), (30, 31)],
        },
    );
    // an older PLAN later: ignored
    h.send(
        &mut d,
        Payload::Plan {
            answers_sample: s.wrapping_sub(1),
            entries: vec![(99, 99), (99, 99), (99, 99)],
        },
    );
    h.tick(&mut d); // S(s+1); period s+1 has the COMMAND
    let (_, x) = h.tick(&mut d); // S(s+2): period s+1
    assert_eq!((x.duty_a, x.status), (10, STATUS_ENABLED));
    // an equal PLAN replaces it (sent before period s+3 is decided, at the tick of S(s+3))
    let p2 = h.send(
        &mut d,
        Payload::Plan {
            answers_sample: s,
            entries: vec![(20, 21), (40, 41)],
        },
    );
    let (_, x) = h.tick(&mut d); // S(s+3) reports period s+2: entry 0 of the first PLAN
    assert_eq!((x.duty_a, x.duty_b), (20, 21));
    assert_eq!(
        x.status,
        STATUS_ENABLED | STATUS_COMMAND_HELD | STATUS_COMMAND_PLANNED
    );
    assert_eq!(x.applied_command_seq, p);
    let (_, x) = h.tick(&mut d); // period s+3: entry 1 of the replacement
    assert_eq!((x.duty_a, x.duty_b, x.applied_command_seq), (40, 41, p2));
    let (_, x) = h.tick(&mut d); // past the end: hold the last duties
    assert_eq!((x.duty_a, x.duty_b), (40, 41));
    assert_eq!(x.status, STATUS_ENABLED | STATUS_COMMAND_HELD);
    assert_eq!(d.stats.plans_ignored_older, 1);
    // more entries than plan_capacity: dropped, counted
    h.send(
        &mut d,
        Payload::Plan {
            answers_sample: s + 10,
            entries: vec![(1, 1); 101],
        },
    );
    assert_eq!(d.stats.dropped_plan_capacity, 1);
}

#[test]
fn run_starts_at_first_enabled_sample() {
    let mut d = DriveCore::new(&opts());
    let mut h = Host::new();
    let last = start(&mut d, &mut h);
    let (k, x) = h.tick(&mut d);
    assert_eq!(k, last + 1);
    assert_ne!(
        x.status & STATUS_ENABLED,
        0,
        "the SAMPLE after the ENABLE shows it (§4.1)"
    );
    assert_eq!(d.run_index(k), Some(0));
    let _ = frame::MAGIC;
}

fn fault_reports(d: &mut DriveCore) -> Vec<(u32, u16, u32)> {
    configs(d)
        .into_iter()
        .filter_map(|f| match f.payload {
            Payload::FaultReport {
                fault_bits,
                at_sample,
            } => Some((f.seq, fault_bits, at_sample)),
            _ => None,
        })
        .collect()
}

#[test]
fn d11_state_bits_next_sample_duties_one_later() {
    let mut d = DriveCore::new(&opts());
    let mut h = Host::new();
    h.hello(&mut d);
    h.tick(&mut d);
    // ENABLE between S(j − 1) and S(j) → S(j) ENABLED
    h.control(&mut d, ACTION_ENABLE);
    let (j, x) = h.tick(&mut d);
    assert_eq!(x.status & STATUS_ENABLED, STATUS_ENABLED);
    assert_eq!(d.run_index(j), Some(0));
    // following C(·, 1000)
    h.cmd(&mut d, j, 1000);
    let (s, _) = h.tick(&mut d);
    h.cmd(&mut d, s, 1000);
    let (s, x) = h.tick(&mut d);
    assert_eq!((x.duty_a, x.status), (1000, STATUS_ENABLED));
    configs(&mut d);
    // C(s, −32768) between S(k − 1) and S(k), k = s + 1
    let k = s + 1;
    h.cmd(&mut d, s, i16::MIN);
    let reps = fault_reports(&mut d);
    assert_eq!(reps.len(), 1);
    assert_eq!(reps[0].1, FAULT_BAD_COMMAND);
    assert_eq!(reps[0].2, k, "at_sample k");
    assert_eq!(reps[0].0, s, "the last SAMPLE sent");
    let (sk, x) = h.tick(&mut d);
    assert_eq!(sk, k);
    assert_eq!(x.fault_bits, FAULT_BAD_COMMAND);
    assert_eq!(x.status & STATUS_ENABLED, 0);
    assert_eq!((x.duty_a, x.duty_b), (1000, 1000), "period k − 1's duties");
    let (_, x) = h.tick(&mut d);
    assert_eq!((x.duty_a, x.duty_b, x.applied_command_seq), (0, 0, 0));
    assert_eq!(x.fault_bits, FAULT_BAD_COMMAND);
}

#[test]
fn d12_watchdog_latches_at_start_of_nth_period() {
    let o = opts();
    let n = o.watchdog_periods as u32;
    let mut d = DriveCore::new(&o);
    let mut h = Host::new();
    h.hello(&mut d);
    h.control(&mut d, ACTION_ENABLE);
    let (s, _) = h.tick(&mut d);
    let c = h.cmd(&mut d, s, 1000);
    let (p, _) = h.tick(&mut d); // period p = s + 1 applies the last COMMAND
    configs(&mut d);
    // S(p + 1) … S(p + N): periods p … p + N − 1, no bit; p + 1 … p + N − 1 held at 1000
    for i in 1..=n {
        let (k, x) = h.tick(&mut d);
        assert_eq!(k, p + i);
        assert_eq!(x.fault_bits, 0, "S(p + {i})");
        assert_eq!(x.status & STATUS_ENABLED, STATUS_ENABLED);
        assert_eq!((x.duty_a, x.duty_b, x.applied_command_seq), (1000, 1000, c));
        if i >= 2 {
            assert_eq!(x.status & STATUS_COMMAND_HELD, STATUS_COMMAND_HELD);
        }
        let reps = fault_reports(&mut d);
        if i < n {
            assert!(reps.is_empty(), "no report before period p + N");
        } else {
            assert_eq!(reps, vec![(p + n, FAULT_WATCHDOG, p + n)]);
        }
    }
    let (k, x) = h.tick(&mut d);
    assert_eq!(k, p + n + 1);
    assert_eq!(x.fault_bits, FAULT_WATCHDOG);
    assert_eq!((x.duty_a, x.duty_b, x.applied_command_seq), (0, 0, 0));
    assert_eq!(x.status, 0);
}

#[test]
fn d13_nothing_before_hello_nor_a_drive_kind() {
    let mut d = DriveCore::new(&opts());
    let mut h = Host::new();
    h.control(&mut d, ACTION_ENABLE); // seq 1, before any HELLO
    assert_eq!(d.stats.dropped_no_session, 1);
    assert!(d.session_host().is_none());
    assert!(
        d.take_outbox().is_empty(),
        "nothing to send, nowhere to send it"
    );
    let (k0, x) = h.tick(&mut d);
    assert_eq!((x.status, x.duty_a, x.duty_b), (0, 0, 0), "outputs off");
    let (k1, _) = h.tick(&mut d);
    assert_eq!(k1, k0 + 1, "the sample index advances without a session");
    h.hello(&mut d); // seq 2
    configs(&mut d);
    let smp = encode(
        1000,
        0,
        &Payload::Sample(Sample {
            encoder_counts: 0,
            adc_a: 0,
            adc_b: 0,
            adc_bus: 0,
            duty_a: 0,
            duty_b: 0,
            applied_command_seq: 0,
            fault_bits: 0,
            status: 0,
        }),
    );
    d.on_frame(&smp, h.addr, 0);
    assert_eq!(d.stats.dropped_wrong_direction, 1);
    let seq = h.control(&mut d, ACTION_ENABLE);
    assert_eq!(seq, 3);
    assert_eq!(d.stats.dropped_sequence, 0, "seq 3 accepted");
    let (_, x) = h.tick(&mut d);
    assert_eq!(x.status & STATUS_ENABLED, STATUS_ENABLED);
}

#[test]
fn d14_disable_and_reset_discard_plan_and_waiting_command() {
    for action in [ACTION_DISABLE, ACTION_RESET] {
        let mut d = DriveCore::new(&opts());
        let mut h = Host::new();
        h.hello(&mut d);
        h.control(&mut d, ACTION_ENABLE);
        let (s, _) = h.tick(&mut d);
        h.cmd(&mut d, s, 7000);
        h.send(
            &mut d,
            Payload::Plan {
                answers_sample: s,
                entries: vec![(2000, 2000), (3000, 3000), (4000, 4000)],
            },
        );
        h.control(&mut d, action);
        h.control(&mut d, ACTION_ENABLE);
        h.tick(&mut d); // S(s + 1)
        for i in 2..6 {
            let (_, x) = h.tick(&mut d); // reports period s + i − 1
            assert_eq!(
                x.status,
                STATUS_ENABLED | STATUS_COMMAND_HELD,
                "action {action}, S(s + {i})"
            );
            assert_eq!((x.duty_a, x.duty_b, x.applied_command_seq), (0, 0, 0));
        }
        assert_eq!(d.stats.commands_applied, 0);
        assert_eq!(d.stats.periods_planned, 0);
    }
}

#[test]
fn d15_enable_and_align_ignored_while_faulted() {
    let mut d = DriveCore::new(&opts());
    let mut h = Host::new();
    h.hello(&mut d);
    h.control(&mut d, ACTION_ENABLE);
    let (s, _) = h.tick(&mut d);
    h.cmd(&mut d, s, 900);
    let (s, _) = h.tick(&mut d);
    h.cmd(&mut d, s, i16::MIN);
    h.tick(&mut d);
    h.control(&mut d, ACTION_ALIGN);
    h.control(&mut d, ACTION_ENABLE);
    assert_eq!(d.stats.controls_ignored, 2);
    for _ in 0..5 {
        let (_, x) = h.tick(&mut d);
        assert_eq!(x.status & (STATUS_ALIGNING | STATUS_ENABLED), 0);
        assert_eq!((x.duty_a, x.duty_b), (0, 0));
        assert_eq!(x.fault_bits, FAULT_BAD_COMMAND);
    }
    h.control(&mut d, ACTION_RESET);
    h.control(&mut d, ACTION_ENABLE);
    let (j, x) = h.tick(&mut d);
    assert_eq!(
        (x.fault_bits, x.status & STATUS_ENABLED),
        (0, STATUS_ENABLED)
    );
    let c = h.cmd(&mut d, j, 500);
    h.tick(&mut d);
    let (_, x) = h.tick(&mut d);
    assert_eq!(
        (x.status, x.duty_a, x.applied_command_seq),
        (STATUS_ENABLED, 500, c),
        "outputs on"
    );
}

#[test]
fn d16_one_fault_report_per_new_bits() {
    let o = opts();
    let n = o.watchdog_periods as u32;
    let mut d = DriveCore::new(&o);
    let mut h = Host::new();
    h.hello(&mut d);
    h.control(&mut d, ACTION_ENABLE);
    let (s, _) = h.tick(&mut d);
    h.cmd(&mut d, s, 100);
    let (s, _) = h.tick(&mut d); // armed
    configs(&mut d);
    h.cmd(&mut d, s, i16::MIN);
    let mut reps = fault_reports(&mut d);
    for _ in 0..n {
        h.tick(&mut d);
        reps.extend(fault_reports(&mut d));
    }
    assert_eq!(
        reps.len(),
        1,
        "the watchdog does not add a second: {reps:?}"
    );
    assert_eq!(reps[0].1, FAULT_BAD_COMMAND);
    // an over-current: a report with both bits, shown by the SAMPLE that found it
    d.motor_mut().s.ia = 5.0;
    let (k, x) = h.tick(&mut d);
    assert_eq!(x.fault_bits, FAULT_BAD_COMMAND | FAULT_OVERCURRENT);
    let reps = fault_reports(&mut d);
    assert_eq!(
        reps,
        vec![(k, FAULT_BAD_COMMAND | FAULT_OVERCURRENT, k)],
        "both bits, at_sample k"
    );
    // the current dies with the outputs off; no further report meanwhile
    for _ in 0..1000 {
        h.tick(&mut d);
    }
    assert!(fault_reports(&mut d).is_empty());
    // after RESET, BAD_COMMAND again → a report
    h.control(&mut d, ACTION_RESET);
    let (s, x) = h.tick(&mut d);
    assert_eq!(x.fault_bits, 0);
    h.cmd(&mut d, s, i16::MIN);
    let reps = fault_reports(&mut d);
    assert_eq!(reps.len(), 1);
    assert_eq!(reps[0].1, FAULT_BAD_COMMAND);
    assert_eq!(d.stats.fault_reports_sent, 3);
}

#[test]
fn d17_enable_during_align_finishes_it_applying_nothing() {
    let o = opts();
    let n = (o.align_ms as u32) * o.rate_hz / 1000;
    let mut d = DriveCore::new(&o);
    let mut h = Host::new();
    h.hello(&mut d);
    h.tick(&mut d);
    h.control(&mut d, ACTION_RESET);
    h.control(&mut d, ACTION_ALIGN);
    h.control(&mut d, ACTION_ENABLE);
    let mut aligning = 0;
    let mut first_clear = None;
    for _ in 0..n + 5 {
        let (k, x) = h.tick(&mut d);
        h.cmd(&mut d, k, 1234);
        if x.status & STATUS_ALIGNING != 0 {
            assert!(first_clear.is_none(), "ALIGNING in one stretch");
            assert_eq!(x.status & STATUS_ENABLED, STATUS_ENABLED);
            assert_eq!(x.applied_command_seq, 0);
            assert!(x.duty_a > 0 || aligning == 0);
            assert_eq!(x.duty_b, 0);
            aligning += 1;
        } else if first_clear.is_none() {
            assert_eq!(x.status & STATUS_ENABLED, STATUS_ENABLED);
            assert_eq!(x.applied_command_seq, 0, "the last aligning period");
            first_clear = Some(k);
        }
    }
    assert_eq!(aligning, n);
    assert!(first_clear.is_some());
    // the COMMAND answering the last ALIGNING SAMPLE was for an aligning period
    assert!(d.stats.commands_discarded_off >= n as u64 - 1);
    assert!(
        d.stats.commands_applied >= 1,
        "commands follow the alignment"
    );
}

#[test]
fn plan_of_1024_entries_kept() {
    let o = DriveOptions {
        plan_capacity: 1024,
        watchdog_periods: 1024,
        ..opts()
    };
    let mut d = DriveCore::new(&o);
    let mut h = Host::new();
    h.hello(&mut d);
    h.control(&mut d, ACTION_ENABLE);
    let (s, _) = h.tick(&mut d);
    let b = encode(
        h.seq + 1,
        0,
        &Payload::Plan {
            answers_sample: s,
            entries: vec![(5, 6); 1024],
        },
    );
    assert_eq!(b.len(), crate::frame::MAX_FRAME_LEN);
    h.seq += 1;
    d.on_frame(&b, h.addr, 0);
    assert_eq!(d.stats.plans_stored, 1);
}

// ---- v3.1 (issue 24): D18–D23 ----

/// ENABLE during an ALIGN: the run starts at the first SAMPLE with ENABLED set and
/// ALIGNING clear (§7 step 5), where the host's k = 0 is.
#[test]
fn d18_run_starts_at_first_enabled_sample_with_aligning_clear() {
    let o = opts();
    let n = (o.align_ms as u32) * o.rate_hz / 1000;
    let mut d = DriveCore::new(&o);
    let mut h = Host::new();
    h.hello(&mut d);
    h.control(&mut d, ACTION_ALIGN);
    h.control(&mut d, ACTION_ENABLE);
    for i in 0..n {
        let (k, x) = h.tick(&mut d);
        assert_ne!(x.status & STATUS_ALIGNING, 0);
        assert_eq!(d.run_index(k), None, "sample {i}: no run while aligning");
    }
    let (k, x) = h.tick(&mut d);
    assert_eq!(
        x.status & (STATUS_ENABLED | STATUS_ALIGNING),
        STATUS_ENABLED
    );
    assert_eq!(d.run_index(k), Some(0));
}

/// Aligned and enabled, no COMMAND yet: a PLAN entry does not end the hold (§4.3).
#[test]
fn d19_no_plan_entry_while_the_aligned_rotor_is_held() {
    let mut d = DriveCore::new(&opts());
    let mut h = Host::new();
    start(&mut d, &mut h);
    let (s, held) = h.tick(&mut d);
    h.send(
        &mut d,
        Payload::Plan {
            answers_sample: s,
            entries: vec![(3000, 3000), (4000, 4000), (5000, 5000)],
        },
    );
    h.tick(&mut d);
    h.tick(&mut d);
    let (_, x) = h.tick(&mut d); // reports period s + 2, entry 0's
    assert_eq!(x.status, STATUS_ENABLED | STATUS_COMMAND_HELD);
    assert_eq!(
        (x.duty_a, x.duty_b, x.applied_command_seq),
        (held.duty_a, 0, 0)
    );
    assert!(held.duty_a > 0);
}

/// DISABLE, RESET or HELLO between S(k − 1) and S(k): S(k) has ENABLED clear and period
/// k − 1's duties; S(k + 1) duties 0 (§4.1, "Mid-period").
#[test]
fn d20_disable_reset_hello_at_once_duties_a_period_later() {
    for action in [Some(ACTION_DISABLE), Some(ACTION_RESET), None] {
        let mut d = DriveCore::new(&opts());
        let mut h = Host::new();
        h.hello(&mut d);
        h.control(&mut d, ACTION_ENABLE);
        let (s, _) = h.tick(&mut d);
        let c = h.cmd(&mut d, s, 2000);
        h.tick(&mut d); // period s + 1 applies C(s)
        match action {
            Some(a) => {
                h.control(&mut d, a);
            }
            None => {
                h.hello(&mut d);
            }
        }
        let (_, x) = h.tick(&mut d);
        assert_eq!(x.status & STATUS_ENABLED, 0, "{action:?}");
        assert_eq!((x.duty_a, x.applied_command_seq), (2000, c), "{action:?}");
        let (_, x) = h.tick(&mut d);
        assert_eq!((x.duty_a, x.duty_b, x.applied_command_seq), (0, 0, 0));
    }
}

/// §4.6: a HELLO from another address does not take a live session over; once its host
/// lets go (DISABLE), it does.
#[test]
fn d21_a_live_session_is_not_taken_over() {
    let mut d = DriveCore::new(&opts());
    let mut h = Host::new();
    start(&mut d, &mut h);
    let (s, _) = h.tick(&mut d);
    h.cmd(&mut d, s, 800);
    h.tick(&mut d);
    let mut other = Host::new();
    other.addr = "127.0.0.1:50002".parse().expect("addr");
    other.hello(&mut d);
    assert_eq!(d.session_host(), Some(h.addr));
    assert_eq!(d.stats.dropped_wrong_source, 1);
    let (_, x) = h.tick(&mut d);
    assert_ne!(x.status & STATUS_ENABLED, 0, "still this host's motor");
    h.control(&mut d, ACTION_DISABLE);
    other.hello(&mut d);
    assert_eq!(d.session_host(), Some(other.addr));
}

/// §4.6: a HELLO stops an ALIGN.
#[test]
fn d22_hello_stops_an_align() {
    let mut d = DriveCore::new(&opts());
    let mut h = Host::new();
    h.hello(&mut d);
    h.control(&mut d, ACTION_ALIGN);
    h.tick(&mut d);
    assert_ne!(h.tick(&mut d).1.status & STATUS_ALIGNING, 0);
    h.hello(&mut d);
    let (_, x) = h.tick(&mut d);
    assert_eq!(x.status & STATUS_ALIGNING, 0);
    let (_, x) = h.tick(&mut d);
    assert_eq!((x.duty_a, x.duty_b), (0, 0));
}

/// §4.7: past a plan's end the last duties are held, COMMAND_HELD without
/// COMMAND_PLANNED, `applied_command_seq` the PLAN frame's.
#[test]
fn d23_past_a_plans_end_held_not_planned() {
    let mut d = DriveCore::new(&opts());
    let mut h = Host::new();
    h.hello(&mut d);
    h.control(&mut d, ACTION_ENABLE);
    let (s, _) = h.tick(&mut d);
    h.cmd(&mut d, s, 1000);
    let p = h.send(
        &mut d,
        Payload::Plan {
            answers_sample: s,
            entries: vec![(2000, 2000), (3000, 3000)],
        },
    );
    for _ in 0..4 {
        h.tick(&mut d);
    }
    let (_, x) = h.tick(&mut d); // period s + 4, past the end
    assert_eq!(x.status, STATUS_ENABLED | STATUS_COMMAND_HELD);
    assert_eq!((x.duty_a, x.applied_command_seq), (3000, p));
}
