# omis: one image for the coordinator (`omis serve`, the default command) and for workers
# (`omis worker --coordinator URL`). See docker-compose.yml.
#
# With an image registry (the default target, `runtime`): omis is compiled in a Rust image and
# runs on Debian slim. Needs BuildKit (Docker >= 23, or DOCKER_BUILDKIT=1) for the cache mounts.
#
#   docker build -t omis .
#
# Without a registry (target `prebuilt`): the runtime gets the host's release binary, on a local
# base image such as the one .ci/base-image makes with debootstrap (nothing is pulled).
#
#   cargo build --release && .ci/base-image
#   docker build --target prebuilt --build-arg RUNTIME_IMAGE=omis-base:bookworm -t omis .
#
#   docker run -e OMIS_CLIENT_TOKEN=... -e OMIS_WORKER_TOKEN=... -p 8570:8570 -v omis-data:/data omis
#
# Binding 0.0.0.0 needs both tokens: without OMIS_CLIENT_TOKEN and OMIS_WORKER_TOKEN (or
# --client-token-file / --worker-token-file) the coordinator refuses to start.

# The code uses edition 2024 and let-chains: Rust >= 1.88.
ARG RUST_IMAGE=rust:1.95-bookworm
# omis needs only glibc and libgcc_s at run time (no TLS, SQLite is built in); its health check
# is `omis healthcheck`, so no curl either. Any glibc Debian >= bookworm root will do.
ARG RUNTIME_IMAGE=debian:bookworm-slim

# ---- the runtime, shared by both paths ----
FROM ${RUNTIME_IMAGE} AS runtime-base
RUN groupadd --system --gid 10001 omis \
 && useradd --system --uid 10001 --gid omis --home-dir /srv/omis --shell /usr/sbin/nologin omis \
 && mkdir -p /data /srv/omis \
 && chown omis:omis /data /srv/omis
COPY --chown=omis:omis scenes/ /srv/omis/scenes/
WORKDIR /srv/omis
USER omis:omis
# Plain logs (no colour codes) for `docker logs`.
ENV OMIS_LOG=info NO_COLOR=1
# The data folder (SQLite database, task results, outputs): mount a volume here.
VOLUME ["/data"]
EXPOSE 8570
# No ENTRYPOINT, so `omis worker ...` works as a command override. omis handles SIGTERM
# itself: the coordinator stops its server, a worker drains (finishes and uploads the tasks in
# hand). No HEALTHCHECK here: workers run this image too and serve no HTTP; docker-compose.yml
# gives the coordinator `omis healthcheck`.
CMD ["omis", "serve", "--bind", "0.0.0.0:8570", "--data", "/data", "--scenes", "/srv/omis/scenes"]

# ---- no registry: the release binary built on the host (target/release/omis) ----
FROM runtime-base AS prebuilt
COPY target/release/omis /usr/local/bin/omis
RUN ["omis", "--version"]

# ---- build: compile in the Rust image ----
FROM ${RUST_IMAGE} AS build
WORKDIR /src
# Only what `cargo build --release` needs (tests/, benches and scenes stay out of this stage).
COPY Cargo.toml Cargo.lock ./
# The build's processor target (x86-64-v3, see README): the image runs on AVX2 and FMA machines.
COPY .cargo ./.cargo
COPY src ./src
# The registry and target caches survive between builds (BuildKit); the binary is copied out
# of the cache mount so the next stage can see it.
RUN --mount=type=cache,target=/usr/local/cargo/registry \
    --mount=type=cache,target=/usr/local/cargo/git \
    --mount=type=cache,target=/src/target \
    cargo build --release --locked --bin omis \
 && install -D -m 0755 target/release/omis /out/omis

# ---- the default target: the compiled binary on the runtime ----
FROM runtime-base AS runtime
COPY --from=build /out/omis /usr/local/bin/omis
