//! The live view, end to end and in process: a WebSocket client (tokio-tungstenite, speaking the
//! Foxglove WebSocket protocol by hand) connects to `exocald demo` with the live view on,
//! subscribes, and receives the URDF, joint states of all seven joints, the arm's frames,
//! collection progress and the calibration result — the same table the session pushed.

use std::time::Duration;

use exocal_log::{fox, proto};
use futures_util::{SinkExt, StreamExt};
use prost::Message as _;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::tungstenite::Message;

use exocald::cmd::demo::{demo_config, run_with, DemoOptions};
use exocald::config::Config;
use exocald::live::LiveView;

/// What the client got, per topic.
#[derive(Default)]
struct Got {
    joint_states: Vec<fox::JointStates>,
    /// Log time of every message, per topic.
    times: std::collections::HashMap<&'static str, Vec<u64>>,
    tf: usize,
    progress: usize,
    calibrations: Vec<proto::Calibration>,
    /// Log time of each calibration message.
    calibration_ns: Vec<u64>,
    urdf: Vec<String>,
    /// Log time of each URDF.
    urdf_ns: Vec<u64>,
    ee_gyro: Vec<proto::AngularRate>,
    ee_mag: Vec<proto::MagneticField>,
}

impl Got {
    fn done(&self) -> bool {
        !self.joint_states.is_empty()
            && self.tf > 0
            && self.progress > 0
            && self.calibrations.iter().any(|c| !c.push.is_empty())
            && self.urdf.len() >= 2
            && !self.ee_gyro.is_empty()
            && !self.ee_mag.is_empty()
    }
}

async fn watch(port: u16, started: std::sync::mpsc::Sender<()>) -> Got {
    let mut request = format!("ws://127.0.0.1:{port}")
        .into_client_request()
        .unwrap();
    request
        .headers_mut()
        .insert("sec-websocket-protocol", "foxglove.sdk.v1".parse().unwrap());
    let (mut ws, _) = tokio_tungstenite::connect_async(request)
        .await
        .expect("connect to the live view");
    let wanted = [
        "/joint_states",
        "/tf",
        "/progress",
        "/calibration",
        "/robot_description",
        "/ee_gyro",
        "/ee_mag",
    ];
    // serverInfo, then the channels.
    let mut topics = std::collections::HashMap::new();
    while !wanted.iter().all(|t| topics.contains_key(*t)) {
        let Some(Ok(Message::Text(text))) = ws.next().await else {
            panic!("the server closed before advertising its channels");
        };
        let v: serde_json::Value = serde_json::from_str(&text).unwrap();
        if v["op"] == "advertise" {
            for ch in v["channels"].as_array().unwrap() {
                let topic = ch["topic"].as_str().unwrap().to_string();
                topics.insert(topic, ch["id"].as_u64().unwrap());
            }
        }
    }
    let subscriptions: Vec<serde_json::Value> = wanted
        .iter()
        .enumerate()
        .map(|(i, t)| serde_json::json!({"id": i, "channelId": topics[*t]}))
        .collect();
    let subscribe = serde_json::json!({"op": "subscribe", "subscriptions": subscriptions});
    ws.send(Message::text(subscribe.to_string())).await.unwrap();
    started.send(()).unwrap();
    let mut got = Got::default();
    while !got.done() {
        let next = tokio::time::timeout(Duration::from_secs(300), ws.next()).await;
        let Ok(Some(Ok(message))) = next else {
            panic!(
                "stream ended: {} joint states, {} tf, {} progress, {} calibrations, {} URDFs, \
                 {} gyro, {} mag",
                got.joint_states.len(),
                got.tf,
                got.progress,
                got.calibrations.len(),
                got.urdf.len(),
                got.ee_gyro.len(),
                got.ee_mag.len()
            );
        };
        let Message::Binary(bytes) = message else {
            continue;
        };
        // messageData: opcode 1, subscription id (u32 LE), log time (u64 LE), payload.
        assert_eq!(bytes[0], 1, "a messageData frame");
        let subscription = u32::from_le_bytes(bytes[1..5].try_into().unwrap()) as usize;
        let log_ns = u64::from_le_bytes(bytes[5..13].try_into().unwrap());
        let payload = &bytes[13..];
        got.times
            .entry(wanted[subscription])
            .or_default()
            .push(log_ns);
        match wanted[subscription] {
            "/joint_states" => got
                .joint_states
                .push(fox::JointStates::decode(payload).unwrap()),
            "/tf" => {
                let tf = fox::FrameTransforms::decode(payload).unwrap();
                assert_eq!(tf.transforms.len(), 8, "base_link → link1 … link7 → tool0");
                got.tf += 1;
            }
            "/progress" => {
                let p = proto::Progress::decode(payload).unwrap();
                assert_eq!(p.coverage.len(), 7);
                got.progress += 1;
            }
            "/calibration" => {
                got.calibrations
                    .push(proto::Calibration::decode(payload).unwrap());
                got.calibration_ns.push(log_ns);
            }
            "/ee_gyro" => {
                // The end effector's IMU stream, declared once in exocal-session's STREAMS.
                let r = proto::AngularRate::decode(payload).unwrap();
                assert_eq!(r.frame_id, "EndEffector gyro");
                got.ee_gyro.push(r);
            }
            "/ee_mag" => {
                // Another raw IMU stream: one entry of the table, its own topic and schema.
                let m = proto::MagneticField::decode(payload).unwrap();
                assert_eq!(m.frame_id, "EndEffector mag");
                // The emulated suit's field is Earth's (~50 µT), in the sensor's frame.
                let norm = (m.x * m.x + m.y * m.y + m.z * m.z).sqrt();
                assert!((20.0..80.0).contains(&norm), "{norm} µT");
                got.ee_mag.push(m);
            }
            _ => {
                // The log's schema, as every channel.
                let urdf = proto::RobotDescription::decode(payload).unwrap();
                got.urdf.push(urdf.data);
                got.urdf_ns.push(log_ns);
            }
        }
    }
    got
}

#[test]
fn a_foxglove_client_watches_the_demo_and_gets_the_calibration() {
    let dir = std::env::temp_dir().join(format!("exocald-live-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let mut config = demo_config(Config::default_config(), &dir, 1.0);
    config.live.enabled = true;
    let live = LiveView::start("127.0.0.1:0".parse().unwrap(), &config).unwrap();
    let port = live.port();
    assert_ne!(port, 0);
    let opts = DemoOptions {
        seed: 2024,
        speed: 1e6,
        output: dir.clone(),
        hold: false,
        quiet: false,
        wearer: Default::default(),
        drift: Default::default(),
    };
    let (got, demo) = std::thread::scope(|s| {
        let (started_tx, started_rx) = std::sync::mpsc::channel();
        let client = s.spawn(move || {
            tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
                .unwrap()
                .block_on(watch(port, started_tx))
        });
        // The session starts once the client listens, so it sees the collection too.
        started_rx
            .recv_timeout(Duration::from_secs(60))
            .expect("the client subscribed");
        let demo = run_with(&config, &opts, Some(&live));
        (client.join().unwrap(), demo)
    });
    let demo = demo
        .map_err(|e| e.error)
        .expect("the demo calibrates and pushes");
    let outcome = demo.summary.outcome.as_ref().unwrap();

    // Joint states of all seven joints, named as the URDF names them.
    let js = got.joint_states.last().unwrap();
    let names: Vec<&str> = js.joints.iter().map(|j| j.name.as_str()).collect();
    assert_eq!(
        names,
        ["joint1", "joint2", "joint3", "joint4", "joint5", "joint6", "joint7"]
    );
    assert!(js
        .joints
        .iter()
        .all(|j| j.position.is_some_and(f64::is_finite)));
    // The calibration result: the table the session pushed, then the push report.
    let last = got.calibrations.last().unwrap();
    let after: Vec<f64> = last.after.iter().map(|r| r.a).collect();
    let pushed: Vec<f64> = outcome.node_rows.iter().map(|r| r.a).collect();
    assert_eq!(after, pushed);
    assert_eq!(last.push.len(), 7);
    assert!(last.push.iter().all(|n| n.holds == "new"));
    // The URDF: nominal at first, the calibrated table once calibrated.
    assert!(got.urdf[0].contains("<robot name=\"exocal_suit\">"));
    assert_ne!(got.urdf[0], *got.urdf.last().unwrap());
    assert!(got.urdf.last().unwrap().contains("joint7"));
    // The calibrated URDF is stamped in session time, with its calibration record.
    let urdf_ns = *got.urdf_ns.last().unwrap();
    assert!(
        got.calibration_ns.contains(&urdf_ns),
        "URDF at {urdf_ns}, calibrations at {:?}",
        got.calibration_ns
    );
    // The streaming channels send at most [live] max_hz of log time, their timestamps never
    // stepping back (the stream gate releases a node's frames a span at a time).
    for topic in ["/joint_states", "/tf", "/ee_gyro", "/ee_mag"] {
        let t = &got.times[topic];
        let back = t.windows(2).filter(|w| w[1] < w[0]).count();
        assert_eq!(back, 0, "{topic}: {back} of {} step back", t.len());
        let min_gap = t.windows(2).map(|w| w[1] - w[0]).min().unwrap();
        let period = (1e9 / config.live.max_hz) as u64;
        assert!(
            min_gap >= period,
            "{topic}: {min_gap} ns between two messages"
        );
        assert!(t.len() > 10, "{topic}: {} messages", t.len());
    }
    drop(live);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// At most `[live] max_clients` at once (clients that never read would each hold a backlog);
/// one more gets HTTP 503, and a slot that frees is taken again.
#[test]
fn the_live_view_takes_at_most_max_clients() {
    let dir = std::env::temp_dir().join(format!("exocald-live-max-{}", std::process::id()));
    let mut config = demo_config(Config::default_config(), &dir, 1.0);
    config.live.enabled = true;
    config.live.max_clients = 2;
    let live = LiveView::start("127.0.0.1:0".parse().unwrap(), &config).unwrap();
    let port = live.port();
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(async move {
            let connect = || async move {
                let mut request = format!("ws://127.0.0.1:{port}")
                    .into_client_request()
                    .unwrap();
                request
                    .headers_mut()
                    .insert("sec-websocket-protocol", "foxglove.sdk.v1".parse().unwrap());
                tokio_tungstenite::connect_async(request).await
            };
            let first = connect().await.expect("the first client");
            let _second = connect().await.expect("the second client");
            match connect().await {
                Err(tokio_tungstenite::tungstenite::Error::Http(r)) => {
                    assert_eq!(r.status().as_u16(), 503)
                }
                other => panic!("a third client: {:?}", other.map(|_| ())),
            }
            drop(first);
            let mut admitted = false;
            for _ in 0..100 {
                tokio::time::sleep(Duration::from_millis(20)).await;
                if connect().await.is_ok() {
                    admitted = true;
                    break;
                }
            }
            assert!(admitted, "the freed slot is taken again");
        });
    drop(live);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Which WebSocket subprotocols the live view accepts (docs/suit.md, "The live view"): the Foxglove
/// SDK's `foxglove.sdk.v1` and `foxglove.sdk.v1.1`; a client offering only the older
/// `foxglove.websocket.v1` gets HTTP 400 (the SDK has no setting for it).
#[test]
fn the_live_view_speaks_the_sdks_subprotocols_and_refuses_the_old_one() {
    let dir = std::env::temp_dir().join(format!("exocald-live-proto-{}", std::process::id()));
    let mut config = demo_config(Config::default_config(), &dir, 1.0);
    config.live.enabled = true;
    let live = LiveView::start("127.0.0.1:0".parse().unwrap(), &config).unwrap();
    let port = live.port();
    let answer = |offer: &'static str| {
        tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap()
            .block_on(async move {
                let mut request = format!("ws://127.0.0.1:{port}")
                    .into_client_request()
                    .unwrap();
                request
                    .headers_mut()
                    .insert("sec-websocket-protocol", offer.parse().unwrap());
                match tokio_tungstenite::connect_async(request).await {
                    Ok((_, response)) => {
                        let chosen = response.headers()["sec-websocket-protocol"].clone();
                        Ok(chosen.to_str().unwrap().to_string())
                    }
                    Err(tokio_tungstenite::tungstenite::Error::Http(r)) => Err(r.status().as_u16()),
                    Err(e) => panic!("{offer}: {e}"),
                }
            })
    };
    assert_eq!(answer("foxglove.sdk.v1"), Ok("foxglove.sdk.v1".to_string()));
    assert_eq!(
        answer("foxglove.sdk.v1.1"),
        Ok("foxglove.sdk.v1.1".to_string())
    );
    assert_eq!(answer("foxglove.websocket.v1"), Err(400));
    drop(live);
    let _ = std::fs::remove_dir_all(&dir);
}
