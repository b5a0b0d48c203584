//! The hierarchical vocabulary tree: training (k-means++ seeding, k-majority centroids,
//! Hamming distance), word lookup and tf-idf bag-of-words vectors.

use crate::features::hamming;
use crate::CoreError;

use super::bow::{BowVector, FeatureVector};

/// A 256-bit ORB descriptor.
pub type Descriptor = [u8; 32];

/// Marks a node that is not a leaf in [`Node::word`].
pub(crate) const NO_WORD: u32 = u32::MAX;

/// Training parameters of a [`Vocabulary`].
#[derive(Debug, Clone, PartialEq)]
pub struct VocabParams {
    /// Branching factor (children per node), 2..=255.
    pub k: usize,
    /// Depth of the tree (levels below the root), 1..=8.
    pub depth: usize,
    /// Seed of the k-means++ seeding and of the descriptor subsampling.
    pub seed: u64,
    /// At most this many k-majority iterations per node.
    pub max_iterations: usize,
    /// Cluster at most this many descriptors (a deterministic uniform subsample); the idf
    /// weights still use every image. `0` = all.
    pub max_descriptors: usize,
}

impl Default for VocabParams {
    fn default() -> Self {
        Self {
            k: 10,
            depth: 5,
            seed: 1,
            max_iterations: 15,
            max_descriptors: 0,
        }
    }
}

/// One node of the tree. Children of a node are contiguous (`first_child..first_child +
/// n_children`) and nodes are stored breadth-first; the root is node 0.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Node {
    /// Cluster centre (k-majority of its members).
    pub desc: Descriptor,
    /// Index of the first child (meaningless when `n_children == 0`).
    pub first_child: u32,
    /// Number of children (0 for a leaf).
    pub n_children: u8,
    /// Depth below the root (root = 0).
    pub level: u8,
    /// Word id of a leaf, [`NO_WORD`] otherwise.
    pub word: u32,
}

/// A hierarchical bag-of-words vocabulary of binary descriptors (Gálvez-López & Tardós
/// 2012): leaves are words, each with an idf weight `ln(N / n_i)` (N training images, `n_i`
/// of them containing the word).
#[derive(Debug, Clone, PartialEq)]
pub struct Vocabulary {
    pub(crate) k: usize,
    pub(crate) depth: usize,
    pub(crate) nodes: Vec<Node>,
    /// idf weight of each word.
    pub(crate) weights: Vec<f32>,
    /// Node index of each word.
    pub(crate) word_nodes: Vec<u32>,
}

/// Small deterministic generator (splitmix64) for seeding and subsampling.
struct SplitMix(u64);

impl SplitMix {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    /// Uniform in `[0, 1)`.
    fn uniform(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }
    fn below(&mut self, n: usize) -> usize {
        (self.uniform() * n as f64) as usize % n.max(1)
    }
}

/// k-majority centre: bit `b` is set when more than half of the members have it set (ties
/// give 0, as in DBoW2's binary mean).
fn majority(descs: &[Descriptor], members: &[u32]) -> Descriptor {
    let mut counts = [0u32; 256];
    for &m in members {
        let d = &descs[m as usize];
        for (byte, &v) in d.iter().enumerate() {
            let c = &mut counts[byte * 8..byte * 8 + 8];
            for (bit, cnt) in c.iter_mut().enumerate() {
                *cnt += u32::from((v >> (7 - bit)) & 1);
            }
        }
    }
    let half = members.len() as u32;
    let mut out = [0u8; 32];
    for (byte, o) in out.iter_mut().enumerate() {
        for bit in 0..8 {
            if 2 * counts[byte * 8 + bit] > half {
                *o |= 1 << (7 - bit);
            }
        }
    }
    out
}

/// Index of the centre nearest to `d` (first one on ties).
#[inline]
fn nearest(centres: &[Descriptor], d: &Descriptor) -> usize {
    let mut best = 0;
    let mut best_d = u32::MAX;
    for (i, c) in centres.iter().enumerate() {
        let dist = hamming(c, d);
        if dist < best_d {
            best_d = dist;
            best = i;
        }
    }
    best
}

/// Clusters `members` into at most `k` groups: k-means++ seeding, then k-majority
/// iterations until the assignment no longer changes. Returns the centres and their
/// (non-empty) member lists.
fn kmeans(
    descs: &[Descriptor],
    members: &[u32],
    k: usize,
    max_iterations: usize,
    rng: &mut SplitMix,
) -> Vec<(Descriptor, Vec<u32>)> {
    if members.len() <= k {
        // Every descriptor is its own cluster.
        return members
            .iter()
            .map(|&m| (descs[m as usize], vec![m]))
            .collect();
    }
    // k-means++: each next centre drawn with probability proportional to D(x)^2.
    let mut centres: Vec<Descriptor> = Vec::with_capacity(k);
    centres.push(descs[members[rng.below(members.len())] as usize]);
    let mut min_d: Vec<f64> = members
        .iter()
        .map(|&m| f64::from(hamming(&centres[0], &descs[m as usize])))
        .collect();
    while centres.len() < k {
        let total: f64 = min_d.iter().map(|d| d * d).sum();
        if total <= 0.0 {
            break; // all remaining descriptors equal a centre
        }
        let mut target = rng.uniform() * total;
        let mut pick = members.len() - 1;
        for (i, d) in min_d.iter().enumerate() {
            target -= d * d;
            if target <= 0.0 && *d > 0.0 {
                pick = i;
                break;
            }
        }
        let c = descs[members[pick] as usize];
        for (md, &m) in min_d.iter_mut().zip(members) {
            *md = md.min(f64::from(hamming(&c, &descs[m as usize])));
        }
        centres.push(c);
    }
    let mut assign: Vec<usize> = vec![usize::MAX; members.len()];
    for _ in 0..max_iterations.max(1) {
        let mut changed = false;
        for (a, &m) in assign.iter_mut().zip(members) {
            let n = nearest(&centres, &descs[m as usize]);
            if *a != n {
                *a = n;
                changed = true;
            }
        }
        if !changed {
            break;
        }
        let mut groups: Vec<Vec<u32>> = vec![Vec::new(); centres.len()];
        for (&a, &m) in assign.iter().zip(members) {
            groups[a].push(m);
        }
        for (c, g) in centres.iter_mut().zip(&groups) {
            if !g.is_empty() {
                *c = majority(descs, g);
            }
        }
    }
    let mut groups: Vec<Vec<u32>> = vec![Vec::new(); centres.len()];
    for (&a, &m) in assign.iter().zip(members) {
        groups[a].push(m);
    }
    centres
        .into_iter()
        .zip(groups)
        .filter(|(_, g)| !g.is_empty())
        .collect()
}

impl Vocabulary {
    /// Trains a vocabulary on the descriptors of `images` (one slice per training image;
    /// the image grouping gives the idf weights). Deterministic for a given `params.seed`.
    pub fn train(images: &[Vec<Descriptor>], params: &VocabParams) -> Result<Self, CoreError> {
        if !(2..=255).contains(&params.k) {
            return Err(CoreError::InvalidArgument(format!(
                "vocabulary branching k = {} outside 2..=255",
                params.k
            )));
        }
        if !(1..=8).contains(&params.depth) {
            return Err(CoreError::InvalidArgument(format!(
                "vocabulary depth = {} outside 1..=8",
                params.depth
            )));
        }
        let mut descs: Vec<Descriptor> = images.iter().flatten().copied().collect();
        if descs.is_empty() {
            return Err(CoreError::NotEnoughData(
                "no descriptor to train a vocabulary".into(),
            ));
        }
        let mut rng = SplitMix(params.seed);
        if params.max_descriptors > 0 && descs.len() > params.max_descriptors {
            // Partial Fisher-Yates: a uniform subsample, deterministic for the seed.
            for i in 0..params.max_descriptors {
                let j = i + rng.below(descs.len() - i);
                descs.swap(i, j);
            }
            descs.truncate(params.max_descriptors);
        }
        let all: Vec<u32> = (0..descs.len() as u32).collect();
        let mut nodes = vec![Node {
            desc: [0; 32],
            first_child: 0,
            n_children: 0,
            level: 0,
            word: NO_WORD,
        }];
        // Breadth-first: the queue order equals the node order, so children blocks are
        // stored in the order of their parents (what the file format relies on).
        let mut queue = std::collections::VecDeque::new();
        queue.push_back((0usize, all));
        while let Some((id, members)) = queue.pop_front() {
            let level = nodes[id].level as usize;
            if level >= params.depth || members.len() <= 1 {
                continue;
            }
            let clusters = kmeans(&descs, &members, params.k, params.max_iterations, &mut rng);
            nodes[id].first_child = nodes.len() as u32;
            nodes[id].n_children = clusters.len() as u8;
            for (c, g) in clusters {
                let child = nodes.len();
                nodes.push(Node {
                    desc: c,
                    first_child: 0,
                    n_children: 0,
                    level: (level + 1) as u8,
                    word: NO_WORD,
                });
                queue.push_back((child, g));
            }
        }
        let mut voc = Self::from_nodes(params.k, params.depth, nodes, Vec::new())?;
        // idf over every training image (not only the clustered subsample).
        let mut n_images_with = vec![0u32; voc.n_words()];
        let mut seen = vec![u32::MAX; voc.n_words()];
        let mut n_images = 0u32;
        for (i, img) in images.iter().enumerate() {
            if img.is_empty() {
                continue;
            }
            n_images += 1;
            for d in img {
                let w = voc.word_of(d) as usize;
                if seen[w] != i as u32 {
                    seen[w] = i as u32;
                    n_images_with[w] += 1;
                }
            }
        }
        let n = f64::from(n_images.max(1));
        voc.weights = n_images_with
            .iter()
            .map(|&c| {
                if c == 0 {
                    n.ln() as f32
                } else {
                    (n / f64::from(c)).ln() as f32
                }
            })
            .collect();
        Ok(voc)
    }

    /// Builds the derived tables (word ids in node order) from a node list; `weights` empty
    /// means "all 1". Validates the structure.
    pub(crate) fn from_nodes(
        k: usize,
        depth: usize,
        mut nodes: Vec<Node>,
        weights: Vec<f32>,
    ) -> Result<Self, CoreError> {
        let mut word_nodes = Vec::new();
        for (i, n) in nodes.iter_mut().enumerate() {
            if n.n_children == 0 {
                n.first_child = 0;
                n.word = word_nodes.len() as u32;
                word_nodes.push(i as u32);
            } else {
                n.word = NO_WORD;
            }
        }
        if word_nodes.is_empty() || nodes.len() < 2 {
            return Err(CoreError::NotEnoughData(
                "vocabulary has no word below the root".into(),
            ));
        }
        let weights = if weights.is_empty() {
            vec![1.0; word_nodes.len()]
        } else {
            weights
        };
        if weights.len() != word_nodes.len() {
            return Err(CoreError::InvalidArgument(format!(
                "{} word weights for {} words",
                weights.len(),
                word_nodes.len()
            )));
        }
        Ok(Self {
            k,
            depth,
            nodes,
            weights,
            word_nodes,
        })
    }

    /// Branching factor it was trained with.
    pub fn k(&self) -> usize {
        self.k
    }

    /// Depth it was trained with (leaves may be shallower).
    pub fn depth(&self) -> usize {
        self.depth
    }

    /// Number of words (leaves).
    pub fn n_words(&self) -> usize {
        self.word_nodes.len()
    }

    /// Number of nodes, root included.
    pub fn n_nodes(&self) -> usize {
        self.nodes.len()
    }

    /// idf weight of `word` (`None` if out of range).
    pub fn word_weight(&self, word: u32) -> Option<f32> {
        self.weights.get(word as usize).copied()
    }

    /// Descends the tree to the word of `d`; also returns the node passed at `level`
    /// (or the leaf if it is shallower).
    #[inline]
    fn descend(&self, d: &Descriptor, level: usize) -> (u32, u32) {
        let mut id = 0usize;
        let mut at_level = 0u32;
        loop {
            let n = &self.nodes[id];
            if n.level as usize == level {
                at_level = id as u32;
            }
            if n.n_children == 0 {
                if (n.level as usize) < level {
                    at_level = id as u32;
                }
                return (n.word, at_level);
            }
            let first = n.first_child as usize;
            let mut best = first;
            let mut best_d = u32::MAX;
            for c in first..first + n.n_children as usize {
                let dist = hamming(&self.nodes[c].desc, d);
                if dist < best_d {
                    best_d = dist;
                    best = c;
                }
            }
            id = best;
        }
    }

    /// The word of one descriptor.
    pub fn word_of(&self, d: &Descriptor) -> u32 {
        self.descend(d, 0).0
    }

    /// Bag-of-words vector of an image: word → tf-idf weight, L1-normalised.
    pub fn transform(&self, descs: &[Descriptor]) -> BowVector {
        let mut entries: Vec<(u32, f32)> = descs
            .iter()
            .map(|d| {
                let w = self.word_of(d);
                (w, self.weights[w as usize])
            })
            .collect();
        BowVector::from_unsorted(&mut entries)
    }

    /// Bag-of-words vector plus a [`FeatureVector`] grouping feature indices by their
    /// ancestor node at `level` (1 = children of the root; DBoW2 uses depth − 4 or so for
    /// guided matching: features can only match inside one group).
    pub fn transform_with_features(
        &self,
        descs: &[Descriptor],
        level: usize,
    ) -> (BowVector, FeatureVector) {
        let mut entries = Vec::with_capacity(descs.len());
        let mut groups: Vec<(u32, u32)> = Vec::with_capacity(descs.len());
        for (i, d) in descs.iter().enumerate() {
            let (w, node) = self.descend(d, level);
            entries.push((w, self.weights[w as usize]));
            groups.push((node, i as u32));
        }
        (
            BowVector::from_unsorted(&mut entries),
            FeatureVector::from_pairs(groups),
        )
    }
}
