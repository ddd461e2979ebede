//! Shared helpers for exocal's end-to-end tests.
//!
//! Suites that need a real CAN interface are built only with the `vcan` feature and run inside
//! `cargo xtask vcan`, which provides `vcan0` and `vcan1` (natively in a private network
//! namespace, or in a QEMU guest when this kernel has no CAN). They call [`require_vcan`] first, so
//! that outside the harness they fail loudly instead of passing as if they had run.

use std::ffi::CString;

/// The environment variable the harness sets inside its namespace or guest.
pub const HARNESS_ENV: &str = "EXOCAL_VCAN_HARNESS";

/// Panics with a message saying how to run the suite unless `iface` exists and is up.
pub fn require_vcan(iface: &str) {
    let name = CString::new(iface).expect("interface name has no NUL");
    // SAFETY: `name` is a valid NUL-terminated C string for the duration of the call.
    #[allow(unsafe_code)]
    let index = unsafe { libc::if_nametoindex(name.as_ptr()) };
    if index == 0 {
        panic!(
            "interface {iface} does not exist: this suite needs real vcan; run it through \
             `cargo xtask test` or `cargo xtask vcan -- <test binary>` (harness env {HARNESS_ENV}={:?})",
            std::env::var(HARNESS_ENV).ok()
        );
    }
    let flags =
        std::fs::read_to_string(format!("/sys/class/net/{iface}/flags")).unwrap_or_default();
    let flags = u32::from_str_radix(flags.trim().trim_start_matches("0x"), 16).unwrap_or(0);
    assert!(
        flags & 1 != 0,
        "interface {iface} exists but is not up (flags {flags:#x})"
    );
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    #[should_panic(expected = "does not exist")]
    fn require_vcan_panics_on_a_missing_interface() {
        require_vcan("exocal-none9");
    }
}
