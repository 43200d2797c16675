//! Puts memory.x where cortex-m-rt's link.x looks for it, and the sample rate
//! (`STEPDRIVE_FIRMWARE_SAMPLE_HZ`, 2000 if unset) where main.rs includes it.
use std::path::PathBuf;

/// The rates the firmware keeps exact: a whole number of SysTick's 25 MHz cycles and of
/// microseconds a period (its timestamps and its network clock count those).
fn valid(hz: u32) -> bool {
    (100..=20_000).contains(&hz) && 25_000_000 % hz == 0 && 1_000_000 % hz == 0
}

fn main() {
    let out = PathBuf::from(std::env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    std::fs::copy("memory.x", out.join("memory.x")).expect("memory.x is beside Cargo.toml");
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rerun-if-changed=memory.x");
    println!("cargo:rerun-if-env-changed=STEPDRIVE_FIRMWARE_SAMPLE_HZ");
    let hz = match std::env::var("STEPDRIVE_FIRMWARE_SAMPLE_HZ") {
        Err(_) => 2_000,
        Ok(text) => match text.parse() {
            Ok(hz) if valid(hz) => hz,
            _ => {
                eprintln!(
                    "STEPDRIVE_FIRMWARE_SAMPLE_HZ={text}: a rate in Hz from 100 to 20000 that \
                     divides 1000000 (a whole number of microseconds a period)"
                );
                std::process::exit(1);
            }
        },
    };
    std::fs::write(
        out.join("sample_rate.rs"),
        format!("/// The sample rate (build.rs: STEPDRIVE_FIRMWARE_SAMPLE_HZ).\nconst SAMPLE_HZ: u32 = {hz};\n"),
    )
    .expect("OUT_DIR is writable");
}
