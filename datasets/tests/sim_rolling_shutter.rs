//! Rolling shutter in the synthetic renderer: each row is rendered with the camera pose at
//! its own capture time `t(v) = t_mid + (v - N/2) t_r / N` (seed eq. 2.61-2.63).
//!
//! A vertical edge of a panel is located in the rendered label image row by row and compared
//! with (a) its projection using the pose at each row's time, which must match within about
//! a pixel, and (b) its projection using the single mid-row (global-shutter) pose, which must
//! be off by several pixels at the top and bottom of the image under fast rotation.

use datasets::sim::{Scenario, SimParams, SimWorld, FIRST_PANEL};
use nalgebra::{Isometry3, Vector2, Vector3};
use slam_core::rolling_shutter::{row_time_ns, solve_row_fixed_point};

/// Image coordinates of the point of the 3D segment `a + s (b - a)` that lies on image row
/// `row` for camera pose `t_wc` (bisection on `s`), if the segment crosses that row.
fn edge_on_row(
    world: &SimWorld,
    t_wc: &Isometry3<f64>,
    a: &Vector3<f64>,
    b: &Vector3<f64>,
    row: f64,
) -> Option<f64> {
    let cam = world.camera();
    let proj = |s: f64| {
        cam.project(
            &t_wc
                .inverse_transform_point(&(a + (b - a) * s).into())
                .coords,
        )
    };
    let (mut lo, mut hi) = (0.0, 1.0);
    let (vlo, vhi) = (proj(lo)?.y - row, proj(hi)?.y - row);
    if vlo * vhi > 0.0 {
        return None;
    }
    for _ in 0..50 {
        let mid = 0.5 * (lo + hi);
        let vm = proj(mid)?.y - row;
        if (vm > 0.0) == (vlo > 0.0) {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Some(proj(0.5 * (lo + hi))?.x)
}

/// Column (x + 0.5) of the label transition next to `u` on row `v`, if any within 6 px.
fn measured_edge(labels: &[u8], width: usize, v: usize, u: f64, label: u8) -> Option<f64> {
    let row = &labels[v * width..(v + 1) * width];
    let u0 = u.floor() as i64;
    (0..=6i64)
        .flat_map(|d| [u0 + d, u0 - d])
        .filter(|&x| x >= 0 && (x as usize) + 1 < width)
        .find(|&x| (row[x as usize] == label) != (row[x as usize + 1] == label))
        .map(|x| x as f64 + 0.5)
}

#[test]
fn rows_are_rendered_at_their_own_capture_times() {
    let mut params = SimParams::new(Scenario::FastRs);
    params.pixel_noise_sigma = 0.0;
    params.frames = Some(640);
    let world = SimWorld::new(params).expect("world");
    let cam = *world.camera();
    let (w, h) = (cam.width as usize, cam.height as usize);
    assert_eq!(world.readout_ns(), 30_000_000);

    // The renderer's per-row pose is the pose at row_time_ns(t_mid, t_r, v, N).
    for (k, v) in [(0usize, 0u32), (7, 100), (300, 479)] {
        let t = row_time_ns(
            world.frame_capture_time_ns(k),
            world.readout_ns(),
            f64::from(v),
            cam.height,
        );
        assert_eq!(world.row_time_ns(k, v), t);
        assert_eq!(world.row_pose(k, v), world.pose_cam_at(t));
    }
    let (t0, t_last) = (
        world.row_time_ns(5, 0),
        world.row_time_ns(5, cam.height - 1),
    );
    assert_eq!(t_last - t0, 30_000_000 - 62_500);

    let mut labels = vec![0u8; w * h];
    let mut checked_frames = 0;
    let mut worst_rs: f64 = 0.0;
    for k in (0..640).step_by(4) {
        let mid_pose = world.pose_cam_at(world.frame_capture_time_ns(k));
        for (i, rect) in world.scene().rects.iter().enumerate().skip(FIRST_PANEL) {
            for s_edge in [0.0, rect.size_u] {
                let (a, b) = (rect.point(s_edge, 0.0), rect.point(s_edge, rect.size_v));
                // Cheap pre-check with the mid pose: the whole edge far from the image borders
                // and far from the global-shutter prediction.
                let rows: Vec<usize> = (0..h).step_by(8).collect();
                let mut pairs = Vec::new();
                for &v in &rows {
                    let rs = edge_on_row(&world, &world.row_pose(k, v as u32), &a, &b, v as f64);
                    let gs = edge_on_row(&world, &mid_pose, &a, &b, v as f64);
                    if let (Some(rs), Some(gs)) = (rs, gs) {
                        if rs > 8.0 && rs < w as f64 - 8.0 {
                            pairs.push((v, rs, gs));
                        }
                    }
                }
                let far: Vec<_> = pairs
                    .iter()
                    .filter(|(v, _, _)| (*v as i64 - h as i64 / 2).abs() > 160)
                    .collect();
                let diff = far.iter().map(|(_, rs, gs)| (rs - gs).abs()).sum::<f64>()
                    / far.len().max(1) as f64;
                if pairs.len() < 30 || far.len() < 10 || diff < 8.0 {
                    continue;
                }
                world.render_labels_into(k, &mut labels).expect("labels");
                let label = (i + 1) as u8;
                let (mut n_ok, mut n_rows) = (0, 0);
                for &(v, rs, gs) in &pairs {
                    // The rendered edge is not occluded by another panel in this row?
                    let Some(m) = measured_edge(&labels, w, v, rs, label) else {
                        continue;
                    };
                    n_rows += 1;
                    worst_rs = worst_rs.max((m - rs).abs());
                    if (m - rs).abs() <= 1.5 {
                        n_ok += 1;
                    }
                    if (v as i64 - h as i64 / 2).abs() > 160 {
                        assert!(
                            (m - gs).abs() > 3.0,
                            "frame {k} row {v}: edge at {m}, GS predicts {gs}, RS {rs}"
                        );
                    }
                    // The rolling-shutter projection fixed point of the edge point seen on this
                    // row lands on this row at this column.
                    let pt = edge_point(&world, &world.row_pose(k, v as u32), &a, &b, v as f64);
                    let (vf, tf) = solve_row_fixed_point(
                        world.frame_capture_time_ns(k),
                        world.readout_ns(),
                        cam.height,
                        1e-6,
                        50,
                        |t| {
                            cam.project(
                                &world
                                    .pose_cam_at(t)
                                    .inverse_transform_point(&pt.into())
                                    .coords,
                            )
                            .map(|p| p.y)
                        },
                    )
                    .expect("fixed point");
                    assert!((vf - v as f64).abs() < 1e-3, "fixed point row {vf} vs {v}");
                    let uv = cam
                        .project(
                            &world
                                .pose_cam_at(tf)
                                .inverse_transform_point(&pt.into())
                                .coords,
                        )
                        .expect("front");
                    assert!((uv - Vector2::new(rs, v as f64)).norm() < 0.05);
                }
                assert!(
                    n_rows >= 20,
                    "frame {k} panel {i}: only {n_rows} rows with a visible edge"
                );
                assert!(
                    n_ok as f64 >= 0.95 * n_rows as f64,
                    "frame {k}: {n_ok}/{n_rows} rows match the RS prediction"
                );
                checked_frames += 1;
                eprintln!(
                    "frame {k} panel {i} edge s={s_edge}: {n_rows} rows, RS-vs-GS mean offset {diff:.1} px at the image ends"
                );
            }
        }
        if checked_frames >= 3 {
            break;
        }
    }
    assert!(
        checked_frames >= 3,
        "found only {checked_frames} frames with a usable edge"
    );
    eprintln!("worst |rendered - RS prediction| = {worst_rs:.2} px");
}

/// The 3D point of the segment seen on image row `row` with pose `t_wc`.
fn edge_point(
    world: &SimWorld,
    t_wc: &Isometry3<f64>,
    a: &Vector3<f64>,
    b: &Vector3<f64>,
    row: f64,
) -> Vector3<f64> {
    let cam = world.camera();
    let v_of = |s: f64| {
        cam.project(
            &t_wc
                .inverse_transform_point(&(a + (b - a) * s).into())
                .coords,
        )
        .map_or(f64::NAN, |p| p.y)
            - row
    };
    let (mut lo, mut hi) = (0.0, 1.0);
    let slo = v_of(lo) > 0.0;
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if (v_of(mid) > 0.0) == slo {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    a + (b - a) * (0.5 * (lo + hi))
}

#[test]
fn global_shutter_renders_every_row_with_the_mid_pose() {
    let mut params = SimParams::new(Scenario::FastRs);
    params.readout_ms = Some(0.0);
    params.frames = Some(3);
    let world = SimWorld::new(params).expect("world");
    for v in [0, 240, 479] {
        assert_eq!(
            world.row_pose(2, v),
            world.pose_cam_at(world.frame_capture_time_ns(2))
        );
    }
}
