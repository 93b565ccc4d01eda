"""The store a benchmark's rigcal processes use: the embedded default, or a fresh
PostgreSQL database and S3 prefix (after `source scripts/backends.sh; start_backends`,
which exports the AWS_* settings the S3 client reads)."""
import os, subprocess, uuid


def add_args(ap):
    ap.add_argument("--postgres", help="PostgreSQL server URL without a database")
    ap.add_argument("--s3-bucket", help="an existing bucket (with --postgres)")


def store_env(a, prefix):
    """The environment for rigcal: RIGCAL_DATABASE_URL / RIGCAL_BLOB_URL of a new database
    and key prefix named PREFIX_<random> when --postgres is given."""
    if bool(a.postgres) != bool(a.s3_bucket):
        raise SystemExit("--postgres and --s3-bucket go together")
    env = dict(os.environ)
    if a.postgres:
        name = f"{prefix}_{uuid.uuid4().hex[:12]}"
        subprocess.check_call(["psql", f"{a.postgres}/postgres", "-qXc", f"CREATE DATABASE {name}"])
        env["RIGCAL_DATABASE_URL"] = f"{a.postgres}/{name}"
        env["RIGCAL_BLOB_URL"] = f"s3://{a.s3_bucket}/{name}"
    return env


def describe(a):
    return "PostgreSQL + S3" if a.postgres else "SQLite + local blobs"
