//! Content-addressed blob directory for image bytes: `blobs/<2 hex>/<sha256>`.
//!
//! Writes are atomic (temp file, fsync, rename, fsync of the directory), so a crash
//! leaves either the whole blob or none, and the database row that names a blob is only
//! written after the blob is durable. Identical bytes are stored once.

use sha2::{Digest, Sha256};
use std::fs::{self, File};
use std::io::{self, Write};
use std::path::{Path, PathBuf};

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

    fn path_of(&self, hash: &str) -> PathBuf {
        self.root.join(&hash[..2]).join(hash)
    }

    /// Store `bytes` (blocking I/O: call from a blocking thread). Returns the hash.
    /// The working directories are created again when they have gone (a cleaned or
    /// restored data directory must not need a restart); every error names the
    /// operation and the path under the blob directory.
    pub fn put(&self, bytes: &[u8]) -> io::Result<String> {
        let hash = sha256_hex(bytes);
        let dest = self.path_of(&hash);
        if dest.exists() {
            return Ok(hash);
        }
        let at = |op: &'static str, p: &Path| {
            let shown = p.strip_prefix(&self.root).unwrap_or(p).display().to_string();
            move |e: io::Error| io::Error::new(e.kind(), format!("{op} blobs/{shown}: {e}"))
        };
        let dir = self.root.join(&hash[..2]);
        let tmp_dir = self.root.join("tmp");
        fs::create_dir_all(&dir).map_err(at("creating", &dir))?;
        fs::create_dir_all(&tmp_dir).map_err(at("creating", &tmp_dir))?;
        let tmp = tmp_dir.join(format!("{}.{}", hash, uuid::Uuid::new_v4().simple()));
        {
            let mut f = File::create(&tmp).map_err(at("creating", &tmp))?;
            f.write_all(bytes).map_err(at("writing", &tmp))?;
            f.sync_all().map_err(at("syncing", &tmp))?;
        }
        if let Err(e) = fs::rename(&tmp, &dest) {
            let _ = fs::remove_file(&tmp);
            return Err(at("renaming into", &dest)(e));
        }
        File::open(&dir)
            .and_then(|d| d.sync_all())
            .map_err(at("syncing", &dir))?;
        Ok(hash)
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
