//! `shoal vocab train`: trains the bag-of-words vocabulary of the loop closer on ORB
//! descriptors of real images (PNG files found recursively under the given folders) and of
//! frames of the synthetic scenes rendered in memory, and writes the binary vocabulary file
//! (`slam_core::place` documents the format).

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use datasets::sim::{Scenario, Scene, SimParams, SimWorld};
use slam_core::features::{GrayImage, OrbExtractor, OrbFeatures, OrbParams};
use slam_core::place::{Descriptor, VocabParams, Vocabulary};

/// `shoal vocab ...`.
#[derive(Debug, clap::Subcommand)]
pub enum VocabCommand {
    /// Train a vocabulary from images and write it.
    Train(TrainArgs),
}

/// Arguments of `shoal vocab train`.
#[derive(Debug, Clone, clap::Args)]
pub struct TrainArgs {
    /// Folders searched recursively for PNG images (repeatable, or several after one flag).
    #[arg(long = "images", num_args = 1..)]
    pub images: Vec<PathBuf>,
    /// Output vocabulary file.
    #[arg(long)]
    pub out: PathBuf,
    /// Branching factor.
    #[arg(long, default_value_t = 10)]
    pub k: usize,
    /// Depth of the tree.
    #[arg(long, default_value_t = 5)]
    pub depth: usize,
    /// ORB features per image.
    #[arg(long, default_value_t = 1000)]
    pub features: usize,
    /// Use at most this many real images (evenly spaced over the sorted list).
    #[arg(long)]
    pub max_images: Option<usize>,
    /// Seed of the clustering, the subsampling and the synthetic scenes (scene seeds are
    /// seed + 100 and seed + 101, so the default avoids the tests' seed 3).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Also render this many synthetic frames (a third from `loop`, a third from each agent
    /// of `two-agents`, evenly spaced in time).
    #[arg(long, default_value_t = 0)]
    pub synthetic: usize,
    /// Cluster at most this many descriptors (uniform subsample; idf uses every image).
    #[arg(long, default_value_t = 300_000)]
    pub max_descriptors: usize,
}

/// Runs a `shoal vocab` subcommand.
pub fn run(cmd: &VocabCommand) -> anyhow::Result<()> {
    match cmd {
        VocabCommand::Train(a) => train(a),
    }
}

fn collect_pngs(dir: &Path, out: &mut Vec<PathBuf>) -> anyhow::Result<()> {
    let entries =
        std::fs::read_dir(dir).with_context(|| format!("reading folder {}", dir.display()))?;
    for e in entries {
        let p = e?.path();
        if p.is_dir() {
            collect_pngs(&p, out)?;
        } else if p.extension().is_some_and(|x| x.eq_ignore_ascii_case("png")) {
            out.push(p);
        }
    }
    Ok(())
}

/// ORB extraction with one extractor per image size.
struct Extractors {
    params: OrbParams,
    by_size: HashMap<(usize, usize), OrbExtractor>,
    feats: OrbFeatures,
}

impl Extractors {
    fn descriptors(
        &mut self,
        pixels: &[u8],
        w: usize,
        h: usize,
    ) -> anyhow::Result<Vec<Descriptor>> {
        let orb = match self.by_size.entry((w, h)) {
            std::collections::hash_map::Entry::Occupied(o) => o.into_mut(),
            std::collections::hash_map::Entry::Vacant(v) => {
                v.insert(OrbExtractor::new(self.params.clone(), w, h)?)
            }
        };
        let img = GrayImage::from_packed(pixels, w, h)?;
        orb.extract(&img, &mut self.feats)?;
        Ok(self.feats.descriptors.clone())
    }
}

/// Renders `n` frames evenly spaced over one agent's sequence.
fn synthetic_frames(
    scenario: Scenario,
    agent: usize,
    scene: &std::sync::Arc<Scene>,
    seed: u64,
    n: usize,
    ex: &mut Extractors,
    out: &mut Vec<Vec<Descriptor>>,
) -> anyhow::Result<()> {
    if n == 0 {
        return Ok(());
    }
    let mut p = SimParams::new(scenario);
    p.seed = seed;
    let world = SimWorld::with_scene(p, agent, scene.clone())?;
    let (w, h) = (
        world.camera().width as usize,
        world.camera().height as usize,
    );
    let mut img = vec![0u8; w * h];
    let total = world.n_frames();
    for i in 0..n {
        let k = i * total / n;
        world.render_frame_into(k, &mut img)?;
        out.push(ex.descriptors(&img, w, h)?);
    }
    Ok(())
}

/// The PNG files under `a.images`, sorted, thinned evenly to `--max-images`.
fn training_images(a: &TrainArgs) -> anyhow::Result<Vec<std::path::PathBuf>> {
    let mut paths = Vec::new();
    for d in &a.images {
        collect_pngs(d, &mut paths)?;
    }
    paths.sort();
    if let Some(m) = a.max_images {
        if paths.len() > m {
            let n = paths.len();
            paths = (0..m).map(|i| paths[i * n / m].clone()).collect();
        }
    }
    Ok(paths)
}

/// ORB descriptors of `a.synthetic` frames of the synthetic scenes (a third of them of
/// the `loop` room, the rest of the two agents' room), appended to `images`.
fn synthetic_descriptors(
    a: &TrainArgs,
    ex: &mut Extractors,
    images: &mut Vec<Vec<Descriptor>>,
) -> anyhow::Result<()> {
    let third = a.synthetic / 3;
    let loop_scene = std::sync::Arc::new(Scene::room(a.seed + 100));
    let n_loop = a.synthetic - 2 * third;
    synthetic_frames(
        Scenario::Loop,
        0,
        &loop_scene,
        a.seed + 100,
        n_loop,
        ex,
        images,
    )?;
    let two_scene = std::sync::Arc::new(Scene::room(a.seed + 101));
    for agent in 0..2 {
        let seed = a.seed + 101;
        synthetic_frames(
            Scenario::TwoAgents,
            agent,
            &two_scene,
            seed,
            third,
            ex,
            images,
        )?;
    }
    Ok(())
}

fn train(a: &TrainArgs) -> anyhow::Result<()> {
    let t0 = Instant::now();
    let paths = training_images(a)?;
    if paths.is_empty() && a.synthetic == 0 {
        anyhow::bail!("no image: give --images folders with PNG files and/or --synthetic N");
    }
    let mut ex = Extractors {
        params: OrbParams {
            n_features: a.features,
            ..OrbParams::default()
        },
        by_size: HashMap::new(),
        feats: OrbFeatures::with_capacity(a.features),
    };
    let mut images: Vec<Vec<Descriptor>> = Vec::new();
    for p in &paths {
        let (w, h, px) = datasets::decode_gray(p)?;
        images.push(
            ex.descriptors(&px, w as usize, h as usize)
                .with_context(|| format!("ORB on {}", p.display()))?,
        );
    }
    let n_real = images.len();
    if a.synthetic > 0 {
        synthetic_descriptors(a, &mut ex, &mut images)?;
    }
    let n_desc: usize = images.iter().map(Vec::len).sum();
    let t_extract = t0.elapsed();
    let params = VocabParams {
        k: a.k,
        depth: a.depth,
        seed: a.seed,
        max_descriptors: a.max_descriptors,
        ..VocabParams::default()
    };
    let t1 = Instant::now();
    let voc = Vocabulary::train(&images, &params)?;
    let t_train = t1.elapsed();
    if let Some(dir) = a.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    voc.save(&a.out)?;
    let size = std::fs::metadata(&a.out)?.len();
    println!(
        "images: {} real + {} synthetic; descriptors: {} ({} clustered)",
        n_real,
        images.len() - n_real,
        n_desc,
        n_desc.min(if a.max_descriptors == 0 {
            usize::MAX
        } else {
            a.max_descriptors
        })
    );
    println!(
        "vocabulary: k = {}, depth = {}, {} words, {} nodes",
        voc.k(),
        voc.depth(),
        voc.n_words(),
        voc.n_nodes()
    );
    println!(
        "time: extraction {:.1} s, training {:.1} s; file {} ({:.2} MB)",
        t_extract.as_secs_f64(),
        t_train.as_secs_f64(),
        a.out.display(),
        size as f64 / 1e6
    );
    Ok(())
}
