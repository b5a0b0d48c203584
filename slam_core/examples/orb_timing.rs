//! ORB extraction timings per stage, and a dump of keypoints + descriptors for comparisons.
//!
//! ```text
//! cargo run --release -p slam_core --example orb_timing -- [--runs N] [--features N] IMG.png...
//! cargo run --release -p slam_core --example orb_timing -- --dump IMG.png OUT.txt
//! cargo run --release -p slam_core --example orb_timing -- --match A.png B.png OUT.txt
//! ```
//! The dump has one line per keypoint: `x y octave angle response size hex(descriptor)`.
//! `--match` writes `x1 y1 x2 y2 distance` per match of A to B (brute force, ratio 0.8, then
//! the rotation-consistency filter).

use std::io::Write;
use std::time::{Duration, Instant};

use slam_core::features::{
    match_brute_force, rotation_consistency, GrayImage, MatchParams, OrbExtractor, OrbFeatures,
    OrbParams, OrbTimings,
};

type AnyResult<T> = Result<T, Box<dyn std::error::Error>>;

fn load(path: &str) -> AnyResult<(Vec<u8>, usize, usize)> {
    let img = image::open(path)?.to_luma8();
    let (w, h) = (img.width() as usize, img.height() as usize);
    Ok((img.into_raw(), w, h))
}

fn extract(path: &str, params: &OrbParams) -> AnyResult<OrbFeatures> {
    let (px, w, h) = load(path)?;
    let mut orb = OrbExtractor::new(params.clone(), w, h)?;
    let mut f = OrbFeatures::with_capacity(params.n_features);
    orb.extract(&GrayImage::from_packed(&px, w, h)?, &mut f)?;
    Ok(f)
}

fn hex(d: &[u8; 32]) -> String {
    d.iter().map(|b| format!("{b:02x}")).collect()
}

fn dump(path: &str, out: &str, params: &OrbParams) -> AnyResult<()> {
    let f = extract(path, params)?;
    let mut file = std::io::BufWriter::new(std::fs::File::create(out)?);
    for (k, d) in f.keypoints.iter().zip(&f.descriptors) {
        writeln!(
            file,
            "{} {} {} {} {} {} {}",
            k.x,
            k.y,
            k.octave,
            k.angle,
            k.response,
            k.size,
            hex(d)
        )?;
    }
    eprintln!("{path}: {} keypoints -> {out}", f.len());
    Ok(())
}

fn match_pair(a: &str, b: &str, out: &str, params: &OrbParams) -> AnyResult<()> {
    let (fa, fb) = (extract(a, params)?, extract(b, params)?);
    let mp = MatchParams {
        ratio: 0.8,
        max_distance: 100,
        ..MatchParams::default()
    };
    let mut matches = Vec::new();
    match_brute_force(&fa.descriptors, &fb.descriptors, &mp, &mut matches);
    let before = matches.len();
    rotation_consistency(&mut matches, &fa.keypoints, &fb.keypoints, 30);
    let mut file = std::io::BufWriter::new(std::fs::File::create(out)?);
    for m in &matches {
        let (p, q) = (
            &fa.keypoints[m.query as usize],
            &fb.keypoints[m.train as usize],
        );
        writeln!(file, "{} {} {} {} {}", p.x, p.y, q.x, q.y, m.distance)?;
    }
    eprintln!(
        "{} x {} features, {before} matches, {} after rotation check -> {out}",
        fa.len(),
        fb.len(),
        matches.len()
    );
    Ok(())
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

fn time(path: &str, runs: usize, params: &OrbParams) -> AnyResult<()> {
    let (px, w, h) = load(path)?;
    let img = GrayImage::from_packed(&px, w, h)?;
    let mut orb = OrbExtractor::new(params.clone(), w, h)?;
    let mut f = OrbFeatures::with_capacity(params.n_features);
    for _ in 0..5 {
        orb.extract(&img, &mut f)?;
    }
    let mut cols: [Vec<f64>; 5] = Default::default();
    for _ in 0..runs {
        let mut t = OrbTimings::default();
        let start = Instant::now();
        orb.extract_timed(&img, &mut f, &mut t)?;
        cols[0].push(ms(start.elapsed()));
        cols[1].push(ms(t.pyramid));
        cols[2].push(ms(t.detect));
        cols[3].push(ms(t.orient));
        cols[4].push(ms(t.describe));
    }
    let min = cols[0].iter().copied().fold(f64::INFINITY, f64::min);
    let [tot, pyr, det, ori, des] = cols.each_mut().map(|c| median(c));
    println!(
        "{path} {w}x{h}: {} kps, median total {tot:.3} ms, min {min:.3} ms (median stages: \
         pyramid {pyr:.3}, detect {det:.3}, orient {ori:.3}, describe {des:.3})",
        f.len()
    );
    Ok(())
}

fn main() -> AnyResult<()> {
    let mut args = std::env::args().skip(1).collect::<Vec<_>>();
    let mut params = OrbParams::default();
    let mut runs = 100;
    let take = |flag: &str, args: &mut Vec<String>| -> Option<String> {
        let i = args.iter().position(|a| a == flag)?;
        args.remove(i);
        (i < args.len()).then(|| args.remove(i))
    };
    if let Some(n) = take("--runs", &mut args) {
        runs = n.parse()?;
    }
    if let Some(n) = take("--features", &mut args) {
        params.n_features = n.parse()?;
    }
    if let Some(n) = take("--bins", &mut args) {
        params.angle_bins = n.parse()?;
    }
    if let Some(n) = take("--share", &mut args) {
        params.level_share_exponent = n.parse()?;
    }
    match args.first().map(String::as_str) {
        Some("--dump") if args.len() == 3 => dump(&args[1], &args[2], &params),
        Some("--match") if args.len() == 4 => match_pair(&args[1], &args[2], &args[3], &params),
        Some(_) => {
            for p in &args {
                time(p, runs, &params)?;
            }
            Ok(())
        }
        None => {
            Err("usage: orb_timing [--runs N] IMG... | --dump IMG OUT | --match A B OUT".into())
        }
    }
}
