//! The vocabulary file format (little-endian throughout):
//!
//! | bytes | content |
//! |---|---|
//! | 8 | magic `SHOALBOW` |
//! | 4 | version (1) |
//! | 4 | k (branching) |
//! | 4 | depth |
//! | 4 | number of nodes N (root included) |
//! | 4 | number of words W |
//! | 33 × N | per node, breadth-first: number of children (u8), centre descriptor (32 B) |
//! | 4 × W | idf weight of each word (f32), words numbered by leaf order |
//! | 8 | FNV-1a 64 checksum of every byte before it |
//!
//! Children of node `i` are the next `n_children(i)` nodes not yet assigned to a parent,
//! taken in node order (node 0 is the root), so no index is stored.

use std::path::Path;

use super::vocabulary::{Node, Vocabulary, NO_WORD};
use crate::CoreError;

const MAGIC: &[u8; 8] = b"SHOALBOW";
const VERSION: u32 = 1;
const HEADER: usize = 8 + 5 * 4;
const NODE_BYTES: usize = 33;

fn fnv1a(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

fn bad(msg: impl Into<String>) -> CoreError {
    CoreError::Format(format!("vocabulary file: {}", msg.into()))
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

impl Vocabulary {
    /// Serialises to the file format above.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out =
            Vec::with_capacity(HEADER + NODE_BYTES * self.nodes.len() + 4 * self.weights.len() + 8);
        out.extend_from_slice(MAGIC);
        for v in [
            VERSION,
            self.k as u32,
            self.depth as u32,
            self.nodes.len() as u32,
            self.weights.len() as u32,
        ] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for n in &self.nodes {
            out.push(n.n_children);
            out.extend_from_slice(&n.desc);
        }
        for w in &self.weights {
            out.extend_from_slice(&w.to_le_bytes());
        }
        let h = fnv1a(&out);
        out.extend_from_slice(&h.to_le_bytes());
        out
    }

    /// Parses the file format above, validating sizes, the tree structure, the weights and
    /// the checksum. Never panics on malformed input.
    pub fn from_bytes(bytes: &[u8]) -> Result<Self, CoreError> {
        if bytes.len() < HEADER + 8 {
            return Err(bad(format!("{} bytes, shorter than a header", bytes.len())));
        }
        if &bytes[..8] != MAGIC {
            return Err(bad("bad magic (not a shoal vocabulary)"));
        }
        let version = u32_at(bytes, 8);
        if version != VERSION {
            return Err(bad(format!("version {version}, expected {VERSION}")));
        }
        let k = u32_at(bytes, 12) as usize;
        let depth = u32_at(bytes, 16) as usize;
        let n_nodes = u32_at(bytes, 20) as usize;
        let n_words = u32_at(bytes, 24) as usize;
        if n_nodes < 2 {
            return Err(bad(format!("{n_nodes} nodes: no word below the root")));
        }
        if !(2..=255).contains(&k) || !(1..=8).contains(&depth) {
            return Err(bad(format!("k = {k}, depth = {depth} out of range")));
        }
        let expected =
            (n_nodes as u64) * NODE_BYTES as u64 + 4 * n_words as u64 + 8 + HEADER as u64;
        if expected != bytes.len() as u64 {
            return Err(bad(format!(
                "{} bytes, header announces {n_nodes} nodes and {n_words} words ({expected} bytes)",
                bytes.len()
            )));
        }
        let body = bytes.len() - 8;
        let stored = u64::from_le_bytes(bytes[body..].try_into().map_err(|_| bad("checksum"))?);
        if fnv1a(&bytes[..body]) != stored {
            return Err(bad("checksum mismatch (corrupt or truncated file)"));
        }
        let mut nodes = Vec::with_capacity(n_nodes);
        let mut next = 1usize; // next node not yet assigned to a parent
        let mut parent_level = vec![0u8; n_nodes];
        for i in 0..n_nodes {
            let at = HEADER + i * NODE_BYTES;
            let n_children = bytes[at];
            if usize::from(n_children) > k {
                return Err(bad(format!("node {i} has {n_children} children > k = {k}")));
            }
            if i > 0 && i >= next {
                return Err(bad(format!("node {i} has no parent")));
            }
            let level = if i == 0 { 0 } else { parent_level[i] };
            if n_children > 0 {
                if level as usize >= depth {
                    return Err(bad(format!("node {i} at depth {level} has children")));
                }
                let end = next + usize::from(n_children);
                if end > n_nodes {
                    return Err(bad(format!("node {i}'s children run past the last node")));
                }
                for pl in &mut parent_level[next..end] {
                    *pl = level + 1;
                }
            }
            let mut desc = [0u8; 32];
            desc.copy_from_slice(&bytes[at + 1..at + NODE_BYTES]);
            nodes.push(Node {
                desc,
                first_child: next as u32,
                n_children,
                level,
                word: NO_WORD,
            });
            next += usize::from(n_children);
        }
        if next != n_nodes {
            return Err(bad(format!(
                "{} nodes have no parent",
                n_nodes.saturating_sub(next)
            )));
        }
        let w_at = HEADER + n_nodes * NODE_BYTES;
        let weights: Vec<f32> = (0..n_words)
            .map(|i| f32::from_le_bytes(u32_at(bytes, w_at + 4 * i).to_le_bytes()))
            .collect();
        if let Some(i) = weights.iter().position(|w| !w.is_finite() || *w < 0.0) {
            return Err(bad(format!("word {i} has weight {}", weights[i])));
        }
        let n_leaves = nodes.iter().filter(|n| n.n_children == 0).count();
        if n_leaves != n_words {
            return Err(bad(format!("{n_words} weights for {n_leaves} leaves")));
        }
        Self::from_nodes(k, depth, nodes, weights).map_err(|e| bad(e.to_string()))
    }

    /// Writes the vocabulary to `path`.
    pub fn save(&self, path: &Path) -> Result<(), CoreError> {
        std::fs::write(path, self.to_bytes()).map_err(|source| CoreError::Io {
            path: path.display().to_string(),
            source,
        })
    }

    /// Reads a vocabulary from `path`.
    pub fn load(path: &Path) -> Result<Self, CoreError> {
        let bytes = std::fs::read(path).map_err(|source| CoreError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::from_bytes(&bytes).map_err(|e| match e {
            CoreError::Format(m) => CoreError::Format(format!("{}: {m}", path.display())),
            e => e,
        })
    }
}
