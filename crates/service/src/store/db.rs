//! The database behind the store and the queue: SQLite (the embedded default) or
//! PostgreSQL (many replicas and workers on many machines).
//!
//! One SQL text per statement serves both: placeholders are `$1, $2, …` (PostgreSQL's;
//! sqlx's SQLite driver binds `$NNN` by number too), every column is a 64-bit integer, a
//! double, text or bytes on both, and the clock of a lease is written `NOW_MS` and
//! replaced by each backend's own "milliseconds since the epoch", so leases follow the
//! database's clock, never a worker's. Where the backends really differ (claiming a job,
//! ordering events, the integrity check, wake-ups) the caller picks the statement with
//! [`Db::backend`]. Not sqlx's `Any` driver: it erases the types both backends check.
//!
//! Values are bound as [`Arg`]s collected before the backend is known, and rows come back
//! as [`Rec`], whose `get` decodes a column on either backend and returns an error (not a
//! panic) for a column that does not decode.

use anyhow::Context;
use sqlx::postgres::{PgPool, PgPoolOptions, PgRow};
use sqlx::sqlite::{
    SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteRow,
    SqliteSynchronous,
};
use sqlx::{AssertSqlSafe, Postgres, Row, Sqlite};
use std::borrow::Cow;
use std::str::FromStr;
use std::time::Duration;

/// Which database a [`Db`] talks to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Backend {
    Sqlite,
    Postgres,
}

/// A connection pool on either backend.
#[derive(Clone, Debug)]
pub enum Db {
    Sqlite(SqlitePool),
    Postgres(PgPool),
}

/// A value to bind, typed the same way on both backends.
#[derive(Clone, Debug)]
pub enum Arg {
    Int(Option<i64>),
    Real(Option<f64>),
    Text(Option<String>),
    Bytes(Option<Vec<u8>>),
}

macro_rules! arg_from {
    ($($t:ty => |$v:ident| $e:expr;)*) => {
        $(impl From<$t> for Arg {
            fn from($v: $t) -> Arg {
                $e
            }
        })*
    };
}

arg_from! {
    i64 => |v| Arg::Int(Some(v));
    Option<i64> => |v| Arg::Int(v);
    f64 => |v| Arg::Real(Some(v));
    Option<f64> => |v| Arg::Real(v);
    &str => |v| Arg::Text(Some(v.to_string()));
    String => |v| Arg::Text(Some(v));
    &String => |v| Arg::Text(Some(v.clone()));
    Option<&str> => |v| Arg::Text(v.map(str::to_string));
    Option<String> => |v| Arg::Text(v);
    &Option<String> => |v| Arg::Text(v.clone());
    &[u8] => |v| Arg::Bytes(Some(v.to_vec()));
    &Vec<u8> => |v| Arg::Bytes(Some(v.clone()));
}

/// A statement and its arguments, not yet tied to a backend.
#[derive(Clone, Debug)]
pub struct Sql {
    text: &'static str,
    args: Vec<Arg>,
}

/// A statement with `$n` placeholders (and `NOW_MS` for the database's clock).
pub fn sql(text: &'static str) -> Sql {
    Sql {
        text,
        args: Vec::new(),
    }
}

/// The database's clock in milliseconds since the Unix epoch, per backend. SQLite's
/// `julianday` works on every SQLite version (`unixepoch('subsec')` needs 3.42).
const SQLITE_NOW_MS: &str = "CAST((julianday('now') - 2440587.5) * 86400000.0 AS INTEGER)";
const POSTGRES_NOW_MS: &str = "CAST(EXTRACT(EPOCH FROM clock_timestamp()) * 1000 AS BIGINT)";

impl Sql {
    pub fn bind(mut self, value: impl Into<Arg>) -> Sql {
        self.args.push(value.into());
        self
    }

    fn text_for(&self, backend: Backend) -> AssertSqlSafe<Cow<'static, str>> {
        let now = match backend {
            Backend::Sqlite => SQLITE_NOW_MS,
            Backend::Postgres => POSTGRES_NOW_MS,
        };
        AssertSqlSafe(if self.text.contains("NOW_MS") {
            Cow::Owned(self.text.replace("NOW_MS", now))
        } else {
            Cow::Borrowed(self.text)
        })
    }

    fn sqlite(&self) -> sqlx::query::Query<'static, Sqlite, sqlx::sqlite::SqliteArguments> {
        bind_all(sqlx::query(self.text_for(Backend::Sqlite)), &self.args)
    }

    fn postgres(&self) -> sqlx::query::Query<'static, Postgres, sqlx::postgres::PgArguments> {
        bind_all(sqlx::query(self.text_for(Backend::Postgres)), &self.args)
    }
}

/// Bind `args` in order, on either backend.
fn bind_all<DB>(
    mut q: sqlx::query::Query<'static, DB, <DB as sqlx::Database>::Arguments>,
    args: &[Arg],
) -> sqlx::query::Query<'static, DB, <DB as sqlx::Database>::Arguments>
where
    DB: sqlx::Database,
    Option<i64>: for<'e> sqlx::Encode<'e, DB> + sqlx::Type<DB>,
    Option<f64>: for<'e> sqlx::Encode<'e, DB> + sqlx::Type<DB>,
    Option<String>: for<'e> sqlx::Encode<'e, DB> + sqlx::Type<DB>,
    Option<Vec<u8>>: for<'e> sqlx::Encode<'e, DB> + sqlx::Type<DB>,
{
    for a in args {
        q = match a {
            Arg::Int(v) => q.bind(*v),
            Arg::Real(v) => q.bind(*v),
            Arg::Text(v) => q.bind(v.clone()),
            Arg::Bytes(v) => q.bind(v.clone()),
        };
    }
    q
}

/// A column type both backends decode.
pub trait Col:
    for<'r> sqlx::Decode<'r, Sqlite>
    + sqlx::Type<Sqlite>
    + for<'r> sqlx::Decode<'r, Postgres>
    + sqlx::Type<Postgres>
{
}
impl<T> Col for T where
    T: for<'r> sqlx::Decode<'r, Sqlite>
        + sqlx::Type<Sqlite>
        + for<'r> sqlx::Decode<'r, Postgres>
        + sqlx::Type<Postgres>
{
}

/// A column named or numbered on both backends.
pub trait Idx: sqlx::ColumnIndex<SqliteRow> + sqlx::ColumnIndex<PgRow> {}
impl Idx for &str {}
impl Idx for usize {}

/// A row from either backend.
pub enum Rec {
    Sqlite(SqliteRow),
    Postgres(PgRow),
}

impl Rec {
    /// Column `i` decoded as `T`; an error names the column when it is missing or of
    /// another type (a schema this build does not expect).
    pub fn get<T: Col>(&self, i: impl Idx) -> sqlx::Result<T> {
        match self {
            Rec::Sqlite(r) => r.try_get(i),
            Rec::Postgres(r) => r.try_get(i),
        }
    }
}

/// A transaction on either backend; rolled back when dropped uncommitted.
pub enum Tx {
    Sqlite(sqlx::Transaction<'static, Sqlite>),
    Postgres(sqlx::Transaction<'static, Postgres>),
}

enum Exec<'a> {
    Sqlite(&'a mut sqlx::SqliteConnection),
    Postgres(&'a mut sqlx::PgConnection),
}

impl Tx {
    fn executor(&mut self) -> Exec<'_> {
        match self {
            Tx::Sqlite(t) => Exec::Sqlite(t),
            Tx::Postgres(t) => Exec::Postgres(t),
        }
    }

    pub async fn execute(&mut self, q: Sql) -> sqlx::Result<u64> {
        Ok(match self.executor() {
            Exec::Sqlite(e) => q.sqlite().execute(e).await?.rows_affected(),
            Exec::Postgres(e) => q.postgres().execute(e).await?.rows_affected(),
        })
    }

    pub async fn fetch_optional(&mut self, q: Sql) -> sqlx::Result<Option<Rec>> {
        Ok(match self.executor() {
            Exec::Sqlite(e) => q.sqlite().fetch_optional(e).await?.map(Rec::Sqlite),
            Exec::Postgres(e) => q.postgres().fetch_optional(e).await?.map(Rec::Postgres),
        })
    }

    pub async fn fetch_one(&mut self, q: Sql) -> sqlx::Result<Rec> {
        Ok(match self.executor() {
            Exec::Sqlite(e) => Rec::Sqlite(q.sqlite().fetch_one(e).await?),
            Exec::Postgres(e) => Rec::Postgres(q.postgres().fetch_one(e).await?),
        })
    }

    pub async fn fetch_all(&mut self, q: Sql) -> sqlx::Result<Vec<Rec>> {
        Ok(match self.executor() {
            Exec::Sqlite(e) => q
                .sqlite()
                .fetch_all(e)
                .await?
                .into_iter()
                .map(Rec::Sqlite)
                .collect(),
            Exec::Postgres(e) => q
                .postgres()
                .fetch_all(e)
                .await?
                .into_iter()
                .map(Rec::Postgres)
                .collect(),
        })
    }

    pub async fn commit(self) -> sqlx::Result<()> {
        match self {
            Tx::Sqlite(t) => t.commit().await,
            Tx::Postgres(t) => t.commit().await,
        }
    }

    /// Make job events of concurrent transactions commit in the order of their ids, so
    /// a stream that reads "every event after id N" never skips one committed late.
    /// PostgreSQL hands out identities before commit; a transaction-scoped advisory lock
    /// taken before the insert serialises the writers until they commit. SQLite has one
    /// writer at a time already.
    pub async fn order_events(&mut self) -> sqlx::Result<()> {
        if let Tx::Postgres(t) = self {
            sqlx::query("SELECT pg_advisory_xact_lock(7230112001)")
                .execute(&mut **t)
                .await?;
        }
        Ok(())
    }
}

/// How long opening an SQLite file waits out another process's lock.
const SQLITE_OPEN_PATIENCE: Duration = Duration::from_secs(10);

/// `SQLITE_BUSY` or one of its extended codes (the low byte is the primary code).
fn is_busy(e: &dyn sqlx::error::DatabaseError) -> bool {
    const SQLITE_BUSY: i32 = 5;
    e.code()
        .and_then(|c| c.parse::<i32>().ok())
        .is_some_and(|c| c & 0xff == SQLITE_BUSY)
}

/// Open a pool on an SQLite file, retrying while another process holds a lock that
/// SQLite does not wait for itself: a replica closing its last connection checkpoints
/// the WAL under an exclusive lock, and a connection opening then may get `SQLITE_BUSY`
/// at once rather than through the busy handler.
async fn open_sqlite(opts: SqliteConnectOptions) -> sqlx::Result<SqlitePool> {
    let start = std::time::Instant::now();
    let mut pause = Duration::from_millis(20);
    loop {
        match SqlitePoolOptions::new()
            .max_connections(8)
            .connect_with(opts.clone())
            .await
        {
            Err(sqlx::Error::Database(e))
                if is_busy(&*e) && start.elapsed() < SQLITE_OPEN_PATIENCE =>
            {
                tokio::time::sleep(pause).await;
                pause = (pause * 2).min(Duration::from_millis(500));
            }
            other => return other,
        }
    }
}

impl Db {
    /// Connect to `url` (`sqlite://PATH` or `postgres://…`) and apply this build's
    /// migrations. PostgreSQL's migrator holds an advisory lock while it runs, so
    /// replicas that start together apply each migration once.
    pub async fn connect(url: &str) -> anyhow::Result<Db> {
        let db = match DatabaseUrl::parse(url)? {
            DatabaseUrl::Sqlite(path) => {
                if let Some(dir) = std::path::Path::new(&path).parent() {
                    std::fs::create_dir_all(dir)
                        .with_context(|| format!("creating directory {}", dir.display()))?;
                }
                // sqlx takes no lock on SQLite, so a `serve` and a `worker` started together
                // on a new file would both apply migration 1, and switching a new file to
                // WAL upgrades a read lock to an exclusive one, which SQLite refuses at once
                // to the second of two processes doing it together (it skips the busy
                // handler where waiting could deadlock); a file lock beside the database
                // serialises opening and migrating (the second finds everything done).
                let lock_path = format!("{path}.migrate-lock");
                let lock = tokio::task::spawn_blocking(move || {
                    let f = std::fs::File::create(&lock_path)
                        .with_context(|| format!("creating {lock_path}"))?;
                    f.lock().with_context(|| format!("locking {lock_path}"))?;
                    anyhow::Ok(f)
                })
                .await
                .context("migration lock task")??;
                // WAL, foreign keys, a busy timeout, synchronous=FULL so an acknowledged
                // write survives a crash.
                let opts = SqliteConnectOptions::from_str(&format!("sqlite://{path}"))?
                    .create_if_missing(true)
                    .journal_mode(SqliteJournalMode::Wal)
                    .synchronous(SqliteSynchronous::Full)
                    .foreign_keys(true)
                    .busy_timeout(Duration::from_secs(10));
                let pool = open_sqlite(opts)
                    .await
                    .with_context(|| format!("opening database {path}"))?;
                sqlx::migrate!("../../migrations/sqlite")
                    .run(&pool)
                    .await
                    .context("applying migrations")?;
                drop(lock);
                Db::Sqlite(pool)
            }
            DatabaseUrl::Postgres(url) => {
                let pool = PgPoolOptions::new()
                    .max_connections(16)
                    .acquire_timeout(Duration::from_secs(10))
                    .connect(&url)
                    .await
                    .with_context(|| format!("connecting to {}", redact(&url)))?;
                sqlx::migrate!("../../migrations/postgres")
                    .run(&pool)
                    .await
                    .context("applying migrations")?;
                Db::Postgres(pool)
            }
        };
        Ok(db)
    }

    pub fn backend(&self) -> Backend {
        match self {
            Db::Sqlite(_) => Backend::Sqlite,
            Db::Postgres(_) => Backend::Postgres,
        }
    }

    /// The statement for this backend, where the two differ.
    pub fn pick(&self, sqlite: &'static str, postgres: &'static str) -> Sql {
        sql(match self.backend() {
            Backend::Sqlite => sqlite,
            Backend::Postgres => postgres,
        })
    }

    pub async fn begin(&self) -> sqlx::Result<Tx> {
        Ok(match self {
            Db::Sqlite(p) => Tx::Sqlite(p.begin().await?),
            Db::Postgres(p) => Tx::Postgres(p.begin().await?),
        })
    }

    pub async fn execute(&self, q: Sql) -> sqlx::Result<u64> {
        Ok(match self {
            Db::Sqlite(p) => q.sqlite().execute(p).await?.rows_affected(),
            Db::Postgres(p) => q.postgres().execute(p).await?.rows_affected(),
        })
    }

    pub async fn fetch_optional(&self, q: Sql) -> sqlx::Result<Option<Rec>> {
        Ok(match self {
            Db::Sqlite(p) => q.sqlite().fetch_optional(p).await?.map(Rec::Sqlite),
            Db::Postgres(p) => q.postgres().fetch_optional(p).await?.map(Rec::Postgres),
        })
    }

    pub async fn fetch_one(&self, q: Sql) -> sqlx::Result<Rec> {
        Ok(match self {
            Db::Sqlite(p) => Rec::Sqlite(q.sqlite().fetch_one(p).await?),
            Db::Postgres(p) => Rec::Postgres(q.postgres().fetch_one(p).await?),
        })
    }

    pub async fn fetch_all(&self, q: Sql) -> sqlx::Result<Vec<Rec>> {
        Ok(match self {
            Db::Sqlite(p) => q
                .sqlite()
                .fetch_all(p)
                .await?
                .into_iter()
                .map(Rec::Sqlite)
                .collect(),
            Db::Postgres(p) => q
                .postgres()
                .fetch_all(p)
                .await?
                .into_iter()
                .map(Rec::Postgres)
                .collect(),
        })
    }

    /// The database's own consistency check: SQLite's `PRAGMA integrity_check` ("ok"
    /// when sound); PostgreSQL checks itself, so there it is a round trip ("ok").
    pub async fn integrity_check(&self) -> sqlx::Result<String> {
        match self {
            Db::Sqlite(p) => sqlx::query("PRAGMA integrity_check")
                .fetch_one(p)
                .await?
                .try_get(0),
            Db::Postgres(p) => {
                sqlx::query("SELECT 1").execute(p).await?;
                Ok("ok".into())
            }
        }
    }
}

/// A parsed `--database-url`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum DatabaseUrl {
    /// The file's path.
    Sqlite(String),
    /// The whole URL, as libpq reads it.
    Postgres(String),
}

impl DatabaseUrl {
    pub fn parse(url: &str) -> anyhow::Result<DatabaseUrl> {
        if let Some(path) = url.strip_prefix("sqlite://") {
            if path.is_empty() {
                anyhow::bail!("database URL {url:?}: expected sqlite://PATH with a file path");
            }
            Ok(DatabaseUrl::Sqlite(path.to_string()))
        } else if url.starts_with("postgres://") || url.starts_with("postgresql://") {
            Ok(DatabaseUrl::Postgres(url.to_string()))
        } else {
            anyhow::bail!(
                "database URL {:?}: expected sqlite://PATH or postgres://USER@HOST/DB",
                redact(url)
            )
        }
    }
}

/// A URL with its password replaced, for messages and logs.
pub fn redact(url: &str) -> String {
    let Some((scheme, rest)) = url.split_once("://") else {
        return url.to_string();
    };
    let (auth, host) = match rest.split_once('@') {
        Some(x) => x,
        None => return url.to_string(),
    };
    match auth.split_once(':') {
        Some((user, _)) => format!("{scheme}://{user}:***@{host}"),
        None => url.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn database_urls_parse_or_say_what_was_expected() {
        assert_eq!(
            DatabaseUrl::parse("sqlite:///tmp/x/rigcal.db").unwrap(),
            DatabaseUrl::Sqlite("/tmp/x/rigcal.db".into())
        );
        assert!(matches!(
            DatabaseUrl::parse("postgres://u@h/db").unwrap(),
            DatabaseUrl::Postgres(_)
        ));
        let e = DatabaseUrl::parse("mysql://u:secret@h/db")
            .unwrap_err()
            .to_string();
        assert!(e.contains("expected sqlite://PATH or postgres://"), "{e}");
        assert!(!e.contains("secret"), "{e}");
        assert!(DatabaseUrl::parse("sqlite://").is_err());
    }

    #[test]
    fn redaction_hides_only_the_password() {
        assert_eq!(
            redact("postgres://u:pw@h:5432/db"),
            "postgres://u:***@h:5432/db"
        );
        assert_eq!(redact("postgres://u@h/db"), "postgres://u@h/db");
    }

    #[test]
    fn the_lease_clock_is_each_backends_own() {
        let q = sql("SELECT NOW_MS + $1").bind(5i64);
        assert!(q.text_for(Backend::Sqlite).0.contains("julianday"));
        assert!(q.text_for(Backend::Postgres).0.contains("clock_timestamp"));
        assert_eq!(sql("SELECT 1").text_for(Backend::Sqlite).0, "SELECT 1");
    }

    #[tokio::test]
    async fn sqlite_binds_numbered_placeholders_by_number() {
        let dir = tempfile::tempdir().unwrap();
        let url = format!("sqlite://{}", dir.path().join("t.db").display());
        let db = Db::connect(&url).await.unwrap();
        let r = db
            .fetch_one(
                sql("SELECT $2 || $1 AS s, $1 IS NULL AS n")
                    .bind("a")
                    .bind("b"),
            )
            .await
            .unwrap();
        assert_eq!(r.get::<String>("s").unwrap(), "ba");
        assert_eq!(r.get::<i64>("n").unwrap(), 0);
        let now: i64 = db
            .fetch_one(sql("SELECT NOW_MS"))
            .await
            .unwrap()
            .get(0)
            .unwrap();
        assert!((now - super::super::now_ms()).abs() < 5_000);
    }
}
