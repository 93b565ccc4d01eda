# rigcal: multi-stage build, small runtime image, non-root, data on a volume. One image
# for both roles: `serve` (the default command) and `worker` (compose.yaml runs both,
# and `migrate`, on PostgreSQL and S3 through RIGCAL_DATABASE_URL / RIGCAL_BLOB_URL).
FROM rust:1-slim-bookworm AS build
WORKDIR /src
COPY Cargo.toml Cargo.lock ./
COPY src src
COPY crates crates
COPY migrations migrations
COPY benches benches
COPY examples examples
COPY openapi.yaml openapi.yaml
RUN cargo build --release --locked --bin rigcal && strip target/release/rigcal

FROM debian:bookworm-slim
RUN apt-get update && apt-get install -y --no-install-recommends ca-certificates curl \
    && rm -rf /var/lib/apt/lists/* \
    && useradd --system --uid 10001 --home-dir /data --shell /usr/sbin/nologin rigcal \
    && mkdir -p /data && chown rigcal /data
COPY --from=build /src/target/release/rigcal /usr/local/bin/rigcal
USER rigcal
WORKDIR /data
VOLUME ["/data"]
ENV RIGCAL_BIND=0.0.0.0:8080 \
    RIGCAL_DATA_DIR=/data \
    RIGCAL_WORKERS=2
EXPOSE 8080
# The API's health; a worker has no port (compose.yaml disables this check for it).
HEALTHCHECK --interval=30s --timeout=3s --start-period=10s \
    CMD curl -fsS http://127.0.0.1:8080/healthz || exit 1
ENTRYPOINT ["rigcal"]
CMD ["serve"]
