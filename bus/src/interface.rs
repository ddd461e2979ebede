//! A CAN interface as the operating system has it: whether it exists, and what to do when it
//! does not or cannot be opened — the hints `exocald` and `exocal-hil` give alike.
//!
//! Contract: [`missing`] names how to create an interface that is not there (a `vcan` one with
//! `ip link`, a real one from its systemd-networkd file), [`open_failure`] turns an open error
//! into one that says whether the kernel lacks SocketCAN or the interface is not a CAN one;
//! both add what to load on a kernel without SocketCAN ([`kernel_has_can`]). They only read
//! `/sys/class/net` and `/proc/net/can`.

use std::path::Path;

/// Why `name` is not an interface this host has, with how to create it; `None` when it exists.
pub fn missing(name: &str) -> Option<String> {
    let valid = !name.is_empty() && name.len() <= 15 && !name.contains('/') && name != "..";
    if valid && Path::new("/sys/class/net").join(name).exists() {
        return None;
    }
    let hint = if name.starts_with("vcan") {
        format!(
            "no such interface; on a bench create it with `ip link add {name} type vcan && \
             ip link set {name} up` (or install systemd/80-vcan0.netdev)"
        )
    } else {
        "no such interface; check the CAN adapter and its systemd-networkd file \
         (systemd/80-can0.network), or pass another interface"
            .to_string()
    };
    Some(with_kernel_hint(hint, kernel_has_can()))
}

/// Whether this kernel has SocketCAN loaded: the `can` module creates `/proc/net/can`.
pub fn kernel_has_can() -> bool {
    Path::new("/proc/net/can").exists()
}

/// `reason`, and on a kernel without CAN, what to load.
fn with_kernel_hint(reason: String, has_can: bool) -> String {
    if has_can {
        reason
    } else {
        format!(
            "{reason}; this kernel has no SocketCAN loaded (no /proc/net/can): `modprobe can-raw` \
             (and `modprobe vcan` for a bench interface), or a kernel built with CONFIG_CAN"
        )
    }
}

/// Why `name` cannot be opened as a CAN socket (`error`), with what to do: the kernel lacks CAN
/// (`has_can` false), or the interface is not a CAN one (its link type), else the error alone.
pub fn open_failure(name: &str, error: &dyn std::fmt::Display, has_can: bool) -> String {
    if !has_can {
        return with_kernel_hint(format!("{error}"), false);
    }
    // ARPHRD_CAN: the link type of every CAN interface, vcan included.
    const ARPHRD_CAN: &str = "280";
    match std::fs::read_to_string(Path::new("/sys/class/net").join(name).join("type")) {
        Ok(t) if t.trim() != ARPHRD_CAN => format!(
            "{error}; `{name}` is not a CAN interface (link type {}, CAN is {ARPHRD_CAN}): pass \
             another (`ip -details link show type can`, or `type vcan`, lists them)",
            t.trim()
        ),
        _ => format!("{error}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_missing_interface_says_how_to_create_it() {
        let vcan = missing("vcan93").expect("no vcan93 here");
        assert!(vcan.contains("ip link add vcan93 type vcan"), "{vcan}");
        assert_eq!(vcan.contains("modprobe"), !kernel_has_can(), "{vcan}");
        assert!(missing("can93").unwrap().contains("80-can0.network"));
        assert!(missing("../etc").is_some() && missing("").is_some());
        assert_eq!(missing("lo"), None);
    }

    /// On a kernel without CAN, or an interface that is not CAN, the error says what
    /// to do instead of a bare "Address family not supported by protocol (os error 97)".
    #[test]
    fn a_kernel_or_interface_without_can_gets_a_hint() {
        let bare = std::io::Error::from_raw_os_error(97);
        let no_can = open_failure("can0", &bare, false);
        assert!(
            no_can.contains("os error 97") && no_can.contains("modprobe can-raw"),
            "{no_can}"
        );
        let not_can = open_failure("lo", &bare, true);
        assert!(
            not_can.contains("`lo` is not a CAN interface (link type 772"),
            "{not_can}"
        );
    }
}
