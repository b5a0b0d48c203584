//! The mapper's counters, as types: the one list of their names (the status file's
//! `counters`, per client `c{i}.{name}`), which the launcher and the tests read back with the
//! same types. The mapper has no crash-recovery state in its status file: a restarted mapper
//! rebuilds its maps from its journal (`--journal`), and its counters carry on.
use serde::{Deserialize, Serialize};
use shoal_runtime::PerClient;

/// One server map as the report lists it (`report.json` `maps`, issue 19).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct MapSummary {
    /// Map id ([`slam_core::ids::MapId`], raw).
    pub id: u64,
    /// Clients with keyframes in it.
    pub clients: Vec<u32>,
    /// Keyframes.
    pub keyframes: u64,
    /// Points.
    pub points: u64,
    /// Lengths are metres (a visual-inertial client's map, or one merged into it).
    pub metric: bool,
    /// The z axis is up.
    pub gravity_aligned: bool,
}

/// The mapper's section of its status file beyond counters (`details`): its live maps.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct MapperDetails {
    /// The live server maps (merged-away maps are gone), by id.
    pub maps: Vec<MapSummary>,
}

/// Counters and gauges of the mapper (all clients).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MapperCounters {
    /// Handler threads started (one per client with keyframes).
    pub handlers_started: u64,
    /// Merges that handed one handler thread's group of clients over to another's.
    pub handler_groups_joined: u64,
    /// Corrections received from the loop closer.
    pub corrections_received: u64,
    /// Corrections not applied (undecodable, no handler for the map, or refused by it).
    pub corrections_refused: u64,
    /// Map merges applied.
    pub corrections_applied_merge: u64,
    /// Pose graph corrections applied.
    pub corrections_applied_pose_graph: u64,
    /// Of the corrections applied, those replayed from the journal.
    pub corrections_replayed: u64,
    /// Time spent applying corrections, µs.
    pub correction_apply_us: u64,
    /// Journals of another version (or without a version header) set aside, not replayed.
    pub journals_rejected: u64,
    /// Resynchronisation requests of a (restarted) loop closer.
    pub resync_requests: u64,
    /// Keyframes sent to the loop closer to resynchronise it.
    pub resync_keyframes_sent: u64,
    /// Lock-step: waits for the loop closer that timed out.
    pub lockstep_loop_timeouts: u64,
    /// Global BAs applied (after loops, merges, revisits; on the groups' global BA
    /// threads).
    pub global_bas: u64,
    /// Of them, visual-inertial (metric, gravity-aligned maps).
    pub global_bas_inertial: u64,
    /// Global BAs not applied: their map was corrected or merged away while they solved,
    /// or the solve failed.
    pub global_bas_dropped: u64,
    /// Time the global BA threads spent solving, µs.
    pub global_ba_us: u64,
    /// The longest global BA solve, µs.
    pub global_ba_max_us: u64,
    /// Time the handler threads spent writing global BAs back, µs.
    pub global_ba_apply_us: u64,
    /// Keyframes that entered a map while its global BA solved, moved with it.
    pub global_ba_keyframes_propagated: u64,
    /// Gauge: live server maps.
    pub maps: u64,
    /// Gauge: keyframes in them.
    pub keyframes: u64,
    /// Gauge: points in them.
    pub points: u64,
    /// Per client (`c{i}.{name}`).
    #[serde(flatten)]
    pub clients: PerClient<MapperClientCounters>,
}

impl MapperCounters {
    /// Corrections applied, both kinds.
    pub fn corrections_applied(&self) -> u64 {
        self.corrections_applied_merge + self.corrections_applied_pose_graph
    }

    /// Client `c`'s counters (zeros when nothing was counted for it).
    pub fn client(&self, c: u32) -> MapperClientCounters {
        self.clients.get(c).cloned().unwrap_or_default()
    }
}

/// Counters and gauges of one client at the mapper.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct MapperClientCounters {
    /// Keyframe messages received (re-sends included).
    pub keyframes_received: u64,
    /// Bytes of those messages (header and payload: keypoint and IMU records).
    pub keyframe_bytes: u64,
    /// Of those messages, the ones carrying an IMU segment (issue 19).
    pub keyframes_with_imu: u64,
    /// IMU samples in those segments.
    pub imu_samples_received: u64,
    /// Keyframes applied visual-only because their IMU segment (or inertial state) did
    /// not hold (`bad_imu_segment` errors).
    pub imu_segments_refused: u64,
    /// Re-sends of keyframes already applied (acknowledged again, not re-applied).
    pub keyframes_duplicate: u64,
    /// Keyframes journaled and queued for the handler.
    pub keyframes_applied: u64,
    /// Acknowledgements sent.
    pub keyframes_acked: u64,
    /// Keyframes replayed from the journal through the handler.
    pub keyframes_replayed: u64,
    /// Kept keyframes forwarded to the loop closer.
    pub keyframes_forwarded: u64,
    /// Lock-step: keyframes reported finished to the tracker.
    pub keyframes_finished: u64,
    /// Pose feedback messages sent.
    pub pose_feedback_sent: u64,
    /// Handler outcomes: the first keyframe of a session.
    pub handled_first: u64,
    /// Handler outcomes: a server map created.
    pub handled_map_created: u64,
    /// Handler outcomes: kept.
    pub handled_kept: u64,
    /// Handler outcomes: discarded.
    pub handled_discarded: u64,
    /// Handler outcomes: a duplicate.
    pub handled_duplicate: u64,
    /// Time the handler spent handling keyframes, µs.
    pub handle_us: u64,
    /// Time the handler spent in idle steps, µs.
    pub idle_us: u64,
    /// The longest backlog of the client's handler group seen behind one of its keyframes.
    pub handler_queue_max: u64,
    /// Gauge: the group's idle interval (keyframes between local BAs in a backlog; real
    /// time adapts it so the handlers keep up, `worker::pacing`).
    pub idle_interval: u64,
    /// The largest idle interval the group took.
    pub idle_interval_max: u64,
    /// Gauge (handler): keyframes inserted in a server map.
    pub keyframes_kept: u64,
    /// Gauge (handler): keyframes refined and discarded.
    pub keyframes_discarded: u64,
    /// Gauge (handler): keyframes culled as redundant.
    pub keyframes_culled: u64,
    /// Gauge (handler): global BAs run for a revisit.
    pub revisit_global_ba: u64,
    /// Gauge (handler): keyframes inserted at their session's end.
    pub kept_at_session_end: u64,
    /// Gauge (handler): keyframes localised in a frozen map (`--localize-only`).
    pub keyframes_localised: u64,
    /// Gauge (handler): its maps relocalised in a frozen map (`--localize-only`), or
    /// sessions that joined a loaded map by the points they name.
    pub relocalisations: u64,
    /// Gauge (handler): sessions whose first keyframe joined the loaded map it names (its
    /// VO started in that map, `tracker.prior_map`).
    pub sessions_joined: u64,
    /// Gauge (handler): global BAs of its current map applied (after loops, merges,
    /// revisits).
    pub global_bas: u64,
    /// Gauge (handler): visual-inertial local BAs solved (metric, gravity-aligned maps).
    pub vi_windows: u64,
    /// Gauge (handler): visual-inertial local BAs not built or failed (a visual one ran).
    pub vi_windows_skipped: u64,
    /// Gauge (handler): server maps created.
    pub maps: u64,
    /// Gauge: the client's keyframes in its current server map.
    pub server_keyframes: u64,
    /// Gauge: the client's current server map, once it has one.
    pub map_id: Option<u64>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use shoal_runtime::Status;

    /// The counters keep the names report.json and its readers know (`maps`,
    /// `corrections_applied_merge`, `c0.keyframes_received`, ...), a client's map id only
    /// once it has one, and come back whole from the status file.
    #[test]
    fn counter_names_in_the_status_file() {
        let mut c = MapperCounters {
            corrections_applied_merge: 1,
            maps: 2,
            ..MapperCounters::default()
        };
        c.clients.of(0).keyframes_received = 5;
        c.clients.of(1).map_id = Some(1 << 40);
        let mut s = Status::new("mapper");
        s.put_counters(&c);
        for k in [
            "maps",
            "corrections_applied_merge",
            "corrections_applied_pose_graph",
            "c0.keyframes_received",
            "c0.keyframes_applied",
            "c0.handle_us",
            "c1.map_id",
        ] {
            assert!(s.counters.contains_key(k), "{k}: {:?}", s.counters);
        }
        assert!(!s.counters.contains_key("c0.map_id"));
        let text = serde_json::to_string(&s).unwrap();
        let back: Status = serde_json::from_str(&text).unwrap();
        assert_eq!(back.counters_as::<MapperCounters>(), c);
        assert_eq!(c.client(0).keyframes_received, 5);
        assert_eq!(c.client(7), MapperClientCounters::default());
        assert_eq!(c.corrections_applied(), 1);
    }

    /// A restarted mapper carries on with its predecessor's counters.
    #[test]
    fn a_restarted_mapper_carries_the_counters_on() {
        use clap::Parser;
        let mut prev = MapperCounters {
            corrections_received: 3,
            ..MapperCounters::default()
        };
        prev.clients.of(0).keyframes_applied = 12;
        let mut s = Status::new("mapper");
        s.put_counters(&prev);
        s.starts = 2;
        let (tx, _rx) = crossbeam_channel::unbounded();
        let params = crate::Params::parse_from(["mapper"]);
        let cfg = params.config().expect("default configuration");
        let mut m = crate::core::Mapper::new(&params, &cfg, s, tx);
        assert_eq!(m.counters, prev);
        m.counters.clients.of(0).keyframes_applied += 1;
        let s = m.status_now();
        assert_eq!(s.counters["c0.keyframes_applied"], 13);
    }
}
