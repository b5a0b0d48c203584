//! What a viewer gets of a run (issue 21), in Foxglove's schemas: in the recording
//! (`--record`, beside its ROS 2 topics) and live over Foxglove's WebSocket protocol
//! (`--viz`), each decoded here independently of the writer (the `mcap` crate's reader,
//! `foxglove::Decode`, a plain WebSocket client) and checked against the run's own outputs.
mod common;

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use common::*;
use foxglove::messages as fg;
use foxglove::Decode;

/// Every message of `file`: topic → [(log time, schema name, data)].
fn messages(file: &Path) -> BTreeMap<String, Vec<(u64, String, Vec<u8>)>> {
    let bytes = std::fs::read(file).expect("recording");
    let mut out: BTreeMap<String, Vec<_>> = BTreeMap::new();
    for m in mcap::MessageStream::new(&bytes).expect("an MCAP file") {
        let m = m.expect("a readable message");
        let schema = m.channel.schema.as_ref().map_or("", |s| s.name.as_str());
        let entry = (m.log_time, schema.to_string(), m.data.to_vec());
        out.entry(m.channel.topic.clone()).or_default().push(entry);
    }
    out
}

/// The rows `t x y z` of a TUM trajectory file.
fn trajectory(file: &Path) -> Vec<[f64; 4]> {
    let text = std::fs::read_to_string(file).expect("trajectory");
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let v: Vec<f64> = l.split_whitespace().map(|x| x.parse().unwrap()).collect();
            [v[0], v[1], v[2], v[3]]
        })
        .collect()
}

/// Two cameras of the `two-agents` scene, recorded: client 0's file holds its camera
/// transforms, its whole path (equal to `trajectory_c0.txt`), its keyframes, the tracked
/// features on each image, and at the end the server map's points and the merge as a line
/// between the two keyframes the loop closer matched, at their final places in the saved
/// map.
#[test]
fn a_recording_holds_the_run_in_foxglove_schemas() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "two-agents", 480, None);
    let (out, rec) = (dir.path().join("out"), dir.path().join("run.mcap"));
    let record = ["--lockstep", "--record", rec.to_str().unwrap()];
    let res = run_pipeline(&[&ds[0], &ds[1]], &out, "foxglove_record", &record);
    assert!(res.status.success());
    let r = report(&out);
    let r0 = &r["record"][0];
    assert!(r0["error"].is_null(), "{r0}");
    let msgs = messages(&dir.path().join("run_c0.mcap"));
    let fox = |topic: &str, schema: &str| {
        let m = msgs.get(topic).unwrap_or_else(|| panic!("no {topic}"));
        assert!(m.iter().all(|(_, s, _)| s == schema), "{topic}: {schema}");
        m
    };

    // The camera transforms and the path: every tracked frame, as trajectory_c0.txt has it.
    let tfs = fox("/shoal/transforms", "foxglove.FrameTransforms");
    let cams: Vec<fg::FrameTransform> = (tfs.iter())
        .flat_map(|(_, _, d)| fg::FrameTransforms::decode(&d[..]).unwrap().transforms)
        .filter(|t| t.parent_frame_id == "map" && t.child_frame_id == "cam0")
        .collect();
    let rows = trajectory(&out.join("trajectory_c0.txt"));
    assert_eq!(cams.len() as u64, r0["poses"].as_u64().unwrap());
    let paths = fox("/shoal/trajectory", "foxglove.PosesInFrame");
    let path = fg::PosesInFrame::decode(&paths.last().unwrap().2[..]).unwrap();
    assert_eq!(path.frame_id, "map");
    assert_eq!((path.poses.len(), rows.len()), (cams.len(), cams.len()));
    for ((t, p), row) in cams.iter().zip(&path.poses).zip(&rows) {
        let (a, b) = (t.translation.unwrap(), p.position.unwrap());
        assert_eq!((a.x, a.y, a.z), (b.x, b.y, b.z));
        let ts = t.timestamp.unwrap();
        let secs = f64::from(ts.sec()) + f64::from(ts.nsec()) * 1e-9;
        assert!((secs - row[0]).abs() < 1e-6, "{secs} vs {}", row[0]);
        let d = [a.x - row[1], a.y - row[2], a.z - row[3]];
        assert!(d.iter().all(|d| d.abs() < 1e-8), "{d:?}");
    }
    let kfs = fox("/shoal/keyframes", "foxglove.PosesInFrame");
    let last = fg::PosesInFrame::decode(&kfs.last().unwrap().2[..]).unwrap();
    assert_eq!(last.poses.len() as u64, r0["keyframes"].as_u64().unwrap());

    // The features: drawn on images of the same stamps, inside them, tens per frame.
    let images: HashMap<u64, ()> = msgs["/cam0/image_raw"].iter().map(|m| (m.0, ())).collect();
    let feats = fox("/cam0/features", "foxglove.ImageAnnotations");
    assert!(
        feats.len() as f64 >= 0.9 * cams.len() as f64,
        "{}",
        feats.len()
    );
    let mut n = 0;
    for (t, _, d) in feats {
        assert!(images.contains_key(t), "features at {t} without an image");
        let a = fg::ImageAnnotations::decode(&d[..]).unwrap();
        let p = &a.points[0];
        assert_eq!(p.timestamp.unwrap().total_nanos(), *t);
        assert!(p
            .points
            .iter()
            .all(|q| (0.0..=752.0).contains(&q.x) && (0.0..=480.0).contains(&q.y)));
        n += p.points.len();
    }
    assert_eq!(r0["feature_frames"].as_u64().unwrap(), feats.len() as u64);
    assert!(n as f64 / feats.len() as f64 > 50.0, "{n} features");

    // The map at the end, and the merge between its keyframes' final centres.
    let cloud = fox("/shoal/map_points", "foxglove.PointCloud");
    let cloud = fg::PointCloud::decode(&cloud[0].2[..]).unwrap();
    assert_eq!(cloud.point_stride, 12);
    assert_eq!(
        (cloud.data.len() / 12) as u64,
        r0["map_points"].as_u64().unwrap()
    );
    assert!(
        r["merges"].as_u64().unwrap() >= 1,
        "no merge: nothing to draw"
    );
    let scene = fox("/shoal/loops", "foxglove.SceneUpdate");
    let scene = fg::SceneUpdate::decode(&scene[0].2[..]).unwrap();
    let line = &scene.entities[0].lines[0];
    assert!(!line.points.is_empty() && line.points.len() % 2 == 0);
    assert_eq!(
        line.points.len() as u64,
        2 * r0["corrections"].as_u64().unwrap()
    );
    let (_, file) = map_store::read(&out.join("record_map.shoalmap")).expect("saved map");
    let centres: Vec<_> = (file.maps.iter())
        .flat_map(|m| m.map.map.keyframes.values())
        .map(|k| k.center())
        .collect();
    for p in &line.points {
        let near = centres
            .iter()
            .any(|c| (c - nalgebra::Vector3::new(p.x, p.y, p.z)).norm() < 1e-9);
        assert!(near, "a loop end at no keyframe: {p:?}");
    }
}

/// A viewer that connects over Foxglove's WebSocket protocol (`foxglove.sdk.v1`) before
/// the run starts (`--viz-wait`) and subscribes to the camera transforms, the features and
/// the image receives them as the run goes: the transforms equal the run's trajectory.
#[test]
fn a_viewer_connected_over_websocket_gets_the_run_live() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "loop", 120, None);
    let out = dir.path().join("out");
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let addr = format!("127.0.0.1:{port}");
    let viewer = std::thread::spawn(move || watch(port));
    let extra = ["--lockstep", "--viz", &addr, "--viz-wait", "60"];
    let res = run_pipeline(&[&ds[0]], &out, "foxglove_live", &extra);
    assert!(res.status.success());
    let got = viewer.join().expect("viewer");
    let rows = trajectory(&out.join("trajectory_c0.txt"));
    let cams: Vec<fg::FrameTransform> = (got["/shoal/transforms"].iter())
        .flat_map(|d| fg::FrameTransforms::decode(&d[..]).unwrap().transforms)
        .filter(|t| t.parent_frame_id == "map" && t.child_frame_id == "cam0")
        .collect();
    assert!(
        cams.len() as f64 >= 0.95 * rows.len() as f64,
        "{} of {}",
        cams.len(),
        rows.len()
    );
    let by_t: HashMap<i64, [f64; 3]> = rows
        .iter()
        .map(|r| ((r[0] * 1e9).round() as i64, [r[1], r[2], r[3]]))
        .collect();
    for t in &cams {
        let ts = t.timestamp.unwrap().total_nanos() as i64;
        let row = by_t.get(&ts).unwrap_or_else(|| panic!("no frame at {ts}"));
        let p = t.translation.unwrap();
        let d = [p.x - row[0], p.y - row[1], p.z - row[2]];
        assert!(d.iter().all(|d| d.abs() < 1e-8), "{d:?} at {ts}");
    }
    let images = &got["/cam0/image"];
    assert!(
        images.len() as f64 >= 0.9 * rows.len() as f64,
        "{} images",
        images.len()
    );
    let img = fg::RawImage::decode(&images[0][..]).unwrap();
    assert_eq!(
        (img.width, img.height, img.encoding.as_str()),
        (752, 480, "mono8")
    );
    assert_eq!(img.data.len(), 752 * 480);
    assert!(got["/cam0/features"].len() as f64 >= 0.9 * rows.len() as f64);
}

/// Connects to `port` (retrying while the run starts), subscribes to three topics and
/// collects their messages until the server closes: topic → message data.
fn watch(port: u16) -> HashMap<String, Vec<Vec<u8>>> {
    use tungstenite::client::IntoClientRequest;
    let mut req = format!("ws://127.0.0.1:{port}")
        .into_client_request()
        .unwrap();
    req.headers_mut()
        .insert("Sec-WebSocket-Protocol", "foxglove.sdk.v1".parse().unwrap());
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    let mut ws = loop {
        match tungstenite::connect(req.clone()) {
            Ok((ws, _)) => break ws,
            Err(_) if std::time::Instant::now() < deadline => {
                std::thread::sleep(std::time::Duration::from_millis(50))
            }
            Err(e) => panic!("cannot connect: {e}"),
        }
    };
    let wanted = ["/shoal/transforms", "/cam0/features", "/cam0/image"];
    let mut subs: HashMap<u32, String> = HashMap::new();
    let mut got: HashMap<String, Vec<Vec<u8>>> = HashMap::new();
    for t in wanted {
        got.insert(t.to_string(), vec![]);
    }
    loop {
        let msg = match ws.read() {
            Ok(m) => m,
            Err(_) => return got,
        };
        match msg {
            tungstenite::Message::Text(t) => {
                let v: serde_json::Value = serde_json::from_str(&t).unwrap();
                if v["op"] != "advertise" {
                    continue;
                }
                let mut list = vec![];
                for ch in v["channels"].as_array().unwrap() {
                    let topic = ch["topic"].as_str().unwrap();
                    if wanted.contains(&topic) {
                        let id = subs.len() as u32 + 1;
                        subs.insert(id, topic.to_string());
                        list.push(serde_json::json!({"id": id, "channelId": ch["id"]}));
                    }
                }
                let sub = serde_json::json!({"op": "subscribe", "subscriptions": list});
                ws.send(tungstenite::Message::Text(sub.to_string().into()))
                    .unwrap();
            }
            tungstenite::Message::Binary(b) if b.first() == Some(&1) => {
                let id = u32::from_le_bytes(b[1..5].try_into().unwrap());
                if let Some(topic) = subs.get(&id) {
                    got.get_mut(topic).unwrap().push(b[13..].to_vec());
                }
            }
            tungstenite::Message::Close(_) => return got,
            _ => {}
        }
    }
}
