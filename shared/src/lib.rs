//! The contract between stepdrive's processes: the message types ([`messages`], [`stats`]),
//! the topics they travel on and the settings every opener uses ([`services`]), the scenario
//! with motor parameters, gains, rates and trajectory ([`scenario`], [`trajectory`]), and the
//! DQ frame the metrics and laws share ([`frames`]). No process logic lives here: timing,
//! ports and the runner are `stepdrive-runtime`'s.

pub mod axis;
pub mod frames;
pub mod messages;
pub mod plant;
pub mod scenario;
pub mod services;
pub mod stack;
pub mod stats;
pub mod trajectory;
pub mod wire;

pub use messages::{DriveCommand, DriveState, TorqueSetpoint};
pub use scenario::{Method, Mode, Scenario, ScenarioError};

/// FNV-1a of `bytes`: a hash every process and build computes alike (a scenario's
/// fingerprint, an instance's lockstep CPUs), unlike the standard library's.
pub fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, &b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

#[cfg(test)]
mod tests {
    /// The published FNV-1a 64 test vectors: a fingerprint stays what it was.
    #[test]
    fn fnv1a_gives_the_published_values() {
        assert_eq!(super::fnv1a(b""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(super::fnv1a(b"a"), 0xaf63_dc4c_8601_ec8c);
        assert_eq!(super::fnv1a(b"foobar"), 0x8594_4171_f739_67e8);
    }
}
