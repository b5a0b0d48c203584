//! Criterion benchmark of ORB extraction and matching on real images (skipped when absent).

use criterion::{criterion_group, criterion_main, Criterion};
use slam_core::features::{
    match_brute_force, GrayImage, MatchParams, OrbExtractor, OrbFeatures, OrbParams,
};

fn load(path: &str) -> Option<(Vec<u8>, usize, usize)> {
    let img = image::open(path).ok()?.to_luma8();
    let (w, h) = (img.width() as usize, img.height() as usize);
    Some((img.into_raw(), w, h))
}

/// `$SHOAL_DATA`, else `<workspace>/../shared/data`.
fn data_dir() -> std::path::PathBuf {
    match std::env::var_os("SHOAL_DATA") {
        Some(d) => d.into(),
        None => std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data"),
    }
}

fn euroc_image() -> Option<String> {
    let dir = data_dir().join("euroc_v101_static/mav0/cam0/data");
    let mut names: Vec<_> = std::fs::read_dir(dir)
        .ok()?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "png"))
        .collect();
    names.sort();
    names.first().map(|p| p.to_string_lossy().into_owned())
}

fn bench_orb(c: &mut Criterion) {
    let kitti = data_dir().join("kitti07/image_0/000000.png");
    let images = [
        ("euroc_752x480", euroc_image()),
        ("kitti_1226x370", Some(kitti.to_string_lossy().into_owned())),
    ];
    for (name, path) in images {
        let Some((px, w, h)) = path.as_deref().and_then(load) else {
            eprintln!(
                "bench_orb: {name} image not found under {:?}, skipped",
                data_dir()
            );
            continue;
        };
        let Ok(img) = GrayImage::from_packed(&px, w, h) else {
            continue;
        };
        let Ok(mut orb) = OrbExtractor::new(OrbParams::default(), w, h) else {
            continue;
        };
        let mut feats = OrbFeatures::with_capacity(1000);
        c.bench_function(&format!("orb_extract_{name}"), |b| {
            b.iter(|| orb.extract(&img, &mut feats))
        });
        let mut matches = Vec::new();
        let params = MatchParams::default();
        c.bench_function(&format!("match_brute_force_{name}"), |b| {
            b.iter(|| {
                match_brute_force(
                    &feats.descriptors,
                    &feats.descriptors,
                    &params,
                    &mut matches,
                )
            })
        });
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(50);
    targets = bench_orb
}
criterion_main!(benches);
