# Sourced by scripts/test.sh (and usable by hand: `source scripts/backends.sh;
# start_backends`): a throwaway PostgreSQL cluster and an S3-compatible server (moto) on
# random loopback ports, for the remote-backend run of the service tests. Exports
# RIGCAL_TEST_POSTGRES, RIGCAL_TEST_S3_BUCKET and the AWS_* settings that reach moto;
# stop_backends removes everything again.
#
# Needs Debian's postgresql (initdb, pg_ctl) and a venv with moto[server] at
# $RIGCAL_MOTO_VENV (scripts/test.sh installs both).

free_port() {
  python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'
}

# Run a PostgreSQL binary as the `postgres` user when we are root (initdb refuses root).
as_pg() {
  if [ "$(id -u)" -eq 0 ]; then
    runuser -u postgres -- "$@"
  else
    "$@"
  fi
}

start_backends() {
  local pgbin
  pgbin="$(ls -d /usr/lib/postgresql/*/bin 2>/dev/null | sort -V | tail -1)"
  if [ -z "$pgbin" ]; then
    echo "PostgreSQL is not installed (apt-get install postgresql)" >&2
    return 1
  fi
  RIGCAL_PG_DIR="$(mktemp -d /tmp/rigcal-pg.XXXXXX)"
  [ "$(id -u)" -ne 0 ] || chown postgres "$RIGCAL_PG_DIR"
  local pg_port
  pg_port="$(free_port)"
  as_pg "$pgbin/initdb" -D "$RIGCAL_PG_DIR/data" --auth=trust -U postgres >/dev/null
  # fsync off: a test cluster need not survive a power cut. Many servers start at once
  # (one per test, each with its pool), hence the connection limit.
  as_pg "$pgbin/pg_ctl" -D "$RIGCAL_PG_DIR/data" -l "$RIGCAL_PG_DIR/log" -w \
    -o "-p $pg_port -k $RIGCAL_PG_DIR -c listen_addresses=127.0.0.1 -c fsync=off -c synchronous_commit=off -c full_page_writes=off -c max_connections=600" \
    start >/dev/null
  export RIGCAL_TEST_POSTGRES="postgres://postgres@127.0.0.1:$pg_port"

  local s3_port
  s3_port="$(free_port)"
  "$RIGCAL_MOTO_VENV/bin/moto_server" -H 127.0.0.1 -p "$s3_port" >"$RIGCAL_PG_DIR/moto.log" 2>&1 &
  RIGCAL_MOTO_PID=$!
  local i
  for i in $(seq 1 100); do
    curl -sf "http://127.0.0.1:$s3_port/" >/dev/null 2>&1 && break
    sleep 0.2
  done
  export RIGCAL_TEST_S3_BUCKET=rigcal-test
  curl -sf -X PUT "http://127.0.0.1:$s3_port/$RIGCAL_TEST_S3_BUCKET" >/dev/null
  export AWS_ACCESS_KEY_ID=testing AWS_SECRET_ACCESS_KEY=testing AWS_REGION=us-east-1
  export AWS_ENDPOINT_URL="http://127.0.0.1:$s3_port" AWS_ALLOW_HTTP=true
  echo "backends: PostgreSQL on port $pg_port, S3 (moto) on port $s3_port" >&2
}

stop_backends() {
  [ -n "${RIGCAL_MOTO_PID:-}" ] && kill "$RIGCAL_MOTO_PID" 2>/dev/null
  if [ -n "${RIGCAL_PG_DIR:-}" ] && [ -d "$RIGCAL_PG_DIR/data" ]; then
    local pgbin
    pgbin="$(ls -d /usr/lib/postgresql/*/bin | sort -V | tail -1)"
    as_pg "$pgbin/pg_ctl" -D "$RIGCAL_PG_DIR/data" -m immediate stop >/dev/null 2>&1
    rm -rf "$RIGCAL_PG_DIR"
  fi
  unset RIGCAL_TEST_POSTGRES RIGCAL_TEST_S3_BUCKET RIGCAL_MOTO_PID RIGCAL_PG_DIR
  return 0
}
