//! `exocal-hil` as a user runs it: a missing interface is named with how to create it, exit 69
//! (as exocald), never anyhow's `Error:` nor, with `RUST_BACKTRACE=1`, a backtrace and exit 1.

use std::process::Command;

#[test]
fn a_missing_interface_says_how_to_create_it_and_exits_69() {
    let dir = std::env::temp_dir().join(format!("exocal-hil-cli-{}", std::process::id()));
    let out = Command::new(env!("CARGO_BIN_EXE_exocal-hil"))
        .args(["--iface", "vcan93", "--flash-dir"])
        .arg(&dir)
        .env("RUST_BACKTRACE", "1")
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(69), "{err}");
    assert!(
        err.starts_with("exocal-hil: CAN interface vcan93: no such interface"),
        "{err}"
    );
    assert!(err.contains("ip link add vcan93 type vcan"), "{err}");
    assert!(
        !err.contains("backtrace") && !err.contains("Error:"),
        "{err}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}
