//! `shoal bench map FILE`: save and load times and file size of a saved-map file, scaled
//! per 1,000 keyframes (BENCHMARKS.md "Saved maps").
use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use map_store::{MapFile, SavedMap};

/// Arguments of `shoal bench map`.
#[derive(clap::Args, Debug)]
pub struct MapArgs {
    /// A saved-map file (`shoal run --save-map`).
    file: PathBuf,
    /// Measure a file made of this many copies of its maps, each copy with clients of its
    /// own (e.g. 8 copies of a 130-keyframe run: about 1,000 keyframes).
    #[arg(long, default_value_t = 1)]
    copies: u32,
    /// Repetitions; the median is reported.
    #[arg(long, default_value_t = 5)]
    repeat: usize,
    /// Where the measured file is written and kept (default: beside FILE, `.bench`
    /// appended, removed at the end).
    #[arg(long)]
    out: Option<PathBuf>,
}

/// `copies` copies of `file`'s maps, copy `i` with its clients renamed from `i · n`.
fn copies_of(file: &MapFile, copies: u32) -> MapFile {
    let mut all: Vec<SavedMap> = Vec::new();
    let feature_level = file.feature_level;
    for i in 0..copies {
        let mut copy = file.clone();
        map_store::remap::remap_clients_from(&mut copy, 1 + i * 64);
        all.extend(copy.maps);
    }
    all.sort_by_key(|m| m.map.id);
    MapFile {
        feature_level,
        maps: all,
    }
}

fn median_ms(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

/// Runs `f` `n` times; the median wall time, ms.
fn timed(n: usize, mut f: impl FnMut() -> anyhow::Result<()>) -> anyhow::Result<f64> {
    let mut t = Vec::with_capacity(n);
    for _ in 0..n.max(1) {
        let t0 = Instant::now();
        f()?;
        t.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    Ok(median_ms(t))
}

/// Measures and prints (module docs).
pub fn run(a: &MapArgs) -> anyhow::Result<()> {
    let (header, file) = map_store::read(&a.file)?;
    let file = copies_of(&file, a.copies.max(1));
    let out = a.out.clone().unwrap_or_else(|| {
        let mut p = a.file.clone().into_os_string();
        p.push(".bench");
        PathBuf::from(p)
    });
    let vocabulary = slam_core::place::Vocabulary::from_bytes(map_store::SHIPPED_VOCABULARY)
        .context("the built-in vocabulary")?;
    let vocab_id = map_store::vocabulary_id(map_store::SHIPPED_VOCABULARY);
    let maps: Vec<slam_core::server::ServerMap> = file.maps.iter().map(|m| m.map.clone()).collect();
    let kfs = file.keyframes();
    let version = env!("CARGO_PKG_VERSION");
    let level = mapper::saved::feature_level();
    // The mapper's save: BoW vectors, encoding, atomic write with fsync.
    let mut bytes = 0;
    let save_ms = timed(a.repeat, || {
        let f = MapFile::from_maps(maps.iter(), &vocabulary, level);
        bytes = map_store::write(&out, &f, vocab_id, version)?;
        Ok(())
    })?;
    let bow_ms = timed(a.repeat, || {
        MapFile::from_maps(maps.iter(), &vocabulary, level);
        Ok(())
    })?;
    // The launcher's check and the mapper's load: read, checksum, decode, validate, remap.
    let load_ms = timed(a.repeat, || {
        map_store::load(&out)?;
        Ok(())
    })?;
    // The loop closer's load: the same, then every keyframe's BoW vector and insertion.
    let cfg = loop_closer::LoopCloserConfig::default();
    let vocab = loop_closer::saved::vocabulary_id(&cfg);
    let closer_ms = timed(a.repeat, || {
        let mut closer = loop_closer::Closer::new(loop_closer::vocabulary(&cfg)?, cfg.method);
        loop_closer::saved::load(&mut closer, &out, vocab, false)?;
        Ok(())
    })?;
    if a.out.is_none() {
        let _ = std::fs::remove_file(&out);
    }
    let per_k = 1000.0 / kfs.max(1) as f64;
    println!(
        "{}: format {}, {} maps, {kfs} keyframes, {} points ({} copies)",
        a.file.display(),
        header.format_version,
        file.maps.len(),
        file.points(),
        a.copies.max(1)
    );
    println!("                          measured   per 1,000 keyframes");
    println!(
        "file size, MB            {:9.2}   {:9.2}",
        bytes as f64 / 1e6,
        bytes as f64 / 1e6 * per_k
    );
    println!(
        "save (mapper), ms        {save_ms:9.1}   {:9.1}",
        save_ms * per_k
    );
    println!(
        "  of which BoW vectors   {bow_ms:9.1}   {:9.1}",
        bow_ms * per_k
    );
    println!(
        "load (launcher, mapper)  {load_ms:9.1}   {:9.1}",
        load_ms * per_k
    );
    println!(
        "load (loop closer), ms   {closer_ms:9.1}   {:9.1}",
        closer_ms * per_k
    );
    Ok(())
}
