//! Clients on other hosts (issue 22), as separate processes on this one: `shoal serve`
//! (mapper, loop closer, zenoh bridge) and `shoal client`s (ingests, tracker, bridge), each
//! with its own iceoryx2 prefix, talking only over TCP on loopback. Every keyframe a client
//! sends is acknowledged end to end by the server's mapper, also across a server that is
//! SIGKILLed in the middle of the run and started again; a client beyond the server's
//! capacity is refused with the reason.
mod common;

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::*;

/// A free TCP port on loopback.
fn free_port() -> u16 {
    let l = std::net::TcpListener::bind("127.0.0.1:0").expect("bind");
    l.local_addr().unwrap().port()
}

/// Starts `shoal serve` on `port` into `out` (`clients` slots); waits until it accepts
/// connections.
fn serve(port: u16, out: &Path, test: &str, clients: u32) -> Child {
    let child = shoal()
        .args(["serve", "--listen", &format!("tcp/127.0.0.1:{port}")])
        .arg("--out")
        .arg(out)
        .args([
            "--clients",
            &clients.to_string(),
            "--ipc-prefix",
            &prefix(test),
        ])
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

/// `shoal client` on `dataset` into `out` with `extra` arguments.
fn client(
    dataset: &Path,
    out: &Path,
    port: u16,
    name: &str,
    test: &str,
    extra: &[&str],
) -> Command {
    let mut cmd = shoal();
    cmd.args(["client", "--connect", &format!("tcp/127.0.0.1:{port}")])
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

/// Two clients of the `two-agents` scene on one server: each gets its own slot, every
/// keyframe it sends is applied by the server's mapper and acknowledged back (the client
/// counts only the mapper's acknowledgements), and the server merges the two maps.
#[test]
fn two_clients_on_a_remote_server_lose_no_keyframe_and_merge() {
    let dir = tempdir();
    let ds = synthetic(&dir.path().join("data"), "two-agents", 480, None);
    let port = free_port();
    let server_out = dir.path().join("server");
    let server = serve(port, &server_out, "remote_srv", 2);
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
    let mut server = serve(port, &server_out, "remote_kill_srv", 2);
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
    let server = serve(port, &server_out, "remote_kill_srv", 2);
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
    let server = serve(port, &server_out, "remote_full_srv", 1);
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
