//! Sparse bag-of-words vectors, feature vectors and the L1 similarity score.

/// A sparse bag-of-words vector: `(word, weight)` sorted by word, one entry per word,
/// L1-normalised (weights sum to 1) unless empty.
#[derive(Debug, Clone, Default, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct BowVector {
    entries: Vec<(u32, f32)>,
}

impl BowVector {
    /// Sums the weights of equal words in `entries` (sorted in place), drops zero weights
    /// and L1-normalises.
    pub fn from_unsorted(entries: &mut [(u32, f32)]) -> Self {
        entries.sort_unstable_by_key(|e| e.0);
        let mut out: Vec<(u32, f32)> = Vec::with_capacity(entries.len());
        for &(w, v) in entries.iter() {
            match out.last_mut() {
                Some(last) if last.0 == w => last.1 += v,
                _ => out.push((w, v)),
            }
        }
        out.retain(|e| e.1 > 0.0);
        let norm: f32 = out.iter().map(|e| e.1.abs()).sum();
        if norm > 0.0 {
            for e in &mut out {
                e.1 /= norm;
            }
        }
        Self { entries: out }
    }

    /// The `(word, weight)` entries, sorted by word.
    pub fn entries(&self) -> &[(u32, f32)] {
        &self.entries
    }

    /// Number of distinct words.
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    /// Whether no word is present.
    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// Weight of `word` (0 if absent).
    pub fn weight(&self, word: u32) -> f32 {
        self.entries
            .binary_search_by_key(&word, |e| e.0)
            .map_or(0.0, |i| self.entries[i].1)
    }
}

/// DBoW2's L1 score `1 - 0.5 |a/|a| - b/|b||_1`, in `[0, 1]` (1 = same distribution,
/// 0 = no common word). For L1-normalised vectors it equals `Σ min(a_i, b_i)` over common
/// words.
pub fn score(a: &BowVector, b: &BowVector) -> f32 {
    let na: f32 = a.entries.iter().map(|e| e.1.abs()).sum();
    let nb: f32 = b.entries.iter().map(|e| e.1.abs()).sum();
    if na <= 0.0 || nb <= 0.0 {
        return 0.0;
    }
    let (mut i, mut j) = (0, 0);
    let mut s = 0.0f32;
    while i < a.entries.len() && j < b.entries.len() {
        let (wa, va) = a.entries[i];
        let (wb, vb) = b.entries[j];
        match wa.cmp(&wb) {
            std::cmp::Ordering::Less => i += 1,
            std::cmp::Ordering::Greater => j += 1,
            std::cmp::Ordering::Equal => {
                s += (va.abs() / na).min(vb.abs() / nb);
                i += 1;
                j += 1;
            }
        }
    }
    s.clamp(0.0, 1.0)
}

/// Feature indices grouped by vocabulary node at one level (for guided matching between two
/// images: only features under the same node are compared). Sorted by node.
#[derive(Debug, Clone, Default, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
pub struct FeatureVector {
    groups: Vec<(u32, Vec<u32>)>,
}

impl FeatureVector {
    /// Groups `(node, feature index)` pairs by node (indices kept in ascending order).
    pub fn from_pairs(mut pairs: Vec<(u32, u32)>) -> Self {
        pairs.sort_unstable();
        let mut groups: Vec<(u32, Vec<u32>)> = Vec::new();
        for (node, f) in pairs {
            match groups.last_mut() {
                Some(g) if g.0 == node => g.1.push(f),
                _ => groups.push((node, vec![f])),
            }
        }
        Self { groups }
    }

    /// `(node, feature indices)` groups, sorted by node.
    pub fn groups(&self) -> &[(u32, Vec<u32>)] {
        &self.groups
    }

    /// Feature indices under `node` (empty if none).
    pub fn features_of(&self, node: u32) -> &[u32] {
        self.groups
            .binary_search_by_key(&node, |g| g.0)
            .map_or(&[], |i| &self.groups[i].1)
    }

    /// Calls `f(indices in a, indices in b)` for every node present in both vectors.
    pub fn for_each_common(&self, other: &FeatureVector, mut f: impl FnMut(&[u32], &[u32])) {
        let (mut i, mut j) = (0, 0);
        while i < self.groups.len() && j < other.groups.len() {
            match self.groups[i].0.cmp(&other.groups[j].0) {
                std::cmp::Ordering::Less => i += 1,
                std::cmp::Ordering::Greater => j += 1,
                std::cmp::Ordering::Equal => {
                    f(&self.groups[i].1, &other.groups[j].1);
                    i += 1;
                    j += 1;
                }
            }
        }
    }
}
