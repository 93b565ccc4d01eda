//! Session archives (tar or zip) read as streams.
//!
//! The request body is spooled to a temporary file as it arrives, and each entry is then
//! copied into a staged blob as it is read (inflated, for zip), with the per-entry, total
//! and entry-count limits checked while copying. So the memory of an upload is a copy
//! buffer and one image at a time (when it is inspected), whatever the archive's size or
//! compression ratio: a zip that inflates to gigabytes stops at the first entry longer
//! than the largest image accepted, and nothing of it is held in memory.

use super::error::ApiError;
use crate::store::blob::{BlobStore, StageError, Staged};
use axum::body::Body;
use axum::http::StatusCode;
use http_body_util::BodyExt;
use std::collections::BTreeMap;
use std::fs::File;
use std::io::{self, BufReader, Read, Seek, SeekFrom};

/// Most entries an archive may hold (directories included).
pub const MAX_ENTRIES: usize = 200_000;
/// Largest zip central directory read to find duplicate names (200 000 entries with
/// names of a few hundred bytes).
const MAX_CENTRAL_DIRECTORY: u64 = 128 << 20;

#[derive(Clone, Copy, Debug)]
pub enum ArchiveKind {
    Tar,
    Zip,
}

impl ArchiveKind {
    /// Whether a body of this Content-Type may be an archive (octet-stream is decided by
    /// its magic bytes, once they are read).
    pub fn may_be(content_type: &str) -> bool {
        content_type == "application/octet-stream" || Self::of(content_type, b"").is_some()
    }

    /// From the Content-Type, or for `application/octet-stream` from the magic bytes
    /// (`head` is the first 512 bytes of the body, or all of it).
    pub fn of(content_type: &str, head: &[u8]) -> Option<Self> {
        match content_type {
            "application/zip" | "application/x-zip-compressed" => Some(Self::Zip),
            "application/x-tar" | "application/tar" => Some(Self::Tar),
            "application/octet-stream" if head.starts_with(b"PK\x03\x04") => Some(Self::Zip),
            "application/octet-stream" if head.len() > 262 && &head[257..262] == b"ustar" => {
                Some(Self::Tar)
            }
            _ => None,
        }
    }
}

/// What an archive may unpack to.
#[derive(Clone, Copy, Debug)]
pub struct Limits {
    /// All entries together, unpacked.
    pub total: u64,
    /// One entry (the largest image accepted on its own).
    pub entry: u64,
    /// `session.json`.
    pub manifest: u64,
}

/// The request body, spooled to a temporary file that is removed when dropped.
pub struct Spooled {
    pub file: tempfile::NamedTempFile,
    pub head: Vec<u8>,
}

fn bad(detail: String) -> ApiError {
    ApiError::new(StatusCode::UNPROCESSABLE_ENTITY, "invalid-archive", detail).field("archive")
}

fn too_large(detail: String) -> ApiError {
    ApiError::new(StatusCode::PAYLOAD_TOO_LARGE, "payload-too-large", detail).field("archive")
}

/// Copy the body into a temporary file under the blob directory, at most `max` bytes.
pub async fn spool(body: Body, blobs: &BlobStore, max: u64) -> Result<Spooled, ApiError> {
    let dir = blobs.tmp_dir().map_err(ApiError::storage)?;
    let file = tempfile::Builder::new()
        .prefix("upload.")
        .tempfile_in(&dir)
        .map_err(|e| ApiError::storage(format!("creating an upload file in blobs/tmp: {e}")))?;
    let mut out = tokio::fs::File::from_std(file.reopen().map_err(ApiError::storage)?);
    let (mut body, mut head, mut len) = (body, Vec::new(), 0u64);
    use tokio::io::AsyncWriteExt;
    while let Some(frame) = body.frame().await {
        let frame = frame.map_err(|e| ApiError::body(&e, max as usize))?;
        let Ok(data) = frame.into_data() else {
            continue;
        };
        len += data.len() as u64;
        if len > max {
            return Err(too_large(format!("an archive of at most {max} bytes")));
        }
        if head.len() < 512 {
            let take = (512 - head.len()).min(data.len());
            head.extend_from_slice(&data[..take]);
        }
        out.write_all(&data)
            .await
            .map_err(|e| ApiError::storage(format!("writing an upload file in blobs/tmp: {e}")))?;
    }
    out.flush().await.map_err(ApiError::storage)?;
    Ok(Spooled { file, head })
}

/// An unpacked archive: the candidate manifests in memory, every other file staged.
pub struct Unpacked {
    /// `session.json` at the top or in one top-level folder: (name, bytes).
    manifests: Vec<(String, Vec<u8>)>,
    pub files: BTreeMap<String, Staged>,
}

impl Unpacked {
    /// The manifest, taken out: `session.json` at the top, else in one folder. Returns
    /// its bytes and the folder prefix image paths are relative to.
    pub fn take_manifest(&mut self) -> Option<(Vec<u8>, String)> {
        let at = (0..self.manifests.len()).min_by_key(|&i| self.manifests[i].0.len())?;
        let (name, bytes) = self.manifests.swap_remove(at);
        let prefix = name.strip_suffix("session.json").unwrap_or("").to_string();
        Some((bytes, prefix))
    }
}

fn is_manifest_name(name: &str) -> bool {
    name == "session.json" || (name.ends_with("/session.json") && name.matches('/').count() == 1)
}

/// Read every regular file of the spooled archive (blocking: call from a blocking
/// thread). Duplicate names are refused (which one the client meant is unknowable).
pub fn unpack(
    kind: ArchiveKind,
    spooled: &Spooled,
    blobs: &BlobStore,
    limits: Limits,
) -> Result<Unpacked, ApiError> {
    let mut out = Unpacked {
        manifests: Vec::new(),
        files: BTreeMap::new(),
    };
    let mut total = 0u64;
    let mut entries = 0usize;
    let mut add = |name: String, r: &mut dyn Read, out: &mut Unpacked| -> Result<(), ApiError> {
        let key = name.trim_start_matches("./").to_string();
        let shown = rigcal_core::session::quoted_prefix(&key);
        if out.files.contains_key(&key) || out.manifests.iter().any(|(n, _)| *n == key) {
            return Err(bad(format!(
                "archive entry names unique, got {shown} twice"
            )));
        }
        let left = limits.total.saturating_sub(total);
        if is_manifest_name(&key) {
            let mut buf = Vec::new();
            r.take(limits.manifest.min(left) + 1)
                .read_to_end(&mut buf)
                .map_err(|e| bad(format!("archive entry {shown} is unreadable: {e}")))?;
            if buf.len() as u64 > limits.manifest {
                return Err(too_large(format!(
                    "{shown}: a manifest of at most {} bytes",
                    limits.manifest
                )));
            }
            total += buf.len() as u64;
            out.manifests.push((key, buf));
        } else {
            let staged = blobs
                .stage(r, limits.entry.min(left))
                .map_err(|e| match e {
                    StageError::Read(e) => bad(format!("archive entry {shown} is unreadable: {e}")),
                    StageError::Store(e) => ApiError::storage(e),
                })?;
            if staged.len > limits.entry {
                return Err(too_large(format!(
                    "archive entry {shown} unpacks to more than {} bytes (the largest image accepted)",
                    limits.entry
                )));
            }
            total += staged.len;
            out.files.insert(key, staged);
        }
        if total > limits.total {
            return Err(too_large(format!(
                "the archive unpacks to more than {} bytes",
                limits.total
            )));
        }
        Ok(())
    };
    let mut count = || {
        entries += 1;
        if entries > MAX_ENTRIES {
            Err(bad(format!("an archive of at most {MAX_ENTRIES} entries")))
        } else {
            Ok(())
        }
    };
    let file = spooled.file.reopen().map_err(ApiError::storage)?;
    match kind {
        ArchiveKind::Tar => {
            let mut ar = tar::Archive::new(BufReader::new(file));
            let iter = ar
                .entries()
                .map_err(|e| bad(format!("not a readable tar archive: {e}")))?;
            for entry in iter {
                count()?;
                let mut entry =
                    entry.map_err(|e| bad(format!("a tar entry is unreadable: {e}")))?;
                if !entry.header().entry_type().is_file() {
                    continue;
                }
                let name = entry
                    .path()
                    .map_err(|_| bad("a tar entry has a path that is not UTF-8".into()))?
                    .to_string_lossy()
                    .to_string();
                add(name, &mut entry, &mut out)?;
            }
        }
        ArchiveKind::Zip => {
            let mut file = file;
            // The zip reader keeps one entry per name; a name twice is found in the
            // central directory itself.
            if let Some(name) = zip_duplicate_name(&mut file).map_err(ApiError::storage)? {
                return Err(bad(format!(
                    "archive entry names unique, got {} twice",
                    rigcal_core::session::quoted_prefix(&name)
                )));
            }
            let mut ar = zip::ZipArchive::new(BufReader::new(file))
                .map_err(|e| bad(format!("not a readable zip archive: {e}")))?;
            for i in 0..ar.len() {
                count()?;
                let mut f = ar
                    .by_index(i)
                    .map_err(|e| bad(format!("zip entry {i} is unreadable: {e}")))?;
                if !f.is_file() {
                    continue;
                }
                let name = f
                    .name()
                    .map_err(|_| bad(format!("zip entry {i} has a name that is not UTF-8")))?
                    .to_string();
                add(name, &mut f, &mut out)?;
            }
        }
    }
    Ok(out)
}

/// A name that the zip's central directory lists twice. Reads the end-of-central-
/// directory record (the last one in the file) and the directory it points to; a zip64
/// directory, whose offset does not fit there, is left to the reader.
fn zip_duplicate_name(f: &mut File) -> io::Result<Option<String>> {
    let len = f.seek(SeekFrom::End(0))?;
    let tail_len = len.min(22 + 65_535);
    f.seek(SeekFrom::Start(len - tail_len))?;
    let mut tail = vec![0u8; tail_len as usize];
    f.read_exact(&mut tail)?;
    let le16 = |b: &[u8], i: usize| Some(u16::from_le_bytes([*b.get(i)?, *b.get(i + 1)?]) as usize);
    let le32 = |b: &[u8], i: usize| {
        Some(
            u32::from_le_bytes([*b.get(i)?, *b.get(i + 1)?, *b.get(i + 2)?, *b.get(i + 3)?]) as u64,
        )
    };
    let Some(eocd) = (0..=tail.len().saturating_sub(22))
        .rev()
        .find(|&i| tail[i..].starts_with(b"PK\x05\x06"))
    else {
        return Ok(None);
    };
    let (Some(count), Some(size), Some(offset)) = (
        le16(&tail, eocd + 10),
        le32(&tail, eocd + 12),
        le32(&tail, eocd + 16),
    ) else {
        return Ok(None);
    };
    if size > MAX_CENTRAL_DIRECTORY || offset.saturating_add(size) > len {
        return Ok(None);
    }
    f.seek(SeekFrom::Start(offset))?;
    let mut cd = vec![0u8; size as usize];
    f.read_exact(&mut cd)?;
    let mut at = 0usize;
    let mut names = std::collections::HashSet::new();
    for _ in 0..count {
        if !cd.get(at..).is_some_and(|b| b.starts_with(b"PK\x01\x02")) {
            return Ok(None);
        }
        let (Some(n), Some(m), Some(k)) =
            (le16(&cd, at + 28), le16(&cd, at + 30), le16(&cd, at + 32))
        else {
            return Ok(None);
        };
        let Some(raw) = cd.get(at + 46..at + 46 + n) else {
            return Ok(None);
        };
        let name = String::from_utf8_lossy(raw).to_string();
        if !names.insert(name.clone()) {
            return Ok(Some(name));
        }
        at += 46 + n + m + k;
    }
    Ok(None)
}
