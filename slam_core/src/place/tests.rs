//! Unit tests of the vocabulary, its file format and the keyframe database.

use super::*;
use crate::features::hamming;
use crate::CoreError;

/// Deterministic test generator.
struct Lcg(u64);
impl Lcg {
    fn next(&mut self) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        self.0 >> 11
    }
    fn desc(&mut self) -> Descriptor {
        std::array::from_fn(|_| self.next() as u8)
    }
    /// `d` with `n` random bits flipped.
    fn noisy(&mut self, d: &Descriptor, n: usize) -> Descriptor {
        let mut o = *d;
        for _ in 0..n {
            let b = (self.next() % 256) as usize;
            o[b / 8] ^= 1 << (b % 8);
        }
        o
    }
}

/// A true centre and its noisy members.
type Cluster = (Descriptor, Vec<Descriptor>);

/// `n_clusters` random centres, `per` members each (up to 12 flipped bits), spread over
/// `n_images` images. Returns the images and, per cluster, its centre and members.
fn clustered(
    n_clusters: usize,
    per: usize,
    n_images: usize,
    seed: u64,
) -> (Vec<Vec<Descriptor>>, Vec<Cluster>) {
    let mut rng = Lcg(seed);
    let mut images = vec![Vec::new(); n_images];
    let mut clusters = Vec::new();
    for _ in 0..n_clusters {
        let c = rng.desc();
        let members: Vec<Descriptor> = (0..per).map(|_| rng.noisy(&c, 12)).collect();
        for (i, m) in members.iter().enumerate() {
            images[i % n_images].push(*m);
        }
        clusters.push((c, members));
    }
    (images, clusters)
}

#[test]
fn training_recovers_clusters() {
    let (images, clusters) = clustered(10, 60, 6, 11);
    let params = VocabParams {
        k: 10,
        depth: 1,
        ..VocabParams::default()
    };
    let voc = Vocabulary::train(&images, &params).unwrap();
    assert_eq!(voc.n_words(), 10);
    let mut words = Vec::new();
    for (centre, members) in &clusters {
        let w = voc.word_of(&members[0]);
        assert!(members.iter().all(|m| voc.word_of(m) == w), "cluster split");
        // The k-majority centre is the true centre (or within a bit or two of it).
        let node = voc.word_nodes[w as usize] as usize;
        assert!(hamming(&voc.nodes[node].desc, centre) <= 2);
        words.push(w);
    }
    words.sort_unstable();
    words.dedup();
    assert_eq!(words.len(), 10, "clusters merged");
}

#[test]
fn deeper_tree_keeps_clusters_under_one_top_node_and_is_deterministic() {
    let (images, clusters) = clustered(5, 200, 10, 5);
    let params = VocabParams {
        k: 5,
        depth: 3,
        seed: 42,
        ..VocabParams::default()
    };
    let voc = Vocabulary::train(&images, &params).unwrap();
    assert!(voc.n_words() > 5 && voc.n_words() <= 125);
    for (_, members) in &clusters {
        let (_, fv) = voc.transform_with_features(members, 1);
        assert_eq!(fv.groups().len(), 1, "one level-1 node per cluster");
        assert_eq!(fv.groups()[0].1.len(), members.len());
    }
    let again = Vocabulary::train(&images, &params).unwrap();
    assert_eq!(voc, again);
    // Every word occurs in every image here: idf 0 would make all vectors empty; words are
    // fine-grained enough at depth 3 that some idf is positive.
    assert!(voc.weights.iter().any(|&w| w > 0.0));
}

#[test]
fn idf_weights_follow_image_counts() {
    // Cluster A in every image, cluster B in one image of four.
    let mut rng = Lcg(3);
    let (a, b) = (rng.desc(), rng.desc());
    let mut images: Vec<Vec<Descriptor>> = (0..4).map(|_| vec![rng.noisy(&a, 3)]).collect();
    images[2].push(rng.noisy(&b, 3));
    let voc = Vocabulary::train(
        &images,
        &VocabParams {
            k: 2,
            depth: 1,
            ..VocabParams::default()
        },
    )
    .unwrap();
    let wa = voc.word_weight(voc.word_of(&a)).unwrap();
    let wb = voc.word_weight(voc.word_of(&b)).unwrap();
    assert!(wa.abs() < 1e-6, "word in all images: idf 0, got {wa}");
    assert!((wb - 4f32.ln()).abs() < 1e-5, "idf ln 4, got {wb}");
}

#[test]
fn bad_parameters_and_empty_input_are_errors() {
    let imgs = vec![vec![[0u8; 32]; 4]];
    for (k, depth) in [(1, 3), (300, 3), (10, 0), (10, 9)] {
        let p = VocabParams {
            k,
            depth,
            ..VocabParams::default()
        };
        assert!(matches!(
            Vocabulary::train(&imgs, &p),
            Err(CoreError::InvalidArgument(_))
        ));
    }
    assert!(Vocabulary::train(&[], &VocabParams::default()).is_err());
}

#[test]
fn score_is_l1_similarity() {
    let (images, _) = clustered(8, 50, 4, 9);
    let voc = Vocabulary::train(
        &images,
        &VocabParams {
            k: 4,
            depth: 3,
            ..VocabParams::default()
        },
    )
    .unwrap();
    let a = voc.transform(&images[0]);
    let b = voc.transform(&images[1]);
    assert!((score(&a, &a) - 1.0).abs() < 1e-5);
    let (sab, sba) = (score(&a, &b), score(&b, &a));
    assert!((sab - sba).abs() < 1e-6 && (0.0..=1.0).contains(&sab));
    // Reference formula 1 - 0.5 |a - b|_1 on dense vectors.
    let mut dense = vec![0f32; voc.n_words()];
    for &(w, v) in a.entries() {
        dense[w as usize] += v;
    }
    for &(w, v) in b.entries() {
        dense[w as usize] -= v;
    }
    let reference = 1.0 - 0.5 * dense.iter().map(|x| x.abs()).sum::<f32>();
    assert!((sab - reference).abs() < 1e-5, "{sab} vs {reference}");
    let sum: f32 = a.entries().iter().map(|e| e.1).sum();
    assert!((sum - 1.0).abs() < 1e-5);
    assert_eq!(score(&a, &BowVector::default()), 0.0);
}

fn small_vocab() -> (Vocabulary, Vec<Vec<Descriptor>>) {
    let (images, _) = clustered(12, 40, 6, 21);
    let voc = Vocabulary::train(
        &images,
        &VocabParams {
            k: 4,
            depth: 3,
            ..VocabParams::default()
        },
    )
    .unwrap();
    (voc, images)
}

#[test]
fn file_round_trip() {
    let (voc, images) = small_vocab();
    let bytes = voc.to_bytes();
    assert_eq!(bytes.len(), 28 + 33 * voc.n_nodes() + 4 * voc.n_words() + 8);
    let back = Vocabulary::from_bytes(&bytes).unwrap();
    assert_eq!(back, voc);
    assert_eq!(back.transform(&images[0]), voc.transform(&images[0]));
    let dir = std::env::temp_dir().join(format!("shoal_voc_{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("v.bin");
    voc.save(&path).unwrap();
    assert_eq!(Vocabulary::load(&path).unwrap(), voc);
    let missing = Vocabulary::load(&dir.join("missing.bin"));
    assert!(matches!(missing, Err(CoreError::Io { .. })), "{missing:?}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Recomputes the trailing checksum so structural errors are reached.
fn reseal(bytes: &mut [u8]) {
    let body = bytes.len() - 8;
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in &bytes[..body] {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    bytes[body..].copy_from_slice(&h.to_le_bytes());
}

fn format_error(bytes: &[u8]) -> String {
    match Vocabulary::from_bytes(bytes) {
        Err(CoreError::Format(m)) => m,
        other => panic!("expected a format error, got {other:?}"),
    }
}

#[test]
fn corrupt_files_are_clear_errors() {
    let (voc, _) = small_vocab();
    let good = voc.to_bytes();
    assert!(format_error(&good[..10]).contains("shorter than a header"));
    assert!(format_error(&good[..good.len() - 1]).contains("bytes"));
    let mut b = good.clone();
    b[0] = b'X';
    assert!(format_error(&b).contains("magic"));
    let mut b = good.clone();
    b[8] = 9;
    assert!(format_error(&b).contains("version"));
    let mut b = good.clone();
    b[100] ^= 0x10;
    assert!(format_error(&b).contains("checksum"));
    // Root with no children: the other nodes have no parent.
    let mut b = good.clone();
    b[28] = 0;
    reseal(&mut b);
    let m = format_error(&b);
    assert!(m.contains("no parent") || m.contains("weights"), "{m}");
    // More children than k.
    let mut b = good.clone();
    b[28] = 200;
    reseal(&mut b);
    assert!(format_error(&b).contains("children"));
    // NaN weight.
    let mut b = good.clone();
    let w_at = b.len() - 8 - 4;
    b[w_at..w_at + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    reseal(&mut b);
    assert!(format_error(&b).contains("weight"));
    // Header announcing a huge node count: size mismatch, no allocation, no panic.
    let mut b = good.clone();
    b[20..24].copy_from_slice(&u32::MAX.to_le_bytes());
    assert!(format_error(&b).contains("announces"));
    // Random garbage of every length never panics.
    let mut rng = Lcg(77);
    for len in 0..200 {
        let g: Vec<u8> = (0..len).map(|_| rng.next() as u8).collect();
        assert!(Vocabulary::from_bytes(&g).is_err());
    }
}

#[test]
fn database_query_add_remove() {
    let (voc, images) = small_vocab();
    let bows: Vec<BowVector> = images.iter().map(|i| voc.transform(i)).collect();
    let mut db = KeyframeDatabase::new(voc.n_words());
    for (i, b) in bows.iter().enumerate() {
        db.add(i as u64 * 10, b);
    }
    assert_eq!(db.len(), bows.len());
    let r = db.query(&bows[2], 0.0, |_| false, 100);
    assert_eq!(r[0], (20, r[0].1));
    assert!((r[0].1 - 1.0).abs() < 1e-5);
    for &(id, s) in &r {
        let expected = score(&bows[2], &bows[(id / 10) as usize]);
        assert!((s - expected).abs() < 1e-5, "{id}: {s} vs {expected}");
    }
    assert!(r.windows(2).all(|w| w[0].1 >= w[1].1), "sorted");
    // Exclusion, threshold and max_results.
    let r2 = db.query(&bows[2], 0.0, |id| id == 20, 100);
    assert!(r2.iter().all(|e| e.0 != 20));
    let r3 = db.query(&bows[2], 0.99, |_| false, 100);
    assert_eq!(r3.len(), 1);
    assert_eq!(db.query(&bows[2], 0.0, |_| false, 2).len(), 2);
    // Removal.
    assert!(db.remove(20));
    assert!(!db.remove(20));
    assert!(db
        .query(&bows[2], 0.0, |_| false, 100)
        .iter()
        .all(|e| e.0 != 20));
    assert_eq!(db.len(), bows.len() - 1);
    // A vector sharing no word is never returned.
    let lonely = BowVector::from_unsorted(&mut [(u32::MAX - 1, 1.0)]);
    assert!(db.query(&lonely, 0.0, |_| false, 10).is_empty());
}

#[test]
fn min_score_among_neighbours() {
    let (voc, images) = small_vocab();
    let bows: Vec<BowVector> = images.iter().map(|i| voc.transform(i)).collect();
    assert_eq!(min_score_among(&bows[0], []), None);
    let m = min_score_among(&bows[0], &bows[1..]).unwrap();
    let expected = bows[1..]
        .iter()
        .map(|b| score(&bows[0], b))
        .fold(f32::INFINITY, f32::min);
    assert_eq!(m, expected);
}

#[test]
fn feature_vector_groups() {
    let fv = FeatureVector::from_pairs(vec![(5, 2), (3, 0), (5, 1), (9, 3)]);
    assert_eq!(fv.features_of(5), &[1, 2]);
    assert_eq!(fv.features_of(4), &[] as &[u32]);
    let other = FeatureVector::from_pairs(vec![(5, 7), (9, 8), (10, 9)]);
    let mut pairs = Vec::new();
    fv.for_each_common(&other, |a, b| pairs.push((a.to_vec(), b.to_vec())));
    assert_eq!(pairs, vec![(vec![1, 2], vec![7]), (vec![3], vec![8])]);
}
