//! The keyframe database: an inverted index word → keyframes, queried with the L1 score.

use std::collections::HashMap;

use super::bow::{score, BowVector};

/// Keyframe id used by the database.
pub type KeyframeId = u64;

/// Inverted index of keyframe bag-of-words vectors. Only keyframes sharing at least one word
/// with a query are scored.
#[derive(Debug, Clone, Default)]
pub struct KeyframeDatabase {
    /// `inverted[word]` = `(keyframe, weight of the word in it)`.
    inverted: Vec<Vec<(KeyframeId, f32)>>,
    /// Each keyframe's vector (for removal and re-scoring).
    vectors: HashMap<KeyframeId, BowVector>,
}

impl KeyframeDatabase {
    /// Empty database for a vocabulary of `n_words` words (grows if larger ids come).
    pub fn new(n_words: usize) -> Self {
        Self {
            inverted: vec![Vec::new(); n_words],
            vectors: HashMap::new(),
        }
    }

    /// Number of keyframes.
    pub fn len(&self) -> usize {
        self.vectors.len()
    }

    /// Whether there is no keyframe.
    pub fn is_empty(&self) -> bool {
        self.vectors.is_empty()
    }

    /// Whether `id` is in the database.
    pub fn contains(&self, id: KeyframeId) -> bool {
        self.vectors.contains_key(&id)
    }

    /// The vector stored for `id`.
    pub fn bow(&self, id: KeyframeId) -> Option<&BowVector> {
        self.vectors.get(&id)
    }

    /// Adds (or replaces) keyframe `id`.
    pub fn add(&mut self, id: KeyframeId, bow: &BowVector) {
        self.remove(id);
        for &(w, v) in bow.entries() {
            let w = w as usize;
            if w >= self.inverted.len() {
                self.inverted.resize(w + 1, Vec::new());
            }
            self.inverted[w].push((id, v));
        }
        self.vectors.insert(id, bow.clone());
    }

    /// Removes keyframe `id`; returns whether it was present.
    pub fn remove(&mut self, id: KeyframeId) -> bool {
        let Some(bow) = self.vectors.remove(&id) else {
            return false;
        };
        for &(w, _) in bow.entries() {
            if let Some(list) = self.inverted.get_mut(w as usize) {
                list.retain(|e| e.0 != id);
            }
        }
        true
    }

    /// Keyframes scoring at least `min_score` against `bow` (L1 score, see
    /// [`score`](super::score)), skipping those for which `exclude(id)` is true, best first
    /// (ties by id), at most `max_results` of them.
    pub fn query(
        &self,
        bow: &BowVector,
        min_score: f32,
        exclude: impl Fn(KeyframeId) -> bool,
        max_results: usize,
    ) -> Vec<(KeyframeId, f32)> {
        let norm: f32 = bow.entries().iter().map(|e| e.1).sum();
        if norm <= 0.0 || max_results == 0 {
            return Vec::new();
        }
        // Stored vectors are L1-normalised: score = Σ over common words of min(a_i, b_i).
        let mut acc: HashMap<KeyframeId, f32> = HashMap::new();
        let mut excluded: HashMap<KeyframeId, bool> = HashMap::new();
        for &(w, v) in bow.entries() {
            let Some(list) = self.inverted.get(w as usize) else {
                continue;
            };
            let v = v / norm;
            for &(id, vk) in list {
                if *excluded.entry(id).or_insert_with(|| exclude(id)) {
                    continue;
                }
                *acc.entry(id).or_insert(0.0) += v.min(vk);
            }
        }
        let mut out: Vec<(KeyframeId, f32)> = acc
            .into_iter()
            .map(|(id, s)| (id, s.clamp(0.0, 1.0)))
            .filter(|&(_, s)| s >= min_score)
            .collect();
        out.sort_unstable_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
        out.truncate(max_results);
        out
    }
}

/// The seed's loop-detection threshold: the lowest score of `bow` against its covisible
/// neighbours' vectors (`None` when there is no neighbour).
pub fn min_score_among<'a>(
    bow: &BowVector,
    neighbours: impl IntoIterator<Item = &'a BowVector>,
) -> Option<f32> {
    neighbours
        .into_iter()
        .map(|n| score(bow, n))
        .min_by(|a, b| a.total_cmp(b))
}
