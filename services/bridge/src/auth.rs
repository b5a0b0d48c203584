//! Only known clients (issue 22): `shoal serve --auth FILE` accepts only the clients of
//! `FILE`, and each only under its own name.
//!
//! - **Who may connect**: zenoh's user-password authentication. `FILE` holds
//!   `NAME:PASSWORD` lines (zenoh's dictionary format, which zenoh reads itself; blank lines
//!   are skipped); a client presents its own line (`shoal client --auth FILE`). zenoh checks the password by a challenge (an HMAC of a
//!   nonce), so it never crosses the network; the data itself is not encrypted (zenoh's TLS
//!   transport would, at the cost of rustls in the build).
//! - **What each may do**: zenoh's access control, default deny, allows a client to say
//!   hello, to publish keyframes under `shoal/kf/{its name}` and to receive
//!   `shoal/fb/{its name}`, nothing else: a client cannot publish into another client's
//!   keyframes, read another's feedback, or answer hellos in the server's place.
//! - **Counted**: a refused connection is seen only inside zenoh's handshake, which logs it;
//!   [`RefusalCounter`] counts those log events (the test of this module holds zenoh to the
//!   message it matches).
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use anyhow::Context;

use crate::wire;

/// One `NAME:PASSWORD` line of a credentials file.
#[derive(Clone, PartialEq, Eq)]
pub struct Credential {
    /// The client's name (zenoh's user).
    pub name: String,
    password: String,
}

impl std::fmt::Debug for Credential {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Credential({:?}, <password>)", self.name)
    }
}

/// The credentials of `path`: one `NAME:PASSWORD` per line, blank lines skipped; an error
/// names the file and line.
pub fn read_credentials(path: &Path) -> anyhow::Result<Vec<Credential>> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading credentials {}", path.display()))?;
    let mut out: Vec<Credential> = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() {
            continue;
        }
        let at = || format!("{}:{}", path.display(), i + 1);
        let Some((name, password)) = line.split_once(':') else {
            anyhow::bail!("{}: expected NAME:PASSWORD", at());
        };
        let (name, password) = (name.trim(), password.trim());
        if !wire::valid_name(name) {
            anyhow::bail!("{}: bad client name {name:?}", at());
        }
        if password.is_empty() {
            anyhow::bail!("{}: empty password for {name:?}", at());
        }
        if out.iter().any(|c| c.name == name) {
            anyhow::bail!("{}: {name:?} twice", at());
        }
        out.push(Credential {
            name: name.into(),
            password: password.into(),
        });
    }
    if out.is_empty() {
        anyhow::bail!("{}: no NAME:PASSWORD line", path.display());
    }
    Ok(out)
}

/// A client's one credential (its file has exactly one line).
pub fn client_credential(path: &Path) -> anyhow::Result<Credential> {
    let mut all = read_credentials(path)?;
    if all.len() != 1 {
        anyhow::bail!(
            "{}: a client's credentials file holds its one NAME:PASSWORD line, not {}",
            path.display(),
            all.len()
        );
    }
    Ok(all.remove(0))
}

/// Sets a client's zenoh user and password.
pub fn client_config(c: &mut zenoh::Config, cred: &Credential) -> anyhow::Result<()> {
    crate::set_config(c, "transport/auth/usrpwd/user", &json(&cred.name))?;
    crate::set_config(c, "transport/auth/usrpwd/password", &json(&cred.password))
}

/// Sets the server's zenoh dictionary (`file`, checked by [`read_credentials`]) and its
/// access control; the known names, in the file's order.
pub fn server_config(c: &mut zenoh::Config, file: &Path) -> anyhow::Result<Vec<String>> {
    let creds = read_credentials(file)?;
    let dict = file
        .to_str()
        .context("a credentials path that is not UTF-8")?;
    crate::set_config(c, "transport/auth/usrpwd/dictionary_file", &json(dict))?;
    crate::set_config(
        c,
        "access_control",
        &acl(creds.iter().map(|k| k.name.as_str())),
    )?;
    Ok(creds.into_iter().map(|k| k.name).collect())
}

/// The access control (zenoh's `access_control` section): default deny; each name may
/// query the hello and get its reply, publish its keyframes, subscribe to and receive its
/// feedback.
fn acl<'a>(names: impl Iterator<Item = &'a str>) -> String {
    let mut rules = vec![
        rule("hello_in", "query", "ingress", wire::HELLO_KEY),
        rule("hello_out", "reply", "egress", wire::HELLO_KEY),
        // The server's declarations reach the clients (what they may use is ingress).
        rule("declared", "declare_subscriber", "egress", "shoal/**"),
        rule("declared_q", "declare_queryable", "egress", "shoal/**"),
    ];
    let (mut subjects, mut policies) = (Vec::new(), Vec::new());
    for (i, name) in names.enumerate() {
        let (kf, fb) = (wire::keyframe_key(name), wire::feedback_key(name));
        rules.push(rule(&format!("kf{i}"), "put", "ingress", &kf));
        rules.push(rule(
            &format!("fbsub{i}"),
            "declare_subscriber",
            "ingress",
            &fb,
        ));
        rules.push(rule(&format!("fb{i}"), "put", "egress", &fb));
        subjects.push(format!(r#"{{"id":"c{i}","usernames":[{}]}}"#, json(name)));
        policies.push(format!(
            r#"{{"rules":["hello_in","hello_out","declared","declared_q","kf{i}","fbsub{i}","fb{i}"],"subjects":["c{i}"]}}"#
        ));
    }
    format!(
        r#"{{"enabled":true,"default_permission":"deny","rules":[{}],"subjects":[{}],"policies":[{}]}}"#,
        rules.join(","),
        subjects.join(","),
        policies.join(",")
    )
}

fn rule(id: &str, message: &str, flow: &str, key: &str) -> String {
    format!(
        r#"{{"id":{},"messages":[{}],"flows":[{}],"key_exprs":[{}],"permission":"allow"}}"#,
        json(id),
        json(message),
        json(flow),
        json(key)
    )
}

fn json(s: &str) -> String {
    format!("{s:?}")
}

/// Counts the connections zenoh refused for their credentials (no credential, an unknown
/// name, a wrong password), from the events zenoh logs in its handshake.
#[derive(Debug, Clone, Default)]
pub struct RefusalCounter(Arc<AtomicU64>);

/// What zenoh's accepting side says when a user-password check fails.
const REFUSAL_MARK: &str = "UsrPwd extension - Recv";

impl RefusalCounter {
    /// Installs the counter as this process's tracing subscriber (once; a second call
    /// returns a counter that stays at zero).
    pub fn install() -> Self {
        use tracing_subscriber::layer::SubscriberExt;
        let me = Self::default();
        let filter = tracing_subscriber::filter::Targets::new()
            .with_target("zenoh_transport::unicast", tracing::Level::DEBUG);
        let layer = tracing_subscriber::filter::Filtered::new(me.clone(), filter);
        let _ = tracing::subscriber::set_global_default(tracing_subscriber::registry().with(layer));
        me
    }

    /// Connections refused so far.
    pub fn count(&self) -> u64 {
        self.0.load(Ordering::Relaxed)
    }
}

impl<S: tracing::Subscriber> tracing_subscriber::Layer<S> for RefusalCounter {
    fn on_event(&self, event: &tracing::Event<'_>, _: tracing_subscriber::layer::Context<'_, S>) {
        struct Find(bool);
        impl tracing::field::Visit for Find {
            fn record_debug(&mut self, _: &tracing::field::Field, value: &dyn std::fmt::Debug) {
                self.0 |= format!("{value:?}").contains(REFUSAL_MARK);
            }
        }
        let mut find = Find(false);
        event.record(&mut find);
        if find.0 {
            self.0.fetch_add(1, Ordering::Relaxed);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;
    use zenoh::Wait;

    fn cred(name: &str, password: &str) -> Credential {
        Credential {
            name: name.into(),
            password: password.into(),
        }
    }

    fn open_client(port: u16, cred: Option<&Credential>) -> zenoh::Result<zenoh::Session> {
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let mut c = crate::zenoh_config("client", &endpoint, false).unwrap();
        if let Some(k) = cred {
            client_config(&mut c, k).unwrap();
        }
        zenoh::open(c).wait()
    }

    /// Over real zenoh sessions on loopback: a known client publishes its own keyframes but
    /// not another's, and receives only its own feedback; a wrong password, an unknown name
    /// and no credential are refused, and counted.
    #[test]
    fn only_known_clients_and_only_their_own_keys() {
        let dir = std::env::temp_dir().join(format!("shoal_auth_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("clients.txt");
        std::fs::write(&file, "alice:pa\n\nbob : pb\n").unwrap();
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let refusals = RefusalCounter::install();
        let mut config =
            crate::zenoh_config("router", &format!("tcp/127.0.0.1:{port}"), true).unwrap();
        let names = server_config(&mut config, &file).unwrap();
        assert_eq!(names, ["alice", "bob"]);
        let server = zenoh::open(config).wait().unwrap();
        let kf = server
            .declare_subscriber(wire::ALL_KEYFRAMES)
            .wait()
            .unwrap();

        let alice = open_client(port, Some(&cred("alice", "pa"))).expect("alice connects");
        let bob = open_client(port, Some(&cred("bob", "pb"))).expect("bob connects");
        let alice_fb = alice
            .declare_subscriber(wire::feedback_key("alice"))
            .wait()
            .unwrap();
        let bob_spy = bob
            .declare_subscriber(wire::feedback_key("alice"))
            .wait()
            .unwrap();
        let bob_all = bob.declare_subscriber("shoal/**").wait().unwrap();
        std::thread::sleep(Duration::from_millis(500));
        alice
            .put(wire::keyframe_key("alice"), "mine")
            .wait()
            .unwrap();
        alice
            .put(wire::keyframe_key("bob"), "forged")
            .wait()
            .unwrap();
        bob.put(wire::keyframe_key("alice"), "forged")
            .wait()
            .unwrap();
        server
            .put(wire::feedback_key("alice"), "ack")
            .wait()
            .unwrap();
        std::thread::sleep(Duration::from_millis(500));
        let got: Vec<String> = std::iter::from_fn(|| kf.try_recv().ok().flatten())
            .map(|s| format!("{} {}", s.key_expr(), s.payload().try_to_string().unwrap()))
            .collect();
        assert_eq!(got, ["shoal/kf/alice mine"], "only alice's own keyframe");
        assert!(
            alice_fb.try_recv().unwrap().is_some(),
            "alice's feedback reaches her"
        );
        assert!(
            bob_spy.try_recv().unwrap().is_none(),
            "bob reads alice's feedback"
        );
        // bob's wildcard subscriber hears only what bob put himself (delivered in his own
        // session), never alice's feedback.
        let heard: Vec<String> = std::iter::from_fn(|| bob_all.try_recv().ok().flatten())
            .map(|s| s.key_expr().to_string())
            .collect();
        assert_eq!(heard, ["shoal/kf/alice"], "bob hears others");

        let before = refusals.count();
        for bad in [
            Some(cred("alice", "wrong")),
            Some(cred("mallory", "pm")),
            None,
        ] {
            assert!(
                open_client(port, bad.as_ref()).is_err(),
                "{bad:?} connected"
            );
        }
        std::thread::sleep(Duration::from_millis(200));
        assert_eq!(refusals.count() - before, 3, "every refusal counted");
        std::fs::remove_dir_all(dir).unwrap();
    }

    #[test]
    fn credentials_files() {
        let dir = std::env::temp_dir().join(format!("shoal_cred_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let f = dir.join("c.txt");
        for (text, why) in [
            ("alice\n", ":1: expected NAME:PASSWORD"),
            ("a:x\nb c:y\n", ":2: bad client name"),
            ("a:\n", ":1: empty password"),
            ("a:x\na:y\n", ":2: \"a\" twice"),
            ("\n", "no NAME:PASSWORD"),
        ] {
            std::fs::write(&f, text).unwrap();
            let e = read_credentials(&f).unwrap_err().to_string();
            assert!(e.contains(why), "{text:?}: {e}");
        }
        std::fs::write(&f, "a:x\nb:y\n").unwrap();
        assert!(client_credential(&f).is_err(), "two lines for one client");
        std::fs::write(&f, "a:x:y\n").unwrap();
        let c = client_credential(&f).unwrap();
        assert_eq!((c.name.as_str(), c.password.as_str()), ("a", "x:y"));
        assert!(
            !format!("{c:?}").contains("x:y"),
            "the password is not printed"
        );
        std::fs::remove_dir_all(dir).unwrap();
    }
}
