//! The drive firmware for QEMU's mps2-an386 (Cortex-M4F): the host's drive core
//! (`stepdrive-drive-core`, every rule of the drive's side of docs/drive-protocol.md) with
//! its simulated power stage (the motor of eq. (1), `stepdrive-motor`), on the protocol's
//! two transports (§2): COBS frames on UART0 and UDP on the board's Ethernet (port 5555 at
//! 10.0.2.15, QEMU's user network), its periods timed by SysTick.
//!
//! Arranged as a small real firmware is: SysTick's interrupt is the sample clock and does
//! nothing but count periods; the links' receive interrupts only wake the core. The main
//! loop takes the frames the links received (they go to the core as they complete), runs
//! each period the clock has given, in order (SAMPLE out, then the period's duties into
//! the stage), and sleeps (WFI) until the next interrupt. A period found more than one tick
//! late still runs (the simulated motor keeps to the clock) and is counted. UART1 carries a
//! log: the configuration at start, then the core's counters every second. UART2 carries
//! the simulated rotor's true state at every sample of a run, as the emulated drive's truth
//! file (`k,t_s,theta_rad,omega_rad_s,i_a_a,i_b_a`), so that what the host reports can be
//! checked against what the motor did.

#![no_std]
#![no_main]

use core::fmt::Write;
use core::sync::atomic::{AtomicU32, Ordering};
use cortex_m::peripheral::syst::SystClkSource;
use cortex_m_rt::{entry, exception};
use link::{Links, Net};
use panic_halt as _;
use smoltcp::iface::{Config as NetConfig, Interface, SocketSet, SocketStorage};
use smoltcp::socket::udp;
use smoltcp::time::Instant;
use smoltcp::wire::{EthernetAddress, IpAddress, IpCidr, Ipv4Address};
use stepdrive_drive_core::simulated::{SimulatedDrive, StageParams, TRUTH_HEADER};
use stepdrive_drive_core::{DriveCore, Limits, Measurement, PowerStage};
use stepdrive_drive_protocol::units::default_config;
use stepdrive_drive_protocol::{encode, Action, Command, Frame, Message, Plan, MAX_FRAME};
use stepdrive_motor::{Disturbance, Motor};
use uart::Uart;

mod eth;
mod link;
mod uart;

/// The board's core clock, which SysTick counts (QEMU's mps2-an386: 25 MHz).
const CORE_HZ: u32 = 25_000_000;
// The sample rate: by default 2 kHz, what a UART-linked board carries (docs/drive-protocol.md
// §2); `run --rate HZ` builds another.
include!(concat!(env!("OUT_DIR"), "/sample_rate.rs"));
/// PLAN entries kept: the most one UDP datagram carries unfragmented on a 1500-byte MTU
/// (smoltcp here does not reassemble fragments; docs/drive-protocol.md §4.7). 208 entries
/// (0.1 s) were too few: a host at ordinary priority once went 208 periods without a
/// COMMAND, and the rotor stepped out on held duties.
const PLAN_CAPACITY: u16 = 360;
/// Periods without a COMMAND before the outputs go off and WATCHDOG latches: 0.176 s, the
/// plan's length less the host's 8 periods between PLANs, so that a plan covers every
/// period until the watchdog trips (§4.7).
const WATCHDOG_PERIODS: u16 = PLAN_CAPACITY - 8;

/// The drive's address on QEMU's user network, and the port it listens on.
const MAC: [u8; 6] = [0x02, 0x00, 0x5d, 0x00, 0x00, 0x01];
const IP: [u8; 4] = [10, 0, 2, 15];
const GATEWAY: [u8; 4] = [10, 0, 2, 2];
const DRIVE_PORT: u16 = 5555;

/// The default scenario's motor and load (docs/paper.md Table I; `[load] torque_nm`), as the
/// emulated drive simulates it for a scenario that leaves `[plant]` alone.
const MOTOR: Motor = Motor::TABLE_I;
const LOAD_NM: f64 = 0.01;
const BUS_V: f64 = 24.0;
/// RK4 steps a period: one (f64 arithmetic is in software on a Cortex-M4F; four steps cost
/// 57 % of the period in QEMU here). scenario-2khz.toml says the same to the host.
const SUBSTEPS: u32 = 1;

/// Periods the sample clock has given.
static TICKS: AtomicU32 = AtomicU32::new(0);

#[exception]
fn SysTick() {
    TICKS.fetch_add(1, Ordering::Relaxed);
}

/// The board's interrupts: UART0's and the Ethernet controller's receive interrupts are
/// unmasked; they woke the core, and the main loop reads what came.
#[exception]
unsafe fn DefaultHandler(_irq: i16) {
    // SAFETY: clearing UART0's interrupt status is all this does to it; the main loop,
    // which owns the UART otherwise, never touches that register.
    let mut uart0 = unsafe { Uart::at(Uart::UART0) };
    uart0.clear_interrupts();
    eth::Lan9118::clear_interrupt();
}

/// An interrupt line of this board.
#[derive(Clone, Copy)]
struct Irq(u16);

// SAFETY: the numbers given are the board's interrupt lines.
unsafe impl cortex_m::interrupt::InterruptNumber for Irq {
    fn number(self) -> u16 {
        self.0
    }
}

/// What the log reports every second.
#[derive(Default)]
struct Counts {
    late: u32,
    busy_max: u32,
    busy_sum: u64,
}

fn log_counters(log: &mut Uart, drive: &SimulatedDrive, links: &Links, n: &Counts) {
    let c = &drive.counters;
    log.line(b"frames ok ", c.frames_ok as i64);
    log.line(b"crc errors ", c.crc_errors as i64);
    log.line(b"bad frames ", c.bad_frames as i64);
    log.line(b"foreign frames ", c.foreign_frames as i64);
    log.line(b"framing errors ", i64::from(links.framing_errors()));
    log.line(b"serial bytes ", i64::from(links.serial_bytes));
    log.line(b"commands applied ", c.commands_applied as i64);
    log.line(b"commands late ", c.commands_late as i64);
    log.line(b"periods held ", c.periods_held as i64);
    log.line(b"periods planned ", c.periods_planned as i64);
    log.line(b"late periods ", i64::from(n.late));
    log.line(b"frames unsent ", i64::from(links.unsent));
    log.line(b"period cycles max ", i64::from(n.busy_max));
    log.line(
        b"period cycles mean ",
        (n.busy_sum / u64::from(SAMPLE_HZ)) as i64,
    );
    log.line(b"latched faults ", i64::from(drive.latched_faults()));
}

/// SysTick's count of core cycles into the current period.
fn now_cycles() -> (u32, u32) {
    // VAL counts down from the reload.
    let val = cortex_m::peripheral::SYST::get_current();
    (TICKS.load(Ordering::Relaxed), CORE_HZ / SAMPLE_HZ - 1 - val)
}

/// A power stage that costs nothing: the drive core's own cost, measured alone.
struct Still;

impl PowerStage for Still {
    fn drive(&mut self, _duty: (i16, i16)) {}

    fn measure(&mut self) -> Measurement {
        Measurement {
            encoder_counts: 0,
            adc_a: 32_768,
            adc_b: 32_768,
            adc_bus: 2_400,
        }
    }
}

/// Periods the core's cost is measured over, and how often a PLAN comes among them: the
/// host's current loop publishes a plan with every 10th COMMAND, and the bridge forwards
/// each (`[drive] plan_every = 1`).
const BENCH_PERIODS: u32 = 1_000;
const BENCH_PLAN_EVERY: u32 = 10;

/// The drive core's cost over [`BENCH_PERIODS`] periods, in core cycles by SysTick
/// (instructions × 1/40 under QEMU's `-icount shift=0`): each period the COMMAND answering
/// the last SAMPLE decoded (CRC included) and taken, every [`BENCH_PLAN_EVERY`]th period a
/// PLAN of [`PLAN_CAPACITY`] entries too, the SAMPLE built and encoded, the period run; the
/// stage and the link left out. The frames are made outside the measured spans (a host's
/// work, not the drive's). `None`: not measured.
fn bench_core(syst: &mut cortex_m::peripheral::SYST) -> Option<u32> {
    let mut core = DriveCore::new(
        default_config(f64::from(SAMPLE_HZ), WATCHDOG_PERIODS, PLAN_CAPACITY),
        0,
        Limits::default(),
    );
    let mut buf = [0u8; MAX_FRAME];
    let mut feed = |core: &mut DriveCore, seq: u32, message: Message| {
        let n = encode(
            &Frame {
                seq,
                timestamp_ns: 0,
                message,
            },
            &mut buf,
        );
        let _ = core.on_frame(&buf[..n]);
    };
    feed(&mut core, 1, Message::Hello);
    feed(&mut core, 2, Message::Control(Action::Enable));
    let mut command = [0u8; 32];
    let mut plan = [0u8; MAX_FRAME];
    syst.set_clock_source(SystClkSource::Core);
    syst.set_reload(0x00FF_FFFF);
    syst.clear_current();
    syst.enable_counter();
    let mut cycles = 0u32;
    let mut seq = 3;
    for k in 0..BENCH_PERIODS {
        // Each COMMAND answers the SAMPLE before the period it is for (SAMPLE seqs count
        // from 1); its PLAN continues it.
        let command_len = encode(
            &Frame {
                seq,
                timestamp_ns: 0,
                message: Message::Command(Command {
                    answers_sample: k,
                    duty_a: 1_000,
                    duty_b: -1_000,
                }),
            },
            &mut buf,
        );
        command[..command_len].copy_from_slice(&buf[..command_len]);
        let plan_len = (k % BENCH_PLAN_EVERY == 0).then(|| {
            let entries = (0..PLAN_CAPACITY).map(|j| [j as i16, -(j as i16)]);
            let message = Message::Plan(Plan::new(k, entries));
            encode(
                &Frame {
                    seq: seq + 1,
                    timestamp_ns: 0,
                    message,
                },
                &mut plan,
            )
        });
        seq += 2;
        let start = cortex_m::peripheral::SYST::get_current();
        let _ = core.on_frame(&command[..command_len]);
        if let Some(n) = plan_len {
            let _ = core.on_frame(&plan[..n]);
        }
        let sample = core.sample_frame(0, &mut Still);
        let n = encode(&sample, &mut buf);
        core::hint::black_box(&buf[..n]);
        let _ = core.run_period(sample.seq, &mut Still);
        // The 24-bit counter counts down, from the reload once started.
        let end = cortex_m::peripheral::SYST::get_current();
        cycles += start.wrapping_sub(end) & 0x00FF_FFFF;
    }
    syst.disable_counter();
    // Every COMMAND but the first (it answers no SAMPLE) applied, and the plans taken, or
    // the figure is not the cost of a commanded period. A count of 0: SysTick did not
    // count (QEMU at SCHED_FIFO on one CPU had not started its clock yet).
    let c = &core.counters;
    let taken = c.commands_applied + 1 >= u64::from(BENCH_PERIODS)
        && c.frames_ok == 2 + u64::from(BENCH_PERIODS + BENCH_PERIODS / BENCH_PLAN_EVERY);
    (taken && cycles > 0).then_some(cycles)
}

#[entry]
fn main() -> ! {
    // SAFETY: the board's UARTs, and only this loop drives them.
    let (line, mut log, mut truth) = unsafe {
        (
            Uart::enable(Uart::UART0),
            Uart::enable(Uart::UART1),
            Uart::enable(Uart::UART2),
        )
    };
    // The emulated drive's scaling and ALIGN (1 A for 300 ms), at this board's rate.
    let config = default_config(f64::from(SAMPLE_HZ), WATCHDOG_PERIODS, PLAN_CAPACITY);
    let stage = StageParams {
        motor: MOTOR,
        load: Disturbance::constant(LOAD_NM),
        sample_hz: f64::from(SAMPLE_HZ),
        substeps: SUBSTEPS,
        bus_v: BUS_V,
    };
    let mut drive = SimulatedDrive::new(config, stage, MOTOR.r);
    let _ = writeln!(truth, "{TRUTH_HEADER}");

    // The UDP link's buffers: never returned from, main's locals live for ever.
    let mut storage = [SocketStorage::EMPTY; 1];
    let (mut rx_meta, mut tx_meta) = (
        [udp::PacketMetadata::EMPTY; 16],
        [udp::PacketMetadata::EMPTY; 16],
    );
    let (mut rx_bytes, mut tx_bytes) = ([0u8; 16 * 1024], [0u8; 16 * 1024]);
    let net = eth::Lan9118::start(MAC).map(|mut eth| {
        let mut iface = Interface::new(
            NetConfig::new(EthernetAddress(MAC).into()),
            &mut eth,
            Instant::ZERO,
        );
        iface.update_ip_addrs(|a| {
            let _ = a.push(IpCidr::new(IpAddress::v4(IP[0], IP[1], IP[2], IP[3]), 24));
        });
        let _ = iface.routes_mut().add_default_ipv4_route(Ipv4Address::new(
            GATEWAY[0], GATEWAY[1], GATEWAY[2], GATEWAY[3],
        ));
        let mut socket = udp::Socket::new(
            udp::PacketBuffer::new(&mut rx_meta[..], &mut rx_bytes[..]),
            udp::PacketBuffer::new(&mut tx_meta[..], &mut tx_bytes[..]),
        );
        let _ = socket.bind(DRIVE_PORT);
        let mut sockets = SocketSet::new(&mut storage[..]);
        let udp = sockets.add(socket);
        Net {
            eth,
            iface,
            sockets,
            udp,
        }
    });
    let has_net = net.is_some();
    let mut links = Links::new(line, net);
    links.line.interrupt_on_receive();

    log.write(b"stepdrive drive firmware (qemu mps2-an386)\n");
    log.line(b"sample rate Hz ", i64::from(SAMPLE_HZ));
    log.line(b"watchdog periods ", i64::from(WATCHDOG_PERIODS));
    log.line(b"plan capacity ", i64::from(PLAN_CAPACITY));
    log.line(
        b"udp port ",
        if has_net { i64::from(DRIVE_PORT) } else { -1 },
    );

    let mut p = cortex_m::Peripherals::take().expect("taken once, at start");
    match bench_core(&mut p.SYST) {
        Some(cycles) => log.line(b"drive core cycles in 1000 periods ", i64::from(cycles)),
        None => {
            log.write(b"drive core cost not measured\n");
        }
    }
    // SAFETY: their handler (DefaultHandler) only clears the devices' interrupts.
    unsafe {
        cortex_m::peripheral::NVIC::unmask(Irq(Uart::UART0_RX_IRQ));
        cortex_m::peripheral::NVIC::unmask(Irq(eth::Lan9118::IRQ));
    }
    p.SYST.set_clock_source(SystClkSource::Core);
    p.SYST.set_reload(CORE_HZ / SAMPLE_HZ - 1);
    p.SYST.clear_current();
    p.SYST.enable_interrupt();
    p.SYST.enable_counter();

    let period_ns = 1_000_000_000 / u64::from(SAMPLE_HZ);
    let period_us = 1_000_000 / i64::from(SAMPLE_HZ);
    let mut frame = [0u8; MAX_FRAME];
    let mut done: u32 = 0;
    let mut counts = Counts::default();
    loop {
        let now = Instant::from_micros(i64::from(done) * period_us);
        while let Some((n, from)) = links.receive(now, &mut frame) {
            if let Some(c) = drive.on_datagram(&frame[..n], from, &mut links.peer) {
                let f = drive.report_frame(Message::Config(c), u64::from(done) * period_ns);
                links.send(&f, from, now);
            }
        }
        let ticks = TICKS.load(Ordering::Relaxed);
        if ticks.wrapping_sub(done) > 1 {
            counts.late += 1;
        }
        while done != ticks {
            let t0 = now_cycles();
            done = done.wrapping_add(1);
            let now_ns = u64::from(done) * period_ns;
            let now = Instant::from_micros(i64::from(done) * period_us);
            let sample = drive.sample_frame(now_ns);
            // No session: nowhere to send (§2), the periods still run.
            if let (true, Some(peer)) = (drive.in_session(), links.peer) {
                links.send(&sample, peer, now);
            }
            if let Some(t) = drive.truth(sample.seq) {
                let _ = writeln!(truth, "{t}");
            }
            if let Some(report) = drive.run_period(sample.seq) {
                let f = drive.report_frame(Message::FaultReport(report), now_ns);
                if let Some(peer) = links.peer {
                    links.send(&f, peer, now);
                }
            }
            let t1 = now_cycles();
            let cycles = i64::from(t1.0.wrapping_sub(t0.0)) * i64::from(CORE_HZ / SAMPLE_HZ)
                + i64::from(t1.1)
                - i64::from(t0.1);
            let cycles = cycles.max(0) as u32;
            counts.busy_max = counts.busy_max.max(cycles);
            counts.busy_sum += u64::from(cycles);
            if done % SAMPLE_HZ == 0 {
                log.line(b"t s ", i64::from(done / SAMPLE_HZ));
                log_counters(&mut log, &drive, &links, &counts);
                counts.busy_max = 0;
                counts.busy_sum = 0;
            }
        }
        // Interrupts masked between the last look and WFI: one that comes in between
        // still wakes it (a pending interrupt ends WFI whatever PRIMASK says).
        cortex_m::interrupt::free(|_| {
            if !links.pending() && TICKS.load(Ordering::Relaxed) == done {
                cortex_m::asm::wfi();
            }
        });
    }
}
