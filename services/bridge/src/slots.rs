//! The server's clients by name (issue 22): each remote client gets a slot (the client
//! index of the server's mapper and loop closer) from its name, the same across reconnects
//! and server restarts (the table is kept in a file, rewritten atomically), up to the
//! server's capacity.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use shm_schema::SCHEMA_VERSION;

use crate::wire::Welcome;

/// The slots given out.
#[derive(Debug, Default)]
pub struct Slots {
    by_name: BTreeMap<String, u32>,
    capacity: u32,
    file: Option<PathBuf>,
    /// With `--auth`: the only names given a slot.
    known: Option<std::collections::BTreeSet<String>>,
}

impl Slots {
    /// The table of `file` (none yet: empty), for `capacity` clients.
    pub fn open(file: Option<&Path>, capacity: u32) -> anyhow::Result<Self> {
        let mut by_name = BTreeMap::new();
        if let Some(text) = file.and_then(|f| std::fs::read_to_string(f).ok()) {
            for (i, line) in text.lines().enumerate() {
                let mut parts = line.split_whitespace();
                let (Some(slot), Some(name), None) = (parts.next(), parts.next(), parts.next())
                else {
                    anyhow::bail!(
                        "{}:{}: expected `SLOT NAME`",
                        file.unwrap().display(),
                        i + 1
                    );
                };
                let slot: u32 = slot.parse().map_err(|_| {
                    anyhow::anyhow!("{}:{}: bad slot {slot:?}", file.unwrap().display(), i + 1)
                })?;
                by_name.insert(name.to_string(), slot);
            }
        }
        Ok(Self {
            by_name,
            capacity,
            file: file.map(Path::to_path_buf),
            known: None,
        })
    }

    /// Only `names` get a slot (the credentials of `--auth`).
    pub fn only(mut self, names: std::collections::BTreeSet<String>) -> Self {
        self.known = Some(names);
        self
    }

    /// The answer to a hello of `name` speaking schema `version`: its slot (a new one when
    /// there is room), or a refusal.
    pub fn welcome(&mut self, version: u32, name: &str) -> Welcome {
        if version != SCHEMA_VERSION {
            return Welcome::Refused(format!(
                "schema version {version}, this server speaks {SCHEMA_VERSION}: run the same \
                 shoal version on both hosts"
            ));
        }
        if self.known.as_ref().is_some_and(|k| !k.contains(name)) {
            return Welcome::Refused(format!("{name:?} is not a known client"));
        }
        if let Some(s) = self.by_name.get(name) {
            return Welcome::Slot(*s);
        }
        let used: std::collections::BTreeSet<u32> = self.by_name.values().copied().collect();
        let Some(free) = (0..self.capacity).find(|s| !used.contains(s)) else {
            return Welcome::Refused(format!(
                "the server is full ({} clients: {})",
                self.capacity,
                self.names().join(", ")
            ));
        };
        self.by_name.insert(name.to_string(), free);
        if let Err(e) = self.save() {
            // The slot is given all the same: a restart would give it again in order.
            eprintln!("[bridge] cannot save the client table: {e}");
        }
        Welcome::Slot(free)
    }

    /// The names, in slot order.
    pub fn names(&self) -> Vec<String> {
        let mut v: Vec<_> = self.by_name.iter().map(|(n, s)| (*s, n.clone())).collect();
        v.sort();
        v.into_iter().map(|(_, n)| n).collect()
    }

    /// The slot of `name`, if it has one.
    pub fn slot_of(&self, name: &str) -> Option<u32> {
        self.by_name.get(name).copied()
    }

    /// The name of slot `slot`.
    pub fn name_of(&self, slot: u32) -> Option<&str> {
        (self.by_name.iter()).find_map(|(n, s)| (*s == slot).then_some(n.as_str()))
    }

    fn save(&self) -> std::io::Result<()> {
        let Some(file) = &self.file else {
            return Ok(());
        };
        let text: String = (self.by_name.iter())
            .map(|(n, s)| format!("{s} {n}\n"))
            .collect();
        let tmp = file.with_extension("tmp");
        std::fs::write(&tmp, text)?;
        std::fs::rename(tmp, file)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A name keeps its slot, through a restart too; beyond the capacity and in another
    /// schema version a client is refused with the reason.
    #[test]
    fn slots_are_stable_and_bounded() {
        let dir = std::env::temp_dir().join(format!("shoal_slots_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("clients.txt");
        let mut s = Slots::open(Some(&file), 2).unwrap();
        assert_eq!(s.welcome(SCHEMA_VERSION, "a"), Welcome::Slot(0));
        assert_eq!(s.welcome(SCHEMA_VERSION, "b"), Welcome::Slot(1));
        assert_eq!(s.welcome(SCHEMA_VERSION, "a"), Welcome::Slot(0));
        let Welcome::Refused(why) = s.welcome(SCHEMA_VERSION, "c") else {
            panic!("a third client in two slots");
        };
        assert!(why.contains("full"), "{why}");
        let Welcome::Refused(why) = s.welcome(SCHEMA_VERSION + 1, "a") else {
            panic!("another schema");
        };
        assert!(why.contains("schema version"), "{why}");
        let mut again = Slots::open(Some(&file), 2).unwrap();
        assert_eq!(again.welcome(SCHEMA_VERSION, "b"), Welcome::Slot(1));
        assert_eq!(again.name_of(0), Some("a"));
        let mut known = Slots::open(Some(&file), 3)
            .unwrap()
            .only(["b".to_string()].into());
        assert_eq!(known.welcome(SCHEMA_VERSION, "b"), Welcome::Slot(1));
        let Welcome::Refused(why) = known.welcome(SCHEMA_VERSION, "z") else {
            panic!("an unknown name");
        };
        assert!(why.contains("not a known client"), "{why}");
        std::fs::write(&file, "x a\n").unwrap();
        assert!(Slots::open(Some(&file), 2).is_err());
        std::fs::remove_dir_all(dir).unwrap();
    }
}
