//! The period loop on a UDP socket: absolute deadlines on `Instant`, sleep until shortly
//! before each deadline and spin the rest, non-blocking reads, fault injection on SAMPLEs.

use std::net::{SocketAddr, UdpSocket};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use crate::core::DriveCore;
use crate::frame::MAX_FRAME_LEN;
use crate::{DriveError, DriveOptions, DriveStats};

/// xorshift64* PRNG for fault injection.
pub struct XorShift(u64);

impl XorShift {
    pub fn new(seed: u64) -> Self {
        XorShift(if seed == 0 {
            0x9E37_79B9_7F4A_7C15
        } else {
            seed
        })
    }
    pub fn next_u64(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        self.0 = x;
        x.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    /// true with probability pct / 100.
    pub fn chance(&mut self, pct: f64) -> bool {
        pct > 0.0 && ((self.next_u64() >> 11) as f64 / (1u64 << 53) as f64) * 100.0 < pct
    }
}

#[cfg(target_os = "linux")]
fn set_timer_slack_ns(ns: u64) {
    extern "C" {
        fn prctl(option: i32, ...) -> i32;
    }
    const PR_SET_TIMERSLACK: i32 = 29;
    // SAFETY: prctl(PR_SET_TIMERSLACK, ns) only changes this thread's timer slack.
    unsafe {
        prctl(PR_SET_TIMERSLACK, ns as std::ffi::c_ulong);
    }
}

#[cfg(not(target_os = "linux"))]
fn set_timer_slack_ns(_ns: u64) {}

fn send(sock: &UdpSocket, to: SocketAddr, bytes: &[u8], stats: &mut DriveStats) {
    if sock.send_to(bytes, to).is_err() {
        stats.send_errors += 1;
    }
}

/// Runs the drive until `stop` is set (or `opts.stop_after` periods).
pub fn serve(opts: &DriveOptions, stop: &AtomicBool) -> Result<DriveStats, DriveError> {
    opts.validate()?;
    let sock = UdpSocket::bind(&opts.listen)?;
    sock.set_nonblocking(true)?;
    set_timer_slack_ns(1000);
    let mut core = DriveCore::new(opts);
    let mut rng = XorShift::new(opts.seed);
    // the largest valid frame (a 1024-entry PLAN, 4 126 bytes) and some: a longer datagram
    // is truncated here and then fails the length check, as it must
    let mut buf = vec![0u8; MAX_FRAME_LEN + 64];
    let period_ns = 1_000_000_000u64 / opts.rate_hz as u64;
    let spin = Duration::from_micros(opts.spin_us);
    let start = Instant::now();
    let mut epoch = start;
    let mut k: u64 = 0;
    let mut extra_stats = DriveStats::default();

    let mut drain = |core: &mut DriveCore, extra: &mut DriveStats, now: Instant| {
        loop {
            match sock.recv_from(&mut buf) {
                Ok((n, from)) => {
                    let ns = now.duration_since(start).as_nanos() as u64;
                    core.on_frame(&buf[..n], from, ns);
                    if let Some(host) = core.session_host() {
                        for f in core.take_outbox() {
                            send(&sock, host, &f, extra);
                        }
                    }
                }
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => break,
                // e.g. ICMP port unreachable reported on a later call: ignore
                Err(_) => break,
            }
        }
    };

    loop {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        if opts.stop_after.is_some_and(|n| k >= n) {
            break;
        }
        let deadline = epoch + Duration::from_nanos(k * period_ns);
        let mut now;
        loop {
            now = Instant::now();
            drain(&mut core, &mut extra_stats, now);
            now = Instant::now();
            if now >= deadline {
                break;
            }
            let left = deadline - now;
            if left > spin {
                std::thread::sleep(left - spin);
            } else {
                std::hint::spin_loop();
            }
        }
        // a stall of this process longer than two periods: pause simulated time
        if now.duration_since(deadline) > Duration::from_nanos(2 * period_ns) {
            extra_stats.overruns += 1;
            epoch = now - Duration::from_nanos(k * period_ns);
        }
        let ns = now.duration_since(start).as_nanos() as u64;
        let seq = core.next_seq();
        let mut bytes = core.period(ns);
        if let Some(host) = core.session_host() {
            let run = core.run_index(seq);
            let mut send_it = true;
            if let Some(r) = run {
                if let Some(at) = opts.dropout_at {
                    if r >= at && r < at + opts.dropout_samples {
                        send_it = false;
                        extra_stats.samples_dropout += 1;
                    }
                }
                if send_it && rng.chance(opts.drop_pct) {
                    send_it = false;
                    extra_stats.samples_dropped_injected += 1;
                }
                if send_it && rng.chance(opts.corrupt_pct) {
                    let bit = (rng.next_u64() % (bytes.len() as u64 * 8)) as usize;
                    bytes[bit / 8] ^= 1 << (bit % 8);
                    extra_stats.samples_corrupted_injected += 1;
                }
            }
            if send_it {
                send(&sock, host, &bytes, &mut extra_stats);
            }
            for f in core.take_outbox() {
                send(&sock, host, &f, &mut extra_stats);
            }
        }
        if opts.verbose && k.is_multiple_of(opts.rate_hz as u64) {
            let m = core.motor().s;
            eprintln!(
                "t={:.1}s seq={} theta={:.5} omega={:.3} ia={:.3} ib={:.3} faults={:#x}",
                k as f64 / opts.rate_hz as f64,
                seq,
                m.theta,
                m.omega,
                m.ia,
                m.ib,
                core.fault_bits()
            );
        }
        k += 1;
    }
    let mut stats = core.stats.clone();
    stats.samples_dropout = extra_stats.samples_dropout;
    stats.samples_dropped_injected = extra_stats.samples_dropped_injected;
    stats.samples_corrupted_injected = extra_stats.samples_corrupted_injected;
    stats.overruns = extra_stats.overruns;
    stats.send_errors = extra_stats.send_errors;
    Ok(stats)
}
