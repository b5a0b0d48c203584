//! The topology of a run as data: one typed descriptor per service, with its role in the
//! data flow, and the start / stop order derived from the roles (not from positions in a
//! list). Consumers start before the producers that feed them, so no sensor publishes before
//! its tracker (or a tracker before the mapper) listens; stopping runs in the exact reverse,
//! so producers stop first and every consumer can take what was sent to it.
use serde::Serialize;

/// What a service does in the data flow.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
pub enum Role {
    /// Host-wide server side (mapper, loop closer): consumes the trackers' keyframes.
    Server,
    /// A client's tracker: consumes its sensors' frames and IMU samples.
    Tracker,
    /// A client's sensor ingest: produces frames or IMU samples.
    Sensor,
}

impl Role {
    /// True for services that must be listening before data is produced.
    pub fn is_consumer(self) -> bool {
        !matches!(self, Role::Sensor)
    }
}

/// Which service it is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum Kind {
    /// The mapper (one per host).
    Mapper,
    /// The loop closer (one per host).
    LoopCloser,
    /// A client's tracker.
    Tracker,
    /// A client's IMU ingest.
    ImuIngest,
    /// A client's camera ingest.
    CameraIngest,
    /// The bridge to another host (issue 22): beside a remote client's tracker (its client
    /// set) or beside the server's mapper (host-wide).
    Bridge,
}

impl Kind {
    /// The role of this kind of service.
    pub fn role(self) -> Role {
        match self {
            // A bridge takes keyframes (client side) or feeds the mapper (server side): it
            // starts before the trackers and stops after them.
            Kind::Mapper | Kind::LoopCloser | Kind::Bridge => Role::Server,
            Kind::Tracker => Role::Tracker,
            Kind::ImuIngest | Kind::CameraIngest => Role::Sensor,
        }
    }

    /// Name in reports (`tracker`, `camera_ingest`, ...).
    pub fn name(self) -> &'static str {
        match self {
            Kind::Mapper => "mapper",
            Kind::LoopCloser => "loop_closer",
            Kind::Tracker => "tracker",
            Kind::ImuIngest => "imu_ingest",
            Kind::CameraIngest => "camera_ingest",
            Kind::Bridge => "bridge",
        }
    }

    /// Subcommand of `shoal service`.
    pub fn subcommand(self) -> &'static str {
        match self {
            Kind::Mapper => "mapper",
            Kind::LoopCloser => "loop-closer",
            Kind::Tracker => "tracker",
            Kind::ImuIngest => "imu-ingest",
            Kind::CameraIngest => "camera-ingest",
            Kind::Bridge => "bridge",
        }
    }
}

/// One service of the run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct ServiceDesc {
    /// Which service.
    pub kind: Kind,
    /// Its client, `None` for host-wide services.
    pub client: Option<u32>,
}

impl ServiceDesc {
    /// Name in reports and `--kill`: `mapper`, `tracker:0`, `camera_ingest:1`, ...
    pub fn name(&self) -> String {
        match self.client {
            Some(c) => format!("{}:{c}", self.kind.name()),
            None => self.kind.name().to_string(),
        }
    }

    /// Role in the data flow.
    pub fn role(&self) -> Role {
        self.kind.role()
    }
}

/// The services of a run with `clients` clients: the host-wide ones, then per client its
/// tracker and sensors (IMU before camera, so the gyro samples of a frame's rows are there
/// when the frame is). The order of this list does not set the start order by itself:
/// [`start_order`] sorts it by role.
pub fn topology(clients: u32) -> Vec<ServiceDesc> {
    let host = |kind| ServiceDesc { kind, client: None };
    let mut list = vec![host(Kind::Mapper), host(Kind::LoopCloser)];
    for c in 0..clients {
        for kind in [Kind::Tracker, Kind::ImuIngest, Kind::CameraIngest] {
            list.push(ServiceDesc {
                kind,
                client: Some(c),
            });
        }
    }
    list
}

/// The services of `clients` clients whose server is on another host (`shoal client`): per
/// client its tracker, sensors and bridge; no mapper nor loop closer here.
pub fn client_topology(clients: u32) -> Vec<ServiceDesc> {
    let mut list = Vec::new();
    for c in 0..clients {
        for kind in [
            Kind::Bridge,
            Kind::Tracker,
            Kind::ImuIngest,
            Kind::CameraIngest,
        ] {
            list.push(ServiceDesc {
                kind,
                client: Some(c),
            });
        }
    }
    list
}

/// The services of a server for remote clients (`shoal serve`): the mapper, the loop closer
/// and the bridge.
pub fn server_topology() -> Vec<ServiceDesc> {
    let host = |kind| ServiceDesc { kind, client: None };
    vec![
        host(Kind::Mapper),
        host(Kind::LoopCloser),
        host(Kind::Bridge),
    ]
}

/// Start phases, as indices into `services`: every consumer (server side, then trackers),
/// then every producer (sensors). The launcher waits for a phase to be ready before starting
/// the next. Within a phase, services keep the order of `services` (stable sort by role).
pub fn start_phases(services: &[ServiceDesc]) -> [Vec<usize>; 2] {
    let order = start_order(services);
    let (consumers, producers) = order
        .into_iter()
        .partition(|&i| services[i].role().is_consumer());
    [consumers, producers]
}

/// Start order, as indices into `services`: by role (server, trackers, sensors), the order
/// of `services` within a role.
pub fn start_order(services: &[ServiceDesc]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..services.len()).collect();
    order.sort_by_key(|&i| services[i].role());
    order
}

/// Stop order: the exact reverse of [`start_order`] (sensors first, the server side last).
pub fn stop_order(services: &[ServiceDesc]) -> Vec<usize> {
    let mut order = start_order(services);
    order.reverse();
    order
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(services: &[ServiceDesc], order: &[usize]) -> Vec<String> {
        order.iter().map(|&i| services[i].name()).collect()
    }

    /// Position of `name` in `order`.
    fn pos(services: &[ServiceDesc], order: &[usize], name: &str) -> usize {
        names(services, order)
            .iter()
            .position(|n| n == name)
            .unwrap_or_else(|| panic!("{name} not in the order"))
    }

    #[test]
    fn one_client_starts_consumers_first_and_stops_in_reverse() {
        let t = topology(1);
        let [consumers, producers] = start_phases(&t);
        assert_eq!(
            names(&t, &consumers),
            ["mapper", "loop_closer", "tracker:0"]
        );
        assert_eq!(names(&t, &producers), ["imu_ingest:0", "camera_ingest:0"]);
        assert_eq!(
            names(&t, &stop_order(&t)),
            [
                "camera_ingest:0",
                "imu_ingest:0",
                "tracker:0",
                "loop_closer",
                "mapper"
            ]
        );
    }

    /// For N clients: every service is started once; every tracker and the server side are
    /// in the first phase, every sensor in the second, each sensor after its own tracker and
    /// each tracker after the mapper; the stop order is the reverse of the start order.
    fn check(n: u32) {
        let t = topology(n);
        assert_eq!(t.len(), 2 + 3 * n as usize);
        let [consumers, producers] = start_phases(&t);
        let start: Vec<usize> = consumers.iter().chain(&producers).copied().collect();
        let mut sorted = start.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..t.len()).collect::<Vec<_>>(), "each once");
        assert!(consumers.iter().all(|&i| t[i].role().is_consumer()));
        assert!(producers.iter().all(|&i| t[i].role() == Role::Sensor));
        assert_eq!(consumers.len(), 2 + n as usize, "N = {n}");
        assert_eq!(producers.len(), 2 * n as usize, "N = {n}");
        let stop = stop_order(&t);
        for c in 0..n {
            let tracker = format!("tracker:{c}");
            assert!(pos(&t, &start, "mapper") < pos(&t, &start, &tracker));
            for sensor in ["imu_ingest", "camera_ingest"] {
                let s = format!("{sensor}:{c}");
                // Every consumer of every client is up before any sensor starts.
                for d in 0..n {
                    let other = format!("tracker:{d}");
                    assert!(
                        pos(&t, &start, &other) < pos(&t, &start, &s),
                        "N = {n}: {other} starts before {s}"
                    );
                }
                assert!(pos(&t, &stop, &s) < pos(&t, &stop, &tracker));
            }
            assert!(pos(&t, &stop, &tracker) < pos(&t, &stop, "mapper"));
        }
        let mut reversed = stop.clone();
        reversed.reverse();
        assert_eq!(reversed, start, "N = {n}: stop is the reverse of start");
    }

    #[test]
    fn consumers_start_first_for_one_two_and_four_clients() {
        for n in [1, 2, 4] {
            check(n);
        }
    }

    #[test]
    fn two_clients_order_is_by_role_not_list_position() {
        let t = topology(2);
        let [consumers, producers] = start_phases(&t);
        assert_eq!(
            names(&t, &consumers),
            ["mapper", "loop_closer", "tracker:0", "tracker:1"]
        );
        assert_eq!(
            names(&t, &producers),
            [
                "imu_ingest:0",
                "camera_ingest:0",
                "imu_ingest:1",
                "camera_ingest:1"
            ]
        );
    }
}
