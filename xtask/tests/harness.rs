//! The harness's contract, checked on whichever path this machine takes (native or QEMU).

use std::process::Command;

fn xtask() -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_xtask"));
    cmd.current_dir(env!("CARGO_MANIFEST_DIR"));
    cmd
}

#[test]
fn harness_returns_the_guest_exit_status_and_output_unchanged() {
    let out = xtask()
        .args(["vcan", "--"])
        .args(["sh", "-c"])
        .arg("test -d /sys/class/net/vcan0 && test -d /sys/class/net/vcan1 && printf 'out\\n\\tline 2' && printf 'err' >&2; exit 42")
        .output()
        .expect("run xtask vcan");
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(42), "stderr: {stderr}");
    assert_eq!(out.stdout, b"out\n\tline 2", "stderr: {stderr}");
    assert!(stderr.contains("err"), "{stderr}");
}

#[test]
fn a_failing_command_inside_fails_the_harness() {
    let out = xtask()
        .args(["vcan", "--", "sh", "-c", "test 1 = 2"])
        .output()
        .expect("run xtask vcan");
    assert_eq!(out.status.code(), Some(1));
}

#[test]
fn the_time_limit_kills_a_hung_run() {
    let started = std::time::Instant::now();
    let out = xtask()
        .args(["vcan", "--timeout", "2", "--", "sleep", "600"])
        .output()
        .expect("run xtask vcan");
    assert_eq!(
        out.status.code(),
        Some(124),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(started.elapsed().as_secs() < 60);
}

#[test]
fn systemd_boots_as_pid1_with_the_setup_applied_and_runs_the_command() {
    let dir = std::env::temp_dir().join(format!("xtask-systemd-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let setup = dir.join("setup.sh");
    std::fs::write(
        &setup,
        "set -e\nmkdir -p /etc/exocal-test\necho from-setup > /etc/exocal-test/marker\n",
    )
    .unwrap();
    let out = xtask()
        .args(["vcan", "--systemd", "--timeout", "400", "--setup"])
        .arg(&setup)
        .args(["--", "sh", "-c"])
        .arg("echo pid1=$(cat /proc/1/comm); cat /etc/exocal-test/marker; systemctl is-active multi-user.target; exit 5")
        .output()
        .expect("run xtask vcan --systemd");
    std::fs::remove_dir_all(&dir).unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(
        out.status.code(),
        Some(5),
        "{stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(stdout, "pid1=systemd\nfrom-setup\nactive\n");
}
