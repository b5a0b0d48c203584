//! Encryption on the wire (issue 22): zenoh's TLS transport (rustls). The server listens on
//! `tls/HOST:PORT` with its certificate chain and private key (PEM files); a client
//! connects to `tls/HOST:PORT` and checks the server's certificate against the CA
//! certificate it is given, and the host it connects to against the certificate's names. TLS
//! encrypts the keyframes and the feedback; who may use the server is still `--auth`'s (the
//! user-password exchange then runs inside the TLS link).
use std::path::Path;

use anyhow::Context;

/// The scheme of TLS endpoints.
pub const SCHEME: &str = "tls/";

/// Whether `endpoint` is a TLS one.
pub fn is_tls(endpoint: &str) -> bool {
    endpoint.starts_with(SCHEME)
}

/// Checks that `path` is a PEM file holding a `what` block (`CERTIFICATE`, `PRIVATE KEY`):
/// an error names the file and what it lacks.
pub fn check_pem(path: &Path, what: &str) -> anyhow::Result<()> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("reading TLS file {}", path.display()))?;
    let begins = text
        .lines()
        .any(|l| l.starts_with("-----BEGIN ") && l.contains(what) && l.ends_with("-----"));
    anyhow::ensure!(
        begins,
        "{}: not a PEM file with a {what} (expected a `-----BEGIN … {what}-----` line)",
        path.display()
    );
    Ok(())
}

/// The server's side: its certificate (chain) and private key.
pub fn server_config(c: &mut zenoh::Config, cert: &Path, key: &Path) -> anyhow::Result<()> {
    check_pem(cert, "CERTIFICATE")?;
    check_pem(key, "PRIVATE KEY")?;
    crate::set_config(c, "transport/link/tls/listen_certificate", &path(cert)?)?;
    crate::set_config(c, "transport/link/tls/listen_private_key", &path(key)?)
}

/// A client's side: the CA certificate the server's must chain to.
pub fn client_config(c: &mut zenoh::Config, ca: &Path) -> anyhow::Result<()> {
    check_pem(ca, "CERTIFICATE")?;
    crate::set_config(c, "transport/link/tls/root_ca_certificate", &path(ca)?)?;
    crate::set_config(c, "transport/link/tls/verify_name_on_connect", "true")
}

/// A path as a JSON5 string.
fn path(p: &Path) -> anyhow::Result<String> {
    let s = p
        .to_str()
        .with_context(|| format!("a TLS path that is not UTF-8: {}", p.display()))?;
    Ok(format!("{s:?}"))
}

/// The launcher's check before any service starts: `endpoint` (of `flag`) is TLS exactly
/// when the TLS files are given, and each given file holds its PEM block. `files`: each
/// one's flag, path if given, and PEM block (`CERTIFICATE`, `PRIVATE KEY`).
pub fn check(
    flag: &str,
    endpoint: &str,
    files: &[(&str, Option<&Path>, &str)],
) -> anyhow::Result<()> {
    let given: Vec<(&str, bool)> = files.iter().map(|f| (f.0, f.1.is_some())).collect();
    check_endpoint(flag, endpoint, &given)?;
    for (_, path, what) in files {
        if let Some(p) = path {
            check_pem(p, what)?;
        }
    }
    Ok(())
}

/// Checks that `endpoint` (of `flag`) is TLS exactly when TLS files (`files`, their flags)
/// are given.
pub fn check_endpoint(flag: &str, endpoint: &str, files: &[(&str, bool)]) -> anyhow::Result<()> {
    let given: Vec<&str> = files.iter().filter(|f| f.1).map(|f| f.0).collect();
    let missing: Vec<&str> = files.iter().filter(|f| !f.1).map(|f| f.0).collect();
    match (is_tls(endpoint), given.is_empty(), missing.is_empty()) {
        (true, _, false) => anyhow::bail!(
            "{flag} {endpoint} is a TLS endpoint: give {}",
            missing.join(" and ")
        ),
        (false, false, _) => anyhow::bail!(
            "{} given, but {flag} {endpoint} is not a TLS endpoint (tls/HOST:PORT)",
            given.join(" and ")
        ),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The endpoint and the files agree, or the error says what is missing; a file that is
    /// no PEM certificate is named.
    #[test]
    fn endpoints_and_files_agree() {
        let cert = [("--tls-cert", true), ("--tls-key", true)];
        assert!(check_endpoint("--listen", "tls/0.0.0.0:7447", &cert).is_ok());
        assert!(check_endpoint("--listen", "tcp/0.0.0.0:7447", &[("--tls-cert", false)]).is_ok());
        let e = check_endpoint(
            "--listen",
            "tls/h:1",
            &[("--tls-cert", true), ("--tls-key", false)],
        );
        assert!(e.unwrap_err().to_string().contains("give --tls-key"));
        let e = check_endpoint("--connect", "tcp/h:1", &[("--tls-ca", true)]);
        assert!(e.unwrap_err().to_string().contains("not a TLS endpoint"));
        let dir = std::env::temp_dir().join(format!("shoal_tls_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let bad = dir.join("ca.pem");
        std::fs::write(&bad, "not a certificate\n").unwrap();
        let e = check_pem(&bad, "CERTIFICATE").unwrap_err().to_string();
        assert!(e.contains("ca.pem") && e.contains("CERTIFICATE"), "{e}");
        std::fs::write(
            &bad,
            "-----BEGIN CERTIFICATE-----\nAA==\n-----END CERTIFICATE-----\n",
        )
        .unwrap();
        assert!(check_pem(&bad, "CERTIFICATE").is_ok());
        assert!(check_pem(&dir.join("none.pem"), "CERTIFICATE").is_err());
        std::fs::remove_dir_all(dir).unwrap();
    }
}
