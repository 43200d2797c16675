//! A client's coordinated move arrives in parts: one request on each axis's command
//! service, each naming every axis of the move ([`request_flags::group`]). So does a
//! multi-axis stream's start: its axes start on one tick and play their points from one
//! origin, so that one stream time is one instant on every axis. The parts come
//! on different ticks (a client sends them one after the other), so each waits, unanswered,
//! until its partners are in; then the move starts on one tick and every part is answered
//! ([`super::group::Coordinator::move_together`]). A part whose partners do not all come
//! within the wait is refused, naming the axes that did not send theirs.
//!
//! Pure: the position loop keeps each axis's waiting part and asks, at every tick, which
//! parts make a whole move and which have waited too long.

use super::coordinated::MAX_AXES;
use super::{refuse, Refused};
use stepdrive_shared::axis::{request_flags, AxisRequest, Refusal, RequestKind};

/// One axis's part of a client's coordinated move, waiting for its partners.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Part {
    /// A move or a stream start ([`RequestKind`]).
    pub kind: u32,
    /// The axes of its move (bit n: axis n), its own among them.
    pub group: u32,
    /// The client and the sequence number every part of one move carries.
    pub client: u32,
    pub seq: u64,
    /// When it came (the state's sample time, s: the axes' ticks share one grid).
    pub since_s: f64,
}

impl Part {
    fn same_move(&self, other: &Part) -> bool {
        self.kind == other.kind
            && self.group == other.group
            && self.client == other.client
            && self.seq == other.seq
    }
}

/// Checks a coordinated part as it comes to axis `axis` of a stack of `axes`: a move to an
/// absolute, finite target, at the axes' move limits, that changes at once, or a stream
/// start (with its lead or the axis's), whose group holds this axis and no axis the stack
/// lacks.
pub fn check_part(r: &AxisRequest, axis: u32, axes: usize, t: f64) -> Result<Part, Refused> {
    let group = request_flags::group(r.flags);
    let is_move = r.kind == RequestKind::Move as u32;
    if !is_move && r.kind != RequestKind::StreamStart as u32 {
        return Err(refuse(
            Refusal::UnknownCommand,
            "a coordinated part is a move (kind 9) or a stream start (kind 12)",
        ));
    }
    if group & (1 << axis) == 0 {
        return Err(refuse(
            Refusal::UnknownAxis,
            format!("the coordinated move's axes (bits {group:#010b}) do not hold axis {axis}, whose service this is"),
        ));
    }
    let beyond = group >> axes.min(MAX_AXES);
    if beyond != 0 {
        let first = beyond.trailing_zeros() as usize + axes;
        return Err(refuse(
            Refusal::UnknownAxis,
            format!(
                "the coordinated move names axis {first}: the stack has axes 0 … {}",
                axes - 1
            ),
        ));
    }
    let unsupported = request_flags::RELATIVE
        | request_flags::AFTER_CURRENT
        | request_flags::HAS_V
        | request_flags::HAS_A
        | request_flags::HAS_J;
    if is_move && r.flags & unsupported != 0 {
        return Err(refuse(
            Refusal::UnknownCommand,
            "a coordinated part is an absolute move that changes at once, at the axis's move \
             limits ([axis] move_*): no relative, after-current or limit flags",
        ));
    }
    if is_move && !r.target_rad.is_finite() {
        return Err(refuse(
            Refusal::NotFinite,
            format!("the target is {}", r.target_rad),
        ));
    }
    Ok(Part {
        kind: r.kind,
        group,
        client: r.client,
        seq: r.seq,
        since_s: t,
    })
}

/// What the waiting parts come to at a tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Gathered {
    /// The axes of a move whose parts are all in (bit per axis; 0: none): it starts now.
    pub start: u32,
    /// Axes whose part waited `wait_s` or more without its partners: refused now.
    pub expired: u32,
}

/// `parts[n]`: axis n's waiting part, if any. At most one move starts per tick (one
/// coordinated move runs at a time: a second would be refused as the first runs).
pub fn gather(parts: &[Option<Part>], t: f64, wait_s: f64) -> Gathered {
    let mut g = Gathered::default();
    for (i, p) in parts.iter().enumerate() {
        let Some(p) = p else { continue };
        let whole = (0..parts.len().min(MAX_AXES))
            .filter(|j| p.group & (1 << j) != 0)
            .all(|j| parts[j].is_some_and(|q| q.same_move(p)));
        let in_range = p.group >> parts.len().min(MAX_AXES) == 0;
        if whole && in_range && g.start == 0 {
            g.start = p.group;
        }
        if g.start & (1 << i) == 0 && t - p.since_s >= wait_s {
            g.expired |= 1 << i;
        }
    }
    g
}

/// The axes of `part`'s move that have not sent theirs, for a refusal's text.
pub fn missing(parts: &[Option<Part>], part: &Part) -> Vec<usize> {
    (0..MAX_AXES)
        .filter(|&j| part.group & (1 << j) != 0)
        .filter(|&j| {
            !parts
                .get(j)
                .copied()
                .flatten()
                .is_some_and(|q| q.same_move(part))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn part(axis: u32, group: u32, seq: u64) -> AxisRequest {
        AxisRequest {
            axis,
            kind: RequestKind::Move as u32,
            seq,
            client: 7,
            flags: request_flags::with_group(0, group),
            target_rad: 1.0,
            ..Default::default()
        }
    }

    #[test]
    fn parts_wait_for_their_partners_and_start_together() {
        let mut parts: [Option<Part>; 3] = [None; 3];
        parts[0] = Some(check_part(&part(0, 0b101, 9), 0, 3, 1.0).expect("part 0"));
        assert_eq!(gather(&parts, 1.0005, 0.05), Gathered::default());
        assert_eq!(missing(&parts, &parts[0].unwrap()), vec![2]);
        parts[2] = Some(check_part(&part(2, 0b101, 9), 2, 3, 1.001).expect("part 2"));
        assert_eq!(
            gather(&parts, 1.0015, 0.05),
            Gathered {
                start: 0b101,
                expired: 0
            }
        );
    }

    #[test]
    fn a_part_of_another_move_does_not_complete_one() {
        let mut parts: [Option<Part>; 2] = [None; 2];
        parts[0] = Some(check_part(&part(0, 0b11, 9), 0, 2, 0.0).expect("part 0"));
        parts[1] = Some(check_part(&part(1, 0b11, 10), 1, 2, 0.0).expect("part 1"));
        assert_eq!(gather(&parts, 0.001, 0.05).start, 0);
        assert_eq!(missing(&parts, &parts[0].unwrap()), vec![1]);
    }

    #[test]
    fn a_part_left_alone_expires_after_the_wait() {
        let mut parts: [Option<Part>; 2] = [None; 2];
        parts[1] = Some(check_part(&part(1, 0b11, 3), 1, 2, 0.5).expect("part 1"));
        assert_eq!(gather(&parts, 0.5495, 0.05).expired, 0);
        assert_eq!(
            gather(&parts, 0.55, 0.05),
            Gathered {
                start: 0,
                expired: 0b10
            }
        );
    }

    #[test]
    fn parts_a_stack_cannot_carry_out_are_refused_as_they_come() {
        let not_its_own = part(1, 0b101, 1);
        let beyond = part(0, 0b1001, 1);
        let relative = AxisRequest {
            flags: part(0, 0b11, 1).flags | request_flags::RELATIVE,
            ..part(0, 0b11, 1)
        };
        let limited = AxisRequest {
            flags: part(0, 0b11, 1).flags | request_flags::HAS_V,
            ..part(0, 0b11, 1)
        };
        let nan = AxisRequest {
            target_rad: f64::NAN,
            ..part(0, 0b11, 1)
        };
        let jog = AxisRequest {
            kind: RequestKind::Jog as u32,
            ..part(0, 0b11, 1)
        };
        for (r, axis, refusal) in [
            (not_its_own, 1, Refusal::UnknownAxis),
            (beyond, 0, Refusal::UnknownAxis),
            (relative, 0, Refusal::UnknownCommand),
            (limited, 0, Refusal::UnknownCommand),
            (nan, 0, Refusal::NotFinite),
            (jog, 0, Refusal::UnknownCommand),
        ] {
            let e = check_part(&r, axis, 3, 0.0).expect_err("refused");
            assert_eq!(e.refusal, refusal, "{}", e.text);
        }
        let e = check_part(&beyond, 0, 3, 0.0).expect_err("refused");
        assert!(
            e.text.contains("axis 3") && e.text.contains("0 … 2"),
            "{}",
            e.text
        );
    }

    #[test]
    fn a_stream_start_is_a_part_and_does_not_complete_a_move() {
        let start = AxisRequest {
            kind: RequestKind::StreamStart as u32,
            flags: part(1, 0b11, 4).flags | request_flags::HAS_LEAD,
            lead_s: 0.02,
            ..part(1, 0b11, 4)
        };
        let mut parts: [Option<Part>; 2] = [None; 2];
        parts[0] = Some(check_part(&part(0, 0b11, 4), 0, 2, 0.0).expect("move part"));
        parts[1] = Some(check_part(&start, 1, 2, 0.0).expect("stream part"));
        assert_eq!(gather(&parts, 0.001, 0.05).start, 0);
        parts[0] =
            Some(check_part(&AxisRequest { axis: 0, ..start }, 0, 2, 0.0).expect("stream part"));
        assert_eq!(gather(&parts, 0.001, 0.05).start, 0b11);
    }

    #[test]
    fn the_group_bits_round_trip_through_the_flags() {
        let flags = request_flags::with_group(request_flags::HAS_A, 0b1010_0001);
        assert_eq!(request_flags::group(flags), 0b1010_0001);
        assert!(flags & request_flags::COORDINATED != 0 && flags & request_flags::HAS_A != 0);
    }
}
