//! Replays a mapper journal (`OUT/mapper_journal.bin`) through fresh keyframe handlers and
//! prints, every N keyframes, the size of the server map and of its client-point
//! association tables, and the heap the replay holds beyond the journal entries not replayed
//! yet: a diagnosis tool for the mapper's memory growth on long runs (BENCHMARKS.md, "Long
//! run").
//!
//! `cargo run --release --example journal_growth -- OUT/mapper_journal.bin [EVERY]`
//!
//! The replay handles every keyframe and runs the idle step after the journaled ones, as a
//! restarted mapper does; corrections are not applied (the growth question does not need
//! them).
use std::collections::{BTreeMap, HashSet};

use shoal_runtime::journal::{read_journal, Entry};
use slam_core::server::{HandlerParams, KeyframeHandler, ServerMaps};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let path = args
        .get(1)
        .ok_or_else(|| anyhow::anyhow!("usage: journal_growth JOURNAL [EVERY]"))?;
    let every: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(250);
    let contents = read_journal(std::path::Path::new(path))?;
    // Heap held by the journal entries not replayed yet, so that the printed heap is the
    // handlers' and maps' own.
    let rec_bytes = |r: &Vec<shm_schema::KeypointRecord>| {
        (r.capacity() * std::mem::size_of::<shm_schema::KeypointRecord>()
            + std::mem::size_of::<shm_schema::KeyframeHeader>()) as i64
    };
    let mut pending_bytes: i64 = contents
        .entries
        .iter()
        .map(|e| match e {
            Entry::Keyframe { records, .. } => rec_bytes(records),
            _ => 0,
        })
        .sum();
    let heap0 = shoal_runtime::heap_in_use_bytes().unwrap_or(0) as i64 - pending_bytes;
    if let Some(p) = &contents.problem {
        eprintln!("journal: {p} (replaying the good prefix)");
    }
    let mut handlers: BTreeMap<u32, KeyframeHandler> = BTreeMap::new();
    let mut maps = ServerMaps::new();
    let mut n = 0usize;
    let mut client_points: HashSet<(u32, u64)> = HashSet::new();
    println!(
        "keyframes,map_keyframes,map_points,associations,pending,distinct_client_points,heap_mib"
    );
    for e in contents.entries {
        match e {
            Entry::Keyframe {
                client,
                header,
                records,
                imu,
            } => {
                pending_bytes -= rec_bytes(&records);
                let kf = match mapper::convert::server_keyframe(client, &header, &records, Ok(&imu))
                {
                    Ok(k) => k.kf,
                    Err(e) => {
                        eprintln!("skipped: {e}");
                        continue;
                    }
                };
                for p in kf.client_points.iter().flatten() {
                    client_points.insert((kf.session_id, *p));
                }
                let h = handlers
                    .entry(client)
                    .or_insert_with(|| KeyframeHandler::new(client, HandlerParams::default()));
                if let Err(e) = h.handle(&mut maps, kf) {
                    eprintln!("handler: {e}");
                }
                n += 1;
                if n.is_multiple_of(every.max(1)) {
                    let (kfs, pts) = maps.values().fold((0, 0), |a, m| {
                        (a.0 + m.map.keyframes.len(), a.1 + m.map.points.len())
                    });
                    let (assoc, pending) = maps.values().fold((0, 0), |a, m| {
                        let (x, y) = m.association_count();
                        (a.0 + x, a.1 + y)
                    });
                    let heap = (shoal_runtime::heap_in_use_bytes().unwrap_or(0) as i64
                        - pending_bytes
                        - heap0) as f64
                        / 1048576.0;
                    println!(
                        "{n},{kfs},{pts},{assoc},{pending},{},{heap:.1}",
                        client_points.len()
                    );
                }
            }
            Entry::Idle { client, .. } => {
                if let Some(h) = handlers.get_mut(&client) {
                    while h.idle_step(&mut maps).is_some() {}
                }
            }
            Entry::Correction { .. } | Entry::MapPoints { .. } => {}
        }
    }
    Ok(())
}
