//! The axis messages as bytes, for links that are not shared memory (the Zenoh gateway,
//! docs/remote.md): each message is its `#[repr(C)]` struct's bytes, little-endian, with
//! no padding (checked below at compile time), named by its type and version.

use crate::axis::{AxisAck, AxisRequest, AxisStatus, AxisStreamPoint};

/// A message that crosses hosts as its bytes.
///
/// # Safety
/// Implemented only for `#[repr(C)]` structs of integers, floats and byte arrays with no
/// padding: every byte of a value is initialised, and every bit pattern is a value.
pub unsafe trait Wire: Copy {
    /// The type's name and version, as on the shared-memory services.
    const TYPE: &'static str;
}

// SAFETY (all four): `#[repr(C)]`, fields of u32/u64/f64/[u8; N] only, and the sizes below
// are the sums of the fields' sizes, so there is no padding.
unsafe impl Wire for AxisRequest {
    const TYPE: &'static str = "stepdrive.AxisRequest.v1";
}
unsafe impl Wire for AxisAck {
    const TYPE: &'static str = "stepdrive.AxisAck.v1";
}
unsafe impl Wire for AxisStatus {
    const TYPE: &'static str = "stepdrive.AxisStatus.v3";
}
unsafe impl Wire for AxisStreamPoint {
    const TYPE: &'static str = "stepdrive.AxisStreamPoint.v1";
}

const _: () = {
    use std::mem::size_of;
    // axis, kind, seq, publish time, client, flags, six f64.
    assert!(size_of::<AxisRequest>() == 4 + 4 + 8 + 8 + 4 + 4 + 6 * 8);
    // request, refusal, state, tick, t, publish time, text_len, reserved, text.
    assert!(
        size_of::<AxisAck>()
            == size_of::<AxisRequest>() + 4 + 4 + 8 + 8 + 8 + 4 + 4 + crate::axis::ACK_TEXT
    );
    // axis, state, tick, t, publish time, statusword, mode, eight f64, fault, warning,
    // device fault, last kind, last seq, move id, refused points, last refusal, epoch,
    // three f64.
    assert!(
        size_of::<AxisStatus>()
            == 4 + 4 + 8 + 8 + 8 + 4 + 4 + 8 * 8 + 4 * 4 + 8 + 8 + 8 + 4 + 4 + 4 * 8
    );
    // axis, flags, stream, seq, four f64, publish time.
    assert!(size_of::<AxisStreamPoint>() == 4 + 4 + 8 + 8 + 4 * 8 + 8);
    // The bytes are the host's: this build speaks little-endian only.
    assert!(cfg!(target_endian = "little"));
};

/// The message's bytes.
pub fn bytes<T: Wire>(m: &T) -> &[u8] {
    // SAFETY: `Wire` types have no padding, so all `size_of::<T>()` bytes are initialised.
    unsafe { std::slice::from_raw_parts((m as *const T).cast::<u8>(), std::mem::size_of::<T>()) }
}

/// Bytes that are not a message of the expected type.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{got} bytes are not a {ty} ({want} bytes)")]
pub struct WrongSize {
    pub ty: &'static str,
    pub got: usize,
    pub want: usize,
}

/// The message in `b`, which must be exactly its size.
pub fn from_bytes<T: Wire>(b: &[u8]) -> Result<T, WrongSize> {
    let want = std::mem::size_of::<T>();
    if b.len() != want {
        return Err(WrongSize {
            ty: T::TYPE,
            got: b.len(),
            want,
        });
    }
    // SAFETY: the length is checked, every bit pattern is a value of a `Wire` type, and
    // the read does not assume alignment.
    Ok(unsafe { std::ptr::read_unaligned(b.as_ptr().cast::<T>()) })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_message_round_trips_through_its_bytes_and_other_sizes_are_refused() {
        let r = AxisRequest {
            axis: 3,
            kind: 7,
            seq: 0x1234_5678_9abc,
            target_rad: -2.5,
            lead_s: f64::NAN,
            ..Default::default()
        };
        let b = bytes(&r).to_vec();
        assert_eq!(b.len(), 80);
        // The layout a stranger reads from the doc: axis first, little-endian.
        assert_eq!(&b[..4], &3u32.to_le_bytes());
        assert_eq!(&b[8..16], &0x1234_5678_9abcu64.to_le_bytes());
        let back: AxisRequest = from_bytes(&b).expect("same size");
        assert_eq!(back.seq, r.seq);
        assert_eq!(back.target_rad, -2.5);
        assert!(back.lead_s.is_nan());
        let short = from_bytes::<AxisRequest>(&b[1..]).expect_err("short");
        assert_eq!((short.got, short.want), (79, 80));
        assert!(from_bytes::<AxisStatus>(&b).is_err());
    }
}
