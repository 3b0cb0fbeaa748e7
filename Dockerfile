# posefuse server image: `docker build -t posefuse .` then `docker run -p 8080:8080 posefuse`.
# The builder uses the same set-up script as CI (scripts/setup.sh) to obtain ONNX Runtime's shared
# library from the pinned Python wheel, so the server and the trainer's checks use one version.
# scripts/container-check.sh builds the image and checks it end to end.
# Without a registry, scripts/container-ci.sh builds this file unchanged with podman, passing a
# `--build-context` for debian:bookworm-slim (made from Debian's packages) and one for the builder
# stage (an image of a binary built outside, with /usr/local/bin/posefuse and /src/.ort/lib).

# nasm: the JPEG decoder's SIMD code (without it, its C code).
# The toolchain CI builds and tests with (Cargo.toml's rust-version is the oldest one supported).
ARG RUST_VERSION=1.95
FROM rust:${RUST_VERSION}-bookworm AS builder
RUN apt-get update \
    && apt-get install -y --no-install-recommends python3 python3-venv nasm \
    && rm -rf /var/lib/apt/lists/*
WORKDIR /src
# Only PyPI is used, and only for ONNX Runtime's wheel: the server needs no PyTorch.
ENV PIP_NO_CACHE_DIR=1
COPY scripts scripts
COPY models-export/requirements.txt models-export/requirements.txt
RUN bash scripts/setup.sh --runtime-only
COPY Cargo.toml Cargo.lock rustfmt.toml ./
COPY proto proto
COPY benches benches
COPY crates crates
COPY src src
# The viewer's page and example frame are embedded in the binary.
COPY assets assets
COPY examples examples
# The release profile has no debug info (the `profiling` profile keeps line tables).
RUN --mount=type=cache,target=/usr/local/cargo/registry \
    --mount=type=cache,target=/src/target \
    cargo build --release --locked --bin posefuse \
    && cp target/release/posefuse /usr/local/bin/posefuse

# No packages added: the server makes no outbound calls, and `posefuse health` is the health probe.
FROM debian:bookworm-slim
RUN useradd --uid 10001 --no-create-home --home-dir /app --shell /usr/sbin/nologin posefuse
WORKDIR /app
COPY --from=builder /usr/local/bin/posefuse /usr/local/bin/posefuse
COPY --from=builder /src/.ort/lib /app/.ort/lib
COPY models/default /app/models/default
ENV ORT_DYLIB_PATH=/app/.ort/lib/libonnxruntime.so \
    POSEFUSE_MODEL_DIR=/app/models/default \
    POSEFUSE_ADDR=0.0.0.0:8080 \
    RUST_LOG=info,ort=warn
USER posefuse
EXPOSE 8080
# Healthy means ready to serve (bundle loaded and warmed, as /readyz), on POSEFUSE_ADDR's port.
HEALTHCHECK --interval=15s --timeout=3s --start-period=30s --retries=3 CMD ["posefuse", "health"]
ENTRYPOINT ["posefuse"]
CMD ["serve"]
