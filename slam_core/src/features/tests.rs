//! Tests of the whole extractor and of matching on synthetic images with known geometry.

use super::*;

/// Deterministic pseudo-random generator (PCG-like LCG).
struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> u32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 33) as u32
    }
    fn range(&mut self, n: u32) -> u32 {
        self.next() % n
    }
}

/// A textured scene: random rectangles and disks of random grey levels, lightly smoothed.
fn scene(w: usize, h: usize, seed: u64) -> Vec<f32> {
    let mut rng = Lcg(seed);
    let mut img = vec![90.0f32; w * h];
    for _ in 0..260 {
        let (cx, cy) = (rng.range(w as u32) as f32, rng.range(h as u32) as f32);
        let (rx, ry) = (4.0 + rng.range(22) as f32, 4.0 + rng.range(22) as f32);
        let v = 20.0 + rng.range(215) as f32;
        let disk = rng.range(2) == 0;
        for y in 0..h {
            for x in 0..w {
                let (dx, dy) = ((x as f32 - cx) / rx, (y as f32 - cy) / ry);
                let inside = if disk {
                    dx * dx + dy * dy <= 1.0
                } else {
                    dx.abs() <= 1.0 && dy.abs() <= 1.0
                };
                if inside {
                    img[y * w + x] = v;
                }
            }
        }
    }
    img
}

/// Bilinear sample of `img` at `(x, y)` (border clamped).
fn sample(img: &[f32], w: usize, h: usize, x: f32, y: f32) -> f32 {
    let x = x.clamp(0.0, (w - 1) as f32 - 1e-3);
    let y = y.clamp(0.0, (h - 1) as f32 - 1e-3);
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let at = |xx: usize, yy: usize| img[yy * w + xx];
    let top = at(x0, y0) * (1.0 - fx) + at(x0 + 1, y0) * fx;
    let bot = at(x0, y0 + 1) * (1.0 - fx) + at(x0 + 1, y0 + 1) * fx;
    top * (1.0 - fy) + bot * fy
}

/// Similarity transform p' = R(theta) (p - c) + c + t.
#[derive(Clone, Copy)]
struct Motion {
    theta_deg: f32,
    c: (f32, f32),
    t: (f32, f32),
}

impl Motion {
    fn apply(&self, (x, y): (f32, f32)) -> (f32, f32) {
        let (s, co) = self.theta_deg.to_radians().sin_cos();
        let (dx, dy) = (x - self.c.0, y - self.c.1);
        (
            co * dx - s * dy + self.c.0 + self.t.0,
            s * dx + co * dy + self.c.1 + self.t.1,
        )
    }
    fn inverse(&self, (x, y): (f32, f32)) -> (f32, f32) {
        let (s, co) = self.theta_deg.to_radians().sin_cos();
        let (dx, dy) = (x - self.c.0 - self.t.0, y - self.c.1 - self.t.1);
        (co * dx + s * dy + self.c.0, -s * dx + co * dy + self.c.1)
    }
}

fn warp(img: &[f32], w: usize, h: usize, m: Motion) -> Vec<u8> {
    let mut out = vec![0u8; w * h];
    for y in 0..h {
        for x in 0..w {
            let (sx, sy) = m.inverse((x as f32, y as f32));
            out[y * w + x] = sample(img, w, h, sx, sy).round().clamp(0.0, 255.0) as u8;
        }
    }
    out
}

fn to_u8(img: &[f32]) -> Vec<u8> {
    img.iter()
        .map(|v| v.round().clamp(0.0, 255.0) as u8)
        .collect()
}

fn extract(px: &[u8], w: usize, h: usize, params: &OrbParams) -> OrbFeatures {
    let mut orb = OrbExtractor::new(params.clone(), w, h).unwrap();
    let mut f = OrbFeatures::default();
    orb.extract(&GrayImage::from_packed(px, w, h).unwrap(), &mut f)
        .unwrap();
    f
}

const W: usize = 480;
const H: usize = 360;

#[test]
fn extractor_basic_properties() {
    let img = to_u8(&scene(W, H, 1));
    let params = OrbParams::default();
    let mut orb = OrbExtractor::new(params.clone(), W, H).unwrap();
    assert_eq!(orb.features_per_level().iter().sum::<usize>(), 1000);
    let view = GrayImage::from_packed(&img, W, H).unwrap();
    let mut f = OrbFeatures::with_capacity(1000);
    let mut t = OrbTimings::default();
    orb.extract_timed(&view, &mut f, &mut t).unwrap();
    assert!(f.len() > 300 && f.len() <= 1000, "{}", f.len());
    assert_eq!(f.keypoints.len(), f.descriptors.len());
    assert!(t.total() > std::time::Duration::ZERO);
    for k in &f.keypoints {
        let s = orb.level_scale(k.octave as usize).unwrap();
        let (lx, ly) = (k.x / s, k.y / s);
        assert!(lx >= 19.0 - 1e-3 && ly >= 19.0 - 1e-3, "{k:?}");
        assert!(
            lx < (W as f32 / s) - 18.0 && ly < (H as f32 / s) - 18.0,
            "{k:?}"
        );
        assert!((0.0..360.0).contains(&k.angle));
        assert!((k.size - 31.0 * s).abs() < 1e-3);
    }
    // Deterministic, and no reallocation of the output once it has grown.
    let (kp_ptr, d_ptr) = (f.keypoints.as_ptr(), f.descriptors.as_ptr());
    let first = f.clone();
    orb.extract(&view, &mut f).unwrap();
    assert_eq!(first.keypoints, f.keypoints);
    assert_eq!(first.descriptors, f.descriptors);
    assert_eq!(
        (kp_ptr, d_ptr),
        (f.keypoints.as_ptr(), f.descriptors.as_ptr())
    );
    // Wrong sizes are errors, not panics.
    let small = GrayImage::from_packed(&img[..100 * 100], 100, 100).unwrap();
    assert!(orb.extract(&small, &mut f).is_err());
    assert!(orb.extract_raw(&img, W, H, W - 1, &mut f).is_err());
    assert!(orb.extract_raw(&img[..W * H - 1], W, H, W, &mut f).is_err());
    assert!(OrbExtractor::new(params.clone(), 30, 300).is_err());
    let bad = OrbParams {
        scale_factor: 1.0,
        ..params
    };
    assert!(OrbExtractor::new(bad, W, H).is_err());
}

#[test]
fn flat_image_gives_no_features() {
    let img = vec![128u8; W * H];
    let f = extract(&img, W, H, &OrbParams::default());
    assert!(f.is_empty());
}

/// Fraction of matches whose second point is within `tol` (scaled by octave) of the first
/// point moved by `m`.
fn geometric_inliers(a: &OrbFeatures, b: &OrbFeatures, matches: &[Match], m: Motion) -> f32 {
    let good = matches
        .iter()
        .filter(|mm| {
            let (p, q) = (
                &a.keypoints[mm.query as usize],
                &b.keypoints[mm.train as usize],
            );
            let (ex, ey) = m.apply((p.x, p.y));
            let tol = 2.5 * (super::ORB_SCALE_FACTOR as f32).powi(p.octave.max(q.octave) as i32);
            (ex - q.x).hypot(ey - q.y) <= tol
        })
        .count();
    good as f32 / matches.len().max(1) as f32
}

#[test]
fn rotated_shifted_image_matches_with_correct_geometry() {
    let base = scene(W, H, 7);
    let m = Motion {
        theta_deg: 30.0,
        c: (W as f32 / 2.0, H as f32 / 2.0),
        t: (12.0, -7.0),
    };
    let (img1, img2) = (to_u8(&base), warp(&base, W, H, m));
    let params = OrbParams::default();
    let (f1, f2) = (extract(&img1, W, H, &params), extract(&img2, W, H, &params));
    let mp = MatchParams {
        max_distance: TH_HIGH,
        ratio: 0.8,
        unique: true,
    };
    let mut matches = Vec::new();
    match_brute_force(&f1.descriptors, &f2.descriptors, &mp, &mut matches);
    assert!(matches.len() > 100, "{} matches", matches.len());
    let ratio = geometric_inliers(&f1, &f2, &matches, m);
    eprintln!(
        "rotated 30 deg: {} matches, geometric inlier ratio {ratio:.3}",
        matches.len()
    );
    assert!(ratio > 0.85, "inlier ratio {ratio} over {}", matches.len());
    // Angles rotate with the image: the difference clusters around -30 degrees.
    let mut close = 0;
    for mm in &matches {
        let (p, q) = (
            &f1.keypoints[mm.query as usize],
            &f2.keypoints[mm.train as usize],
        );
        let d = (q.angle - p.angle - 30.0).rem_euclid(360.0);
        close += (d.min(360.0 - d) < 15.0) as usize;
    }
    assert!(
        close as f32 > 0.8 * matches.len() as f32,
        "{close}/{}",
        matches.len()
    );
    // Unique: no train index twice.
    let mut trains: Vec<u32> = matches.iter().map(|m| m.train).collect();
    trains.sort_unstable();
    trains.dedup();
    assert_eq!(trains.len(), matches.len());
}

#[test]
fn rotation_consistency_removes_injected_wrong_matches() {
    let base = scene(W, H, 11);
    let m = Motion {
        theta_deg: 20.0,
        c: (W as f32 / 2.0, H as f32 / 2.0),
        t: (5.0, 3.0),
    };
    let (img1, img2) = (to_u8(&base), warp(&base, W, H, m));
    let params = OrbParams::default();
    let (f1, f2) = (extract(&img1, W, H, &params), extract(&img2, W, H, &params));
    let mut matches = Vec::new();
    match_brute_force(
        &f1.descriptors,
        &f2.descriptors,
        &MatchParams::default(),
        &mut matches,
    );
    let n_good = matches.len();
    assert!(n_good > 50, "{n_good}");
    // Inject wrong matches whose angle difference is far from the true rotation.
    let mut rng = Lcg(5);
    let mut injected = 0;
    while injected < n_good / 2 {
        let q = rng.range(f1.len() as u32);
        let t = rng.range(f2.len() as u32);
        let d = (f2.keypoints[t as usize].angle - f1.keypoints[q as usize].angle - 20.0)
            .rem_euclid(360.0);
        if d.min(360.0 - d) > 40.0 {
            matches.push(Match {
                query: q,
                train: t,
                distance: 0,
            });
            injected += 1;
        }
    }
    let all = matches.len();
    let removed = rotation_consistency(&mut matches, &f1.keypoints, &f2.keypoints, 30);
    assert_eq!(all - removed, matches.len());
    let wrong_left = matches.iter().filter(|m| m.distance == 0).count();
    assert!(
        wrong_left * 10 <= injected,
        "{wrong_left} of {injected} wrong matches left"
    );
    let good_left = matches.len() - wrong_left;
    eprintln!("rotation check: {wrong_left}/{injected} wrong and {good_left}/{n_good} good left");
    assert!(
        good_left as f32 > 0.8 * n_good as f32,
        "{good_left}/{n_good}"
    );
}

#[test]
fn windowed_matching_on_shifted_frames() {
    let base = scene(W, H, 3);
    let m = Motion {
        theta_deg: 2.0,
        c: (W as f32 / 2.0, H as f32 / 2.0),
        t: (6.0, 4.0),
    };
    let (img1, img2) = (to_u8(&base), warp(&base, W, H, m));
    let params = OrbParams::default();
    let (f1, f2) = (extract(&img1, W, H, &params), extract(&img2, W, H, &params));
    let mut grid = FeatureGrid::new(W, H, 16.0).unwrap();
    grid.build(&f2.keypoints);

    // The grid query returns exactly the brute-force window members.
    let (cx, cy, r) = (200.0, 150.0, 37.0);
    let mut got = Vec::new();
    grid.for_each_in_window(&f2.keypoints, cx, cy, r, 0, 2, |i| got.push(i));
    got.sort_unstable();
    let want: Vec<usize> = (0..f2.len())
        .filter(|&i| {
            let k = &f2.keypoints[i];
            (k.x - cx).abs() <= r && (k.y - cy).abs() <= r && k.octave <= 2
        })
        .collect();
    assert_eq!(got, want);

    let wp = WindowMatchParams {
        radius: 20.0,
        max_octave: 7,
        ..WindowMatchParams::default()
    };
    let mut matches = Vec::new();
    match_two_frames_windowed(&f1, &f2, &grid, None, &wp, &mut matches).unwrap();
    assert!(matches.len() > 100, "{}", matches.len());
    let ratio = geometric_inliers(&f1, &f2, &matches, m);
    eprintln!(
        "windowed: {} matches, geometric inlier ratio {ratio:.3}",
        matches.len()
    );
    assert!(ratio > 0.9, "inlier ratio {ratio}");

    // Single query.
    let k0 = matches[0];
    let p = f1.keypoints[k0.query as usize];
    let d = &f1.descriptors[k0.query as usize];
    let best = match_in_window(&grid, &f2, (p.x, p.y), 20.0, (p.octave, p.octave), d).unwrap();
    assert_eq!(best.index, k0.train as usize);
    assert!(best.distance <= best.second_distance);

    // Wrong number of predictions is an error.
    let preds = vec![[0.0f32; 2]; f1.len() + 1];
    assert!(match_two_frames_windowed(&f1, &f2, &grid, Some(&preds), &wp, &mut matches).is_err());
}

#[test]
fn hamming_counts_bits() {
    let a = [0u8; 32];
    let mut b = [0u8; 32];
    assert_eq!(hamming(&a, &b), 0);
    b[0] = 0b1011;
    b[31] = 0xff;
    assert_eq!(hamming(&a, &b), 11);
    assert_eq!(hamming(&[0xff; 32], &a), 256);
}
