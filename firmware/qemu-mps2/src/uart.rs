//! mps2-an386's UART0 (CMSDK APB UART at 0x4000_4000), transmit only, polled.

const BASE: usize = 0x4000_4000;
const DATA: *mut u32 = BASE as *mut u32;
const STATE: *const u32 = (BASE + 0x04) as *const u32;
const CTRL: *mut u32 = (BASE + 0x08) as *mut u32;
const TX_FULL: u32 = 1;
const TX_ENABLE: u32 = 1;
const RX_ENABLE: u32 = 2;

pub struct Uart0;

impl Uart0 {
    pub fn enable() -> Self {
        // SAFETY: UART0's registers on this board; nothing else touches them.
        unsafe {
            core::ptr::write_volatile(CTRL, TX_ENABLE | RX_ENABLE);
            // Without one read of the data register the host's first byte came ~1 s late
            // (measured in QEMU 7.2).
            let _ = core::ptr::read_volatile(DATA);
        }
        Self
    }

    pub fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            // SAFETY: as above.
            unsafe {
                while core::ptr::read_volatile(STATE) & TX_FULL != 0 {}
                core::ptr::write_volatile(DATA, u32::from(b));
            }
        }
    }

    /// `label` and `value` in decimal, then a newline.
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
