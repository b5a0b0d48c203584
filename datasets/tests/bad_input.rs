//! Bad input: readers skip and report (file + line) or fail with an error naming the file.

use std::fs;
use std::path::Path;

use datasets::trajectory::{
    detect_format, read_kitti, read_trajectory, write_kitti, write_tum, TrajectoryFormat,
};
use datasets::{
    decode_gray_into, image_size, open, DatasetError, DatasetKind, InputIssue, IssueKind,
    StampedPose,
};

const YAML: &str = "%YAML:1.0\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: [1.0, 0.0, 0.0, 0.1, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]\nrate_hz: 20\nresolution: [4, 3]\nintrinsics: [100.0, 101.0, 2.0, 1.5]\ndistortion_coefficients: [0.1, 0.01, 0.001, 0.0001]\nreadout_time_ns: 20000000\ntime_offset_ns: 1500000\n";

fn write_png(path: &Path, w: u32, h: u32) {
    let img = image::GrayImage::from_fn(w, h, |x, y| image::Luma([(x * 10 + y) as u8]));
    img.save(path).expect("write png");
}

/// A minimal EuRoC folder; returns its root.
fn euroc(dir: &Path, cam_csv: &str, imu_csv: &str, gt_csv: &str) -> std::path::PathBuf {
    let mav = dir.join("mav0");
    fs::create_dir_all(mav.join("cam0/data")).expect("mkdir");
    fs::create_dir_all(mav.join("imu0")).expect("mkdir");
    fs::create_dir_all(mav.join("state_groundtruth_estimate0")).expect("mkdir");
    fs::write(mav.join("cam0/sensor.yaml"), YAML).expect("yaml");
    for t in [100, 200, 300, 400] {
        write_png(&mav.join(format!("cam0/data/{t}.png")), 4, 3);
    }
    fs::write(mav.join("cam0/data.csv"), cam_csv).expect("csv");
    fs::write(mav.join("imu0/data.csv"), imu_csv).expect("csv");
    fs::write(mav.join("state_groundtruth_estimate0/data.csv"), gt_csv).expect("csv");
    dir.to_path_buf()
}

fn has(issues: &[InputIssue], file: &str, line: usize, kind: IssueKind) -> bool {
    issues
        .iter()
        .any(|i| i.path.ends_with(file) && i.line == line && i.kind == kind)
}

#[test]
fn euroc_lenient_lines_and_missing_images() {
    let tmp = tempfile::tempdir().expect("tmp");
    let cam = "#timestamp [ns],filename\n100,100.png\n200,200.png\n150,150.png\n200,200.png\n300\n400,400.png\n500,500.png\n";
    let imu = "#t\n100,0,0,0,0,0,9.8\n105,0,0,0,0,0\n110,0,0,0,0,0,x\n110,0,0,0,0,0,9.8\n108,0,0,0,0,0,9.8\n";
    let gt = "#t,p,q\n100,0,0,0,1,0,0,0\n300,2,0,0,1,0,0,0\n350,9,9,9,0,0,0,0\n";
    let root = euroc(tmp.path(), cam, imu, gt);
    let ds = open(&root).expect("open");
    assert_eq!(ds.kind, DatasetKind::Euroc);
    let csv = "cam0/data.csv";
    assert!(
        has(&ds.issues, csv, 4, IssueKind::NonMonotonic),
        "{:#?}",
        ds.issues
    );
    assert!(
        has(&ds.issues, csv, 5, IssueKind::NonMonotonic),
        "{:#?}",
        ds.issues
    );
    assert!(
        has(&ds.issues, csv, 6, IssueKind::MalformedLine),
        "{:#?}",
        ds.issues
    );
    assert!(
        has(&ds.issues, csv, 8, IssueKind::MissingImage),
        "{:#?}",
        ds.issues
    );
    assert!(has(
        &ds.issues,
        "imu0/data.csv",
        3,
        IssueKind::MalformedLine
    ));
    assert!(has(
        &ds.issues,
        "imu0/data.csv",
        4,
        IssueKind::MalformedLine
    ));
    assert!(has(&ds.issues, "imu0/data.csv", 6, IssueKind::NonMonotonic));
    assert!(has(
        &ds.issues,
        "state_groundtruth_estimate0/data.csv",
        4,
        IssueKind::MalformedLine
    ));
    // t_d = 1.5 ms is added to every frame; readout and calibration come from the YAML.
    let t: Vec<i64> = ds.frames.iter().map(|f| f.t_ns).collect();
    assert_eq!(t, vec![1_500_100, 1_500_200, 1_500_400]);
    assert_eq!(ds.camera.readout_ns, 20_000_000);
    assert_eq!(ds.frames[0].readout_ns, 20_000_000);
    assert_eq!((ds.camera.model.k1, ds.camera.model.p2), (0.1, 0.0001));
    assert_eq!(ds.imu.len(), 2);
    // Ground truth covers 100..300 ns only: all frames (now at 1.5 ms) are outside it.
    assert_eq!(ds.ground_truth.as_ref().map(Vec::len), Some(0));
    // Error messages name file and line.
    let i = &ds.issues[0];
    assert!(i.path.is_absolute() || i.path.exists());
}

#[test]
fn euroc_gt_interpolated_and_mapped_to_camera() {
    let tmp = tempfile::tempdir().expect("tmp");
    let cam = "#t,f\n100,100.png\n200,200.png\n300,300.png\n400,400.png\n";
    let root = euroc(tmp.path(), cam, "", "");
    // No time offset for this one.
    let yaml = YAML.replace("time_offset_ns: 1500000\n", "");
    fs::write(root.join("mav0/cam0/sensor.yaml"), yaml).expect("yaml");
    fs::write(
        root.join("mav0/state_groundtruth_estimate0/data.csv"),
        "0,0,0,0,1,0,0,0\n250,5,0,0,1,0,0,0\n300,5,0,0,1,0,0,0\n",
    )
    .expect("gt");
    let ds = open(&root).expect("open");
    let gt = ds.ground_truth.as_ref().expect("gt");
    let x: Vec<(i64, f64)> = gt.iter().map(|p| (p.t_ns, p.pose.translation.x)).collect();
    // T_BS has +0.1 m along x; 400 is past the end of the ground truth.
    assert_eq!(x, vec![(100, 2.1), (200, 4.1), (300, 5.1)]);

    // The generator's camera-to-world TUM file beside mav0 wins, shifted by t_d.
    fs::write(
        root.join("groundtruth_cam0.txt"),
        "# t ...\n0.000000100 7 0 0 0 0 0 1\n0.000000300 9 0 0 0 0 0 1\n",
    )
    .expect("tum");
    let ds = open(&root).expect("open");
    let x: Vec<(i64, f64)> = ds
        .ground_truth
        .expect("gt")
        .iter()
        .map(|p| (p.t_ns, p.pose.translation.x))
        .collect();
    assert_eq!(x, vec![(100, 7.0), (200, 8.0), (300, 9.0)]);
}

#[test]
fn hard_errors_name_the_file() {
    let tmp = tempfile::tempdir().expect("tmp");
    let missing = tmp.path().join("nope");
    let e = open(&missing).map(|_| ()).unwrap_err();
    assert!(
        matches!(e, DatasetError::NotFound { .. }) && e.to_string().contains("nope"),
        "{e}"
    );
    let e = open(tmp.path()).map(|_| ()).unwrap_err();
    assert!(matches!(e, DatasetError::UnknownFormat { .. }), "{e}");

    // Unparseable calibration is a hard error naming sensor.yaml.
    let root = euroc(&tmp.path().join("e"), "100,100.png\n", "", "");
    fs::write(
        root.join("mav0/cam0/sensor.yaml"),
        "%YAML:1.0\nresolution: [4]\nintrinsics: [1,1,1,1]\n",
    )
    .expect("yaml");
    let e = open(&root).map(|_| ()).unwrap_err().to_string();
    assert!(e.contains("sensor.yaml") && e.contains("resolution"), "{e}");
    fs::write(
        root.join("mav0/cam0/sensor.yaml"),
        "resolution: [4, 3]\nintrinsics: [1, 1, 1]\n",
    )
    .expect("yaml");
    assert!(open(&root)
        .map(|_| ())
        .unwrap_err()
        .to_string()
        .contains("intrinsics"));
    fs::remove_file(root.join("mav0/cam0/data.csv")).expect("rm");
    fs::write(root.join("mav0/cam0/sensor.yaml"), YAML).expect("yaml");
    let e = open(&root).map(|_| ()).unwrap_err();
    assert!(
        matches!(e, DatasetError::NotFound { .. }) && e.to_string().contains("data.csv"),
        "{e}"
    );

    // KITTI without calib.txt; bad P0.
    let k = tmp.path().join("k");
    fs::create_dir_all(k.join("image_0")).expect("mkdir");
    fs::write(k.join("times.txt"), "0.0\n").expect("times");
    let e = open(&k).map(|_| ()).unwrap_err().to_string();
    assert!(e.contains("calib.txt"), "{e}");
    fs::write(k.join("calib.txt"), "P0: 1 2 3\n").expect("calib");
    let e = open(&k).map(|_| ()).unwrap_err().to_string();
    assert!(e.contains("calib.txt:1"), "{e}");
}

#[test]
fn kitti_and_phone_lenient() {
    let tmp = tempfile::tempdir().expect("tmp");
    let k = tmp.path().join("sequences/07");
    fs::create_dir_all(k.join("image_0")).expect("mkdir");
    fs::write(k.join("calib.txt"), "P0: 500 0 320 0 0 500 240 0 0 0 1 0\n").expect("calib");
    fs::write(k.join("times.txt"), "0.0\n0.1\nbad\n0.05\n0.4\n0.5\n").expect("times");
    for i in [0, 1, 2, 3, 4] {
        write_png(&k.join(format!("image_0/{i:06}.png")), 8, 6);
    }
    let pose = |x: f64| format!("1 0 0 {x} 0 1 0 0 0 0 1 0\n");
    fs::create_dir_all(tmp.path().join("poses")).expect("mkdir");
    let poses = [
        pose(0.0),
        pose(1.0),
        pose(2.0),
        pose(3.0),
        "1 2 3\n".into(),
        pose(5.0),
    ]
    .concat();
    fs::write(tmp.path().join("poses/07.txt"), poses).expect("poses");
    let ds = open(&k).expect("open kitti");
    assert!(
        has(&ds.issues, "times.txt", 3, IssueKind::MalformedLine),
        "{:#?}",
        ds.issues
    );
    assert!(
        has(&ds.issues, "times.txt", 4, IssueKind::NonMonotonic),
        "{:#?}",
        ds.issues
    );
    assert!(
        has(&ds.issues, "times.txt", 6, IssueKind::MissingImage),
        "{:#?}",
        ds.issues
    );
    assert!(
        has(&ds.issues, "poses/07.txt", 5, IssueKind::MalformedLine),
        "{:#?}",
        ds.issues
    );
    let t: Vec<i64> = ds.frames.iter().map(|f| f.t_ns).collect();
    assert_eq!(t, vec![0, 100_000_000, 400_000_000]);
    assert_eq!((ds.camera.model.width, ds.camera.model.height), (8, 6));
    let gt: Vec<f64> = ds
        .ground_truth
        .expect("gt")
        .iter()
        .map(|p| p.pose.translation.x)
        .collect();
    assert_eq!(gt, vec![0.0, 1.0]); // frame 4's pose line is malformed

    let p = tmp.path().join("phone");
    fs::create_dir_all(p.join("frames")).expect("mkdir");
    let meta = "Timestamp[nanosec],fx[px],fy[px],Frame No.,Exposure time[nanosec],Sensor frame duration[nanosec],Frame readout time[nanosec]\n\
                1000,500,500,1,100,0,20\n2000,500,500,2,100\n3000,500,500,3,100,0,20\n2500,500,500,4,100,0,20\n5000,500,500,5,100,0,20\n";
    fs::write(p.join("movie_metadata.csv"), meta).expect("meta");
    for i in [1, 2, 3, 4] {
        write_png(&p.join(format!("frames/{i:04}.png")), 6, 4);
    }
    fs::write(p.join("gyro_accel.csv"), "Timestamp[nanosec],gx,gy,gz,ax,ay,az,Unix\n10,0,0,0,0,0,9.8,1\n5,0,0,0,0,0,9.8,1\n20,0,0,\n").expect("imu");
    let ds = open(&p).expect("open phone");
    assert!(
        has(
            &ds.issues,
            "movie_metadata.csv",
            3,
            IssueKind::MalformedLine
        ),
        "{:#?}",
        ds.issues
    );
    assert!(
        has(&ds.issues, "movie_metadata.csv", 5, IssueKind::NonMonotonic),
        "{:#?}",
        ds.issues
    );
    assert!(
        has(&ds.issues, "movie_metadata.csv", 6, IssueKind::MissingImage),
        "{:#?}",
        ds.issues
    );
    assert!(
        has(&ds.issues, "gyro_accel.csv", 3, IssueKind::NonMonotonic),
        "{:#?}",
        ds.issues
    );
    assert!(
        has(&ds.issues, "gyro_accel.csv", 4, IssueKind::MalformedLine),
        "{:#?}",
        ds.issues
    );
    let t: Vec<i64> = ds.frames.iter().map(|f| f.t_ns).collect();
    assert_eq!(t, vec![1060, 3060]);
    assert!(ds.frames[1].path.ends_with("frames/0003.png"));
    assert_eq!((ds.camera.model.cx, ds.camera.model.cy), (3.0, 2.0));
}

#[test]
fn corrupt_and_odd_pngs() {
    let tmp = tempfile::tempdir().expect("tmp");
    let good = tmp.path().join("good.png");
    write_png(&good, 5, 4);
    let bytes = fs::read(&good).expect("read");
    // Truncated data: header readable, decode fails with an Image error naming the file.
    let trunc = tmp.path().join("trunc.png");
    fs::write(&trunc, &bytes[..bytes.len() - 20]).expect("write");
    assert_eq!(image_size(&trunc).expect("header"), (5, 4));
    let mut buf = vec![0u8; 20];
    let e = decode_gray_into(&trunc, &mut buf, 5, 4).unwrap_err();
    assert!(
        matches!(e, DatasetError::Image { .. }) && e.to_string().contains("trunc.png"),
        "{e}"
    );
    // Garbage.
    let junk = tmp.path().join("junk.png");
    fs::write(&junk, b"definitely not a png at all....").expect("write");
    assert!(matches!(image_size(&junk), Err(DatasetError::Image { .. })));
    assert!(matches!(
        decode_gray_into(&junk, &mut buf, 5, 4),
        Err(DatasetError::Image { .. })
    ));
    assert!(matches!(
        image_size(&tmp.path().join("none.png")),
        Err(DatasetError::NotFound { .. })
    ));
    // RGB is converted to gray.
    let rgb = tmp.path().join("rgb.png");
    image::RgbImage::from_pixel(5, 4, image::Rgb([90, 90, 90]))
        .save(&rgb)
        .expect("rgb");
    decode_gray_into(&rgb, &mut buf, 5, 4).expect("rgb decode");
    assert!(buf.iter().all(|&v| v == 90));
    // 8-bit gray decodes straight into the buffer.
    decode_gray_into(&good, &mut buf, 5, 4).expect("decode");
    assert_eq!(buf[5 + 2], 21);
}

#[test]
fn trajectory_files_roundtrip_and_issues() {
    let tmp = tempfile::tempdir().expect("tmp");
    let tum = tmp.path().join("t.txt");
    fs::write(
        &tum,
        "# comment\n1403715273.262142976 1 2 3 0 0 0 1\n1403715273.3 1 2 3 0 0\n1403715273.2 1 2 3 0 0 0 1\n\
         1403715273.4 1 2 3 0 0 0 0\n1403715273.5 1 2 3 0 0 0.7071067811865476 0.7071067811865476\n",
    )
    .expect("tum");
    assert_eq!(detect_format(&tum).expect("fmt"), TrajectoryFormat::Tum);
    let t = read_trajectory(&tum).expect("read");
    assert_eq!(t.poses.len(), 2);
    assert_eq!(t.poses[0].t_ns, 1_403_715_273_262_142_976);
    assert!(has(&t.issues, "t.txt", 3, IssueKind::MalformedLine));
    assert!(has(&t.issues, "t.txt", 4, IssueKind::NonMonotonic));
    assert!(has(&t.issues, "t.txt", 5, IssueKind::MalformedLine)); // zero quaternion

    let out = tmp.path().join("o.txt");
    write_tum(&out, &t.poses).expect("write");
    let back = read_trajectory(&out).expect("read back");
    assert_eq!(back.poses, t.poses);

    let k = tmp.path().join("k.txt");
    write_kitti(&k, &t.poses).expect("write kitti");
    assert_eq!(detect_format(&k).expect("fmt"), TrajectoryFormat::Kitti);
    let kb = read_kitti(&k, None).expect("read kitti");
    assert!(!kb.timestamped);
    assert_eq!(
        kb.poses.iter().map(|p| p.t_ns).collect::<Vec<_>>(),
        vec![0, 1]
    );
    let (qa, qb) = (kb.poses[1].pose.rotation, t.poses[1].pose.rotation);
    assert!((qa.coords - qb.coords).norm() < 1e-12 || (qa.coords + qb.coords).norm() < 1e-12);
    let times = tmp.path().join("times.txt");
    fs::write(&times, "0.5\n").expect("times");
    let kt = read_kitti(&k, Some(&times)).expect("kitti+times");
    assert_eq!(kt.poses.len(), 1);
    assert!(
        has(&kt.issues, "k.txt", 2, IssueKind::MissingTime)
            && has(&kt.issues, "times.txt", 0, IssueKind::LengthMismatch)
    );
    let bad = tmp.path().join("bad.txt");
    fs::write(&bad, "1 2 3\n").expect("bad");
    assert!(read_trajectory(&bad)
        .map(|_| ())
        .unwrap_err()
        .to_string()
        .contains("bad.txt:1"));
    let _unused: Option<StampedPose> = None;
}
