//! Place recognition: a hierarchical bag-of-words vocabulary of ORB descriptors
//! (Gálvez-López & Tardós 2012, "Bags of binary words"), tf-idf vectors with the L1 score,
//! and a keyframe database with an inverted index.
//!
//! ```
//! use slam_core::place::{score, KeyframeDatabase, VocabParams, Vocabulary};
//! // Two "images" of random descriptors.
//! let mut s = 7u64;
//! let mut next = || { s = s.wrapping_mul(6364136223846793005).wrapping_add(1); (s >> 33) as u8 };
//! let images: Vec<Vec<[u8; 32]>> =
//!     (0..2).map(|_| (0..200).map(|_| std::array::from_fn(|_| next())).collect()).collect();
//! let params = VocabParams { k: 4, depth: 3, ..VocabParams::default() };
//! let voc = Vocabulary::train(&images, &params).unwrap();
//! let a = voc.transform(&images[0]);
//! assert!((score(&a, &a) - 1.0).abs() < 1e-5);
//! let mut db = KeyframeDatabase::new(voc.n_words());
//! db.add(0, &a);
//! db.add(1, &voc.transform(&images[1]));
//! let best = db.query(&a, 0.0, |_| false, 1);
//! assert_eq!(best[0].0, 0);
//! let back = Vocabulary::from_bytes(&voc.to_bytes()).unwrap();
//! assert_eq!(back, voc);
//! ```

mod bow;
mod database;
mod io;
#[cfg(test)]
mod tests;
mod vocabulary;

pub use bow::{score, BowVector, FeatureVector};
pub use database::{min_score_among, KeyframeDatabase, KeyframeId};
pub use vocabulary::{Descriptor, VocabParams, Vocabulary};
