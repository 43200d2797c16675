//! Frame codec for protocol version 3 (§3, §4). Decoding validates in the order §3 gives.

use crate::crc::crc32;

pub const MAGIC: u16 = 0x5344;
pub const VERSION: u8 = 3;
pub const HEADER_LEN: usize = 18;
pub const OVERHEAD: usize = HEADER_LEN + 4;
pub const MAX_PLAN_ENTRIES: usize = 1024;
/// Largest valid frame: a 1024-entry PLAN.
pub const MAX_FRAME_LEN: usize = OVERHEAD + 8 + 4 * MAX_PLAN_ENTRIES;

pub const KIND_SAMPLE: u8 = 1;
pub const KIND_COMMAND: u8 = 2;
pub const KIND_CONTROL: u8 = 3;
pub const KIND_FAULT_REPORT: u8 = 4;
pub const KIND_CONFIG: u8 = 5;
pub const KIND_HELLO: u8 = 6;
pub const KIND_PLAN: u8 = 7;

pub const ACTION_ENABLE: u8 = 1;
pub const ACTION_DISABLE: u8 = 2;
pub const ACTION_RESET: u8 = 3;
pub const ACTION_ALIGN: u8 = 4;

pub const STATUS_ENABLED: u16 = 1;
pub const STATUS_COMMAND_HELD: u16 = 2;
pub const STATUS_COMMAND_PLANNED: u16 = 4;
pub const STATUS_ALIGNING: u16 = 8;

pub const FAULT_WATCHDOG: u16 = 1;
pub const FAULT_OVERCURRENT: u16 = 2;
pub const FAULT_BUS_VOLTAGE: u16 = 4;
pub const FAULT_BAD_COMMAND: u16 = 8;

/// "Newer" (§3.1): 0 < a − b < 2^31 in u32 arithmetic.
pub fn is_newer(a: u32, b: u32) -> bool {
    let d = a.wrapping_sub(b);
    d != 0 && d < 0x8000_0000
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Sample {
    pub encoder_counts: i32,
    pub adc_a: u16,
    pub adc_b: u16,
    pub adc_bus: u16,
    pub duty_a: i16,
    pub duty_b: i16,
    pub applied_command_seq: u32,
    pub fault_bits: u16,
    pub status: u16,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Config {
    pub sample_rate_hz: u32,
    pub counts_per_rev: u32,
    pub current_ua_per_count: u32,
    pub current_zero_count: u16,
    pub bus_uv_per_count: u32,
    pub watchdog_periods: u16,
    pub encoder_direction: i8,
    pub plan_capacity: u16,
    pub align_current_ma: u16,
    pub align_ms: u16,
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Payload {
    Sample(Sample),
    Command {
        answers_sample: u32,
        duty_a: i16,
        duty_b: i16,
    },
    Control {
        action: u8,
    },
    FaultReport {
        fault_bits: u16,
        at_sample: u32,
    },
    Config(Config),
    Hello {
        requested_version: u8,
    },
    Plan {
        answers_sample: u32,
        entries: Vec<(i16, i16)>,
    },
}

impl Payload {
    pub fn kind(&self) -> u8 {
        match self {
            Payload::Sample(_) => KIND_SAMPLE,
            Payload::Command { .. } => KIND_COMMAND,
            Payload::Control { .. } => KIND_CONTROL,
            Payload::FaultReport { .. } => KIND_FAULT_REPORT,
            Payload::Config(_) => KIND_CONFIG,
            Payload::Hello { .. } => KIND_HELLO,
            Payload::Plan { .. } => KIND_PLAN,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Frame {
    pub seq: u32,
    pub timestamp_ns: u64,
    pub payload: Payload,
}

/// Why a frame was dropped by validation (§3, in the order checked).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DecodeError {
    TooShort,
    LengthMismatch,
    Crc,
    Magic,
    Version(u8),
    UnknownKind(u8),
    PayloadLen,
    BadField,
    Reserved,
}

fn fixed_len(kind: u8) -> Option<usize> {
    match kind {
        KIND_SAMPLE => Some(22),
        KIND_COMMAND => Some(8),
        KIND_CONTROL => Some(4),
        KIND_FAULT_REPORT => Some(8),
        KIND_CONFIG => Some(28),
        KIND_HELLO => Some(4),
        _ => None,
    }
}

fn u16_at(b: &[u8], o: usize) -> u16 {
    u16::from_le_bytes([b[o], b[o + 1]])
}
fn i16_at(b: &[u8], o: usize) -> i16 {
    i16::from_le_bytes([b[o], b[o + 1]])
}
fn u32_at(b: &[u8], o: usize) -> u32 {
    u32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]])
}
fn i32_at(b: &[u8], o: usize) -> i32 {
    i32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]])
}

/// Encodes one frame.
pub fn encode(seq: u32, timestamp_ns: u64, payload: &Payload) -> Vec<u8> {
    let mut p: Vec<u8> = Vec::with_capacity(32);
    match payload {
        Payload::Sample(s) => {
            p.extend_from_slice(&s.encoder_counts.to_le_bytes());
            p.extend_from_slice(&s.adc_a.to_le_bytes());
            p.extend_from_slice(&s.adc_b.to_le_bytes());
            p.extend_from_slice(&s.adc_bus.to_le_bytes());
            p.extend_from_slice(&s.duty_a.to_le_bytes());
            p.extend_from_slice(&s.duty_b.to_le_bytes());
            p.extend_from_slice(&s.applied_command_seq.to_le_bytes());
            p.extend_from_slice(&s.fault_bits.to_le_bytes());
            p.extend_from_slice(&s.status.to_le_bytes());
        }
        Payload::Command {
            answers_sample,
            duty_a,
            duty_b,
        } => {
            p.extend_from_slice(&answers_sample.to_le_bytes());
            p.extend_from_slice(&duty_a.to_le_bytes());
            p.extend_from_slice(&duty_b.to_le_bytes());
        }
        Payload::Control { action } => p.extend_from_slice(&[*action, 0, 0, 0]),
        Payload::FaultReport {
            fault_bits,
            at_sample,
        } => {
            p.extend_from_slice(&fault_bits.to_le_bytes());
            p.extend_from_slice(&[0, 0]);
            p.extend_from_slice(&at_sample.to_le_bytes());
        }
        Payload::Config(c) => {
            p.extend_from_slice(&c.sample_rate_hz.to_le_bytes());
            p.extend_from_slice(&c.counts_per_rev.to_le_bytes());
            p.extend_from_slice(&c.current_ua_per_count.to_le_bytes());
            p.extend_from_slice(&c.current_zero_count.to_le_bytes());
            p.extend_from_slice(&c.bus_uv_per_count.to_le_bytes());
            p.extend_from_slice(&c.watchdog_periods.to_le_bytes());
            p.extend_from_slice(&c.encoder_direction.to_le_bytes());
            p.extend_from_slice(&c.plan_capacity.to_le_bytes());
            p.extend_from_slice(&c.align_current_ma.to_le_bytes());
            p.extend_from_slice(&c.align_ms.to_le_bytes());
            p.push(0);
        }
        Payload::Hello { requested_version } => p.extend_from_slice(&[*requested_version, 0, 0, 0]),
        Payload::Plan {
            answers_sample,
            entries,
        } => {
            p.extend_from_slice(&answers_sample.to_le_bytes());
            p.extend_from_slice(&(entries.len() as u16).to_le_bytes());
            p.extend_from_slice(&[0, 0]);
            for (a, b) in entries {
                p.extend_from_slice(&a.to_le_bytes());
                p.extend_from_slice(&b.to_le_bytes());
            }
        }
    }
    let mut f = Vec::with_capacity(OVERHEAD + p.len());
    f.extend_from_slice(&MAGIC.to_le_bytes());
    f.push(VERSION);
    f.push(payload.kind());
    f.extend_from_slice(&seq.to_le_bytes());
    f.extend_from_slice(&timestamp_ns.to_le_bytes());
    f.extend_from_slice(&(p.len() as u16).to_le_bytes());
    f.extend_from_slice(&p);
    let crc = crc32(&f);
    f.extend_from_slice(&crc.to_le_bytes());
    f
}

/// Decodes and validates one frame (§3 "Validation", in its order). Never panics.
pub fn decode(b: &[u8]) -> Result<Frame, DecodeError> {
    if b.len() < OVERHEAD {
        return Err(DecodeError::TooShort);
    }
    let payload_len = u16_at(b, 16) as usize;
    if b.len() != OVERHEAD + payload_len {
        return Err(DecodeError::LengthMismatch);
    }
    let body = HEADER_LEN + payload_len;
    if crc32(&b[..body]) != u32_at(b, body) {
        return Err(DecodeError::Crc);
    }
    if u16_at(b, 0) != MAGIC {
        return Err(DecodeError::Magic);
    }
    if b[2] != VERSION {
        return Err(DecodeError::Version(b[2]));
    }
    let kind = b[3];
    if !(KIND_SAMPLE..=KIND_PLAN).contains(&kind) {
        return Err(DecodeError::UnknownKind(kind));
    }
    let p = &b[HEADER_LEN..body];
    if kind == KIND_PLAN {
        if payload_len < 8 || !(payload_len - 8).is_multiple_of(4) {
            return Err(DecodeError::PayloadLen);
        }
        let n = (payload_len - 8) / 4;
        if !(1..=MAX_PLAN_ENTRIES).contains(&n) {
            return Err(DecodeError::PayloadLen);
        }
        if u16_at(p, 4) as usize != n {
            return Err(DecodeError::PayloadLen);
        }
    } else if fixed_len(kind) != Some(payload_len) {
        return Err(DecodeError::PayloadLen);
    }
    let seq = u32_at(b, 4);
    let timestamp_ns = u64::from_le_bytes([b[8], b[9], b[10], b[11], b[12], b[13], b[14], b[15]]);
    let payload = match kind {
        KIND_SAMPLE => {
            let status = u16_at(p, 20);
            if status & !0x000F != 0 {
                return Err(DecodeError::Reserved);
            }
            Payload::Sample(Sample {
                encoder_counts: i32_at(p, 0),
                adc_a: u16_at(p, 4),
                adc_b: u16_at(p, 6),
                adc_bus: u16_at(p, 8),
                duty_a: i16_at(p, 10),
                duty_b: i16_at(p, 12),
                applied_command_seq: u32_at(p, 14),
                fault_bits: u16_at(p, 18),
                status,
            })
        }
        KIND_COMMAND => Payload::Command {
            answers_sample: u32_at(p, 0),
            duty_a: i16_at(p, 4),
            duty_b: i16_at(p, 6),
        },
        KIND_CONTROL => {
            let action = p[0];
            if !(ACTION_ENABLE..=ACTION_ALIGN).contains(&action) {
                return Err(DecodeError::BadField);
            }
            if p[1..4] != [0, 0, 0] {
                return Err(DecodeError::Reserved);
            }
            Payload::Control { action }
        }
        KIND_FAULT_REPORT => {
            if u16_at(p, 2) != 0 {
                return Err(DecodeError::Reserved);
            }
            Payload::FaultReport {
                fault_bits: u16_at(p, 0),
                at_sample: u32_at(p, 4),
            }
        }
        KIND_CONFIG => {
            let c = Config {
                sample_rate_hz: u32_at(p, 0),
                counts_per_rev: u32_at(p, 4),
                current_ua_per_count: u32_at(p, 8),
                current_zero_count: u16_at(p, 12),
                bus_uv_per_count: u32_at(p, 14),
                watchdog_periods: u16_at(p, 18),
                encoder_direction: p[20] as i8,
                plan_capacity: u16_at(p, 21),
                align_current_ma: u16_at(p, 23),
                align_ms: u16_at(p, 25),
            };
            if !config_valid(&c) {
                return Err(DecodeError::BadField);
            }
            if p[27] != 0 {
                return Err(DecodeError::Reserved);
            }
            Payload::Config(c)
        }
        KIND_HELLO => {
            if p[0] != VERSION {
                return Err(DecodeError::BadField);
            }
            if p[1..4] != [0, 0, 0] {
                return Err(DecodeError::Reserved);
            }
            Payload::Hello {
                requested_version: p[0],
            }
        }
        _ => {
            if u16_at(p, 6) != 0 {
                return Err(DecodeError::Reserved);
            }
            let n = u16_at(p, 4) as usize;
            let entries = (0..n)
                .map(|j| (i16_at(p, 8 + 4 * j), i16_at(p, 10 + 4 * j)))
                .collect();
            Payload::Plan {
                answers_sample: u32_at(p, 0),
                entries,
            }
        }
    };
    Ok(Frame {
        seq,
        timestamp_ns,
        payload,
    })
}

/// CONFIG's valid values (§4.5), except the sample rate's match with a scenario.
pub fn config_valid(c: &Config) -> bool {
    (100..=100_000).contains(&c.sample_rate_hz)
        && (4..=(1 << 30)).contains(&c.counts_per_rev)
        && c.current_ua_per_count > 0
        && c.bus_uv_per_count > 0
        && c.watchdog_periods >= 2
        && (c.encoder_direction == 1 || c.encoder_direction == -1)
        && c.plan_capacity as usize <= MAX_PLAN_ENTRIES
        && (c.align_ms == 0 || c.align_current_ma > 0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Parses the hex bytes of a fenced block.
    fn hex(s: &str) -> Vec<u8> {
        s.split_whitespace()
            .map(|h| u8::from_str_radix(h, 16).expect("hex"))
            .collect()
    }

    fn roundtrip(bytes: &[u8], seq: u32, ts: u64, payload: Payload, crc: u32) {
        assert_eq!(encode(seq, ts, &payload), bytes);
        let f = decode(bytes).expect("vector decodes");
        assert_eq!(f.seq, seq);
        assert_eq!(f.timestamp_ns, ts);
        assert_eq!(f.payload, payload);
        assert_eq!(u32_at(bytes, bytes.len() - 4), crc);
        // every single-bit flip is rejected
        for i in 0..bytes.len() * 8 {
            let mut c = bytes.to_vec();
            c[i / 8] ^= 1 << (i % 8);
            assert!(decode(&c).is_err(), "flip of bit {i} accepted");
        }
    }

    #[test]
    fn vector_command() {
        let b = hex("44 53 03 02 07 00 00 00 E8 03 00 00 00 00 00 00 08 00 06 00 00 00 E8 03 18 FC 40 62 6A B8");
        assert_eq!(b.len(), 30);
        let p = Payload::Command {
            answers_sample: 6,
            duty_a: 1000,
            duty_b: -1000,
        };
        roundtrip(&b, 7, 1000, p, 0xB86A_6240);
    }

    #[test]
    fn vector_plan() {
        let b = hex("44 53 03 07 08 00 00 00 D0 07 00 00 00 00 00 00 10 00 06 00 00 00 02 00 00 00 E8 03 18 FC D0 07 30 F8 AF 2B DF E0");
        assert_eq!(b.len(), 38);
        let p = Payload::Plan {
            answers_sample: 6,
            entries: vec![(1000, -1000), (2000, -2000)],
        };
        roundtrip(&b, 8, 2000, p, 0xE0DF_2BAF);
    }

    #[test]
    fn vector_config() {
        let b = hex("44 53 03 05 00 00 00 00 B8 0B 00 00 00 00 00 00 1C 00 20 4E 00 00 00 00 10 00 64 00 00 00 00 80 10 27 00 00 E8 03 01 C8 00 E8 03 2C 01 00 94 DA 28 F8");
        assert_eq!(b.len(), 50);
        let c = Config {
            sample_rate_hz: 20_000,
            counts_per_rev: 1 << 20,
            current_ua_per_count: 100,
            current_zero_count: 32768,
            bus_uv_per_count: 10_000,
            watchdog_periods: 1000,
            encoder_direction: 1,
            plan_capacity: 200,
            align_current_ma: 1000,
            align_ms: 300,
        };
        roundtrip(&b, 0, 3000, Payload::Config(c), 0xF828_DA94);
    }

    #[test]
    fn vector_sample() {
        let b = hex("44 53 03 01 2A 00 00 00 20 0B 20 00 00 00 00 00 16 00 00 00 04 00 E6 85 00 80 60 09 00 40 00 00 11 00 00 00 00 00 01 00 2D 7C 8A 2A");
        assert_eq!(b.len(), 44);
        let s = Sample {
            encoder_counts: 262_144,
            adc_a: 34278,
            adc_b: 32768,
            adc_bus: 2400,
            duty_a: 16384,
            duty_b: 0,
            applied_command_seq: 17,
            fault_bits: 0,
            status: STATUS_ENABLED,
        };
        roundtrip(&b, 42, 2_100_000, Payload::Sample(s), 0x2A8A_7C2D);
    }

    #[test]
    fn validation_order_and_reasons() {
        let good = encode(3, 0, &Payload::Control { action: 1 });
        assert!(decode(&good).is_ok());
        assert_eq!(decode(&good[..21]), Err(DecodeError::TooShort));
        let mut longer = good.clone();
        longer.push(0);
        assert_eq!(decode(&longer), Err(DecodeError::LengthMismatch));
        // an action out of range, with a correct CRC
        let bad = encode(3, 0, &Payload::Control { action: 5 });
        assert_eq!(decode(&bad), Err(DecodeError::BadField));
        let bad = encode(3, 0, &Payload::Control { action: 0 });
        assert_eq!(decode(&bad), Err(DecodeError::BadField));
        // a reserved byte set, CRC recomputed
        let mut r = good.clone();
        r[19] = 1;
        let n = r.len();
        let crc = crc32(&r[..n - 4]);
        r[n - 4..].copy_from_slice(&crc.to_le_bytes());
        assert_eq!(decode(&r), Err(DecodeError::Reserved));
        // version 2, CRC recomputed
        let mut v = good.clone();
        v[2] = 2;
        let crc = crc32(&v[..n - 4]);
        v[n - 4..].copy_from_slice(&crc.to_le_bytes());
        assert_eq!(decode(&v), Err(DecodeError::Version(2)));
        // HELLO asking for version 2
        let h = encode(
            1,
            0,
            &Payload::Hello {
                requested_version: 2,
            },
        );
        assert_eq!(decode(&h), Err(DecodeError::BadField));
        // a PLAN whose count disagrees with its length
        let mut p = encode(
            1,
            0,
            &Payload::Plan {
                answers_sample: 1,
                entries: vec![(1, 1), (2, 2)],
            },
        );
        p[22] = 3;
        let n = p.len();
        let crc = crc32(&p[..n - 4]);
        p[n - 4..].copy_from_slice(&crc.to_le_bytes());
        assert_eq!(decode(&p), Err(DecodeError::PayloadLen));
    }

    #[test]
    fn newer_is_wrapping() {
        assert!(is_newer(1, 0));
        assert!(is_newer(0, u32::MAX));
        assert!(!is_newer(5, 5));
        assert!(!is_newer(4, 5));
        assert!(!is_newer(0x8000_0000, 0));
    }
}
