//! Fault injection: what a bad link or a sick board does to the frames a drive sends, kept
//! apart from the drive's period logic so that the drive (`crate::node`) reads as a drive.
//! Every choice is a function of the sample index and a seeded generator: the same frames
//! are lost in every run.

use stepdrive_drive_protocol::transport::Wire;
use stepdrive_drive_protocol::{encode, Frame, MAX_FRAME};

/// Faults the emulator can inject (0 / `None` = off).
#[derive(Debug, Clone, Default)]
pub struct FaultInjection {
    /// Drop every N-th outgoing SAMPLE.
    pub drop_every: u64,
    /// Flip one bit in every N-th outgoing SAMPLE.
    pub corrupt_every: u64,
    /// Send every N-th SAMPLE after the next one.
    pub reorder_every: u64,
    /// Hold every N-th SAMPLE for `delay_ns` before sending it (longer than a period: it
    /// arrives after newer ones).
    pub delay_every: u64,
    pub delay_ns: u64,
    /// Send every N-th SAMPLE twice.
    pub duplicate_every: u64,
    /// Stop sending samples (but keep running) after this many seconds.
    pub stop_after_s: Option<f64>,
    /// Latch an over-current fault after this many seconds.
    pub overcurrent_after_s: Option<f64>,
    /// Freeze the drive once, at this many seconds, for `freeze_ns`: no frames, its clock
    /// paused, as when the host stops its process.
    pub freeze_at_s: Option<f64>,
    pub freeze_ns: u64,
    /// Drop (corrupt) each SAMPLE with this probability, from a fixed seed.
    pub drop_fraction: f64,
    pub corrupt_fraction: f64,
    /// Drop `dropout_samples` SAMPLEs in a row from this many seconds on (a link outage).
    pub dropout_at_s: Option<f64>,
    pub dropout_samples: u64,
    /// A broken alignment (§7): never finishing, or aligning the wrong way.
    pub align: AlignFault,
}

/// How an ALIGN can go wrong on a real board.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum AlignFault {
    #[default]
    None,
    /// ALIGNING stays set: the alignment never ends.
    Stuck,
    /// Phase A energized the wrong way: the rotor rests half an electrical period from
    /// the zero the host then assumes.
    Reversed,
    /// Phase A's motor leads swapped at the drive's terminals: the drive's own shunt still
    /// reads the current it drives (+I while aligning), but the winding carries it the
    /// other way round, in every period, so the rotor aligns half an electrical period off
    /// and every COMMAND's phase A acts backwards.
    SwappedLeads,
}

impl AlignFault {
    /// Breaks `drive`'s alignment as this says: in the core (an alignment that never
    /// ends), in its ALIGN's duty (reversed) or in the wiring (swapped leads).
    pub fn apply(self, drive: &mut crate::EmulatedDrive) {
        drive.break_alignment(
            self == Self::Stuck,
            self == Self::SwappedLeads,
            self == Self::Reversed,
        );
    }
}

/// A xorshift64* generator: the injected losses are the same in every run.
struct Dice(u64);

impl Dice {
    fn roll(&mut self, p: f64) -> bool {
        if p <= 0.0 {
            return false;
        }
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        let u = (self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 11) as f64 / (1u64 << 53) as f64;
        u < p
    }
}

/// Sends a frame; a full socket or line buffer drops it, as a wire would.
pub fn send_frame(wire: &mut Wire, frame: &Frame, buf: &mut [u8; MAX_FRAME]) {
    let n = encode(frame, buf);
    wire.send(&buf[..n]);
}

/// What the injector asks of the drive's period before its sample.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Before {
    /// An ordinary period.
    Go,
    /// Latch an over-current now.
    Overcurrent,
    /// Stop everything for this long (no frames, the drive's time paused).
    Freeze { ns: u64 },
}

/// The injected faults' state over a run.
pub struct Injector {
    plan: FaultInjection,
    dice: Dice,
    dropout_left: Option<u64>,
    froze: bool,
    tripped: bool,
    reordered: Option<Frame>,
    delayed: Option<(Frame, u64)>,
}

impl Injector {
    pub fn new(plan: FaultInjection) -> Self {
        Self {
            plan,
            dice: Dice(0x9E37_79B9_7F4A_7C15),
            dropout_left: None,
            froze: false,
            tripped: false,
            reordered: None,
            delayed: None,
        }
    }

    pub fn align(&self) -> AlignFault {
        self.plan.align
    }

    /// What happens to the period `t_s` seconds into the run (from its ENABLE; negative
    /// before one).
    pub fn before(&mut self, t_s: f64) -> Before {
        if !self.tripped && self.plan.overcurrent_after_s.is_some_and(|a| t_s >= a) {
            self.tripped = true;
            return Before::Overcurrent;
        }
        if !self.froze && self.plan.freeze_at_s.is_some_and(|a| t_s >= a) {
            self.froze = true;
            return Before::Freeze {
                ns: self.plan.freeze_ns,
            };
        }
        Before::Go
    }

    /// Sends sample `k`'s frame as the injected faults have it: dropped, corrupted,
    /// reordered, delayed, duplicated, or as is.
    pub fn send_sample(
        &mut self,
        wire: &mut Wire,
        frame: &Frame,
        k: u64,
        t_s: f64,
        now_ns: u64,
        buf: &mut [u8; MAX_FRAME],
    ) {
        let p = &self.plan;
        let mut silent = p.stop_after_s.is_some_and(|s| t_s >= s);
        if p.dropout_at_s.is_some_and(|s| t_s >= s) {
            let left = self.dropout_left.get_or_insert(p.dropout_samples);
            if *left > 0 {
                *left -= 1;
                silent = true;
            }
        }
        let every = |n: u64| n > 0 && k.is_multiple_of(n);
        let (drop_fraction, corrupt_fraction) = (p.drop_fraction, p.corrupt_fraction);
        let dropped = every(p.drop_every) || self.dice.roll(drop_fraction);
        if silent || dropped {
            return;
        }
        if every(p.corrupt_every) || self.dice.roll(corrupt_fraction) {
            let n = encode(frame, buf);
            buf[n / 2] ^= 0x10;
            wire.send(&buf[..n]);
        } else if every(p.reorder_every) {
            self.reordered = Some(*frame);
        } else if every(p.delay_every) && self.delayed.is_none() {
            self.delayed = Some((*frame, now_ns + p.delay_ns));
        } else {
            send_frame(wire, frame, buf);
            if let Some(late) = self.reordered.take() {
                send_frame(wire, &late, buf);
            }
            if every(p.duplicate_every) {
                send_frame(wire, frame, buf);
            }
        }
    }

    /// A delayed frame due before `next_deadline_ns`: when to send it. It leaves when its
    /// time comes, within this period or a later one; the drive's clock never waits for it
    /// past the next deadline.
    pub fn delayed_due(&self, next_deadline_ns: u64) -> Option<u64> {
        self.delayed
            .and_then(|(_, at)| (at < next_deadline_ns).then_some(at))
    }

    /// Sends the delayed frame.
    pub fn send_delayed(&mut self, wire: &mut Wire, buf: &mut [u8; MAX_FRAME]) {
        if let Some((frame, _)) = self.delayed.take() {
            send_frame(wire, &frame, buf);
        }
    }
}
