//! The drive wire protocol, version 3 (`docs/drive-protocol.md` is the specification; this
//! crate is its reference codec). The codec needs no `std` and no allocator, so a drive's
//! firmware can use this very code (`default-features = false`); with the default `std`
//! feature the crate adds the host side's byte transports ([`transport`]: UDP, serial) and
//! the unit conversions a CONFIG defines ([`units`]).
//!
//! Frames are little-endian with fixed fields:
//!
//! ```text
//! 0  u16 magic 0x5344      2  u8 version (3)     3  u8 kind
//! 4  u32 seq (drive: sample index; host: frame counter)
//! 8  u64 timestamp_ns (sender's monotonic clock)
//! 16 u16 payload_len       18 payload            18+n u32 CRC-32 of bytes 0..18+n
//! ```
//!
//! CRC-32/ISO-HDLC: polynomial 0x04C11DB7 (reflected 0xEDB88320), init 0xFFFFFFFF,
//! reflected in and out, final XOR 0xFFFFFFFF; check value of "123456789" is 0xCBF43926.
//! On UDP one datagram is one frame; on serial frames are COBS-encoded and end in 0x00.

#![cfg_attr(not(feature = "std"), no_std)]

#[cfg(feature = "std")]
pub mod transport;
pub mod units;

use thiserror::Error;

pub const MAGIC: u16 = 0x5344;
pub const VERSION: u8 = 3;
pub const HEADER_LEN: usize = 18;
pub const CRC_LEN: usize = 4;
/// Most entries one PLAN can carry: 51.2 ms at 20 kHz, longer than the default watchdog
/// (1000 periods), so that a drive which keeps this many never holds a stale duty while a
/// late host is still within its watchdog.
pub const MAX_PLAN_ENTRIES: usize = 1024;
/// PLAN payload: answers_sample, count, reserved, then 4 bytes an entry.
const PLAN_HEADER: usize = 8;
/// Largest frame of this version (a full PLAN).
pub const MAX_FRAME: usize = HEADER_LEN + PLAN_HEADER + 4 * MAX_PLAN_ENTRIES + CRC_LEN;

/// Drive fault bits (SAMPLE.fault_bits, FAULT_REPORT.fault_bits).
pub mod faults {
    /// No valid COMMAND for the watchdog's number of periods; outputs off until RESET.
    pub const WATCHDOG: u16 = 1 << 0;
    /// Phase current above the drive's limit; outputs off until RESET.
    pub const OVERCURRENT: u16 = 1 << 1;
    /// Bus voltage outside the drive's range.
    pub const BUS_VOLTAGE: u16 = 1 << 2;
    /// A COMMAND asked for a duty outside ±MAX_DUTY (rejected, not applied).
    pub const BAD_COMMAND: u16 = 1 << 3;

    /// The set bits by name ("WATCHDOG, OVERCURRENT"; an unknown bit by its value), for
    /// messages (no allocation: the codec builds without std).
    pub fn named(bits: u16) -> Named {
        Named(bits)
    }

    /// See [`named`].
    #[derive(Debug, Clone, Copy, PartialEq, Eq)]
    pub struct Named(pub u16);

    impl core::fmt::Display for Named {
        fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
            const NAMES: [(u16, &str); 4] = [
                (WATCHDOG, "WATCHDOG"),
                (OVERCURRENT, "OVERCURRENT"),
                (BUS_VOLTAGE, "BUS_VOLTAGE"),
                (BAD_COMMAND, "BAD_COMMAND"),
            ];
            let set = (0..16).map(|i| 1u16 << i).filter(|bit| self.0 & bit != 0);
            for (n, bit) in set.enumerate() {
                if n > 0 {
                    f.write_str(", ")?;
                }
                match NAMES.iter().find(|(b, _)| *b == bit) {
                    Some((_, name)) => f.write_str(name)?,
                    None => write!(f, "{bit:#06x}")?,
                }
            }
            Ok(())
        }
    }
}

/// SAMPLE.status bits.
pub mod status {
    /// Outputs are enabled (the bridge sent ENABLE and no fault is latched).
    pub const ENABLED: u16 = 1 << 0;
    /// The previous period's COMMAND was missing; the drive held the one before, or applied
    /// a PLAN entry ([`COMMAND_PLANNED`]).
    pub const COMMAND_HELD: u16 = 1 << 1;
    /// With [`COMMAND_HELD`]: the duties came from the PLAN.
    pub const COMMAND_PLANNED: u16 = 1 << 2;
    /// The drive is aligning the rotor (CONTROL ALIGN): phase A at the align current.
    pub const ALIGNING: u16 = 1 << 3;
}

/// Duty ±32767 means ±100 % of the bus voltage on that phase.
pub const MAX_DUTY: i16 = 32767;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Sample {
    /// Multi-turn encoder count (wraps at ±2^31).
    pub encoder_counts: i32,
    /// Raw phase-current ADC readings (offset binary).
    pub adc_a: u16,
    pub adc_b: u16,
    /// Raw bus-voltage ADC reading.
    pub adc_bus: u16,
    /// Duties applied over the period that ended at this sample.
    pub duty_a: i16,
    pub duty_b: i16,
    /// `seq` of the COMMAND frame applied over that period; 0 if none.
    pub applied_command_seq: u32,
    pub fault_bits: u16,
    pub status: u16,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Command {
    /// SAMPLE `seq` this command was computed from.
    pub answers_sample: u32,
    pub duty_a: i16,
    pub duty_b: i16,
}

/// Duties the host expects to send next, for a drive whose COMMAND is late: entry j is for
/// the period that starts at SAMPLE `answers_sample` + 2 + j (the period after the one the
/// COMMAND answering `answers_sample` is for). Entries past `count` are zero.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Plan {
    pub answers_sample: u32,
    /// 1 ..= MAX_PLAN_ENTRIES.
    pub count: u16,
    pub duties: [[i16; 2]; MAX_PLAN_ENTRIES],
}

impl Plan {
    /// The plan continuing the COMMAND that answers `answers_sample`: `entries` (the first
    /// [`MAX_PLAN_ENTRIES`] of them), (duty_a, duty_b) for the periods from
    /// `answers_sample + 2` on.
    pub fn new(answers_sample: u32, entries: impl IntoIterator<Item = [i16; 2]>) -> Self {
        let mut duties = [[0; 2]; MAX_PLAN_ENTRIES];
        let mut count = 0;
        for (slot, entry) in duties.iter_mut().zip(entries) {
            *slot = entry;
            count += 1;
        }
        Self {
            answers_sample,
            count,
            duties,
        }
    }

    pub fn entries(&self) -> &[[i16; 2]] {
        &self.duties[..usize::from(self.count).min(MAX_PLAN_ENTRIES)]
    }
}

/// A received PLAN, its entries still in the frame's bytes ([`decode_view`]): a drive takes
/// a frame every period, and a [`Plan`] held inline made every one of them a 4 KB copy.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PlanView<'a> {
    pub answers_sample: u32,
    /// 1 ..= MAX_PLAN_ENTRIES, the entries' count.
    pub count: u16,
    table: &'a [u8],
}

impl<'a> PlanView<'a> {
    /// (duty_a, duty_b) for the periods from `answers_sample + 2` on.
    pub fn entries(&self) -> impl ExactSizeIterator<Item = [i16; 2]> + 'a {
        self.table.chunks_exact(4).map(|e| {
            [
                i16::from_le_bytes([e[0], e[1]]),
                i16::from_le_bytes([e[2], e[3]]),
            ]
        })
    }

    pub fn to_plan(&self) -> Plan {
        Plan::new(self.answers_sample, self.entries())
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Action {
    Enable = 1,
    Disable = 2,
    /// Clears latched faults (outputs stay off until ENABLE).
    Reset = 3,
    /// Phase A at CONFIG's align current for its align time: the rotor comes to rest at an
    /// electrical zero (N_r θ ≡ 0 mod 2π); then outputs off, not enabled.
    Align = 4,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FaultReport {
    pub fault_bits: u16,
    /// SAMPLE seq at which the fault latched.
    pub at_sample: u32,
}

/// The drive's scaling, sent after HELLO: everything the bridge needs to convert units.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Config {
    pub sample_rate_hz: u32,
    pub counts_per_rev: u32,
    /// Phase-current scale, µA per ADC count, and the ADC reading at zero current.
    pub current_ua_per_count: u32,
    pub current_zero_count: u16,
    /// Bus-voltage scale, µV per ADC count.
    pub bus_uv_per_count: u32,
    pub watchdog_periods: u16,
    /// +1 if positive encoder counts are positive θ, −1 otherwise.
    pub encoder_direction: i8,
    /// PLAN entries the drive keeps; 0: it ignores PLAN frames (none are sent).
    pub plan_capacity: u16,
    /// Phase A current of an ALIGN, mA, and how long it is applied, ms (0 ms: the drive
    /// does not align; the host must know the encoder's electrical zero).
    pub align_current_ma: u16,
    pub align_ms: u16,
    pub reserved: [u8; 1],
}

/// A CONFIG field outside what the protocol allows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
#[error("CONFIG field {field} = {value} is invalid: {rule}")]
pub struct ConfigError {
    pub field: &'static str,
    pub value: i64,
    pub rule: &'static str,
}

impl Config {
    /// Checks every field against §4.5 of the specification, first failure first.
    pub fn check(&self) -> Result<(), ConfigError> {
        let rules: [(&'static str, i64, bool, &'static str); 9] = [
            (
                "sample_rate_hz",
                self.sample_rate_hz.into(),
                (100..=100_000).contains(&self.sample_rate_hz),
                "must be 100 … 100 000",
            ),
            (
                "counts_per_rev",
                self.counts_per_rev.into(),
                (4..=1 << 30).contains(&self.counts_per_rev),
                "must be 4 … 2^30",
            ),
            (
                "current_ua_per_count",
                self.current_ua_per_count.into(),
                self.current_ua_per_count > 0,
                "must be > 0",
            ),
            (
                "bus_uv_per_count",
                self.bus_uv_per_count.into(),
                self.bus_uv_per_count > 0,
                "must be > 0",
            ),
            (
                "watchdog_periods",
                self.watchdog_periods.into(),
                self.watchdog_periods >= 2,
                "must be ≥ 2 (1 would latch on any late COMMAND)",
            ),
            (
                "encoder_direction",
                self.encoder_direction.into(),
                self.encoder_direction == 1 || self.encoder_direction == -1,
                "must be +1 or −1",
            ),
            (
                "plan_capacity",
                self.plan_capacity.into(),
                usize::from(self.plan_capacity) <= MAX_PLAN_ENTRIES,
                "must be 0 … 1024",
            ),
            (
                "align_current_ma",
                self.align_current_ma.into(),
                self.align_ms == 0 || self.align_current_ma > 0,
                "must be > 0 when align_ms is",
            ),
            (
                "align_ms",
                self.align_ms.into(),
                self.align_ms == 0
                    || u64::from(self.align_ms) * u64::from(self.sample_rate_hz) >= 1000,
                "must last at least one sample period when not 0",
            ),
        ];
        match rules.into_iter().find(|r| !r.2) {
            Some((field, value, _, rule)) => Err(ConfigError { field, value, rule }),
            None => Ok(()),
        }
    }
}

/// A message; `P` is how a PLAN is held: a [`Plan`] of its own (what a host builds, what
/// [`decode`] gives) or a [`PlanView`] of the received bytes ([`decode_view`]).
// A Message lives on the stack of the wire path, which must not allocate: the 4 KB PLAN
// variant stays inline rather than boxed.
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Message<P = Plan> {
    /// drive → host, every period.
    Sample(Sample),
    /// host → drive, every period.
    Command(Command),
    /// host → drive.
    Control(Action),
    /// drive → host, when a fault latches.
    FaultReport(FaultReport),
    /// drive → host, answering HELLO.
    Config(Config),
    /// host → drive: announces the host (its UDP address) and asks for CONFIG.
    Hello,
    /// host → drive, every few periods when the drive keeps plans.
    Plan(P),
}

impl<P> Message<P> {
    pub fn kind(&self) -> u8 {
        match self {
            Message::Sample(_) => 1,
            Message::Command(_) => 2,
            Message::Control(_) => 3,
            Message::FaultReport(_) => 4,
            Message::Config(_) => 5,
            Message::Hello => 6,
            Message::Plan(_) => 7,
        }
    }

    /// The same message with its PLAN (if it is one) held as `f` makes it.
    pub fn map_plan<Q>(self, f: impl FnOnce(P) -> Q) -> Message<Q> {
        match self {
            Message::Sample(s) => Message::Sample(s),
            Message::Command(c) => Message::Command(c),
            Message::Control(a) => Message::Control(a),
            Message::FaultReport(r) => Message::FaultReport(r),
            Message::Config(c) => Message::Config(c),
            Message::Hello => Message::Hello,
            Message::Plan(p) => Message::Plan(f(p)),
        }
    }
}

impl Message {
    /// The payload length this message encodes to.
    fn payload_len(&self) -> usize {
        match self {
            Message::Plan(p) => PLAN_HEADER + 4 * p.entries().len(),
            _ => Self::fixed_len(self.kind()).unwrap_or(0),
        }
    }

    /// Payload length of the fixed-size kinds.
    fn fixed_len(kind: u8) -> Option<usize> {
        Some(match kind {
            1 => 22,
            2 => 8,
            3 => 4,
            4 => 8,
            5 => 28,
            6 => 4,
            _ => return None,
        })
    }

    /// Whether a payload of `len` bytes is valid for `kind` (PLAN: 8 + 4·count, count ≥ 1).
    fn valid_len(kind: u8, len: usize) -> Result<(), DecodeError> {
        let expected = match kind {
            7 => {
                let entries = len.saturating_sub(PLAN_HEADER) / 4;
                PLAN_HEADER + 4 * entries.clamp(1, MAX_PLAN_ENTRIES)
            }
            k => Self::fixed_len(k).ok_or(DecodeError::BadKind(k))?,
        };
        if expected == len {
            Ok(())
        } else {
            Err(DecodeError::BadLength {
                kind,
                expected,
                got: len,
            })
        }
    }
}

/// A decoded frame (`P` as in [`Message`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Frame<P = Plan> {
    pub seq: u32,
    pub timestamp_ns: u64,
    pub message: Message<P>,
}

#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum DecodeError {
    #[error("frame of {0} bytes is too short")]
    TooShort(usize),
    #[error("bad magic {0:#06x}")]
    BadMagic(u16),
    #[error("unsupported protocol version {0}")]
    BadVersion(u8),
    #[error("unknown message kind {0}")]
    BadKind(u8),
    #[error("kind {kind} needs a {expected}-byte payload, frame says {got}")]
    BadLength {
        kind: u8,
        expected: usize,
        got: usize,
    },
    #[error("frame length {frame} does not match payload length {payload}")]
    LengthMismatch { frame: usize, payload: usize },
    #[error("CRC mismatch: frame says {got:#010x}, computed {computed:#010x}")]
    BadCrc { got: u32, computed: u32 },
    #[error("invalid control action {0}")]
    BadAction(u8),
    #[error("PLAN says {count} entries in a payload of {len} bytes")]
    BadPlanCount { count: u16, len: usize },
    #[error("bad COBS encoding")]
    BadCobs,
    #[error("kind {0} frame with non-zero reserved bytes")]
    Reserved(u8),
}

/// Reserved bytes must be zero: a frame is read one way only, and re-encodes to itself.
fn zero(kind: u8, reserved: &[u8]) -> Result<(), DecodeError> {
    if reserved.iter().all(|&b| b == 0) {
        Ok(())
    } else {
        Err(DecodeError::Reserved(kind))
    }
}

/// CRC-32/ISO-HDLC (the zlib/Ethernet CRC).
pub fn crc32(data: &[u8]) -> u32 {
    // crc32fast: the same CRC (IEEE 802.3, reflected, 0xEDB88320), 16 bytes a step instead
    // of one; a 4 KB PLAN went through the byte-wise table on both sides of every link.
    crc32fast::hash(data)
}

struct Writer<'a> {
    buf: &'a mut [u8; MAX_FRAME],
    at: usize,
}

impl Writer<'_> {
    fn put(&mut self, bytes: &[u8]) {
        self.buf[self.at..self.at + bytes.len()].copy_from_slice(bytes);
        self.at += bytes.len();
    }
}

/// Encodes a frame into `buf`; returns its length. No allocation.
pub fn encode(frame: &Frame, buf: &mut [u8; MAX_FRAME]) -> usize {
    let kind = frame.message.kind();
    let len = frame.message.payload_len();
    let mut w = Writer { buf, at: 0 };
    w.put(&MAGIC.to_le_bytes());
    w.put(&[VERSION, kind]);
    w.put(&frame.seq.to_le_bytes());
    w.put(&frame.timestamp_ns.to_le_bytes());
    w.put(&(len as u16).to_le_bytes());
    match frame.message {
        Message::Sample(s) => {
            w.put(&s.encoder_counts.to_le_bytes());
            w.put(&s.adc_a.to_le_bytes());
            w.put(&s.adc_b.to_le_bytes());
            w.put(&s.adc_bus.to_le_bytes());
            w.put(&s.duty_a.to_le_bytes());
            w.put(&s.duty_b.to_le_bytes());
            w.put(&s.applied_command_seq.to_le_bytes());
            w.put(&s.fault_bits.to_le_bytes());
            w.put(&s.status.to_le_bytes());
        }
        Message::Command(c) => {
            w.put(&c.answers_sample.to_le_bytes());
            w.put(&c.duty_a.to_le_bytes());
            w.put(&c.duty_b.to_le_bytes());
        }
        Message::Control(a) => w.put(&[a as u8, 0, 0, 0]),
        Message::FaultReport(f) => {
            w.put(&f.fault_bits.to_le_bytes());
            w.put(&[0, 0]);
            w.put(&f.at_sample.to_le_bytes());
        }
        Message::Config(c) => {
            w.put(&c.sample_rate_hz.to_le_bytes());
            w.put(&c.counts_per_rev.to_le_bytes());
            w.put(&c.current_ua_per_count.to_le_bytes());
            w.put(&c.current_zero_count.to_le_bytes());
            w.put(&c.bus_uv_per_count.to_le_bytes());
            w.put(&c.watchdog_periods.to_le_bytes());
            w.put(&c.encoder_direction.to_le_bytes());
            w.put(&c.plan_capacity.to_le_bytes());
            w.put(&c.align_current_ma.to_le_bytes());
            w.put(&c.align_ms.to_le_bytes());
            w.put(&c.reserved);
        }
        Message::Hello => w.put(&[VERSION, 0, 0, 0]),
        Message::Plan(p) => {
            w.put(&p.answers_sample.to_le_bytes());
            w.put(&(p.entries().len() as u16).to_le_bytes());
            w.put(&[0, 0]);
            // One bounds check for the table, not four an entry: a PLAN is the largest frame.
            let n = p.entries().len();
            let table = &mut w.buf[w.at..w.at + 4 * n];
            for (out, [a, b]) in table.chunks_exact_mut(4).zip(p.entries()) {
                out[..2].copy_from_slice(&a.to_le_bytes());
                out[2..].copy_from_slice(&b.to_le_bytes());
            }
            w.at += 4 * n;
        }
    }
    let end = w.at;
    let crc = crc32(&w.buf[..end]);
    w.put(&crc.to_le_bytes());
    w.at
}

struct Reader<'a> {
    b: &'a [u8],
    at: usize,
}

impl Reader<'_> {
    fn take<const N: usize>(&mut self) -> [u8; N] {
        let mut out = [0u8; N];
        out.copy_from_slice(&self.b[self.at..self.at + N]);
        self.at += N;
        out
    }
    fn u16(&mut self) -> u16 {
        u16::from_le_bytes(self.take())
    }
    fn i16(&mut self) -> i16 {
        i16::from_le_bytes(self.take())
    }
    fn u32(&mut self) -> u32 {
        u32::from_le_bytes(self.take())
    }
    fn i32(&mut self) -> i32 {
        i32::from_le_bytes(self.take())
    }
}

/// Decodes and checks one frame: length, magic, version, kind, payload length, CRC.
pub fn decode(b: &[u8]) -> Result<Frame, DecodeError> {
    let f = decode_view(b)?;
    Ok(Frame {
        seq: f.seq,
        timestamp_ns: f.timestamp_ns,
        message: f.message.map_plan(|p| p.to_plan()),
    })
}

/// [`decode`], a PLAN's entries left in `b`: nothing the size of a PLAN is built or copied.
pub fn decode_view(b: &[u8]) -> Result<Frame<PlanView<'_>>, DecodeError> {
    if b.len() < HEADER_LEN + CRC_LEN {
        return Err(DecodeError::TooShort(b.len()));
    }
    let payload = usize::from(u16::from_le_bytes([b[16], b[17]]));
    if b.len() != HEADER_LEN + payload + CRC_LEN {
        return Err(DecodeError::LengthMismatch {
            frame: b.len(),
            payload,
        });
    }
    let body = &b[..b.len() - CRC_LEN];
    let got = u32::from_le_bytes([
        b[b.len() - 4],
        b[b.len() - 3],
        b[b.len() - 2],
        b[b.len() - 1],
    ]);
    let computed = crc32(body);
    if got != computed {
        return Err(DecodeError::BadCrc { got, computed });
    }
    let mut r = Reader { b: body, at: 0 };
    let magic = r.u16();
    if magic != MAGIC {
        return Err(DecodeError::BadMagic(magic));
    }
    let [version, kind] = r.take::<2>();
    if version != VERSION {
        return Err(DecodeError::BadVersion(version));
    }
    Message::valid_len(kind, payload)?;
    let seq = r.u32();
    let timestamp_ns = u64::from_le_bytes(r.take());
    r.at += 2;
    let message = match kind {
        1 => Message::Sample(Sample {
            encoder_counts: r.i32(),
            adc_a: r.u16(),
            adc_b: r.u16(),
            adc_bus: r.u16(),
            duty_a: r.i16(),
            duty_b: r.i16(),
            applied_command_seq: r.u32(),
            fault_bits: r.u16(),
            status: r.u16(),
        }),
        2 => Message::Command(Command {
            answers_sample: r.u32(),
            duty_a: r.i16(),
            duty_b: r.i16(),
        }),
        3 => {
            let [a, reserved @ ..] = r.take::<4>();
            zero(kind, &reserved)?;
            Message::Control(match a {
                1 => Action::Enable,
                2 => Action::Disable,
                3 => Action::Reset,
                4 => Action::Align,
                other => return Err(DecodeError::BadAction(other)),
            })
        }
        4 => {
            let fault_bits = r.u16();
            zero(kind, &r.take::<2>())?;
            Message::FaultReport(FaultReport {
                fault_bits,
                at_sample: r.u32(),
            })
        }
        5 => {
            let config = Config {
                sample_rate_hz: r.u32(),
                counts_per_rev: r.u32(),
                current_ua_per_count: r.u32(),
                current_zero_count: r.u16(),
                bus_uv_per_count: r.u32(),
                watchdog_periods: r.u16(),
                encoder_direction: i8::from_le_bytes(r.take()),
                plan_capacity: r.u16(),
                align_current_ma: r.u16(),
                align_ms: r.u16(),
                reserved: r.take(),
            };
            zero(kind, &config.reserved)?;
            Message::Config(config)
        }
        7 => {
            let answers_sample = r.u32();
            let count = r.u16();
            zero(kind, &r.take::<2>())?;
            let entries = (payload - PLAN_HEADER) / 4;
            if usize::from(count) != entries {
                return Err(DecodeError::BadPlanCount {
                    count,
                    len: payload,
                });
            }
            Message::Plan(PlanView {
                answers_sample,
                count,
                table: &body[r.at..r.at + 4 * entries],
            })
        }
        6 => {
            let [version, reserved @ ..] = r.take::<4>();
            zero(kind, &reserved)?;
            if version != VERSION {
                return Err(DecodeError::BadVersion(version));
            }
            Message::Hello
        }
        other => return Err(DecodeError::BadKind(other)),
    };
    Ok(Frame {
        seq,
        timestamp_ns,
        message,
    })
}

/// COBS-encodes `data` into `out` (needs `data.len() + data.len()/254 + 2` bytes) and
/// appends the 0x00 delimiter; returns the encoded length.
pub fn cobs_encode(data: &[u8], out: &mut [u8]) -> usize {
    let mut code_at = 0;
    let mut at = 1;
    let mut code = 1u8;
    for &byte in data {
        if byte == 0 {
            out[code_at] = code;
            code_at = at;
            at += 1;
            code = 1;
        } else {
            out[at] = byte;
            at += 1;
            code += 1;
            if code == 0xFF {
                out[code_at] = code;
                code_at = at;
                at += 1;
                code = 1;
            }
        }
    }
    out[code_at] = code;
    out[at] = 0;
    at + 1
}

/// Decodes one COBS frame (without its 0x00 delimiter) into `out`; returns the length.
pub fn cobs_decode(data: &[u8], out: &mut [u8]) -> Result<usize, DecodeError> {
    let mut at = 0;
    let mut n = 0;
    while at < data.len() {
        let code = data[at];
        if code == 0 {
            return Err(DecodeError::BadCobs);
        }
        at += 1;
        for _ in 1..code {
            let b = *data.get(at).ok_or(DecodeError::BadCobs)?;
            if b == 0 {
                return Err(DecodeError::BadCobs);
            }
            *out.get_mut(n).ok_or(DecodeError::BadCobs)? = b;
            n += 1;
            at += 1;
        }
        if code != 0xFF && at < data.len() {
            *out.get_mut(n).ok_or(DecodeError::BadCobs)? = 0;
            n += 1;
        }
    }
    Ok(n)
}

/// The longest COBS encoding of a frame, its 0x00 delimiter included.
pub const MAX_ENCODED: usize = MAX_FRAME + MAX_FRAME / 254 + 2;

/// COBS frames out of a byte stream a byte at a time, in a fixed buffer: a firmware's
/// receive path (no allocation, nothing to grow). Bytes up to a 0x00 delimiter are one
/// frame; a run longer than any frame's encoding is dropped up to its delimiter, and a
/// broken encoding is dropped, both counted. Empty frames (delimiters back to back, as a
/// sender may use to resynchronise) are skipped.
pub struct FrameCollector {
    buf: [u8; MAX_ENCODED],
    len: usize,
    overlong: bool,
    /// Frames dropped for a broken or overlong encoding.
    pub framing_errors: u32,
}

impl Default for FrameCollector {
    fn default() -> Self {
        Self::new()
    }
}

impl FrameCollector {
    pub const fn new() -> Self {
        Self {
            buf: [0; MAX_ENCODED],
            len: 0,
            overlong: false,
            framing_errors: 0,
        }
    }

    /// Takes one byte; at a delimiter that ends a whole frame, the frame decoded into
    /// `out` (its length).
    pub fn push(&mut self, byte: u8, out: &mut [u8]) -> Option<usize> {
        if byte != 0 {
            match self.buf.get_mut(self.len) {
                Some(slot) => {
                    *slot = byte;
                    self.len += 1;
                }
                None => self.overlong = true,
            }
            return None;
        }
        let (len, overlong) = (self.len, self.overlong);
        self.len = 0;
        self.overlong = false;
        if overlong {
            self.framing_errors = self.framing_errors.wrapping_add(1);
            return None;
        }
        if len == 0 {
            return None;
        }
        match cobs_decode(&self.buf[..len], out) {
            Ok(n) if n > 0 => Some(n),
            _ => {
                self.framing_errors = self.framing_errors.wrapping_add(1);
                None
            }
        }
    }
}

/// Classifies an incoming sequence number against the last accepted one: only strictly
/// newer frames are accepted (wrapping comparison, so a u32 counter may roll over).
pub fn is_newer(seq: u32, last: Option<u32>) -> bool {
    match last {
        None => true,
        Some(l) => {
            let d = seq.wrapping_sub(l);
            d != 0 && d < 0x8000_0000
        }
    }
}

/// Recomputes the CRC of a frame whose bytes were changed, so that it passes the CRC
/// check and the receiver's other checks are what meets it (tests and tools). Frames
/// shorter than a header and a CRC are left as they are.
pub fn reseal(bytes: &mut [u8]) {
    if bytes.len() >= HEADER_LEN + CRC_LEN {
        let end = bytes.len() - CRC_LEN;
        let crc = crc32(&bytes[..end]);
        bytes[end..].copy_from_slice(&crc.to_le_bytes());
    }
}

/// A frame of any `kind` byte around an arbitrary `payload`, with a matching CRC: what a
/// receiver must survive whatever the payload says (tests and tools).
#[cfg(feature = "std")]
pub fn raw_frame(seq: u32, kind: u8, payload: &[u8]) -> Vec<u8> {
    let mut bytes = MAGIC.to_le_bytes().to_vec();
    bytes.extend_from_slice(&[VERSION, kind]);
    bytes.extend_from_slice(&seq.to_le_bytes());
    bytes.extend_from_slice(&0u64.to_le_bytes());
    bytes.extend_from_slice(&(payload.len() as u16).to_le_bytes());
    bytes.extend_from_slice(payload);
    bytes.extend_from_slice(&[0; CRC_LEN]);
    reseal(&mut bytes);
    bytes
}

/// One encoded frame as bytes (tests and tools).
#[cfg(feature = "std")]
pub fn frame_bytes(seq: u32, message: Message) -> Vec<u8> {
    let mut b = [0u8; MAX_FRAME];
    let frame = Frame {
        seq,
        timestamp_ns: 0,
        message,
    };
    let n = encode(&frame, &mut b);
    b[..n].to_vec()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Fault bits read as the document names them; a bit it does not name, by value.
    #[test]
    fn fault_bits_by_name() {
        let named = |b| faults::named(b).to_string();
        assert_eq!(named(faults::OVERCURRENT), "OVERCURRENT");
        assert_eq!(
            named(faults::WATCHDOG | faults::BAD_COMMAND | 0x0100),
            "WATCHDOG, BAD_COMMAND, 0x0100"
        );
        assert_eq!(named(0), "");
    }

    /// The CRC test vectors of docs/drive-protocol.md.
    #[test]
    fn crc_vectors() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
        assert_eq!(crc32(b""), 0);
        assert_eq!(crc32(&[0u8]), 0xD202_EF8D);
        let frame = Frame {
            seq: 7,
            timestamp_ns: 1_000,
            message: Message::Command(Command {
                answers_sample: 6,
                duty_a: 1000,
                duty_b: -1000,
            }),
        };
        let mut buf = [0u8; MAX_FRAME];
        let n = encode(&frame, &mut buf);
        assert_eq!(n, 30);
        assert_eq!(
            buf[..n],
            [
                0x44, 0x53, 0x03, 0x02, 0x07, 0x00, 0x00, 0x00, 0xE8, 0x03, 0x00, 0x00, 0x00, 0x00,
                0x00, 0x00, 0x08, 0x00, 0x06, 0x00, 0x00, 0x00, 0xE8, 0x03, 0x18, 0xFC, 0x40, 0x62,
                0x6A, 0xB8
            ]
        );
        let mut duties = [[0i16; 2]; MAX_PLAN_ENTRIES];
        duties[0] = [1000, -1000];
        duties[1] = [2000, -2000];
        let plan = Frame {
            seq: 8,
            timestamp_ns: 2_000,
            message: Message::Plan(Plan {
                answers_sample: 6,
                count: 2,
                duties,
            }),
        };
        let n = encode(&plan, &mut buf);
        assert_eq!(
            buf[..n],
            [
                0x44, 0x53, 0x03, 0x07, 0x08, 0x00, 0x00, 0x00, 0xD0, 0x07, 0x00, 0x00, 0x00, 0x00,
                0x00, 0x00, 0x10, 0x00, 0x06, 0x00, 0x00, 0x00, 0x02, 0x00, 0x00, 0x00, 0xE8, 0x03,
                0x18, 0xFC, 0xD0, 0x07, 0x30, 0xF8, 0xAF, 0x2B, 0xDF, 0xE0
            ]
        );
    }

    /// Frames fed a byte at a time come out whole, between garbage, an overlong run and a
    /// broken encoding, each of those counted once.
    #[test]
    fn the_collector_takes_frames_a_byte_at_a_time() {
        let mut c = FrameCollector::new();
        let mut out = [0u8; MAX_FRAME];
        let mut enc = [0u8; MAX_ENCODED];
        let mut feed = |c: &mut FrameCollector, bytes: &[u8]| -> Vec<Vec<u8>> {
            let mut got = Vec::new();
            for &b in bytes {
                if let Some(n) = c.push(b, &mut out) {
                    got.push(out[..n].to_vec());
                }
            }
            got
        };
        let hello = frame_bytes(7, Message::Hello);
        let n = cobs_encode(&hello, &mut enc);
        let mut line = vec![0, 0];
        line.extend_from_slice(&enc[..n]);
        // Longer than any frame's encoding, then its delimiter.
        line.extend(std::iter::repeat_n(0x55u8, MAX_ENCODED + 10));
        line.push(0);
        // A code byte pointing past the frame's end.
        line.extend_from_slice(&[5, 1, 0]);
        line.extend_from_slice(&enc[..n]);
        let got = feed(&mut c, &line);
        assert_eq!(got, vec![hello.clone(), hello.clone()]);
        assert_eq!(c.framing_errors, 2);
        assert_eq!(decode(&got[0]).map(|f| f.seq), Ok(7));
    }

    #[test]
    fn cobs_vectors() {
        let mut out = [0u8; 300];
        let cases: [(&[u8], &[u8]); 4] = [
            (&[0x00], &[0x01, 0x01, 0x00]),
            (&[0x00, 0x00], &[0x01, 0x01, 0x01, 0x00]),
            (
                &[0x11, 0x22, 0x00, 0x33],
                &[0x03, 0x11, 0x22, 0x02, 0x33, 0x00],
            ),
            (
                &[0x11, 0x00, 0x00, 0x00],
                &[0x02, 0x11, 0x01, 0x01, 0x01, 0x00],
            ),
        ];
        for (raw, enc) in cases {
            let n = cobs_encode(raw, &mut out);
            assert_eq!(&out[..n], enc);
            let mut back = [0u8; 300];
            let m = cobs_decode(&enc[..enc.len() - 1], &mut back).unwrap();
            assert_eq!(&back[..m], raw);
        }
    }

    fn arb_message() -> impl Strategy<Value = Message> {
        prop_oneof![
            (
                any::<i32>(),
                any::<u16>(),
                any::<u16>(),
                any::<u16>(),
                any::<i16>(),
                any::<i16>(),
                any::<u32>(),
                any::<u16>(),
                any::<u16>()
            )
                .prop_map(|(e, a, b, bus, da, db, s, f, st)| Message::Sample(Sample {
                    encoder_counts: e,
                    adc_a: a,
                    adc_b: b,
                    adc_bus: bus,
                    duty_a: da,
                    duty_b: db,
                    applied_command_seq: s,
                    fault_bits: f,
                    status: st
                })),
            (any::<u32>(), any::<i16>(), any::<i16>()).prop_map(|(s, a, b)| Message::Command(
                Command {
                    answers_sample: s,
                    duty_a: a,
                    duty_b: b
                }
            )),
            prop_oneof![
                Just(Action::Enable),
                Just(Action::Disable),
                Just(Action::Reset),
                Just(Action::Align)
            ]
            .prop_map(Message::Control),
            (any::<u16>(), any::<u32>()).prop_map(|(f, s)| Message::FaultReport(FaultReport {
                fault_bits: f,
                at_sample: s
            })),
            (
                any::<u32>(),
                any::<u32>(),
                any::<u32>(),
                any::<u16>(),
                any::<u32>(),
                any::<u16>(),
                any::<i8>()
            )
                .prop_map(|(r, c, i, z, b, w, d)| Message::Config(Config {
                    sample_rate_hz: r,
                    counts_per_rev: c,
                    current_ua_per_count: i,
                    current_zero_count: z,
                    bus_uv_per_count: b,
                    watchdog_periods: w,
                    encoder_direction: d,
                    plan_capacity: w,
                    align_current_ma: z,
                    align_ms: w,
                    reserved: [0; 1]
                })),
            Just(Message::Hello),
            (
                any::<u32>(),
                proptest::collection::vec(any::<[i16; 2]>(), 1..=MAX_PLAN_ENTRIES)
            )
                .prop_map(|(s, entries)| {
                    let mut duties = [[0i16; 2]; MAX_PLAN_ENTRIES];
                    duties[..entries.len()].copy_from_slice(&entries);
                    Message::Plan(Plan {
                        answers_sample: s,
                        count: entries.len() as u16,
                        duties,
                    })
                }),
        ]
    }

    proptest! {
        #[test]
        fn every_kind_round_trips(seq in any::<u32>(), ts in any::<u64>(), message in arb_message()) {
            let frame = Frame { seq, timestamp_ns: ts, message };
            let mut buf = [0u8; MAX_FRAME];
            let n = encode(&frame, &mut buf);
            prop_assert_eq!(decode(&buf[..n]), Ok(frame));
            // And through COBS, as on a serial line.
            let mut enc = [0u8; 2 * MAX_FRAME];
            let m = cobs_encode(&buf[..n], &mut enc);
            prop_assert!(!enc[..m - 1].contains(&0));
            let mut dec = [0u8; MAX_FRAME];
            let k = cobs_decode(&enc[..m - 1], &mut dec).unwrap();
            prop_assert_eq!(decode(&dec[..k]), Ok(frame));
        }

        #[test]
        fn every_single_bit_corruption_is_detected(seq in any::<u32>(), message in arb_message()) {
            let frame = Frame { seq, timestamp_ns: 42, message };
            let mut buf = [0u8; MAX_FRAME];
            let n = encode(&frame, &mut buf);
            for bit in 0..n * 8 {
                let mut bad = buf;
                bad[bit / 8] ^= 1 << (bit % 8);
                prop_assert!(decode(&bad[..n]).is_err(), "bit {} undetected", bit);
            }
            // Truncated or extended frames are rejected too.
            prop_assert!(decode(&buf[..n - 1]).is_err());
            prop_assert!(decode(&buf[..(n + 1).min(MAX_FRAME)]).is_err() || n == MAX_FRAME);
        }
    }

    proptest! {
        /// Arbitrary bytes: no panic, and whatever is accepted re-encodes to exactly the
        /// bytes it came from (there is one way to write every frame).
        #[test]
        fn arbitrary_bytes_never_panic_and_accepted_frames_re_encode_identically(
            bytes in proptest::collection::vec(any::<u8>(), 0..MAX_FRAME + 16),
            lie in any::<bool>(),
        ) {
            let mut bytes = bytes;
            if lie {
                reseal(&mut bytes);
            }
            if let Ok(frame) = decode(&bytes) {
                let mut buf = [0u8; MAX_FRAME];
                let n = encode(&frame, &mut buf);
                prop_assert_eq!(&buf[..n], &bytes[..]);
            }
        }

        /// Valid frames with bytes changed and the CRC made to match: the structural checks
        /// alone must hold the line (no panic, no over-read; accepted frames re-encode).
        #[test]
        fn consistent_liars_are_refused_or_exact(
            seq in any::<u32>(),
            message in arb_message(),
            edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 1..6),
            cut in proptest::option::of(any::<usize>()),
        ) {
            let frame = Frame { seq, timestamp_ns: 7, message };
            let mut buf = [0u8; MAX_FRAME];
            let n = encode(&frame, &mut buf);
            let mut bytes = buf[..n].to_vec();
            for (at, value) in edits {
                let at = at % bytes.len();
                bytes[at] = value;
            }
            if let Some(cut) = cut {
                bytes.truncate(cut % (bytes.len() + 1));
            }
            reseal(&mut bytes);
            if let Ok(f) = decode(&bytes) {
                let mut again = [0u8; MAX_FRAME];
                let m = encode(&f, &mut again);
                prop_assert_eq!(&again[..m], &bytes[..]);
            }
        }

        /// COBS decoding of arbitrary bytes: no panic, never past the output.
        #[test]
        fn arbitrary_cobs_never_panics(
            data in proptest::collection::vec(any::<u8>(), 0..600),
            room in 0usize..600,
        ) {
            let mut out = vec![0u8; room];
            if let Ok(n) = cobs_decode(&data, &mut out) {
                prop_assert!(n <= room);
            }
        }

        /// Any bytes, then a frame: the collector never panics, and the frame comes out
        /// whole after the first delimiter.
        #[test]
        fn the_collector_resynchronises_after_any_bytes(
            garbage in proptest::collection::vec(any::<u8>(), 0..2000),
            seq in any::<u32>(),
        ) {
            let mut c = FrameCollector::new();
            let mut out = [0u8; MAX_FRAME];
            for &b in &garbage {
                if let Some(n) = c.push(b, &mut out) {
                    prop_assert!(n <= MAX_FRAME);
                }
            }
            let frame = frame_bytes(seq, Message::Hello);
            let mut enc = [0u8; MAX_ENCODED];
            let n = cobs_encode(&frame, &mut enc);
            let mut got = None;
            for &b in [0u8].iter().chain(&enc[..n]) {
                if let Some(k) = c.push(b, &mut out) {
                    got = Some(out[..k].to_vec());
                }
            }
            prop_assert_eq!(got, Some(frame));
        }
    }

    /// A PLAN must carry exactly `count` entries, 1 ..= MAX_PLAN_ENTRIES.
    #[test]
    fn plan_lengths_are_checked() {
        let mut duties = [[0i16; 2]; MAX_PLAN_ENTRIES];
        duties[0] = [5, 5];
        let one = Frame {
            seq: 1,
            timestamp_ns: 0,
            message: Message::Plan(Plan {
                answers_sample: 0,
                count: 1,
                duties,
            }),
        };
        let mut buf = [0u8; MAX_FRAME];
        let n = encode(&one, &mut buf);
        assert_eq!(decode(&buf[..n]), Ok(one));
        // Count field says 2 with one entry's bytes (CRC recomputed: a consistent liar).
        let mut bad = buf;
        bad[HEADER_LEN + 4] = 2;
        let crc = crc32(&bad[..n - CRC_LEN]);
        bad[n - CRC_LEN..n].copy_from_slice(&crc.to_le_bytes());
        assert!(matches!(
            decode(&bad[..n]),
            Err(DecodeError::BadPlanCount { count: 2, .. })
        ));
        // An empty PLAN is malformed.
        let mut empty = buf;
        empty[16] = PLAN_HEADER as u8;
        empty[HEADER_LEN + 4] = 0;
        let m = HEADER_LEN + PLAN_HEADER;
        let crc = crc32(&empty[..m]);
        empty[m..m + CRC_LEN].copy_from_slice(&crc.to_le_bytes());
        assert!(matches!(
            decode(&empty[..m + CRC_LEN]),
            Err(DecodeError::BadLength { kind: 7, .. })
        ));
    }

    /// Reserved bytes must be zero: a frame with any set is refused, not read past.
    #[test]
    fn reserved_bytes_must_be_zero() {
        let cases = [
            (Message::Control(Action::Enable), HEADER_LEN + 1),
            (
                Message::FaultReport(FaultReport {
                    fault_bits: 1,
                    at_sample: 2,
                }),
                HEADER_LEN + 2,
            ),
            (Message::Hello, HEADER_LEN + 3),
        ];
        for (message, reserved_at) in cases {
            let mut bytes = frame_bytes(1, message);
            assert!(decode(&bytes).is_ok());
            bytes[reserved_at] = 1;
            reseal(&mut bytes);
            assert_eq!(decode(&bytes), Err(DecodeError::Reserved(message.kind())));
        }
    }

    #[test]
    fn sequence_numbers_accept_only_newer() {
        assert!(is_newer(5, None));
        assert!(is_newer(6, Some(5)));
        assert!(!is_newer(5, Some(5)));
        assert!(!is_newer(4, Some(5)));
        assert!(is_newer(0, Some(u32::MAX)));
    }
}
