//! Persistent state: SQLite through sqlx (schema only through `migrations/`) and the
//! content-addressed blob directory for image bytes.
//!
//! Queries are checked at run time, not by sqlx's compile-time macros: a fresh clone
//! builds without a database or a `.sqlx/` cache, and the integration tests exercise
//! every query against a real database.

pub mod blob;
pub mod idempotency;

use anyhow::Context;
pub use blob::BlobStore;
use sha2::Digest;
use sqlx::sqlite::{
    SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteSynchronous,
};
use sqlx::Row;
use std::path::Path;
use std::str::FromStr;
use std::time::Duration;

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
    pub pool: SqlitePool,
    pub blobs: BlobStore,
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

fn tenant_from(row: &sqlx::sqlite::SqliteRow) -> Tenant {
    Tenant {
        id: row.get("id"),
        name: row.get("name"),
        max_rms_px: row.get("max_rms_px"),
        max_sigma_translation_m: row.get("max_sigma_translation_m"),
        max_sigma_rotation_deg: row.get("max_sigma_rotation_deg"),
    }
}

fn session_from(row: &sqlx::sqlite::SqliteRow) -> SessionRow {
    SessionRow {
        id: row.get("id"),
        tenant_id: row.get("tenant_id"),
        vehicle_id: row.get("vehicle_id"),
        method: row.get("method"),
        manifest: row.get("manifest"),
        capture_check: row.get("capture_check"),
        created_at: row.get("created_at"),
    }
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
        sqlx::query("UPDATE tenants SET max_rms_px = ?, max_sigma_translation_m = ?, max_sigma_rotation_deg = ? WHERE id = ?")
            .bind(max_rms_px)
            .bind(max_sigma_translation_m)
            .bind(max_sigma_rotation_deg)
            .bind(tenant_id)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// Open (creating if needed) the database and blob directory under `data_dir`, and
    /// apply pending migrations. WAL, foreign keys, a busy timeout, synchronous=FULL so an
    /// acknowledged write survives a crash.
    pub async fn open(data_dir: &Path) -> anyhow::Result<Store> {
        std::fs::create_dir_all(data_dir)
            .with_context(|| format!("creating data directory {}", data_dir.display()))?;
        let db = data_dir.join("rigcal.db");
        let opts = SqliteConnectOptions::from_str(&format!("sqlite://{}", db.display()))?
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .synchronous(SqliteSynchronous::Full)
            .foreign_keys(true)
            .busy_timeout(Duration::from_secs(10));
        let pool = SqlitePoolOptions::new()
            .max_connections(8)
            .connect_with(opts)
            .await
            .with_context(|| format!("opening database {}", db.display()))?;
        sqlx::migrate!("../../migrations")
            .run(&pool)
            .await
            .context("applying migrations")?;
        let blobs = BlobStore::open(&data_dir.join("blobs"))
            .with_context(|| format!("opening blob directory in {}", data_dir.display()))?;
        Ok(Store { pool, blobs })
    }

    pub async fn ensure_tenant(&self, name: &str) -> sqlx::Result<Tenant> {
        sqlx::query("INSERT INTO tenants (id, name, created_at) VALUES (?, ?, ?) ON CONFLICT(name) DO NOTHING")
            .bind(uuid::Uuid::new_v4().to_string())
            .bind(name)
            .bind(now_ms())
            .execute(&self.pool)
            .await?;
        let row = sqlx::query("SELECT * FROM tenants WHERE name = ?")
            .bind(name)
            .fetch_one(&self.pool)
            .await?;
        Ok(tenant_from(&row))
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
        sqlx::query(
            "INSERT INTO api_keys (id, tenant_id, key_hash, prefix, created_at) VALUES (?, ?, ?, ?, ?)",
        )
        .bind(uuid::Uuid::new_v4().to_string())
        .bind(&t.id)
        .bind(key_hash(&secret))
        .bind(&secret[..7])
        .bind(now_ms())
        .execute(&self.pool)
        .await?;
        Ok(secret)
    }

    /// API keys (never the secrets: id, tenant, the first characters, dates), oldest
    /// first, of one tenant or all.
    pub async fn api_keys(&self, tenant: Option<&str>) -> sqlx::Result<Vec<ApiKeyRow>> {
        let rows = sqlx::query("SELECT k.id, t.name, k.prefix, k.created_at, k.revoked_at FROM api_keys k JOIN tenants t ON t.id = k.tenant_id WHERE ?1 IS NULL OR t.name = ?1 ORDER BY k.created_at, k.id")
            .bind(tenant)
            .fetch_all(&self.pool)
            .await?;
        Ok(rows
            .iter()
            .map(|r| ApiKeyRow {
                id: r.get("id"),
                tenant: r.get("name"),
                prefix: r.get("prefix"),
                created_at: r.get("created_at"),
                revoked_at: r.get("revoked_at"),
            })
            .collect())
    }

    /// Revoke the key `id`; `false` if there is no such key or it was revoked already.
    pub async fn revoke_api_key(&self, id: &str) -> sqlx::Result<bool> {
        let n =
            sqlx::query("UPDATE api_keys SET revoked_at = ? WHERE id = ? AND revoked_at IS NULL")
                .bind(now_ms())
                .bind(id)
                .execute(&self.pool)
                .await?
                .rows_affected();
        Ok(n == 1)
    }

    pub async fn tenant_for_key(&self, key: &str) -> sqlx::Result<Option<Tenant>> {
        let row = sqlx::query(
            "SELECT t.* FROM api_keys k JOIN tenants t ON t.id = k.tenant_id WHERE k.key_hash = ? AND k.revoked_at IS NULL",
        )
        .bind(key_hash(key))
        .fetch_optional(&self.pool)
        .await?;
        Ok(row.as_ref().map(tenant_from))
    }

    pub async fn tenant(&self, id: &str) -> sqlx::Result<Option<Tenant>> {
        let row = sqlx::query("SELECT * FROM tenants WHERE id = ?")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        Ok(row.as_ref().map(tenant_from))
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
            created_at: now_ms(),
        };
        sqlx::query("INSERT INTO sessions (id, tenant_id, vehicle_id, method, manifest, capture_check, created_at) VALUES (?, ?, ?, ?, ?, ?, ?)")
            .bind(&row.id)
            .bind(&row.tenant_id)
            .bind(&row.vehicle_id)
            .bind(&row.method)
            .bind(&row.manifest)
            .bind(&row.capture_check)
            .bind(row.created_at)
            .execute(&self.pool)
            .await?;
        Ok(row)
    }

    /// A tenant's session; `None` for a session of another tenant (never revealed).
    pub async fn session(&self, tenant: &Tenant, id: &str) -> sqlx::Result<Option<SessionRow>> {
        let row = sqlx::query("SELECT * FROM sessions WHERE id = ? AND tenant_id = ?")
            .bind(id)
            .bind(&tenant.id)
            .fetch_optional(&self.pool)
            .await?;
        Ok(row.as_ref().map(session_from))
    }

    pub async fn session_by_id(&self, id: &str) -> sqlx::Result<Option<SessionRow>> {
        let row = sqlx::query("SELECT * FROM sessions WHERE id = ?")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        Ok(row.as_ref().map(session_from))
    }

    pub async fn images(&self, session_id: &str) -> sqlx::Result<Vec<ImageRow>> {
        let rows = sqlx::query("SELECT * FROM images WHERE session_id = ? ORDER BY frame, camera")
            .bind(session_id)
            .fetch_all(&self.pool)
            .await?;
        Ok(rows
            .iter()
            .map(|r| ImageRow {
                camera: r.get("camera"),
                frame: r.get("frame"),
                sha256: r.get("sha256"),
                bytes: r.get("bytes"),
                format: r.get("format"),
                width: r.get("width"),
                height: r.get("height"),
            })
            .collect())
    }

    /// Record an image whose blob is already durable. Returns the stored row: the new
    /// one, or the one already there (the caller compares hashes for idempotency).
    pub async fn insert_image(&self, session_id: &str, img: &ImageRow) -> sqlx::Result<ImageRow> {
        sqlx::query("INSERT INTO images (session_id, camera, frame, sha256, bytes, format, width, height, created_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT(session_id, camera, frame) DO NOTHING")
            .bind(session_id)
            .bind(&img.camera)
            .bind(img.frame)
            .bind(&img.sha256)
            .bind(img.bytes)
            .bind(&img.format)
            .bind(img.width)
            .bind(img.height)
            .bind(now_ms())
            .execute(&self.pool)
            .await?;
        let r =
            sqlx::query("SELECT * FROM images WHERE session_id = ? AND camera = ? AND frame = ?")
                .bind(session_id)
                .bind(&img.camera)
                .bind(img.frame)
                .fetch_one(&self.pool)
                .await?;
        Ok(ImageRow {
            camera: r.get("camera"),
            frame: r.get("frame"),
            sha256: r.get("sha256"),
            bytes: r.get("bytes"),
            format: r.get("format"),
            width: r.get("width"),
            height: r.get("height"),
        })
    }

    pub async fn integrity_check(&self) -> sqlx::Result<String> {
        let row = sqlx::query("PRAGMA integrity_check")
            .fetch_one(&self.pool)
            .await?;
        Ok(row.get(0))
    }
}
