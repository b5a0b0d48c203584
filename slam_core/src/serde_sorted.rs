//! Serialisation of hash maps in key order (feature `serde`), so that the same map always
//! gives the same bytes (a saved map file is reproducible: save → load → save is identical).
use std::collections::{BTreeMap, HashMap};
use std::hash::BuildHasher;

use serde::{Serialize, Serializer};

/// A `HashMap` written as its entries in ascending key order.
pub fn map<K, V, H, S>(m: &HashMap<K, V, H>, s: S) -> Result<S::Ok, S::Error>
where
    K: Ord + Serialize,
    V: Serialize,
    H: BuildHasher,
    S: Serializer,
{
    let sorted: BTreeMap<&K, &V> = m.iter().collect();
    sorted.serialize(s)
}

/// A `HashMap` of `HashMap`s written in ascending key order at both levels.
pub fn nested<K, K2, V, H, H2, S>(
    m: &HashMap<K, HashMap<K2, V, H2>, H>,
    s: S,
) -> Result<S::Ok, S::Error>
where
    K: Ord + Serialize,
    K2: Ord + Serialize,
    V: Serialize,
    H: BuildHasher,
    H2: BuildHasher,
    S: Serializer,
{
    let sorted: BTreeMap<&K, BTreeMap<&K2, &V>> =
        m.iter().map(|(k, v)| (k, v.iter().collect())).collect();
    sorted.serialize(s)
}
