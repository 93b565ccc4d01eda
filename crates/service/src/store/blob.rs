//! Content-addressed blob store for image bytes, `<2 hex>/<sha256>` under its root: a
//! local directory (`file://DIR`, the embedded default) or S3-compatible object storage
//! (`s3://BUCKET/PREFIX`, through the `object_store` crate, for replicas and workers on
//! many machines).
//!
//! Bytes are first *staged* in a local spool directory while they are hashed (one copy
//! buffer of memory, whatever the size), then *committed* to their content address.
//! Locally a commit is an atomic rename with fsyncs, so a crash leaves either the whole
//! blob or none; on S3 it is one PUT with `If-None-Match: *` (a conditional create), so
//! two replicas storing the same image store it once and neither overwrites the other.
//! The database row that names a blob is only written after the commit returns. Every
//! read verifies the bytes against their name.
//!
//! The API is blocking (call it from a blocking thread): the engine reads images from
//! its own threads. The S3 backend runs its requests on the runtime it was opened on.

use anyhow::Context;
use object_store::{ObjectStore, ObjectStoreExt, PutMode, PutOptions, PutPayload};
use sha2::{Digest, Sha256};
use std::fs::{self, File};
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Bytes copied into the blob directory's `tmp/` but not yet stored: read back with
/// [`Staged::read`], stored with [`BlobStore::commit`], removed when dropped.
#[derive(Debug)]
pub struct Staged {
    path: PathBuf,
    pub sha256: String,
    pub len: u64,
}

impl Staged {
    pub fn read(&self) -> io::Result<Vec<u8>> {
        fs::read(&self.path)
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        // After a commit the file has been renamed away; then there is nothing to remove.
        let _ = fs::remove_file(&self.path);
    }
}

/// Why staging failed: the source could not be read (a corrupt archive entry, a client
/// that went away) or the blob directory could not be written.
#[derive(Debug)]
pub enum StageError {
    Read(io::Error),
    Store(io::Error),
}

#[derive(Clone, Debug)]
pub struct BlobStore {
    /// Local spool for staged bytes (and other working files): always on this host.
    spool: PathBuf,
    backend: Backend,
}

#[derive(Clone, Debug)]
enum Backend {
    /// A directory of this host.
    Local { root: PathBuf },
    /// A bucket (and key prefix) of S3-compatible storage.
    S3 {
        store: Arc<dyn ObjectStore>,
        prefix: String,
        shown: String,
        runtime: tokio::runtime::Handle,
    },
}

/// SHA-256 of `bytes`, lower-case hex.
pub fn sha256_hex(bytes: &[u8]) -> String {
    hex::encode(Sha256::digest(bytes))
}

fn valid_hash(hash: &str) -> bool {
    hash.len() == 64
        && hash
            .bytes()
            .all(|b| b.is_ascii_hexdigit() && !b.is_ascii_uppercase())
}

/// A parsed `--blob-url`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum BlobUrl {
    Local(PathBuf),
    S3 { bucket: String, prefix: String },
}

impl BlobUrl {
    pub fn parse(url: &str) -> anyhow::Result<BlobUrl> {
        if let Some(path) = url.strip_prefix("file://") {
            if path.is_empty() {
                anyhow::bail!("blob URL {url:?}: expected file://DIR with a directory");
            }
            Ok(BlobUrl::Local(PathBuf::from(path)))
        } else if let Some(rest) = url.strip_prefix("s3://") {
            let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
            let valid = |c: char| c.is_ascii_lowercase() || c.is_ascii_digit() || ".-".contains(c);
            if bucket.len() < 3 || bucket.len() > 63 || !bucket.chars().all(valid) {
                anyhow::bail!("blob URL {url:?}: expected s3://BUCKET/PREFIX with a bucket name of 3-63 lower-case letters, digits, '.' or '-'");
            }
            let prefix = prefix.trim_matches('/');
            if prefix.split('/').any(|p| p == "." || p == "..") {
                anyhow::bail!("blob URL {url:?}: the prefix may not contain '.' or '..' segments");
            }
            Ok(BlobUrl::S3 {
                bucket: bucket.to_string(),
                prefix: prefix.to_string(),
            })
        } else {
            anyhow::bail!("blob URL {url:?}: expected file://DIR or s3://BUCKET/PREFIX")
        }
    }
}

impl BlobStore {
    /// A local blob directory (its spool is its own `tmp/`), created if missing.
    pub fn open_dir(root: &Path) -> io::Result<Self> {
        fs::create_dir_all(root.join("tmp"))?;
        Ok(Self {
            spool: root.join("tmp"),
            backend: Backend::Local {
                root: root.to_path_buf(),
            },
        })
    }

    /// Open the blob store at `url`, spooling under `data_dir` for remote stores. S3
    /// settings (credentials, region, endpoint, plain HTTP) come from the standard `AWS_*`
    /// variables; the bucket must exist and be reachable, checked here so a wrong
    /// setting fails at start and not at the first upload.
    pub async fn open(url: &str, data_dir: &Path) -> anyhow::Result<Self> {
        match BlobUrl::parse(url)? {
            BlobUrl::Local(root) => Self::open_dir(&root)
                .with_context(|| format!("opening blob directory {}", root.display())),
            BlobUrl::S3 { bucket, prefix } => {
                let store = object_store::aws::AmazonS3Builder::from_env()
                    .with_bucket_name(&bucket)
                    .build()
                    .with_context(|| format!("configuring S3 storage for {url}"))?;
                let blobs = Self {
                    spool: data_dir.join("spool"),
                    backend: Backend::S3 {
                        store: Arc::new(store),
                        prefix,
                        shown: url.to_string(),
                        runtime: tokio::runtime::Handle::current(),
                    },
                };
                blobs
                    .probe()
                    .await
                    .with_context(|| format!("reaching blob store {url}"))?;
                Ok(blobs)
            }
        }
    }

    /// Where blobs live, for logs and messages.
    pub fn describe(&self) -> String {
        match &self.backend {
            Backend::Local { root } => root.display().to_string(),
            Backend::S3 { shown, .. } => shown.clone(),
        }
    }

    /// Check that the store answers and can be written (readiness): a local probe file,
    /// or a HEAD on the bucket for S3 (a missing key is an answer; a refused connection,
    /// a missing bucket or bad credentials are not).
    pub async fn probe(&self) -> io::Result<()> {
        match &self.backend {
            Backend::Local { .. } => {
                let dir = self.tmp_dir()?;
                let probe = dir.join(format!("ready-{}", uuid::Uuid::new_v4().simple()));
                tokio::fs::write(&probe, b"ok")
                    .await
                    .map_err(|e| self.at("writing", &probe, e))?;
                // The probe is removed best-effort: a leftover in tmp/ is harmless.
                let _ = tokio::fs::remove_file(&probe).await;
                Ok(())
            }
            Backend::S3 { store, prefix, .. } => {
                let key = object_store::path::Path::from(format!("{prefix}/ready-probe"));
                match store.head(&key).await {
                    Ok(_) | Err(object_store::Error::NotFound { .. }) => Ok(()),
                    Err(e) => Err(remote(e)),
                }
            }
        }
    }

    /// The working directory for temporary files (created again if it has gone).
    pub fn tmp_dir(&self) -> io::Result<PathBuf> {
        fs::create_dir_all(&self.spool).map_err(|e| self.at("creating", &self.spool, e))?;
        Ok(self.spool.clone())
    }

    fn path_of(root: &Path, hash: &str) -> PathBuf {
        root.join(&hash[..2]).join(hash)
    }

    fn key_of(prefix: &str, hash: &str) -> object_store::path::Path {
        let key = format!("{}/{}", &hash[..2], hash);
        object_store::path::Path::from(if prefix.is_empty() {
            key
        } else {
            format!("{prefix}/{key}")
        })
    }

    /// Store `bytes`. Returns the hash.
    pub fn put(&self, bytes: &[u8]) -> io::Result<String> {
        match self.stage(&mut &bytes[..], u64::MAX) {
            Ok(staged) => self.commit(staged),
            Err(StageError::Read(e) | StageError::Store(e)) => Err(e),
        }
    }

    /// Copy `r` into a temporary file in the spool while hashing it, reading at most
    /// `limit + 1` bytes (so a caller sees an entry that is too long without inflating
    /// it further). Memory is one copy buffer, whatever the size. Nothing is visible in
    /// the store until [`BlobStore::commit`]; a dropped [`Staged`] removes its file.
    pub fn stage(&self, r: &mut dyn Read, limit: u64) -> Result<Staged, StageError> {
        let tmp_dir = self.tmp_dir().map_err(StageError::Store)?;
        let path = tmp_dir.join(format!("stage.{}", uuid::Uuid::new_v4().simple()));
        let mut f =
            File::create(&path).map_err(|e| StageError::Store(self.at("creating", &path, e)))?;
        let mut staged = Staged {
            path,
            sha256: String::new(),
            len: 0,
        };
        let mut hasher = Sha256::new();
        let mut buf = vec![0u8; 64 << 10];
        let mut r = r.take(limit.saturating_add(1));
        loop {
            let n = match r.read(&mut buf) {
                Ok(0) => break,
                Ok(n) => n,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                Err(e) => return Err(StageError::Read(e)),
            };
            hasher.update(&buf[..n]);
            f.write_all(&buf[..n])
                .map_err(|e| StageError::Store(self.at("writing", &staged.path, e)))?;
            staged.len += n as u64;
        }
        f.sync_all()
            .map_err(|e| StageError::Store(self.at("syncing", &staged.path, e)))?;
        staged.sha256 = hex::encode(hasher.finalize());
        Ok(staged)
    }

    /// Move a staged file to its content address. Identical bytes already stored are
    /// kept and the staged copy dropped. Locally: atomic rename, then fsync of the
    /// directory, whose directories are created again when they have gone (a cleaned or
    /// restored data directory must not need a restart). On S3: a conditional create.
    pub fn commit(&self, staged: Staged) -> io::Result<String> {
        let hash = staged.sha256.clone();
        match &self.backend {
            Backend::Local { root } => {
                let dest = Self::path_of(root, &hash);
                if dest.exists() {
                    return Ok(hash);
                }
                let dir = root.join(&hash[..2]);
                fs::create_dir_all(&dir).map_err(|e| self.at("creating", &dir, e))?;
                fs::rename(&staged.path, &dest).map_err(|e| self.at("renaming into", &dest, e))?;
                File::open(&dir)
                    .and_then(|d| d.sync_all())
                    .map_err(|e| self.at("syncing", &dir, e))?;
            }
            Backend::S3 {
                store,
                prefix,
                runtime,
                ..
            } => {
                let bytes = staged.read()?;
                let key = Self::key_of(prefix, &hash);
                let opts = PutOptions {
                    mode: PutMode::Create,
                    ..PutOptions::default()
                };
                let put = store.put_opts(&key, PutPayload::from(bytes), opts);
                match runtime.block_on(put) {
                    Ok(_) | Err(object_store::Error::AlreadyExists { .. }) => {}
                    // Another writer's create of the same key raced ours: the same bytes.
                    Err(object_store::Error::Precondition { .. }) => {}
                    Err(e) => return Err(remote(e)),
                }
            }
        }
        Ok(hash)
    }

    /// An I/O error that names the operation and the path under the blob store (for the
    /// log; the API answers storage-unavailable without it).
    fn at(&self, op: &str, p: &Path, e: io::Error) -> io::Error {
        let shown = match &self.backend {
            Backend::Local { root } => p.strip_prefix(root).unwrap_or(p).display().to_string(),
            Backend::S3 { .. } => p.display().to_string(),
        };
        io::Error::new(e.kind(), format!("{op} blobs/{shown}: {e}"))
    }

    /// Read a blob back, verifying its content against its name.
    pub fn get(&self, hash: &str) -> io::Result<Vec<u8>> {
        if !valid_hash(hash) {
            return Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                "not a blob hash",
            ));
        }
        let bytes = match &self.backend {
            Backend::Local { root } => fs::read(Self::path_of(root, hash))?,
            Backend::S3 {
                store,
                prefix,
                runtime,
                ..
            } => {
                let key = Self::key_of(prefix, hash);
                runtime
                    .block_on(async { store.get(&key).await?.bytes().await })
                    .map_err(remote)?
                    .to_vec()
            }
        };
        if sha256_hex(&bytes) != hash {
            return Err(io::Error::new(
                io::ErrorKind::InvalidData,
                format!("blob {hash} is corrupt"),
            ));
        }
        Ok(bytes)
    }

    /// Whether the blob is there (without reading it).
    pub async fn contains(&self, hash: &str) -> io::Result<bool> {
        if !valid_hash(hash) {
            return Ok(false);
        }
        match &self.backend {
            Backend::Local { root } => Ok(Self::path_of(root, hash).exists()),
            Backend::S3 { store, prefix, .. } => {
                match store.head(&Self::key_of(prefix, hash)).await {
                    Ok(_) => Ok(true),
                    Err(object_store::Error::NotFound { .. }) => Ok(false),
                    Err(e) => Err(remote(e)),
                }
            }
        }
    }
}

/// An object-store failure as an I/O error of the matching kind.
fn remote(e: object_store::Error) -> io::Error {
    let kind = match &e {
        object_store::Error::NotFound { .. } => io::ErrorKind::NotFound,
        object_store::Error::PermissionDenied { .. }
        | object_store::Error::Unauthenticated { .. } => io::ErrorKind::PermissionDenied,
        _ => io::ErrorKind::Other,
    };
    io::Error::new(kind, format!("object storage: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn put_is_idempotent_and_verified() {
        let dir = tempfile::tempdir().unwrap();
        let store = BlobStore::open_dir(dir.path()).unwrap();
        let a = store.put(b"hello").unwrap();
        let b = store.put(b"hello").unwrap();
        assert_eq!(a, b);
        assert_eq!(store.get(&a).unwrap(), b"hello");
        assert!(fs::read_dir(dir.path().join("tmp"))
            .unwrap()
            .next()
            .is_none());
        // Corruption on disk is detected, not served.
        fs::write(BlobStore::path_of(dir.path(), &a), b"jello").unwrap();
        assert!(store.get(&a).is_err());
        assert!(store.get("../etc/passwd").is_err());
    }

    #[test]
    fn blob_urls_parse_or_say_what_was_expected() {
        assert_eq!(
            BlobUrl::parse("file:///var/rigcal/blobs").unwrap(),
            BlobUrl::Local("/var/rigcal/blobs".into())
        );
        assert_eq!(
            BlobUrl::parse("s3://rigcal-blobs/prod/").unwrap(),
            BlobUrl::S3 {
                bucket: "rigcal-blobs".into(),
                prefix: "prod".into()
            }
        );
        for bad in [
            "s3://",
            "s3://UPPER/x",
            "s3://ok-bucket/../x",
            "gs://b/x",
            "file://",
        ] {
            let e = BlobUrl::parse(bad).unwrap_err().to_string();
            assert!(
                e.contains("expected") || e.contains("may not"),
                "{bad}: {e}"
            );
        }
    }
}
