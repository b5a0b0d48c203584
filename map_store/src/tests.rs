//! Round trip, refusals, atomic write and the id remap.

use std::path::Path;

use nalgebra::{Isometry3, Vector3};
use slam_core::camera::PinholeRadtan;
use slam_core::features::{KeyPoint, OrbFeatures};
use slam_core::ids::{ClientId, KeyframeId, MapId, MapPointId};
use slam_core::server::{MapFrame, ServerMap};
use slam_core::vo::Keyframe;

use super::*;
use crate::remap::SAVED_CLIENT_BASE;

/// A keyframe of client `c` with id `k`, `n` keypoints, camera at `x` on the x axis.
fn keyframe(c: u32, k: u64, n: usize, x: f64) -> Keyframe {
    Keyframe {
        id: KeyframeId::new(ClientId::new(c), k).raw(),
        t_ns: k as i64 * 50_000_000,
        t_cw: Isometry3::translation(-x, 0.0, 0.0),
        camera: PinholeRadtan::pinhole(640, 480, 500.0, 500.0, 320.0, 240.0),
        readout_ns: 0,
        features: OrbFeatures {
            keypoints: (0..n).map(|i| KeyPoint::at_level0(i as f32, 2.0)).collect(),
            descriptors: (0..n).map(|i| [(i * 7 + k as usize) as u8; 32]).collect(),
            ..OrbFeatures::default()
        },
        points: vec![None; n],
        inertial: None,
        imu: None,
    }
}

/// A map of client `c` (map index `index`): three keyframes sharing four points.
fn server_map(c: u32, index: u32, frame: MapFrame) -> ServerMap {
    let first_point = MapPointId::first_of_client(ClientId::new(c)).raw();
    let mut m = ServerMap::new(
        MapId::new(ClientId::new(c), index),
        c,
        1,
        first_point,
        frame,
    );
    for k in 0..3 {
        m.map.insert_keyframe(keyframe(c, k, 6, k as f64 * 0.1));
    }
    let kf = |k: u64| KeyframeId::new(ClientId::new(c), k).raw();
    for i in 0..4u32 {
        let p = Vector3::new(i as f64, 0.5, 4.0 + c as f64);
        m.map
            .add_point(p, kf(0), &[(kf(0), i), (kf(1), i), (kf(2), i + 1)]);
    }
    for k in 0..3 {
        m.map.update_covisibility(kf(k));
    }
    m
}

fn saved(m: ServerMap) -> SavedMap {
    let clients = clients_of(&m);
    let bow = m
        .map
        .keyframes
        .keys()
        .map(|k| (*k, BowVector::default(), FeatureVector::default()))
        .collect();
    SavedMap {
        map: m,
        clients,
        bow,
    }
}

fn two_maps() -> MapFile {
    MapFile {
        feature_level: 2,
        maps: vec![
            saved(server_map(0, 0, MapFrame::VISUAL)),
            saved(server_map(1, 2, MapFrame::INERTIAL)),
        ],
    }
}

fn payload(f: &MapFile) -> Vec<u8> {
    postcard::to_stdvec(f).expect("encodes")
}

/// Save → load gives the same maps (same encoding, same points, observations and
/// covisibility), and saving the loaded file gives the same bytes.
#[test]
fn a_round_trip_is_byte_identical() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (a, b) = (dir.path().join("a.shoalmap"), dir.path().join("b.shoalmap"));
    let file = two_maps();
    let n = write(&a, &file, 0x1234, "0.1.0").expect("written");
    let (header, back) = read(&a).expect("reads");
    assert_eq!(n, std::fs::metadata(&a).expect("exists").len());
    assert_eq!(header.vocabulary_id, 0x1234);
    assert_eq!(header.shoal_version, "0.1.0");
    assert_eq!(payload(&back), payload(&file));
    let (m0, m1) = (&back.maps[0].map, &back.maps[1].map);
    assert_eq!(m1.frame, MapFrame::INERTIAL);
    assert_eq!(m0.map.points.len(), 4);
    let (k0, k1) = (
        KeyframeId::new(ClientId::new(0), 0).raw(),
        KeyframeId::new(ClientId::new(0), 1).raw(),
    );
    assert_eq!(m0.map.covis_weight(k0, k1), 4);
    assert_eq!(m0.map.keyframes[&k1].points.iter().flatten().count(), 4);
    write(&b, &back, 0x1234, "0.1.0").expect("written again");
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
}

fn written() -> (tempfile::TempDir, std::path::PathBuf, Vec<u8>) {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("m.shoalmap");
    write(&path, &two_maps(), 7, "0.1.0").expect("written");
    let bytes = std::fs::read(&path).expect("read");
    (dir, path, bytes)
}

/// Every truncation is refused as such, naming the file.
#[test]
fn a_truncated_file_is_refused() {
    let (_dir, path, bytes) = written();
    for cut in [12, 29, bytes.len() / 2, bytes.len() - 1] {
        let e = read_bytes(&bytes[..cut], &path).expect_err("truncated");
        assert!(
            matches!(e, MapFileError::Truncated { .. }),
            "cut {cut}: {e}"
        );
        assert!(e.to_string().contains("m.shoalmap"), "{e}");
    }
}

/// Flipping any one byte past the magic and version makes the file refused (mostly by the
/// checksum; a flipped length is a truncation or trailing bytes).
#[test]
fn one_flipped_byte_is_refused() {
    let (_dir, path, bytes) = written();
    let mut checksum = 0;
    for at in 12..bytes.len() {
        let mut b = bytes.clone();
        b[at] ^= 0x10;
        match read_bytes(&b, &path) {
            Err(MapFileError::Checksum { .. }) => checksum += 1,
            Err(MapFileError::Truncated { .. } | MapFileError::TrailingBytes { .. }) => {}
            other => panic!("byte {at} flipped: {other:?}"),
        }
    }
    assert!(checksum > bytes.len() - 30, "{checksum} of {}", bytes.len());
}

/// A file of another version is refused with both versions and its writer named; a file
/// without the magic is not a map.
#[test]
fn another_version_and_a_wrong_magic_are_refused() {
    let (_dir, path, mut bytes) = written();
    bytes[8..12].copy_from_slice(&7u32.to_le_bytes());
    let e = read_bytes(&bytes, &path).expect_err("version");
    let text = e.to_string();
    assert!(matches!(
        e,
        MapFileError::Version {
            found: 7,
            expected: FORMAT_VERSION,
            ..
        }
    ));
    assert!(
        text.contains("version 7") && text.contains(&format!("version {FORMAT_VERSION}")),
        "{text}"
    );
    assert!(text.contains("shoal 0.1.0"), "{text}");
    bytes[0] = b'X';
    let e = read_bytes(&bytes, &path).expect_err("magic");
    assert!(matches!(e, MapFileError::NotAMap { .. }), "{e}");
    let e = read_bytes(b"", &path).expect_err("empty");
    assert!(matches!(e, MapFileError::NotAMap { .. }), "{e}");
}

/// A payload that passes the checksum but is inconsistent (a keyframe with fewer point
/// slots than keypoints) is refused by the validation.
#[test]
fn an_inconsistent_map_is_refused() {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("bad.shoalmap");
    let mut file = two_maps();
    let kf = file.maps[0]
        .map
        .map
        .keyframes
        .values_mut()
        .next()
        .expect("a keyframe");
    kf.points.pop();
    write(&path, &file, 0, "0.1.0").expect("written");
    let e = read(&path).expect_err("inconsistent");
    assert!(matches!(e, MapFileError::Invalid { .. }), "{e}");
}

/// A write into a folder that cannot take it fails, leaves the old file as it was and no
/// temporary file behind.
#[test]
fn a_failed_write_leaves_no_file() {
    let dir = tempfile::tempdir().expect("tempdir");
    let missing = dir.path().join("no/such/dir/m.shoalmap");
    let e = write(&missing, &two_maps(), 0, "0.1.0").expect_err("no folder");
    assert!(matches!(e, MapFileError::Io { .. }), "{e}");
    // The target is a folder: the rename fails after the temporary file was written.
    let target = dir.path().join("m.shoalmap");
    std::fs::create_dir(&target).expect("dir");
    std::fs::write(target.join("keep"), b"x").expect("file");
    let e = write(&target, &two_maps(), 0, "0.1.0").expect_err("rename over a folder");
    assert!(
        matches!(
            e,
            MapFileError::Io {
                what: "renaming the temporary file",
                ..
            }
        ),
        "{e}"
    );
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(
        left,
        vec![std::ffi::OsString::from("m.shoalmap")],
        "{left:?}"
    );
    assert!(target.join("keep").exists());
}

/// Clients 0 and 1 become the first two saved clients in every id; links stay consistent
/// (each point's observations name keyframes that see it), and the same file always gets
/// the same ids.
#[test]
fn loaded_clients_are_renamed_everywhere() {
    let mut file = two_maps();
    let table = remap::remap_clients(&mut file);
    assert_eq!(
        table,
        [(0, SAVED_CLIENT_BASE), (1, SAVED_CLIENT_BASE + 1)].into()
    );
    let m = &file.maps[0].map;
    assert_eq!(m.id, MapId::new(ClientId::new(SAVED_CLIENT_BASE), 0));
    assert_eq!(m.client_id, SAVED_CLIENT_BASE);
    assert_eq!(file.maps[0].clients, vec![SAVED_CLIENT_BASE]);
    assert_eq!(
        file.maps[1].map.id,
        MapId::new(ClientId::new(SAVED_CLIENT_BASE + 1), 2)
    );
    let base = ClientId::new(SAVED_CLIENT_BASE);
    for (k, kf) in &m.map.keyframes {
        assert_eq!(KeyframeId::from_raw(*k).client(), base);
        for p in kf.points.iter().flatten() {
            assert_eq!(MapPointId::from_raw(*p).client(), base);
            assert!(m.map.points[p].observations.iter().any(|o| o.0 == *k));
        }
    }
    for p in m.map.points.values() {
        assert_eq!(KeyframeId::from_raw(p.first_kf).client(), base);
    }
    let k = |i| KeyframeId::new(base, i).raw();
    assert_eq!(m.map.covis_weight(k(0), k(1)), 4);
    assert_eq!(MapPointId::from_raw(m.map.next_point_id()).client(), base);
    assert!(file.maps[0]
        .bow
        .iter()
        .all(|(b, _, _)| KeyframeId::from_raw(*b).client() == base));
    // A file saved after loading holds saved clients: they are renamed again, distinct.
    let mut again = file.clone();
    again.maps.push(saved(server_map(0, 0, MapFrame::VISUAL)));
    let t2 = remap::remap_clients(&mut again);
    let news: std::collections::BTreeSet<u32> = t2.values().copied().collect();
    assert_eq!(news.len(), 3);
    let mut twice = two_maps();
    remap::remap_clients(&mut twice);
    assert_eq!(payload(&twice), payload(&file));
}

/// The BoW and feature vectors of a file made from maps are the vocabulary's transform of
/// each keyframe's descriptors, one per keyframe.
#[test]
fn a_file_made_from_maps_holds_bow_vectors() {
    let vocab = slam_core::place::Vocabulary::from_bytes(SHIPPED_VOCABULARY).expect("vocabulary");
    let m = server_map(0, 0, MapFrame::VISUAL);
    let file = MapFile::from_maps([&m], &vocab, 2);
    assert_eq!(file.maps[0].bow.len(), 3);
    assert_eq!(file.feature_level, 2);
    let (k, bow, fv) = &file.maps[0].bow[1];
    let descriptors = &m.map.keyframes[k].features.descriptors;
    assert_eq!(*bow, vocab.transform(descriptors));
    assert_eq!(*fv, vocab.transform_with_features(descriptors, 2).1);
    assert!(!bow.is_empty() && !fv.groups().is_empty());
    assert_eq!(file.maps[0].clients, vec![0]);
}

/// PLY export: the header counts the points of the maps asked for; ASCII has one line per
/// point, binary 24 bytes per point.
#[test]
fn ply_export_writes_the_points() {
    let file = two_maps();
    let mut ascii = Vec::new();
    let n = ply::write_points(&mut ascii, &file, None, ply::PlyEncoding::Ascii).unwrap();
    assert_eq!(n, 8);
    let text = String::from_utf8(ascii).unwrap();
    assert!(text.contains("element vertex 8\n"), "{text}");
    let body = text.split("end_header\n").nth(1).unwrap();
    assert_eq!(body.lines().count(), 8);
    assert_eq!(body.lines().next(), Some("0 0.5 4"));
    let mut bin = Vec::new();
    let only = Some(file.maps[1].map.id.raw());
    let n = ply::write_points(&mut bin, &file, only, ply::PlyEncoding::BinaryLittleEndian).unwrap();
    assert_eq!(n, 4);
    let header_end = bin.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
    assert_eq!(bin.len() - header_end, 4 * 24);
}

/// A payload that passes the checksum but holds more than the maps (another layout under
/// the same version number) is refused, not half-read.
#[test]
fn a_payload_with_bytes_after_the_maps_is_refused() {
    let mut payload = payload(&two_maps());
    payload.extend_from_slice(&[0, 0]);
    let bytes = format::with_header(&payload, 0, "0.1.0");
    let e = read_bytes(&bytes, Path::new("x.shoalmap")).expect_err("refused");
    assert!(matches!(e, MapFileError::Decode { .. }), "{e}");
    assert!(e.to_string().contains("2 bytes left after the maps"), "{e}");
}

/// Issue 20: a map kept in memory and the same map saved and loaded give the same results.
/// Client 3 maps the constructed scene (keyframes 0-6). Its maps are renamed as a load
/// renames them twice: straight from memory (with the handler's client-point associations
/// still in them) and through an encoded file. In each, client 4 then maps keyframes 2-3
/// in a frame of its own (half the scale, turned and shifted), its map merges into the
/// loaded one by the true similarity, and keyframes 4-9 follow: every handler report and
/// the final maps are the same, byte for byte, and the poses are on the truth.
#[test]
fn a_map_through_a_file_gives_the_results_of_the_map_in_memory() {
    use slam_core::lie::Sim3;
    use slam_core::server::test_scene::{keyframe, true_pose, CLIENT};
    use slam_core::server::{merge_maps, transform_pose, HandlerParams, KeyframeHandler};
    let mut maps = slam_core::server::ServerMaps::new();
    let mut a = KeyframeHandler::new(CLIENT, HandlerParams::default());
    for k in 0..7 {
        let t = true_pose(k);
        a.handle(&mut maps, keyframe(k as u64, 1, &t, &t)).unwrap();
        a.idle_step(&mut maps);
    }
    let vocab = slam_core::place::Vocabulary::from_bytes(SHIPPED_VOCABULARY).expect("vocabulary");
    let file = MapFile::from_maps(maps.values(), &vocab, 4);
    let bytes = encode(&file, 0, "0.1.0").expect("encodes");
    let (_, mut through_file) = read_bytes(&bytes, Path::new("a.shoalmap")).expect("decodes");
    let mut in_memory = file;
    remap::remap_clients(&mut in_memory);
    remap::remap_clients(&mut through_file);
    let s_cw = Sim3::new(
        nalgebra::UnitQuaternion::from_euler_angles(0.05, -0.1, 0.3),
        Vector3::new(0.4, -0.2, 0.1),
        0.5,
    );
    let session_b = |loaded: MapFile| {
        let mut maps: slam_core::server::ServerMaps =
            loaded.maps.into_iter().map(|s| (s.map.id, s.map)).collect();
        let into = *maps.keys().next().expect("one loaded map");
        let mut b = KeyframeHandler::new(CLIENT + 1, HandlerParams::default());
        let mut reports = Vec::new();
        for k in 2..10 {
            if k == 4 {
                let from = b.current_map_id().expect("b's own map");
                let s = s_cw.inverse();
                merge_maps(&mut maps, from, into, &s, &[]).expect("merged");
                assert!(b.apply_merge(from, into, &s, true));
            }
            let t_wk = true_pose(k);
            let mut kf = keyframe(k as u64, 1, &t_wk, &transform_pose(&s_cw, &t_wk));
            kf.client_id = CLIENT + 1;
            let r = b.handle(&mut maps, kf).expect("handled");
            if k >= 4 {
                let err = (r.t_sk.unwrap().translation.vector - t_wk.translation.vector).norm();
                assert!(err < 2e-3, "keyframe {k} is {err} off the truth");
            }
            // The idle step's BA report without its timing.
            let idle = b.idle_step(&mut maps);
            let ba = idle.as_ref().and_then(|i| i.ba.as_ref());
            let ba = ba.map(|b| (b.final_cost, b.iterations, b.n_inliers));
            let idle = idle.map(|i| (ba, i.culled, i.global));
            reports.push(format!("{r:?} {idle:?}"));
        }
        let encoded: Vec<Vec<u8>> = maps
            .values()
            .map(|m| postcard::to_stdvec(m).unwrap())
            .collect();
        (reports, encoded)
    };
    let (reports_memory, maps_memory) = session_b(in_memory);
    let (reports_file, maps_file) = session_b(through_file);
    assert_eq!(reports_memory, reports_file);
    assert!(maps_memory == maps_file, "the final maps differ");
}
