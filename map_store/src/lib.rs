//! The saved-map file of shoal (`shoal run --save-map` / `--load-map`, `shoal map`): the
//! server's maps (keyframes with features and descriptors, map points, covisibility, each
//! keyframe's bag-of-words vector, per-map metadata) in one versioned, checksummed file,
//! written atomically.
//!
//! Layout ([`format`]): a fixed header (magic, format version, vocabulary identity, payload
//! length, CRC-32 of the payload, shoal version string), then the payload: a [`MapFile`]
//! encoded with postcard. Reading checks, in this order, the magic, the version (both
//! versions named when they differ), the length (truncation), the checksum (corruption),
//! then decodes and validates ([`MapFile::validate`]); a file that fails any check is
//! refused whole, never half-loaded.
//!
//! ```no_run
//! let path = std::path::Path::new("run.shoalmap");
//! let (header, file) = map_store::read(path)?;
//! let bytes = std::fs::metadata(path).map_or(0, |m| m.len());
//! println!("{}", map_store::info::describe(&header, &file, path, bytes));
//! # Ok::<(), map_store::MapFileError>(())
//! ```
#![deny(missing_docs)]

pub mod error;
pub mod format;
pub mod info;
pub mod ply;
pub mod remap;

use serde::{Deserialize, Serialize};
use slam_core::ids::KeyframeId;
use slam_core::place::{BowVector, FeatureVector, Vocabulary};
use slam_core::server::ServerMap;
use slam_core::vo::KfId;

pub use error::MapFileError;
pub use format::{encode, read, read_bytes, write, Header, FORMAT_VERSION, MAGIC};

/// The vocabulary shipped with the project (`assets/orb_vocab.bin`), built in: the one
/// whose identity a saved file records when no other is configured.
pub static SHIPPED_VOCABULARY: &[u8] = include_bytes!("../../assets/orb_vocab.bin");

/// The identity of a vocabulary: CRC-32 of its file's bytes.
pub fn vocabulary_id(bytes: &[u8]) -> u32 {
    crc32fast::hash(bytes)
}

/// A digest of a server map's saved content (CRC-32 of its postcard encoding): what
/// `--localize-only` compares at the end with the loaded map's to show nothing was added
/// to it or moved. `None` when it cannot be encoded.
pub fn map_digest(map: &ServerMap) -> Option<u32> {
    postcard::to_stdvec(map).ok().map(|b| crc32fast::hash(&b))
}

/// One saved server map with what place recognition needs of its keyframes.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SavedMap {
    /// The map (keyframes, points, observations, covisibility, frame, ids); its client
    /// point associations are not saved (they only mean something to live clients).
    pub map: ServerMap,
    /// Clients with keyframes in it, ascending.
    pub clients: Vec<u32>,
    /// Bag-of-words and feature vector of each keyframe (server keyframe id order),
    /// computed with the vocabulary named in the header ([`Header::vocabulary_id`]), the
    /// feature vectors at [`MapFile::feature_level`].
    pub bow: Vec<(KfId, BowVector, FeatureVector)>,
}

/// The payload of a saved-map file.
#[derive(Debug, Clone, Serialize, Deserialize, Default)]
pub struct MapFile {
    /// Vocabulary level of the keyframes' feature vectors (`LoopDetectorParams::
    /// feature_level`; 0 with no feature vectors).
    pub feature_level: u32,
    /// The maps, by ascending map id.
    pub maps: Vec<SavedMap>,
}

impl MapFile {
    /// The file of `maps` (cloned, by ascending id), each keyframe's BoW vector and feature
    /// vector at `feature_level` computed with `vocabulary`.
    pub fn from_maps<'a>(
        maps: impl IntoIterator<Item = &'a ServerMap>,
        vocabulary: &Vocabulary,
        feature_level: u32,
    ) -> Self {
        let mut maps: Vec<SavedMap> = maps
            .into_iter()
            .map(|m| SavedMap {
                clients: clients_of(m),
                bow: m
                    .map
                    .keyframes
                    .iter()
                    .map(|(k, kf)| {
                        let descriptors = &kf.features.descriptors;
                        let level = feature_level as usize;
                        let (bow, fv) = vocabulary.transform_with_features(descriptors, level);
                        (*k, bow, fv)
                    })
                    .collect(),
                map: m.clone(),
            })
            .collect();
        maps.sort_by_key(|m| m.map.id);
        Self {
            feature_level,
            maps,
        }
    }

    /// Keyframes over all maps.
    pub fn keyframes(&self) -> usize {
        self.maps.iter().map(|m| m.map.map.keyframes.len()).sum()
    }

    /// Points over all maps.
    pub fn points(&self) -> usize {
        self.maps.iter().map(|m| m.map.map.points.len()).sum()
    }

    /// Checks what the services rely on, so that a file that decodes but is inconsistent
    /// is refused rather than half-used: per keyframe one descriptor and one point slot
    /// per keypoint, a finite pose, its key equal to its id; every point's key equal to its
    /// id and its position finite; map ids unique.
    pub fn validate(&self) -> Result<(), String> {
        let mut ids = std::collections::BTreeSet::new();
        for m in &self.maps {
            let id = m.map.id;
            if !ids.insert(id) {
                return Err(format!("map {:#x} appears twice", id.raw()));
            }
            for (k, kf) in &m.map.map.keyframes {
                let n = kf.features.keypoints.len();
                let consistent =
                    *k == kf.id && kf.features.descriptors.len() == n && kf.points.len() == n;
                let t = kf.t_cw.translation.vector;
                let q = kf.t_cw.rotation.coords;
                if !consistent || !t.iter().chain(q.iter()).all(|v| v.is_finite()) {
                    return Err(format!(
                        "map {:#x}: keyframe {k:#x} is inconsistent (id {:#x}, {n} keypoints, {} descriptors, {} point slots, or a non-finite pose)",
                        id.raw(),
                        kf.id,
                        kf.features.descriptors.len(),
                        kf.points.len()
                    ));
                }
            }
            for (p, mp) in &m.map.map.points {
                if *p != mp.id || !mp.p_w.iter().all(|v| v.is_finite()) {
                    return Err(format!(
                        "map {:#x}: point {p:#x} is inconsistent (id {:#x} or a non-finite position)",
                        id.raw(),
                        mp.id
                    ));
                }
            }
        }
        Ok(())
    }
}

/// Clients with keyframes in `m`, ascending.
fn clients_of(m: &ServerMap) -> Vec<u32> {
    let set: std::collections::BTreeSet<u32> = m
        .map
        .keyframes
        .keys()
        .map(|k| KeyframeId::from_raw(*k).client().raw())
        .collect();
    set.into_iter().collect()
}

/// A map file read for a run: checked, decoded and its clients renamed to the saved-clients
/// range ([`remap`]).
#[derive(Debug)]
pub struct Loaded {
    /// The header.
    pub header: Header,
    /// The maps, with their new ids.
    pub file: MapFile,
    /// Client renaming `old → new`.
    pub clients: std::collections::BTreeMap<u32, u32>,
    /// File size, bytes.
    pub bytes: u64,
}

/// Reads the map file at `path` for a run ([`Loaded`]).
pub fn load(path: &std::path::Path) -> Result<Loaded, MapFileError> {
    let bytes = std::fs::read(path).map_err(|source| MapFileError::Io {
        path: path.to_path_buf(),
        what: "reading",
        source,
    })?;
    let (header, mut file) = read_bytes(&bytes, path)?;
    let clients = remap::remap_clients(&mut file);
    Ok(Loaded {
        header,
        file,
        clients,
        bytes: bytes.len() as u64,
    })
}

#[cfg(test)]
mod tests;
