# syntax=docker/dockerfile:1
#
# omis: one image for the coordinator (`omis serve`, the default command) and for workers
# (`omis worker --coordinator URL`). See docker-compose.yml.
#
#   docker build -t omis .
#   docker run -e OMIS_TOKEN=... -e OMIS_WORKER_TOKEN=... -p 8570:8570 -v omis-data:/data omis
#
# Binding 0.0.0.0 needs both tokens: without OMIS_TOKEN and OMIS_WORKER_TOKEN (or
# --token-file / --worker-token-file) the coordinator refuses to start.

# The code uses edition 2024 and let-chains: Rust >= 1.88.
ARG RUST_VERSION=1.95

# ---- build ----
FROM rust:${RUST_VERSION}-bookworm AS build
WORKDIR /src
# Only what `cargo build --release` needs (tests/, benches and scenes stay out of this stage).
COPY Cargo.toml Cargo.lock ./
COPY src ./src
# The registry and target caches survive between builds (BuildKit); the binary is copied out
# of the cache mount so the next stage can see it.
RUN --mount=type=cache,target=/usr/local/cargo/registry \
    --mount=type=cache,target=/usr/local/cargo/git \
    --mount=type=cache,target=/src/target \
    cargo build --release --locked --bin omis \
 && install -D -m 0755 target/release/omis /out/omis

# ---- runtime ----
FROM debian:bookworm-slim AS runtime
# ca-certificates for https coordinators; curl for the coordinator's healthcheck
# (docker-compose.yml: GET /healthz).
RUN apt-get update \
 && apt-get install -y --no-install-recommends ca-certificates curl \
 && rm -rf /var/lib/apt/lists/*
RUN groupadd --system --gid 10001 omis \
 && useradd --system --uid 10001 --gid omis --home-dir /srv/omis --shell /usr/sbin/nologin omis \
 && mkdir -p /data /srv/omis \
 && chown omis:omis /data /srv/omis
COPY --from=build /out/omis /usr/local/bin/omis
COPY --chown=omis:omis scenes/ /srv/omis/scenes/
WORKDIR /srv/omis
USER omis:omis
ENV OMIS_LOG=info
# The data folder (SQLite database, task results, outputs): mount a volume here.
VOLUME ["/data"]
EXPOSE 8570
# No ENTRYPOINT, so `omis worker ...` works as a command override. omis handles SIGTERM
# itself: the coordinator stops its server, a worker drains (finishes and uploads the tasks in
# hand). No HEALTHCHECK here: workers run this image too and serve no HTTP.
CMD ["omis", "serve", "--bind", "0.0.0.0:8570", "--data", "/data", "--scenes", "/srv/omis/scenes"]
