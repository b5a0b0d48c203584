//! ROS 1 bags (issue 21), on bags written by an independent writer (the `rosbags` Python
//! package, `benches/make_ros1_bag.py`; the two small bags are in `tests/data`): the frames,
//! pixels, stamps, IMU samples and camera come back as written, from plain and bz2 chunks;
//! a cut bag, a bag of another format and a missing topic are clear errors naming the file.

use std::path::{Path, PathBuf};

use datasets::mcap_bag::Topics;
use datasets::{open, open_with, DatasetKind, FrameReader, OpenOptions};

const T0: i64 = 1_403_636_580_013_555_456;
const PERIOD: i64 = 50_000_000;
const W: u32 = 64;
const H: u32 = 48;

fn bag(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

fn pixel(x: u32, y: u32, k: u32) -> u8 {
    (((x * 5 + y * 3 + 7 * k) ^ (x * y)) % 256) as u8
}

/// Every frame, its stamp and pixels, the IMU samples and the camera, from both bags.
#[test]
fn a_ros1_bag_reads_back_what_was_written() {
    for name in ["small_ros1.bag", "small_ros1_bz2.bag"] {
        let ds = open(&bag(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(ds.kind, DatasetKind::Ros1Bag);
        assert!(ds.first_row_stamps, "ROS stamps are first-row times");
        assert_eq!(ds.frames.len(), 10, "{name}");
        let mut reader = FrameReader::default();
        let mut px = vec![0u8; (W * H) as usize];
        for (k, f) in ds.frames.iter().enumerate() {
            assert_eq!(f.t_ns, T0 + k as i64 * PERIOD, "{name} frame {k}");
            reader.read_gray_into(f, &mut px, W, H).expect("decodes");
            let want: Vec<u8> = (0..H)
                .flat_map(|y| (0..W).map(move |x| pixel(x, y, k as u32)))
                .collect();
            assert!(px == want, "{name}: frame {k}'s pixels");
        }
        assert_eq!(ds.imu.len(), 104, "{name}");
        let s = ds.imu[3];
        assert_eq!(s.t_ns, T0 - 20_000_000 + 3 * 5_000_000);
        assert_eq!(s.gyro, [0.03, 0.2, -0.3]);
        assert_eq!(s.accel, [0.1, 9.81, 0.003]);
        let m = &ds.camera.model;
        assert_eq!((m.width, m.height), (W, H));
        assert_eq!((m.fx, m.fy, m.cx, m.cy), (50.0, 51.0, 32.0, 24.0));
        assert_eq!((m.k1, m.k2, m.p1, m.p2), (-0.1, 0.01, 0.001, -0.002));
        assert!(ds.issues.is_empty(), "{name}: {:?}", ds.issues);
    }
}

/// A bag cut in the middle (its index lost), a file that only looks like one and a topic
/// the bag lacks: errors naming the file and what is wrong.
#[test]
fn bad_ros1_bags_are_clear_errors() {
    let dir = tempfile::tempdir().expect("tempdir");
    let bytes = std::fs::read(bag("small_ros1.bag")).expect("bag");
    let cut = dir.path().join("cut.bag");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).expect("write");
    let e = open(&cut).expect_err("a cut bag").to_string();
    assert!(e.contains("cut.bag"), "{e}");
    let fake = dir.path().join("fake.bag");
    std::fs::write(&fake, b"#ROSBAG V2.0\nnot really").expect("write");
    let e = open(&fake).expect_err("not a bag").to_string();
    assert!(e.contains("fake.bag") && e.contains("ROS 1 bag"), "{e}");
    let options = OpenOptions {
        topics: Topics {
            image: Some("/cam1/image_raw".into()),
            imu: None,
        },
        ..OpenOptions::default()
    };
    let e = open_with(&bag("small_ros1.bag"), &options)
        .expect_err("missing")
        .to_string();
    assert!(e.contains("no topic /cam1/image_raw"), "{e}");
    assert!(e.contains("/cam0/image_raw (sensor_msgs/Image)"), "{e}");
}

/// One flipped byte anywhere in the bag (every 97th byte, plain and bz2 chunks): opening
/// and reading every frame either works or is an error, never a panic; a frame read comes
/// out of the right size.
#[test]
fn a_damaged_ros1_bag_never_panics() {
    let dir = tempfile::tempdir().expect("tempdir");
    for name in ["small_ros1.bag", "small_ros1_bz2.bag"] {
        let bytes = std::fs::read(bag(name)).expect("bag");
        let (mut opened, mut refused) = (0, 0);
        for at in (13..bytes.len()).step_by(97) {
            let mut damaged = bytes.clone();
            damaged[at] ^= 0x5a;
            let path = dir.path().join(format!("flip_{at}.bag"));
            std::fs::write(&path, &damaged).expect("write");
            let Ok(ds) = open(&path) else {
                refused += 1;
                continue;
            };
            opened += 1;
            let (w, h) = (ds.camera.model.width, ds.camera.model.height);
            let mut px = vec![0u8; (w * h) as usize];
            let mut reader = FrameReader::default();
            for f in &ds.frames {
                let _ = reader.read_gray_into(f, &mut px, w, h);
            }
        }
        eprintln!("{name}: {opened} damaged copies opened, {refused} refused");
        assert!(
            opened > 0 && refused > 0,
            "{name}: {opened} opened, {refused} refused"
        );
    }
}
