//! The server's clients by name (issue 22): each remote client gets a slot (the client
//! index of the server's mapper and loop closer) from its name, the same across reconnects
//! and server restarts (the table is kept in a file, rewritten atomically), up to the
//! server's capacity. With `--auth`, a known name's first slot is its rank in the
//! credentials file (when free), not its order of arrival: the server's client indices, and
//! so the map (whose client's map a merge keeps, in which order keyframes tie), are those
//! of a single-host `shoal run` with the datasets in the file's order. The table also keeps
//! each name's runs apart: a new run (another run id in the hello) gets a start base past
//! every start the name's keyframes have carried ([`crate::run_ids`]).
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use shm_schema::SCHEMA_VERSION;

use crate::wire::Welcome;

/// A name's entry: its slot, and its runs' start bases ([`crate::run_ids`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Entry {
    slot: u32,
    /// The run that said hello last, and its start base.
    run: u64,
    base: u32,
    /// The next start no run of the name has used (the next run's base is one below).
    next_start: u32,
}

/// The slots given out.
#[derive(Debug, Default)]
pub struct Slots {
    by_name: BTreeMap<String, Entry>,
    capacity: u32,
    file: Option<PathBuf>,
    /// With `--auth`: the only names given a slot, in the credentials file's order.
    known: Option<Vec<String>>,
}

impl Slots {
    /// The table of `file` (none yet: empty), for `capacity` clients.
    pub fn open(file: Option<&Path>, capacity: u32) -> anyhow::Result<Self> {
        let mut by_name = BTreeMap::new();
        if let Some((f, text)) = file.and_then(|f| Some((f, std::fs::read_to_string(f).ok()?))) {
            for (i, line) in text.lines().enumerate() {
                let (name, entry) = parse_line(line)
                    .map_err(|e| anyhow::anyhow!("{}:{}: {e}", f.display(), i + 1))?;
                by_name.insert(name, entry);
            }
        }
        Ok(Self {
            by_name,
            capacity,
            file: file.map(Path::to_path_buf),
            known: None,
        })
    }

    /// Only `names` get a slot (the credentials of `--auth`, in the file's order).
    pub fn only(mut self, names: Vec<String>) -> Self {
        self.known = Some(names);
        self
    }

    /// The answer to a hello of `name`'s run `run` speaking schema `version`: its slot (a
    /// new one when there is room) and the run's start base, or a refusal.
    pub fn welcome(&mut self, version: u32, name: &str, run: u64) -> Welcome {
        if version != SCHEMA_VERSION {
            return Welcome::Refused(format!(
                "schema version {version}, this server speaks {SCHEMA_VERSION}: run the same \
                 shoal version on both hosts"
            ));
        }
        let rank = match &self.known {
            Some(k) => match k.iter().position(|n| n == name) {
                Some(r) => u32::try_from(r).ok(),
                None => return Welcome::Refused(format!("{name:?} is not a known client")),
            },
            None => None,
        };
        let entry = match self.by_name.get(name) {
            Some(e) if e.run == run => *e,
            Some(e) => Entry {
                run,
                base: e.next_start - 1,
                ..*e
            },
            None => match self.free_slot(rank) {
                Some(slot) => Entry {
                    slot,
                    run,
                    base: 0,
                    next_start: 1,
                },
                None => {
                    return Welcome::Refused(format!(
                        "the server is full ({} clients: {})",
                        self.capacity,
                        self.names().join(", ")
                    ))
                }
            },
        };
        self.set(name, entry);
        Welcome::Slot {
            slot: entry.slot,
            start_base: entry.base,
        }
    }

    /// A free slot: `preferred` when free and within the capacity, else the first free one.
    fn free_slot(&self, preferred: Option<u32>) -> Option<u32> {
        let used: std::collections::BTreeSet<u32> = self.by_name.values().map(|e| e.slot).collect();
        let free = |s: &u32| *s < self.capacity && !used.contains(s);
        preferred
            .filter(free)
            .or_else(|| (0..self.capacity).find(free))
    }

    /// `name`'s keyframe carried start `start` (the server's numbering): later runs start
    /// past it.
    pub fn saw_start(&mut self, name: &str, start: u32) {
        if let Some(e) = self.by_name.get(name).copied() {
            if start >= e.next_start {
                self.set(
                    name,
                    Entry {
                        next_start: start + 1,
                        ..e
                    },
                );
            }
        }
    }

    /// Sets `name`'s entry, saving the table when it changed.
    fn set(&mut self, name: &str, entry: Entry) {
        if self.by_name.insert(name.to_string(), entry) == Some(entry) {
            return;
        }
        if let Err(e) = self.save() {
            // Kept in memory all the same: a restart before the next save would give the
            // slot again in order, and the start base of the run that said hello last.
            eprintln!("[bridge] cannot save the client table: {e}");
        }
    }

    /// The names, in slot order.
    pub fn names(&self) -> Vec<String> {
        self.by_slot()
            .into_iter()
            .map(|(_, n)| n.to_string())
            .collect()
    }

    /// The slots and their names, in slot order.
    pub fn by_slot(&self) -> Vec<(u32, &str)> {
        let mut v: Vec<_> = (self.by_name.iter())
            .map(|(n, e)| (e.slot, n.as_str()))
            .collect();
        v.sort();
        v
    }

    /// The slot of `name`, if it has one.
    pub fn slot_of(&self, name: &str) -> Option<u32> {
        self.by_name.get(name).map(|e| e.slot)
    }

    /// The name of slot `slot`.
    pub fn name_of(&self, slot: u32) -> Option<&str> {
        (self.by_name.iter()).find_map(|(n, e)| (e.slot == slot).then_some(n.as_str()))
    }

    fn save(&self) -> std::io::Result<()> {
        let Some(file) = &self.file else {
            return Ok(());
        };
        let text: String = (self.by_name.iter())
            .map(|(n, e)| format!("{} {n} {} {} {}\n", e.slot, e.run, e.base, e.next_start))
            .collect();
        let tmp = file.with_extension("tmp");
        std::fs::write(&tmp, text)?;
        std::fs::rename(tmp, file)
    }
}

/// A table line: `SLOT NAME RUN BASE NEXT_START`.
fn parse_line(line: &str) -> Result<(String, Entry), String> {
    let f: Vec<&str> = line.split_whitespace().collect();
    let [slot, name, run, base, next] = f.as_slice() else {
        return Err("expected `SLOT NAME RUN BASE NEXT_START`".into());
    };
    let num = |what: &str, v: &str| v.parse::<u64>().map_err(|_| format!("bad {what} {v:?}"));
    let small = |what: &str, v: &str| {
        num(what, v).and_then(|n| u32::try_from(n).map_err(|_| format!("bad {what} {v:?}")))
    };
    let entry = Entry {
        slot: small("slot", slot)?,
        run: num("run", run)?,
        base: small("start base", base)?,
        next_start: small("next start", next)?.max(1),
    };
    Ok((name.to_string(), entry))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The slot and start base `s` gives run `run` of `name`.
    fn welcome(s: &mut Slots, name: &str, run: u64) -> (u32, u32) {
        match s.welcome(SCHEMA_VERSION, name, run) {
            Welcome::Slot { slot, start_base } => (slot, start_base),
            Welcome::Refused(why) => panic!("{name} refused: {why}"),
        }
    }

    /// The reason `s` refuses `name`.
    fn refusal(s: &mut Slots, version: u32, name: &str) -> String {
        match s.welcome(version, name, 1) {
            Welcome::Refused(why) => why,
            w => panic!("{name} welcome: {w:?}"),
        }
    }

    /// A name keeps its slot, through a restart too; beyond the capacity and in another
    /// schema version a client is refused with the reason.
    #[test]
    fn slots_are_stable_and_bounded() {
        let dir = std::env::temp_dir().join(format!("shoal_slots_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("clients.txt");
        let mut s = Slots::open(Some(&file), 2).unwrap();
        assert_eq!(welcome(&mut s, "a", 1), (0, 0));
        assert_eq!(welcome(&mut s, "b", 1), (1, 0));
        assert_eq!(welcome(&mut s, "a", 1), (0, 0));
        assert!(refusal(&mut s, SCHEMA_VERSION, "c").contains("full"));
        assert!(refusal(&mut s, SCHEMA_VERSION + 1, "a").contains("schema version"));
        let mut again = Slots::open(Some(&file), 2).unwrap();
        assert_eq!(welcome(&mut again, "b", 1), (1, 0));
        assert_eq!(again.name_of(0), Some("a"));
        let mut known = Slots::open(Some(&file), 3)
            .unwrap()
            .only(vec!["b".into(), "c".into()]);
        assert_eq!(welcome(&mut known, "b", 1).0, 1);
        assert!(refusal(&mut known, SCHEMA_VERSION, "z").contains("not a known client"));
        // A known name's first slot is its rank in the credentials file, whatever the
        // order of arrival; a rank beyond the capacity, or taken, gets the first free slot.
        let names = || vec!["d".into(), "e".into(), "f".into()];
        let mut ranked = Slots::open(None, 2).unwrap().only(names());
        assert_eq!(welcome(&mut ranked, "e", 1).0, 1);
        assert_eq!(welcome(&mut ranked, "f", 1).0, 0);
        let mut ranked = Slots::open(None, 3).unwrap().only(names());
        assert_eq!(welcome(&mut ranked, "f", 1).0, 2);
        assert_eq!(welcome(&mut ranked, "d", 1).0, 0);
        std::fs::write(&file, "x a\n").unwrap();
        let err = Slots::open(Some(&file), 2).unwrap_err().to_string();
        assert!(err.contains("clients.txt:1"), "{err}");
        std::fs::remove_dir_all(dir).unwrap();
    }

    /// Each run of a name gets a start base past every start its earlier runs' keyframes
    /// carried, the same for every hello of the run, also after a restart of the server.
    #[test]
    fn each_run_starts_past_the_earlier_ones() {
        let dir = std::env::temp_dir().join(format!("shoal_runs_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("clients.txt");
        let mut s = Slots::open(Some(&file), 2).unwrap();
        assert_eq!(welcome(&mut s, "a", 11), (0, 0));
        s.saw_start("a", 1);
        s.saw_start("a", 2); // the run's tracker restarted once
        assert_eq!(
            welcome(&mut s, "a", 11),
            (0, 0),
            "a reconnect of the same run"
        );
        assert_eq!(
            welcome(&mut s, "a", 12),
            (0, 2),
            "the next run: start 1 becomes 3"
        );
        s.saw_start("a", 3);
        let mut restarted = Slots::open(Some(&file), 2).unwrap();
        assert_eq!(welcome(&mut restarted, "a", 12), (0, 2));
        assert_eq!(welcome(&mut restarted, "a", 13), (0, 3));
        assert_eq!(
            welcome(&mut restarted, "b", 13),
            (1, 0),
            "runs are per name"
        );
        std::fs::remove_dir_all(dir).unwrap();
    }
}
