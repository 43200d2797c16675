//! The drive firmware for the ST NUCLEO-H743ZI2 (STM32H743ZI, Cortex-M7 at 480 MHz): the
//! host's drive core (`stepdrive-drive-core`, every rule of the drive's side of
//! docs/drive-protocol.md) over a real power stage: TIM1's PWM into two full bridges, two
//! phase currents and the bus voltage sampled by the ADCs at the PWM's centre, TIM4
//! counting a quadrature encoder; UDP on the board's Ethernet (embassy-net) as the link.
//!
//! Arranged as a motor drive's firmware is:
//! - **Sample clock: the hardware.** TIM1 runs the PWM, centre-aligned at `PWM_HZ`; its
//!   update event at each centre of the PWM (the counter's top and bottom) triggers the
//!   ADCs' injected conversions. The end of ADC1's conversions raises the ADC interrupt,
//!   the highest priority in the system; at every `SAMPLE_DIV`-th top (all low sides on,
//!   the current at its ripple's middle) it runs one period of the drive core:
//!   the frames the link received since the last period go to the core (they take effect
//!   before the sample, §4.1), the SAMPLE is taken, the period's duties are written to
//!   TIM1's preloaded compare registers and the bridges enabled or opened, and the SAMPLE
//!   (and a FAULT_REPORT, a CONFIG) is queued for the link. The interrupt never waits:
//!   the queues are lock-free, a full one drops and counts.
//! - **Network: thread mode.** embassy's executor runs the IP stack and the link task,
//!   which moves datagrams between the UDP socket and the two queues. The session's host
//!   is the address of the HELLO last answered (§2), kept by the sample interrupt with the
//!   core.
//! - **The duties start half a PWM period after their sample**: the compare registers
//!   are preloaded, and TIM1 loads them at its next update (the bottom after the sampling
//!   top), so the four legs change together and never mid-pulse. The period the protocol
//!   calls k therefore runs from T_pwm/2 after SAMPLE k (25 µs at 20 kHz PWM).
//! - **Log**: defmt over RTT (probe-rs shows it), the configuration at start and every
//!   second the core's counters and the sample interrupt's cost in core cycles.

#![no_std]
#![no_main]

mod board;
mod convert;
mod stage;

use core::cell::RefCell;
use core::sync::atomic::{AtomicU32, Ordering};
use defmt::{info, unwrap, warn};
use defmt_rtt as _;
use embassy_executor::Spawner;
use embassy_futures::select::{select, Either};
use embassy_net::udp::{PacketMetadata, UdpSocket};
use embassy_net::{IpEndpoint, Ipv4Address, Ipv4Cidr, Stack, StackResources};
use embassy_stm32::adc::{Adc, AdcChannel, AnyAdcChannel, Resolution, SampleTime};
use embassy_stm32::eth::{self, Ethernet, GenericPhy, PacketQueue};
use embassy_stm32::gpio::{Level, Output, OutputType, Speed};
use embassy_stm32::interrupt::{self, InterruptExt, Priority};
use embassy_stm32::pac;
use embassy_stm32::peripherals::{ADC1, ADC2, ETH, TIM1};
use embassy_stm32::time::Hertz;
use embassy_stm32::timer::low_level::{CountingMode, OutputCompareMode, Timer};
use embassy_stm32::timer::qei::{Qei, QeiPin};
use embassy_stm32::timer::simple_pwm::PwmPin;
use embassy_stm32::timer::{Ch1, Ch2, Ch3, Ch4, Channel};
use embassy_stm32::{bind_interrupts, Config};
use embassy_sync::blocking_mutex::raw::CriticalSectionRawMutex;
use embassy_sync::blocking_mutex::CriticalSectionMutex;
use embassy_sync::signal::Signal;
use heapless::spsc::{Consumer, Producer, Queue};
use panic_probe as _;
use static_cell::StaticCell;
use stepdrive_drive_core::{DriveCore, DriveCounters};
use stepdrive_drive_protocol::{encode, Frame, Message, MAX_FRAME};

bind_interrupts!(struct Irqs {
    ETH => eth::InterruptHandler;
});

/// The largest datagram taken: what a 1500-byte MTU carries in one IPv4 fragment (the IP
/// stack does not reassemble fragments, so nothing larger arrives).
const DATAGRAM: usize = 1472;
/// Received datagrams waiting for the next period (a COMMAND and now and then a PLAN
/// each period; a HELLO or CONTROL beside them). heapless' queue holds N − 1.
const RX_SLOTS: usize = 8;
/// Frames the drive sends, waiting for the link task (a SAMPLE a period, now and then a
/// FAULT_REPORT or CONFIG).
const TX_SLOTS: usize = 16;
/// The longest frame the drive sends: a CONFIG (22 + 28 bytes).
const TX_FRAME: usize = 64;
const PERIOD_NS: u64 = 1_000_000_000 / board::SAMPLE_HZ as u64;

/// A datagram from the link, for the core.
struct Datagram {
    from: IpEndpoint,
    len: u16,
    bytes: [u8; DATAGRAM],
}

/// A frame for the link.
struct Outgoing {
    to: IpEndpoint,
    len: u8,
    bytes: [u8; TX_FRAME],
}

/// What the sample interrupt owns: the drive core, the stage, the session's host.
struct Sampler {
    core: DriveCore,
    stage: stage::Stage,
    peer: Option<IpEndpoint>,
    rx: Consumer<'static, Datagram, RX_SLOTS>,
    tx: Producer<'static, Outgoing, TX_SLOTS>,
    /// Periods run: the sample index's clock (§3.2: a drive without a clock sends seq × T).
    periods: u64,
    scratch: [u8; MAX_FRAME],
}

static SAMPLER: CriticalSectionMutex<RefCell<Option<Sampler>>> =
    CriticalSectionMutex::new(RefCell::new(None));
/// The sample interrupt queued frames for the link.
static TX_READY: Signal<CriticalSectionRawMutex, ()> = Signal::new();
/// Counted for the log.
static RX_DROPPED: AtomicU32 = AtomicU32::new(0);
static TX_DROPPED: AtomicU32 = AtomicU32::new(0);
static TX_FAILED: AtomicU32 = AtomicU32::new(0);
static TOPS: AtomicU32 = AtomicU32::new(0);
static CYCLES_MAX: AtomicU32 = AtomicU32::new(0);
static CYCLES_SUM: AtomicU32 = AtomicU32::new(0);
static PERIODS_LOGGED: AtomicU32 = AtomicU32::new(0);

impl Sampler {
    /// One sample period, at the PWM centre that sampled it.
    fn period(&mut self) {
        let now_ns = self.periods * PERIOD_NS;
        // Every frame received before the sampling instant takes effect before it (§4.1).
        while let Some(d) = self.rx.dequeue() {
            let bytes = &d.bytes[..usize::from(d.len)];
            if let Some(c) = self.core.on_datagram(bytes, d.from, &mut self.peer) {
                let f = self.core.report_frame(Message::Config(c), now_ns);
                self.send(&f, d.from);
            }
        }
        let sample = self.core.sample_frame(now_ns, &mut self.stage);
        let report = self.core.run_period(sample.seq, &mut self.stage);
        let on = convert::bridges_enabled(self.stage.duty, self.core.outputs_on());
        self.stage.enable_bridges(on);
        // No session: nowhere to send (§2); the periods still run.
        if let (true, Some(peer)) = (self.core.in_session(), self.peer) {
            self.send(&sample, peer);
        }
        if let Some(r) = report {
            let f = self.core.report_frame(Message::FaultReport(r), now_ns);
            if let Some(peer) = self.peer {
                self.send(&f, peer);
            }
        }
        self.periods += 1;
    }

    fn send(&mut self, frame: &Frame, to: IpEndpoint) {
        let n = encode(frame, &mut self.scratch);
        let mut out = Outgoing {
            to,
            len: n as u8,
            bytes: [0; TX_FRAME],
        };
        // Only SAMPLE, CONFIG and FAULT_REPORT are sent: all shorter than TX_FRAME.
        let Some(src) = self.scratch.get(..n).filter(|_| n <= TX_FRAME) else {
            TX_DROPPED.fetch_add(1, Ordering::Relaxed);
            return;
        };
        out.bytes[..n].copy_from_slice(src);
        if self.tx.enqueue(out).is_err() {
            TX_DROPPED.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// ADC1 and ADC2's interrupt: the end of ADC1's injected conversions, triggered by TIM1's
/// update at each PWM centre.
#[cortex_m_rt::interrupt]
fn ADC() {
    let isr = pac::ADC1.isr().read();
    // Write one to clear.
    pac::ADC1.isr().write(|w| w.set_jeos(true));
    if !isr.jeos() {
        return;
    }
    // The update comes at the top and at the bottom: the top (the counter turned down) is
    // the sample's, and only every SAMPLE_DIV-th.
    if pac::TIM1.cr1().read().dir() != pac::timer::vals::Dir::DOWN {
        return;
    }
    if TOPS.fetch_add(1, Ordering::Relaxed) % board::SAMPLE_DIV != 0 {
        return;
    }
    let start = cortex_m::peripheral::DWT::cycle_count();
    SAMPLER.lock(|s| {
        if let Some(s) = s.borrow_mut().as_mut() {
            s.period();
        }
    });
    let cycles = cortex_m::peripheral::DWT::cycle_count().wrapping_sub(start);
    CYCLES_MAX.fetch_max(cycles, Ordering::Relaxed);
    CYCLES_SUM.fetch_add(cycles, Ordering::Relaxed);
    PERIODS_LOGGED.fetch_add(1, Ordering::Relaxed);
    TX_READY.signal(());
}

type Device = Ethernet<'static, ETH, GenericPhy>;

#[embassy_executor::task]
async fn net_task(mut runner: embassy_net::Runner<'static, Device>) -> ! {
    runner.run().await
}

/// Moves datagrams between the UDP socket and the sample interrupt's queues.
#[embassy_executor::task]
async fn link_task(
    stack: Stack<'static>,
    mut rx: Producer<'static, Datagram, RX_SLOTS>,
    mut tx: Consumer<'static, Outgoing, TX_SLOTS>,
) -> ! {
    static RX_META: StaticCell<[PacketMetadata; 16]> = StaticCell::new();
    static TX_META: StaticCell<[PacketMetadata; 16]> = StaticCell::new();
    static RX_BYTES: StaticCell<[u8; 16 * 1024]> = StaticCell::new();
    static TX_BYTES: StaticCell<[u8; 4 * 1024]> = StaticCell::new();
    let mut socket = UdpSocket::new(
        stack,
        RX_META.init([PacketMetadata::EMPTY; 16]),
        RX_BYTES.init([0; 16 * 1024]),
        TX_META.init([PacketMetadata::EMPTY; 16]),
        TX_BYTES.init([0; 4 * 1024]),
    );
    unwrap!(socket.bind(board::DRIVE_PORT));
    loop {
        while let Some(o) = tx.dequeue() {
            if socket
                .send_to(&o.bytes[..usize::from(o.len)], o.to)
                .await
                .is_err()
            {
                TX_FAILED.fetch_add(1, Ordering::Relaxed);
            }
        }
        let received = socket.recv_from_with(|data, meta| {
            let n = data.len().min(DATAGRAM);
            let mut d = Datagram {
                from: meta.endpoint,
                len: n as u16,
                bytes: [0; DATAGRAM],
            };
            // A datagram longer than any frame taken cannot be one: the core sees it cut,
            // and refuses it (its CRC).
            d.bytes[..n].copy_from_slice(&data[..n]);
            d
        });
        if let Either::First(d) = select(received, TX_READY.wait()).await {
            if rx.enqueue(d).is_err() {
                RX_DROPPED.fetch_add(1, Ordering::Relaxed);
            }
        }
    }
}

/// Every second: the core's counters and the sample interrupt's cost.
#[embassy_executor::task]
async fn log_task() -> ! {
    let mut last = DriveCounters::default();
    let mut last_faults = 0;
    loop {
        embassy_time::Timer::after_secs(1).await;
        let (c, faults_latched) = SAMPLER.lock(|s| {
            s.borrow()
                .as_ref()
                .map(|s| (s.core.counters, s.core.latched_faults()))
                .unwrap_or_default()
        });
        let n = PERIODS_LOGGED.swap(0, Ordering::Relaxed).max(1);
        let max = CYCLES_MAX.swap(0, Ordering::Relaxed);
        let mean = CYCLES_SUM.swap(0, Ordering::Relaxed) / n;
        info!(
            "periods {} | sample irq cycles max {} mean {} (period {}) | frames ok {} crc {} bad {} foreign {} stale {} | commands applied {} late {} held {} planned {} | rx dropped {} tx dropped {} tx failed {} | faults {=u16:#x}",
            n,
            max,
            mean,
            board_cycles_per_period(),
            c.frames_ok - last.frames_ok,
            c.crc_errors,
            c.bad_frames,
            c.foreign_frames,
            c.stale_frames,
            c.commands_applied - last.commands_applied,
            c.commands_late,
            c.periods_held,
            c.periods_planned,
            RX_DROPPED.load(Ordering::Relaxed),
            TX_DROPPED.load(Ordering::Relaxed),
            TX_FAILED.load(Ordering::Relaxed),
            faults_latched,
        );
        if faults_latched != last_faults && faults_latched != 0 {
            warn!(
                "faults latched {=u16:#x} (bit 0 WATCHDOG, 1 OVERCURRENT, 2 BUS_VOLTAGE, 3 BAD_COMMAND): the outputs are off until the host's RESET",
                faults_latched
            );
        }
        last = c;
        last_faults = faults_latched;
    }
}

const CORE_HZ: u32 = 480_000_000;

fn board_cycles_per_period() -> u32 {
    CORE_HZ / board::SAMPLE_HZ
}

#[embassy_executor::main]
async fn main(spawner: Spawner) {
    let mut config = Config::default();
    {
        use embassy_stm32::rcc::*;
        // 480 MHz from the 64 MHz HSI (the Ethernet PHY brings its own 50 MHz RMII clock;
        // nothing here needs a crystal's accuracy): VCO 16 MHz × 60 = 960 MHz, P / 2.
        config.rcc.hsi = Some(HSIPrescaler::DIV1);
        config.rcc.csi = true;
        config.rcc.pll1 = Some(Pll {
            source: PllSource::HSI,
            prediv: PllPreDiv::DIV4,
            mul: PllMul::MUL60,
            divp: Some(PllDiv::DIV2),
            divq: None,
            divr: None,
        });
        // The ADCs' kernel clock: 100 MHz, which embassy's driver halves to the 50 MHz
        // the ADC allows.
        config.rcc.pll2 = Some(Pll {
            source: PllSource::HSI,
            prediv: PllPreDiv::DIV4,
            mul: PllMul::MUL50,
            divp: Some(PllDiv::DIV8),
            divq: None,
            divr: None,
        });
        config.rcc.sys = Sysclk::PLL1_P;
        config.rcc.ahb_pre = AHBPrescaler::DIV2; // 240 MHz
        config.rcc.apb1_pre = APBPrescaler::DIV2; // 120 MHz, timers 240 MHz
        config.rcc.apb2_pre = APBPrescaler::DIV2; // 120 MHz, TIM1 240 MHz
        config.rcc.apb3_pre = APBPrescaler::DIV2;
        config.rcc.apb4_pre = APBPrescaler::DIV2;
        config.rcc.voltage_scale = VoltageScale::Scale0;
        config.rcc.mux.adcsel = mux::Adcsel::PLL2_P;
    }
    let p = embassy_stm32::init(config);

    let mut cp = unwrap!(cortex_m::Peripherals::take());
    cp.DCB.enable_trace();
    cp.DWT.enable_cycle_counter();
    // The instruction cache only: the data cache would need the Ethernet DMA's buffers
    // kept out of it (an MPU region), which embassy's driver does not set up.
    cp.SCB.enable_icache();

    let drive_config = board::config();
    let limits = board::limits(&drive_config);
    info!(
        "stepdrive drive firmware (NUCLEO-H743ZI2): {}.{}.{}.{}:{} | sample {} Hz, PWM {} Hz | counts/rev {} | {} uA/count, zero {} | bus {} uV/count | overcurrent {} counts, bus {}..{} counts | watchdog {} periods, plan {} entries",
        board::IP[0],
        board::IP[1],
        board::IP[2],
        board::IP[3],
        board::DRIVE_PORT,
        board::SAMPLE_HZ,
        board::PWM_HZ,
        drive_config.counts_per_rev,
        drive_config.current_ua_per_count,
        drive_config.current_zero_count,
        drive_config.bus_uv_per_count,
        limits.overcurrent_counts.unwrap_or(0),
        limits.bus_counts.map_or(0, |b| b.0),
        limits.bus_counts.map_or(0, |b| b.1),
        drive_config.watchdog_periods,
        drive_config.plan_capacity,
    );

    // ---- The bridges: enables low (every switch open) before anything switches.
    let enable_a = Output::new(p.PF13, Level::Low, Speed::Low);
    let enable_b = Output::new(p.PF12, Level::Low, Speed::Low);

    // ---- TIM1: four PWM channels, centre-aligned at PWM_HZ, each leg at 50 % (duty 0).
    let _pins = (
        PwmPin::<TIM1, Ch1>::new(p.PE9, OutputType::PushPull),
        PwmPin::<TIM1, Ch2>::new(p.PE11, OutputType::PushPull),
        PwmPin::<TIM1, Ch3>::new(p.PE13, OutputType::PushPull),
        PwmPin::<TIM1, Ch4>::new(p.PE14, OutputType::PushPull),
    );
    // The pins keep their alternate function for ever (nothing resets a pin it leaves).
    core::mem::forget(_pins);
    let pwm = Timer::new(p.TIM1);
    pwm.set_counting_mode(CountingMode::CenterAlignedBothInterrupts);
    // Up and down once a PWM period: the counter's rate is twice the PWM's.
    pwm.set_frequency(Hertz(2 * board::PWM_HZ));
    let arr = pwm.get_max_compare_value() as u16;
    if u32::from(arr) != board::TIM1_CLOCK_HZ / (2 * board::PWM_HZ) {
        warn!(
            "TIM1 reload {} is not TIM1_CLOCK_HZ / (2 PWM_HZ): check the clock tree",
            arr
        );
    }
    let (half, _) = convert::bridge_compares(0, arr);
    for ch in [Channel::Ch1, Channel::Ch2, Channel::Ch3, Channel::Ch4] {
        pwm.set_output_compare_mode(ch, OutputCompareMode::PwmMode1);
        pwm.set_output_compare_preload(ch, true);
        pwm.set_compare_value(ch, u32::from(half));
        pwm.enable_channel(ch, true);
    }
    pwm.set_autoreload_preload(true);
    // TRGO on every update (the PWM's top and bottom: the repetition counter stays 0), for
    // the ADCs. embassy's timer driver (0.4) has no master-mode setter.
    pac::TIM1
        .cr2()
        .modify(|w| w.set_mms(pac::timer::vals::Mms::UPDATE));
    pwm.enable_outputs();

    // ---- TIM4: the quadrature encoder (16 bits, extended to 32 in convert.rs).
    let encoder = Qei::new(p.TIM4, QeiPin::new(p.PD12), QeiPin::new(p.PD13));
    let count = convert::EncoderCount::new(encoder.count());

    // ---- ADC1 (phase A, then the bus) and ADC2 (phase B), 16 bits.
    let mut adc1 = Adc::new(p.ADC1);
    let mut adc2 = Adc::new(p.ADC2);
    for adc in [&mut adc1 as &mut dyn AdcSetup, &mut adc2] {
        adc.setup();
    }
    let mut phase_a: AnyAdcChannel<ADC1> = p.PA3.degrade_adc();
    let mut bus: AnyAdcChannel<ADC1> = p.PC0.degrade_adc();
    let mut phase_b: AnyAdcChannel<ADC2> = p.PB1.degrade_adc();
    // One software conversion each: embassy configures the channel (its pin analog, its
    // preselection and sample time); with the bridges open, the current readings are the
    // amplifiers' zero, which CONFIG states as `current_zero_count`.
    let zero_a = adc1.blocking_read(&mut phase_a);
    let zero_b = adc2.blocking_read(&mut phase_b);
    let bus_now = adc1.blocking_read(&mut bus);
    info!(
        "at rest: phase A {} phase B {} (CONFIG zero {}), bus {} counts",
        zero_a, zero_b, drive_config.current_zero_count, bus_now
    );
    let off = |z: u16| z.abs_diff(drive_config.current_zero_count);
    if off(zero_a) > 500 || off(zero_b) > 500 {
        warn!("a current reading at rest is far from CONFIG's zero: check board.rs (AMP_ZERO_MV) and the amplifiers' reference");
    }
    // Injected conversions on TIM1's TRGO (JEXTSEL 0: tim1_trgo, RM0433 "ADC injected
    // triggers"), rising edge: embassy's ADC driver for this ADC (v4) has no triggered
    // conversions. The queue of injected contexts off, so every trigger converts the
    // one sequence.
    let (ch_a, ch_b, ch_bus) = (
        phase_a.get_hw_channel(),
        phase_b.get_hw_channel(),
        bus.get_hw_channel(),
    );
    for (adc, ranks) in [(pac::ADC1, &[ch_a, ch_bus][..]), (pac::ADC2, &[ch_b][..])] {
        adc.cfgr().modify(|w| w.set_jqdis(true));
        adc.jsqr().write(|w| {
            w.set_jl(ranks.len() as u8 - 1);
            for (i, &ch) in ranks.iter().enumerate() {
                w.set_jsq(i, ch);
            }
            w.set_jextsel(0);
            w.set_jexten(pac::adc::vals::Exten::RISING_EDGE);
        });
        adc.cr().modify(|w| w.set_jadstart(true));
    }
    pac::ADC1.isr().write(|w| w.set_jeos(true));
    pac::ADC1.ier().modify(|w| w.set_jeosie(true));

    // ---- The link: Ethernet (the board's LAN8742A over RMII), a static address.
    static PACKETS: StaticCell<PacketQueue<4, 4>> = StaticCell::new();
    let device = Ethernet::new(
        PACKETS.init(PacketQueue::<4, 4>::new()),
        p.ETH,
        Irqs,
        p.PA1,  // REF_CLK
        p.PA2,  // MDIO
        p.PC1,  // MDC
        p.PA7,  // CRS_DV
        p.PC4,  // RXD0
        p.PC5,  // RXD1
        p.PG13, // TXD0
        p.PB13, // TXD1
        p.PG11, // TX_EN
        GenericPhy::new_auto(),
        board::MAC,
    );
    let [a, b, c, d] = board::IP;
    let net_config = embassy_net::Config::ipv4_static(embassy_net::StaticConfigV4 {
        address: Ipv4Cidr::new(Ipv4Address::new(a, b, c, d), board::PREFIX_LEN),
        gateway: board::GATEWAY.map(|[a, b, c, d]| Ipv4Address::new(a, b, c, d)),
        dns_servers: heapless::Vec::new(),
    });
    static RESOURCES: StaticCell<StackResources<2>> = StaticCell::new();
    // The seed only randomizes TCP's and DNS's choices, which the drive does not use.
    let (stack, runner) = embassy_net::new(
        device,
        net_config,
        RESOURCES.init(StackResources::new()),
        0x5d,
    );

    // ---- The queues between the link task and the sample interrupt, and the core.
    static RX_QUEUE: StaticCell<Queue<Datagram, RX_SLOTS>> = StaticCell::new();
    static TX_QUEUE: StaticCell<Queue<Outgoing, TX_SLOTS>> = StaticCell::new();
    let (rx_producer, rx_consumer) = RX_QUEUE.init(Queue::new()).split();
    let (tx_producer, tx_consumer) = TX_QUEUE.init(Queue::new()).split();
    let mut stage = stage::Stage {
        pwm,
        arr,
        encoder,
        count,
        enable_a,
        enable_b,
        duty: (0, 0),
        _adc1: adc1,
        _adc2: adc2,
    };
    stage.enable_bridges(false);
    let mut core = DriveCore::new(drive_config, board::align_duty(), limits);
    core.set_alignment(board::ALIGN_MA, board::ALIGN_MS, board::align_duty());
    SAMPLER.lock(|s| {
        s.replace(Some(Sampler {
            core,
            stage,
            peer: None,
            rx: rx_consumer,
            tx: tx_producer,
            periods: 0,
            scratch: [0; MAX_FRAME],
        }))
    });

    // The sample interrupt above everything; the IP stack's (Ethernet, the time driver's
    // TIM2) below it.
    interrupt::ETH.set_priority(Priority::P4);
    interrupt::TIM2.set_priority(Priority::P4);
    interrupt::ADC.set_priority(Priority::P0);
    // SAFETY: its handler touches only the sample state, behind SAMPLER's lock.
    unsafe { interrupt::ADC.enable() };
    // The counter starts: the PWM runs and the ADCs convert at every centre.
    stage_start();

    unwrap!(spawner.spawn(net_task(runner)));
    unwrap!(spawner.spawn(link_task(stack, rx_producer, tx_consumer)));
    unwrap!(spawner.spawn(log_task()));
}

/// Starts TIM1's counter, its preloaded registers loaded first (an update event by
/// software: embassy's timer driver (0.4) has no call for it).
fn stage_start() {
    pac::TIM1.egr().write(|w| w.set_ug(true));
    SAMPLER.lock(|s| {
        if let Some(s) = s.borrow().as_ref() {
            s.stage.pwm.start();
        }
    });
}

/// The ADC settings both converters share.
trait AdcSetup {
    fn setup(&mut self);
}

impl AdcSetup for Adc<'static, ADC1> {
    fn setup(&mut self) {
        self.set_resolution(Resolution::BITS16);
        self.set_sample_time(SampleTime::CYCLES16_5);
    }
}

impl AdcSetup for Adc<'static, ADC2> {
    fn setup(&mut self) {
        self.set_resolution(Resolution::BITS16);
        self.set_sample_time(SampleTime::CYCLES16_5);
    }
}
