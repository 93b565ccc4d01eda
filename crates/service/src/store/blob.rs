//! Content-addressed blob directory for image bytes: `blobs/<2 hex>/<sha256>`.
//!
//! Writes are atomic (temp file, fsync, rename, fsync of the directory), so a crash
//! leaves either the whole blob or none, and the database row that names a blob is only
//! written after the blob is durable. Identical bytes are stored once.

use sha2::{Digest, Sha256};
use std::fs::{self, File};
use std::io::{self, Read, Write};
use std::path::{Path, PathBuf};

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
    root: PathBuf,
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

impl BlobStore {
    pub fn open(root: &Path) -> io::Result<Self> {
        fs::create_dir_all(root.join("tmp"))?;
        Ok(Self {
            root: root.to_path_buf(),
        })
    }

    /// The working directory for temporary files (created again if it has gone).
    pub fn tmp_dir(&self) -> io::Result<PathBuf> {
        let dir = self.root.join("tmp");
        fs::create_dir_all(&dir).map_err(|e| self.at("creating", &dir, e))?;
        Ok(dir)
    }

    fn path_of(&self, hash: &str) -> PathBuf {
        self.root.join(&hash[..2]).join(hash)
    }

    /// Store `bytes` (blocking I/O: call from a blocking thread). Returns the hash.
    pub fn put(&self, bytes: &[u8]) -> io::Result<String> {
        match self.stage(&mut &bytes[..], u64::MAX) {
            Ok(staged) => self.commit(staged),
            Err(StageError::Read(e) | StageError::Store(e)) => Err(e),
        }
    }

    /// Copy `r` into a temporary file under `tmp/` while hashing it, reading at most
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

    /// Move a staged file to its content address (atomic rename, then fsync of the
    /// directory). Identical bytes already stored are kept and the staged copy dropped.
    /// The directories are created again when they have gone (a cleaned or restored
    /// data directory must not need a restart).
    pub fn commit(&self, staged: Staged) -> io::Result<String> {
        let hash = staged.sha256.clone();
        let dest = self.path_of(&hash);
        if dest.exists() {
            return Ok(hash);
        }
        let dir = self.root.join(&hash[..2]);
        fs::create_dir_all(&dir).map_err(|e| self.at("creating", &dir, e))?;
        fs::rename(&staged.path, &dest).map_err(|e| self.at("renaming into", &dest, e))?;
        File::open(&dir)
            .and_then(|d| d.sync_all())
            .map_err(|e| self.at("syncing", &dir, e))?;
        Ok(hash)
    }

    /// An I/O error that names the operation and the path under the blob directory
    /// (for the log; the API answers storage-unavailable without it).
    fn at(&self, op: &str, p: &Path, e: io::Error) -> io::Error {
        let shown = p.strip_prefix(&self.root).unwrap_or(p).display();
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
        let bytes = fs::read(self.path_of(hash))?;
        if sha256_hex(&bytes) != hash {
            return Err(io::Error::new(
                io::ErrorKind::InvalidData,
                format!("blob {hash} is corrupt"),
            ));
        }
        Ok(bytes)
    }

    pub fn contains(&self, hash: &str) -> bool {
        valid_hash(hash) && self.path_of(hash).exists()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn put_is_idempotent_and_verified() {
        let dir = tempfile::tempdir().unwrap();
        let store = BlobStore::open(dir.path()).unwrap();
        let a = store.put(b"hello").unwrap();
        let b = store.put(b"hello").unwrap();
        assert_eq!(a, b);
        assert_eq!(store.get(&a).unwrap(), b"hello");
        assert!(fs::read_dir(dir.path().join("tmp"))
            .unwrap()
            .next()
            .is_none());
        // Corruption on disk is detected, not served.
        fs::write(store.path_of(&a), b"jello").unwrap();
        assert!(store.get(&a).is_err());
        assert!(store.get("../etc/passwd").is_err());
    }
}
