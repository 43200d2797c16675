//! The power stage on the board: TIM1's four PWM channels into two full bridges, the
//! bridges' enable pins, TIM4 as the quadrature encoder, and the three ADC readings TIM1
//! triggers at the PWM's centre (main.rs sets that up).

use crate::convert::{bridge_compares, EncoderCount};
use embassy_stm32::adc::Adc;
use embassy_stm32::gpio::Output;
use embassy_stm32::pac;
use embassy_stm32::peripherals::{ADC1, ADC2, TIM1, TIM4};
use embassy_stm32::timer::low_level::Timer;
use embassy_stm32::timer::qei::Qei;
use embassy_stm32::timer::Channel;
use stepdrive_drive_core::{Measurement, PowerStage};

pub struct Stage {
    pub pwm: Timer<'static, TIM1>,
    /// TIM1's auto-reload: the counter runs 0 … arr … 0 each PWM period.
    pub arr: u16,
    pub encoder: Qei<'static, TIM4>,
    pub count: EncoderCount,
    /// The bridges' enables (DRV8412 RESET_AB and RESET_CD: low opens every switch).
    pub enable_a: Output<'static>,
    pub enable_b: Output<'static>,
    /// The duties the core drove this period.
    pub duty: (i16, i16),
    // Kept: dropping them would gate the ADCs' clock.
    pub _adc1: Adc<'static, ADC1>,
    pub _adc2: Adc<'static, ADC2>,
}

impl Stage {
    /// Opens or closes the bridges' switches as a whole (outputs off: high impedance).
    pub fn enable_bridges(&mut self, on: bool) {
        if on {
            self.enable_a.set_high();
            self.enable_b.set_high();
        } else {
            self.enable_a.set_low();
            self.enable_b.set_low();
        }
    }
}

impl PowerStage for Stage {
    fn drive(&mut self, duty: (i16, i16)) {
        self.duty = duty;
        let (a1, a2) = bridge_compares(duty.0, self.arr);
        let (b1, b2) = bridge_compares(duty.1, self.arr);
        // Preloaded: the four take effect together at TIM1's next update, the PWM's next
        // centre (main.rs: the period's duties start half a PWM period after its sample).
        self.pwm.set_compare_value(Channel::Ch1, u32::from(a1));
        self.pwm.set_compare_value(Channel::Ch2, u32::from(a2));
        self.pwm.set_compare_value(Channel::Ch3, u32::from(b1));
        self.pwm.set_compare_value(Channel::Ch4, u32::from(b2));
    }

    fn measure(&mut self) -> Measurement {
        // The injected conversions TIM1 triggered at this sample's PWM centre (embassy's ADC
        // driver has no timer-triggered conversions for this ADC; main.rs sets them up on
        // the registers): ADC1 rank 1 phase A, rank 2 the bus; ADC2 rank 1 phase B.
        // 16-bit results, as the protocol carries them.
        let adc_a = pac::ADC1.jdr(0).read().jdata() as u16;
        let adc_bus = pac::ADC1.jdr(1).read().jdata() as u16;
        let adc_b = pac::ADC2.jdr(0).read().jdata() as u16;
        Measurement {
            encoder_counts: self.count.update(self.encoder.count()),
            adc_a,
            adc_b,
            adc_bus,
        }
    }
}
