//! MCAP / ROS 2 bag reading and `convert --to mcap` writing (issue 21), on files written by
//! the `mcap` crate's writer: a synthetic EuRoC-layout sequence converted and read back
//! (same frames, pixels, IMU samples, times and calibration, bit for bit), a ROS 2 bag with
//! first-row stamps, and damaged bags (missing topic, unknown encoding, non-increasing
//! stamps, a cut file, a damaged chunk): a clear error, or the rest of the file used.

mod common;

use std::collections::BTreeMap;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use datasets::mcap_bag::msgs::{self, names, Bytes, Header, Time};
use datasets::mcap_bag::write::{write_dataset, Compression, WriteSettings};
use datasets::mcap_bag::Topics;
use datasets::{open, open_with, Dataset, DatasetKind, FrameReader, IssueKind, OpenOptions};

/// A small synthetic sequence (EuRoC layout, rolling shutter, IMU, ground truth).
fn synthetic(dir: &Path, frames: usize) -> PathBuf {
    let mut p = datasets::sim::SimParams::new("loop".parse().expect("scenario"));
    p.frames = Some(frames);
    p.readout_ms = Some(12.0);
    p.seed = 5;
    let s = datasets::sim::generate(&p, dir).expect("generate");
    s.agents[0].dir.clone()
}

fn imu_yaml(ds: &Dataset) -> datasets::euroc::ImuSensorCalib {
    datasets::euroc::read_imu_sensor_yaml(&ds.root.join("mav0/imu0/sensor.yaml")).expect("yaml")
}

/// Every frame's pixels.
fn pixels(ds: &Dataset) -> Vec<Vec<u8>> {
    let (w, h) = (ds.camera.model.width, ds.camera.model.height);
    let mut reader = FrameReader::default();
    ds.frames
        .iter()
        .map(|f| {
            let mut buf = vec![0u8; (w * h) as usize];
            reader.read_gray_into(f, &mut buf, w, h).expect("frame");
            buf
        })
        .collect()
}

/// What a replay uses of a dataset is the same in both.
fn assert_same_replay(a: &Dataset, b: &Dataset) {
    assert_eq!(a.camera, b.camera);
    assert_eq!(a.frames.len(), b.frames.len());
    for (x, y) in a.frames.iter().zip(&b.frames) {
        assert_eq!((x.t_ns, x.readout_ns), (y.t_ns, y.readout_ns));
    }
    assert_eq!(a.imu, b.imu);
    assert_eq!(a.ground_truth, b.ground_truth);
    assert_eq!(pixels(a), pixels(b));
}

#[test]
fn synthetic_round_trip_is_exact() {
    let dir = tempfile::tempdir().unwrap();
    let src = synthetic(&dir.path().join("sim"), 24);
    let ds = open(&src).expect("open folder");
    let yaml = imu_yaml(&ds);
    for compression in [Compression::Zstd, Compression::Lz4, Compression::None] {
        let out = dir.path().join(format!("sim_{compression:?}.mcap"));
        let settings = WriteSettings {
            compression,
            chunk_bytes: Some(300_000),
        };
        let s = write_dataset(&ds, Some(&yaml), &out, &settings).expect("write");
        assert_eq!((s.frames, s.imu_samples), (ds.frames.len(), ds.imu.len()));
        assert!(s.skipped_frames.is_empty());
        let back = open(&out).expect("open mcap");
        assert_eq!(back.kind, DatasetKind::Mcap);
        assert!(back.issues.is_empty(), "{:?}", back.issues);
        assert!(
            !back.first_row_stamps,
            "shoal's own stamps are middle-row times"
        );
        assert_eq!(back.imu_calib, Some(yaml));
        assert!(back.camera.readout_ns > 0 && back.camera.t_bs_given);
        assert_same_replay(&ds, &back);
        assert!(matches!(
            back.frames[0].source,
            datasets::FrameSource::Mcap(_)
        ));
    }
    // Converting the MCAP again gives the same dataset (no second time conversion).
    let first = dir.path().join("sim_Zstd.mcap");
    let again = dir.path().join("again.mcap");
    let ds1 = open(&first).unwrap();
    write_dataset(
        &ds1,
        ds1.imu_calib.as_ref(),
        &again,
        &WriteSettings::default(),
    )
    .unwrap();
    assert_same_replay(&ds, &open(&again).unwrap());
}

/// A calibration file over a shoal MCAP moves the frames by the t_d difference only (its
/// stamps are middle-row times), as over the folder.
#[test]
fn calibration_over_shoal_mcap_matches_folder() {
    let dir = tempfile::tempdir().unwrap();
    let src = synthetic(&dir.path().join("sim"), 6);
    let ds = open(&src).unwrap();
    let out = dir.path().join("sim.mcap");
    write_dataset(&ds, Some(&imu_yaml(&ds)), &out, &WriteSettings::default()).unwrap();
    let mut cal = datasets::calibration::CalibrationFile::from_dataset(&ds.camera, None);
    cal.camera.time_offset_ns += 4e6;
    cal.camera.readout_ns = 20e6;
    let file = dir.path().join("cal.toml");
    cal.write(&file).unwrap();
    let opts = OpenOptions {
        calib: Some(file),
        ..OpenOptions::default()
    };
    let (a, b) = (
        open_with(&src, &opts).unwrap(),
        open_with(&out, &opts).unwrap(),
    );
    let ta: Vec<i64> = a.frames.iter().map(|f| f.t_ns).collect();
    let tb: Vec<i64> = b.frames.iter().map(|f| f.t_ns).collect();
    assert_eq!(ta, tb);
    assert_eq!(tb[0], ds.frames[0].t_ns + 4_000_000);
}

// ---- A ROS 2 bag written with the mcap crate: first-row stamps, CameraInfo, IMU ----

/// Writes a bag: channels by (topic, schema), messages `(channel, stamp, bytes)`.
struct Bag {
    w: mcap::Writer<BufWriter<std::fs::File>>,
    ids: BTreeMap<String, u16>,
    seq: u32,
}

impl Bag {
    fn new(path: &Path, compression: Option<mcap::Compression>, chunk: u64) -> Self {
        Self::with_options(
            path,
            mcap::WriteOptions::new()
                .compression(compression)
                .chunk_size(Some(chunk)),
        )
    }

    /// Messages as top-level records, no chunks (as a recorder that streams writes).
    fn unchunked(path: &Path) -> Self {
        Self::with_options(path, mcap::WriteOptions::new().use_chunks(false))
    }

    fn with_options(path: &Path, options: mcap::WriteOptions) -> Self {
        let f = BufWriter::new(std::fs::File::create(path).unwrap());
        let w = options.profile("ros2").create(f).unwrap();
        Self {
            w,
            ids: BTreeMap::new(),
            seq: 0,
        }
    }

    fn channel(&mut self, topic: &str, schema: &str, encoding: &str) {
        let sid = self
            .w
            .add_schema(schema, "ros2msg", b"(definition)")
            .unwrap();
        let id = self
            .w
            .add_channel(sid, topic, encoding, &BTreeMap::new())
            .unwrap();
        self.ids.insert(topic.into(), id);
    }

    fn put(&mut self, topic: &str, t_ns: i64, data: &[u8]) {
        self.seq += 1;
        let header = mcap::records::MessageHeader {
            channel_id: self.ids[topic],
            sequence: self.seq,
            // A recorder's receive time, after the stamp.
            log_time: (t_ns + 2_000_000) as u64,
            publish_time: (t_ns + 2_000_000) as u64,
        };
        self.w.write_to_known_channel(&header, data).unwrap();
    }

    fn finish(mut self) {
        self.w.finish().unwrap();
    }
}

const W: u32 = 16;
const H: u32 = 8;
const T0: i64 = 1_700_000_000_000_000_000;
const PERIOD: i64 = 50_000_000;

fn stamp(t_ns: i64) -> Time {
    Time::from_ns(t_ns).unwrap()
}

/// RGB pixels of frame `k`.
fn rgb(k: usize) -> Vec<u8> {
    (0..W * H)
        .flat_map(|i| {
            let (x, y) = ((i % W) as usize, (i / W) as usize);
            [
                ((x * 13 + k * 7) % 256) as u8,
                ((y * 29 + k) % 256) as u8,
                ((x * y + 3 * k) % 256) as u8,
            ]
        })
        .collect()
}

fn image_msg(k: usize, t_ns: i64, encoding: &str, data: &[u8], step: u32) -> Vec<u8> {
    msgs::encode(
        &msgs::Image {
            header: Header {
                stamp: stamp(t_ns),
                frame_id: "camera".into(),
            },
            height: H,
            width: W,
            encoding: encoding.into(),
            is_bigendian: 0,
            step,
            data: Bytes(data),
        },
        data.len() + 100,
    )
    .unwrap_or_else(|e| panic!("frame {k}: {e}"))
}

fn camera_info_msg(t_ns: i64, width: u32) -> Vec<u8> {
    msgs::encode(
        &msgs::CameraInfo {
            header: Header {
                stamp: stamp(t_ns),
                frame_id: "camera".into(),
            },
            height: H,
            width,
            distortion_model: "plumb_bob".into(),
            d: vec![-0.1, 0.01, 0.001, -0.002, 0.0],
            k: [20.0, 0.0, 8.0, 0.0, 21.0, 4.0, 0.0, 0.0, 1.0],
            r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            p: [0.0; 12],
            binning_x: 0,
            binning_y: 0,
            roi: msgs::RegionOfInterest::default(),
        },
        400,
    )
    .unwrap()
}

fn imu_msg(t_ns: i64, i: usize) -> Vec<u8> {
    let v = |a: f64| msgs::Vector3 {
        x: a,
        y: -a,
        z: 9.81,
    };
    msgs::encode(
        &msgs::Imu {
            header: Header {
                stamp: stamp(t_ns),
                frame_id: "imu".into(),
            },
            orientation: msgs::Quaternion::default(),
            orientation_covariance: [-1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            angular_velocity: v(i as f64 * 0.01),
            angular_velocity_covariance: [0.0; 9],
            linear_acceleration: v(i as f64 * 0.1),
            linear_acceleration_covariance: [0.0; 9],
        },
        400,
    )
    .unwrap()
}

/// What to put into a ROS 2 bag of `frames` frames, 4 IMU samples per frame period.
#[derive(Default)]
struct Spec {
    /// Pixel encoding of frame k, else rgb8.
    encoding: BTreeMap<usize, &'static str>,
    /// Stamp of frame k instead of its nominal one.
    stamp: BTreeMap<usize, i64>,
    /// No CameraInfo.
    no_info: bool,
}

fn frame_stamp(spec: &Spec, k: usize) -> i64 {
    spec.stamp
        .get(&k)
        .copied()
        .unwrap_or(T0 + k as i64 * PERIOD)
}

fn ros2_bag(path: &Path, frames: usize, spec: &Spec) {
    let mut bag = Bag::new(path, Some(mcap::Compression::Lz4), 2_000);
    bag.channel("/cam/image_raw", names::IMAGE, "cdr");
    bag.channel("/cam/camera_info", names::CAMERA_INFO, "cdr");
    bag.channel("/imu/data", names::IMU, "cdr");
    bag.channel("/rosout", "rcl_interfaces/msg/Log", "cdr");
    if !spec.no_info {
        bag.put("/cam/camera_info", T0, &camera_info_msg(T0, W));
    }
    for k in 0..frames {
        for j in 0..4 {
            let t = T0 + k as i64 * PERIOD + j * PERIOD / 4;
            bag.put("/imu/data", t, &imu_msg(t, 4 * k + j as usize));
        }
        let enc = spec.encoding.get(&k).copied().unwrap_or("rgb8");
        let mut px = rgb(k);
        if enc == "bgr8" {
            px.chunks_exact_mut(3).for_each(|p| p.swap(0, 2));
        }
        let t = frame_stamp(spec, k);
        bag.put("/cam/image_raw", t, &image_msg(k, t, enc, &px, W * 3));
        bag.put("/rosout", t, b"\x00\x01\x00\x00not a log message");
    }
    bag.finish();
}

/// Gray of frame `k` as the `image` crate computes it from RGB.
fn luma(k: usize) -> Vec<u8> {
    let img = image::RgbImage::from_raw(W, H, rgb(k)).unwrap();
    image::DynamicImage::ImageRgb8(img).into_luma8().into_raw()
}

#[test]
fn ros2_bag_with_first_row_stamps() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bag.mcap");
    let spec = Spec {
        encoding: [(3, "bgr8")].into(),
        ..Spec::default()
    };
    ros2_bag(&path, 10, &spec);
    let ds = open(&path).expect("open bag");
    assert_eq!(ds.kind, DatasetKind::Mcap);
    assert!(ds.issues.is_empty(), "{:?}", ds.issues);
    assert!(ds.first_row_stamps);
    assert_eq!(ds.frames.len(), 10);
    assert_eq!(ds.imu.len(), 40);
    assert_eq!(ds.imu[5].gyro, [0.05, -0.05, 9.81]);
    assert_eq!(ds.imu[5].t_ns, T0 + PERIOD + PERIOD / 4);
    // Without a calibration file t_r = t_d = 0: the frame time is the header stamp.
    assert_eq!(ds.frames[2].t_ns, T0 + 2 * PERIOD);
    let m = &ds.camera.model;
    assert_eq!(
        (m.width, m.height, m.fx, m.fy, m.cx, m.cy),
        (W, H, 20.0, 21.0, 8.0, 4.0)
    );
    assert_eq!((m.k1, m.k2, m.p1, m.p2), (-0.1, 0.01, 0.001, -0.002));
    assert!(!ds.camera.t_bs_given);
    assert!((ds.camera.rate_hz - 20.0).abs() < 1e-9);
    let px = pixels(&ds);
    for (k, p) in px.iter().enumerate() {
        assert_eq!(p, &luma(k), "frame {k}");
    }
    // A calibration file: middle-row time = stamp + t_r/2 + t_d.
    let mut cal = datasets::calibration::CalibrationFile::from_dataset(&ds.camera, None);
    cal.camera.readout_ns = 10e6;
    cal.camera.time_offset_ns = 3e6;
    let file = dir.path().join("cal.toml");
    cal.write(&file).unwrap();
    let opts = OpenOptions {
        calib: Some(file),
        ..OpenOptions::default()
    };
    let cds = open_with(&path, &opts).unwrap();
    assert_eq!(cds.frames[2].t_ns, T0 + 2 * PERIOD + 5_000_000 + 3_000_000);
    assert_eq!(cds.frames[2].readout_ns, 10_000_000);
    assert_eq!(cds.imu, ds.imu, "IMU stamps are sample times: unchanged");
    // Converted, it becomes a shoal file with middle-row times.
    let out = dir.path().join("converted.mcap");
    write_dataset(&cds, None, &out, &WriteSettings::default()).unwrap();
    let conv = open(&out).unwrap();
    assert!(!conv.first_row_stamps);
    assert_eq!(conv.frames[2].t_ns, cds.frames[2].t_ns);
    assert_eq!(pixels(&conv), px);
    // The same bag as a rosbag2 folder.
    let bag_dir = dir.path().join("rosbag2");
    std::fs::create_dir(&bag_dir).unwrap();
    std::fs::rename(&path, bag_dir.join("rosbag2_0.mcap")).unwrap();
    std::fs::write(
        bag_dir.join("metadata.yaml"),
        "rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: mcap\n  \
         relative_file_paths:\n    - rosbag2_0.mcap\n  duration:\n    nanoseconds: 1\n",
    )
    .unwrap();
    let folder = open(&bag_dir).expect("open rosbag2 folder");
    assert_eq!(folder.frames.len(), 10);
    assert_eq!(pixels(&folder), px);
}

#[test]
fn compressed_and_foxglove_images_and_topic_choice() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bag.mcap");
    let mut bag = Bag::new(&path, Some(mcap::Compression::Zstd), 1 << 20);
    bag.channel("/a/compressed", names::COMPRESSED_IMAGE, "cdr");
    bag.channel("/b/raw", names::FOXGLOVE_RAW_IMAGE, "cdr");
    bag.channel("/c/proto", names::IMAGE, "protobuf");
    for k in 0..3 {
        let t = T0 + k as i64 * PERIOD;
        let mut png = Vec::new();
        image::RgbImage::from_raw(W, H, rgb(k))
            .unwrap()
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .unwrap();
        let c = msgs::CompressedImage {
            header: Header {
                stamp: stamp(t),
                frame_id: "a".into(),
            },
            format: "png".into(),
            data: Bytes(&png),
        };
        bag.put("/a/compressed", t, &msgs::encode(&c, 100).unwrap());
        let gray = luma(k);
        let f = msgs::FoxgloveRawImage {
            timestamp: stamp(t + 1),
            frame_id: "b".into(),
            width: W,
            height: H,
            encoding: "mono8".into(),
            step: W,
            data: Bytes(&gray),
        };
        bag.put("/b/raw", t, &msgs::encode(&f, 100).unwrap());
    }
    bag.finish();
    let calib = dir.path().join("cal.toml");
    let mut cal = datasets::calibration::CalibrationFile::from_dataset(
        &datasets::CameraCalib {
            model: datasets::PinholeRadtan::from_coefficients(
                W,
                H,
                [20.0, 20.0, 8.0, 4.0],
                [0.0; 5],
            ),
            t_bs: nalgebra::Isometry3::identity(),
            t_bs_given: true,
            readout_ns: 0,
            time_offset_ns: 0,
            rate_hz: 20.0,
        },
        None,
    );
    cal.camera.rate_hz = 20.0;
    cal.write(&calib).unwrap();
    let topic = |t: Option<&str>| OpenOptions {
        calib: Some(calib.clone()),
        topics: Topics {
            image: t.map(String::from),
            imu: None,
        },
        ..OpenOptions::default()
    };
    // Found by type: the raw topic before the compressed one.
    let auto = open_with(&path, &topic(None)).unwrap();
    assert_eq!(auto.frames[0].t_ns, T0 + 1);
    assert!(auto.issues.iter().any(|i| i.kind == IssueKind::MissingFile));
    let png = open_with(&path, &topic(Some("/a/compressed"))).unwrap();
    assert_eq!(png.frames[0].t_ns, T0);
    assert_eq!(pixels(&png), pixels(&auto));
    assert_eq!(pixels(&png)[2], luma(2));
    // The same messages unchunked (top-level message records) read the same.
    let flat = dir.path().join("flat.mcap");
    let mut bag = Bag::unchunked(&flat);
    bag.channel("/b/raw", names::FOXGLOVE_RAW_IMAGE, "cdr");
    for (k, f) in auto.frames.iter().enumerate() {
        let gray = luma(k);
        let m = msgs::FoxgloveRawImage {
            timestamp: stamp(f.t_ns),
            frame_id: "b".into(),
            width: W,
            height: H,
            encoding: "mono8".into(),
            step: W,
            data: Bytes(&gray),
        };
        bag.put("/b/raw", f.t_ns, &msgs::encode(&m, 100).unwrap());
    }
    bag.finish();
    let flat_ds = open_with(&flat, &topic(None)).unwrap();
    assert!(matches!(
        flat_ds.frames[1].source,
        datasets::FrameSource::Mcap(datasets::mcap_bag::McapFrameRef { in_chunk: None, .. })
    ));
    assert_eq!(pixels(&flat_ds), pixels(&auto));
    let e = open_with(&path, &topic(Some("/c/proto")))
        .unwrap_err()
        .to_string();
    assert!(e.contains("encoded as protobuf"), "{e}");
    // No CameraInfo and no calibration file: the error says what to give.
    let e = open(&path).unwrap_err().to_string();
    assert!(e.contains("bag.mcap") && e.contains("--calib"), "{e}");
}

// ---- Bad input ----

#[test]
fn missing_topics_are_errors_naming_the_file_and_topics() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bag.mcap");
    ros2_bag(&path, 3, &Spec::default());
    let asked = |image: Option<&str>, imu: Option<&str>| {
        open_with(
            &path,
            &OpenOptions {
                calib: None,
                topics: Topics {
                    image: image.map(String::from),
                    imu: imu.map(String::from),
                },
                ..OpenOptions::default()
            },
        )
    };
    let e = asked(Some("/nope"), None).unwrap_err().to_string();
    assert!(
        e.contains("bag.mcap") && e.contains("no topic /nope") && e.contains("/cam/image_raw"),
        "{e}"
    );
    let e = asked(None, Some("/imu/other")).unwrap_err().to_string();
    assert!(e.contains("no IMU topic /imu/other"), "{e}");
    let e = asked(Some("/imu/data"), None).unwrap_err().to_string();
    assert!(e.contains("sensor_msgs/msg/Imu"), "{e}");
    // A bag without images at all.
    let imu_only = dir.path().join("imu.mcap");
    let mut bag = Bag::new(&imu_only, None, 1 << 20);
    bag.channel("/imu/data", names::IMU, "cdr");
    bag.put("/imu/data", T0, &imu_msg(T0, 0));
    bag.finish();
    let e = open(&imu_only).unwrap_err().to_string();
    assert!(
        e.contains("no image topic") && e.contains("/imu/data"),
        "{e}"
    );
    // Not an MCAP file.
    let junk = dir.path().join("junk.mcap");
    std::fs::write(&junk, b"not an mcap file at all").unwrap();
    let e = open(&junk).unwrap_err().to_string();
    assert!(e.contains("junk.mcap"), "{e}");
}

#[test]
fn unknown_encodings_and_non_increasing_stamps_are_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bag.mcap");
    let spec = Spec {
        encoding: [(2, "bayer_rggb8"), (5, "16UC1")].into(),
        stamp: [(7, T0 + 6 * PERIOD - 1)].into(),
        ..Spec::default()
    };
    ros2_bag(&path, 10, &spec);
    let ds = open(&path).expect("the rest of the bag is used");
    assert_eq!(ds.frames.len(), 7);
    let kinds: Vec<_> = ds.issues.iter().map(|i| i.kind).collect();
    assert_eq!(
        kinds,
        [
            IssueKind::BadMessage,
            IssueKind::BadMessage,
            IssueKind::NonMonotonic
        ]
    );
    let d = &ds.issues[0].detail;
    assert!(
        d.contains("/cam/image_raw") && d.contains("message 3") && d.contains("bayer_rggb8"),
        "{d}"
    );
    assert!(
        ds.issues[2].detail.contains("not after"),
        "{}",
        ds.issues[2].detail
    );
    let kept: Vec<usize> = ds
        .frames
        .iter()
        .map(|f| ((f.t_ns - T0) / PERIOD) as usize)
        .collect();
    assert_eq!(kept, [0, 1, 3, 4, 6, 8, 9]);
    assert_eq!(pixels(&ds)[2], luma(3));
    // Every frame in an unknown encoding: an error naming the topic and the encoding.
    let all_bad = dir.path().join("bad.mcap");
    let spec = Spec {
        encoding: (0..3).map(|k| (k, "yuv422")).collect(),
        ..Spec::default()
    };
    ros2_bag(&all_bad, 3, &spec);
    let e = open(&all_bad).unwrap_err().to_string();
    assert!(
        e.contains("no usable image on topic /cam/image_raw") && e.contains("yuv422"),
        "{e}"
    );
}

#[test]
fn cut_file_keeps_what_comes_before_the_cut() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bag.mcap");
    ros2_bag(&path, 20, &Spec::default());
    let whole = open(&path).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    let cut = dir.path().join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 6 / 10]).unwrap();
    let ds = open(&cut).expect("a cut file is read up to the cut");
    let n = ds.frames.len();
    assert!((8..20).contains(&n), "{n} frames");
    let t: Vec<_> = ds.issues.iter().map(|i| i.kind).collect();
    assert_eq!(t, [IssueKind::TruncatedFile]);
    assert!(ds.issues[0].detail.contains("cannot be read past byte"));
    assert_eq!(pixels(&ds), pixels(&whole)[..n].to_vec());
    assert_eq!(ds.imu[..], whole.imu[..ds.imu.len()]);
    // Cut inside the first chunk: nothing usable, and the error says the file is damaged.
    let early = dir.path().join("early.mcap");
    std::fs::write(&early, &bytes[..300]).unwrap();
    let e = open(&early).unwrap_err().to_string();
    assert!(
        e.contains("early.mcap") && e.contains("the file is damaged") && e.contains("past byte"),
        "{e}"
    );
}

#[test]
fn damaged_chunk_is_skipped_and_later_chunks_used() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bag.mcap");
    ros2_bag(&path, 20, &Spec::default());
    let whole = open(&path).unwrap();
    let mut bytes = std::fs::read(&path).unwrap();
    // Damage the compressed data of the chunk holding frame 10.
    let datasets::FrameSource::Mcap(at) = whole.frames[10].source else {
        panic!("an MCAP frame")
    };
    let mid = (at.record_offset + at.record_len / 2) as usize;
    for b in &mut bytes[mid..mid + 16] {
        *b ^= 0x5a;
    }
    let damaged = dir.path().join("damaged.mcap");
    std::fs::write(&damaged, &bytes).unwrap();
    let ds = open(&damaged).expect("the other chunks are used");
    assert!(ds.issues.iter().all(|i| i.kind == IssueKind::TruncatedFile));
    assert_eq!(ds.issues.len(), 1, "{:?}", ds.issues);
    assert!(ds.issues[0]
        .detail
        .contains(&format!("byte {}", at.record_offset)));
    let times: Vec<i64> = ds.frames.iter().map(|f| f.t_ns).collect();
    assert!(!times.contains(&whole.frames[10].t_ns));
    assert!(times.contains(&whole.frames[19].t_ns) && times.len() >= 17);
    // The frames kept still decode to the same pixels.
    let all = pixels(&whole);
    for (f, p) in ds.frames.iter().zip(pixels(&ds)) {
        let k = whole.frames.iter().position(|g| g.t_ns == f.t_ns).unwrap();
        assert_eq!(p, all[k]);
    }
}

#[cfg_attr(
    not(shoal_data),
    ignore = "needs ../shared/data/euroc_v101_static (set SHOAL_DATA)"
)]
#[test]
fn euroc_v101_static_round_trip() {
    let src = common::data_dir("euroc_v101_static").join("euroc_v101_static");
    let ds = open(&src).expect("open");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("v101.mcap");
    let yaml = imu_yaml(&ds);
    let s = write_dataset(&ds, Some(&yaml), &out, &WriteSettings::default()).unwrap();
    assert_eq!((s.frames, s.imu_samples), (95, ds.imu.len()));
    let back = open(&out).unwrap();
    assert!(back.issues.is_empty(), "{:?}", back.issues);
    assert_same_replay(&ds, &back);
    assert_eq!(back.imu_calib, Some(yaml));
}
