//! Loaded maps get client ids of their own, so that their keyframe, point and map ids never
//! collide with the live run's: the clients of a file are renamed, in ascending order, to
//! [`SAVED_CLIENT_BASE`], `SAVED_CLIENT_BASE + 1`, ... (a file saved by a run that had itself
//! loaded one holds such clients too; they stay distinct). Live clients are numbered from 0
//! and never reach the base.
use std::collections::{BTreeMap, BTreeSet};

use slam_core::ids::{ClientId, KeyframeId, MapId, MapPointId};

use crate::MapFile;

pub use slam_core::ids::SAVED_CLIENT_BASE;

/// Every client id `file` uses: in map ids, per-map client lists, keyframe ids, point ids.
fn clients_of(file: &MapFile) -> BTreeSet<u32> {
    let mut c = BTreeSet::new();
    for m in &file.maps {
        c.insert(m.map.id.client().raw());
        c.insert(m.map.client_id);
        c.extend(m.clients.iter().copied());
        let map = &m.map.map;
        c.extend(
            map.keyframes
                .keys()
                .map(|k| KeyframeId::from_raw(*k).client().raw()),
        );
        c.extend(
            map.points
                .keys()
                .map(|p| MapPointId::from_raw(*p).client().raw()),
        );
    }
    c
}

/// Renames the clients of `file` to the saved-clients range (module docs) in every id it
/// holds: map ids, map clients, keyframe ids (keys, point observations, covisibility,
/// BoW vectors), point ids (keys, keyframe links, the point counter). Returns the renaming
/// `old → new`. The same file always gets the same ids (the mapper and the loop closer
/// each load it and must agree).
pub fn remap_clients(file: &mut MapFile) -> BTreeMap<u32, u32> {
    remap_clients_from(file, SAVED_CLIENT_BASE)
}

/// [`remap_clients`] to `base`, `base + 1`, ... (`shoal bench map` makes a large file of
/// copies of one this way).
pub fn remap_clients_from(file: &mut MapFile, base: u32) -> BTreeMap<u32, u32> {
    let table: BTreeMap<u32, u32> = clients_of(file).into_iter().zip(base..).collect();
    let client = |c: u32| ClientId::new(table.get(&c).copied().unwrap_or(c));
    let kf = |k: u64| {
        let id = KeyframeId::from_raw(k);
        KeyframeId::new(client(id.client().raw()), id.client_kf()).raw()
    };
    let pt = |p: u64| {
        let id = MapPointId::from_raw(p);
        MapPointId::first_of_client(client(id.client().raw())).raw() + id.counter()
    };
    for m in &mut file.maps {
        let sm = &mut m.map;
        sm.id = MapId::new(client(sm.id.client().raw()), sm.id.index());
        sm.client_id = client(sm.client_id).raw();
        sm.map.rename_ids(kf, pt);
        for c in &mut m.clients {
            *c = client(*c).raw();
        }
        m.clients.sort_unstable();
        for (k, _, _) in &mut m.bow {
            *k = kf(*k);
        }
    }
    file.maps.sort_by_key(|m| m.map.id);
    table
}
