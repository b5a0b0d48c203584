//! What produced a run, recorded in `report.json` so a result can be reproduced: the command
//! line, the program version and git commit it was built from, the full run configuration,
//! and a checksum of every input dataset.
//!
//! Dataset checksum: every regular file under the dataset folder (symbolic links to files
//! followed, to folders not), in sorted relative-path order; each file's content is hashed
//! with CRC-32 (`crc32fast`, SIMD: the reading dominates), and the dataset checksum is the
//! FNV-1a 64 of the manifest of `relative path, size, CRC-32` lines. Any change of a file's
//! content, size or name, or an added or removed file, changes it.
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::Serialize;

/// Commit the binary was built from (`unknown` without git), set by `build.rs`.
pub const GIT_COMMIT: &str = env!("SHOAL_GIT_COMMIT");

/// `true` / `false`: the build's tracked files differed from [`GIT_COMMIT`]; `unknown`.
pub const GIT_DIRTY: &str = env!("SHOAL_GIT_DIRTY");

/// The provenance section of the report.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Provenance {
    /// The launcher's command line, as given.
    pub command_line: Vec<String>,
    /// Program version (`Cargo.toml`).
    pub version: String,
    /// Git commit of the build (`unknown` without git).
    pub git_commit: String,
    /// True when the build had uncommitted changes to tracked files (`None`: unknown).
    pub git_dirty: Option<bool>,
    /// The full run configuration.
    pub config: serde_json::Value,
    /// One checksum per input dataset, in client order.
    pub datasets: Vec<DatasetChecksum>,
}

impl Provenance {
    /// The provenance of this process's run of `config` with dataset checksums `datasets`.
    pub fn of(config: serde_json::Value, datasets: Vec<DatasetChecksum>) -> Self {
        Self {
            command_line: std::env::args_os()
                .map(|a| a.to_string_lossy().into_owned())
                .collect(),
            version: env!("CARGO_PKG_VERSION").to_string(),
            git_commit: GIT_COMMIT.to_string(),
            git_dirty: match GIT_DIRTY {
                "true" => Some(true),
                "false" => Some(false),
                _ => None,
            },
            config,
            datasets,
        }
    }
}

/// Checksum of one dataset folder.
#[derive(Debug, Clone, Default, Serialize, PartialEq)]
pub struct DatasetChecksum {
    /// The dataset folder.
    pub path: String,
    /// Files hashed.
    pub files: u64,
    /// Bytes hashed.
    pub bytes: u64,
    /// FNV-1a 64 of the manifest (relative path, size, CRC-32 of each file), 16 hex digits;
    /// `None` when the folder could not be read (`error` says why).
    pub checksum: Option<String>,
    /// Why there is no checksum.
    pub error: Option<String>,
    /// Time spent hashing, s.
    pub hash_s: f64,
}

/// Checksums of `datasets` (see the module documentation).
pub fn dataset_checksums(datasets: &[PathBuf]) -> Vec<DatasetChecksum> {
    datasets.iter().map(|d| dataset_checksum(d)).collect()
}

/// Checksum of the dataset folder `root`; a read error is reported in the result.
pub fn dataset_checksum(root: &Path) -> DatasetChecksum {
    let start = Instant::now();
    let mut sum = DatasetChecksum {
        path: root.display().to_string(),
        ..Default::default()
    };
    match manifest(root) {
        Ok((text, files, bytes)) => {
            sum.files = files;
            sum.bytes = bytes;
            sum.checksum = Some(format!("{:016x}", fnv1a64(text.as_bytes())));
        }
        Err(e) => sum.error = Some(e),
    }
    sum.hash_s = start.elapsed().as_secs_f64();
    sum
}

/// The manifest of `root` (`relative path \t size \t crc32` lines in sorted path order),
/// the number of files and their bytes. A dataset that is one file (an MCAP recording) is
/// its own one-line manifest, named by its file name.
fn manifest(root: &Path) -> Result<(String, u64, u64), String> {
    if root.is_file() {
        let name = root.file_name().map(|n| n.to_string_lossy().into_owned());
        let dir = root.parent().unwrap_or(Path::new("."));
        return manifest_of(dir, name.into_iter().collect());
    }
    let mut files = Vec::new();
    list_files(root, "", &mut files)?;
    manifest_of(root, files)
}

/// The manifest of `files` (paths relative to `root`).
fn manifest_of(root: &Path, mut files: Vec<String>) -> Result<(String, u64, u64), String> {
    files.sort();
    let mut text = String::new();
    let mut bytes = 0;
    let mut buf = vec![0u8; 1 << 20];
    for rel in &files {
        let path = root.join(rel);
        let (crc, size) =
            crc32_file(&path, &mut buf).map_err(|e| format!("{}: {e}", path.display()))?;
        bytes += size;
        text.push_str(&format!("{rel}\t{size}\t{crc:08x}\n"));
    }
    Ok((text, files.len() as u64, bytes))
}

/// Adds the regular files under `dir` (relative paths with `/`, prefixed by `rel`) to `out`.
fn list_files(dir: &Path, rel: &str, out: &mut Vec<String>) -> Result<(), String> {
    let rd = std::fs::read_dir(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    for entry in rd {
        let entry = entry.map_err(|e| format!("{}: {e}", dir.display()))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        let rel_name = if rel.is_empty() {
            name
        } else {
            format!("{rel}/{name}")
        };
        let ft = entry
            .file_type()
            .map_err(|e| format!("{}: {e}", entry.path().display()))?;
        if ft.is_dir() {
            list_files(&entry.path(), &rel_name, out)?;
        } else if ft.is_file() || (ft.is_symlink() && entry.path().is_file()) {
            out.push(rel_name);
        }
    }
    Ok(())
}

/// CRC-32 and size of the file at `path`, read through `buf`.
fn crc32_file(path: &Path, buf: &mut [u8]) -> std::io::Result<(u32, u64)> {
    let mut f = std::fs::File::open(path)?;
    let mut h = crc32fast::Hasher::new();
    let mut size = 0u64;
    loop {
        let n = f.read(buf)?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
        size += n as u64;
    }
    Ok((h.finalize(), size))
}

/// FNV-1a, 64 bits.
fn fnv1a64(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(*b)).wrapping_mul(0x0100_0000_01b3)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn checksum_is_stable_and_sees_content_names_and_new_files() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        std::fs::create_dir_all(root.join("cam0/data")).unwrap();
        std::fs::write(root.join("cam0/data/1.png"), b"pixels one").unwrap();
        std::fs::write(root.join("cam0/data/2.png"), b"pixels two").unwrap();
        std::fs::write(root.join("times.txt"), b"1\n2\n").unwrap();
        let a = dataset_checksum(root);
        assert_eq!((a.files, a.bytes), (3, 24));
        assert!(a.error.is_none(), "{a:?}");
        let first = a.checksum.clone().unwrap();
        assert_eq!(first.len(), 16);
        assert_eq!(dataset_checksum(root).checksum, a.checksum, "stable");
        // One byte of one file.
        std::fs::write(root.join("cam0/data/2.png"), b"pixels twO").unwrap();
        let b = dataset_checksum(root).checksum.unwrap();
        assert_ne!(b, first);
        // Same contents under swapped names.
        std::fs::write(root.join("cam0/data/1.png"), b"pixels twO").unwrap();
        std::fs::write(root.join("cam0/data/2.png"), b"pixels one").unwrap();
        assert_ne!(dataset_checksum(root).checksum.unwrap(), b);
        // Back to the original: the original checksum.
        std::fs::write(root.join("cam0/data/1.png"), b"pixels one").unwrap();
        std::fs::write(root.join("cam0/data/2.png"), b"pixels two").unwrap();
        assert_eq!(dataset_checksum(root).checksum.unwrap(), first);
        // An added empty file.
        std::fs::write(root.join("notes"), b"").unwrap();
        assert_ne!(dataset_checksum(root).checksum.unwrap(), first);
        // A missing folder: no checksum, the reason.
        let m = dataset_checksum(&root.join("missing"));
        assert!(m.checksum.is_none() && m.error.is_some(), "{m:?}");
    }

    /// The cost of the checksum on a real dataset, against FNV-1a 64 over the whole
    /// content (the hand-rolled alternative): `SHOAL_CHECKSUM_BENCH=/path/to/dataset cargo
    /// test --bin shoal checksum_cost -- --ignored --nocapture` (figures in BENCHMARKS.md).
    #[test]
    #[ignore = "benchmark: needs SHOAL_CHECKSUM_BENCH"]
    fn checksum_cost() {
        let Ok(dir) = std::env::var("SHOAL_CHECKSUM_BENCH") else {
            panic!("set SHOAL_CHECKSUM_BENCH to a dataset folder");
        };
        let root = Path::new(&dir);
        for round in 0..3 {
            let t = Instant::now();
            let sum = dataset_checksum(root);
            let crc_s = t.elapsed().as_secs_f64();
            let mut files = Vec::new();
            list_files(root, "", &mut files).unwrap();
            files.sort();
            let t = Instant::now();
            let mut h = 0u64;
            for f in &files {
                h ^= fnv1a64(&std::fs::read(root.join(f)).unwrap());
            }
            let fnv_s = t.elapsed().as_secs_f64();
            let mb = sum.bytes as f64 / 1e6;
            println!(
                "round {round}: {} files, {mb:.1} MB: crc32 manifest {:.1} ms ({:.0} MB/s), \
                 fnv1a64 of the content {:.1} ms ({:.0} MB/s) [{h:x}]",
                sum.files,
                crc_s * 1e3,
                mb / crc_s,
                fnv_s * 1e3,
                mb / fnv_s
            );
        }
    }

    #[test]
    fn fnv1a64_reference_values() {
        assert_eq!(fnv1a64(b""), 0xcbf2_9ce4_8422_2325);
        assert_eq!(fnv1a64(b"a"), 0xaf63_dc4c_8601_ec8c);
    }
}
