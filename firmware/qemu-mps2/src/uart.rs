//! mps2-an386's CMSDK APB UARTs, polled: UART0 carries the drive protocol, UART1 the
//! firmware's log, UART2 the simulated rotor's true state.

const DATA: usize = 0x00;
const STATE: usize = 0x04;
const CTRL: usize = 0x08;
/// Interrupt status; a 1 written clears its bit.
const INT: usize = 0x0C;
const TX_FULL: u32 = 1;
const RX_FULL: u32 = 2;
const TX_ENABLE: u32 = 1;
const RX_ENABLE: u32 = 2;
const RX_INTERRUPT: u32 = 8;
/// Polls of a full transmitter before a frame is given up: the line's reader is gone or
/// stalled, and the sample loop must not wait on it (the host's watchdog and this drive's
/// catch what a lost frame means).
const TX_PATIENCE: u32 = 10_000;

pub struct Uart {
    base: usize,
}

impl Uart {
    pub const UART0: usize = 0x4000_4000;
    pub const UART1: usize = 0x4000_5000;
    pub const UART2: usize = 0x4000_6000;
    /// UART0's receive interrupt on this board (QEMU's mps2: RX at IRQ 0, TX at 1).
    pub const UART0_RX_IRQ: u16 = 0;

    /// The UART at `base`, as it is.
    ///
    /// # Safety
    /// `base` is one of this board's UARTs.
    pub unsafe fn at(base: usize) -> Self {
        Self { base }
    }

    /// # Safety
    /// `base` is one of this board's UARTs, and nothing else drives it.
    pub unsafe fn enable(base: usize) -> Self {
        let u = Self { base };
        u.set(CTRL, TX_ENABLE | RX_ENABLE);
        // Without one read of the data register the host's first byte came ~1 s late
        // (measured in QEMU 7.2).
        let _ = u.get(DATA);
        u
    }

    /// A received byte raises the UART's receive interrupt: it wakes the core from WFI.
    pub fn interrupt_on_receive(&mut self) {
        self.set(CTRL, self.get(CTRL) | RX_INTERRUPT);
    }

    /// Clears the UART's interrupts (their handler's work: the main loop reads the bytes).
    pub fn clear_interrupts(&mut self) {
        self.set(INT, 0b11);
    }

    /// Whether a received byte is waiting.
    pub fn received(&self) -> bool {
        self.get(STATE) & RX_FULL != 0
    }

    fn get(&self, reg: usize) -> u32 {
        // SAFETY: a register of the UART `enable` was given.
        unsafe { core::ptr::read_volatile((self.base + reg) as *const u32) }
    }

    fn set(&self, reg: usize, value: u32) {
        // SAFETY: as above.
        unsafe { core::ptr::write_volatile((self.base + reg) as *mut u32, value) }
    }

    /// A received byte, if one is waiting.
    pub fn read(&mut self) -> Option<u8> {
        self.received().then(|| self.get(DATA) as u8)
    }

    /// Sends `bytes`; false if the transmitter stayed full and the rest was dropped.
    pub fn write(&mut self, bytes: &[u8]) -> bool {
        for &b in bytes {
            let mut polls = 0;
            while self.get(STATE) & TX_FULL != 0 {
                polls += 1;
                if polls > TX_PATIENCE {
                    return false;
                }
            }
            self.set(DATA, u32::from(b));
        }
        true
    }

    /// `label` and `value` in decimal, then a newline (the log).
    pub fn line(&mut self, label: &[u8], value: i64) {
        self.write(label);
        if value < 0 {
            self.write(b"-");
        }
        let mut digits = [0u8; 20];
        let mut n = value.unsigned_abs();
        let mut i = digits.len();
        loop {
            i -= 1;
            digits[i] = b'0' + (n % 10) as u8;
            n /= 10;
            if n == 0 {
                break;
            }
        }
        self.write(&digits[i..]);
        self.write(b"\n");
    }
}

impl core::fmt::Write for Uart {
    fn write_str(&mut self, s: &str) -> core::fmt::Result {
        match self.write(s.as_bytes()) {
            true => Ok(()),
            false => Err(core::fmt::Error),
        }
    }
}
