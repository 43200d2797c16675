//! mps2-an386's Ethernet controller (an SMSC LAN9118 at 0x4020_0000) as a smoltcp device:
//! whole frames through its FIFOs, its receive interrupt waking the core. QEMU hands it
//! each frame whole (its UART model hands over a byte per main-loop wake-up, too few for
//! a COMMAND every period at 2 kHz).

use smoltcp::phy::{self, DeviceCapabilities, Medium};
use smoltcp::time::Instant;

const BASE: usize = 0x4020_0000;
const RX_DATA_FIFO: usize = 0x00;
const TX_DATA_FIFO: usize = 0x20;
const RX_STATUS_FIFO: usize = 0x40;
const TX_STATUS_FIFO: usize = 0x48;
const IRQ_CFG: usize = 0x54;
const INT_STS: usize = 0x58;
const INT_EN: usize = 0x5C;
const BYTE_TEST: usize = 0x64;
const TX_CFG: usize = 0x70;
const HW_CFG: usize = 0x74;
const RX_FIFO_INF: usize = 0x7C;
const TX_FIFO_INF: usize = 0x80;
const MAC_CSR_CMD: usize = 0xA4;
const MAC_CSR_DATA: usize = 0xA8;

/// IRQ_CFG: the interrupt line enabled, active high, push-pull.
const IRQ_ENABLE_HIGH: u32 = 0x100 | 0x10 | 0x01;
/// INT_STS / INT_EN: the receive status FIFO above its level (a frame came).
const RX_STATUS_LEVEL: u32 = 0x08;
const TX_ON: u32 = 0x02;
const SOFT_RESET: u32 = 0x01;
const MAC_CR: u32 = 1;
const MAC_ADDRH: u32 = 2;
const MAC_ADDRL: u32 = 3;
const MAC_RX_ENABLE: u32 = 0x04;
const MAC_TX_ENABLE: u32 = 0x08;
const MAC_CSR_BUSY: u32 = 0x8000_0000;
/// TX command A: the buffer is the frame's first and last segment.
const TX_FIRST_LAST: u32 = 0x2000 | 0x1000;

/// The largest Ethernet frame (without its CRC) this device passes.
pub const MTU: usize = 1514;

pub struct Lan9118 {
    rx: [u8; MTU + 4],
    tx: [u8; MTU],
    /// Frames the receive FIFO held that were too long for `rx` (dropped).
    pub oversized: u32,
}

fn get(reg: usize) -> u32 {
    // SAFETY: a register of this board's LAN9118.
    unsafe { core::ptr::read_volatile((BASE + reg) as *const u32) }
}

fn set(reg: usize, value: u32) {
    // SAFETY: as above.
    unsafe { core::ptr::write_volatile((BASE + reg) as *mut u32, value) }
}

fn mac_write(reg: u32, value: u32) {
    set(MAC_CSR_DATA, value);
    set(MAC_CSR_CMD, MAC_CSR_BUSY | reg);
}

impl Lan9118 {
    /// The LAN9118's receive interrupt on this board (QEMU's mps2-an385/386: IRQ 13).
    pub const IRQ: u16 = 13;

    /// Resets the controller, gives it `mac`, turns its transmitter and receiver on and
    /// its receive interrupt; `None` if no LAN9118 answers at its address.
    pub fn start(mac: [u8; 6]) -> Option<Self> {
        if get(BYTE_TEST) != 0x8765_4321 {
            return None;
        }
        set(HW_CFG, SOFT_RESET);
        mac_write(
            MAC_ADDRL,
            u32::from_le_bytes([mac[0], mac[1], mac[2], mac[3]]),
        );
        mac_write(MAC_ADDRH, u32::from(mac[4]) | u32::from(mac[5]) << 8);
        mac_write(MAC_CR, MAC_RX_ENABLE | MAC_TX_ENABLE);
        set(TX_CFG, TX_ON);
        set(IRQ_CFG, IRQ_ENABLE_HIGH);
        set(INT_EN, RX_STATUS_LEVEL);
        Some(Self {
            rx: [0; MTU + 4],
            tx: [0; MTU],
            oversized: 0,
        })
    }

    /// Clears the receive interrupt (its handler's work: the main loop reads the frames).
    pub fn clear_interrupt() {
        set(INT_STS, RX_STATUS_LEVEL);
    }

    /// Whether a received frame is waiting.
    pub fn received() -> bool {
        (get(RX_FIFO_INF) >> 16) & 0xFF != 0
    }

    /// The next received frame into `rx`, without its CRC: its length.
    fn pop_frame(&mut self) -> Option<usize> {
        while Self::received() {
            let status = get(RX_STATUS_FIFO);
            // With its CRC, which the FIFO holds too.
            let len = ((status >> 16) & 0x3FFF) as usize;
            let words = len.div_ceil(4);
            if len < 4 || len > self.rx.len() {
                for _ in 0..words {
                    let _ = get(RX_DATA_FIFO);
                }
                self.oversized = self.oversized.wrapping_add(1);
                continue;
            }
            for w in 0..words {
                let bytes = get(RX_DATA_FIFO).to_le_bytes();
                let at = w * 4;
                let n = 4.min(self.rx.len() - at);
                self.rx[at..at + n].copy_from_slice(&bytes[..n]);
            }
            return Some(len - 4);
        }
        None
    }

    fn send(frame: &[u8]) {
        set(TX_DATA_FIFO, TX_FIRST_LAST | frame.len() as u32);
        set(TX_DATA_FIFO, frame.len() as u32);
        for chunk in frame.chunks(4) {
            let mut word = [0u8; 4];
            word[..chunk.len()].copy_from_slice(chunk);
            set(TX_DATA_FIFO, u32::from_le_bytes(word));
        }
        // The TX status FIFO fills one entry a frame: drained here, nothing reads it.
        while (get(TX_FIFO_INF) >> 16) & 0xFF != 0 {
            let _ = get(TX_STATUS_FIFO);
        }
    }
}

pub struct Rx<'a>(&'a [u8]);
pub struct Tx<'a>(&'a mut [u8; MTU]);

impl phy::RxToken for Rx<'_> {
    fn consume<R, F: FnOnce(&[u8]) -> R>(self, f: F) -> R {
        f(self.0)
    }
}

impl phy::TxToken for Tx<'_> {
    fn consume<R, F: FnOnce(&mut [u8]) -> R>(self, len: usize, f: F) -> R {
        let len = len.min(MTU);
        let r = f(&mut self.0[..len]);
        Lan9118::send(&self.0[..len]);
        r
    }
}

impl phy::Device for Lan9118 {
    type RxToken<'a> = Rx<'a>;
    type TxToken<'a> = Tx<'a>;

    fn receive(&mut self, _now: Instant) -> Option<(Rx<'_>, Tx<'_>)> {
        let n = self.pop_frame()?;
        Some((Rx(&self.rx[..n]), Tx(&mut self.tx)))
    }

    fn transmit(&mut self, _now: Instant) -> Option<Tx<'_>> {
        Some(Tx(&mut self.tx))
    }

    fn capabilities(&self) -> DeviceCapabilities {
        let mut c = DeviceCapabilities::default();
        c.medium = Medium::Ethernet;
        c.max_transmission_unit = MTU;
        c
    }
}
