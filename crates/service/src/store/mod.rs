//! Persistent state: the database ([`db::Db`], SQLite or PostgreSQL through sqlx, schema
//! only through `migrations/<backend>/`) and the content-addressed blob store for image
//! bytes ([`BlobStore`], a local directory or S3-compatible object storage).
//!
//! Queries are checked at run time, not by sqlx's compile-time macros: a fresh clone
//! builds without a database or a `.sqlx/` cache, and the integration tests exercise
//! every query against a real database of each backend.

pub mod blob;
pub mod db;
pub mod detections;
pub mod idempotency;
pub mod vehicle_models;
pub mod webhooks;

pub use blob::BlobStore;
use db::{sql, Db, Rec};
use sha2::Digest;
use std::path::Path;

/// Milliseconds since the Unix epoch.
pub fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}

/// RFC 3339 (UTC, milliseconds) of a stored time.
pub fn rfc3339(ms: i64) -> String {
    let t = time::OffsetDateTime::from_unix_timestamp_nanos(ms as i128 * 1_000_000)
        .unwrap_or(time::OffsetDateTime::UNIX_EPOCH);
    t.format(&time::format_description::well_known::Rfc3339)
        .unwrap_or_default()
}

/// Parse RFC 3339 into milliseconds since the epoch.
pub fn parse_rfc3339(s: &str) -> Option<i64> {
    time::OffsetDateTime::parse(s, &time::format_description::well_known::Rfc3339)
        .ok()
        .map(|t| (t.unix_timestamp_nanos() / 1_000_000) as i64)
}

#[derive(Clone)]
pub struct Store {
    pub db: Db,
    pub blobs: BlobStore,
}

/// Where the store lives: a database URL and a blob URL. The embedded default is a
/// data directory's `rigcal.db` and `blobs/`.
#[derive(Clone, Debug)]
pub struct Location {
    /// `sqlite://PATH` or `postgres://…`.
    pub database_url: String,
    /// `file://DIR` or `s3://BUCKET/PREFIX`.
    pub blob_url: String,
    /// Local working space (upload spools, bundles being written): always on this host.
    pub data_dir: std::path::PathBuf,
}

impl Location {
    /// The embedded default under `data_dir`, with either URL overridden when given.
    pub fn new(data_dir: &Path, database_url: Option<&str>, blob_url: Option<&str>) -> Location {
        Location {
            database_url: database_url.map_or_else(
                || format!("sqlite://{}", data_dir.join("rigcal.db").display()),
                str::to_string,
            ),
            blob_url: blob_url.map_or_else(
                || format!("file://{}", data_dir.join("blobs").display()),
                str::to_string,
            ),
            data_dir: data_dir.to_path_buf(),
        }
    }

    /// Where the store is, for a log line (passwords hidden).
    pub fn describe(&self) -> String {
        format!("{} and {}", db::redact(&self.database_url), self.blob_url)
    }
}

#[derive(Clone, Debug)]
pub struct Tenant {
    pub id: String,
    pub name: String,
    pub max_rms_px: f64,
    pub max_sigma_translation_m: f64,
    pub max_sigma_rotation_deg: f64,
}

#[derive(Clone, Debug)]
pub struct SessionRow {
    pub id: String,
    pub tenant_id: String,
    pub vehicle_id: Option<String>,
    pub method: String,
    pub manifest: String,
    pub capture_check: Option<String>,
    /// Of the images awaiting detection, how many the stored check covers, and how many
    /// there are (both `None` for a check computed at creation from the session's own
    /// detections, which is complete).
    pub check_detected: Option<i64>,
    pub check_expected: Option<i64>,
    pub created_at: i64,
}

/// An API key as listed: never its secret.
#[derive(Clone, Debug, serde::Serialize)]
pub struct ApiKeyRow {
    pub id: String,
    pub tenant: String,
    pub prefix: String,
    pub created_at: i64,
    pub revoked_at: Option<i64>,
}

#[derive(Clone, Debug, serde::Serialize)]
pub struct ImageRow {
    pub camera: String,
    pub frame: i64,
    pub sha256: String,
    pub bytes: i64,
    pub format: String,
    pub width: i64,
    pub height: i64,
}

fn tenant_from(row: &Rec) -> sqlx::Result<Tenant> {
    Ok(Tenant {
        id: row.get("id")?,
        name: row.get("name")?,
        max_rms_px: row.get("max_rms_px")?,
        max_sigma_translation_m: row.get("max_sigma_translation_m")?,
        max_sigma_rotation_deg: row.get("max_sigma_rotation_deg")?,
    })
}

fn session_from(row: &Rec) -> sqlx::Result<SessionRow> {
    Ok(SessionRow {
        id: row.get("id")?,
        tenant_id: row.get("tenant_id")?,
        vehicle_id: row.get("vehicle_id")?,
        method: row.get("method")?,
        manifest: row.get("manifest")?,
        capture_check: row.get("capture_check")?,
        check_detected: row.get("check_detected")?,
        check_expected: row.get("check_expected")?,
        created_at: row.get("created_at")?,
    })
}

fn image_from(r: &Rec) -> sqlx::Result<ImageRow> {
    Ok(ImageRow {
        camera: r.get("camera")?,
        frame: r.get("frame")?,
        sha256: r.get("sha256")?,
        bytes: r.get("bytes")?,
        format: r.get("format")?,
        width: r.get("width")?,
        height: r.get("height")?,
    })
}

/// SHA-256 of an API key, hex: what is stored and looked up.
pub fn key_hash(key: &str) -> String {
    hex::encode(sha2::Sha256::digest(key.as_bytes()))
}

impl Store {
    /// Replace a tenant's acceptance thresholds.
    pub async fn set_thresholds(
        &self,
        tenant_id: &str,
        max_rms_px: f64,
        max_sigma_translation_m: f64,
        max_sigma_rotation_deg: f64,
    ) -> sqlx::Result<()> {
        self.db.execute(sql("UPDATE tenants SET max_rms_px = $1, max_sigma_translation_m = $2, max_sigma_rotation_deg = $3 WHERE id = $4")
            .bind(max_rms_px)
            .bind(max_sigma_translation_m)
            .bind(max_sigma_rotation_deg)
            .bind(tenant_id))
            .await?;
        Ok(())
    }

    /// The embedded default: the database and blob directory under `data_dir`.
    pub async fn open(data_dir: &Path) -> anyhow::Result<Store> {
        Store::connect(&Location::new(data_dir, None, None)).await
    }

    /// Connect to the database (applying pending migrations) and the blob store.
    pub async fn connect(at: &Location) -> anyhow::Result<Store> {
        let db = Db::connect(&at.database_url).await?;
        let blobs = BlobStore::open(&at.blob_url, &at.data_dir).await?;
        Ok(Store { db, blobs })
    }

    pub async fn ensure_tenant(&self, name: &str) -> sqlx::Result<Tenant> {
        self.db.execute(sql("INSERT INTO tenants (id, name, created_at) VALUES ($1, $2, $3) ON CONFLICT(name) DO NOTHING")
            .bind(uuid::Uuid::new_v4().to_string())
            .bind(name)
            .bind(now_ms()))
            .await?;
        let row = self
            .db
            .fetch_one(sql("SELECT * FROM tenants WHERE name = $1").bind(name))
            .await?;
        tenant_from(&row)
    }

    /// Create an API key for `tenant` (created if new). Returns the key: it is shown once
    /// and only its hash is stored.
    pub async fn create_api_key(&self, tenant: &str) -> sqlx::Result<String> {
        let t = self.ensure_tenant(tenant).await?;
        let secret = format!(
            "rk_{}{}",
            uuid::Uuid::new_v4().simple(),
            uuid::Uuid::new_v4().simple()
        );
        self.db.execute(sql("INSERT INTO api_keys (id, tenant_id, key_hash, prefix, created_at) VALUES ($1, $2, $3, $4, $5)")
        .bind(uuid::Uuid::new_v4().to_string())
        .bind(&t.id)
        .bind(key_hash(&secret))
        .bind(&secret[..7])
        .bind(now_ms()))
        .await?;
        Ok(secret)
    }

    /// API keys (never the secrets: id, tenant, the first characters, dates), oldest
    /// first, of one tenant or all.
    pub async fn api_keys(&self, tenant: Option<&str>) -> sqlx::Result<Vec<ApiKeyRow>> {
        let rows = self.db.fetch_all(sql("SELECT k.id, t.name, k.prefix, k.created_at, k.revoked_at FROM api_keys k JOIN tenants t ON t.id = k.tenant_id WHERE $1 IS NULL OR t.name = $1 ORDER BY k.created_at, k.id")
            .bind(tenant))
            .await?;
        rows.iter()
            .map(|r| {
                Ok(ApiKeyRow {
                    id: r.get("id")?,
                    tenant: r.get("name")?,
                    prefix: r.get("prefix")?,
                    created_at: r.get("created_at")?,
                    revoked_at: r.get("revoked_at")?,
                })
            })
            .collect()
    }

    /// Revoke the key `id`; `false` if there is no such key or it was revoked already.
    pub async fn revoke_api_key(&self, id: &str) -> sqlx::Result<bool> {
        let n = self
            .db
            .execute(
                sql("UPDATE api_keys SET revoked_at = $1 WHERE id = $2 AND revoked_at IS NULL")
                    .bind(now_ms())
                    .bind(id),
            )
            .await?;
        Ok(n == 1)
    }

    pub async fn tenant_for_key(&self, key: &str) -> sqlx::Result<Option<Tenant>> {
        let row = self.db.fetch_optional(sql("SELECT t.* FROM api_keys k JOIN tenants t ON t.id = k.tenant_id WHERE k.key_hash = $1 AND k.revoked_at IS NULL")
        .bind(key_hash(key)))
        .await?;
        row.as_ref().map(tenant_from).transpose()
    }

    pub async fn tenant(&self, id: &str) -> sqlx::Result<Option<Tenant>> {
        let row = self
            .db
            .fetch_optional(sql("SELECT * FROM tenants WHERE id = $1").bind(id))
            .await?;
        row.as_ref().map(tenant_from).transpose()
    }

    pub async fn insert_session(
        &self,
        tenant: &Tenant,
        vehicle_id: Option<&str>,
        method: &str,
        manifest: &str,
        capture_check: Option<&str>,
    ) -> sqlx::Result<SessionRow> {
        let row = SessionRow {
            id: uuid::Uuid::new_v4().to_string(),
            tenant_id: tenant.id.clone(),
            vehicle_id: vehicle_id.map(str::to_string),
            method: method.to_string(),
            manifest: manifest.to_string(),
            capture_check: capture_check.map(str::to_string),
            check_detected: None,
            check_expected: None,
            created_at: now_ms(),
        };
        self.db.execute(sql("INSERT INTO sessions (id, tenant_id, vehicle_id, method, manifest, capture_check, created_at) VALUES ($1, $2, $3, $4, $5, $6, $7)")
            .bind(&row.id)
            .bind(&row.tenant_id)
            .bind(&row.vehicle_id)
            .bind(&row.method)
            .bind(&row.manifest)
            .bind(&row.capture_check)
            .bind(row.created_at))
            .await?;
        Ok(row)
    }

    /// A tenant's session; `None` for a session of another tenant (never revealed).
    pub async fn session(&self, tenant: &Tenant, id: &str) -> sqlx::Result<Option<SessionRow>> {
        let row = self
            .db
            .fetch_optional(
                sql("SELECT * FROM sessions WHERE id = $1 AND tenant_id = $2")
                    .bind(id)
                    .bind(&tenant.id),
            )
            .await?;
        row.as_ref().map(session_from).transpose()
    }

    pub async fn session_by_id(&self, id: &str) -> sqlx::Result<Option<SessionRow>> {
        let row = self
            .db
            .fetch_optional(sql("SELECT * FROM sessions WHERE id = $1").bind(id))
            .await?;
        row.as_ref().map(session_from).transpose()
    }

    pub async fn images(&self, session_id: &str) -> sqlx::Result<Vec<ImageRow>> {
        let rows = self
            .db
            .fetch_all(
                sql("SELECT * FROM images WHERE session_id = $1 ORDER BY frame, camera")
                    .bind(session_id),
            )
            .await?;
        rows.iter().map(image_from).collect()
    }

    /// Record an image whose blob is already durable and, when `detect`, queue its
    /// detection in the same transaction (so no stored image lacks its detection row).
    /// Returns the stored row: the new one, or the one already there (the caller
    /// compares hashes for idempotency).
    pub async fn insert_image(
        &self,
        session_id: &str,
        img: &ImageRow,
        detect: bool,
    ) -> sqlx::Result<ImageRow> {
        let mut tx = self.db.begin().await?;
        let n = tx.execute(sql("INSERT INTO images (session_id, camera, frame, sha256, bytes, format, width, height, created_at) VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9) ON CONFLICT(session_id, camera, frame) DO NOTHING")
            .bind(session_id)
            .bind(&img.camera)
            .bind(img.frame)
            .bind(&img.sha256)
            .bind(img.bytes)
            .bind(&img.format)
            .bind(img.width)
            .bind(img.height)
            .bind(now_ms()))
            .await?;
        if n == 1 && detect {
            tx.execute(sql("INSERT INTO image_detections (id, session_id, camera, frame, sha256, status, created_at) VALUES ($1, $2, $3, $4, $5, 'pending', $6) ON CONFLICT(session_id, camera, frame) DO NOTHING")
                .bind(uuid::Uuid::new_v4().to_string())
                .bind(session_id)
                .bind(&img.camera)
                .bind(img.frame)
                .bind(&img.sha256)
                .bind(now_ms()))
                .await?;
            // Idle workers on PostgreSQL wake for work on this channel (jobs and images).
            if self.db.backend() == db::Backend::Postgres {
                tx.execute(
                    sql("SELECT pg_notify($1, $2)")
                        .bind(crate::jobs::queue::JOBS_CHANNEL)
                        .bind(session_id),
                )
                .await?;
            }
        }
        let r = tx
            .fetch_one(
                sql("SELECT * FROM images WHERE session_id = $1 AND camera = $2 AND frame = $3")
                    .bind(session_id)
                    .bind(&img.camera)
                    .bind(img.frame),
            )
            .await?;
        tx.commit().await?;
        image_from(&r)
    }

    pub async fn integrity_check(&self) -> sqlx::Result<String> {
        self.db.integrity_check().await
    }
}
