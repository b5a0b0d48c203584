//! Build script of the `shoal` package. Each concern is its own function, called from `main`.
use std::path::Path;
use std::process::Command;

#[path = "build_support/shoal_data.rs"]
mod shoal_data;

fn main() {
    // Real-data tests (`tests/`): `cfg(shoal_data)` when `../shared/data` (or $SHOAL_DATA) exists.
    shoal_data::emit_data_cfg(Path::new(env!("CARGO_MANIFEST_DIR")));
    git_provenance();
    netns_cfg();
}

/// Emits `cfg(shoal_netns)` when this machine lets the tests make network namespaces joined
/// by TUN devices (root, `/dev/net/tun`, `ip netns`): the lossy-link test of `tests/remote.rs`
/// then runs, and is otherwise reported as ignored, with the reason.
fn netns_cfg() {
    println!("cargo::rustc-check-cfg=cfg(shoal_netns)");
    let root = std::fs::read_to_string("/proc/self/status").is_ok_and(|s| {
        s.lines()
            .find_map(|l| l.strip_prefix("Uid:"))
            .and_then(|l| l.split_whitespace().nth(1))
            == Some("0")
    });
    let tun = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open("/dev/net/tun")
        .is_ok();
    let probe = format!("shoal-build-probe-{}", std::process::id());
    let netns = root
        && tun
        && Command::new("ip")
            .args(["netns", "add", &probe])
            .output()
            .is_ok_and(|o| o.status.success());
    if netns {
        let _ = Command::new("ip").args(["netns", "del", &probe]).output();
        println!("cargo::rustc-cfg=shoal_netns");
    }
}

/// Emits `SHOAL_GIT_COMMIT` (the commit the binary is built from, `unknown` without git or
/// outside a git checkout) and `SHOAL_GIT_DIRTY` (`true` when tracked files differ from that
/// commit, `false` when they do not, `unknown` without git), which `report.json` records.
/// Reruns when HEAD moves (commit, checkout), when the index changes, and when a source file
/// of the workspace changes (an unstaged edit makes the tree dirty).
fn git_provenance() {
    let git = |args: &[&str]| -> Option<String> {
        let out = Command::new("git").args(args).output().ok()?;
        out.status
            .success()
            .then(|| String::from_utf8_lossy(&out.stdout).trim().to_string())
    };
    let commit = git(&["rev-parse", "HEAD"]).filter(|c| !c.is_empty());
    let dirty =
        match &commit {
            Some(_) => git(&["status", "--porcelain", "--untracked-files=no"])
                .map_or("unknown", |s| if s.is_empty() { "false" } else { "true" }),
            None => "unknown",
        };
    println!(
        "cargo:rustc-env=SHOAL_GIT_COMMIT={}",
        commit.as_deref().unwrap_or("unknown")
    );
    println!("cargo:rustc-env=SHOAL_GIT_DIRTY={dirty}");
    // HEAD, the branch it points to and the index (paths resolved by git: a worktree keeps
    // them outside the checkout).
    // A path that does not exist would make cargo rerun this script on every build.
    let watch = |p: &str| {
        if Path::new(p).exists() {
            println!("cargo:rerun-if-changed={p}");
        }
    };
    let branch = git(&["symbolic-ref", "-q", "HEAD"]);
    for name in ["HEAD", "index", "packed-refs"]
        .into_iter()
        .chain(branch.as_deref())
    {
        if let Some(p) = git(&["rev-parse", "--git-path", name]) {
            watch(&p);
        }
    }
    for p in [
        "build.rs",
        "Cargo.toml",
        "Cargo.lock",
        "src",
        "tests",
        "benches",
        "examples",
        "shm_schema",
        "slam_core",
        "datasets",
        "services",
    ] {
        watch(p);
    }
}
