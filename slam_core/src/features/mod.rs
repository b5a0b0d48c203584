//! ORB features: image pyramid, FAST-9 with quadtree spreading, intensity-centroid orientation,
//! rotated BRIEF descriptors, and descriptor matching.
//!
//! ```
//! use slam_core::features::{GrayImage, OrbExtractor, OrbFeatures, OrbParams};
//! let (w, h) = (160, 120);
//! let pixels: Vec<u8> = (0..w * h).map(|i| ((i % w) ^ (i / w)) as u8).collect();
//! let img = GrayImage::from_packed(&pixels, w, h).unwrap();
//! let mut orb = OrbExtractor::new(OrbParams::default(), w, h).unwrap();
//! let mut feats = OrbFeatures::with_capacity(1000);
//! orb.extract(&img, &mut feats).unwrap();
//! assert_eq!(feats.keypoints.len(), feats.descriptors.len());
//! ```

mod distribute;
mod extractor;
mod fast;
mod image;
mod matching;
mod orb;
mod pattern;
mod pyramid;
mod scale;
mod simd;
#[cfg(test)]
mod tests;
pub mod tracks;

pub use extractor::{KeyPoint, OrbExtractor, OrbFeatures, OrbParams, OrbTimings, PATCH_SIZE};
pub use image::{GrayBuffer, GrayImage};
pub use matching::*;
pub use pyramid::Pyramid;
pub(crate) use scale::powi_f64;
pub use scale::{PyramidScale, MAX_LEVELS, ORB_N_LEVELS, ORB_SCALE_FACTOR};
