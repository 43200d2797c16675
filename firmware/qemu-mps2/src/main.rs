//! A first firmware: the host's drive core (`stepdrive-drive-core`) over the motor model
//! (`stepdrive-motor`) as its simulated power stage, on QEMU's mps2-an386 (Cortex-M4F).
//! It plays a fixed session into the core as frames (HELLO, ENABLE, then a COMMAND answering
//! each SAMPLE), runs the periods, and prints what the SAMPLEs said and where the rotor went
//! on UART0. Not yet the drive of issue 45 item 3: no serial transport, no SysTick clock.

#![no_std]
#![no_main]

use cortex_m_rt::entry;
use panic_halt as _;
use stepdrive_drive_core::{DriveCore, Limits, Measurement, PowerStage};
use stepdrive_drive_protocol::{encode, Action, Command, Config, Frame, Message, MAX_FRAME};
use stepdrive_motor::{Disturbance, Motor, MotorState, THETA};

mod uart;

const SAMPLE_HZ: u32 = 20_000;
const BUS_V: f64 = 24.0;
const COUNTS_PER_REV: u32 = 1 << 20;
const PERIODS: u32 = 2_000;

/// The motor of the paper's Table 1 behind two bridges, read back in drive units.
struct SimulatedStage {
    motor: Motor,
    load: Disturbance,
    x: MotorState,
}

impl PowerStage for SimulatedStage {
    fn drive(&mut self, duty: (i16, i16)) {
        let volts = |d: i16| f64::from(d) / f64::from(stepdrive_drive_protocol::MAX_DUTY) * BUS_V;
        let period = 1.0 / f64::from(SAMPLE_HZ);
        let v = [volts(duty.0), volts(duty.1)];
        self.x = self
            .motor
            .integrate_loaded(&self.x, v, &self.load, 0.0, period, 4);
    }

    fn measure(&mut self) -> Measurement {
        let counts = self.x[THETA] / core::f64::consts::TAU * f64::from(COUNTS_PER_REV);
        Measurement {
            encoder_counts: counts as i32,
            adc_a: 32_768,
            adc_b: 32_768,
            adc_bus: 24_000,
        }
    }
}

fn config() -> Config {
    Config {
        sample_rate_hz: SAMPLE_HZ,
        counts_per_rev: COUNTS_PER_REV,
        current_ua_per_count: 100,
        current_zero_count: 32_768,
        bus_uv_per_count: 1_000,
        watchdog_periods: 1_000,
        encoder_direction: 1,
        plan_capacity: 0,
        align_current_ma: 0,
        align_ms: 0,
        reserved: [0],
    }
}

/// Hands `message` to the core as the host's frame `seq`.
fn send(core: &mut DriveCore, seq: u32, message: Message) {
    let mut buf = [0u8; MAX_FRAME];
    let n = encode(
        &Frame {
            seq,
            timestamp_ns: 0,
            message,
        },
        &mut buf,
    );
    let _ = core.on_frame(&buf[..n]);
}

#[entry]
fn main() -> ! {
    let mut out = uart::Uart0::enable();
    let mut core = DriveCore::new(config(), 0, Limits::default());
    let mut stage = SimulatedStage {
        motor: Motor {
            l: 40e-3,
            r: 14.8,
            j: 8e-5,
            k_m: 0.5,
            n_r: 50.0,
            b: 5e-3,
        },
        load: Disturbance::constant(0.0),
        x: MotorState::zeros(),
    };
    send(&mut core, 0, Message::Hello);
    send(&mut core, 1, Message::Control(Action::Enable));
    let mut last_counts = 0;
    for k in 0..PERIODS {
        let frame = core.sample_frame(u64::from(k), &mut stage);
        if let Message::Sample(s) = frame.message {
            last_counts = s.encoder_counts;
        }
        // Phase A at a fifth of the bus: the rotor turns to, and rests at, its zero.
        send(
            &mut core,
            2 + k,
            Message::Command(Command {
                answers_sample: frame.seq,
                duty_a: 6_553,
                duty_b: 0,
            }),
        );
        let _ = core.run_period(frame.seq.wrapping_add(1), &mut stage);
    }
    out.line(b"periods ", PERIODS as i64);
    out.line(b"commands applied ", core.counters.commands_applied as i64);
    out.line(b"last encoder counts ", i64::from(last_counts));
    out.line(b"theta urad ", (stage.x[THETA] * 1e6) as i64);
    out.line(b"i_a uA ", (stage.x[2] * 1e6) as i64);
    out.write(b"done\n");
    loop {
        cortex_m::asm::wfi();
    }
}
