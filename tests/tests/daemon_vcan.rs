//! End to end on real vcan: `exocal-hil` (the paper scenario, drift on) and `exocald calibrate`,
//! as separate processes, exactly as a bench runs them.
//!
//! - the daemon calibrates and pushes; every node's persisted table equals the daemon's result by
//!   CRC; the pushed table, judged independently on held-out motion of the true arm, is at least
//!   80% better than nominal;
//! - the session's MCAP reads back with the mcap crate and with python's `mcap` reader (CRC
//!   validated), every channel is present, and the raw frames logged are exactly the frames a
//!   capture socket saw on the bus over the same window (nothing lost, nothing invented);
//! - SIGTERM during collection leaves a finished MCAP and pushes nothing; a missing interface is
//!   a clear error;
//! - `exocald nodes` lists every node's table as its flash holds it and names a node that does
//!   not answer (exit 69, `--json`);
//! - `exocald run` (serve) on short sessions: one started by SIGUSR1, a second SIGUSR1 and a
//!   Trigger frame during it ignored (and said so), the next started by a Trigger frame, SIGTERM
//!   while collecting (75, log finished) and, in a second daemon, while idle (0).
//!
//! Every wait is on an event — a line of the daemon's or the hil's stderr — bounded only as a
//! guard against a hang.
//!
//! Needs vcan0 and the binaries: run through `cargo xtask test` (which builds them and sets
//! `EXOCAL_BIN_DIR` and `EXOCAL_PYTHON`).

use std::collections::{BTreeMap, HashSet};
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use calib_core::{objective_y, DhRow, DhTable, Sample, Scenario, ScenarioConfig};
use exocal_dbc::table::Field;
use exocal_dbc::NodeId;

#[path = "common/log_json.rs"]
mod log_json;

/// Simulated time per wall-clock time for the emulated suit. At 1× the QEMU guest keeps up with
/// ~3,000 frames/s with room to spare, so node clocks stay a clean line against host time.
const SPEED: &str = "1";

fn workspace() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("workspace root")
        .to_path_buf()
}

fn bin(name: &str) -> PathBuf {
    let dir = std::env::var_os("EXOCAL_BIN_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace().join("target/release"));
    let path = dir.join(name);
    assert!(
        path.is_file(),
        "{} not built: run through `cargo xtask test`, or `cargo build --release --bins` first",
        path.display()
    );
    path
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("exocal-e2e-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// The shipped configuration, pointed at vcan0 and `out`, collecting `min_s` seconds.
fn config(dir: &Path, out: &Path, min_s: f64) -> PathBuf {
    config_with(dir, out, &[("min_duration_s", format!("{min_s:.1}"))])
}

/// The shipped configuration, pointed at vcan0 and `out`, with `keys` set (`key = value`), its
/// window fixed (stop-when-good-enough off) unless `stop_at_expected_error` is set.
fn config_with(dir: &Path, out: &Path, keys: &[(&str, String)]) -> PathBuf {
    let shipped = std::fs::read_to_string(workspace().join("daemon/exocald.toml")).unwrap();
    let mut text = String::new();
    for line in shipped.lines() {
        let key = line.split('=').next().unwrap_or("").trim();
        let set = keys.iter().find(|(k, _)| *k == key);
        let line = match key {
            "interface" => "interface = \"vcan0\"".to_string(),
            "directory" => format!("directory = {:?}", out.display().to_string()),
            _ if set.is_some() => format!("{key} = {}", set.unwrap().1),
            // A fixed window unless set: the guest's emulated CPU would spend the window on
            // the good-enough estimates (LS + EM every 5 s).
            "stop_at_expected_error" => format!("# {line}"),
            _ => line.to_string(),
        };
        text.push_str(&line);
        text.push('\n');
    }
    let path = dir.join("exocald.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// The lines a child writes to stderr, as they come (a thread reads them), echoed to ours.
struct Lines {
    rx: mpsc::Receiver<String>,
    seen: Vec<String>,
}

impl Lines {
    fn of(stderr: std::process::ChildStderr, who: &'static str) -> Lines {
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                eprintln!("[{who}] {line}");
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Lines {
            rx,
            seen: Vec::new(),
        }
    }

    /// Waits for the next line containing `needle` (the guard: `limit`), and returns it.
    fn wait_for(&mut self, needle: &str, limit: Duration) -> String {
        self.wait_for_each(&[needle], limit).remove(0)
    }

    /// Every line the child wrote, once it has exited (its stderr closed).
    fn all(mut self) -> Vec<String> {
        self.seen.extend(self.rx.iter());
        self.seen
    }

    /// Waits for the next line that `want` accepts (the guard: `limit`; `what` names it in
    /// the panic), and returns it.
    fn wait_until(&mut self, what: &str, want: impl Fn(&str) -> bool, limit: Duration) -> String {
        let deadline = Instant::now() + limit;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.rx.recv_timeout(left) {
                Ok(line) => {
                    self.seen.push(line.clone());
                    if want(&line) {
                        return line;
                    }
                }
                Err(e) => panic!(
                    "no {what} ({e:?} after {limit:?}); lines so far:\n{}",
                    self.seen.join("\n")
                ),
            }
        }
    }

    /// Waits until a line containing each of `needles` has come, in any order (the guard:
    /// `limit`); returns those lines, in the order of `needles`.
    fn wait_for_each(&mut self, needles: &[&str], limit: Duration) -> Vec<String> {
        let deadline = Instant::now() + limit;
        let mut found: Vec<Option<String>> = vec![None; needles.len()];
        while found.iter().any(Option::is_none) {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.rx.recv_timeout(left) {
                Ok(line) => {
                    self.seen.push(line.clone());
                    if let Some(k) = (0..needles.len())
                        .find(|&k| found[k].is_none() && line.contains(needles[k]))
                    {
                        found[k] = Some(line);
                    }
                }
                Err(e) => panic!(
                    "no line with {needles:?} ({e:?} after {limit:?}); lines so far:\n{}",
                    self.seen.join("\n")
                ),
            }
        }
        found.into_iter().flatten().collect()
    }
}

/// Time limits that only catch hangs: the suites wait on events (a readiness line, a progress
/// line, a process's exit), never on how fast a loaded host or the TCG guest runs.
const HANG: Duration = Duration::from_secs(1800);

/// A credentials directory as systemd makes it, holding `exocal-keys` (test keys): the
/// daemon reads it through `$CREDENTIALS_DIRECTORY`, the hil's nodes are provisioned from it.
fn credentials(dir: &Path) -> PathBuf {
    let creds = dir.join("credentials");
    if !creds.join("exocal-keys").exists() {
        std::fs::create_dir_all(&creds).unwrap();
        let mut text: String = (1..=7u128)
            .map(|n| {
                format!(
                    "Joint{n} {:032x}\n",
                    n * 0x0123_4567_89ab_cdef_0f1e_2d3c_4b5a_6978
                )
            })
            .collect();
        text.push_str("EndEffector 21be7911eb2dfb39e83b39a63b2d5ad0\n");
        text.push_str("Trigger 95057c9d33381fbef4c25044b45b37a5\n");
        std::fs::write(creds.join("exocal-keys"), text).unwrap();
    }
    creds
}

/// The daemon's state directory (`$STATE_DIRECTORY`, the shipped unit's `StateDirectory=`):
/// with keys, exocald keeps the nodes' freshness counters and the trigger counter there.
fn state(dir: &Path) -> PathBuf {
    let state = dir.join("state");
    std::fs::create_dir_all(&state).unwrap();
    state
}

/// `exocald --config <cfg> <args…>` with the test's credentials and state directories under
/// `dir`, its stdin closed.
fn keyed_exocald(dir: &Path, cfg: &Path, args: &[&str]) -> Command {
    let mut c = Command::new(bin("exocald"));
    c.arg("--config")
        .arg(cfg)
        .args(args)
        .env("CREDENTIALS_DIRECTORY", credentials(dir))
        .env("STATE_DIRECTORY", state(dir))
        .stdin(Stdio::null());
    c
}

struct Hil {
    child: Child,
    flash: PathBuf,
    /// Keeps reading (and echoing) the hil's stderr, so that its pipe never fills.
    _stderr: Lines,
}

impl Hil {
    fn start(dir: &Path, duration_s: u32) -> Hil {
        Hil::start_with(dir, duration_s, "")
    }

    /// The paper scenario with `extra` TOML appended, playing for `duration_s`; returns once its
    /// nodes are up (its readiness line: the flash is written, the bus open).
    fn start_with(dir: &Path, duration_s: u32, extra: &str) -> Hil {
        let flash = dir.join("flash");
        // The paper scenario, with the raw IMU channels (70% of the traffic, unused by the
        // calibration) at 10 Hz instead of 100 Hz, so that the TCG guest keeps up.
        let paper = std::fs::read_to_string(workspace().join("hil/scenarios/paper.toml")).unwrap();
        let scenario = dir.join("scenario.toml");
        let text = paper.replace("imu_hz = 100.0", "imu_hz = 10.0") + extra;
        std::fs::write(&scenario, text).unwrap();
        let mut child = Command::new(bin("exocal-hil"))
            .arg("--scenario")
            .arg(&scenario)
            .args(["--iface", "vcan0", "--speed", SPEED, "--duration"])
            .arg(duration_s.to_string())
            .arg("--flash-dir")
            .arg(&flash)
            .arg("--keys")
            .arg(credentials(dir).join("exocal-keys"))
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start exocal-hil");
        let mut lines = Lines::of(child.stderr.take().expect("piped"), "hil");
        // The readiness line: its socket is open and its nodes have booted, their flash written.
        lines.wait_for("exocal-hil: playing", HANG);
        Hil {
            child,
            flash,
            _stderr: lines,
        }
    }

    /// CRC of the table each joint node holds in its flash (`None`: nothing flashed yet).
    fn held_crcs(&self) -> BTreeMap<u8, Option<u32>> {
        (1..=7u8)
            .map(|n| {
                let node = NodeId::new(n).unwrap();
                let image = exocal_hil::flash::read(&self.flash, node).expect("flash readable");
                (n, image.map(|i| i.table.crc()))
            })
            .collect()
    }

    /// The D-H table the joint nodes hold.
    fn held_table(&self) -> DhTable<7> {
        DhTable {
            rows: std::array::from_fn(|i| {
                let node = NodeId::new(i as u8 + 1).unwrap();
                let t = exocal_hil::flash::read(&self.flash, node)
                    .unwrap()
                    .unwrap()
                    .table;
                DhRow {
                    a: t.si(Field::A),
                    alpha: t.si(Field::Alpha),
                    d: t.si(Field::D),
                    theta_offset: t.si(Field::ThetaOffset),
                }
            }),
        }
    }

    fn stop(self) {
        drop(self);
    }
}

/// A test that fails must not leave the hil playing on vcan0 for the suites after it.
impl Drop for Hil {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Every frame on vcan0 (id, data), recorded by an independent socket, like candump.
struct Capture {
    stop: std::sync::Arc<std::sync::atomic::AtomicBool>,
    thread: std::thread::JoinHandle<Vec<(u32, Vec<u8>)>>,
}

impl Capture {
    fn start() -> Capture {
        use socketcan::{EmbeddedFrame, Socket, SocketOptions};
        let sock = socketcan::CanSocket::open("vcan0").expect("capture socket");
        if sock
            .set_socket_option_int(libc::SOL_SOCKET, libc::SO_RCVBUFFORCE, 16 << 20)
            .is_err()
        {
            sock.set_socket_option_int(libc::SOL_SOCKET, libc::SO_RCVBUF, 16 << 20)
                .unwrap();
        }
        sock.set_read_timeout(Duration::from_millis(100)).unwrap();
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let flag = stop.clone();
        let thread = std::thread::spawn(move || {
            let mut frames = Vec::new();
            while !flag.load(std::sync::atomic::Ordering::Relaxed) {
                if let Ok(f) = sock.read_frame() {
                    let id = match f.id() {
                        embedded_can::Id::Standard(s) => u32::from(s.as_raw()),
                        embedded_can::Id::Extended(e) => e.as_raw(),
                    };
                    frames.push((id, f.data().to_vec()));
                }
            }
            frames
        });
        Capture { stop, thread }
    }

    fn finish(self) -> Vec<(u32, Vec<u8>)> {
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        self.thread.join().unwrap()
    }
}

/// The session's MCAP file in `out` (exactly one).
fn mcap_file(out: &Path) -> PathBuf {
    let files: Vec<PathBuf> = std::fs::read_dir(out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
        .collect();
    assert_eq!(files.len(), 1, "one MCAP per session: {files:?}");
    files[0].clone()
}

/// Messages per topic, read with the mcap crate (summary and every message).
fn mcap_topics(path: &Path) -> (BTreeMap<String, u64>, Vec<(String, serde_json::Value)>) {
    let bytes = std::fs::read(path).unwrap();
    let summary = mcap::Summary::read(&bytes)
        .expect("summary readable")
        .expect("a finished file has a summary");
    let mut counts: BTreeMap<String, u64> = summary
        .channels
        .values()
        .map(|c| (c.topic.clone(), 0))
        .collect();
    let mut messages = Vec::new();
    for m in mcap::MessageStream::new(&bytes).expect("message stream") {
        let m = m.expect("every message readable");
        *counts.entry(m.channel.topic.clone()).or_default() += 1;
        let schema = m.channel.schema.as_ref().map_or("", |s| s.name.as_str());
        for v in log_json::log_message_json(
            &m.channel.topic,
            schema,
            &m.channel.message_encoding,
            &m.data,
        ) {
            messages.push((m.channel.topic.clone(), v));
        }
    }
    (counts, messages)
}

/// Messages per topic, read with python's `mcap` reader with CRC validation.
fn python_topics(path: &Path) -> BTreeMap<String, u64> {
    let python = std::env::var("EXOCAL_PYTHON")
        .expect("EXOCAL_PYTHON: run through `cargo xtask test`, which makes the venv");
    let script = r#"import json, sys
from mcap.reader import make_reader
counts = {}
with open(sys.argv[1], "rb") as f:
    reader = make_reader(f, validate_crcs=True)
    for ch in reader.get_summary().channels.values():
        counts.setdefault(ch.topic, 0)
    for _schema, channel, _message in reader.iter_messages():
        counts[channel.topic] = counts.get(channel.topic, 0) + 1
print(json.dumps(counts))
"#;
    let out = Command::new(&python)
        .args(["-c", script])
        .arg(path)
        .output()
        .expect("run python");
    assert!(
        out.status.success(),
        "python mcap reader failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("counts as JSON")
}

fn frame_of(v: &serde_json::Value) -> (u32, Vec<u8>) {
    let id = v["id"].as_u64().expect("id") as u32;
    let data = v["data"]
        .as_array()
        .expect("data")
        .iter()
        .map(|b| b.as_u64().expect("byte") as u8)
        .collect();
    (id, data)
}

const TOPICS: [&str; 11] = [
    "/can/rx",
    "/can/tx",
    "/joint_states",
    "/ee_pose",
    "/ee_gyro",
    "/ee_mag",
    "/tf",
    "/aligned",
    "/progress",
    "/calibration",
    "/events",
];

#[test]
fn calibrate_on_vcan0_pushes_a_table_every_node_holds_and_logs_every_frame() {
    exocal_tests::require_vcan("vcan0");
    let dir = scratch("calibrate");
    let out = dir.join("out");
    let cfg = config(&dir, &out, 60.0);
    let capture = Capture::start();
    // The arm keeps moving after the window; once its motion ends, the nodes keep answering
    // (the push) until `stop`, however long the calibration takes.
    let hil = Hil::start(&dir, 400);
    let factory = hil.held_crcs();
    let started = Instant::now();
    let daemon = keyed_exocald(&dir, &cfg, &["calibrate"])
        .output()
        .expect("run exocald");
    let frames = capture.finish();
    let stdout = String::from_utf8_lossy(&daemon.stdout);
    let stderr = String::from_utf8_lossy(&daemon.stderr);
    println!(
        "exocald ({:.0} s):\n{stdout}",
        started.elapsed().as_secs_f64()
    );
    let held = hil.held_crcs();
    let pushed = hil.held_table();
    hil.stop();
    assert_eq!(
        daemon.status.code(),
        Some(0),
        "exocald calibrate failed:\n{stderr}"
    );

    // Every node holds a new table, and it is the one the daemon says it pushed.
    let (counts, messages) = mcap_topics(&mcap_file(&out));
    let push = messages
        .iter()
        .rev()
        .find(|(t, v)| t == "/calibration" && v.get("nodes").is_some())
        .map(|(_, v)| v.clone())
        .expect("push report in /calibration");
    for node in push["nodes"].as_array().unwrap() {
        let name = node["node"].as_str().unwrap();
        let n: u8 = name.trim_start_matches("Joint").parse().expect("JointN");
        let sent = node["new_crc"].as_u64().unwrap() as u32;
        assert_eq!(node["holds"], "new", "{node}");
        assert_eq!(
            held[&n],
            Some(sent),
            "node {n} flash holds {:?}, daemon sent {sent:#x}",
            held[&n]
        );
        assert_ne!(
            held[&n], factory[&n],
            "node {n} still holds its factory table"
        );
    }

    // Judged independently: held-out motion of the true arm (Table 4, drift on), unseen seed.
    let heldout: Vec<Sample<7>> = Scenario::new(ScenarioConfig::paper(), 0xE2E)
        .take(6000)
        .map(|s| s.sample)
        .collect();
    let y_nominal = objective_y(&DhTable::paper_nominal(), &heldout);
    let y_pushed = objective_y(&pushed, &heldout);
    let better = 1.0 - y_pushed / y_nominal;
    println!(
        "held-out y: nominal {y_nominal:.3}, pushed {y_pushed:.3} ({:.1}% better)",
        better * 100.0
    );
    assert!(
        better >= 0.80,
        "pushed table only {:.1}% better than nominal on held-out motion",
        better * 100.0
    );

    // The log: every channel, the same counts in python (CRCs validated), and exactly the frames
    // that were on the bus over the session's window.
    for topic in TOPICS {
        assert!(
            counts.contains_key(topic),
            "channel {topic} missing: {counts:?}"
        );
    }
    assert_eq!(
        python_topics(&mcap_file(&out)),
        counts,
        "python and Rust readers disagree"
    );
    let rx: Vec<(u32, Vec<u8>)> = messages
        .iter()
        .filter(|(t, _)| t == "/can/rx")
        .map(|(_, v)| frame_of(v))
        .collect();
    let tx_ids: HashSet<u32> = messages
        .iter()
        .filter(|(t, _)| t == "/can/tx")
        .map(|(_, v)| frame_of(v).0)
        .collect();
    // At least every frame of the collection window (the summary's count; the frames that
    // arrive while calibrating and pushing come on top, as many as that took).
    let window_frames: usize = stdout
        .lines()
        .find_map(|l| l.strip_prefix("frames: "))
        .and_then(|l| l.split(' ').next())
        .and_then(|n| n.parse().ok())
        .expect("the summary's frames line");
    assert!(
        window_frames > 60_000 && rx.len() >= window_frames,
        "{} frames logged, {window_frames} received in the window",
        rx.len()
    );
    let bus: Vec<&(u32, Vec<u8>)> = frames.iter().filter(|f| !tx_ids.contains(&f.0)).collect();
    let first = bus
        .windows(8)
        .position(|w| w.iter().zip(&rx[..8]).all(|(a, b)| *a == b))
        .expect("the daemon's first frames appear on the bus");
    let window = &bus[first..(first + rx.len()).min(bus.len())];
    let mismatch = window.iter().zip(&rx).position(|(a, b)| *a != b);
    assert_eq!(
        (window.len(), mismatch),
        (rx.len(), None),
        "the daemon's /can/rx is not exactly the bus over its window"
    );
    println!(
        "MCAP: {} raw frames = the bus over the session; channels {counts:?}",
        rx.len()
    );

    // The live run left its report next to the log, and the recorded session recalibrates
    // offline (no bus) to the same result: the same samples, the same held-out errors.
    let log = mcap_file(&out);
    assert!(
        log.with_extension("html").is_file(),
        "no report next to {}",
        log.display()
    );
    let offline = Command::new(bin("exocald"))
        .arg("--config")
        .arg(&cfg)
        .args(["offline", "--input"])
        .arg(&log)
        .arg("--report")
        .arg(dir.join("offline.html"))
        .stdin(Stdio::null())
        .output()
        .expect("run exocald offline");
    let replayed = String::from_utf8_lossy(&offline.stdout);
    assert_eq!(
        offline.status.code(),
        Some(0),
        "exocald offline failed:\n{replayed}\n{}",
        String::from_utf8_lossy(&offline.stderr)
    );
    for key in ["aligned samples:", "held-out mean error"] {
        let line = |text: &str| {
            text.lines()
                .find(|l| l.starts_with(key))
                .map(str::to_owned)
                .unwrap_or_else(|| panic!("no {key:?} line in:\n{text}"))
        };
        assert_eq!(line(&replayed), line(&stdout), "offline and live disagree");
        println!("offline = live: {}", line(&replayed));
    }
}

#[test]
fn sigterm_during_collection_finishes_the_log_and_pushes_nothing() {
    exocal_tests::require_vcan("vcan0");
    let dir = scratch("sigterm");
    let out = dir.join("out");
    let cfg = config(&dir, &out, 60.0);
    let hil = Hil::start(&dir, 120);
    let factory = hil.held_crcs();
    let mut daemon = keyed_exocald(&dir, &cfg, &["calibrate"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start exocald");
    // Mid-collection by the daemon's own account: its progress line after 5 s of collecting
    // (of the 60 s window), whatever that took in real time.
    let mut lines = Lines::of(daemon.stderr.take().expect("piped"), "exocald");
    let progress = lines.wait_until(
        "progress line after 5 s of collection",
        |l| {
            l.strip_prefix("exocald: collecting ")
                .and_then(|r| r.split(' ').next())
                .and_then(|s| s.parse::<f64>().ok())
                .is_some_and(|s| s >= 5.0)
        },
        HANG,
    );
    println!("SIGTERM after: {progress}");
    // SAFETY: plain kill(2) on our child.
    #[allow(unsafe_code)]
    unsafe {
        libc::kill(daemon.id() as i32, libc::SIGTERM)
    };
    let deadline = Instant::now() + HANG;
    let status = loop {
        if let Some(s) = daemon.try_wait().unwrap() {
            break s;
        }
        assert!(Instant::now() < deadline, "exocald ignored SIGTERM");
        std::thread::sleep(Duration::from_millis(50));
    };
    let stderr = lines.all();
    let _ = daemon.wait_with_output().unwrap();
    let held = hil.held_crcs();
    hil.stop();
    assert_eq!(
        status.code(),
        Some(75),
        "interrupted session exits EX_TEMPFAIL: {}",
        stderr.join("\n")
    );
    assert_eq!(held, factory, "a table was pushed after SIGTERM");
    let (counts, messages) = mcap_topics(&mcap_file(&out));
    let frames = messages.iter().filter(|(t, _)| t == "/can/rx").count();
    assert!(frames > 1000, "{frames} frames received: {counts:?}");
    assert!(
        messages
            .iter()
            .all(|(t, v)| t != "/calibration" || v.get("nodes").is_none()),
        "a push report in an interrupted session"
    );
    assert_eq!(python_topics(&mcap_file(&out)), counts);
}

#[test]
fn a_missing_interface_is_a_clear_error() {
    exocal_tests::require_vcan("vcan0");
    let dir = scratch("noiface");
    let out = Command::new(bin("exocald"))
        .args(["calibrate", "--interface", "vcan9", "--output"])
        .arg(dir.join("out"))
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(69), "{stderr}");
    assert!(stderr.contains("vcan9"), "{stderr}");
}

/// `exocald nodes` against the hil's nodes, Joint4 silent: every other node's CRC and table as
/// its flash holds them, Joint4 named, exit 69.
#[test]
fn nodes_lists_what_every_node_holds_and_names_a_silent_one() {
    exocal_tests::require_vcan("vcan0");
    let dir = scratch("nodes");
    let out = dir.join("out");
    let cfg = config(&dir, &out, 60.0);
    let hil = Hil::start_with(
        &dir,
        600,
        "\n[[faults.transfer]]\nnode = 4\nbehaviour = \"silent\"\n",
    );
    let held = hil.held_crcs();
    let run = Command::new(bin("exocald"))
        .arg("--config")
        .arg(&cfg)
        .args(["nodes", "--json"])
        .stdin(Stdio::null())
        .output()
        .expect("run exocald nodes");
    hil.stop();
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(69), "{stderr}");
    assert!(stderr.contains("no answer from Joint4"), "{stderr}");
    let listing: serde_json::Value = serde_json::from_slice(&run.stdout).expect("JSON listing");
    println!("{listing:#}");
    assert_eq!(listing["missing"], serde_json::json!(["Joint4"]));
    assert_eq!(listing["compared_with"], serde_json::Value::Null);
    for node in listing["nodes"].as_array().unwrap() {
        let n = node["id"].as_u64().unwrap() as u8;
        if n == 4 {
            assert_eq!(node["answered"], false, "{node}");
            continue;
        }
        assert_eq!(node["crc"].as_u64().map(|c| c as u32), held[&n], "{node}");
        let tau = node["table"]["tau_s"].as_f64().unwrap();
        assert!((tau - 1.0).abs() < 1e-9, "the factory τ: {node}");
    }
}

/// `exocald run` on vcan0: sessions on demand by SIGUSR1 or an authentic Trigger frame (the
/// keys from `$CREDENTIALS_DIRECTORY`, as systemd gives them), triggers during a session
/// ignored, a forged and a replayed Trigger frame refused, SIGTERM in either state. Sessions
/// are short (3 s, any motion; a dry run) so the guest is not kept busy; the cooldown is 1 s.
#[test]
fn serve_runs_a_session_per_trigger_and_stops_on_sigterm() {
    use socketcan::{CanFrame, Socket};
    exocal_tests::require_vcan("vcan0");
    let dir = scratch("serve");
    let out = dir.join("out");
    let cfg = config_with(
        &dir,
        &out,
        &[
            ("min_duration_s", "3.0".into()),
            ("max_duration_s", "3.0".into()),
            ("excitation_required", "0.01".into()),
            ("min_samples", "50".into()),
            ("grid_hz", "50.0".into()),
            ("cooldown_s", "1.0".into()),
        ],
    );
    let hil = Hil::start(&dir, 600);
    let keys = exocal_dbc::auth::KeySet::parse(
        &std::fs::read_to_string(credentials(&dir).join("exocal-keys")).unwrap(),
    )
    .unwrap();
    let can = socketcan::CanSocket::open("vcan0").expect("a socket to send triggers");
    let counter = std::cell::Cell::new(0u32);
    let send = |t: exocal_dbc::Trigger| {
        let frame: CanFrame = exocal_dbc::Message::Trigger(t).to_frame().unwrap();
        can.write_frame(&frame).expect("send a Trigger frame");
    };
    // An authentic, fresh Trigger frame (the next counter); returns it for replays.
    let trigger = || {
        counter.set(counter.get() + 1);
        let t = exocal_dbc::auth::trigger(
            keys.trigger().unwrap(),
            exocal_dbc::TriggerCommand::StartCalibration,
            counter.get(),
        );
        send(t);
        t
    };
    let signal = |child: &Child, sig: i32| {
        // SAFETY: plain kill(2) on our child.
        #[allow(unsafe_code)]
        let rc = unsafe { libc::kill(child.id() as i32, sig) };
        assert_eq!(rc, 0);
    };
    let serve = || {
        let mut child = keyed_exocald(&dir, &cfg, &["run", "--dry-run"])
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start exocald run");
        let lines = Lines::of(child.stderr.take().unwrap(), "exocald");
        (child, lines)
    };
    let started = Instant::now();
    let (mut daemon, mut lines) = serve();
    lines.wait_for("idle: waiting for a trigger", HANG);

    // 1. By signal; a second signal and a Trigger frame while it collects are ignored.
    signal(&daemon, libc::SIGUSR1);
    lines.wait_for("trigger received (SIGUSR1): starting a session", HANG);
    lines.wait_for("logging to", HANG);
    signal(&daemon, libc::SIGUSR1);
    trigger();
    lines.wait_for_each(
        &[
            "trigger ignored (SIGUSR1): a session is running",
            "trigger ignored (CAN Trigger frame): a session is running",
        ],
        HANG,
    );
    lines.wait_for("idle: waiting for a trigger", HANG);

    // 2. A forged frame starts nothing; by a fresh frame: the next session is this one (the
    // ignored triggers were not queued).
    std::thread::sleep(Duration::from_millis(1500)); // past the cooldown
    let mut forged = exocal_dbc::auth::trigger(
        keys.trigger().unwrap(),
        exocal_dbc::TriggerCommand::StartCalibration,
        counter.get() + 1,
    );
    forged.mac ^= 1;
    send(forged);
    lines.wait_for("Trigger frame(s) refused", HANG);
    let second = trigger();
    let next = lines.wait_for("trigger received", HANG);
    assert!(next.contains("(CAN Trigger frame)"), "{next}");
    lines.wait_for("logging to", HANG);

    // 3. SIGTERM while it collects: interrupted (75), its log finished.
    signal(&daemon, libc::SIGTERM);
    let status = daemon.wait().unwrap();
    assert_eq!(status.code(), Some(75), "{}", lines.seen.join("\n"));
    let sessions = lines
        .seen
        .iter()
        .filter(|l| l.contains("trigger received"))
        .count();
    assert_eq!(sessions, 2, "{}", lines.seen.join("\n"));
    let mut logs: Vec<PathBuf> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
        .collect();
    logs.sort();
    assert_eq!(logs.len(), 2, "one log per session: {logs:?}");
    for log in &logs {
        mcap_topics(log); // finished: the summary reads
    }
    // The first session's log says it ignored the frame.
    let events: Vec<String> = {
        let bytes = std::fs::read(&logs[0]).unwrap();
        mcap::MessageStream::new(&bytes)
            .unwrap()
            .filter_map(|m| m.ok())
            .filter(|m| m.channel.topic == "/events")
            .map(|m| String::from_utf8_lossy(&m.data).into_owned())
            .collect()
    };
    assert!(
        events
            .iter()
            .any(|e| e.contains("trigger ignored (CAN Trigger frame)")),
        "{events:?}"
    );

    // 4. Restarted, it remembers the last accepted counter: a replay of the frame that started
    // the second session is refused. SIGTERM while idle: a clean exit, no session.
    let (mut idle, mut lines) = serve();
    lines.wait_for("idle: waiting for a trigger", HANG);
    send(second);
    lines.wait_for("Trigger frame(s) refused", HANG);
    signal(&idle, libc::SIGTERM);
    let status = idle.wait().unwrap();
    hil.stop();
    assert_eq!(status.code(), Some(0), "{}", lines.seen.join("\n"));
    println!(
        "serve: two sessions, two ignored triggers, a forged and a replayed trigger refused, \
         SIGTERM collecting and idle in {:.1} s",
        started.elapsed().as_secs_f64()
    );
}
