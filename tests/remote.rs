//! Clients on other hosts (issue 22), as separate processes on this one: `shoal serve`
//! (mapper, loop closer, zenoh bridge) and `shoal client`s (ingests, tracker, bridge), each
//! with its own iceoryx2 prefix, talking only over the network: TCP or TLS on loopback,
//! through a relay that cuts, partitions, delays and watches the bytes
//! ([`net_proxy::Relay`]), or between two network namespaces over a slow link that drops
//! packets ([`net_proxy::lossy::LossyLink`]). Every keyframe a client sends is acknowledged
//! end to end by the server's mapper, also across a server that is SIGKILLed in the middle
//! of the run and started again, and across a client's runs; a client beyond the server's
//! capacity, or without the right credential, is refused with the reason. A server started
//! from a saved map takes a client that localised in the same file into it at once.
mod common;
mod net_proxy;

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::*;

/// A free TCP port on loopback.
fn free_port() -> u16 {
    let l = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    l.local_addr().unwrap().port()
}

/// `shoal serve` listening on `listen` into `out` (`clients` slots, `extra` arguments).
fn serve_cmd(listen: &str, out: &Path, test: &str, clients: u32, extra: &[&str]) -> Command {
    let mut cmd = shoal();
    cmd.args(["serve", "--listen", listen])
        .arg("--out")
        .arg(out)
        .args([
            "--clients",
            &clients.to_string(),
            "--ipc-prefix",
            &prefix(test),
        ])
        .args(extra);
    cmd
}

/// Starts `shoal serve` on `port` into `out` (`clients` slots, `extra` arguments); waits
/// until it accepts connections.
fn serve(port: u16, out: &Path, test: &str, clients: u32, extra: &[&str]) -> Child {
    let listen = format!("tcp/127.0.0.1:{port}");
    start_server(serve_cmd(&listen, out, test, clients, extra), port)
}

/// Starts the server `cmd` listening on loopback `port`; waits until it accepts
/// connections.
fn start_server(mut cmd: Command, port: u16) -> Child {
    let child = cmd
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("start shoal serve");
    let deadline = Instant::now() + Duration::from_secs(60);
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(
            Instant::now() < deadline,
            "the server never listened on {port}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    child
}

/// Stops a server with SIGINT (its report is written then) and waits for it.
fn stop(mut server: Child) {
    // SAFETY: a signal to our own child.
    unsafe { libc::kill(server.id() as i32, libc::SIGINT) };
    let status = server.wait().expect("wait for shoal serve");
    assert!(status.success(), "shoal serve exited with {status}");
}

/// `shoal client` on `dataset` into `out` with `extra` arguments, to a server on loopback.
fn client(
    dataset: &Path,
    out: &Path,
    port: u16,
    name: &str,
    test: &str,
    extra: &[&str],
) -> Command {
    let server = format!("tcp/127.0.0.1:{port}");
    client_of(&server, dataset, out, name, test, extra)
}

/// `shoal client` of the server at `endpoint` on `dataset` into `out`.
fn client_of(
    endpoint: &str,
    dataset: &Path,
    out: &Path,
    name: &str,
    test: &str,
    extra: &[&str],
) -> Command {
    let mut cmd = shoal();
    cmd.args(["client", "--connect", endpoint])
        .arg("--dataset")
        .arg(dataset)
        .arg("--out")
        .arg(out)
        .args([
            "--name",
            name,
            "--quiet",
            "--mode",
            "mono",
            "--ipc-prefix",
            &prefix(test),
        ])
        .args(["--max-seconds", "600"])
        .args(extra)
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    cmd
}

fn u(v: &serde_json::Value) -> u64 {
    v.as_u64().unwrap_or_else(|| panic!("not a count: {v}"))
}

/// Asserts a finished `shoal client` succeeded (showing its stderr if not).
fn succeeded(run: &std::process::Output) {
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
}

/// The client report of `out`, whose client sent at least `min` keyframes and saw every
/// one acknowledged by the server's mapper; the report and the count.
fn all_acked(out: &Path, min: u64) -> (serde_json::Value, u64) {
    let rep = report(out);
    let c = &rep["clients"][0];
    let sent = u(&c["keyframes_sent"]);
    assert!(sent >= min, "{c:#}");
    assert_eq!(u(&c["keyframes_acked"]), sent, "{c:#}");
    (rep, sent)
}

/// Two clients of the `two-agents` scene on one server: each gets its own slot, every
/// keyframe it sends is applied by the server's mapper and acknowledged back (the client
/// counts only the mapper's acknowledgements), and the server merges the two maps.
#[test]
fn two_clients_on_a_remote_server_lose_no_keyframe_and_merge() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "two-agents", 480, None);
    let port = free_port();
    let server_out = dir.path().join("server");
    let server = serve(port, &server_out, "remote_srv", 2, &[]);
    let sync_off = ["--lockstep"];
    let outs = [dir.path().join("a"), dir.path().join("b")];
    let mut runs: Vec<Child> = (0..2)
        .map(|i| {
            let name = ["phone-a", "phone-b"][i];
            client(
                &ds[i],
                &outs[i],
                port,
                name,
                &format!("remote_c{i}"),
                &sync_off,
            )
            .spawn()
            .expect("start shoal client")
        })
        .collect();
    for r in &mut runs {
        assert!(r.wait().unwrap().success(), "a client failed");
    }
    stop(server);
    let srv = report(&server_out);
    let clients = srv["remote_clients"].as_array().expect("remote_clients");
    assert_eq!(clients.len(), 2, "{srv:#}");
    for (i, out) in outs.iter().enumerate() {
        let rep = report(out);
        let c = &rep["clients"][0];
        let sent = u(&c["keyframes_sent"]);
        assert!(sent >= 5, "client {i} sent {sent} keyframes");
        assert_eq!(u(&c["keyframes_acked"]), sent, "client {i}: {c:#}");
        let mine = clients
            .iter()
            .find(|r| r["name"] == ["phone-a", "phone-b"][i])
            .expect("the client in the server's table");
        assert_eq!(u(&mine["keyframes_applied"]), sent, "{mine}");
        let bridge = &rep["bridges"]["bridge:0"];
        eprintln!("client {i}: {sent} keyframes sent and acknowledged; bridge {bridge}");
        assert!(u(&bridge["keyframes_forwarded"]) >= sent, "{bridge}");
        assert_eq!(
            u(&bridge["roundtrips"]),
            sent,
            "every keyframe's round trip: {bridge}"
        );
        assert!(u(&bridge["roundtrip_us_p99"]) >= u(&bridge["roundtrip_us_p50"]));
        assert_eq!(u(&bridge["feedback_refused"]), 0, "{bridge}");
    }
    assert!(u(&srv["merges"]) >= 1, "no merge: {}", srv["maps"]);
    let slots: Vec<u64> = clients.iter().map(|c| u(&c["slot"])).collect();
    assert!(slots.contains(&0) && slots.contains(&1), "{slots:?}");
}

/// The server is SIGKILLed while a client runs (real time) and started again on the same
/// folder: the client keeps its slot, the keyframes sent meanwhile come again from its
/// tracker, and at the end every keyframe is applied and acknowledged once.
#[test]
fn a_server_killed_and_restarted_loses_no_keyframe() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "loop", 500, None);
    let port = free_port();
    let server_out = dir.path().join("server");
    let mut server = serve(port, &server_out, "remote_kill_srv", 2, &[]);
    let out = dir.path().join("c");
    // A small window: keyframes leave it (and go to the server) all along the run.
    let window = ["--set", "tracker.window=6"];
    let mut run = client(&ds[0], &out, port, "walker", "remote_kill_c", &window)
        .spawn()
        .expect("start shoal client");
    std::thread::sleep(Duration::from_secs(8));
    server.kill().expect("SIGKILL the server");
    server.wait().unwrap();
    std::thread::sleep(Duration::from_secs(3));
    let server = serve(port, &server_out, "remote_kill_srv", 2, &[]);
    assert!(run.wait().unwrap().success(), "the client failed");
    stop(server);
    let srv = report(&server_out);
    let rep = report(&out);
    let c = &rep["clients"][0];
    let sent = u(&c["keyframes_sent"]);
    assert!(sent >= 10, "{sent} keyframes");
    assert_eq!(u(&c["keyframes_acked"]), sent, "{c:#}");
    let me = &srv["remote_clients"][0];
    assert_eq!(me["name"], "walker");
    assert_eq!(u(&me["keyframes_applied"]), sent, "{me}");
    assert_eq!(u(&me["maps"]), 1, "{me}");
    let bridge = &rep["bridges"]["bridge:0"];
    eprintln!("{sent} keyframes sent and acknowledged; bridge {bridge}; server {me}");
    assert!(
        u(&bridge["keyframes_forwarded"]) + u(&bridge["keyframes_unsent"]) > sent,
        "{bridge}"
    );
}

/// A server with room for one client refuses a second, which says why and goes on without
/// a server (its tracker still poses every frame); the server counts the refusal.
#[test]
fn a_client_beyond_the_capacity_is_refused() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "two-agents", 120, None);
    let port = free_port();
    let server_out = dir.path().join("server");
    let server = serve(port, &server_out, "remote_full_srv", 1, &[]);
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    let ok = client(&ds[0], &a, port, "first", "remote_full_a", &["--lockstep"])
        .output()
        .unwrap();
    assert!(ok.status.success());
    let refused = client(&ds[1], &b, port, "second", "remote_full_b", &["--lockstep"])
        .output()
        .unwrap();
    stop(server);
    let rep = report(&b);
    let text = serde_json::to_string(&rep["errors"]).unwrap();
    assert!(text.contains("refused") && text.contains("full"), "{text}");
    assert_eq!(u(&rep["clients"][0]["keyframes_acked"]), 0);
    assert_eq!(
        u(&rep["clients"][0]["frames_posed"]),
        120,
        "the client went on alone"
    );
    let _ = refused;
    let srv = report(&server_out);
    assert_eq!(
        u(&srv["bridges"]["bridge"]["hellos_refused"]),
        1,
        "{}",
        srv["bridges"]
    );
    assert_eq!(srv["remote_clients"].as_array().unwrap().len(), 1);
}

/// The network between a client and its server fails twice in the middle of a real-time
/// run (through [`net_proxy::Relay`]): every connection is cut, then a 30 s partition
/// passes nothing. The client's local services never wait (every frame is posed), its
/// bridge reconnects, the keyframes lost on the way come again from the tracker (which
/// waits for the server after the end of its stream), and at the end every keyframe is
/// applied and acknowledged once, in the one map the client started.
#[test]
fn a_cut_connection_and_a_30_s_partition_lose_no_keyframe() {
    let dir = tempdir();
    let frames = 500;
    let ds = synthetic(&dir.path().join("data"), "loop", frames, None);
    let port = free_port();
    let server_out = dir.path().join("server");
    let server = serve(port, &server_out, "remote_cut_srv", 1, &[]);
    let relay = net_proxy::Relay::start(port, Duration::ZERO);
    let out = dir.path().join("c");
    let window = ["--set", "tracker.window=6"];
    let mut run = client(&ds[0], &out, relay.port, "walker", "remote_cut_c", &window)
        .spawn()
        .expect("start shoal client");
    std::thread::sleep(Duration::from_secs(6));
    relay.cut();
    std::thread::sleep(Duration::from_secs(4));
    relay.partition(true);
    std::thread::sleep(Duration::from_secs(30));
    relay.partition(false);
    assert!(run.wait().unwrap().success(), "the client failed");
    stop(server);
    let srv = report(&server_out);
    let rep = report(&out);
    let c = &rep["clients"][0];
    assert_eq!(
        u(&c["frames_posed"]),
        frames as u64,
        "every frame posed: {c:#}"
    );
    let sent = u(&c["keyframes_sent"]);
    assert!(sent >= 10, "{sent} keyframes");
    assert_eq!(u(&c["keyframes_acked"]), sent, "{c:#}");
    let me = &srv["remote_clients"][0];
    assert_eq!(u(&me["keyframes_applied"]), sent, "{me}");
    assert_eq!(u(&me["maps"]), 1, "the client rejoined its map: {me}");
    let bridge = &rep["bridges"]["bridge:0"];
    eprintln!(
        "{sent} keyframes sent and acknowledged over {} connections; bridge {bridge}; server \
         {me}",
        relay.connections()
    );
    assert!(
        relay.connections() >= 3,
        "{} connections",
        relay.connections()
    );
    assert!(u(&bridge["link_losses"]) >= 1, "{bridge}");
    assert!(u(&bridge["connects"]) >= 2, "{bridge}");
}

/// A server with `--auth` serves a known client (every keyframe acknowledged, also through
/// its `--max-keyframe-rate` of 1 a second: the keyframes over it are refused, counted and
/// sent again) and refuses one with a wrong password, which says so and goes on alone; the
/// server counts the refusal. Which keys each known client may use is held by zenoh's
/// access control (`bridge::auth`'s test).
#[test]
fn only_known_clients_with_their_credentials_are_served() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "two-agents", 120, None);
    let port = free_port();
    let known = dir.path().join("clients.txt");
    std::fs::write(&known, "alice:correct horse\nbob:battery staple\n").unwrap();
    let (alice_key, mallory_key) = (dir.path().join("alice.txt"), dir.path().join("m.txt"));
    std::fs::write(&alice_key, "alice:correct horse\n").unwrap();
    std::fs::write(&mallory_key, "bob:guess\n").unwrap();
    let server_out = dir.path().join("server");
    let auth = [
        "--auth",
        known.to_str().unwrap(),
        "--max-keyframe-rate",
        "1",
    ];
    let server = serve(port, &server_out, "remote_auth_srv", 2, &auth);
    let (a, m) = (dir.path().join("a"), dir.path().join("m"));
    let alice = ["--lockstep", "--auth", alice_key.to_str().unwrap()];
    let ok = client(&ds[0], &a, port, "alice", "remote_auth_a", &alice)
        .output()
        .unwrap();
    succeeded(&ok);
    let mallory = [
        "--lockstep",
        "--auth",
        mallory_key.to_str().unwrap(),
        "--set",
        "tracker.end_wait_s=12",
    ];
    let refused = client(&ds[1], &m, port, "bob", "remote_auth_m", &mallory)
        .output()
        .unwrap();
    assert!(refused.status.success(), "the refused client still ran");
    stop(server);
    let rep = report(&a);
    let c = &rep["clients"][0];
    let sent = u(&c["keyframes_sent"]);
    assert!(sent >= 3, "{c:#}");
    assert_eq!(u(&c["keyframes_acked"]), sent, "{c:#}");
    let rep = report(&m);
    let text = serde_json::to_string(&rep["errors"]).unwrap();
    assert!(
        text.contains("refused the credential of \\\"bob\\\""),
        "{text}"
    );
    assert_eq!(u(&rep["clients"][0]["keyframes_acked"]), 0);
    assert_eq!(u(&rep["clients"][0]["frames_posed"]), 120, "went on alone");
    let srv = report(&server_out);
    let bridge = &srv["bridges"]["bridge"];
    eprintln!("alice: {sent} keyframes acknowledged; server bridge {bridge}");
    assert!(u(&bridge["auth_refused"]) >= 1, "{bridge}");
    assert!(u(&bridge["keyframes_over_rate"]) >= 1, "{bridge}");
    let clients = srv["remote_clients"].as_array().unwrap();
    assert_eq!(clients.len(), 1, "{clients:?}");
    assert_eq!(u(&clients[0]["keyframes_applied"]), sent);
}

/// The client's tracker is SIGKILLed in the middle of a 30 s partition, holding keyframes
/// it sent and never saw acknowledged: a remote client's spool keeps every keyframe until
/// the mapper acknowledges it (`tracker.spool_until_ack`), so its successor sends them
/// again from disk, and when the network is back every keyframe reaches the server once
/// (the mapper's acknowledgements, and its count, agree); the spool is empty at the end.
#[test]
fn a_client_killed_during_a_partition_resends_from_its_spool() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "loop", 500, None);
    let port = free_port();
    let server_out = dir.path().join("server");
    let server = serve(port, &server_out, "remote_spool_srv", 1, &[]);
    let relay = net_proxy::Relay::start(port, Duration::ZERO);
    let out = dir.path().join("c");
    let args = ["--set", "tracker.window=6", "--kill", "tracker:0@14"];
    let mut run = client(&ds[0], &out, relay.port, "walker", "remote_spool_c", &args)
        .spawn()
        .expect("start shoal client");
    std::thread::sleep(Duration::from_secs(6));
    relay.partition(true);
    std::thread::sleep(Duration::from_secs(30));
    relay.partition(false);
    assert!(run.wait().unwrap().success(), "the client failed");
    stop(server);
    let rep = report(&out);
    let c = &rep["clients"][0];
    let at_crash = u(&c["keyframes_unacked_at_crash"]);
    assert!(at_crash >= 1, "the kill found keyframes in flight: {c:#}");
    assert!(u(&c["keyframes_recovered"]) >= at_crash, "{c:#}");
    let srv = report(&server_out);
    let me = &srv["remote_clients"][0];
    eprintln!("{at_crash} in flight at the kill; client {c}; server {me}");
    // Every acknowledgement is the mapper's; one the partition swallowed comes again for
    // the keyframe re-sent from the spool (applied once).
    let (applied, acked) = (u(&me["keyframes_applied"]), u(&c["keyframes_acked"]));
    assert!(
        applied <= acked && acked <= applied + at_crash,
        "{me} {c:#}"
    );
    assert!(applied >= 10, "{me}");
    // (The successor's new monocular session is a map of its own on the server until the
    // loop closer finds where it overlaps the first: one or two maps, both this client's.)
    let spool: Vec<_> = std::fs::read_dir(out.join("spool").join("c0"))
        .map(|d| d.flatten().map(|e| e.path()).collect())
        .unwrap_or_default();
    assert!(spool.is_empty(), "left in the spool: {spool:?}");
}

/// A client 50 ms of round trip away (25 ms each way through [`net_proxy::Relay`]; `tc
/// netem` would also drop packets, but its kernel module is not on every test machine):
/// the hello, every keyframe and every acknowledgement cross, and each round trip the
/// bridge measured includes the network's 50 ms.
#[test]
fn a_client_50_ms_away_is_served() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "two-agents", 120, None);
    let port = free_port();
    let server_out = dir.path().join("server");
    let server = serve(port, &server_out, "remote_far_srv", 1, &[]);
    let relay = net_proxy::Relay::start(port, Duration::from_millis(25));
    let out = dir.path().join("c");
    let run = client(
        &ds[0],
        &out,
        relay.port,
        "far",
        "remote_far_c",
        &["--lockstep"],
    )
    .output()
    .unwrap();
    succeeded(&run);
    stop(server);
    let (rep, sent) = all_acked(&out, 3);
    let bridge = &rep["bridges"]["bridge:0"];
    eprintln!("{sent} keyframes 50 ms away; bridge {bridge}");
    assert_eq!(u(&bridge["roundtrips"]), sent, "{bridge}");
    assert!(u(&bridge["roundtrip_us_p50"]) >= 50_000, "{bridge}");
}

/// The same client runs twice against one server (a phone's second session): the second
/// run's tracker numbers its sessions and keyframes from 1 again, and the server keeps the
/// runs apart (`bridge::run_ids`: each run a start base past the earlier ones). Every
/// keyframe of both runs is applied, none is acknowledged as a re-send of the first run's
/// without being applied, and the two runs' maps of the same place merge.
#[test]
fn a_second_run_of_a_client_is_applied_not_taken_for_re_sends() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "two-agents", 200, None);
    let port = free_port();
    let server_out = dir.path().join("server");
    let server = serve(port, &server_out, "remote_runs_srv", 1, &[]);
    let mut sent = 0;
    for run in 0..2 {
        let out = dir.path().join(format!("run{run}"));
        let r = client(
            &ds[0],
            &out,
            port,
            "walker",
            "remote_runs_c",
            &["--lockstep"],
        )
        .output()
        .unwrap();
        succeeded(&r);
        let (rep, n) = all_acked(&out, 5);
        let bridge = &rep["bridges"]["bridge:0"];
        let base = u(&bridge["start_base"]);
        assert!((base == 0) == (run == 0), "run {run}: {bridge}");
        sent += n;
    }
    stop(server);
    let srv = report(&server_out);
    let me = &srv["remote_clients"][0];
    eprintln!(
        "{sent} keyframes in two runs; server {me}; maps {}",
        srv["maps"]
    );
    assert_eq!(me["name"], "walker");
    assert_eq!(u(&me["keyframes_applied"]), sent, "{me}");
    assert_eq!(u(&me["keyframes_received"]), sent, "{me}");
    assert!(u(&srv["merges"]) >= 1, "the runs' maps: {}", srv["maps"]);
}

/// A saved map served remotely: the server starts from A's file (`shoal serve --load-map`),
/// a monocular client given the same file (`shoal client --load-map`) relocalises in it
/// within its first frames, and the server takes its session into the loaded map at its
/// first keyframe: one map with both clients, no merge, every keyframe acknowledged.
#[test]
fn a_client_of_a_server_with_a_saved_map_starts_in_it() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "loop", 200, None);
    let file = dir.path().join("a.shoalmap");
    let f = file.to_str().unwrap();
    let a = ["--lockstep", "--frames", "0..60", "--save-map", f];
    let out_a = dir.path().join("a");
    assert!(run_pipeline(&[&ds[0]], &out_a, "remote_map_a", &a)
        .status
        .success());
    let port = free_port();
    let server_out = dir.path().join("server");
    let server = serve(port, &server_out, "remote_map_srv", 1, &["--load-map", f]);
    let out = dir.path().join("b");
    let extra = ["--lockstep", "--load-map", f];
    let r = client(&ds[0], &out, port, "b", "remote_map_c", &extra)
        .output()
        .unwrap();
    succeeded(&r);
    let (rep, _) = all_acked(&out, 3);
    stop(server);
    let prior = &rep["clients"][0]["prior_map"];
    let t_reloc = prior["relocalised_t_s"].as_f64().expect("relocalised");
    let t0 = datasets::open(&ds[0]).unwrap().frames[0].t_ns as f64 * 1e-9;
    assert!(
        t_reloc - t0 < 0.2,
        "relocalised {} s in: {prior}",
        t_reloc - t0
    );
    let srv = report(&server_out);
    let m: mapper::MapperCounters = service_counters(&srv, "mapper");
    assert_eq!(m.client(0).sessions_joined, 1, "{:?}", m.client(0));
    assert_eq!(u(&srv["merges"]), 0);
    let maps = srv["maps"].as_array().unwrap();
    assert_eq!(maps.len(), 1, "{maps:?}");
    assert_eq!(maps[0]["clients"], serde_json::json!([0, 8_388_608]));
    assert!(
        srv["map_loaded"]["keyframes"].as_u64().unwrap() >= 5,
        "{}",
        srv["map_loaded"]
    );
}

/// A server on a `tls/` endpoint (`--tls-cert`, `--tls-key`; with `--auth`): a client
/// given the CA that signed its certificate (`--tls-ca`) is served, every keyframe
/// acknowledged, and nothing it sends crosses in the clear: the relay between them sees
/// neither its hello nor its name, which it does see from the same client of a `tcp/`
/// server. A client given another CA does not trust the server, says so and goes on alone.
#[test]
fn tls_encrypts_what_crosses_and_a_client_checks_the_server() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "two-agents", 120, None);
    let tls = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/tls");
    let file = |n: &str| tls.join(n).to_str().unwrap().to_string();
    let (known, key) = (dir.path().join("clients.txt"), dir.path().join("alice.txt"));
    std::fs::write(&known, "alice:pa55\n").unwrap();
    std::fs::write(&key, "alice:pa55\n").unwrap();
    let (known, key) = (known.to_str().unwrap(), key.to_str().unwrap());
    let (cert, pkey) = (file("server.pem"), file("server.key"));
    // (scheme, the client's CA, whether it is served)
    let cases = [
        ("tcp", None, true),
        ("tls", Some(file("ca.pem")), true),
        ("tls", Some(file("other_ca.pem")), false),
    ];
    for (i, (scheme, ca, served)) in cases.into_iter().enumerate() {
        let port = free_port();
        let mut extra = vec!["--auth", known];
        if scheme == "tls" {
            extra.extend(["--tls-cert", &cert, "--tls-key", &pkey]);
        }
        let listen = format!("{scheme}/127.0.0.1:{port}");
        let server_out = dir.path().join(format!("server{i}"));
        let test = format!("remote_tls_srv{i}");
        let server = start_server(serve_cmd(&listen, &server_out, &test, 1, &extra), port);
        let relay = net_proxy::Relay::start(port, Duration::ZERO);
        let mut args = vec![
            "--lockstep",
            "--auth",
            key,
            "--set",
            "tracker.end_wait_s=12",
        ];
        if let Some(ca) = &ca {
            args.extend(["--tls-ca", ca]);
        }
        let endpoint = format!("{scheme}/127.0.0.1:{}", relay.port);
        let out = dir.path().join(format!("c{i}"));
        let test = format!("remote_tls_c{i}");
        let run = client_of(&endpoint, &ds[0], &out, "alice", &test, &args)
            .output()
            .unwrap();
        succeeded(&run);
        stop(server);
        let rep = report(&out);
        let c = &rep["clients"][0];
        let (sent, acked) = (u(&c["keyframes_sent"]), u(&c["keyframes_acked"]));
        let clear = relay.saw(b"shoal-hello") || relay.saw(b"alice");
        eprintln!("{scheme}, CA {ca:?}: {acked} of {sent} acknowledged; in the clear: {clear}");
        if !served {
            let text = serde_json::to_string(&rep["errors"]).unwrap();
            assert!(text.contains("--tls-ca"), "{text}");
            assert_eq!(acked, 0, "{c:#}");
            assert_eq!(u(&c["frames_posed"]), 120, "went on alone");
            continue;
        }
        assert!(sent >= 3, "{c:#}");
        assert_eq!(acked, sent, "{c:#}");
        assert_eq!(clear, scheme == "tcp", "what crossed {scheme} in the clear");
    }
}

/// A client 50 ms of round trip away on a link that also drops 1 % of the packets each way
/// ([`net_proxy::lossy::LossyLink`]: the server and the client each in a network namespace
/// of its own, so the server listens off loopback, which needs `--auth`). Every keyframe is
/// applied and acknowledged end to end, once; the link really dropped packets on the way.
#[test]
#[cfg_attr(
    not(shoal_netns),
    ignore = "needs root, /dev/net/tun and `ip netns` (a lossy link between two namespaces)"
)]
fn a_client_over_a_slow_lossy_link_loses_no_keyframe() {
    use net_proxy::lossy::{LossyLink, SERVER_ADDR};
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "two-agents", 240, None);
    let link = LossyLink::start(Duration::from_millis(25), 0.01);
    let (known, key) = (dir.path().join("clients.txt"), dir.path().join("far.txt"));
    std::fs::write(&known, "far:over the hills\n").unwrap();
    std::fs::write(&key, "far:over the hills\n").unwrap();
    let server_out = dir.path().join("server");
    let endpoint = format!("tcp/{SERVER_ADDR}:7447");
    let auth = ["--auth", known.to_str().unwrap()];
    let serve = serve_cmd(&endpoint, &server_out, "remote_lossy_srv", 1, &auth);
    let server = LossyLink::exec_in(&link.server_ns, &serve)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("start shoal serve in its namespace");
    wait_listening(server.id(), 7447);
    let out = dir.path().join("c");
    let args = ["--lockstep", "--auth", key.to_str().unwrap()];
    let run = client_of(&endpoint, &ds[0], &out, "far", "remote_lossy_c", &args);
    let run = LossyLink::exec_in(&link.client_ns, &run)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .output()
        .unwrap();
    succeeded(&run);
    stop(server);
    let (rep, sent) = all_acked(&out, 5);
    let me = &report(&server_out)["remote_clients"][0];
    assert_eq!(u(&me["keyframes_applied"]), sent, "{me}");
    let bridge = &rep["bridges"]["bridge:0"];
    eprintln!(
        "{sent} keyframes over the lossy link ({} packets carried, {} dropped); bridge {bridge}",
        link.carried(),
        link.dropped()
    );
    assert!(link.dropped() >= 5, "the link dropped {}", link.dropped());
    assert_eq!(u(&bridge["roundtrips"]), sent, "{bridge}");
    assert!(u(&bridge["roundtrip_us_p50"]) >= 50_000, "{bridge}");
}

/// Waits until process `pid` (in a namespace of its own) listens on TCP `port`, from its
/// `/proc/PID/net/tcp` (which lists the sockets of the process's namespace).
fn wait_listening(pid: u32, port: u16) {
    let deadline = Instant::now() + Duration::from_secs(60);
    let local = format!(":{port:04X} ");
    loop {
        let table = std::fs::read_to_string(format!("/proc/{pid}/net/tcp")).unwrap_or_default();
        // Columns: sl, local_address, rem_address, st (0A: LISTEN).
        let listening = table.lines().any(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            f.len() > 3 && format!("{} ", f[1]).ends_with(&local) && f[3] == "0A"
        });
        if listening {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "the server never listened on {port}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}
